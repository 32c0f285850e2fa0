"""What `haactl cluster|host|ddb|logs` need from a cluster, whatever runs it.

A `Backend` knows the hosts of one cluster (names, control addresses, whether each process or container
is alive, paused or gone) and how to start, kill, pause, resume and restart them. Two implementations:
`haa.cluster.local_backend.LocalBackend` (haa-hostd processes on loopback, recorded in a state file) and
`haa.cluster.compose_backend.ComposeBackend` (the docker compose cluster of compose/compose.yaml, through the
docker SDK). Everything that only talks to the hosts' control API — status fan-out, waiting for the group
to form, for a host to leave the view or to rejoin, a graceful leave — is written once here, and so is what
the container backends (compose, swarm) share: their docker SDK client (`docker_client`), their log followers.

A cluster made with `--tls` (mutual TLS, docs/deploy.md) gives the backend haactl's client certificate
(`tls`); `connect` is the one place a control channel is made, over TLS when the cluster has it.

Every operator mistake or unreachable cluster raises `ClusterError` with one clear line; the CLI prints it
and exits with code 1.
"""

from __future__ import annotations

import os
import queue
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import grpc

from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb
from haa.tls import ClientTls

#: host states (process or container)
ALIVE = "alive"
PAUSED = "paused"
KILLED = "killed"
LEFT = "left"
DEAD = "dead"  # exited on its own, or stopped by something else
STOPPED = "stopped"  # created, never started (compose)
UP_STATES = frozenset({ALIVE, PAUSED})


class ClusterError(Exception):
    """An error the operator can act on; `str()` is one line."""


class StartError(ClusterError):
    """A host process exited right after it was started (bad settings, port in use, ...)."""


def state_phrase(name: str, state: str) -> str:
    """ "host h5 has left", "host h2 is killed", ..."""
    return f"host {name} {'has left' if state == LEFT else 'is ' + state}"


def natural_key(name: str) -> tuple[str, int, str]:
    """Sort h2 before h10."""
    m = re.match(r"^(.*?)(\d+)$", name)
    return (m.group(1), int(m.group(2)), name) if m else (name, -1, name)


def merged_follow(names: Sequence[str], follow: Callable[[str, queue.Queue[tuple[str, str]], threading.Event], None]
                  ) -> Iterator[tuple[str, str]]:
    """(host, line) pairs from one `follow(name, q, stop)` thread per host, merged as they come, until the
    consumer stops (then `stop` is set: each follower ends at its next check). The container backends'
    `log_records(follow=True)`."""
    q: queue.Queue[tuple[str, str]] = queue.Queue()
    stop = threading.Event()
    for n in names:
        threading.Thread(target=follow, args=(n, q, stop), daemon=True).start()
    try:
        while True:
            yield q.get()
    finally:
        stop.set()


def docker_client() -> Any:
    """The docker SDK client of the container backends (compose, swarm), or `ClusterError` with what to do."""
    try:
        import docker
    except ImportError:
        raise ClusterError("the docker SDK is not installed in this environment (pip install docker)") from None
    try:
        client = docker.from_env(version="auto", timeout=60)
        client.ping()
    except Exception as e:  # docker.errors.DockerException, requests errors
        where = os.environ.get("DOCKER_HOST", "the local docker socket")
        raise ClusterError(
            f"no docker engine reachable at {where} ({e.__class__.__name__}): `make docker-setup`"
        ) from None
    return client


@dataclass
class HostInfo:
    """One host as the backend sees it (no RPC involved)."""

    name: str
    address: str  # control address reachable from this machine (HOST:PORT)
    state: str  # ALIVE, PAUSED, KILLED, LEFT, DEAD, STOPPED
    core: bool = False
    pid: int | None = None
    container: str | None = None  # short container id (compose)
    detail: str = ""  # e.g. the exit code of a dead container
    metrics_url: str = ""  # its Prometheus /metrics reachable from this machine ("" if it serves none)

    @property
    def up(self) -> bool:
        return self.state in UP_STATES


