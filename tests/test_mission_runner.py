"""The mission runner: schedule timing, the transcript, the experiment statistics, the results JSON,
`haactl mission run` on a bad file, the runner on real processes with stand-in team agents
(tests/test_mission_runner_fakes.py: the runner's own checks, independent of the real team), and the real
team on missions/quick.yaml.

`run(mission_file, tmp_path, ...)` runs a mission and returns the results dict: the end-to-end mission test
of the real team is one call of it (with the default agent types) plus its asserts.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
from helpers import wait_sync, wait_value
from test_mission_runner_fakes import EST_OFFSET_M, FAKE_AVATAR, FAKE_DURATION_S, FAKE_EXEC

from haa.lab.experiments import af as ex
from haa.mission import attached, load_mission, plan, results
from haa.mission import runner as rn
from haa.mission import transcript as tr
from haa.sim.schedule import load_schedule

REPO = Path(__file__).resolve().parents[1]
HAACTL = [sys.executable, "-c", "from haactl.main import app; app()"]

FAKE_MISSION = """\
name: fake
scenario: explore
arena: small
seed: 3
speed: 4
complete: {explored: 0.6, time_limit_s: 90}
hosts:
  start: 2
  schedule:
    - {at_s: 4, join: h3}
    - {at_s: 12, leave: h2}
avatars:
  - {name: s1, type: seeker, pose: [0.5, 0.5, 1.5708], leave_at_s: 15}
  - {name: s2, type: seeker, pose: [2.9, 0.5, 1.5708], join_at_s: 6}
