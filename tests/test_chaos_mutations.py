"""Every chaos check can fail on real hosts: one short local chaos run per mutation of
haa.lab.chaos.mutations — every haa-hostd of the run a deliberately broken variant — must fail exactly the check
that mutation targets and pass the others. Plans of 3 hosts and 3-16 s; the settle wait is cut short where
the broken group cannot settle (a diverged replica, an agent never recovered)."""

from __future__ import annotations

from pathlib import Path

import pytest

from haa.lab.chaos.mutations import MUTATIONS
from haa.lab.chaos.plan import PlanError, parse_plan
from haa.lab.chaos.run import run_local

WRITES = {"hosts": 3, "workload": "ddb-writes", "agents": 3, "period_s": 0.1}
PLANS = {
    "ack-before-commit": {**WRITES, "duration_s": 4, "settle_s": 20, "faults": []},
    "diverge-replica": {**WRITES, "agents": 1, "duration_s": 3, "settle_s": 3, "faults": []},
    # a killed writer's held write (5 s) lands after its successor's first writes (recovery takes ~1 s)
    "late-commit": {**WRITES, "period_s": 0.2, "duration_s": 16, "settle_s": 20,
                    "faults": [{"every_s": 4, "action": "kill", "target": "random-agent"}]},
    "drop-message": {"hosts": 3, "workload": "counters", "agents": 2, "period_s": 0.05, "duration_s": 4,
                     "settle_s": 20, "faults": []},
    "no-recovery": {**WRITES, "agents": 2, "duration_s": 5, "settle_s": 3,
                    "faults": [{"at_s": 1, "action": "kill", "target": "agent A1"}]},
}


def test_every_mutation_has_a_plan() -> None:
    assert set(PLANS) == set(MUTATIONS)


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_the_mutated_hosts_fail_exactly_their_check(name: str, tmp_path: Path) -> None:
    plan = parse_plan({"name": f"mutation-{name}", "seed": 3, "mutation": name, **PLANS[name]})
    res = run_local(plan, tmp_path / "run")
    assert not res.error, res.error
    failed = {k for k, c in res.checks.items() if not c.passed}
    detail = {k: c.detail for k, c in res.checks.items()}
    assert failed == {MUTATIONS[name]}, detail
    assert not res.passed


def test_a_mutation_is_refused_inside_a_mission_and_unknown_names_are_errors() -> None:
    with pytest.raises(PlanError, match="unknown mutation 'nope'"):
        parse_plan({"name": "x", "duration_s": 5, "mutation": "nope"})


def test_a_pair_that_never_crashed_may_lose_nothing_at_all() -> None:
    """Per-sender order across transfers: `lost_after_recovery` is allowed only where the counter
    or its peer crashed (a recovery from an older backup, Alg. 8)."""
    from haa.lab.chaos.checks import check_counter_streams

    def reps(lost_after_recovery: int) -> dict:
        stats = {"A1": {"id": "a1", "peer": "b1", "received": 50, "lost_after_recovery": lost_after_recovery,
                        "thaws": 2},
                 "A1.1": {"id": "b1", "peer": "a1", "received": 48, "thaws": 1}}
        return {"h1": {"status": {"member": True},
                       "objects": {f"demo/{n}": {"type": "json", "value": v} for n, v in stats.items()}}}

    crash = {"h1": [{"ts": 1.0, "event": "agent_crashed", "fields": {"agent": "b1", "name": "A1.1", "detail": ""}}]}
    ok = check_counter_streams(reps(0), {})
    assert ok.passed and "2 counters whose pair never crashed" in ok.detail and "across 3 transfers" in ok.detail
    bad = check_counter_streams(reps(3), {})
    assert not bad.passed and "lost_after_recovery 3 though neither it nor its peer crashed" in bad.detail
    assert check_counter_streams(reps(3), crash).passed  # its peer was recovered: allowed


def test_a_run_never_stops_a_cluster_it_did_not_start(tmp_path: Path) -> None:
    """`chaos run --compose` while the compose project already runs: refused with one line, and the running
    cluster is left alone (run_on stops only what its start brought up)."""
    from haa.cluster.backend import ClusterError
    from haa.lab.chaos.run import run_on

    calls: list[str] = []

    class Running:
        backend = None

        def problems(self, plan):
            return []

        def start(self, plan, progress):
            calls.append("start")
            raise ClusterError("the compose cluster is running (h1, h2, h3): a chaos run brings up its own")

        def stop(self, out, progress):
            calls.append("stop")

    plan = parse_plan({"name": "x", "duration_s": 5, "workload": "ddb-writes"})
    res = run_on(Running(), plan, tmp_path / "run")  # type: ignore[arg-type]
    assert calls == ["start"] and "brings up its own" in res.error and not res.passed