def rpc_error_text(name: str, address: str, err: grpc.RpcError, what: str = "") -> str:
    """A one-line explanation of a failed control call."""
    code = err.code() if hasattr(err, "code") else None
    detail = err.details() if hasattr(err, "details") else str(err)
    where = f"host {name} ({address})"
    if code == grpc.StatusCode.UNAUTHENTICATED:
        return f"{where} rejected the cluster token: the token file does not belong to this cluster"
    if code == grpc.StatusCode.UNAVAILABLE:
        if "ssl" in detail.lower() or "handshake" in detail.lower() or "certificate" in detail.lower():
            return f"{where} refused the TLS handshake: this cluster's client certificate does not fit ({detail[:200]})"
        return f"{where} does not answer (connection refused or closed): is it down?"
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        return f"{where} did not answer in time{f' ({what})' if what else ''}: paused, hung or overloaded?"
    if code == grpc.StatusCode.UNIMPLEMENTED:
        return f"{where} does not implement {what or 'this call'}: an older haa-hostd (rebuild the image?)"
    return f"{where}: {what + ' failed: ' if what else ''}{code.name if code else 'error'}: {detail}"


@dataclass
class Formation:
    """Progress of a group towards an expected member set."""

    done: bool
    members: list[str] = field(default_factory=list)
    leader: str = ""
    view: int = 0
    joined: int = 0  # hosts that report themselves members of the agreed view
    note: str = ""


def agreed_group(replies: dict[str, cpb.StatusReply]) -> tuple[list[str], str, int]:
    """The group as the most advanced member sees it: (members, leader, view)."""
    best: cpb.StatusReply | None = None
    for r in replies.values():
        if r.member and (best is None or (r.view, r.global_seq) > (best.view, best.global_seq)):
            best = r
    if best is None:
        return [], "", 0
    return list(best.members), best.leader, int(best.view)


