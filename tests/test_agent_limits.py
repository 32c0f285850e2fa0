"""Agent configs and resource limits: an agent config is checked before its spawn commits; an
agent that cannot start backs off and ends `failed` (not recovered until an operator moves it); an agent over
its type's memory or CPU limit is killed by its host and recovered, the host staying responsive.

The table part is sans-I/O (AgentTable.apply). The rest runs real processes: a 2-host group with the agent
layer, requests injected through the raw control-API client (`ControlClient`, with the token: haactl's own
checks do not protect the cluster), and the test agent types of tests/limitagents.py, loaded by the fork
servers through HAA_AGENT_MODULES."""

from __future__ import annotations

import itertools
import json
import os
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest
from helpers import run, until

from haa.cluster.hostprocs import MemberGroup, MemberHost
from haa.cluster.hostprocs import wait_for as wait
from haa.core.agents.agentroute import Router
from haa.core.agents.agentstep import Propose, Route
from haa.core.ddb import agenttable as at
from haa.core.ddb import ops as ddb
from haa.hostd.agentproc import AgentSupervisor, Envelope, Failed, InstanceSpec
from haa.pb import agenttx_pb2 as apb
from haa.sdk.base import new_agent_id

TESTS = Path(__file__).resolve().parent
TOKEN = "limits-test-token"
NAMES = ["h1", "h2"]
ARGS = ["--rebalance-period", "0", "--agent-hang-timeout", "2"]
MEMBERS = ("h1", "h2")


# ============================================================================ the table (sans-I/O)


def tx(**kw: object) -> bytes:
    t = apb.AgentTx()
    ((kind, body),) = kw.items()
    getattr(t, kind).CopyFrom(body)
    return at.encode(t)


def started(t: at.AgentTable, agent: str = "a", host: str = "h1") -> at.AgentRecord:
    """Create (once), allocate to `host` and commit its recovery: active on `host`."""
    if t.get(agent) is None:
        c = apb.AgentCreate(id=agent, type="counter", cost=0.1, recovery="backup", host=host)
        assert t.apply(tx(create=c), MEMBERS).ok
    assert t.apply(tx(move=apb.AgentMove(id=agent, host=host)), MEMBERS).ok
    assert t.apply(tx(recovered=apb.AgentRecovered(id=agent, host=host)), MEMBERS).ok
    r = t.get(agent)
    assert r is not None and r.status == at.ACTIVE
    return r


def fail(t: at.AgentTable, agent: str = "a", early: bool = True, reason: str = "spawn failed: boom",
         host: str = "h1", epoch: int | None = None) -> at.AgentApplied:
    r = t.get(agent)
    assert r is not None
    f = apb.AgentFailed(id=agent, host=host, epoch=r.epoch if epoch is None else epoch, reason=reason, early=early)
    return t.apply(tx(failed=f), MEMBERS)


def test_consecutive_early_failures_end_failed_with_the_reason() -> None:
    t = at.AgentTable()
    for n in range(1, at.MAX_START_FAILURES):
        started(t)
        assert fail(t).ok
        r = t.get("a")
        assert (r.status, r.failures, r.fail_reason) == (at.CRASHED, n, "spawn failed: boom")
    started(t)
    assert fail(t, reason="exited code 1 (agent error: on_start raised)").ok
    r = t.get("a")
    assert (r.status, r.failures) == (at.FAILED, at.MAX_START_FAILURES)
    assert r.fail_reason == "exited code 1 (agent error: on_start raised)"
    # a failed agent is not recovered, by anybody
    assert not t.apply(tx(recovered=apb.AgentRecovered(id="a", host="h1")), MEMBERS).ok
    assert not t.apply(tx(recovered=apb.AgentRecovered(id="a", host="h2")), MEMBERS).ok
    # an operator move retries it: crashed again, from a clean count, allocated where asked
    assert t.apply(tx(move=apb.AgentMove(id="a", host="h2")), MEMBERS).ok
    r = t.get("a")
    assert (r.status, r.failures, r.alloc) == (at.CRASHED, 0, "h2")
    assert t.apply(tx(recovered=apb.AgentRecovered(id="a", host="h2")), MEMBERS).ok
    assert t.invalid_values() == []


