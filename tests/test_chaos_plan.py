"""haa.lab.chaos without a cluster: the plan schema (one error line naming the field), the refusal of a local
partition, the injector's schedule against a fake backend (at_s, every_s, pauses ended, life_s draws per
agent instance, the live-majority guard, the seed), and the CHAOS_HANG hook of AgentBase in-process."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from haa.cluster.agents import AgentRow
from haa.cluster.backend import ALIVE, KILLED, PAUSED, HostInfo
from haa.lab.chaos import inject
from haa.lab.chaos.inject import Injector, local_problems
from haa.lab.chaos.plan import PlanError, load_plan, parse_plan
from haa.pb import agent_pb2 as pb
from haa.sdk.base import CHAOS_HANG, AgentBase, AgentContext, new_agent_id
from haactl.main import app

ISSUE_PLAN = """
name: r1-extreme
seed: 7
duration_s: 120
faults:
  - {at_s: 20, action: kill, target: host h3}
  - {at_s: 30, action: pause, target: host h2, for_s: 5}
  - {at_s: 40, action: restart, target: host h3}
  - {life_s: [30, 90], action: hang, target: agents, hang_s: 30}
  - {every_s: 25, action: kill, target: random-agent}
  - {at_s: 60, action: partition, target: [h1, h2], for_s: 10}
