"""The docker compose cluster of compose/compose.yaml as a `Backend` (ComposeBackend).

* Containers are found by their labels `com.docker.compose.project=haa` and `com.docker.compose.service=hN`
  (container names differ between compose v1 and v2), through the docker SDK
  (`docker.from_env(version="auto")`: the engine here speaks API 1.41).
* `up` and `down` run `docker compose` (v2) or `docker-compose` (v1) on the compose file; kill, pause,
  resume, restart, stop and logs use the SDK. `up` builds the image first (scripts/build-image.sh) when it
  is missing.
* The control API of hN is the port its container publishes for 7000/tcp (127.0.0.1:17001..17010); the
  token is compose/token (next to the compose file).
* Core hosts are the names in the services' `--core` argument (h1, h2, h3).
* `up(tls=True)` (`haactl cluster up --compose --tls`): a new cluster CA and certificates in compose/tls
  (haa.cluster.tls; each host's directory compose/tls/hosts/hN is bind-mounted into its container alone at
  /run/haa/tls) and HAA_TLS_DIR=/run/haa/tls (haa-hostd's `--tls-dir`). Later commands see HAA_TLS_DIR in the
  running containers' environment and talk to them with haactl's certificate (compose/tls/client).
* Only services that run `haa-hostd --name <service>` are hosts (`host_service`). Others — the `sim`
  service (profile `sim`, the avatar simulator) — are never listed, started, named or counted as hosts.

Environment: HAA_COMPOSE_FILE (default: compose/compose.yaml under the current directory, else the one of
this checkout), HAA_COMPOSE_PROJECT (default haa), HAA_COMPOSE_CMD (e.g. "docker-compose").
"""

from __future__ import annotations

import contextlib
import os
import queue
import secrets
import shlex
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator, Sequence
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
CONTROL_PORT = "7000/tcp"
#: each container's Prometheus /metrics (haa-hostd --metrics-port, HAA_METRICS_PORT in compose/compose.yaml)
METRICS_PORT = "9400/tcp"
#: where a host's own compose/tls/hosts/hN is mounted in its container (compose.yaml)
TLS_MOUNT = "/run/haa/tls"
LABEL_PROJECT = "com.docker.compose.project"
LABEL_SERVICE = "com.docker.compose.service"


def default_compose_file() -> Path:
    env = os.environ.get("HAA_COMPOSE_FILE")
    if env:
        return Path(env)
    here = Path.cwd() / "compose" / "compose.yaml"
    return here if here.exists() else REPO / "compose" / "compose.yaml"


def compose_command() -> list[str]:
    env = os.environ.get("HAA_COMPOSE_CMD")
    if env:
        return shlex.split(env)
    if shutil.which("docker"):
        r = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30)
        if r.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise ClusterError("neither `docker compose` (v2) nor `docker-compose` (v1) is installed: `make docker-setup`")


def host_service(name: str, svc: Any) -> bool:
    """A service of the compose file is a host when its command passes `--name <service name>` (haa-hostd);
    any other service (the simulator `sim`, tools) is not."""
    if not isinstance(svc, dict):
        return False
    cmd = [str(x) for x in svc.get("command") or []]
    return "--name" in cmd[:-1] and cmd[cmd.index("--name") + 1] == name


