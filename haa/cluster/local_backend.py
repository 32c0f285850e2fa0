"""A cluster of membership-mode `haa-hostd` processes on loopback, driven by `haactl` (LocalBackend).

The cluster lives in one root directory (default `.haa/cluster` under the current directory, or
`$HAA_CLUSTER_DIR`, or `--root`):

    <root>/cluster.json        state file: token file, core list, hostd arguments, per host its address,
                               pid (+ process start time, so that a reused pid is not mistaken for it),
                               whether it is core, how it was stopped
    <root>/token               the cluster token (mode 600)
    <root>/tls/                with `up(tls=True)` (`haactl cluster up --tls`): the cluster CA, one certificate per
                               host (tls/hosts/<name>/, given to it as --tls-dir) and haactl's (tls/client/);
                               keys mode 600 (haa.cluster.tls, docs/deploy.md)
    <root>/<name>/             the host's --data-dir: JSON-lines log <name>.jsonl, stderr.<n>.txt per start

Each host also gets a free loopback port of its own for its Prometheus `/metrics` (`--metrics-port`, haa.metrics;
`metrics_port` in the state file, `metrics_url` in `haactl cluster status --json`).

Processes are started in their own session, so they outlive the `haactl` command that started them and
an interrupt of the terminal does not reach them; later commands find them through the state file.
Every host gets the same `--core h1=ADDR,...` list (the first K hosts); hosts added later are not core and
find the group through that list (Alg. 3).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import shlex
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import psutil

from haa import files
from haa.cluster.backend import (
    ALIVE,
    DEAD,
    KILLED,
    LEFT,
    PAUSED,
    Backend,
    ClusterError,
    HostInfo,
    StartError,
    natural_key,
    state_phrase,
)
from haa.cluster.procs import free_port, member_command, start_hostd, stderr_file, write_token
from haa.cluster.tls import CLIENT_DIR, HOSTS_DIR, CaError, ClusterCA, make_cluster_tls
from haa.tls import ClientTls, TlsError, load_client

STATE_FILE = "cluster.json"
LAST_STATE_FILE = "cluster.last.json"  # the state of the cluster `down` stopped, so that `logs` still finds it
STATE_VERSION = 1


def default_root() -> Path:
    env = os.environ.get("HAA_CLUSTER_DIR")
    return Path(env) if env else Path.cwd() / ".haa" / "cluster"


def check_yaml(path: Path) -> dict[str, Any]:
    """Parse a hostd config file here, so that a broken file gives one error instead of N dead hosts (with
    haa-hostd's limits: haa.files); returns its settings."""
    from haa.hostd.daemon import CONFIG_MAX_BYTES, CONFIG_MAX_NODES

    try:
        data = files.load_yaml(path, what="config file", max_bytes=CONFIG_MAX_BYTES, max_nodes=CONFIG_MAX_NODES)
    except files.FileError as e:
        raise ClusterError(f"config file {e.path}: {e.reason.replace('not valid YAML', 'broken YAML', 1)}") from None
    if data is not None and not isinstance(data, dict):
        kind = type(data).__name__
        raise ClusterError(f"config file {path}: the top level must be a mapping (key: value), not {kind}")
    return data or {}


def machine_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a container's cpuset), else os.cpu_count()."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def share_of_cores(hosts: int, cores: int | None = None) -> float:
    """Each host's capacity K_h when `hosts` hosts share this machine: its cores divided among them (issue 15:
    a local cluster of N hosts on a 2-core machine must not believe it has N cores), within the allocator's
    bounds (docs/allocation.md, "host capacities")."""
    from haa.core.allocation.specs import MAX_CAPACITY, MIN_CAPACITY

    c = machine_cores() if cores is None else cores
    return min(MAX_CAPACITY, max(MIN_CAPACITY, round(c / max(1, hosts), 3)))


def _sets_capacity(args: Sequence[str], settings: dict[str, Any]) -> bool:
    """Whether the operator configured a capacity: `--capacity` in the hostd arguments, the config file's
    `capacity`, or HAA_CAPACITY in the environment the hosts inherit."""
    return (
        any(a == "--capacity" or a.startswith("--capacity=") for a in args)
        or settings.get("capacity") is not None
        or bool(os.environ.get("HAA_CAPACITY"))
    )


def _proc_state(pid: int | None, create_time: float | None) -> str | None:
    """ALIVE / PAUSED for our process, None if it is gone (or the pid now belongs to another process)."""
    if not pid:
        return None
    try:
        p = psutil.Process(pid)
        if create_time is not None and abs(p.create_time() - create_time) > 0.5:
            return None
        st = p.status()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return None
    if st == psutil.STATUS_ZOMBIE:
        with contextlib.suppress(ChildProcessError, OSError):
            os.waitpid(pid, os.WNOHANG)  # reap it if it is our child
        return None
    if st in (psutil.STATUS_STOPPED, psutil.STATUS_TRACING_STOP):
        return PAUSED
    return ALIVE


def _reap(pid: int, timeout: float) -> bool:
    """Wait up to `timeout` s for our child `pid` to exit and reap it; True once reaped or if it is not our
    child. Needed after `_proc_state` said "gone" on seeing a zombie: a zombie thread-group leader may still
    have threads running (haa-hostd's gRPC threads wind down after its main thread returned), so the reap
    there can come too early and the process would stay a zombie of ours."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            done, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return True
        if done:
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)


class LocalBackend(Backend):
    kind = "local"

    def __init__(self, root: Path | None = None, last: bool = False) -> None:
        self.root = (root or default_root()).absolute()
        self.state: dict[str, Any] = {}
        self._procs: dict[str, subprocess.Popen[bytes]] = {}
        self._last = last
        self.reload()
        token = ""
        tf = self.state.get("token_file")
        if tf:
            try:
                token = files.read_token(tf)
            except files.FileError as e:
                raise ClusterError(f"cannot read the cluster token {e}") from None
        super().__init__(token, self._load_tls())

    def _load_tls(self) -> ClientTls | None:
        """haactl's client certificate if the cluster was made with `--tls`."""
        d = self.state.get("tls_dir")
        if not d:
            return None
        try:
            return load_client(Path(d) / CLIENT_DIR)
        except TlsError as e:
            raise ClusterError(f"this cluster uses TLS, but haactl's certificate is unusable: {e}") from None

    # ------------------------------------------------------------------ state file
    @property
    def state_path(self) -> Path:
        return self.root / STATE_FILE

    def load(self, path: Path | None = None) -> None:
        path = path or self.state_path
        if not path.exists():
            self.state = {}
            return
        try:
            self.state = files.load_json(path, what="cluster state file")
        except files.FileError as e:
            raise ClusterError(f"broken state file: {e}") from None
        if not isinstance(self.state, dict):
            raise ClusterError(f"broken state file {path}: not a JSON object")
        if self.state.get("version") != STATE_VERSION:
            raise ClusterError(f"state file {path} has an unknown version; remove it (`haactl cluster down --purge`)")

    def reload(self) -> None:
        self.load()
        if not self.state and self._last:  # `logs` or `down --purge` after `cluster down`
            self.load(self.root / LAST_STATE_FILE)

    def save(self) -> None:
        tmp = self.state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.state, indent=2) + "\n")
        tmp.replace(self.state_path)

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Re-read, modify and write the state file under an exclusive lock."""
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / "cluster.lock", "w") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                self.reload()
                yield
                if self.state:
                    self.save()
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    # ------------------------------------------------------------------ Backend
    def describe(self) -> str:
        return f"local cluster in {self.root}"

    def _rec(self, name: str) -> dict[str, Any]:
        rec = self.state.get("hosts", {}).get(name)
        if rec is None:
            self.host(name)  # raises the "unknown host" error with the list of hosts
            raise AssertionError(name)
        return rec

    def hosts(self) -> list[HostInfo]:
        out = []
        for name, rec in self.state.get("hosts", {}).items():
            st = _proc_state(rec.get("pid"), rec.get("create_time"))
            if st is None:
                st = {"kill": KILLED, "leave": LEFT, "down": DEAD}.get(rec.get("stopped_by") or "", DEAD)
            mp = rec.get("metrics_port")
            out.append(HostInfo(name, rec["address"], st, bool(rec.get("core")), pid=rec.get("pid"),
                                metrics_url=f"http://127.0.0.1:{mp}/metrics" if mp else ""))
        return sorted(out, key=lambda h: natural_key(h.name))

    def _spawn(self, name: str) -> None:
        rec = self._rec(name)
        data_dir = Path(rec["data_dir"])
        rec["starts"] = int(rec.get("starts", 0)) + 1
        args = list(self.state["args"])
        if rec.get("metrics_port"):
            args += ["--metrics-port", str(rec["metrics_port"])]
        if self.state.get("tls_dir"):
            args += ["--tls-dir", str(Path(self.state["tls_dir"]) / HOSTS_DIR / name)]
        cmd = member_command(name, rec["address"], self.state["core"], Path(self.state["token_file"]), data_dir, args)
        p = start_hostd(cmd, data_dir, rec["starts"], detach=True)  # outlives this command (module docstring)
        err_path = stderr_file(data_dir, rec["starts"])
        self._procs[name] = p
        try:
            ct = psutil.Process(p.pid).create_time()
        except psutil.NoSuchProcess:
            ct = None
        rec.update(pid=p.pid, create_time=ct, stopped_by=None, stderr=str(err_path), started=time.time())

    def check_started(self) -> None:
        """Raise if a process started by this command has already exited (bad settings, port in use)."""
        for name, p in self._procs.items():
            code = p.poll()
            if code is None:
                continue
            rec = self.state["hosts"][name]
            try:
                lines = [ln for ln in Path(rec["stderr"]).read_text(errors="replace").splitlines() if ln.strip()]
            except OSError:
                lines = []
            last = lines[-1] if lines else "(no output)"
            raise StartError(f"host {name} exited at start with code {code}: {last} (stderr: {rec['stderr']})")

    def up(
        self,
        hosts: int,
        core: int,
        hostd_args: Sequence[str] = (),
        config: Path | None = None,
        capacity: float | None = None,
        tls: bool = False,
    ) -> list[str]:
        """Create the state file and start h1..hN (the first `core` are core); returns the names. With `tls`,
        a new cluster CA and certificates in <root>/tls: the hosts talk and serve over mutual TLS.

        Capacity K_h of every host: `capacity` when given; else what `hostd_args`, the config file or
        HAA_CAPACITY say; else this machine's cores divided among the N hosts (`share_of_cores`)."""
        settings = check_yaml(config) if config is not None else {}
        if capacity is None and not _sets_capacity(hostd_args, settings):
            capacity = share_of_cores(hosts)
        with self.locked():
            running = [h.name for h in self.hosts() if h.up]
            if running:
                raise ClusterError(
                    f"a cluster is already running in {self.root} ({', '.join(running)}): `haactl cluster down` first"
                )
            names = [f"h{i + 1}" for i in range(hosts)]
            last = LocalBackend(self.root, last=True).state if not self.state else self.state
            for old in last.get("hosts", {}).values():  # logs of a previous cluster
                shutil.rmtree(old["data_dir"], ignore_errors=True)
            (self.root / LAST_STATE_FILE).unlink(missing_ok=True)
            for n in names:  # a data dir of a previous life would make a host re-apply instead of forming
                shutil.rmtree(self.root / n, ignore_errors=True)
            token_file = self.root / "token"
            write_token(token_file, secrets.token_hex(32), private=True)
            self.token = token_file.read_text().strip()
            tls_dir = self.root / "tls"
            if tls:
                try:
                    make_cluster_tls(tls_dir, names)
                except CaError as e:
                    raise ClusterError(str(e)) from None
                self.tls = load_client(tls_dir / CLIENT_DIR)
            else:
                shutil.rmtree(tls_dir, ignore_errors=True)
                self.tls = None
            addrs = {n: f"127.0.0.1:{free_port()}" for n in names}
            args = list(hostd_args)
            if config is not None:
                args += ["--config", str(config.absolute())]
            if capacity is not None:  # last: wins over a --capacity in hostd_args
                args += ["--capacity", repr(float(capacity))]
            self.state = {
                "version": STATE_VERSION,
                "kind": "local",
                "created": time.time(),
                "token_file": str(token_file),
                "tls_dir": str(tls_dir) if tls else "",
                "core": {n: addrs[n] for n in names[:core]},
                "args": args,
                "hosts": {
                    n: {"address": addrs[n], "core": i < core, "data_dir": str(self.root / n), "starts": 0,
                        "metrics_port": free_port()}
                    for i, n in enumerate(names)
                },
            }
            for n in names:
                self._spawn(n)
        return names

    def _signal(self, name: str, sig: int) -> None:
        rec = self._rec(name)
        with contextlib.suppress(ProcessLookupError):
            os.kill(rec["pid"], sig)

    def _require(self, name: str, *states: str) -> HostInfo:
        h = self.host(name)
        if h.state not in states:
            raise ClusterError(state_phrase(name, h.state))
        return h

    def kill(self, name: str) -> None:
        self._require(name, ALIVE, PAUSED)
        with self.locked():
            self._signal(name, signal.SIGKILL)
            self._rec(name)["stopped_by"] = "kill"
        self.wait_gone(name, 10)

    def pause(self, name: str) -> None:
        self._require(name, ALIVE)
        self._signal(name, signal.SIGSTOP)
        self._wait_state(name, PAUSED)

    def resume(self, name: str) -> None:
        self._require(name, PAUSED)
        self._signal(name, signal.SIGCONT)
        self._wait_state(name, ALIVE)

    def _wait_state(self, name: str, state: str, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        while self.host(name).state != state:
            if time.monotonic() > deadline:
                raise ClusterError(f"host {name} did not become {state} within {timeout:.0f} s")
            time.sleep(0.02)

    def restart(self, name: str) -> HostInfo:
        h = self.host(name)
        if h.up:
            raise ClusterError(f"{state_phrase(name, h.state)}: kill it or let it leave before restarting it")
        with self.locked():
            self._spawn(name)
        return self.host(name)

    def add(self, name: str) -> HostInfo:
        with self.locked():
            if not self.state:
                raise ClusterError(f"no cluster running ({self.describe()}); start one with `haactl cluster up`")
            if name in self.state["hosts"]:
                raise ClusterError(f"host {name} already exists ({self.host(name).state}); use `haactl host restart`")
            self.state["hosts"][name] = {
                "address": f"127.0.0.1:{free_port()}",
                "core": False,
                "data_dir": str(self.root / name),
                "starts": 0,
                "metrics_port": free_port(),
            }
            shutil.rmtree(self.root / name, ignore_errors=True)
            if self.state.get("tls_dir"):  # its certificate, from the cluster's CA
                try:
                    ClusterCA.load(Path(self.state["tls_dir"])).issue_host(name)
                except CaError as e:
                    raise ClusterError(f"cannot make a certificate for {name}: {e}") from None
            self._spawn(name)
        return self.host(name)

    def next_name(self) -> str:
        used = {int(n[1:]) for n in self.state.get("hosts", {}) if n[:1] == "h" and n[1:].isdigit()}
        i = 1
        while i in used:
            i += 1
        return f"h{i}"

    def terminate(self, name: str, timeout: float) -> None:
        h = self.host(name)
        if not h.up:
            return
        self._signal(name, signal.SIGCONT)
        self._signal(name, signal.SIGTERM)
        self.wait_gone(name, timeout)

    def wait_gone(self, name: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while self.host(name).up:
            p = self._procs.get(name)
            if p is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(0.05)
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        pid = self._rec(name).get("pid")
        if pid:
            _reap(int(pid), max(0.0, deadline - time.monotonic()))
        return True

    def mark_left(self, name: str) -> None:
        with self.locked():
            self._rec(name)["stopped_by"] = "leave"

    def down(self, grace: float = 5.0, purge: bool = False) -> dict[str, str]:
        """Stop every host (SIGTERM = graceful leave, SIGKILL after `grace` s); remove the state file (and
        with `purge` the logs). Returns how each running host ended."""
        out: dict[str, str] = {}
        with self.locked():
            up = [h for h in self.hosts() if h.up]
            for h in up:
                self._signal(h.name, signal.SIGCONT)
                self._signal(h.name, signal.SIGTERM)
            deadline = time.monotonic() + grace
            for h in up:
                while self.host(h.name).up and time.monotonic() < deadline:
                    time.sleep(0.05)
                if self.host(h.name).up:
                    self._signal(h.name, signal.SIGKILL)
                    self.wait_gone(h.name, 10)
                    out[h.name] = "SIGKILL"
                else:
                    out[h.name] = "SIGTERM"
                p = self._procs.get(h.name)
                if p is not None:  # our own child: reap it (no zombie left behind)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        p.wait(1)
                pid = self.state["hosts"][h.name].get("pid")
                if pid:  # started by this process through another backend object: reap it too
                    _reap(int(pid), 5.0)
                self.state["hosts"][h.name]["stopped_by"] = "down"
            hosts = self.state.get("hosts", {})
            if purge:
                self.state_path.unlink(missing_ok=True)
                (self.root / LAST_STATE_FILE).unlink(missing_ok=True)
            elif self.state:
                self.save()
                self.state_path.replace(self.root / LAST_STATE_FILE)
            if purge:
                for rec in hosts.values():
                    shutil.rmtree(rec["data_dir"], ignore_errors=True)
                (self.root / "token").unlink(missing_ok=True)
                shutil.rmtree(self.root / "tls", ignore_errors=True)
            self.state = {}
        if purge:
            (self.root / "cluster.lock").unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                self.root.rmdir()
        return out

    # ------------------------------------------------------------------ logs
    def log_path(self, name: str) -> Path:
        return Path(self._rec(name)["data_dir"]) / f"{name}.jsonl"

    def log_records(self, names: Sequence[str], follow: bool) -> Iterator[tuple[str, str]]:
        offsets: dict[str, int] = {}
        partial: dict[str, bytes] = {}

        def read_new(name: str) -> list[str]:
            path = self.log_path(name)
            try:
                with open(path, "rb") as f:
                    f.seek(offsets.get(name, 0))
                    data = f.read()
            except FileNotFoundError:
                return []
            offsets[name] = offsets.get(name, 0) + len(data)
            data = partial.pop(name, b"") + data
            lines = data.split(b"\n")
            if lines[-1]:
                partial[name] = lines[-1]
            return [ln.decode("utf-8", "replace") for ln in lines[:-1] if ln.strip()]

        for n in names:
            for line in read_new(n):
                yield n, line
        while follow:
            time.sleep(0.2)
            for n in names:
                for line in read_new(n):
                    yield n, line

    def hostd_args_text(self) -> str:
        return shlex.join(self.state.get("args", []))
