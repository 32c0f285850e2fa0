"""The Docker Swarm stack of compose/stack.yaml as a `Backend` (SwarmBackend; `haactl ... --swarm`).

* The stack (default name `haa`, env HAA_SWARM_STACK) has a core service (`<stack>_core`: tasks core1..core3)
  and a host service (`<stack>_host`: host1..hostN, `docker service scale <stack>_host=N`) plus the simulator.
  A service of the stack file is a host service when its environment names each task by its slot
  (`HAA_NAME: <prefix>{{.Task.Slot}}`); the core names are those of `HAA_CORE`. Host `host4` is slot 4 of the
  host service: the swarm keeps a slot's name across the tasks that fill it (a crashed task's replacement is
  a new incarnation of the same host, with the same data volume).
* The state of a host is the state of the newest task of its slot (running: alive or paused; complete: left,
  exit 0; failed: killed (137) or dead; not yet running: stopped, e.g. a replacement waiting for the restart
  delay). A slot the swarm removed (scaled down) is not listed.
* Control: each task's container is reached from this machine at its address on `docker_gwbridge` (the bridge
  that links a swarm task to its own machine), port 7000; /metrics on 9400. Only tasks that run on the machine
  whose engine haactl talks to (DOCKER_HOST) are reachable so; docs/swarm.md says how to work with several.
* `up` runs `docker stack deploy` (HAA_SWARM_HOSTS = the host service's replicas, HAA_CAPACITY), after removing
  the data volumes of an earlier run of the same stack (a host with old known hosts would re-apply to a group
  that no longer exists); `down` runs `docker stack rm`, waits until the tasks, the network and the secret are
  gone, and removes the stack's data volumes (`<stack>_core_N`, `<stack>_host_N`, label
  com.docker.stack.namespace) and its TLS directory. kill, pause, resume, stop and logs use the docker SDK on
  the task's container.
* The token is the file the stack's `haa_token` secret is made from (compose/token next to the stack file).
* `up(tls=True)` (`haactl cluster up --swarm --tls`): a new cluster CA, an enrollment token and haactl's client
  certificate in compose/tls/swarm-<stack>/, deployed with compose/stack-tls.yaml over the stack file: every
  task enrolls for a certificate of its own name (haa.cluster.enroll). Later commands see HAA_TLS_ENROLL in the
  core service and talk to the hosts with haactl's certificate.

Environment: HAA_STACK_FILE (default: compose/stack.yaml under the current directory, else the one of this
checkout), HAA_SWARM_STACK (default haa), HAA_SWARM_TIMEOUT (seconds `down` waits, default 120).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import queue
import re
import secrets
import shlex
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from haa import files
from haa.cluster.backend import (
    ALIVE,
    DEAD,
    KILLED,
    LEFT,
    PAUSED,
    STOPPED,
    UP_STATES,
    Backend,
    ClusterError,
    HostInfo,
    docker_client,
    merged_follow,
    natural_key,
    state_phrase,
)
from haa.cluster.tls import CLIENT_DIR, CaError, make_cluster_tls
from haa.tls import TlsError, load_client

REPO = Path(__file__).resolve().parents[2]
CONTROL_PORT = 7000
METRICS_PORT = 9400
GWBRIDGE = "docker_gwbridge"
LABEL_STACK = "com.docker.stack.namespace"
SLOT = "{{.Task.Slot}}"
#: the enrollment token's file in the stack's TLS directory (secret haa_enroll_token)
ENROLL_TOKEN = "enroll-token"
#: task states before the container runs (swarmkit's TaskState names)
STARTING = frozenset({"new", "pending", "assigned", "accepted", "preparing", "ready", "starting"})


def default_stack_file() -> Path:
    env = os.environ.get("HAA_STACK_FILE")
    if env:
        return Path(env)
    here = Path.cwd() / "compose" / "stack.yaml"
    return here if here.exists() else REPO / "compose" / "stack.yaml"


def _env_of(svc: Any) -> dict[str, str]:
    env = svc.get("environment") if isinstance(svc, dict) else None
    if isinstance(env, dict):
        return {str(k): "" if v is None else str(v) for k, v in env.items()}
    if isinstance(env, list):
        return dict(str(e).partition("=")[::2] for e in env)
    return {}


def task_time(text: str) -> dt.datetime:
    """A swarm timestamp ("2026-11-27T22:40:01.123456789Z": nanoseconds) as a datetime."""
    m = re.match(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)(?:\.(\d+))?", text or "")
    if not m:
        return dt.datetime.min
    frac = (m.group(2) or "0")[:6].ljust(6, "0")
    return dt.datetime.fromisoformat(f"{m.group(1)}.{frac}")


@dataclass
class Slot:
    """One host of the swarm: a slot of a host service and its tasks (newest last)."""

    name: str
    service: str  # the stack file's service name (core, host)
    slot: int
    tasks: list[dict[str, Any]]

    @property
    def task(self) -> dict[str, Any]:
        return self.tasks[-1]

    @property
    def container_id(self) -> str:
        return str(((self.task.get("Status") or {}).get("ContainerStatus") or {}).get("ContainerID") or "")


class SwarmBackend(Backend):
    kind = "swarm"

    def __init__(self, stack_file: Path | None = None, stack: str | None = None) -> None:
        self.file = (stack_file or default_stack_file()).absolute()
        self.stack = stack or os.environ.get("HAA_SWARM_STACK", "haa")
        if not re.fullmatch(r"[a-z0-9][a-z0-9_.-]{0,40}", self.stack):
            raise ClusterError(f"stack name {self.stack!r}: use lower-case letters, digits, '-', '_', '.'")
        try:
            spec = files.load_yaml(self.file, what="stack file")
        except files.FileError as e:
            raise ClusterError(str(e)) from None
        services = dict((spec or {}).get("services") or {}) if isinstance(spec, dict) else {}
        if not services:
            raise ClusterError(f"stack file {self.file} defines no services")
        #: host services of the stack file -> the name prefix of their tasks (HAA_NAME: <prefix>{{.Task.Slot}})
        self.prefixes: dict[str, str] = {}
        core_spec = ""
        for n, s in services.items():
            env = _env_of(s)
            name = env.get("HAA_NAME", "")
            if name.endswith(SLOT) and SLOT not in name[: -len(SLOT)]:
                self.prefixes[str(n)] = name[: -len(SLOT)]
                core_spec = core_spec or env.get("HAA_CORE", "")
        if not self.prefixes:
            raise ClusterError(f"stack file {self.file}: no service names its tasks with HAA_NAME: <prefix>{SLOT}")
        self.core_names = [item.split("=", 1)[0] for item in core_spec.split(",") if item]
        self.core_service = next(
            (svc for svc, p in self.prefixes.items() if self.core_names and self.core_names[0].startswith(p)
             and self.core_names[0][len(p):].isdigit()), "")
        others = [s for s in self.prefixes if s != self.core_service]
        self.host_service = "host" if "host" in others else (others[0] if others else "")
        if not self.core_service or not self.host_service:
            raise ClusterError(f"stack file {self.file}: needs a core service (its tasks named as in HAA_CORE) "
                               "and a host service")
        self.token_file = self._token_file(spec)
        token = ""
        if self.token_file.is_file():
            try:
                token = files.read_text(self.token_file, what="token file", max_bytes=files.MAX_TOKEN_BYTES).strip()
            except files.FileError as e:
                raise ClusterError(f"cannot read the cluster token {e}") from None
        super().__init__(token)
        self._docker: Any = None
        #: the TLS overlay (compose/stack-tls.yaml) and this stack's CA, enrollment token and haactl's certificate
        self.tls_file = self.file.parent / "stack-tls.yaml"
        self.tls_dir = self.file.parent / "tls" / f"swarm-{self.stack}"
        self._tls_known = False
        self._tls_lock = threading.Lock()
        self.image = str(next(iter(services.values())).get("image") or "haa-hostd:latest")
        self.image = re.sub(r"\$\{HAA_IMAGE:-([^}]*)\}", lambda m: os.environ.get("HAA_IMAGE") or m.group(1),
                            self.image)

    def _token_file(self, spec: dict[str, Any]) -> Path:
        sec = ((spec.get("secrets") or {}).get("haa_token") or {}) if isinstance(spec.get("secrets"), dict) else {}
        f = sec.get("file") if isinstance(sec, dict) else None
        return (self.file.parent / str(f or "token")).absolute()

    @property
    def docker(self) -> Any:
        if self._docker is None:
            self._docker = docker_client()
        return self._docker

    def describe(self) -> str:
        return f"swarm stack {self.stack} ({self.file})"

    def service_name(self, svc: str) -> str:
        return f"{self.stack}_{svc}"

    # ------------------------------------------------------------------ swarm state
    def swarm_problem(self) -> str | None:
        """Why this engine cannot deploy a stack (None: it is a swarm manager)."""
        info = self.docker.info().get("Swarm") or {}
        if info.get("LocalNodeState") != "active":
            return ("this docker engine is not in a swarm: `docker swarm init --advertise-addr 127.0.0.1` (one "
                    "machine) or docs/swarm.md (several)")
        if not info.get("ControlAvailable"):
            return "this docker engine is a swarm worker: run haactl against a manager (DOCKER_HOST)"
        return None

    def services(self) -> dict[str, Any]:
        """The stack's services that run hosts, by their stack-file name."""
        if self.swarm_problem():
            return {}
        found = self.docker.services.list(filters={"label": f"{LABEL_STACK}={self.stack}"})
        by_name = {s.name: s for s in found}
        return {svc: by_name[self.service_name(svc)] for svc in self.prefixes if self.service_name(svc) in by_name}

    def slots(self) -> dict[str, Slot]:
        """Every host of the stack by name (slots the swarm removed when scaling down are left out)."""
        out: dict[str, Slot] = {}
        for svc, service in self.services().items():
            by_slot: dict[int, list[dict[str, Any]]] = {}
            for t in service.tasks():
                if t.get("Slot"):
                    by_slot.setdefault(int(t["Slot"]), []).append(t)
            for slot, tasks in by_slot.items():
                tasks.sort(key=lambda t: task_time(t.get("CreatedAt", "")))
                if tasks[-1].get("DesiredState") == "remove":
                    continue  # scaled down
                name = f"{self.prefixes[svc]}{slot}"
                out[name] = Slot(name, svc, slot, tasks)
        return out

    def _gw_addresses(self) -> dict[str, str]:
        """Container id -> its IPv4 address on docker_gwbridge (the swarm tasks of this machine)."""
        import docker

        try:
            net = self.docker.networks.get(GWBRIDGE)
        except docker.errors.NotFound:
            return {}
        out = {}
        for cid, ep in (net.attrs.get("Containers") or {}).items():
            ip = str(ep.get("IPv4Address") or "").split("/")[0]
            if ip:
                out[cid] = ip
        return out

    def _state(self, s: Slot) -> tuple[str, str]:
        t = s.task
        st = t.get("Status") or {}
        state = str(st.get("State") or "")
        code = (st.get("ContainerStatus") or {}).get("ExitCode")
        if state == "running":
            if s.container_id:
                with contextlib.suppress(Exception):
                    if self.docker.containers.get(s.container_id).status == "paused":
                        return PAUSED, ""
            return ALIVE, ""
        if state in STARTING:
            prev = s.tasks[-2] if len(s.tasks) > 1 else None
            pst = (prev.get("Status") or {}) if prev is not None else {}
            if pst.get("State") == "failed":  # a crashed task, its replacement waiting for the restart delay
                pcode = (pst.get("ContainerStatus") or {}).get("ExitCode")
                return (KILLED if pcode == 137 else DEAD), f"exit {pcode}; the swarm restarts it (task {state})"
            return STOPPED, f"task {state}"
        if state == "complete":
            return LEFT, "exit 0"
        if state == "failed":
            return (KILLED if code == 137 else DEAD), f"exit {code}"
        return DEAD, f"task {state or 'unknown'}: {st.get('Err') or st.get('Message') or ''}".rstrip(": ")

    def _info(self, s: Slot, gw: dict[str, str]) -> HostInfo:
        state, detail = self._state(s)
        ip = gw.get(s.container_id, "")
        if not ip and state in UP_STATES:
            node = str(s.task.get("NodeID") or "?")[:12]
            detail = f"on node {node}, not this machine's engine"
        address = f"{ip}:{CONTROL_PORT}" if ip else f"{s.name}:{CONTROL_PORT}"
        return HostInfo(
            s.name, address, state, s.name in self.core_names, container=s.container_id[:12] or None, detail=detail,
            metrics_url=f"http://{ip}:{METRICS_PORT}/metrics" if ip else "",
        )

    def hosts(self) -> list[HostInfo]:
        slots = self.slots()
        gw = self._gw_addresses() if slots else {}
        return sorted((self._info(s, gw) for s in slots.values()), key=lambda h: natural_key(h.name))

    def require_hosts(self) -> list[HostInfo]:
        hosts = self.hosts()
        if not hosts:
            problem = self.swarm_problem()
            raise ClusterError(problem or f"no cluster running ({self.describe()}); start one with "
                               "`haactl cluster up --swarm`")
        return hosts

    def slot(self, name: str) -> Slot:
        s = self.slots().get(name)
        if s is None:
            self.host(name)  # the unknown host error
            raise ClusterError(f"host {name} has no task")
        return s

    def container(self, name: str) -> Any:
        """The container of the newest task of host `name` (it must run on this machine)."""
        import docker

        s = self.slot(name)
        if not s.container_id:
            raise ClusterError(f"host {name}'s task has no container yet ({self._state(s)[1]})")
        try:
            return self.docker.containers.get(s.container_id)
        except docker.errors.NotFound:
            raise ClusterError(f"host {name} runs on node {str(s.task.get('NodeID'))[:12]}, not on this machine's "
                               "engine: point DOCKER_HOST at that node") from None

    def _wait(self, name: str, states: Sequence[str], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            s = self.slots().get(name)
            if s is not None and self._state(s)[0] in states:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.2)

    # ------------------------------------------------------------------ deploy
    def docker_cli(self, *args: str, timeout: float = 300, env: dict[str, str] | None = None) -> str:
        if not shutil.which("docker"):
            raise ClusterError("the docker command is not installed: `make docker-setup`")
        cmd = ["docker", *args]
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=self.file.parent,
                               env={**os.environ, **(env or {})})
        except subprocess.TimeoutExpired:
            raise ClusterError(f"`{shlex.join(cmd)}` did not finish within {timeout:.0f} s") from None
        if r.returncode != 0:
            tail = "; ".join(ln for ln in (r.stderr or r.stdout).strip().splitlines()[-3:])
            raise ClusterError(f"`{shlex.join(cmd)}` failed: {tail}")
        return r.stdout + r.stderr

    def ensure_ready(self) -> None:
        """A swarm manager, the image, and the token file (made when missing, as `make image` does)."""
        import docker

        problem = self.swarm_problem()
        if problem:
            raise ClusterError(problem)
        try:
            self.docker.images.get(self.image)
        except docker.errors.ImageNotFound:
            raise ClusterError(f"image {self.image} is missing: `make image` builds it") from None
        if self.token_file.is_dir():
            with contextlib.suppress(OSError):
                self.token_file.rmdir()
        if not self.token_file.is_file() or not self.token_file.read_text().strip():
            old = os.umask(0o077)
            try:
                self.token_file.write_text(secrets.token_hex(32) + "\n")
            finally:
                os.umask(old)
        self.token = self.token_file.read_text().strip()

    def docker_cores(self) -> int:
        """The cores of the swarm's nodes (`docker info` NCPU of this one when there is a single node)."""
        try:
            nodes = self.docker.nodes.list()
            n = sum(int(((nd.attrs.get("Description") or {}).get("Resources") or {}).get("NanoCPUs") or 0)
                    for nd in nodes) // 10**9
        except Exception:
            n = 0
        return n if n > 0 else max(1, os.cpu_count() or 1)

    def volumes(self) -> list[Any]:
        return list(self.docker.volumes.list(filters={"label": f"{LABEL_STACK}={self.stack}"}))

    def up(self, hosts: int, core: int | None = None, log: Any = print, capacity: float | None = None,
           tls: bool = False) -> list[str]:
        ncore = len(self.core_names)
        if tls and not self.tls_file.is_file():
            raise ClusterError(f"--tls needs {self.tls_file} next to the stack file (it adds the enrollment service)")
        if core is not None and core != ncore:
            raise ClusterError(f"the stack's core is {', '.join(self.core_names)} ({ncore} hosts); --core {core} is "
                               "not possible with --swarm")
        if hosts < ncore:
            raise ClusterError(f"--hosts {hosts}: the stack's core alone has {ncore} hosts")
        self.ensure_ready()
        if self.services():
            raise ClusterError(f"the {self.describe()} is already running: `haactl cluster down --swarm` first")
        self._wait_removed(30.0)  # a `docker stack rm` of the same stack may still be tearing down
        for v in self.volumes():  # data dirs of an earlier run: their hosts would re-apply to a group that is gone
            with contextlib.suppress(Exception):
                v.remove(force=True)
        env = {"HAA_SWARM_HOSTS": str(hosts - ncore)}
        if capacity is not None:
            env["HAA_CAPACITY"] = repr(float(capacity))
        elif not os.environ.get("HAA_CAPACITY"):
            from haa.cluster.local_backend import share_of_cores

            env["HAA_CAPACITY"] = repr(share_of_cores(hosts, self.docker_cores()))
        cfiles = ["--compose-file", str(self.file)]
        if tls:  # a new CA, the enrollment token and haactl's certificate; the tasks enroll for theirs
            try:
                ca = make_cluster_tls(self.tls_dir, [])
            except CaError as e:
                raise ClusterError(str(e)) from None
            fd = os.open(self.tls_dir / ENROLL_TOKEN, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(secrets.token_hex(32) + "\n")
            self.tls = load_client(ca.client_dir)
            env["HAA_SWARM_TLS_DIR"] = str(self.tls_dir)
            cfiles += ["--compose-file", str(self.tls_file)]
        else:
            self.tls = None
        self._tls_known = True
        self.docker_cli("stack", "deploy", *cfiles, "--prune", self.stack, env=env)
        prefix_core, prefix_host = self.prefixes[self.core_service], self.prefixes[self.host_service]
        return [f"{prefix_core}{i}" for i in range(1, ncore + 1)] + [f"{prefix_host}{i}"
                                                                     for i in range(1, hosts - ncore + 1)]

    def _wait_removed(self, timeout: float) -> bool:
        """Wait until no container, network or secret of the stack is left; True if so."""
        deadline = time.monotonic() + timeout
        flt = {"label": f"{LABEL_STACK}={self.stack}"}
        while True:
            left = (self.docker.containers.list(all=True, filters=flt, sparse=True)
                    or self.docker.networks.list(filters=flt) or self.docker.secrets.list(filters=flt))
            if not left:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.5)

    def down(self, grace: float = 5.0) -> str:
        """`docker stack rm` (each task gets SIGTERM: a graceful leave, SIGKILL after the stack's
        stop_grace_period), then the stack's data volumes. `grace` is the stack file's; kept for the interface."""
        del grace
        if self.swarm_problem():
            raise ClusterError(str(self.swarm_problem()))
        flt = {"label": f"{LABEL_STACK}={self.stack}"}
        running = self.docker.services.list(filters=flt)
        if running:
            self.docker_cli("stack", "rm", self.stack)
        timeout = float(os.environ.get("HAA_SWARM_TIMEOUT") or 120)
        if not self._wait_removed(timeout):
            raise ClusterError(f"the stack {self.stack} is still tearing down after {timeout:.0f} s "
                               "(`docker stack ps` shows what is left)")
        gone = 0
        for v in self.volumes():
            try:
                v.remove(force=True)
                gone += 1
            except Exception as e:
                raise ClusterError(f"cannot remove volume {v.name} of the stack: {e}") from None
        if self.tls_dir.is_dir():  # the stack's CA and haactl's certificate: useless once the stack is gone
            shutil.rmtree(self.tls_dir, ignore_errors=True)
            self.tls = None
        return f"removed {len(running)} services and {gone} data volumes"

    def connect(self, h: HostInfo, timeout: float | None = None) -> Any:
        with self._tls_lock:  # statuses() connects from several threads: decide once, before any of them dials
            if not self._tls_known:  # does the running stack use TLS? (HAA_TLS_ENROLL in its core service)
                core = self.services().get(self.core_service)
                spec = (((core.attrs.get("Spec") or {}).get("TaskTemplate") or {}).get("ContainerSpec") or {}) \
                    if core is not None else {}
                if any(e.startswith("HAA_TLS_ENROLL=") and e != "HAA_TLS_ENROLL=" for e in spec.get("Env") or []):
                    try:
                        self.tls = load_client(self.tls_dir / CLIENT_DIR)
                    except TlsError as e:
                        raise ClusterError(f"the swarm stack uses TLS, but haactl's certificate is unusable: {e}") \
                            from None
                self._tls_known = True
        return super().connect(h, timeout)

    # ------------------------------------------------------------------ Backend
    def kill(self, name: str) -> None:
        c = self.container(name)
        if c.status == "paused":
            c.unpause()
        c.kill()
        self._wait(name, (KILLED, DEAD, LEFT, STOPPED), 10)

    def pause(self, name: str) -> None:
        self._require(name, ALIVE).pause()

    def resume(self, name: str) -> None:
        self._require(name, PAUSED).unpause()

    def _require(self, name: str, *states: str) -> Any:
        state = self._state(self.slot(name))[0]
        if state not in states:
            raise ClusterError(state_phrase(name, state))
        return self.container(name)

    def restart(self, name: str) -> HostInfo:
        """The swarm restarts a crashed task itself (restart_policy on-failure, after its delay): wait for it."""
        s = self.slot(name)
        state, detail = self._state(s)
        prev = (s.tasks[-2].get("Status") or {}).get("State") if len(s.tasks) > 1 else None
        if state == ALIVE and prev == "failed":
            return self.host(name)  # the swarm has restarted it already
        if state in UP_STATES:
            raise ClusterError(f"{state_phrase(name, state)}: kill it or let it leave before restarting it")
        if state == LEFT:
            raise ClusterError(
                f"host {name} left (its task completed with exit 0) and the swarm restarts failed tasks only: "
                f"`docker service update --force {self.service_name(s.service)}` renews every task of the service, "
                "one at a time")
        if not self._wait(name, (ALIVE,), 60):
            raise ClusterError(f"the swarm did not start a new task of {name} within 60 s "
                               f"({self._state(self.slot(name))[1] or detail})")
        return self.host(name)

    def next_name(self) -> str:
        """The host the next `docker service scale` +1 makes: the swarm gives the new task the lowest free slot."""
        used = {s.slot for s in self.slots().values() if s.service == self.host_service}
        slot = next(i for i in range(1, len(used) + 2) if i not in used)
        return f"{self.prefixes[self.host_service]}{slot}"

    def add(self, name: str) -> HostInfo:
        want = self.next_name()
        if name != want:
            raise ClusterError(f"the swarm names hosts by task slot: the next host of service "
                               f"{self.service_name(self.host_service)} is {want}, not {name!r}")
        service = self.services().get(self.host_service)
        if service is None:
            raise ClusterError(f"no service {self.service_name(self.host_service)}: `haactl cluster up --swarm` first")
        replicas = int(((service.attrs.get("Spec") or {}).get("Mode") or {}).get("Replicated", {}).get("Replicas", 0))
        service.scale(replicas + 1)
        if not self._wait(name, (ALIVE,), 60):
            have = sorted(self.slots(), key=natural_key)
            raise ClusterError(f"no running task {name} 60 s after scaling {self.service_name(self.host_service)} to "
                               f"{replicas + 1} (hosts: {', '.join(have)})")
        return self.host(name)

    def terminate(self, name: str, timeout: float) -> None:
        c = self.container(name)
        if c.status == "paused":
            c.unpause()
        c.stop(timeout=max(1, round(timeout)))

    def wait_gone(self, name: str, timeout: float) -> bool:
        return self._wait(name, (KILLED, LEFT, DEAD, STOPPED), timeout)

    def mark_left(self, name: str) -> None:
        """Nothing to record: a task that left completes with exit 0."""

    # ------------------------------------------------------------------ logs
    def _containers(self, name: str) -> list[Any]:
        """The containers of every task of host `name` still on this machine, oldest first."""
        import docker

        out = []
        for t in self.slot(name).tasks:
            cid = ((t.get("Status") or {}).get("ContainerStatus") or {}).get("ContainerID")
            if cid:
                with contextlib.suppress(docker.errors.NotFound):
                    out.append(self.docker.containers.get(cid))
        return out

    def log_records(self, names: Sequence[str], follow: bool) -> Iterator[tuple[str, str]]:
        if not follow:
            for n in names:
                for c in self._containers(n):
                    for line in c.logs(stdout=True, stderr=True).decode("utf-8", "replace").splitlines():
                        if line.strip():
                            yield n, line
            return
        yield from merged_follow(names, self._follow)

    def _follow(self, name: str, q: queue.Queue[tuple[str, str]], stop: threading.Event) -> None:
        """Stream the log of the newest task's container; when a replacement task starts, stream its log."""
        seen: set[str] = set()
        while not stop.is_set():
            try:
                cs = self._containers(name)
            except ClusterError:
                cs = []
            fresh = [c for c in cs if c.id not in seen]
            if not fresh:
                time.sleep(1.0)
                continue
            for c in fresh[:-1]:  # ended tasks not streamed yet: their whole log
                seen.add(c.id)
                for line in c.logs(stdout=True, stderr=True).decode("utf-8", "replace").splitlines():
                    if line.strip():
                        q.put((name, line))
            c = fresh[-1]
            seen.add(c.id)
            buf = b""
            with contextlib.suppress(Exception):  # the container went away while streaming
                for chunk in c.logs(stdout=True, stderr=True, stream=True, follow=True):
                    buf += chunk
                    *lines, buf = buf.split(b"\n")
                    for raw in lines:
                        line = raw.decode("utf-8", "replace")
                        if line.strip():
                            q.put((name, line))
                    if stop.is_set():
                        return