def test_a_failure_after_the_start_resets_the_count_and_so_does_a_transfer() -> None:
    t = at.AgentTable()
    for _ in range(3):
        started(t)
        fail(t)
    assert t.get("a").failures == 3
    started(t)
    assert fail(t, early=False, reason="killed by signal 9").ok
    r = t.get("a")
    assert (r.status, r.failures, r.fail_reason) == (at.CRASHED, 0, "killed by signal 9")
    for _ in range(2):
        started(t)
        fail(t)
    r = started(t)
    assert r.failures == 2
    assert t.apply(tx(freeze=apb.AgentFreeze(id="a", host="h1", epoch=r.epoch)), MEMBERS).ok
    assert t.apply(tx(release=apb.AgentRelease(id="a", host="h1", epoch=r.epoch)), MEMBERS).ok
    assert t.get("a").failures == 0  # it ran until it froze: it was up


def test_pushes_to_a_frozen_agent_count_their_bytes_and_carry_at_most_what_its_queue_keeps() -> None:
    """The router holds messages for an agent that is not active while one push per agent is in OAC: their payload
    bytes are counted (`held_bytes`: a host admits a message for that route only while they are few,
    haa.hostd.budget), and one push carries at most MAX_QUEUE_BYTES of payload (a queue keeps no more; 512
    maximum-size messages used to make a 2 GiB transaction), one message whatever its size."""
    t = at.AgentTable()
    c = apb.AgentCreate(id="a", type="counter", cost=0.1, recovery="backup", host="h1")
    assert t.apply(tx(create=c), MEMBERS).ok  # new: its messages go to queue2
    view = SimpleNamespace(table=t, name="h1")
    r = Router(view, {}, 512, Counter())  # type: ignore[arg-type]
    big = 3 * 1024 * 1024
    for i in range(3):
        assert r.route(apb.RoutedMsg(dst="a", payload=bytes([i]) * big)) == []
    assert r.held_bytes == 3 * big
    pushes = []
    while r.held_bytes:
        (p,) = r.flush()
        assert isinstance(p, Propose) and p.kind == "push"
        assert len(p.tx.push.msgs) == 1  # two would be over MAX_QUEUE_BYTES
        assert r.flush() == []  # one push per agent in OAC at a time
        pushes.append(p.tx.push.msgs[0].payload[0])
        assert r.push_done(p.epoch, True, True) == []
    assert pushes == [0, 1, 2]
    for _ in range(600):
        r.route(apb.RoutedMsg(dst="a", payload=b"x"))
    (p,) = r.flush()
    assert len(p.tx.push.msgs) == 512 and r.held_bytes == 600
    assert r.push_done(p.epoch, False, True) == [Route(tuple(p.tx.push.msgs))]  # aborted: routed again
    assert r.held_bytes == 88


