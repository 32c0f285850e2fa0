"""Helpers of the container chaos tests: is docker usable here, and a `Chaos` handle on the compose cluster
that reads it through the control API (statuses, convergence, removal, the leader)."""

from __future__ import annotations

import random
from collections.abc import Callable, Iterable
from typing import Any

import grpc
from helpers import wait_sync

from haa.cluster.compose_backend import ComposeBackend
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb

NAMES = [f"h{i}" for i in range(1, 11)]


def docker_problem() -> str | None:
    """Why the chaos tests cannot run here (None: they can)."""
    try:
        import docker
    except ImportError:
        return "the docker SDK is not installed"
    try:
        client = docker.from_env(version="auto", timeout=10)
        client.ping()
    except Exception as e:
        return f"no docker engine reachable ({e.__class__.__name__}): run `make docker-setup`"
    try:
        client.images.get("haa-hostd:latest")
    except docker.errors.ImageNotFound:
        return "the image haa-hostd:latest is missing: run `make image`"
    finally:
        client.close()
    return None


class Chaos:
    """The compose cluster under test plus helpers that read it through the control API."""

    def __init__(self, backend: ComposeBackend, seed: int) -> None:
        self.backend = backend
        self.seed = seed
        self.rng = random.Random(seed)
        self.addr = {h.name: h.address for h in backend.hosts()}

    def client(self, name: str, timeout: float = 3.0) -> ControlClient:
        return ControlClient(self.addr[name], self.backend.token, timeout=timeout)

    def alive(self) -> list[str]:
        return [h.name for h in self.backend.hosts() if h.state == "alive"]

    def statuses(self, names: Iterable[str] | None = None) -> dict[str, cpb.StatusReply]:
        out = {}
        for n, r in self.backend.statuses(names, timeout=2.0).items():
            if isinstance(r, cpb.StatusReply):
                out[n] = r
        return out

    def wait(self, pred: Callable[[], Any], timeout: float, what: str) -> Any:
        """`pred()` once true (an RPC error is "not yet"); the timeout message names the seed."""
        return wait_sync(pred, timeout, f"{what} (seed {self.seed})", interval=0.2, ignore=(grpc.RpcError,))

    def converged(self, expect: list[str]) -> dict[str, cpb.StatusReply] | None:
        """Every expected host answers, is a member of the same view with exactly `expect` and holds the
        same DDB; None otherwise."""
        st = self.statuses(expect)
        if len(st) != len(expect):
            return None
        views = {(tuple(r.members), r.view, r.ddb_hash, r.state_hash) for r in st.values()}
        if len(views) != 1 or not all(r.member for r in st.values()):
            return None
        members = next(iter(views))[0]
        return st if sorted(members) == sorted(expect) else None

    def wait_converged(self, expect: list[str], timeout: float) -> dict[str, cpb.StatusReply]:
        try:
            return self.wait(lambda: self.converged(expect), timeout, f"{len(expect)} hosts in one view, equal DDB")
        except AssertionError as e:
            raise AssertionError(f"{e}\n{self.describe()}") from None

    def describe(self) -> str:
        """One line per host: what it thinks of the group (for failure messages)."""
        states = {h.name: h.state for h in self.backend.hosts()}
        st = self.statuses()
        lines = []
        for n in NAMES:
            r = st.get(n)
            if r is None:
                lines.append(f"  {n}: {states.get(n, '?')}, no answer")
                continue
            lines.append(
                f"  {n}: inc {r.incarnation} member={r.member} view {r.view} leader {r.leader} "
                f"members {','.join(r.members)} suspects {','.join(r.suspicions) or '-'} "
                f"locked {r.locked or '-'} applicants {','.join(r.applicants) or '-'} "
                f"active_tx {r.active_transactions} global_seq {r.global_seq} ddb {r.ddb_size}/{r.ddb_hash[:8]}"
            )
        return "\n".join(lines)

    def removed(self, gone: list[str]) -> bool:
        st = {n: r for n, r in self.statuses().items() if n not in gone}
        return bool(st) and all(r.member and not set(gone) & set(r.members) for r in st.values())

    def wait_removed(self, gone: list[str], timeout: float) -> None:
        self.wait(lambda: self.removed(gone), timeout, f"{gone} removed from every view")

    def leader(self) -> str:
        st = self.statuses()
        leaders = {r.leader for r in st.values() if r.member}
        assert len(leaders) == 1, f"members disagree on the leader: {leaders}"
        return leaders.pop()
