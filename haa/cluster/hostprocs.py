"""Host processes for experiments and tests: real `haa-hostd` processes on free loopback ports, one data dir each.

Used by the experiments (haa.lab.experiments: AP-1..AP-4, ddb, memory) and the tests (moved here from
haactl/local.py: haa must not import haactl). Each host gets its own folder under the cluster
root (`<root>/<name>/`: JSON-lines log `<name>.jsonl`, stderr per start) and the cluster shares one token
file. `HostProc` is one host process (start, SIGKILL, SIGSTOP/SIGCONT, SIGTERM, control client);
`LocalCluster` starts them all and waits until every host trusts every other (with `tls`, over mutual TLS:
a cluster CA and certificates in `<root>/tls`, haa.cluster.tls). `free_port`, `hostd_command`
and `member_command` live in haa.cluster.procs (the local cluster backend and the mission runner use them too)
and are importable from here as before. `MemberHost` is one membership-mode host with a given core (the
experiments grow and shrink groups of them); `wait_for` polls a condition, RPC errors counting as "not yet".
(`haactl cluster` itself runs on haa.cluster.local_backend, which keeps its state on disk between commands.)
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import grpc

from haa.cluster.procs import free_port, hostd_command, member_command
from haa.cluster.tls import CLIENT_DIR, make_cluster_tls
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb
from haa.tls import ClientTls, load_client

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


class HostProc:
    def __init__(
        self, name: str, port: int, peers: dict[str, int], root: Path, token_file: Path, args: list[str],
        tls: ClientTls | None = None,
    ) -> None:
        self.name = name
        self.tls = tls
        self.port = port
        self.address = f"127.0.0.1:{port}"
        self.data_dir = root / name
        self.cmd = [
            *hostd_command(),
            "--name",
            name,
            "--listen",
            self.address,
            "--peers",
            ",".join(f"{p}=127.0.0.1:{pp}" for p, pp in peers.items()),
            "--token-file",
            str(token_file),
            "--data-dir",
            str(self.data_dir),
            *args,
        ]
        self.proc: subprocess.Popen[bytes] | None = None
        self.token = token_file.read_text().strip()
        self._client: ControlClient | None = None
        self.starts = 0

    def start(self) -> None:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.starts += 1
        err = open(self.data_dir / f"stderr.{self.starts}.txt", "wb")  # noqa: SIM115 - owned by the process
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=err, env={**os.environ})
        err.close()

    @property
    def client(self) -> ControlClient:
        if self._client is None:
            self._client = ControlClient(self.address, self.token, tls=self.tls, server_name=self.name)
        return self._client

    def status(self) -> cpb.StatusReply:
        return self.client.status()

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def kill9(self) -> None:
        self.signal(signal.SIGKILL)
        assert self.proc is not None
        self.proc.wait(10)

    def terminate(self, timeout: float = 10.0) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
        return self.proc.wait(timeout)

    def log_events(self) -> list[dict[str, Any]]:
        path = self.data_dir / f"{self.name}.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


class LocalCluster:
    """N haa-hostd processes, full mesh, on free loopback ports."""

    def __init__(
        self, names: list[str], root: Path, token: str | None = None, args: list[str] | None = None, tls: bool = False
    ) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        token = token or secrets.token_hex(24)
        self.token = token
        self.token_file = root / "token"
        self.token_file.write_text(token + "\n")
        self.token_file.chmod(0o600)
        ports = {n: free_port() for n in names}
        client = None
        if tls:
            ca = make_cluster_tls(root / "tls", names)
            client = load_client(root / "tls" / CLIENT_DIR)
        self.hosts = {
            n: HostProc(n, ports[n], {p: pp for p, pp in ports.items() if p != n}, root, self.token_file,
                        [*(args or []), *(["--tls-dir", str(ca.host_dir(n))] if tls else [])], client)
            for n in names
        }

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


def member_group(base: Path, hosts: int, hostd_yaml: str, core_size: int = 3, tag: str = "group") -> list[MemberHost]:
    """`hosts` membership-mode hosts h1..hN under `base`, not started: a fresh cluster token in `base/token`, the
    first `core_size` as the core process list, each without agents and with `hostd_yaml` (the text of a
    hostd.yaml, written to `base/hostd.yaml`) as its configuration. The benchmarks' group (haa.lab.experiments.ddb,
    haa/lab/bench/seq_ab.py)."""
    token = f"{tag}-{time.time_ns()}"
    (base / "token").write_text(token + "\n")
    conf = base / "hostd.yaml"
    conf.write_text(hostd_yaml)
    names = [f"h{i + 1}" for i in range(hosts)]
    ports = {n: free_port() for n in names}
    core = {n: f"127.0.0.1:{ports[n]}" for n in names[:core_size]}
    return [MemberHost(n, ports[n], core, base, token, ["--no-agents", "--config", str(conf)]) for n in names]


class MemberHost:
    """One membership-mode haa-hostd process on loopback, its data dir `<root>/<name>` and the cluster token
    file `<root>/token` (restartable: each start is a new incarnation). Used by benchmarks and tests."""

    def __init__(
        self, name: str, port: int, core: dict[str, str], root: Path, token: str, args: list[str] | None = None
    ) -> None:
        self.name = name
        self.address = f"127.0.0.1:{port}"
        self.data_dir = root / name
        self.log_file = self.data_dir / f"{name}.jsonl"
        self.cmd = member_command(name, self.address, core, root / "token", self.data_dir, args)
        self.proc: subprocess.Popen[bytes] | None = None
        self.client = ControlClient(self.address, token)
        self.starts = 0

    def start(self) -> None:
        self.starts += 1
        self.data_dir.mkdir(parents=True, exist_ok=True)
        with open(self.data_dir / f"stderr.{self.starts}.txt", "wb") as err:
            self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=err)

    def status(self) -> cpb.StatusReply:
        return self.client.status()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
            self.proc.wait(10)

    def events(self, since: float, names: set[str] | None = None) -> list[dict[str, Any]]:
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
