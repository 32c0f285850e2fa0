"""A real control-system agent on virtual time: ExecutiveMission in the deterministic simulator.

The agent's own code runs unchanged on `haa.sdk.sched.VirtualScheduler`; its DDB reads and writes, spawns,
backups and messages go through the simulated hosts (haa.lab.dsim.vagent), which crash, pause, kill, hang and move
it. Also: the virtual scheduler alone, and the event heap every simulator shares (haa.lab.dsim.scheduler).
"""

from __future__ import annotations

import json

import pytest

from haa.agents.executive_mission import ExecutiveMission
from haa.lab.dsim import vagent
from haa.lab.dsim.scheduler import EventHeap
from haa.lab.dsim.sweep import run_seed
from haa.sdk.sched import VirtualScheduler

# ------------------------------------------------------------------------------------------------ the event heap


def test_event_heap_orders_by_time_then_push_order():
    q: EventHeap[str] = EventHeap()
    q.push(2.0, "late")
    q.push(1.0, "first at 1")
    gen = q.new_id()  # a number from the same counter: later pushes sort after it
    q.push(1.0, "second at 1")
    q.push(0.5, "early")
    assert gen == 3 and len(q) == 4 and q.next_time() == 0.5
    assert [q.pop()[2] for _ in range(4)] == ["early", "first at 1", "second at 1", "late"]
    assert not q and q.next_time() == float("inf")


# ------------------------------------------------------------------------------------------------ virtual time


class Loop:
    """A minimal simulator: one EventHeap and a clock, as SimCluster runs the agents' events."""

    def __init__(self) -> None:
        self.q: EventHeap = EventHeap()
        self.now = 0.0
        self.sched = VirtualScheduler(lambda: self.now, lambda t, fn: self.q.push(t, fn))

    def run(self, until: float = 1e9) -> None:
        while self.q and self.q.next_time() <= until:
            self.now, _seq, fn = self.q.pop()
            fn()


def test_virtual_timers_futures_timeouts_and_queue():
    loop = Loop()
    s = loop.sched
    seen: list[tuple[float, str]] = []
    s.call_at(2.0, lambda: seen.append((loop.now, "b")))
    s.call_at(1.0, lambda: seen.append((loop.now, "a")))
    s.call_at(1.5, lambda: seen.append((loop.now, "cancelled"))).cancel()
    fut = s.create_future()
    slow = s.create_future()
    box = s.queue()

    async def worker() -> str:
        await s.sleep(0.25)
        seen.append((loop.now, "slept"))
        got = await s.wait_for(fut, 10.0)  # resolved at t=3
        try:
            await s.wait_for(slow, 0.5)  # never resolved: times out after 0.5 virtual seconds
        except TimeoutError:
            seen.append((loop.now, "timeout"))
        assert slow.cancelled()  # as asyncio.wait_for: the awaited future is cancelled
        item = await box.get()  # put at t=5
        return f"{got}/{item}"

    task = s.spawn(worker())
    s.call_at(3.0, lambda: fut.set_result("answer"))
    s.call_at(5.0, lambda: box.put_nowait("mail"))
    loop.run()
    assert seen == [(0.25, "slept"), (1.0, "a"), (2.0, "b"), (3.5, "timeout")]
    assert task.result.result() == "answer/mail"
    assert s.clock.now() == loop.now and s.clock_for(object()) is s.clock  # type: ignore[arg-type]


def test_a_task_that_awaits_asyncio_fails_and_a_closed_scheduler_runs_nothing():
    loop = Loop()
    s = loop.sched

    class Socket:  # what an I/O library's awaitable hands its event loop
        def __await__(self):
            yield "wait for readable"

    async def raw() -> None:
        await Socket()  # not the agent's scheduler: cannot run on virtual time

    task = s.spawn(raw())
    loop.run()
    with pytest.raises(RuntimeError, match="outside the agent's scheduler"):
        task.result.result()
    ran: list[int] = []
    s.call_at(1.0, lambda: ran.append(1))
    s.close()
    loop.run()
    assert ran == []


# ------------------------------------------------------------------------------------------------ ExecutiveMission


def _exec_starts(sim: vagent.RealAgentSim) -> list[tuple[str, bytes | None]]:
    return [(mode, state) for a, _e, mode, state in sim.ah.recovered_starts if a == sim.ah.ids[0]]


def _exec_thaws(sim: vagent.RealAgentSim) -> int:
    """Transfers of the executive (the only agent without a parent: its children are named A<n>.<k>)."""
    return sum(1 for _t, _h, name, ev in sim.ah.timeline if ev == "thawed" and "." not in name)