class ComposeBackend(Backend):
    kind = "compose"

    def __init__(self, compose_file: Path | None = None, project: str | None = None) -> None:
        self.file = (compose_file or default_compose_file()).absolute()
        self.project = project or os.environ.get("HAA_COMPOSE_PROJECT", "haa")
        try:
            spec = files.load_yaml(self.file, what="compose file")
        except files.FileError as e:
            raise ClusterError(f"compose file {e}") from None
        if not isinstance(spec, dict | None) or not isinstance((spec or {}).get("services") or {}, dict):
            raise ClusterError(f"compose file {self.file}: expected a mapping with a `services` mapping")
        services: dict[str, Any] = dict((spec or {}).get("services") or {})
        if not services:
            raise ClusterError(f"compose file {self.file} defines no services")
        #: the hosts (haa-hostd services), and every other service (not hosts: e.g. `sim`)
        self.services: dict[str, Any] = {n: s for n, s in services.items() if host_service(n, s)}
        self.other_services: dict[str, Any] = {n: s for n, s in services.items() if n not in self.services}
        if not self.services:
            raise ClusterError(f"compose file {self.file}: no service runs haa-hostd with --name <service>")
        self.core_names = self._core_names()
        self.token_file = self.file.parent / "token"
        token = ""
        if self.token_file.is_file():
            try:
                token = files.read_text(self.token_file, what="token file", max_bytes=files.MAX_TOKEN_BYTES).strip()
            except files.FileError as e:
                raise ClusterError(f"cannot read the cluster token {e}") from None
        super().__init__(token)
        self._docker: Any = None
        self.tls_dir = self.file.parent / "tls"
        self._tls_known = False
        self._tls_lock = threading.Lock()

    def _core_names(self) -> list[str]:
        for svc in self.services.values():
            cmd = [str(x) for x in svc.get("command") or []]
            if "--core" in cmd:
                spec = cmd[cmd.index("--core") + 1]
                return [item.split("=", 1)[0] for item in spec.split(",") if item]
        return []

    @property
    def docker(self) -> Any:
        if self._docker is None:
            self._docker = docker_client()
        return self._docker

    def describe(self) -> str:
        return f"compose cluster (project {self.project}, {self.file})"

    def image(self) -> str:
        first = next(iter(self.services.values()))
        return str(first.get("image", "haa-hostd:latest"))

    # ------------------------------------------------------------------ containers
    def containers(self) -> dict[str, Any]:
        found = self.docker.containers.list(all=True, filters={"label": f"{LABEL_PROJECT}={self.project}"})
        out: dict[str, Any] = {}
        for c in found:
            svc = c.labels.get(LABEL_SERVICE)
            if svc in self.services:
                out[svc] = c
        return out

    def container(self, name: str) -> Any:
        c = self.containers().get(name)
        if c is None:
            self.host(name)  # unknown host error
            raise ClusterError(f"host {name} has no container")
        return c

    @staticmethod
    def _state(c: Any) -> tuple[str, str]:
        st = c.attrs.get("State", {})
        status = st.get("Status", c.status)
        if status in ("running", "restarting"):
            return ALIVE, ""
        if status == "paused":
            return PAUSED, ""
        if status == "created":
            return STOPPED, ""
        code = st.get("ExitCode")
        if code == 137 or st.get("OOMKilled"):
            return KILLED, f"exit {code}"
        if code == 0:
            return LEFT, "exit 0"
        return DEAD, f"exit {code}"

    @staticmethod
    def _address(c: Any) -> str:
        ports = (c.attrs.get("HostConfig") or {}).get("PortBindings") or {}
        bind = (ports.get(CONTROL_PORT) or [{}])[0]
        host = bind.get("HostIp") or "127.0.0.1"
        return f"{'127.0.0.1' if host == '0.0.0.0' else host}:{bind.get('HostPort', '?')}"

    @staticmethod
    def _metrics_url(c: Any) -> str:
        """The published port of the container's /metrics ("" if it publishes none)."""
        ports = (c.attrs.get("HostConfig") or {}).get("PortBindings") or {}
        bind = (ports.get(METRICS_PORT) or [{}])[0]
        if not bind.get("HostPort"):
            return ""
        host = bind.get("HostIp") or "127.0.0.1"
        return f"http://{'127.0.0.1' if host == '0.0.0.0' else host}:{bind['HostPort']}/metrics"

    def hosts(self) -> list[HostInfo]:
        out = []
        for name, c in self.containers().items():
            state, detail = self._state(c)
            out.append(
                HostInfo(name, self._address(c), state, name in self.core_names, container=c.short_id, detail=detail,
                         metrics_url=self._metrics_url(c))
            )
        return sorted(out, key=lambda h: natural_key(h.name))

    def _wait(self, name: str, states: Sequence[str], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            c = self.container(name)
            if self._state(c)[0] in states:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.1)

    def _require(self, name: str, *states: str) -> Any:
        c = self.container(name)
        state = self._state(c)[0]
        if state not in states:
            raise ClusterError(state_phrase(name, state))
        return c

    # ------------------------------------------------------------------ compose
    def compose(self, *args: str, timeout: float = 300, env: dict[str, str] | None = None) -> str:
        cmd = [*compose_command(), "-f", str(self.file), "-p", self.project, *args]
        full_env = {**os.environ, **env} if env else None
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=self.file.parent, env=full_env)
        except subprocess.TimeoutExpired:
            raise ClusterError(f"`{shlex.join(cmd)}` did not finish within {timeout:.0f} s") from None
        if r.returncode != 0:
            tail = "; ".join(ln for ln in (r.stderr or r.stdout).strip().splitlines()[-3:])
            raise ClusterError(f"`{shlex.join(cmd[len(compose_command()) :])}` failed: {tail}")
        return r.stdout + r.stderr

    def ensure_image(self, log: Any = print) -> None:
        """Build the image (scripts/build-image.sh) if it is missing; make sure the token file exists."""
        import docker

        try:
            self.docker.images.get(self.image())
        except docker.errors.ImageNotFound:
            script = self.file.parent.parent / "scripts" / "build-image.sh"
            if not script.exists():
                raise ClusterError(f"image {self.image()} is missing and there is no {script} to build it") from None
            log(f"image {self.image()} is missing: building it with {script} (a few minutes the first time)")
            r = subprocess.run([str(script)], cwd=script.parent.parent)
            if r.returncode != 0:
                raise ClusterError(f"{script} failed (exit {r.returncode})") from None
        if self.token_file.is_dir():
            with contextlib.suppress(OSError):
                self.token_file.rmdir()  # made by an `up` before the first build (missing bind-mount source)
        if not self.token_file.is_file() or not self.token_file.read_text().strip():
            old = os.umask(0o077)
            try:
                self.token_file.write_text(secrets.token_hex(32) + "\n")
            finally:
                os.umask(old)
        self.token = self.token_file.read_text().strip()

    def docker_cores(self) -> int:
        """The docker host's cores (`docker info` NCPU; this machine's when docker does not say)."""
        try:
            n = int(self.docker.info().get("NCPU") or 0)
        except Exception:
            n = 0
        return n if n > 0 else max(1, os.cpu_count() or 1)

    def connect(self, h: HostInfo, timeout: float | None = None) -> Any:
        # does the running cluster use TLS? (its containers' HAA_TLS_DIR) — decided once, under a lock:
        # `statuses()` connects from several threads, and one must not go on in plain text while another is
        # still loading haactl's certificate
        with self._tls_lock:
            if not self._tls_known:
                on = any(
                    e.startswith("HAA_TLS_DIR=") and e != "HAA_TLS_DIR="
                    for c in self.containers().values()
                    for e in (c.attrs.get("Config") or {}).get("Env") or []
                )
                if on:
                    try:
                        self.tls = load_client(self.tls_dir / CLIENT_DIR)
                    except TlsError as e:
                        raise ClusterError(
                            f"the compose cluster uses TLS, but haactl's certificate is unusable: {e}") from None
                self._tls_known = True
        return super().connect(h, timeout)

    def up(
        self, hosts: int, core: int | None = None, log: Any = print, capacity: float | None = None, tls: bool = False
    ) -> list[str]:
        names = sorted(self.services, key=natural_key)
        if hosts > len(names):
            raise ClusterError(f"the compose file defines {len(names)} hosts ({names[0]}..{names[-1]}), not {hosts}")
        if core is not None and core != len(self.core_names):
            raise ClusterError(
                f"the compose file's core is {', '.join(self.core_names)} ({len(self.core_names)} hosts); "
                f"--core {core} is not possible with --compose"
            )
        running = [h.name for h in self.hosts() if h.up]
        if running:
            raise ClusterError(
                f"the compose cluster is already running ({', '.join(running)}): `haactl cluster down --compose` first"
            )
        self.ensure_image(log)
        names = names[:hosts]
        if self.containers():  # stopped containers of an earlier run: their data dirs would make them re-apply
            self.compose("down", "--timeout", "1", "--remove-orphans")
        # capacity K_h (issue 15): the hosts share the docker host's cores, unless HAA_CAPACITY is set or a
        # service's command gives --capacity (which wins over the environment); compose.yaml passes
        # HAA_CAPACITY on to every host (docs/allocation.md, "host capacities")
        env: dict[str, str] = {}
        if capacity is not None:
            env["HAA_CAPACITY"] = repr(float(capacity))
        elif not os.environ.get("HAA_CAPACITY"):
            from haa.cluster.local_backend import share_of_cores

            env["HAA_CAPACITY"] = repr(share_of_cores(hosts, self.docker_cores()))
        env["HAA_TLS_DIR"] = TLS_MOUNT if tls else ""
        if tls:  # a certificate for every host service (so that `host add` finds one), and haactl's
            try:
                make_cluster_tls(self.tls_dir, sorted(self.services, key=natural_key))
            except CaError as e:
                raise ClusterError(str(e)) from None
            self.tls = load_client(self.tls_dir / CLIENT_DIR)
        else:
            self.tls = None
        self._tls_known = True
        self.compose("up", "-d", "--force-recreate", *names, env=env)
        return names

    def down(self, grace: float = 5.0) -> str:
        return self.compose("down", "--timeout", str(max(1, round(grace))), "--remove-orphans")

    # ------------------------------------------------------------------ Backend
    def kill(self, name: str) -> None:
        c = self._require(name, ALIVE, PAUSED)
        if self._state(c)[0] == PAUSED:
            c.unpause()
        c.kill()
        self._wait(name, (KILLED, DEAD, LEFT), 10)

    def pause(self, name: str) -> None:
        self._require(name, ALIVE).pause()

    def resume(self, name: str) -> None:
        self._require(name, PAUSED).unpause()

    def restart(self, name: str) -> HostInfo:
        c = self.container(name)
        state = self._state(c)[0]
        if state in (ALIVE, PAUSED):
            raise ClusterError(f"{state_phrase(name, state)}: kill it or let it leave before restarting it")
        c.start()
        self._wait(name, (ALIVE,), 10)
        return self.host(name)

    def add(self, name: str) -> HostInfo:
        if name not in self.services:
            names = sorted(self.services, key=natural_key)
            raise ClusterError(f"the compose file defines hosts {names[0]}..{names[-1]} only, not {name!r}")
        c = self.containers().get(name)
        if c is not None:
            state = self._state(c)[0]
            if state in (ALIVE, PAUSED):
                raise ClusterError(f"host {name} is already {state}")
            return self.restart(name)
        if not self.token:
            self.ensure_image()
        self.compose("up", "-d", "--no-deps", name)
        return self.host(name)

    def next_name(self) -> str:
        have = self.containers()
        for n in sorted(self.services, key=natural_key):
            if n not in have:
                return n
        raise ClusterError("every host of the compose file already has a container")

    def terminate(self, name: str, timeout: float) -> None:
        c = self.container(name)
        if self._state(c)[0] == PAUSED:
            c.unpause()
        c.stop(timeout=max(1, round(timeout)))

    def wait_gone(self, name: str, timeout: float) -> bool:
        return self._wait(name, (KILLED, LEFT, DEAD, STOPPED), timeout)

    def mark_left(self, name: str) -> None:
        """Nothing to record: a container that left exits with code 0."""

    # ------------------------------------------------------------------ logs
    def log_records(self, names: Sequence[str], follow: bool) -> Iterator[tuple[str, str]]:
        if not follow:
            for n in names:
                raw = self.container(n).logs(stdout=True, stderr=True)
                for line in raw.decode("utf-8", "replace").splitlines():
                    if line.strip():
                        yield n, line
            return
        yield from merged_follow(names, self._follow)

    def _follow(self, name: str, q: queue.Queue[tuple[str, str]], stop: threading.Event) -> None:
        """Stream one container's log; when it stops, wait for it to run again and stream it again, skipping
        the lines already seen (docker's fixed-width timestamps tell which lines are new)."""
        last = ""
        while not stop.is_set():
            try:
                c = self.container(name)
                buf = b""
                for chunk in c.logs(stdout=True, stderr=True, stream=True, follow=True, timestamps=True):
                    buf += chunk
                    *lines, buf = buf.split(b"\n")
                    for raw in lines:
                        ts, _, line = raw.decode("utf-8", "replace").partition(" ")
                        if ts <= last or not line.strip():
                            continue
                        last = ts
                        q.put((name, line))
                    if stop.is_set():
                        return
            except ClusterError:
                pass
            except Exception:  # the container went away while streaming
                time.sleep(0.5)
            while not stop.is_set():
                time.sleep(1.0)
                with contextlib.suppress(Exception):
                    if self._state(self.container(name))[0] == ALIVE:
                        break