def test_hostile_failed_transactions_are_refused_or_bounded_identically() -> None:
    """An AgentFailed from a buggy or hostile peer: wrong host, stale epoch, unknown agent, a huge reason, a
    failed agent reported again. Applying stays total, two replicas stay equal, the table stays in bounds."""
    a, b = at.AgentTable(), at.AgentTable()
    hostile = [
        apb.AgentFailed(id="a", host="h2", epoch=1, reason="not the owner", early=True),
        apb.AgentFailed(id="a", host="h1", epoch=99, reason="stale", early=True),
        apb.AgentFailed(id="nope", host="h1", epoch=1, reason="unknown", early=True),
        apb.AgentFailed(id="a", host="h1", epoch=1, reason="\n\x00" + "r" * 1_000_000, early=True),
        apb.AgentFailed(id="", host="", epoch=2**64 - 1, reason="", early=True),
    ]
    for t in (a, b):
        started(t)
        results = [t.apply(tx(failed=f), MEMBERS) for f in hostile]
        assert [r.ok for r in results] == [False, False, False, True, False]
        r = t.get("a")
        assert r.status == at.CRASHED and r.failures == 1
        assert 0 < len(r.fail_reason) <= at.MAX_FAIL_REASON and "\n" not in r.fail_reason
        for _ in range(at.MAX_START_FAILURES + 2):  # more early failures than it takes: still bounded
            if t.get("a").status == at.CRASHED:
                started(t)
            fail(t)
        assert t.get("a").status == at.FAILED and t.get("a").failures == at.MAX_START_FAILURES
        assert not fail(t, epoch=t.get("a").epoch).ok  # a failed agent has no owner: refused
        assert t.invalid_values() == []
    assert a.content_hash() == b.content_hash()
    c = at.AgentTable.restore(a.snapshot())
    assert c.content_hash() == a.content_hash()
    assert (c.get("a").status, c.get("a").failures, c.get("a").fail_reason) == (
        at.FAILED, at.MAX_START_FAILURES, a.get("a").fail_reason)


# ============================================================================ the supervisor: CPU limit


