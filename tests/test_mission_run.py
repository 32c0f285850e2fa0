"""The robot team on real processes: one short shared mission carries the checks — it completes
while SupervisorExplore and a path planner are killed and a host retires mid-mission; the results have every
key; the agents made no ground-truth or Detect call; readings were processed; nothing is left running."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_mission_runner import no_processes_left, our_processes

from haa.mission import load_mission, results
from haa.mission import runner as rn

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def ci_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    tmp = tmp_path_factory.mktemp("mission")
    r = rn.run_mission(load_mission(HERE / "missions" / "ci.yaml"), None, tmp / "out")
    no_processes_left(str(tmp))
    return r, tmp


def test_the_mission_completes_with_every_result_key(ci_run: tuple[dict, Path]) -> None:
    r, tmp = ci_run
    assert set(results.REQUIRED_KEYS) <= set(r)
    assert r["completed"] is True, (r["reason"], r.get("errors"))
    assert not r.get("errors"), r["errors"]
    assert 0 < r["coverage"] <= 1 and 0 < r["accuracy"] <= 1 and r["position_error_m"] is not None
    # the team's landmark map against the true landmarks (Table 7.1-1's landmark rows)
    assert 0 <= r["landmark_error_m"] < 3 and r["landmark_covariance_m"] > 0, r["landmark_error_m"]
    assert r["duration_s"] > 24  # the host left before the end
    for f in ("map.png", "allocation.png", "transcript.txt", "results.json"):
        assert (tmp / "out" / f).stat().st_size > 0, f
    assert json.loads((tmp / "out" / "results.json").read_text())["completed"] is True
    assert not our_processes(str(tmp)), "processes left behind"


def test_agents_are_honest_robots(ci_run: tuple[dict, Path]) -> None:
    """No ground-truth service or Detect call by any agent (haa-sim counts them per caller)."""
    r, _ = ci_run
    assert r["sim_truth_calls"] == {}, r["sim_truth_calls"]


def test_readings_flow_through_the_sensor_agents(ci_run: tuple[dict, Path]) -> None:
    r, _ = ci_run
    assert r["readings_generated"] > 20
    done = r["readings_processed"] + (r["readings_discarded"] or 0)
    assert 0.8 * r["readings_generated"] <= done <= r["readings_generated"]
    assert r["processings"] >= r["readings_processed"] > 0  # an image is one reading, two processings


def test_killed_agents_are_recovered_and_the_host_leave_is_graceful(ci_run: tuple[dict, Path]) -> None:
    _, tmp = ci_run
    text = (tmp / "out" / "transcript.txt").read_text()
    assert "h3 has left" in text
    lines = text.splitlines()
    for type_name, kind in (("supervisor_explore", "SupervisorExplore"), ("path_planner", "AgentPathPlanner")):
        killed = next(i for i, line in enumerate(lines) if f"({type_name}) killed on" in line)
        name = lines[killed].split()[1]
        assert any(f"{name} ({kind}) recovered by" in line for line in lines[killed:]), (kind, name)
    assert "Mission finished" in text


def test_a_chaos_plan_runs_inside_the_mission(ci_run: tuple[dict, Path]) -> None:
    """tests/missions/ci-chaos.yaml: ExecutiveAvatar's loop blocked at 20 s simulated; its host finds the hang,
    kills it and it is recovered; the fault is on the transcript and in chaos.json."""
    r, tmp = ci_run
    assert r["chaos"]["plan"] == "ci-chaos" and r["chaos"]["by_action"] == {"hang": 1}, r["chaos"]
    faults = json.loads((tmp / "out" / "chaos.json").read_text())["faults"]
    assert [(f["action"], f["ok"]) for f in faults] == [("hang", True)] and 19.5 <= faults[0]["t"] <= 24, faults
    lines = (tmp / "out" / "transcript.txt").read_text().splitlines()
    hung = next(i for i, line in enumerate(lines) if " hangs by chaos" in line)
    name = lines[hung].split()[1]
    assert any(f"{name} (ExecutiveAvatar) recovered by" in line for line in lines[hung:]), lines[hung:]