"""


# ---------------------------------------------------------------------------------------------- helpers


def mission_file(tmp_path: Path, text: str = FAKE_MISSION, name: str = "m.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def fake_team(monkeypatch) -> tuple[str, str]:
    """Make the hosts load the stand-in team agents; their type names."""
    here = str(Path(__file__).parent)
    monkeypatch.setenv("PYTHONPATH", here + os.pathsep + os.environ.get("PYTHONPATH", ""))
    monkeypatch.setenv("HAA_AGENT_MODULES", "test_mission_runner_fakes")
    return FAKE_EXEC, FAKE_AVATAR


def run(path: Path, tmp_path: Path, speed: float | None = None, agent_types=(rn.EXECUTIVE, rn.AVATAR), **kw):
    """Run the mission file on its own local cluster and haa-sim; the results dict (also in tmp_path/out)."""
    return rn.run_mission(load_mission(path), speed, tmp_path / "out", agent_types=agent_types, **kw)


def our_processes(marker: str) -> list[str]:
    """Processes whose command line mentions `marker` (a tmp path of this test)."""
    out = []
    for p in psutil.process_iter(["cmdline", "status"]):
        try:
            if p.info["status"] != psutil.STATUS_ZOMBIE and marker in " ".join(p.info["cmdline"] or []):
                out.append(" ".join(p.info["cmdline"])[:160])
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return out


def no_processes_left(marker: str, timeout: float = 10.0) -> None:
    """Wait until no process mentions `marker` (a finished mission's processes exit shortly after it)."""
    wait_value(lambda: our_processes(marker), lambda ps: not ps, timeout, f"no process of {marker} left behind",
               interval=0.1, show="\n".join)


# ---------------------------------------------------------------------------------------------- schedules


def test_due_applies_entries_in_order_at_their_time():
    times = [0.0, 60.0, 60.0, 120.0]
    assert plan.due(times, 0, 0.0) == 1
    assert plan.due(times, 1, 59.9) == 1
    assert plan.due(times, 1, 60.0) == 3  # entries at the same time together, in file order
    assert plan.due(times, 3, 1e9) == 4 and plan.due([], 0, 5.0) == 0


def test_host_and_avatar_plans_follow_the_mission(tmp_path):
    m = load_mission(REPO / "missions" / "af1.yaml")
    hp = plan.host_plan(m)
    assert hp[:3] == [(60.0, "leave", "h4"), (120.0, "join", "h5"), (180.0, "leave", "h5")]
    ap = plan.avatar_plan(m)
    assert ap[:3] == [(0.0, "join", "s1"), (0.0, "join", "s2"), (0.0, "join", "s3")]
    assert (120.0, "retire", "s1") in ap and ap[-1][0] == 150.0
    # the --schedule file haa-sim gets says the same
    f = tmp_path / "sched.yaml"
    f.write_text(plan.schedule_yaml(m))
    entries = load_schedule(f, len(m.arena.start_poses))
    assert [(e.at, e.kind) for e in entries] == [(0.0, "join")] * 3 + [(120.0, "retire"), (150.0, "join"),
                                                                        (150.0, "join")]
    assert entries[3].retire == "s1" and entries[4].join.id in ("s4", "s5") and entries[4].join.start is not None


def test_the_end_of_a_mission():
    assert plan.status_outcome(None) is None and plan.status_outcome({"state": "running"}) is None
    assert plan.status_outcome({"state": "complete", "reason": "95.1 % explored"}) == (True, "95.1 % explored")
    assert plan.status_outcome({"state": "stopped"}) == (False, "stopped")
    assert not plan.time_limit_reached(900.0, 900.0) and plan.time_limit_reached(902.0, 900.0)
    assert plan.mission_duration({"started_t": 10.0, "finished_t": 238.0}, 300.0) == 228.0
    assert plan.mission_duration({"started_t": 10.0, "finished_t": None}, 300.0) == 290.0
    assert plan.mission_duration(None, 42.0) == 42.0


# ---------------------------------------------------------------------------------------------- transcript


def test_transcript_clock_and_lines():
    assert tr.clock(0) == "00:00" and tr.clock(51.9) == "00:51" and tr.clock(238) == "03:58"
    assert tr.clock(6001) == "100:01" and tr.clock(-3) == "00:00"
    assert tr.class_name("avatar_simulation") == "AvatarSimulation" and tr.class_name("path_planner") == \
        "AgentPathPlanner"
    assert tr.class_name("my_new_thing") == "MyNewThing"
    lines = tr.mission_lines([
        json.dumps({"t": 10.0, "agent": "", "type": "", "text": "Mission started"}).encode(),
        {"t": 51.2, "agent": "A1", "type": "supervisor_explore", "text": "target (1.0, 2.0) for s1"},
        b"not json", {"no": "text"},
    ])
    assert [ln.format() for ln in lines] == ["00:10 Mission started",
                                             "00:51 A1 (SupervisorExplore) target (1.0, 2.0) for s1"]


def test_host_timelines_become_fig_7_1_3_lines():
    def rec(ts, host, event, agent, name, detail=""):
        return {"ts": ts, "host": host, "event": f"agent_{event}",
                "fields": {"agent": agent, "name": name, "detail": detail}}

    records = [
        rec(100.0, "h1", "created", "id1", "A1", "avatar_simulation"),
        rec(100.01, "h2", "created", "id1", "A1", "avatar_simulation"),  # every member reports it
        rec(100.5, "h2", "spawning", "id1", "A1"),
        rec(101.0, "h2", "active", "id1", "A1", "fresh state"),
        rec(112.0, "h2", "freezing", "id1", "A1", "to h3"),
        rec(114.0, "h3", "thawed", "id1", "A1", "0 queued messages"),
        rec(120.0, "h3", "crashed", "id1", "A1", "exit code -9"),
        rec(120.2, "h1", "crashed", "id1", "A1"),  # a member's bare report of the same crash
        rec(121.0, "h1", "recovered", "id1", "A1"),
        {"ts": 122.0, "host": "h1", "event": "suspicion", "fields": {"peer": "h3"}},
    ]
    events = tr.host_agent_events(records)
    assert len(events) == 9
    cm = tr.ClockMap(speed=2.0)
    cm.add(100.0, 0.0)
    cm.add(110.0, 20.0)
    lines = tr.host_agent_lines(events, cm)
    assert [ln.format() for ln in lines] == [
        "00:00 A1 (AvatarSimulation) requested by the operator",
        "00:02 A1 (AvatarSimulation) spawned by h2",
        "00:24 A1 (AvatarSimulation) freezing on h2 (to h3)",
        "00:28 A1 (AvatarSimulation) thawed by h3",
        "00:40 A1 (AvatarSimulation) crashed on h3: exit code -9",
        "00:42 A1 (AvatarSimulation) recovered by h1",
    ]
    merged = tr.merge([tr.Line(24.0, "h4 retires (graceful leave)")], lines)
    assert [ln.text for ln in merged][2:4] == ["h4 retires (graceful leave)",
                                              "A1 (AvatarSimulation) freezing on h2 (to h3)"]


def test_the_clock_map_follows_the_sampled_simulator():
    cm = tr.ClockMap(speed=4.0)
    assert not cm
    cm.add(10.0, 0.0)
    cm.add(12.0, 6.0)  # the simulator ran at 3x, not 4x
    cm.add(11.0, 9.0)  # out of order: ignored
    assert cm.to_sim(11.0) == pytest.approx(3.0)
    assert cm.to_sim(9.0) == pytest.approx(-4.0) and cm.to_sim(13.0) == pytest.approx(10.0)


# ---------------------------------------------------------------------------------------------- experiments


def test_statistics_are_the_thesis_ones():
    s = ex.stats([3.5, 4.0, None, 4.5, float("nan")])
    assert s.n == 3 and s.mean == pytest.approx(4.0)
    assert s.std == pytest.approx(math.sqrt(1 / 6))  # population STD
    assert s.rms**2 == pytest.approx(s.mean**2 + s.std**2)
    assert ex.stats([]) == ex.Stats(0, None, None, None)
    # Table 7.1-1's duration row satisfies RMS² = mean² + STD² (thesis guide §3.1)
    _rep, mean, rms, std = ex.THESIS["af1"]["Mission Duration [min]"]
    assert math.sqrt(mean**2 + std**2) == pytest.approx(rms, abs=1e-3)


def synthetic_runs(n=5):
    runs = []
    for k in range(n):
        runs.append({"seed": 1 + k, "completed": k != 2, "reason": "x", "duration_s": 200.0 + 10 * k,
                     "coverage": 0.9 + 0.01 * k, "accuracy": 0.91, "position_error_m": 0.05 + 0.01 * k,
                     "hosts_avg_thesis": 4.5, "agents_avg": 13.0, "transfers": k, "landmark_error_m": None})
    return runs


def test_the_representative_run_is_the_completed_one_nearest_the_means():
    runs = synthetic_runs()
    assert ex.representative(runs) == 1 or ex.representative(runs) == 3  # k=2 is nearest but did not complete
    runs[2]["completed"] = True
    assert ex.representative(runs) == 2
    assert ex.representative([]) is None


def test_the_summary_has_every_table_row_beside_the_thesis():
    s = ex.summarize("af1", synthetic_runs())
    assert s["runs"] == 5 and s["completed"] == 4
    rows = {r["title"]: r for r in s["rows"]}
    d = rows["Mission Duration [min]"]
    assert d["n"] == 5 and d["mean"] == pytest.approx(220 / 60) and d["thesis"] == [3.802, 3.871, 3.884, 0.324816]
    assert rows["Landmark Err [m]"]["n"] == 0 and rows["Landmark Err [m]"]["mean"] is None
    assert rows["Transfers"]["thesis"] is None and rows["Transfers"]["mean"] == pytest.approx(2.0)
    table = ex.table_rows(s)
    assert table[0][0] == "Mission Duration [min]" and table[0][6] == "3.871" and len(table[0]) == 9


def test_an_experiment_runs_each_seed_and_writes_its_json(tmp_path):
    seen = []

    def fake_run(mission, speed=None, out_dir=None, log=None):
        seen.append((mission.spec.seed, speed, out_dir.name))
        return {"seed": mission.spec.seed, "completed": True, "duration_s": 100.0 + mission.spec.seed,
                "coverage": 0.9, "accuracy": 0.9}

    doc = ex.run_experiment("af2", runs=3, speed=4.0, out_dir=tmp_path / "runs", json_out=tmp_path / "af2.json",
                            run_fn=fake_run)
    assert seen == [(1, 4.0, "seed1"), (2, 4.0, "seed2"), (3, 4.0, "seed3")]  # missions/af2.yaml has seed 1
    saved = json.loads((tmp_path / "af2.json").read_text())
    assert saved["seeds"] == [1, 2, 3] and len(saved["results"]) == 3 and saved["representative_seed"] == 2
    assert saved["provenance"]["mission_sha256"] and doc["json"] == str(tmp_path / "af2.json")


def test_an_interrupted_experiment_resumes_at_its_next_seed_and_not_from_another_setup(tmp_path):
    seen = []

    def fake_run(mission, speed=None, out_dir=None, log=None):
        seen.append(mission.spec.seed)
        if len(seen) == 3:
            raise KeyboardInterrupt  # the session ends mid-run
        return {"seed": mission.spec.seed, "completed": True, "duration_s": 1700.0 + mission.spec.seed,
                "collectables_total": 20, "cargo_collected": 20}

    js = tmp_path / "af3.json"
    with pytest.raises(KeyboardInterrupt):
        ex.run_experiment("af3", runs=4, speed=1.0, out_dir=tmp_path / "runs", json_out=js, run_fn=fake_run)
    assert json.loads((tmp_path / "af3-partial.json").read_text())["seeds"] == [1, 2]
    logs: list[str] = []
    doc = ex.run_experiment("af3", runs=4, speed=1.0, out_dir=tmp_path / "runs", json_out=js, run_fn=fake_run,
                            resume=True, log=logs.append)
    assert seen == [1, 2, 3, 3, 4] and doc["seeds"] == [1, 2, 3, 4] and not doc["partial"]
    assert any("resuming from" in m and "2 run(s)" in m for m in logs)
    assert not (tmp_path / "af3-partial.json").exists()
    cargo = next(r for r in doc["rows"] if r["title"] == "Cargo Collected")
    assert cargo["mean"] == 20 and cargo["thesis"] == [20.0, 20.0, 20.0, 0.0]
    # another speed: its runs are not these; it starts again from the first seed
    seen.clear()
    logs.clear()
    ex.run_experiment("af3", runs=1, speed=2.0, out_dir=tmp_path / "runs", json_out=js, run_fn=fake_run,
                      resume=True, log=logs.append)
    assert seen == [1] and any("not resuming" in m and "speed" in m for m in logs)


def test_an_experiment_can_compare_the_exploration_strategies_on_the_same_seeds(tmp_path):
    seen = []

    def fake_run(mission, speed=None, out_dir=None, log=None):
        seen.append((mission.spec.seed, mission.spec.exploration))
        return {"seed": mission.spec.seed, "completed": True, "duration_s": 100.0}

    doc = ex.run_experiment("af1", runs=2, out_dir=tmp_path / "runs", json_out=tmp_path / "f.json", run_fn=fake_run,
                            exploration="frontier")
    assert seen == [(1, "frontier"), (2, "frontier")] and doc["exploration"] == "frontier"
    with pytest.raises(ValueError, match="exploration"):
        ex.run_experiment("af1", runs=1, run_fn=fake_run, exploration="random")


# ---------------------------------------------------------------------------------------------- the command line


def test_a_bad_mission_file_gets_one_line_and_starts_nothing(tmp_path):
    bad = mission_file(tmp_path, FAKE_MISSION.replace("arena: small", "arena: small\nparticles: 0"), "bad.yaml")
    out = tmp_path / "out"
    p = subprocess.run([*HAACTL, "mission", "run", str(bad), "-o", str(out)], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    assert p.returncode == 2, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "bad.yaml: particles:" in lines[0], p.stderr
    assert not out.exists() and not our_processes(str(tmp_path))


def test_without_the_team_agents_the_runner_says_so_before_starting_anything(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "haa.agents.executive_mission" else real(name, *a))
    with pytest.raises(plan.MissionRunError, match="executive_mission"):
        run(mission_file(tmp_path), tmp_path)
    assert not (tmp_path / "out" / "cluster").exists()


# ---------------------------------------------------------------------------------------------- real processes


def test_a_mission_with_stand_in_agents_runs_end_to_end(tmp_path, monkeypatch):
    """Real haa-hostd processes and haa-sim, the host schedule (a join and a graceful leave), an avatar that
    joins late and one that retires; the stand-in executive completes after FAKE_DURATION_S simulated s."""
    types = fake_team(monkeypatch)
    t0 = time.time()
    r = run(mission_file(tmp_path), tmp_path, agent_types=types)
    assert set(results.REQUIRED_KEYS) <= set(r)
    assert r["completed"] is True, r["reason"]
    assert r["duration_s"] == pytest.approx(FAKE_DURATION_S, abs=2.0) and r["wall_s"] < time.time() - t0 + 1
    assert r["position_error_m"] == pytest.approx(EST_OFFSET_M, abs=1e-6)
    assert 0.0 < r["coverage"] <= 1.0 and 0.0 < r["accuracy"] <= 1.0 and r["explored"] == pytest.approx(1.0)
    assert r["readings_generated"] > 0 and r["processings"] == 2 * r["readings_processed"]
    assert 2.0 <= r["hosts_avg"] <= 3.0 and r["hosts_avg_thesis"] == pytest.approx(r["hosts_avg"] + 1)
    assert 1.0 <= r["agents_avg"] <= 3.0
    # every agent h2 runs when it retires is handed over, not recovered. Usually the first two agents go one to
    # each starting host (and stay there when h3 joins: join hysteresis), but placing both on h1 is a tie the
    # allocation may break either way when h2's load report is late (the machine under load), so the count comes
    # from where the transcript last saw each agent before the leave
    events = [json.loads(ln) for ln in (tmp_path / "out" / "transcript.jsonl").read_text().splitlines()]
    leave_t = next(e["t"] for e in events if e["text"] == "h2 retires (graceful leave)")
    where = {e["agent"]: e["host"] for e in events
             if e["t"] < leave_t and e["event"] in ("active", "thawed", "recovered")}
    on_h2 = sorted(a for a, h in where.items() if h == "h2")
    assert r["transfers"] >= len(on_h2) and r["agent_failures"] == 0, (on_h2, r["transfers"])
    assert r["provenance"]["seed"] == 3 and r["provenance"]["machine"]["cpu_count"] == os.cpu_count()
    assert 0.0 <= r["cpu_percent"] <= 100.0
    out = tmp_path / "out"
    assert json.loads((out / "results.json").read_text())["completed"] is True
    assert (out / "map.png").stat().st_size > 1000 and (out / "allocation.png").stat().st_size > 1000
    text = (out / "transcript.txt").read_text()
    for want in ("h3 starts and joins", "h2 retires (graceful leave)", "avatar s2 (seeker) joined the arena",
                 "avatar s1 left the arena (retired)", "Mission started", "Mission finished",
                 "(FakeExecutiveMission) requested by the operator"):
        assert want in text, text
    clocks = [ln[:5] for ln in text.splitlines()]
    assert clocks == sorted(clocks, key=lambda c: (int(c[:2]), int(c[3:])))
    no_processes_left(str(tmp_path))


def test_start_status_stop_on_a_running_cluster(tmp_path, monkeypatch):
    """`haactl mission start|status|logs|stop` through the library: the conductor runs the mission in the
    background; a second start is refused; stop removes the agents and the haa-sim start started."""
    from haa.cluster.local_backend import LocalBackend

    types = fake_team(monkeypatch)
    root = tmp_path / "cluster"
    b = LocalBackend(root)
    b.up(2, 2)
    try:
        wait_sync(lambda: b.formation(["h1", "h2"]).done, 60, "h1 and h2 in one group", interval=0.2)
        m = load_mission(mission_file(tmp_path, FAKE_MISSION.replace("speed: 4", "speed: 2")))
        st = attached.start_attached(root, m, agent_types=types)
        assert st["pid"] and st["mission"] == "fake"
        with pytest.raises(plan.MissionRunError, match="is running"):
            attached.start_attached(root, m, agent_types=types)
        st = wait_value(lambda: attached.read_json(attached.mission_dir(root) / attached.STATE_FILE),
                        lambda st: (st and st.get("state") == "running" and st.get("avatars")
                                    and st["avatars"][0]["agent"]
                                    and sum(len(v) for v in st["agents_per_host"].values()) >= 2),
                        60, "the mission running, its agents placed", interval=0.3)
        assert st["hosts"] == ["h1", "h2"]  # the host schedule is not applied to the operator's cluster
        wait_sync(lambda: any("requested by the operator" in ln["text"] for ln in attached.live_transcript(root)),
                  attached.TRANSCRIPT_PERIOD + 10, "the live transcript to show the executive requested", interval=0.3)
        res = attached.stop_attached(root)
        assert res["was_running"] and res["sim"] == "stopped"
        assert res["results"]["completed"] is False and res["results"]["reason"] == "stopped by the operator"
        agents = [a for a in LocalBackend(root).hosts()]
        assert agents and not our_processes(str(attached.mission_dir(root)))
        assert not attached.conductor_alive(attached.read_json(attached.mission_dir(root) / attached.STATE_FILE))
    finally:
        attached.stop_attached(root)
        b.down(grace=1.0)
    assert not our_processes(str(tmp_path))


@pytest.mark.slow
def test_the_quick_mission_of_the_robot_team(tmp_path):
    """The real team (haa/agents/) on missions/quick.yaml: it completes, the results have every key, the
    agents made no ground-truth or Detect call, nothing is left running. (Further checks of a shared short
    mission — an agent kill, a host leave — are in test_mission_run.py and test_mission_failures.py.)"""
    r = run(REPO / "missions" / "quick.yaml", tmp_path, speed=2.0)
    assert set(results.REQUIRED_KEYS) <= set(r)
    assert r["completed"] is True, (r["reason"], r["errors"])
    assert r["sim_truth_calls"] == {}, r["sim_truth_calls"]
    assert r["readings_generated"] > 0 and r["readings_processed"] > 0
    assert 0 < r["coverage"] <= 1 and 0 < r["accuracy"] <= 1 and r["position_error_m"] is not None
    assert r["agents_avg"] > 5 and 1.5 <= r["hosts_avg"] <= 2.0
    assert "Mission finished" in (tmp_path / "out" / "transcript.txt").read_text()
    no_processes_left(str(tmp_path))