def test_executive_mission_state_survives_crashes_kills_and_moves():
    """The recovery mix (host crashes, agent kills and hangs, moves, pauses, false suspicions) on 5 hosts: the
    executive's mission survives — resumed from its backup or from mission/status, never started twice, its
    children not spawned again, the mission stopped by its time limit — and the agent layer's properties hold."""
    recovered_from_backup = recovered_without = thaws = dups = 0
    for seed in (0, 1, 2, 3, 4, 5, 12):  # 12: a crash before the executive's first backup
        sim, vs = vagent.run_real(seed, 5, "recovery")
        assert sim.quiescent, f"seed {seed}: did not get quiet"
        assert vs == [], f"seed {seed}: {[str(v) for v in vs]}"
        starts = _exec_starts(sim)
        recovered_from_backup += sum(1 for mode, st in starts if mode == "recover" and st is not None)
        recovered_without += sum(1 for mode, st in starts if mode == "recover" and st is None)
        thaws += _exec_thaws(sim)
        dups += vagent.duplicate_children(sim)
        st = json.loads(sim._members()[0].core.m.state.ddb.get("mission/status").data)
        assert st["state"] == "stopped" and st["reason"] == "time limit"
    # the faults did reach the agent: recoveries from a backup and without one, and transfers
    assert recovered_from_backup >= 5 and recovered_without >= 1 and thaws >= 2, (
        recovered_from_backup, recovered_without, thaws)
    assert dups <= 3  # the window ExecutiveMission documents (vagent: EX-Once)


def test_executive_transfers_keep_its_state():
    """The transfer mix (moves under pauses and false suspicions, no crash): every thaw continues the mission."""
    thaws = 0
    for seed in range(4):
        sim, vs = vagent.run_real(seed, 5, "transfer")
        assert vs == [] and sim.quiescent, f"seed {seed}: {[str(v) for v in vs]}"
        assert [m for m, _s in _exec_starts(sim)] == ["fresh"]  # moved, never restarted
        thaws += _exec_thaws(sim)
    assert thaws >= 10


def test_same_seed_same_trace():
    """A seed reproduces its run (the trace hash covers every frame the executive's hosts received). Across
    PYTHONHASHSEEDs too: `hashseed.trace_hashes([("executive", 5, 5)], ["0", "7"])` gives one output (not run
    here: two fresh interpreters importing the agent stack take longer than this file's budget)."""
    a, b = run_seed("executive", 5, 5), run_seed("executive", 5, 5)
    assert a.trace_hash == b.trace_hash and a.events == b.events and a.stats == b.stats
    assert run_seed("executive", 6, 5).trace_hash != a.trace_hash


def test_the_checks_catch_an_executive_that_forgets_its_mission(monkeypatch):
    """Break the executive on purpose: a recovered instance drops its backup and begins the mission afresh.
    EX-Resume (another start time) and EX-Once (a second "Mission started", children spawned again) fire."""
    monkeypatch.setattr(ExecutiveMission, "recover", lambda self, backup: None)

    async def begin_again(self: ExecutiveMission) -> str:
        return "start"

    monkeypatch.setattr(ExecutiveMission, "_resume_from_status", begin_again)
    props: set[str] = set()
    for seed in (0, 1, 2):
        _sim, vs = vagent.run_real(seed, 5, "recovery")
        props |= {v.prop for v in vs}
    assert {"EX-Resume", "EX-Once"} <= props


def test_a_write_aborted_under_a_suspicion_waits_for_the_group_instead_of_failing_the_agent():
    """Seed 1263 (7 hosts): a delay spike h2->h1 made h1 suspect h2 while h3 still trusted it, so h1's removal
    of h2 was voted down and every OAC transaction h1 proposed aborted until the spike ended (AC-Non-Triviality).
    The executive's `spawn_child` was re-proposed at once after each abort: 50 attempts in 0.8 s, then
    "gave up after 50 attempts (aborted)", and `on_start` failed (EX-Finish). A write aborted while its host
    suspects a member is now held, uncounted, until the suspicion ends or the view changes
    (haa.core.membership.groupwrites)."""
    r = run_seed("executive", 1263, 7)
    assert not r.violations, r.violations