class Backend(ABC):
    """A cluster of haa-hostd hosts that this machine can reach and control."""

    kind = ""
    rpc_timeout = 2.0

    def __init__(self, token: str, tls: ClientTls | None = None) -> None:
        self.token = token
        #: haactl's client certificate of a `--tls` cluster (None: token only)
        self.tls = tls

    def connect(self, h: HostInfo, timeout: float | None = None) -> ControlClient:
        """A control client of host `h` (over mutual TLS, checking the host's certificate, if the cluster has it)."""
        return ControlClient(h.address, self.token, timeout=timeout or self.rpc_timeout, tls=self.tls,
                             server_name=h.name)

    # ------------------------------------------------------------------ backend-specific
    @abstractmethod
    def describe(self) -> str:
        """One line: which cluster this is (for headers and errors)."""

    @abstractmethod
    def hosts(self) -> list[HostInfo]:
        """Every host of the cluster, in natural name order (empty: no cluster)."""

    @abstractmethod
    def kill(self, name: str) -> None:
        """SIGKILL (connection refused from now on)."""

    @abstractmethod
    def pause(self, name: str) -> None:
        """SIGSTOP / freeze (a hung host: its TCP connections stay open)."""

    @abstractmethod
    def resume(self, name: str) -> None:
        """SIGCONT / unfreeze."""

    @abstractmethod
    def restart(self, name: str) -> HostInfo:
        """Start a stopped host again (a new incarnation, same data dir, that re-applies)."""

    @abstractmethod
    def add(self, name: str) -> HostInfo:
        """Start a new non-core host that joins through the core list."""

    @abstractmethod
    def next_name(self) -> str:
        """A free host name for `host add` without a name."""

    @abstractmethod
    def terminate(self, name: str, timeout: float) -> None:
        """SIGTERM (graceful leave) and wait until it is gone."""

    @abstractmethod
    def wait_gone(self, name: str, timeout: float) -> bool:
        """Wait until the host's process/container has stopped; True if it did."""

    @abstractmethod
    def mark_left(self, name: str) -> None:
        """Record that the host left gracefully (for `status`)."""

    @abstractmethod
    def log_records(self, names: Sequence[str], follow: bool) -> Iterator[tuple[str, str]]:
        """(host, raw log line) pairs: everything logged so far, then — with `follow` — new lines as they
        come, until the consumer stops."""

    # ------------------------------------------------------------------ common
    def host(self, name: str) -> HostInfo:
        hosts = self.hosts()
        for h in hosts:
            if h.name == name:
                return h
        known = ", ".join(h.name for h in hosts) or "none"
        raise ClusterError(f"unknown host {name!r} in the {self.describe()} (hosts: {known})")

    def require_hosts(self) -> list[HostInfo]:
        hosts = self.hosts()
        if not hosts:
            up = "haactl cluster up" + (" --compose" if self.kind == "compose" else "")
            raise ClusterError(f"no cluster running ({self.describe()}); start one with `{up}`")
        return hosts

    def client(self, name: str, timeout: float | None = None) -> ControlClient:
        h = self.host(name)
        if h.state != ALIVE:
            hint = {PAUSED: "haactl host resume", KILLED: "haactl host restart", LEFT: "haactl host restart"}
            extra = f" ({hint[h.state]} {name})" if h.state in hint else ""
            raise ClusterError(f"{state_phrase(name, h.state)}{extra}")
        return self.connect(h, timeout)

    def call(self, name: str, fn: Callable[[ControlClient], Any], what: str, timeout: float | None = None) -> Any:
        """Run one control call on host `name`, turning RPC failures into `ClusterError`."""
        c = self.client(name, timeout)
        try:
            return fn(c)
        except grpc.RpcError as e:
            raise ClusterError(rpc_error_text(name, c.address, e, what)) from None
        finally:
            c.close()

    def statuses(
        self, names: Iterable[str] | None = None, timeout: float | None = None
    ) -> dict[str, cpb.StatusReply | Exception]:
        """Status of the named hosts (default: every alive host), in parallel; failures as exceptions."""
        infos = {h.name: h for h in self.hosts()}
        wanted = [n for n in (names if names is not None else infos) if n in infos and infos[n].state == ALIVE]
        out: dict[str, cpb.StatusReply | Exception] = {}

        def one(n: str) -> tuple[str, cpb.StatusReply | Exception]:
            c = self.connect(infos[n], timeout)
            try:
                return n, c.status()
            except grpc.RpcError as e:
                return n, e
            finally:
                c.close()

        if wanted:
            with ThreadPoolExecutor(max_workers=min(16, len(wanted))) as pool:
                out.update(pool.map(one, wanted))
        return out

    def check_token(self, replies: dict[str, cpb.StatusReply | Exception]) -> None:
        """A wrong token makes every host answer UNAUTHENTICATED: say so instead of "not formed yet"."""
        errs = [e for e in replies.values() if isinstance(e, grpc.RpcError)]
        if errs and all(e.code() == grpc.StatusCode.UNAUTHENTICATED for e in errs) and len(errs) == len(replies):
            name = next(iter(replies))
            raise ClusterError(rpc_error_text(name, self.host(name).address, errs[0]))

    def formation(self, expect: Sequence[str]) -> Formation:
        """Has the group formed with exactly `expect` as members, agreed by every one of them?"""
        replies = self.statuses(expect)
        self.check_token(replies)
        ok = {n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply)}
        members, leader, view = agreed_group(ok)
        joined = sum(1 for r in ok.values() if r.member and r.view == view and list(r.members) == members)
        done = len(ok) == len(expect) and joined == len(expect) and sorted(members) == sorted(expect)
        down = [n for n in expect if n not in ok]
        note = f"view {view}, leader {leader or '-'}" if members else "no group yet"
        if down:
            note += f"; not answering: {', '.join(down[:4])}{' ...' if len(down) > 4 else ''}"
        return Formation(done, members, leader, view, joined, note)

    def removed_everywhere(self, gone: Sequence[str]) -> Formation:
        """Is every name in `gone` out of the view of every alive member?"""
        replies = self.statuses()
        self.check_token(replies)
        ok = {n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply) and n not in gone}
        members, leader, view = agreed_group(ok)
        still = [n for n, r in ok.items() if r.member and any(g in r.members for g in gone)]
        live_members = [n for n, r in ok.items() if r.member]
        done = bool(live_members) and not still
        note = f"view {view}; still in the view of {', '.join(still)}" if still else f"view {view}"
        return Formation(done, members, leader, view, len(live_members) - len(still), note)

    def rejoined(self, name: str, incarnation: int | None = None) -> Formation:
        """Is host `name` (its current incarnation) a member in the view of every alive member?"""
        replies = self.statuses()
        self.check_token(replies)
        ok = {n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply)}
        own = ok.get(name)
        inc = incarnation if incarnation is not None else (own.incarnation if own is not None else None)
        members, leader, view = agreed_group(ok)
        agree = [
            n
            for n, r in ok.items()
            if r.member and any(m.name == name and (inc is None or m.incarnation == inc) for m in r.member_info)
        ]
        live_members = [n for n, r in ok.items() if r.member]
        done = own is not None and own.member and len(agree) == len(live_members)
        note = f"view {view}; {len(agree)}/{len(live_members)} members have {name}"
        return Formation(done, members, leader, view, len(agree), note)

    def pick_host(self, prefer: str | None = None) -> str:
        """An alive host to talk to: `prefer` if given (must be alive), else the first alive member."""
        if prefer:
            self.client(prefer).close()  # raises ClusterError if unknown or not alive
            return prefer
        hosts = self.require_hosts()
        alive = [h.name for h in hosts if h.state == ALIVE]
        if not alive:
            raise ClusterError(f"no host is alive in the {self.describe()}")
        replies = self.statuses(alive)
        self.check_token(replies)
        for n in alive:
            r = replies.get(n)
            if isinstance(r, cpb.StatusReply) and r.member:
                return n
        for n in alive:
            if isinstance(replies.get(n), cpb.StatusReply):
                return n
        raise ClusterError(f"no alive host answers in the {self.describe()}")

    def leave(self, name: str, timeout: float = 20.0) -> str:
        """Graceful leave: the Leave RPC (the host exits once the group removed it); SIGTERM if the RPC is
        unavailable. Returns how it left."""
        how = "Leave RPC"
        c = self.client(name, timeout=timeout)
        try:
            reply = c.leave(exit=True, timeout=timeout)
            if not reply.left:
                raise ClusterError(f"host {name} did not leave: {reply.reason or 'no reason given'}")
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.UNAUTHENTICATED:
                raise ClusterError(rpc_error_text(name, c.address, e, "Leave")) from None
            # UNIMPLEMENTED (older daemon), or the process exited before the reply made it back
            if e.code() == grpc.StatusCode.UNIMPLEMENTED:
                how = "SIGTERM"
                self.terminate(name, timeout)
        finally:
            c.close()
        if not self.wait_gone(name, timeout):
            how += " + SIGTERM (still running after the leave)"
            self.terminate(name, timeout)
        self.mark_left(name)
        return how


def wait_until(
    check: Callable[[], Formation],
    timeout: float,
    on_progress: Callable[[Formation], None] | None = None,
    interval: float = 0.2,
    what: str = "the cluster",
) -> tuple[Formation, float]:
    """Poll `check` until done (returns it and the seconds it took) or raise `ClusterError` on timeout."""
    t0 = time.monotonic()
    last = Formation(False, note="no answer yet")
    while True:
        try:
            last = check()
        except grpc.RpcError as e:  # pragma: no cover - statuses() catches these
            last = Formation(False, note=str(e.code()))
        if on_progress:
            on_progress(last)
        if last.done:
            return last, time.monotonic() - t0
        if time.monotonic() - t0 > timeout:
            raise ClusterError(f"timed out after {timeout:.0f} s waiting for {what} ({last.note})")
        time.sleep(interval)