@pytest.fixture
def agent_modules(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fork servers started from here load tests/limitagents.py."""
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    monkeypatch.setenv("HAA_AGENT_MODULES", "limitagents")


def test_an_agent_over_its_cpu_limit_is_killed_with_the_reason(agent_modules: None) -> None:
    """limits-spin declares CPU_LIMIT 0.1: spinning (while it still heartbeats) it is killed once its share over
    the window (2 s here, 10 s by default) exceeds it; an idle agent of the same type is left alone."""

    async def main() -> None:
        events: list[object] = []
        sup = AgentSupervisor("h1", events.append, heartbeat_period=0.2, hang_timeout=3.0, cpu_window=0.5,
                              cpu_limit_window=2.0)
        await sup.start()
        try:
            spin_info = sup.imported_type("limits-spin")  # HAA_AGENT_MODULES: imported at the fork server's start
            assert spin_info is not None and spin_info.cpu_limit == pytest.approx(0.1)
            counter = await sup.type_info("counter")
            assert counter is not None and counter.has_config and not spin_info.has_config
            spin, idle = (InstanceSpec(new_agent_id(), n, "limits-spin", b"", 1) for n in ("A1", "A2"))
            for spec in (spin, idle):
                await sup.spawn(spec)
                sup.start_fresh(spec.agent_id)
            sup.deliver(spin.agent_id, Envelope("", spin.agent_id, b"spin", conv=1))
            await until(lambda: any(isinstance(e, Failed) for e in events), 30, "the spinning agent to be stopped",
                        interval=0.05)
            failed = [e for e in events if isinstance(e, Failed)]
            assert [e.agent_id for e in failed] == [spin.agent_id]
            assert failed[0].reason.startswith("over its CPU limit of 0.1 cores"), failed[0].reason
            assert sup.state(idle.agent_id) == "running" and sup.over_limit == 1
        finally:
            await sup.close()

    run(main(), 60)


# ============================================================================ real hosts


@pytest.fixture(scope="module")
def hosts(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, MemberHost]]:
    mp = pytest.MonkeyPatch()
    path = os.environ.get("PYTHONPATH", "")
    mp.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    mp.setenv("HAA_AGENT_MODULES", "limitagents")
    root: Path = tmp_path_factory.mktemp("limits")
    group = MemberGroup(root, NAMES, core=NAMES, token=TOKEN, args=ARGS)
    hs = group.hosts
    try:
        group.start()
        wait(lambda: all(len(h.status().members) == 2 for h in hs.values()), 40, "a group of 2")
        wait(lambda: "limits-startfail" in hs["h1"].client.agent_list().agent_types, 20, "the test agent types")
        yield hs
    finally:
        group.close()
        mp.undo()


def agents(hs: dict[str, MemberHost]) -> dict[str, object]:
    return {a.id: a for a in hs["h1"].client.agent_list().agents}


def timeline(hs: dict[str, MemberHost], agent_id: str) -> list[tuple[float, str, str, str]]:
    """(time, event, host, detail) of one agent from every host's kept timeline, in time order."""
    out = []
    for h in hs.values():
        stream = h.client.agent_events(history=True, timeout=1.5)
        try:
            for e in stream:
                if e.agent == agent_id:
                    out.append((e.time, e.event, e.host, e.detail))
        except Exception:  # the stream ends at its deadline
            pass
    return sorted(out)


def warnings(hs: dict[str, MemberHost], event: str, agent_id: str, since: float) -> int:
    """Warning lines `event` about `agent_id` in every host's log (the timeline's info lines not counted)."""
    n = 0
    for h in hs.values():
        for e in h.events(since, {event}):
            if e.get("level") == "warning" and e.get("fields", {}).get("agent") == agent_id:
                n += 1
    return n


def test_invalid_configs_are_refused_before_anything_commits(hosts: dict[str, MemberHost]) -> None:
    c = hosts["h2"].client
    before = set(agents(hosts))
    r = c.agent_spawn("counter", b'{"period": "x"}')
    assert not r.ok and not r.id, r
    assert r.reason == "counter: config.period: Input should be a valid number (got 'x')", r.reason
    for config, why in [
        (b'{"period": 0}', "config.period: Input should be greater than or equal to 0.001"),
        (b'{"perod": 1}', "config.perod: Extra inputs are not permitted"),
        (b"[1, 2]", "config: Input should be an object"),
        (b"{bad", "config: Invalid JSON"),
        # larger than a fork-server packet: the config travels in a memfd
        (json.dumps({"peer": "p" * (at.MAX_CONFIG - 20)}).encode(), "config.peer: String should have at most 256"),
    ]:
        r = c.agent_spawn("counter", config)
        assert not r.ok and why in r.reason, (config[:40], r.reason)
    # an agent's spawn_child is checked the same way: the requesting agent gets the reason
    probe = c.agent_spawn("probe", b'{"record": false}')
    assert probe.ok, probe
    wait(lambda: agents(hosts)[probe.id].status == "active", 20, "the probe active")
    cmd = {"op": "spawn_child", "type": "counter", "config": {"period": "x"}}
    rep = c.agent_request(probe.id, json.dumps(cmd).encode(), timeout=10)
    assert not rep.ok and "config.period: Input should be a valid number" in rep.error, rep
    time.sleep(0.5)  # a quiet period: a spawn committed by mistake would show now
    assert set(agents(hosts)) == before | {probe.id}  # nothing else was committed
    assert c.agent_remove(probe.id).ok


def test_an_agent_that_cannot_start_backs_off_ends_failed_and_a_move_retries_it(
        hosts: dict[str, MemberHost]) -> None:
    c = hosts["h1"].client
    t0 = time.time()
    r = c.agent_spawn("limits-startfail")
    assert r.ok, r
    wait(lambda: agents(hosts)[r.id].status == "failed", 45, "the agent failed")
    a = agents(hosts)[r.id]
    assert a.failures == at.MAX_START_FAILURES and "this agent cannot start" in a.fail_reason, a
    time.sleep(1.0)  # failed is terminal: nobody starts it again
    tl = timeline(hosts, r.id)
    starts = [t for t, ev, _h, _d in tl if ev in ("spawning", "recovering")]
    assert len(starts) == at.MAX_START_FAILURES, tl
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    # backoff 0.5, 1, 2, 4 s (plus each start's own time): the spacing grows
    assert gaps[2] > gaps[0] and gaps[3] > gaps[1] and gaps[3] >= 3.5, gaps
    assert any(ev == "failed" and "this agent cannot start" in d for _t, ev, _h, d in tl), tl
    # the host logs one failure per try, not a storm (the defect: 872 warnings in 10 s)
    assert warnings(hosts, "agent_failed", r.id, t0) <= at.MAX_START_FAILURES
    assert warnings(hosts, "agent_spawn_failed", r.id, t0) <= at.MAX_START_FAILURES
    # an operator move retries it, from a clean count
    assert c.agent_move(r.id, "h2").ok
    wait(lambda: len([1 for _t, ev, _h, _d in timeline(hosts, r.id) if ev == "recovering"]) >= len(starts), 15,
         "a new start after the move")
    assert c.agent_remove(r.id).ok


def test_an_agent_over_its_memory_limit_is_killed_and_recovered_while_writes_commit(
        hosts: dict[str, MemberHost]) -> None:
    c = hosts["h1"].client
    r = c.agent_spawn("limits-greedy")
    assert r.ok, r
    wait(lambda: (a := agents(hosts)[r.id]).status == "active" and a.life == 1, 20, "the greedy agent active")
    rep = c.agent_request(r.id, b"grow", timeout=10)
    assert rep.ok and rep.payload == b"growing", rep
    slowest = 0.0
    end = time.monotonic() + 30
    i = 0
    while True:
        t = time.monotonic()
        w = c.ddb_write([ddb.put(f"limits/{i}", "blob", b"v")], timeout=5)
        slowest = max(slowest, time.monotonic() - t)
        assert w.committed, w
        i += 1
        a = agents(hosts)[r.id]
        if a.status == "active" and a.life == 2:
            break
        assert time.monotonic() < end, f"the greedy agent was not recovered: {a}"
        time.sleep(0.05)
    assert slowest < 1.0, f"a DDB write took {slowest:.2f} s while the agent was stopped"
    tl = timeline(hosts, r.id)
    assert any(ev == "crashed" and "over its memory limit of 96 MiB" in d for _t, ev, _h, d in tl), tl
    assert any(ev == "recovered" for _t, ev, _h, _d in tl), tl
    assert c.agent_remove(r.id).ok


def test_a_ddb_write_from_a_stale_instance_is_fenced() -> None:
    """Two instances' outputs: a DDB write an agent instance asks for is taken only while
    the table gives this host the agent at that instance's epoch; an instance displaced by a newer one (another
    host recovered the agent) gets an error instead."""
    from types import SimpleNamespace

    from haa.core.ddb import agenttable as at
    from haa.hostd.agentdriver import AgentDriver
    from haa.pb import agenttx_pb2 as apb

    table = at.AgentTable()
    c = apb.AgentCreate(id="a", type="counter", cost=0.1, transfer_penalty=0.1, recovery="backup", host="h1")
    for kind, body in (("create", c), ("move", apb.AgentMove(id="a", host="h1")),
                       ("recovered", apb.AgentRecovered(id="a", host="h1"))):
        tx = apb.AgentTx()
        getattr(tx, kind).CopyFrom(body)
        assert table.apply(tx.SerializeToString(), ("h1", "h2")).ok
    drv = AgentDriver.__new__(AgentDriver)
    drv.host = SimpleNamespace(name="h1", agent_table=lambda: table)  # type: ignore[assignment]
    drv.epochs = {"a": 1}
    assert drv._fenced("a") == ""
    drv.epochs = {"a": 0}  # an older instance of a, still running here
    assert "stale instance" in drv._fenced("a")
    drv.host = SimpleNamespace(name="h2", agent_table=lambda: table)  # type: ignore[assignment]
    drv.epochs = {"a": 1}  # h2 runs an instance the table does not give it
    assert "stale instance" in drv._fenced("a")
    assert "stale instance" in drv._fenced("unknown")
