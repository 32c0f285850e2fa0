"""A live 3-host cluster for the hostile-client and hostile-peer suites, and its health check.

`start_cluster(root)` starts h1..h3 (membership mode, on loopback) and a counter pair on h2; `assert_healthy`
checks what must hold after every hostile request: every host lives, the group agrees on one view, the DDB
replicas are equal at a common sequence number, a write commits within a second, and no agent has two live
instances. Used by tests/test_hostile_clients.py and tests/test_hostile_peers.py (import it as `hostilecluster`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import grpc
import psutil

from haa.cluster.hostprocs import MemberGroup, MemberHost
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import ops as ddb

TOKEN = "hostile-peers-token"
NAMES = ["h1", "h2", "h3"]
ARGS = ["--rebalance-period", "0", "--agent-hang-timeout", "2"]
AGENTS = ("A1", "A1.1")


# ------------------------------------------------------------------------------------------- the cluster


class Cluster:
    def __init__(self, root: Path) -> None:
        self.root = root
        self.group = MemberGroup(root, NAMES, core=NAMES, token=TOKEN, args=ARGS)
        self.core = self.group.core
        self.hosts = self.group.hosts

    def second(self, name: str, tag: str) -> MemberHost:
        """Another haa-hostd under `name` (its own port and data directory), not started yet."""
        return self.group.new_host(name, root=self.root / tag)

    def members(self) -> list[MemberHost]:
        """The three hosts of the fixture (their current processes)."""
        return list(self.hosts.values())

    def close(self) -> None:
        self.group.close()


def view(h: MemberHost) -> tuple[tuple[tuple[str, int], ...], int]:
    s = h.status()
    return tuple((m.name, m.incarnation) for m in s.member_info), s.view


def agreed(hosts: list[MemberHost]) -> tuple[tuple[str, int], ...] | None:
    """The common member list (name, incarnation) if every host is a member of one and the same view whose
    names are exactly `hosts`' names, each at the incarnation its process reports; else None."""
    vs = {view(h) for h in hosts}
    if len(vs) != 1:
        return None
    members = next(iter(vs))[0]
    mine = {(h.name, h.status().incarnation) for h in hosts}
    return members if set(members) == mine else None


def live_instances(procs: list[MemberHost]) -> dict[str, list[str]]:
    """Agent name -> the hosts whose instance of it may output (phase active or freezing, process alive)."""
    out: dict[str, list[str]] = {}
    for h in procs:
        if not h.alive():
            continue
        try:
            agents = h.client.agent_list().agents
        except grpc.RpcError:
            continue
        for a in agents:
            if a.local_phase in ("active", "freezing") and a.pid > 0 and psutil.pid_exists(a.pid):
                out.setdefault(a.name, []).append(f"{h.name}@{h.address}")
    return out


def owner_runs(c: Cluster, name: str) -> str | None:
    """The host that owns `name` in the table and runs it alone, in phase active; None otherwise."""
    hs = c.members()
    rec = {a.name: a for a in hs[0].client.agent_list().agents}.get(name)
    if rec is None or rec.status != "active":
        return None
    runners = [(h.name, a.local_phase) for h in hs for a in h.client.agent_list().agents
               if a.name == name and a.local_phase]
    return rec.owner if runners == [(rec.owner, "active")] else None


def settled(c: Cluster) -> bool:
    return all(owner_runs(c, n) for n in AGENTS)


def assert_healthy(c: Cluster, extra: list[MemberHost] = ()) -> None:  # type: ignore[assignment]
    """Every host lives, one view with all three, equal DDB replicas, a write commits within a second, and
    no agent has two instances that may output."""
    hs = c.members()
    assert all(h.alive() for h in hs), [h.name for h in hs if not h.alive()]
    wait(lambda: agreed(hs), 20, "one view of h1, h2, h3")
    wait(lambda: len({(s.ddb_seq, s.ddb_hash) for s in (h.status() for h in hs)}) == 1, 10, "equal replicas")
    t0 = time.monotonic()
    r = hs[0].client.ddb_write([ddb.put(f"probe/{t0}", "blob", b"x")])
    took = time.monotonic() - t0
    assert r.committed, r.reason
    assert took < 1.0, f"a DDB write took {took:.2f} s"
    twice = {n: where for n, where in live_instances([*hs, *extra]).items() if len(where) > 1}
    assert not twice, f"agents with two live instances: {twice}"


def start_cluster(root: Path) -> Cluster:
    """Three hosts in one group, running a counter pair (A1, A1.1) on h2; `close()` it when done."""
    c = Cluster(root)
    for h in c.members():
        h.start()
    try:
        wait(lambda: agreed(c.members()), 30, "a group of 3")
        h1 = c.hosts["h1"].client
        r = h1.agent_spawn("counter", json.dumps({"spawn_peer": True, "period": 0.03, "backup_every": 10}).encode())
        assert r.ok, r
        wait(lambda: settled(c), 30, "A1 and A1.1 active")
        # h2 runs both agents: the host that is impersonated and displaced by tests/test_hostile_peers.py
        for n in AGENTS:
            if owner_runs(c, n) != "h2":
                assert h1.agent_move(n, "h2").ok
                wait(lambda n=n: owner_runs(c, n) == "h2", 20, f"{n} on h2")  # type: ignore[misc]
    except BaseException:
        c.close()
        raise
    return c
