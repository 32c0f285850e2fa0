"""The agent layer on real haa-hostd processes: a 4-host local cluster runs a counter pair while agents are
moved, killed, handed over by a graceful leave (thesis AF-1) and recovered after a host crash."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest

from haa.cluster.hostprocs import MemberGroup, MemberHost
from haa.cluster.hostprocs import wait_for as wait

TOKEN = "agents-test-token"
NAMES = ["h1", "h2", "h3", "h4"]
CORE = ["h1", "h2", "h3"]
ARGS = ["--rebalance-period", "0", "--drain-timeout", "8", "--agent-hang-timeout", "2"]


@pytest.fixture(scope="module")
def hosts(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, MemberHost]]:
    root: Path = tmp_path_factory.mktemp("agents")
    group = MemberGroup(root, NAMES, core=CORE, token=TOKEN, args=ARGS)
    hs = group.hosts
    group.start()
    try:
        wait(lambda: all(len(h.status().members) == 4 for h in hs.values()), 40, "a group of 4")
        yield hs
    finally:
        group.close()


def live(hs: dict[str, MemberHost]) -> list[MemberHost]:
    return [h for h in hs.values() if h.alive()]


def table(hs: dict[str, MemberHost]) -> dict[str, object]:
    return {a.name: a for a in live(hs)[0].client.agent_list().agents}


def active_on(hs: dict[str, MemberHost], name: str) -> str | None:
    """The host whose instance of `name` is active and which the table names owner; None while moving or
    starting. The owner's own phase must be "active": the table says active as soon as OAC(recovered) commits,
    while the process may still be starting (a shell killed then is replaced, not recovered: recovery.py)."""
    t = table(hs)
    a = t.get(name)
    if a is None or a.status != "active":
        return None
    runners = [(h.name, x.local_phase) for h in live(hs) for x in h.client.agent_list().agents
               if x.name == name and x.local_phase]
    return a.owner if runners == [(a.owner, "active")] else None


def counters(hs: dict[str, MemberHost], name: str) -> dict[str, int]:
    r = live(hs)[0].client.ddb_get(keys=[f"demo/{name}"])
    return json.loads(r.objects[0].value) if r.objects else {}


def settled(hs: dict[str, MemberHost]) -> bool:
    return all(active_on(hs, n) for n in ("A1", "A1.1"))


def test_counter_pair_survives_moves_kills_leave_and_crash(hosts: dict[str, MemberHost]) -> None:
    h1 = hosts["h1"].client
    r = h1.agent_spawn("counter", json.dumps({"spawn_peer": True, "period": 0.03, "backup_every": 25}).encode())
    assert r.ok and r.name == "A1", r
    wait(lambda: settled(hosts), 20, "A1 and its child A1.1 active")
    tree = table(hosts)
    assert tree["A1.1"].parent == tree["A1"].id

    # an operator move is a transfer (Alg. 5-6): nothing lost
    src = active_on(hosts, "A1")
    dst = next(n for n in NAMES if n != src)
    assert h1.agent_move("A1", dst).ok
    wait(lambda: active_on(hosts, "A1") == dst, 15, f"A1 thawed on {dst}")
    # SIGKILL of the agent process: a failure, recovered from its latest backup (Alg. 8)
    owner = active_on(hosts, "A1.1")
    assert owner is not None
    pid = next(a.pid for a in hosts[owner].client.agent_list().agents if a.name == "A1.1")
    assert pid > 0
    os.kill(pid, signal.SIGKILL)
    wait(lambda: (a := table(hosts)["A1.1"]).status == "active" and a.life == 2 and active_on(hosts, "A1.1"), 20,
         "A1.1 recovered")
    # a graceful leave hands the agents over first (thesis AF-1): a transfer, not a recovery
    wait(lambda: settled(hosts), 15, "settled")
    leaver = active_on(hosts, "A1")
    assert leaver is not None
    lives = {n: table(hosts)[n].life for n in ("A1", "A1.1")}
    hosts[leaver].proc.send_signal(signal.SIGTERM)
    assert hosts[leaver].proc.wait(30) == 0
    wait(lambda: settled(hosts) and active_on(hosts, "A1") != leaver, 20, "A1 handed over")
    assert {n: table(hosts)[n].life for n in ("A1", "A1.1")} == lives  # thawed, not recovered
    # a host crash: its agents are recovered elsewhere once the group removed it
    victim = active_on(hosts, "A1")
    assert victim is not None
    agent_pids = [a.pid for a in hosts[victim].client.agent_list().agents if a.local_phase]
    hosts[victim].kill()
    wait(lambda: settled(hosts) and active_on(hosts, "A1") != victim, 30, "A1 recovered after the crash")
    # the dead host's agent processes did not outlive it
    wait(lambda: not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
                         for p in agent_pids), 10, "the crashed host's agents gone")

    # at rest: every message of a sender life that did not crash arrived once, in order
    time.sleep(1.5)  # the pair runs a while on the healed group: a loss or a duplicate would show in its stats
    for name in ("A1", "A1.1"):
        c = counters(hosts, name)
        assert c["received"] > 10, c
        assert (c["lost"], c["out_of_order"], c["duplicate"]) == (0, 0, 0), (name, c)
    assert table(hosts)["A1"].recovery == "backup"


def test_operator_requests_reach_the_agent_wherever_it_runs(hosts: dict[str, MemberHost]) -> None:
    owner = active_on(hosts, "A1")
    assert owner is not None
    for h in live(hosts):  # through the owner and through every other host
        r = h.client.agent_request("A1", b"stats", timeout=5)
        assert r.ok, r.error
        assert json.loads(r.payload)["name"] == "A1"
    bad = live(hosts)[0].client.agent_request("A1", b"no-such-request")
    assert not bad.ok and "unknown counter request" in bad.error
    assert "unknown agent" in live(hosts)[0].client.agent_request("A42", b"stats").error


def test_spawn_errors_are_clear(hosts: dict[str, MemberHost]) -> None:
    c = live(hosts)[0].client
    r = c.agent_spawn("no-such-type")
    assert not r.ok and "unknown agent type" in r.reason and "counter" in r.reason
    assert not c.agent_move("A99", "h1").ok
    owner = active_on(hosts, "A1")
    other = next(h for h in live(hosts) if h.name != owner).client
    r = other.agent_kill("A1")  # only the host running an agent can kill its process
    assert not r.ok and r.owner == owner and f"its owner is {owner}" in r.reason
    lst = c.alloc("status")
    assert lst.session >= 1 and not lst.paused
    follower = next(h for h in live(hosts) if h.status().rank > 0).client
    before = follower.alloc("status").session
    follower.alloc("run")  # a member that is not the leader passes the request on
    wait(lambda: follower.alloc("status").session > before, 10, "a session started by the leader")
    assert c.alloc("pause").paused
    assert not c.alloc("resume").paused


def test_kill_of_an_agent_still_starting_is_refused(hosts: dict[str, MemberHost]) -> None:
    """While an agent's process is a shell (here: every fork server stopped, so no shell says hello), its host
    refuses to kill it: a killed shell is only replaced (recovery.py), and the operator would wait for a
    recovery that never comes. Once the fork servers run again the agent starts normally."""
    servers = [p for h in live(hosts) for p in psutil.Process(h.proc.pid).children()
               if "forkserver" in " ".join(p.cmdline())]
    assert len(servers) == len(live(hosts)), servers
    for p in servers:
        p.suspend()
    try:
        c = live(hosts)[0].client
        r = c.agent_spawn("counter", json.dumps({"period": 0.05}).encode())
        assert r.ok, r

        def starting() -> str | None:
            return next((h.name for h in live(hosts) for x in h.client.agent_list().agents
                         if x.name == r.name and x.local_phase == "recovering"), None)

        owner = wait(starting, 10, f"{r.name} being prepared by a host")
        k = hosts[owner].client.agent_kill(r.name)
        assert not k.ok and f"still starting on {owner} (recovering)" in k.reason, k
    finally:
        for p in servers:
            p.resume()
    wait(lambda: active_on(hosts, r.name), 20, f"{r.name} active once the fork servers run")
    assert table(hosts)[r.name].life == 1  # started once, never recovered


def test_a_spawn_with_the_same_key_gets_the_same_child(hosts: dict[str, MemberHost]) -> None:
    """Idempotent spawn (docs/agents.md): a second spawn_child with a key the parent already used answers the
    child the first one created; key "" always creates one."""
    c = live(hosts)[0].client
    r = c.agent_spawn("probe", b"{}")
    assert r.ok, r
    wait(lambda: active_on(hosts, r.name), 20, f"{r.name} active")

    def spawn(key: str | None) -> str:
        cmd: dict[str, object] = {"op": "spawn_child", "type": "probe"}
        if key is not None:
            cmd["key"] = key
        a = c.agent_request(r.name, json.dumps(cmd).encode(), timeout=20)
        assert a.ok, a.error
        return str(json.loads(a.payload))

    first = spawn("k")
    assert spawn("k") == first
    others = {spawn(""), spawn(""), spawn("j")}
    assert len(others) == 3 and first not in others
    kids = [a for a in c.agent_list().agents if a.name.startswith(r.name + ".")]
    assert len(kids) == 4, [a.name for a in kids]