"""


def plan(**kw):
    base = {"name": "t", "duration_s": 30, "faults": []}
    base.update(kw)
    return parse_plan(base, "plan p.yaml")


def test_the_issue_plan_validates_as_written():
    p = parse_plan(yaml.safe_load(ISSUE_PLAN))
    assert [f.action for f in p.faults] == ["kill", "pause", "restart", "hang", "kill", "partition"]
    assert p.faults[0].target.kind == "host" and p.faults[0].target.value == "h3"
    assert p.faults[3].target.kind == "agents" and p.faults[3].life_s == (30, 90)
    assert p.faults[4].target.kind == "random-agent" and p.faults[4].every_s == 25
    assert p.faults[5].target.hosts == ("h1", "h2")
    for t in ("random-host", "agent A1.2", "agent-type counter"):
        assert plan(faults=[{"at_s": 1, "action": "kill", "target": t}]).faults[0].target.text() == t


@pytest.mark.parametrize("fault, expect", [
    ({"at_s": 1, "action": "hang", "target": "agents"}, "faults[0]: hang needs hang_s"),
    ({"at_s": 1, "action": "kill", "target": "host h9"}, "faults[0].target: h9 is not a host of this plan"),
    ({"at_s": 1, "action": "explode", "target": "agents"}, "faults[0].action: Input should be"),
    ({"at_s": 1, "action": "kill", "target": "hots h1"}, "faults[0].target: unknown target 'hots h1'"),
    ({"at_s": 1, "action": "kill", "target": "host h1", "colour": 2}, "faults[0].colour: unknown key"),
    ({"at_s": 31, "action": "kill", "target": "host h1"}, "faults[0].at_s: 31 is not before duration_s 30"),
    ({"life_s": [5, 2], "action": "hang", "target": "agents", "hang_s": 1}, "faults[0].life_s: the window"),
    ({"action": "kill", "target": "host h1"}, "faults[0]: needs a schedule"),
    ({"at_s": 1, "action": "pause", "target": "agents", "for_s": 1}, "faults[0]: pause applies to hosts"),
    ({"at_s": 1, "action": "hang", "target": "host h1", "hang_s": 1}, "faults[0]: hang applies to agents"),
    ({"at_s": 1, "action": "pause", "target": "host h1"}, "faults[0]: pause needs for_s"),
    ({"at_s": 1, "action": "kill", "target": "host h1", "for_s": 2}, "faults[0]: for_s is for pause"),
    ({"at_s": 1, "action": "partition", "target": "host h1", "for_s": 2}, "partition takes a list of hosts"),
    ({"at_s": 1, "action": "kill", "target": ["h1"]}, "a list of hosts is a partition's target"),
    ({"life_s": [1, 2], "action": "kill", "target": "random-agent"}, "life_s draws a failure time per agent"),
    ({"life_s": [1, 2], "at_s": 1, "action": "kill", "target": "agents"}, "life_s is a schedule of its own"),
    ({"at_s": -1, "action": "kill", "target": "host h1"}, "faults[0].at_s: Input should be greater than or equal"),
])
def test_a_bad_fault_is_one_line_naming_the_field(fault, expect):
    with pytest.raises(PlanError) as e:
        plan(faults=[fault])
    text = str(e.value)
    assert "\n" not in text and text.startswith("plan p.yaml: ")
    assert expect in text, text


@pytest.mark.parametrize("data, expect", [
    ({"name": "t", "duration_s": 0}, "duration_s: Input should be greater than 0"),
    ({"name": "t", "duration_s": 5, "hosts": 2}, "hosts: Input should be greater than or equal to 3"),
    ({"name": "t", "duration_s": 5, "workload": "mission"}, "workload: Input should be 'ddb-writes' or 'counters'"),
    ({"name": "bad name", "duration_s": 5}, "name: String should match pattern"),
    ([1, 2], "the top level must be a mapping"),
])
def test_bad_plan_level_keys(data, expect):
    with pytest.raises(PlanError, match=None) as e:
        parse_plan(data, "plan p.yaml")
    assert expect in str(e.value) and "\n" not in str(e.value)


def test_load_plan_reports_broken_yaml_and_missing_files(tmp_path: Path):
    f = tmp_path / "p.yaml"
    f.write_text("name: x\nfaults: [\n")
    with pytest.raises(PlanError, match=r"chaos plan .*p.yaml: not valid YAML at line \d+"):
        load_plan(f)
    with pytest.raises(PlanError, match="no such file"):
        load_plan(tmp_path / "missing.yaml")


def test_partition_is_refused_on_the_local_cluster_before_anything_starts(tmp_path: Path):
    p = parse_plan(yaml.safe_load(ISSUE_PLAN))
    assert local_problems(p) == [
        "faults[5]: partition is not available on the local cluster (its hosts share loopback and there is no "
        "link to cut without root); run the plan with --compose, or remove this fault"]
    f = tmp_path / "p.yaml"
    f.write_text(ISSUE_PLAN)
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["chaos", "run", str(f), "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "partition is not available on the local cluster" in r.output
    assert not (out / "cluster").exists()  # nothing started


def test_cli_bad_plan_exits_2_with_one_line(tmp_path: Path):
    f = tmp_path / "p.yaml"
    f.write_text("name: x\nduration_s: 5\nfaults:\n - {at_s: 1, action: hang, target: agents}\n")
    r = CliRunner().invoke(app, ["chaos", "run", str(f), "--out", str(tmp_path / "run")])
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "faults[0]: hang needs hang_s" in lines[0]


# ------------------------------------------------------------------ the injector against a fake cluster

class FakeBackend:
    """Hosts and agents in memory; records what the injector does."""

    def __init__(self, n: int = 5) -> None:
        self.state = {f"h{i}": ALIVE for i in range(1, n + 1)}
        self.calls: list[tuple[str, str]] = []
        self.rows: list[AgentRow] = []

    def hosts(self):
        return [HostInfo(n, "127.0.0.1:1", s) for n, s in self.state.items()]

    def kill(self, name):
        self.calls.append(("kill", name))
        self.state[name] = KILLED

    def pause(self, name):
        self.calls.append(("pause", name))
        self.state[name] = PAUSED

    def resume(self, name):
        self.calls.append(("resume", name))
        self.state[name] = ALIVE

    def restart(self, name):
        self.calls.append(("restart", name))
        self.state[name] = ALIVE


def row(name: str, epoch: int = 1, host: str = "h1", state: str = "active") -> AgentRow:
    return AgentRow(name=name, id=f"id-{name}", type="chaos_writer", state=state, host=host, cpu=0, parent="",
                    parent_id="", epoch=epoch, backup=False, status=state, owner=host, alloc=host,
                    phases={host: state})


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


def injector(p, backend, monkeypatch, agent_calls=None):
    clk = Clock()
    inj = Injector(p, backend, clock=clk, sleep=clk.sleep)
    monkeypatch.setattr(inj, "agents", lambda fresh=False: backend.rows)

    def agent_fault(i, f, r):
        (agent_calls if agent_calls is not None else []).append((round(inj.now(), 1), f.action, r.name, r.epoch))
        inj._record(f.action, r.name, i, True, "", r.id, r.epoch)

    monkeypatch.setattr(inj, "_agent_fault", agent_fault)
    return inj


def test_host_faults_follow_the_plan_and_pauses_end(monkeypatch):
    p = plan(duration_s=20, faults=[
        {"at_s": 2, "action": "kill", "target": "host h3"},
        {"at_s": 5, "action": "pause", "target": "host h2", "for_s": 3},
        {"at_s": 10, "action": "restart", "target": "host h3"},
        {"at_s": 15, "action": "pause", "target": "host h4", "for_s": 30},  # still paused at the end
    ])
    b = FakeBackend()
    recs = injector(p, b, monkeypatch).run()
    assert b.calls == [("kill", "h3"), ("pause", "h2"), ("resume", "h2"), ("restart", "h3"), ("pause", "h4"),
                       ("resume", "h4")]
    assert [(r.action, r.target, r.ok) for r in recs][:4] == [
        ("kill", "h3", True), ("pause", "h2", True), ("resume", "h2", True), ("restart", "h3", True)]
    times = [r.t for r in recs]
    assert times[0] == pytest.approx(2, abs=0.25) and times[2] == pytest.approx(8, abs=0.25)
    assert all(s == ALIVE for s in b.state.values())


def test_a_host_fault_that_leaves_no_live_majority_is_skipped_with_the_reason(monkeypatch):
    p = plan(duration_s=10, hosts=4, faults=[
        {"at_s": 1, "action": "kill", "target": "host h1"},
        {"at_s": 2, "action": "kill", "target": "host h2"},  # 2 of 3 left: refused
        {"at_s": 3, "action": "pause", "target": "random-host", "for_s": 1},  # 2 live of 3: refused
    ])
    b = FakeBackend(4)
    recs = injector(p, b, monkeypatch).run()
    assert b.calls == [("kill", "h1")]
    assert [r.ok for r in recs] == [True, False, False]
    assert "skipped: would leave 2 live hosts of 2 in the group" in recs[1].detail
    assert "skipped: would leave 2 live hosts of 3 in the group" in recs[2].detail


def test_every_s_and_random_targets_are_reproducible_from_the_seed(monkeypatch):
    def once(seed):
        p = plan(duration_s=30, seed=seed, faults=[{"every_s": 5, "action": "kill", "target": "random-agent"}])
        b = FakeBackend()
        b.rows = [row(f"A{i}") for i in range(1, 8)]
        calls = []
        injector(p, b, monkeypatch, calls).run()
        return calls

    a = once(1)
    assert [c[0] for c in a] == pytest.approx([5, 10, 15, 20, 25], abs=0.25)
    assert a == once(1)
    assert [c[2] for c in a] != [c[2] for c in once(2)]


def test_life_s_draws_once_per_instance_and_again_after_recovery(monkeypatch):
    p = plan(duration_s=40, faults=[{"life_s": [3, 6], "action": "hang", "target": "agents", "hang_s": 2}])
    b = FakeBackend()
    b.rows = [row("A1"), row("A2")]
    calls: list = []
    inj = injector(p, b, monkeypatch, calls)
    monkeypatch.setattr(inject, "AGENT_POLL", 0.5)

    orig = inj._fire

    def fire(d):
        orig(d)
        if d.kind == "life":  # the hung instance is recovered with the next epoch
            b.rows = [row(r.name, r.epoch + 1) if r.id == d.target else r for r in b.rows]

    monkeypatch.setattr(inj, "_fire", fire)
    inj.run()
    by_agent: dict[str, list] = {}
    for t, action, name, epoch in calls:
        assert action == "hang"
        by_agent.setdefault(name, []).append((t, epoch))
    for name, hits in by_agent.items():
        epochs = [e for _, e in hits]
        assert epochs == list(range(1, len(epochs) + 1)), (name, hits)  # each instance hung once
        gaps = [b2 - b1 for (b1, _), (b2, _) in zip([(0.0, 0), *hits], hits, strict=False)]
        assert all(3 - 0.6 <= g <= 6 + 0.6 for g in gaps), (name, gaps)  # its own draw in the window
        assert len(hits) >= 5  # 40 s / at most ~6 s per life


# ------------------------------------------------------------------ the hang hook, in-process

class Echo(AgentBase):
    TYPE = "t-echo"

    async def on_request(self, src, payload):
        return b"echo:" + payload


def test_chaos_hang_blocks_the_agents_own_loop_then_fails():
    async def main():
        frames: list = []
        init = pb.HostToAgent.Init(agent_id=new_agent_id(), name="A1", type_name="t-echo", epoch=1, host="h1")
        ctx = AgentContext(init, Echo, frames.append)
        ctx.feed(pb.HostToAgent(start=pb.HostToAgent.Start()))
        ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="start")))
        # an agent's request with the same bytes is an ordinary request
        ctx.feed(pb.HostToAgent(deliver=pb.AgentMsg(src="some-agent", dst=init.agent_id, payload=CHAOS_HANG + b"5",
                                                    conv=7)))
        ctx.feed(pb.HostToAgent(deliver=pb.AgentMsg(src="@h1", dst=init.agent_id, payload=CHAOS_HANG + b"0.4",
                                                    conv=8)))
        ticks = 0

        async def ticker():
            nonlocal ticks
            while True:
                await asyncio.sleep(0.02)
                ticks += 1

        t = asyncio.create_task(ticker())
        t0 = time.monotonic()
        code = await asyncio.wait_for(ctx.run(), 10)
        took = time.monotonic() - t0
        t.cancel()
        return frames, code, took, ticks

    frames, code, took, ticks = asyncio.run(main())
    sent = [f.sent for f in frames if f.WhichOneof("msg") == "sent"]
    assert sent[0].conv == 7 and bytes(sent[0].payload).startswith(b"echo:")
    assert sent[1].conv == 8 and bytes(sent[1].payload) == b"hanging"
    assert code == 1 and took >= 0.4
    assert ticks <= 3  # the loop was blocked: another task could not run during the hang
    errors = [f.error.message for f in frames if f.WhichOneof("msg") == "error"]
    assert errors == ["chaos hang: blocked its event loop for 0.4 s"]


# ------------------------------------------------------------------ the counters workload's checks

def counters_run(tmp_path: Path, **changes) -> Path:
    """A run directory with two live replicas holding the same counter statistics (`changes` applied to A1's)."""
    import json

    stats = {"A1": {"received": 50, "lost": 0, "out_of_order": 0, "duplicate": 0, "stale": 0,
                    "lost_after_recovery": 3},
             "A1.1": {"received": 48, "lost": 0, "out_of_order": 0, "duplicate": 0, "stale": 0,
                      "lost_after_recovery": 0}}
    stats["A1"].update(changes)
    (tmp_path / "replicas").mkdir()
    (tmp_path / "hosts").mkdir()
    for h in ("h1", "h2"):
        rec = {"host": h, "status": {"member": True, "members": ["h1", "h2"], "view": 3, "ddb_hash": "ab"},
               "objects": {f"demo/{n}": {"type": "json", "value": s} for n, s in stats.items()}}
        (tmp_path / "replicas" / f"{h}.json").write_text(json.dumps(rec))
    return tmp_path


@pytest.mark.parametrize("changes, failing", [
    ({}, set()),
    ({"stale": 2}, {"single_instance"}),
    ({"lost": 1}, {"counter_streams"}),
    ({"out_of_order": 1}, {"counter_streams"}),
    ({"duplicate": 4}, {"counter_streams"}),
])
def test_counters_checks_fail_on_exactly_their_fault(tmp_path: Path, changes, failing):
    from haa.lab.chaos.checks import run_checks

    checks = run_checks(counters_run(tmp_path, **changes), "counters")
    assert set(checks) == {"replicas_agree", "single_instance", "counter_streams", "crashed_agents_recovered"}
    assert {k for k, c in checks.items() if not c.passed} == failing, checks


def test_crashes_logged_after_the_run_ended_are_not_the_runs() -> None:
    """`cluster down` stops the hosts after the replicas were read (t_end): an agent frozen and crashed
    then is not a crash of the run (it flaked test_chaos_run once); one before t_end still counts."""
    from haa.lab.chaos.checks import check_crashed_recovered

    def rec(ts: float, ev: str) -> dict:
        return {"ts": ts, "event": ev, "fields": {"agent": "a-1", "name": "A1", "detail": "x"}}

    logs = {"h1": [rec(10.0, "agent_thawed"), rec(31.7, "agent_crashed")]}
    assert not check_crashed_recovered(logs).passed
    assert check_crashed_recovered(logs, t_end=31.6).passed
    assert not check_crashed_recovered({"h1": [rec(20.0, "agent_crashed")]}, t_end=31.6).passed


def test_a_plan_without_duration_is_for_missions_only(tmp_path):
    """duration_s may be left out of a plan a mission names (it lasts until the mission ends); `chaos run`
    refuses such a plan before it starts anything."""
    from haa.lab.chaos.run import run_local

    plan = parse_plan({"name": "m", "faults": [{"life_s": [30, 90], "action": "hang", "target": "agents",
                                                "hang_s": 30}]}, "p.yaml")
    assert plan.duration_s is None
    with pytest.raises(PlanError, match="duration_s: needed by `haactl chaos run`"):
        run_local(plan, tmp_path / "run")
    assert not (tmp_path / "run").exists()