def test_an_executive_whose_start_record_loses_resumes_the_recorded_start():
    """The path of `ExecutiveMission._record_start` a compare-and-set exists for, driven frame by frame: a
    recovered instance without a backup reads no `mission/status`, begins the mission, and its create of the
    status fails — its predecessor's start, still on its way through the group when it read, committed first.
    It resumes from the recorded start (no "Mission started"), and its next status carries that start time."""
    from haa.pb import agent_pb2 as pb
    from haa.sdk import registry
    from haa.sdk.context import AgentContext

    loop = Loop()
    frames: list[pb.AgentToHost] = []
    init = pb.HostToAgent.Init(agent_id="e1", name="A1", type_name=ExecutiveMission.TYPE,
                               config=vagent.mission_config(7), epoch=2, host="h1")
    ctx = AgentContext(init, registry.get(ExecutiveMission.TYPE), frames.append, scheduler=loop.sched)
    loop.sched.spawn(ctx.run())
    ctx.feed(pb.HostToAgent(recover=pb.HostToAgent.Recover(has_backup=False)))
    ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="recover")))
    earlier = {"state": "running", "t": 1.2, "explored": 0.0, "reason": "", "started_t": 1.0, "finished_t": None,
               "children": {}}
    store: dict[str, bytes] = {}
    writes: list[list] = []
    for _ in range(40):  # the host's side: answer what the agent asked, until it writes its status again
        loop.run(until=loop.now)  # what is due now (not the calls' timeouts)
        todo, frames[:] = list(frames), []
        for f in todo:
            kind = f.WhichOneof("msg")
            if kind == "ddb_get":
                value = store.get(f.ddb_get.key)
                ans = pb.HostToAgent.Answer(req_id=f.ddb_get.req_id, ok=True, missing=value is None, value=value or b"")
            elif kind == "ddb_write":
                ops = list(f.ddb_write.ops)
                writes.append(ops)
                if any(op.WhichOneof("op") == "cas" for op in ops):  # the predecessor's start committed first
                    store["mission/status"] = json.dumps(earlier).encode()
                    errors = ["atomic batch aborted: op 1 failed", "version mismatch: expected absent, found 3"]
                else:
                    errors = [""] * len(ops)
                ans = pb.HostToAgent.Answer(req_id=f.ddb_write.req_id, ok=True, op_errors=errors)
            elif kind == "spawn_child":
                ans = pb.HostToAgent.Answer(req_id=f.spawn_child.req_id, ok=True, value=b"child")
            else:
                continue
            ctx.feed(pb.HostToAgent(answer=ans))
        puts = [json.loads(op.put.value) for ops in writes for op in ops
                if op.WhichOneof("op") == "put" and op.put.key == "mission/status"]
        if puts:
            break
    assert [op.WhichOneof("op") for op in writes[0]] == ["put", "cas"] and writes[0][1].cas.expected_version == 0
    assert puts and puts[0]["started_t"] == 1.0, puts
    lines = [json.loads(i)["text"] for ops in writes for op in ops if op.WhichOneof("op") == "log_append"
             for i in op.log_append.items]
    assert not any(t.startswith("Mission started") for t in lines), lines


def test_a_recovered_executive_resumes_a_start_that_committed_after_it_looked():
    """Seed 569 (7 hosts): the first instance wrote `mission/params`, then its first `mission/status`, which
    was still on its way through the group (it took 0.9 s to commit) when the instance was killed; the recovered one
    read no status on its host's replica and began the mission again, and the first start committed 14 ms
    before its own: `mission/status` carried two start times (EX-Resume). The params and the first status
    are now one atomic batch whose status op only creates the key, so the start is recorded once: a recovered
    instance reads it or, when its own create loses to a start still on its way, resumes from that one (the
    test above). In this schedule the one batch commits before the kill and the recovered instance reads it."""
    r = run_seed("executive", 569, 7)
    assert not r.violations, r.violations


def test_a_start_that_never_committed_is_not_the_missions_start():
    """Seed 49 (7 hosts, a group of 3): the first instance proposed the mission's start on h1 during a delay
    spike on h1's links; h2 and h3 suspected h1 and removed it, the transaction aborted and h1 came back as a
    new incarnation: the start never committed. The recovered instance found no status and began the mission —
    the only start the DDB ever held, the transcript's only "Mission started". EX-Resume took the mission's
    start from the first status *proposed* (and only from puts: the create-only start, a compare-and-set, went
    unseen); counting the start there, it reported a second start here (as it did in seeds 494, 769, 822, 1102,
    1422 before the start became one batch). It takes statuses, the start included, as the DDB applies them:
    a write that never committed wrote nothing (AC-Uniform-Validity, thesis L545)."""
    r = run_seed("executive", 49, 7)
    assert not r.violations, r.violations
