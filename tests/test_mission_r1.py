"""Experiment R-1 (haa/lab/experiments/r1.py): the chaos plan of each failure level, eq. 7.3-1's fit, the table beside
Table 7.3-1 and the JSON — with a stand-in for the mission run (the real missions are a benchmark:
`haactl experiment r1`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from haa.lab.chaos.plan import load_plan
from haa.lab.experiments import r1
from haa.mission.schema import load_mission


def test_the_duration_model_fit_recovers_k() -> None:
    pts = [(5.5, (5.5 + 0.55) / 5.5), (2.0, (2.0 + 0.55) / 2.0), (1.0, 1.55)]
    assert r1.fit_k(pts) == pytest.approx(0.55)
    assert r1.fit_k([]) is None
    assert [r1.mtf_min(w) for _, w in r1.LEVELS] == [None, 5.5, 2.0, 1.0]


def test_each_level_runs_its_plan_on_the_same_seeds(tmp_path: Path) -> None:
    seen = []

    def fake_run(mission, speed=None, out_dir=None, log=None):
        plan = load_plan(Path(mission.spec.chaos)) if mission.spec.chaos else None
        seen.append((mission.spec.seed, plan.faults[0].life_s if plan else None, out_dir.parent.name))
        d = {"none": 150.0, "moderate": 160.0, "high": 180.0, "extreme": 210.0}[out_dir.parent.name]
        return {"seed": mission.spec.seed, "completed": True, "duration_s": d + mission.spec.seed,
                "coverage": 0.9, "accuracy": 0.92, "agent_failures": 0 if plan is None else 5}

    doc = r1.run_r1(2, out_dir=tmp_path / "runs", json_out=tmp_path / "r1.json", run_fn=fake_run)
    assert [s for s, _, _ in seen] == [1, 2] * 4  # missions/r1.yaml has seed 1
    assert [w for _, w, _ in seen[::2]] == [None, (60.0, 600.0), (60.0, 180.0), (30.0, 90.0)]
    plan = load_plan(tmp_path / "runs" / "extreme" / "seed1" / "plan.yaml")
    assert plan.faults[0].action == "hang" and plan.faults[0].hang_s == r1.HANG_S and plan.duration_s is None
    assert doc["increase"]["extreme"] == pytest.approx(211.5 / 151.5 - 1)
    assert doc["k_min"] is not None and doc["k_min"] > 0 and not doc["partial"]
    saved = json.loads((tmp_path / "r1.json").read_text())
    assert set(saved["results"]) == {"none", "moderate", "high", "extreme"} and saved["runs_done"] == 8
    rows = r1.table(doc)
    dur = next(r for r in rows if r[0] == "Mission Duration [min]")
    assert dur[1] == "2.525" and dur[5:] == ("2.573", "2.842", "3.261", "3.900")
    assert next(r for r in r1.table(doc, "std") if r[0] == "Mission Duration [min]")[5] == "0.26060"


def test_unknown_levels_are_refused_before_anything_runs(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="levels: unknown sometimes"):
        r1.run_r1(1, levels=["none", "sometimes"], run_fn=lambda *a, **k: {}, json_out=tmp_path / "x.json")
    assert not (tmp_path / "x.json").exists()


def test_the_r1_mission_is_the_thesis_setup() -> None:
    m = load_mission(r1.MISSIONS / "r1.yaml")
    assert (m.spec.arena, m.spec.hosts.start, len(m.spec.avatars), m.spec.complete.explored) == ("small", 3, 4, 0.95)
    assert {a.type for a in m.spec.avatars} == {"seeker"} and not m.spec.hosts.schedule
