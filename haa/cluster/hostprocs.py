"""Local hosts for benchmarks and tests: real `haa-hostd` processes on free loopback ports, one data dir each.

The one helper the experiments (haa.lab.experiments: AP-1..AP-4, ddb, memory), the tests and the scripts in bench/
start hosts with (moved here from haactl/local.py: haa must not import haactl). Every host gets its own folder
under the cluster root (`<root>/<name>/`: JSON-lines log `<name>.jsonl`, stderr per start) and the hosts of a
cluster share one token file.

* `HostProc` — one host process: start (again: a new incarnation), SIGKILL, SIGSTOP/SIGCONT, SIGTERM, its control
  client, its log. `MemberHost` makes one in membership mode (it finds the group through a core list, Alg. 3).
* `MemberGroup` — membership-mode hosts h1..hN under one root, the first K the core list; started, waited for
  until they form one group, killed together.
* `LocalCluster` — static-mode hosts, full mesh (`--peers`), waited for until every host trusts every other
  (with `tls`, over mutual TLS: a cluster CA and certificates in `<root>/tls`, haa.cluster.tls).
* `wait_for` polls a condition, RPC errors counting as "not yet".

`free_port`, `hostd_command` and `member_command` live in haa.cluster.procs (with `start_hostd`, which every local
host process is started by: the operator's cluster of haa.cluster.local_backend too) and are importable from here
as before. (`haactl cluster` and `haactl chaos run` use haa.cluster.local_backend, which keeps its state on disk
between commands; `LocalHosts` of haa.lab.experiments.localhosts is not a cluster of processes but several agent
supervisors in one process.)
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc

from haa.cluster.procs import free_port, hostd_command, member_command, start_hostd, static_command, write_token
from haa.cluster.tls import CLIENT_DIR, make_cluster_tls
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb
from haa.tls import ClientTls, load_client

__all__ = [
    "HostProc",
    "LocalCluster",
    "MemberGroup",
    "MemberHost",
    "free_port",
    "hostd_command",
    "member_command",
    "member_group",
    "wait_for",
]

T = TypeVar("T")


def wait_for(fn: Callable[[], T], timeout: float, what: str, interval: float = 0.05) -> T:
    """Poll `fn` until it returns something truthy (RPC errors count as "not yet")."""
    deadline = time.monotonic() + timeout
    last_err: Exception | None = None
    while True:
        try:
            v = fn()
            if v:
                return v
        except grpc.RpcError as e:
            last_err = e
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout}s waiting for {what} (last error: {last_err})")
        time.sleep(interval)


# ---------------------------------------------------------------------------------------------- one host


class HostProc:
    """One haa-hostd process on loopback: `name` at `address`, started with command line `cmd`, its data dir
    `data_dir`, the cluster `token` (and `tls`, haactl's certificate, for its control client). Not started until
    `start()`; each start is a new process (a new incarnation)."""

    def __init__(self, name: str, address: str, cmd: list[str], data_dir: Path, token: str,
                 tls: ClientTls | None = None) -> None:
        self.name = name
        self.address = address
        self.port = int(address.rpartition(":")[2])
        self.cmd = cmd
        self.data_dir = data_dir
        self.log_file = data_dir / f"{name}.jsonl"
        self.token = token
        self.tls = tls
        self.proc: subprocess.Popen[bytes] | None = None
        self._client: ControlClient | None = None
        self.starts = 0

    def start(self) -> None:
        self.starts += 1
        self.proc = start_hostd(self.cmd, self.data_dir, self.starts)

    @property
    def client(self) -> ControlClient:
        """Its control client (made at first use; `close()` closes it)."""
        if self._client is None:
            self._client = ControlClient(self.address, self.token, tls=self.tls, server_name=self.name)
        return self._client

    def status(self) -> cpb.StatusReply:
        return self.client.status()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def kill9(self) -> None:
        """SIGKILL (the process must have been started) and wait for it."""
        self.signal(signal.SIGKILL)
        assert self.proc is not None
        self.proc.wait(10)

    def kill(self) -> None:
        """SIGKILL it if it runs (paused or not) and wait for it; nothing if it does not."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
            self.proc.wait(10)

    def terminate(self, timeout: float = 10.0) -> int:
        """SIGTERM (a graceful stop; SIGCONT first, should it be paused); its exit code."""
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
        return self.proc.wait(timeout)

    def log_events(self) -> list[dict[str, Any]]:
        """Every line of its JSON-lines log."""
        return [json.loads(line) for line in self.log_file.read_text().splitlines() if line.strip()]

    def events(self, since: float, names: set[str] | None = None) -> list[dict[str, Any]]:
        """Its log's events stamped at or after `since` (of the given event names), none if it has no log yet;
        a line that does not parse is skipped."""
        if not self.log_file.exists():
            return []
        out = []
        for line in self.log_file.read_text().splitlines():
            try:
                e = json.loads(line)
            except ValueError:
                continue
            if e.get("ts", 0) >= since and (names is None or e.get("event") in names):
                out.append(e)
        return out

    def close(self) -> None:
        """Close its control client and kill the process if it still runs."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


class MemberHost(HostProc):
    """One membership-mode haa-hostd process on loopback port `port`, its data dir `<root>/<name>` and the cluster
    token file `<root>/token` (holding `token`); it finds the group through `core` (name -> address, Alg. 3)."""

    def __init__(
        self, name: str, port: int, core: dict[str, str], root: Path, token: str, args: list[str] | None = None
    ) -> None:
        address = f"127.0.0.1:{port}"
        super().__init__(name, address, member_command(name, address, core, root / "token", root / name, args),
                         root / name, token)


# ---------------------------------------------------------------------------------------------- groups


class MemberGroup:
    """Membership-mode hosts on loopback under one root (module docstring): the cluster token file `<root>/token`,
    the hosts `hosts` (a number: h1..hN; or their names), the first `core` of them (or the names given) the core
    list every host is started with, each on a free port with the arguments `args`. Not started until `start()`;
    `close()` (or the end of a `with`) kills every process of the group, also those made by `new_host`."""

    def __init__(self, root: Path, hosts: int | Sequence[str], *, core: int | Sequence[str] = 3,
                 token: str | None = None, args: Sequence[str] = ()) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.token = token or os.urandom(16).hex()
        write_token(root / "token", self.token)
        self.names = [f"h{i}" for i in range(1, hosts + 1)] if isinstance(hosts, int) else list(hosts)
        ports = {n: free_port() for n in self.names}
        core_names = self.names[:core] if isinstance(core, int) else list(core)
        #: the core list: name -> address
        self.core = {n: f"127.0.0.1:{ports[n]}" for n in core_names}
        self.args = list(args)
        self.hosts: dict[str, MemberHost] = {
            n: MemberHost(n, ports[n], self.core, root, self.token, list(self.args)) for n in self.names
        }
        self._others: list[MemberHost] = []

    def __enter__(self) -> MemberGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getitem__(self, name: str) -> MemberHost:
        return self.hosts[name]

    def __iter__(self) -> Iterator[MemberHost]:
        return iter(self.hosts.values())

    def new_host(self, name: str, args: Sequence[str] | None = None, root: Path | None = None) -> MemberHost:
        """Another host (not started) that finds this group through its core list: its own free port, the group's
        arguments unless `args` are given, and under `root` (its own data root: the token file is written there
        too) or the group's. Not one of `hosts`; `close()` kills it too."""
        if root is not None and root != self.root:
            root.mkdir(parents=True, exist_ok=True)
            write_token(root / "token", self.token)
        h = MemberHost(name, free_port(), self.core, root or self.root, self.token,
                       list(self.args if args is None else args))
        self._others.append(h)
        return h

    def start(self, names: Sequence[str] | None = None) -> None:
        """Start the hosts (all, or those named)."""
        for n in names or self.names:
            self.hosts[n].start()

    def form(self, timeout: float = 60.0, *, what: str | None = None, interval: float = 0.05) -> float:
        """Start every host and wait until they form one group (`wait_members`); the seconds that took."""
        t0 = time.monotonic()
        self.start()
        self.wait_members(timeout, what=what, interval=interval)
        return time.monotonic() - t0

    def members(self, name: str) -> list[str]:
        """The members of the view host `name` has now."""
        return list(self.hosts[name].status().members)

    def wait_members(self, timeout: float = 60.0, names: Sequence[str] | None = None, *, what: str | None = None,
                     interval: float = 0.05) -> None:
        """Wait until every host of `names` (default: all) is in a view of exactly `names`."""
        want = set(names or self.names)
        wait_for(lambda: all(set(self.members(x)) == want for x in want), timeout,
                 what or f"the group {sorted(want)}", interval=interval)

    def close(self) -> None:
        """Kill every process of the group and close their control clients."""
        seen: set[int] = set()
        for h in [*self.hosts.values(), *self._others]:
            if id(h) in seen:
                continue
            seen.add(id(h))
            h.kill()
            h.close()


def member_group(base: Path, hosts: int, hostd_yaml: str, core_size: int = 3, tag: str = "group") -> list[MemberHost]:
    """`hosts` membership-mode hosts h1..hN under `base`, not started (a `MemberGroup`'s hosts): a fresh cluster
    token, the first `core_size` as the core list, each without agents and with `hostd_yaml` (the text of a
    hostd.yaml, written to `base/hostd.yaml`) as its configuration. The DDB benchmarks' group
    (haa.lab.experiments.ddb, haa.lab.bench.seq_ab)."""
    conf = base / "hostd.yaml"
    conf.write_text(hostd_yaml)
    group = MemberGroup(base, hosts, core=core_size, token=f"{tag}-{time.time_ns()}",
                        args=["--no-agents", "--config", str(conf)])
    return list(group.hosts.values())


class LocalCluster:
    """N static-mode haa-hostd processes, full mesh, on free loopback ports (module docstring)."""

    def __init__(
        self, names: list[str], root: Path, token: str | None = None, args: list[str] | None = None, tls: bool = False
    ) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        token = token or secrets.token_hex(24)
        self.token = token
        self.token_file = root / "token"
        write_token(self.token_file, token, private=True)
        addrs = {n: f"127.0.0.1:{free_port()}" for n in names}
        client = None
        if tls:
            ca = make_cluster_tls(root / "tls", names)
            client = load_client(root / "tls" / CLIENT_DIR)
        self.hosts: dict[str, HostProc] = {}
        for n in names:
            host_args = [*(args or []), *(["--tls-dir", str(ca.host_dir(n))] if tls else [])]
            peers = {p: a for p, a in addrs.items() if p != n}
            cmd = static_command(n, addrs[n], peers, self.token_file, root / n, host_args)
            self.hosts[n] = HostProc(n, addrs[n], cmd, root / n, token, client)

    def __getitem__(self, name: str) -> HostProc:
        return self.hosts[name]

    def start(self) -> None:
        for h in self.hosts.values():
            h.start()

    def all_trusted(self, names: list[str] | None = None) -> bool:
        """Every listed host knows every other's current incarnation, trusts it and has its link up."""
        names = names or list(self.hosts)
        st = {n: self.hosts[n].status() for n in names}
        for n in names:
            for p in st[n].peers:
                if p.name not in st:
                    continue
                if p.incarnation != st[p.name].incarnation or p.suspected or p.excluded or not p.connected:
                    return False
        return True

    def wait_trusted(self, timeout: float = 20.0, names: list[str] | None = None) -> None:
        wait_for(lambda: self.all_trusted(names), timeout, "every host to trust every other")

    def close(self) -> None:
        for h in self.hosts.values():
            h.close()

    def __enter__(self) -> LocalCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
