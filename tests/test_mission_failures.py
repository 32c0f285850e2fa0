"""Failures during a mission on real processes: killing any one agent or host, or retiring a host
or an avatar, mid-mission — the mission goes on and completes, and nothing committed is lost.

The CI mission (tests/test_mission_run.py) kills SupervisorExplore and a path planner and retires a host. This
module adds one short mission to the default suite (tests/missions/failures.yaml: SupervisorSLAM, an avatar
agent and ExecutiveAvatar killed, a seeker retiring and a late one joining; ~25 s wall) and, marked slow, the
rest: every agent type killed (two of them twice), a host crash and restart, the graceful leave of the hosts
running SupervisorSLAM and ExecutiveMission. Each test asserts on the transcript and on what the team wrote
in the DDB, not only on `completed`:

* the prediction chain of every avatar, through its agent's crash and recovery: between two committed anchors
  (`slam/anchor/<avatar>`: the odometry pose of a committed prediction) the Predict events of `slam/log`,
  integrated without noise from the first, must land on the second (a gap or an overlap in the chain moves
  it by speed x the gap) — `Mirror` follows a host's mirror stream, so it sees every log item and anchor
  before SupervisorSLAM trims the log;
* the explored share must not drop (SupervisorSLAM's successor rebuilds the map from `slam/ckpt/*` + `slam/log`:
  nothing committed is lost);
* no reading is lost: at the last poll (one replica, one instant) every reading generated is processed,
  discarded or still waiting in `slam/raw/` (an avatar agent that numbered readings again after a crash would
  overwrite waiting ones); the registries (`avatars/`, `assign/`, `targets/`,
  `slam/estimates`) say what the transcript says.

`haactl mission run FILE --speed 4 -o DIR --transcript` runs the same mission files by hand.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from test_mission_runner import no_processes_left

from haa.cluster import queries
from haa.mission import load_mission, plan
from haa.mission import runner as rn

HERE = Path(__file__).resolve().parent
MISSIONS = HERE / "missions"


# ---------------------------------------------------------------------------------------------- the tap


class Mirror(threading.Thread):
    """Follows one host's mirror stream (a snapshot, then every applied batch) into a local replica: every
    `slam/log` item by index and every committed anchor (`slam/anchor/<avatar>`: time -> odometry pose). When
    the host goes (a leave, the end), it follows another one from a fresh snapshot."""

    def __init__(self, run: rn.MissionRun) -> None:
        super().__init__(daemon=True, name="mission-mirror")
        self.run_ = run
        self.items: dict[int, bytes] = {}
        self.anchors: dict[str, dict[float, tuple[float, float, float]]] = {}
        self.log_first = 0
        self.snapshots = 0
        self.stop = threading.Event()

    def _event(self, ev: Any) -> None:
        if ev.key == "slam/log" and ev.kind == "append":
            self.items[ev.index] = bytes(ev.value)
        elif ev.key == "slam/log" and ev.kind == "trim":
            self.log_first = ev.index
        elif ev.key.startswith("slam/anchor/") and ev.kind in ("add", "write"):
            v = json.loads(ev.value) if isinstance(ev.value, str | bytes) else ev.value
            self.anchors.setdefault(ev.key[len("slam/anchor/"):], {})[float(v["t"])] = tuple(v["pose"])

    def _load(self, db: Any) -> None:
        log = db.get("slam/log")
        if log is not None:
            first, items = log.value["first"], log.value["items"]
            self.log_first = first
            for k, item in enumerate(items):
                self.items.setdefault(first + k, bytes(item))
        for o in db.items("slam/anchor/"):
            v = o.value if isinstance(o.value, dict) else json.loads(o.value)
            self.anchors.setdefault(o.key[len("slam/anchor/"):], {})[float(v["t"])] = tuple(v["pose"])

    def run(self) -> None:
        from haa.core.ddb.ddb import Ddb

        while not self.stop.is_set():
            hosts = queries.alive_hosts(self.run_.backend)
            if not hosts:
                self.stop.wait(0.2)
                continue
            c = queries.host_client(self.run_.backend, hosts[0], 3.0)
            try:
                db = None
                for m in c.mirror(views=False, timeout=None):
                    if self.stop.is_set():
                        break
                    if m.WhichOneof("event") == "snapshot":
                        db = Ddb.restore(m.snapshot.SerializeToString())
                        db.watch(self._event)
                        self._load(db)
                        self.snapshots += 1
                    elif m.WhichOneof("event") == "batch" and db is not None:
                        db.apply(m.batch.payload)
            except grpc.RpcError:
                self.stop.wait(0.2)
            finally:
                c.close()


@dataclass
class Tap:
    """The runner's `on_poll` hook (once a wall second): starts the `Mirror` (every log item and anchor), keeps
    the last snapshot of the team's registries and counters. `act(run, tap)`, if given, runs first (actions
    chosen at run time)."""

    act: Callable[[rn.MissionRun, Tap], None] | None = None
    mirror: Mirror | None = None
    snap: dict[str, Any] = field(default_factory=dict)
    polls: int = 0
    fired: dict[str, Any] = field(default_factory=dict)  # actions `act` has taken -> what it noted

    @property
    def items(self) -> dict[int, bytes]:
        return self.mirror.items if self.mirror else {}

    @property
    def anchors(self) -> dict[str, dict[float, tuple[float, float, float]]]:
        return self.mirror.anchors if self.mirror else {}

    @property
    def log_first(self) -> int:
        """The log's first index (> 0: SupervisorSLAM has checkpointed and trimmed it)."""
        return self.mirror.log_first if self.mirror else 0

    def __call__(self, run: rn.MissionRun) -> None:
        if self.mirror is None:
            self.mirror = Mirror(run)
            self.mirror.start()
        if self.act is not None:
            self.act(run, self)
        self.polls += 1
        got = queries.ddb_read(run.backend, prefix="", prefer=run.reader)
        if got is None:
            return
        keep = ("avatars/", "assign/", "targets/", "bids/", "slam/estimates", "mission/status", "stats/")
        self.snap = {k: v for k, v in got[1].items() if k.startswith(keep)}
        self.snap["pending"] = sum(k.startswith("slam/raw/") for k in got[1])  # readings not processed yet


def chain_checks(tap: Tap) -> dict[str, list[tuple[float, float, float]]]:
    """Per avatar, [(t0, t1, deviation)] for consecutive committed anchors t0 < t1 whose predictions the tap saw
    in full: the distance (m, plus heading difference in rad) between anchor t1's odometry pose and anchor t0's
    integrated through every Predict event after it up to t1, without noise (haa.slam.motion.propagate). 0 up
    to float error when the chain has neither gap nor overlap."""
    from haa.slam import events as sev
    from haa.slam.motion import propagate, wrap_angle

    preds: dict[str, list[tuple[int, Any]]] = {}
    for i in sorted(tap.items):
        ev = sev.decode(tap.items[i])
        if isinstance(ev, sev.Predict):
            preds.setdefault(ev.avatar, []).append((i, ev.prediction))
    have = set(tap.items)
    rng = np.random.default_rng(0)
    out: dict[str, list[tuple[float, float, float]]] = {}
    for avatar, anchors in tap.anchors.items():
        ps = preds.get(avatar, [])
        at = {p.t: k for k, (_, p) in enumerate(ps)}
        ts = sorted(t for t in anchors if t in at)
        res = []
        for t0, t1 in itertools.pairwise(ts):
            k0, k1 = at[t0], at[t1]
            if any(i not in have for i in range(ps[k0][0], ps[k1][0] + 1)):
                continue  # a poll came after a trim: not seen in full
            s = np.array([anchors[t0]], dtype=float)
            t = t0
            for _, p in ps[k0 + 1:k1 + 1]:
                s = propagate(s, replace(p, sigma_xy=0.0, sigma_theta=0.0), p.t - t, rng)
                t = p.t
            end = anchors[t1]
            dev = math.hypot(s[0, 0] - end[0], s[0, 1] - end[1]) + abs(float(wrap_angle(s[0, 2] - end[2])))
            res.append((t0, t1, dev))
        out[avatar] = res
    return out


def kill_slam_after_checkpoint(run: rn.MissionRun, tap: Tap) -> None:
    """`Tap.act`: kill SupervisorSLAM (as `agent_faults` does) once it has written a checkpoint and trimmed the
    log, so that its successor must come back from `slam/ckpt/*` + `slam/log`."""
    if "slam" not in tap.fired and tap.log_first > 0 and run.mission_time() > 16:
        tap.fired["slam"] = tap.log_first
        run.pending.append(run.host_pool.submit(run.kill_agent, run.mission_time(), "supervisor_slam"))


def leave_host_of(*steps: tuple[float, str]) -> Callable[[rn.MissionRun, Tap], None]:
    """`Tap.act`: from mission time `at`, retire (graceful leave) the host that runs the agent of type
    `type_name`, once, for each (at, type_name); notes the host in `tap.fired[type_name]`."""

    def act(run: rn.MissionRun, tap: Tap) -> None:
        t = run.mission_time()
        for at, type_name in steps:
            if type_name in tap.fired or t < at or len(run.members) < 2:
                continue
            host = next((a.owner for a in run.rows.values() if a.type == type_name and a.status == "active"), "")
            if host in run.members:
                tap.fired[type_name] = host
                run.pending.append(run.host_pool.submit(run.host_action, t, "leave", host))

    return act


# ---------------------------------------------------------------------------------------------- helpers


@dataclass
class Run:
    results: dict[str, Any]
    tap: Tap
    text: str
    explored: list[tuple[float, float]]
    out: Path

    @property
    def lines(self) -> list[str]:
        return self.text.splitlines()

    def mm_ss(self, line: str) -> float:
        m, s = line.split()[0].split(":")
        return 60 * int(m) + int(s)


def run_mission_file(path: Path, out: Path, act: Callable[[rn.MissionRun, Tap], None] | None = None) -> Run:
    tap = Tap(act)
    mission = load_mission(path)
    run = rn.MissionRun(mission, None, out, None, None, on_poll=tap)
    try:
        results = run.run()
    finally:
        if tap.mirror is not None:
            tap.mirror.stop.set()
            tap.mirror.join(10)
    text = (out / "transcript.txt").read_text()
    return Run(results, tap, text, list(run.tally.samples.explored), out)


def recoveries(r: Run, type_name: str, kind: str) -> list[tuple[str, float, float]]:
    """[(agent name, killed at, recovered at)] (mm:ss resolution) for every agent_faults kill of `type_name`;
    asserts that each killed agent was recovered afterwards."""
    out = []
    for i, line in enumerate(r.lines):
        if f"({type_name}) killed on" in line:
            name = line.split()[1]
            rec = next((x for x in r.lines[i:] if f"{name} ({kind}) recovered by" in x), None)
            assert rec is not None, f"{name} ({kind}) killed at {line.split()[0]} and never recovered\n{r.text}"
            out.append((name, r.mm_ss(line), r.mm_ss(rec)))
    assert out, f"no kill of {type_name} in the transcript\n{r.text}"
    return out


def assert_completed(r: Run) -> None:
    res = r.results
    assert res["completed"] is True, (res["reason"], res.get("errors"), r.text[-3000:])
    assert not res.get("errors"), res["errors"]
    assert "Mission finished" in r.text
    no_processes_left(str(r.out))


def assert_nothing_lost(r: Run, min_checks: int = 3, spanning: dict[str, float] | None = None) -> None:
    """The explored share never drops; every avatar's prediction chain is continuous (also across `spanning`:
    avatar -> a time t some check (t0, t1) must span as t0 <= t < t1: the committed anchor an avatar agent's
    successor went on from, named in its "resumed after a crash" line — not the crash's mm:ss + 1 s, which an
    anchor can sit on exactly, leaving no pair that spans it strictly); readings are not left behind."""
    drops = [(t1, e0, e1) for (_, e0), (t1, e1) in itertools.pairwise(r.explored) if e1 < e0 - 0.01]
    assert not drops, f"explored share dropped: {drops}"
    checks = chain_checks(r.tap)
    for avatar, res in checks.items():
        assert len(res) >= min_checks, (avatar, len(res), r.tap.polls)
        bad = [c for c in res if c[2] > 1e-3]
        assert not bad, f"{avatar}: prediction chain broken between anchors {bad}"
    for avatar, t in (spanning or {}).items():
        assert any(t0 <= t < t1 for t0, t1, _ in checks.get(avatar, [])), (
            f"no chain check of {avatar} spans {t:g} s: {[(a, b) for a, b, _ in checks.get(avatar, [])]}")
    st = {k[len("stats/"):]: v for k, v in r.tap.snap.items() if k.startswith("stats/")}
    gen, done = st["readings_generated"], st["readings_processed"] + st.get("readings_discarded", 0)
    # a reading whose processings are all marked done keeps its raw key until SupervisorSLAM deletes it: in
    # that window it counts as processed and as pending; one neither processed nor pending would be lost
    assert done <= gen <= done + r.tap.snap["pending"], (st, r.tap.snap["pending"])
    assert done >= 0.6 * gen > 0, st


# ---------------------------------------------------------------------------------------------- unit


def test_a_host_kill_the_group_cannot_survive_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """With two hosts a crash leaves no majority: OAC never decides, the dead host is never removed and its
    agents never recovered (docs/membership.md, Open problems) — the runner refuses such a schedule."""
    text = (MISSIONS / "failures.yaml").read_text().split("avatars:")[1].split("agent_faults:")[0]
    two = tmp_path / "two.yaml"
    two.write_text("name: two\nscenario: explore\narena: small\nspeed: 4\nhosts:\n  start: 2\n  schedule:\n"
                   "    - {at_s: 10, kill: h2}\n    - {at_s: 30, restart: h2}\navatars:" + text)
    mission = load_mission(two)
    (problem,) = plan.host_kill_problems(mission)
    assert "kill h2 at 10 s leaves 1 of 2 hosts" in problem
    with pytest.raises(plan.MissionRunError, match="kill h2 at 10 s leaves 1 of 2"):
        rn.run_mission(mission, None, tmp_path / "out")
    assert not (tmp_path / "out" / "cluster").exists(), "nothing may start"
    three = tmp_path / "three.yaml"
    three.write_text(two.read_text().replace("start: 2", "start: 3"))
    assert plan.host_kill_problems(load_mission(three)) == []
    again = tmp_path / "again.yaml"  # two kills in a row: the second finds a group of two
    again.write_text(three.read_text().replace("{at_s: 30, restart: h2}", "{at_s: 30, kill: h3}"))
    assert [p.split(" leaves")[0] for p in plan.host_kill_problems(load_mission(again))] == [
        "hosts.schedule: kill h3 at 30 s"]


# ---------------------------------------------------------------------------------------------- default


@pytest.fixture(scope="module")
def failures_run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    return run_mission_file(MISSIONS / "failures.yaml", tmp_path_factory.mktemp("failures") / "out")


def test_the_failures_mission_completes(failures_run: Run) -> None:
    assert_completed(failures_run)
    assert failures_run.results["sim_truth_calls"] == {}


def test_supervisor_slam_recovers_from_the_log_losing_nothing(failures_run: Run) -> None:
    """Killed at 12 s, before its first checkpoint: its successor replays the whole log (the checkpoint +
    log case is test_supervisor_slam_killed_after_its_checkpoint_and_again, slow)."""
    r = failures_run
    ((_, killed, recovered),) = recoveries(r, "supervisor_slam", "SupervisorSLAM")
    assert recovered - killed <= 8, r.text  # simulated s (the host's first restart backoff is 0.5 s wall)
    assert any(t > recovered + 4 for t, _ in r.explored), "the mission ended before the map could be checked"
    assert_nothing_lost(r)


def test_an_avatar_agent_resumes_its_prediction_chain_after_a_crash(failures_run: Run) -> None:
    r = failures_run
    ((name, killed, _),) = recoveries(r, "avatar_simulation", "AvatarSimulation")
    resumed = [x for x in r.lines if x.split()[1:3] == [name, "(AvatarSimulation)"] and "resumed after a crash" in x]
    assert len(resumed) == 1, r.text
    m = re.search(r"predictions from t=([\d.]+) \(the committed anchor\), readings from #(\d+)", resumed[0])
    assert m and float(m[1]) <= killed + 1, resumed[0]
    registered = {x.split()[1]: x.split()[4] for x in r.lines if "(AvatarSimulation) avatar" in x and "registered" in x}
    avatar = registered[name]
    assert_nothing_lost(r, spanning={avatar: float(m[1])})


def test_executive_avatar_restarts_and_keeps_the_assignments(failures_run: Run) -> None:
    r = failures_run
    recoveries(r, "executive_avatar", "ExecutiveAvatar")
    snap = r.tap.snap
    assert snap["assign/s2"]["task"] == "explore" and snap["assign/s3"]["task"] == "explore", snap


def test_a_retiring_avatar_is_dropped_and_a_late_one_gets_a_target(failures_run: Run) -> None:
    r = failures_run
    text, snap = r.text, r.tap.snap
    assert re.search(r"A[\d.]+ \(AvatarSimulation\) avatar s1 retired \(", text), text
    assert re.search(r"\(SupervisorExplore\) controls .*\(lost s1\)", text), text
    assert "s1 released" in text
    assert snap["avatars/s1"]["status"] == "retired"
    assert "assign/s1" not in snap and not any(k.startswith("bids/s1/") for k in snap), sorted(snap)
    assert "s1" not in snap["slam/estimates"], "SupervisorSLAM still estimates the retired avatar"
    assert "avatar s3 (seeker) joined the arena" in text and "avatar s3 (seeker) registered" in text
    assert re.search(r"\(SupervisorExplore\) controls .*\(gained s3\)", text), text
    assert "assigned s3 to explore" in text
    assert snap["targets/s3"]["task"] == "explore" and "s3" in snap["slam/estimates"], snap


# ---------------------------------------------------------------------------------------------- slow


TYPES = (("executive_mission", "ExecutiveMission"), ("executive_avatar", "ExecutiveAvatar"),
         ("supervisor_explore", "SupervisorExplore"), ("path_planner", "AgentPathPlanner"),
         ("sensor_landmark", "AgentSensorLandmark"), ("sensor_floorfinder", "AgentSensorFloorFinder"),
         ("sensor_cooccupancy", "AgentSensorCooccupancy"), ("sensor_sonar", "AgentSensorSonar"),
         ("avatar_simulation", "AvatarSimulation"), ("supervisor_slam", "SupervisorSLAM"))


@pytest.mark.slow
def test_every_agent_type_killed_the_avatar_agent_twice(tmp_path: Path) -> None:
    """tests/missions/kill_each.yaml: every type killed once (SupervisorSLAM after its first checkpoint: its
    successor restores `slam/ckpt/*` and replays the rest of the log), the avatar agent twice; each is
    recovered with its App. III strategy, within 10 s simulated, and the mission completes."""
    r = run_mission_file(MISSIONS / "kill_each.yaml", tmp_path / "out", act=kill_slam_after_checkpoint)
    assert_completed(r)
    assert r.tap.fired.get("slam", 0) > 0, "SupervisorSLAM was not killed after a checkpoint"
    times = {}
    for type_name, kind in TYPES:
        kills = recoveries(r, type_name, kind)
        for name, killed, recovered in kills:
            assert recovered - killed <= 10, (name, killed, recovered, r.text)
        times[type_name] = kills
    (a1, _, _), (a2, k2, _) = times["avatar_simulation"]
    assert a1 == a2, "the same avatar agent is killed twice"
    strategies = {"ExecutiveMission": "from backup", "ExecutiveAvatar": "fresh state", "SupervisorExplore":
                  "from backup", "SupervisorSLAM": "from backup", "AvatarSimulation": "from backup",
                  "AgentPathPlanner": "fresh state", "AgentSensorSonar": "fresh state"}
    for kind, how in strategies.items():
        assert re.search(rf"\({kind}\) recovered by h\d \({how}\)", r.text), (kind, how)
    assert re.search(r"\(ExecutiveMission\) resumed after a crash: mission running", r.text), r.text
    registered = {x.split()[1]: x.split()[4] for x in r.lines if "(AvatarSimulation) avatar" in x and "registered" in x}
    resumed = [x for x in r.lines if f"{a1} (AvatarSimulation) resumed after a crash" in x]
    # the second kill may come while the first successor is still in on_resume (its line never written)
    assert 1 <= len(resumed) <= 2 and r.mm_ss(resumed[-1]) >= k2, resumed
    # each successor went on from the committed anchor its line names (one line: the last successor's, which
    # then took over the chain across both crashes)
    anchors = [float(m[1]) for x in resumed if (m := re.search(r"predictions from t=([\d.]+) \(the committed", x))]
    assert len(anchors) == len(resumed), resumed
    assert_nothing_lost(r, spanning={registered[a1]: anchors[0]})
    checks = chain_checks(r.tap)[registered[a1]]  # the second crash is spanned too
    assert any(t0 <= anchors[-1] < t1 for t0, t1, _ in checks), (anchors, [(a, b) for a, b, _ in checks])


@pytest.mark.slow
def test_a_host_crash_and_restart(tmp_path: Path) -> None:
    """tests/missions/hosts.yaml: h2 killed at 16 s, restarted at 22 s. The agents it ran are recovered on the
    others within 10 s simulated (host failure detection + Alg. 8), h2 rejoins, the mission completes."""
    r = run_mission_file(MISSIONS / "hosts.yaml", tmp_path / "out")
    assert_completed(r)
    kill = next(i for i, x in enumerate(r.lines) if "h2 crashes (SIGKILL of its haa-hostd)" in x)
    t_kill = r.mm_ss(r.lines[kill])
    crashed = [x for x in r.lines[kill:] if re.search(r"\) crashed on h2", x)]
    assert crashed, r.text
    for x in crashed:
        name, kind = x.split()[1:3]
        rec = next((y for y in r.lines if y.split()[1:3] == [name, kind] and " recovered by h" in y
                    and r.mm_ss(y) >= r.mm_ss(x)), None)
        assert rec is not None and "recovered by h2" not in rec, (x, rec, r.text)
        assert r.mm_ss(rec) - t_kill <= 10, (x, rec)
    restart = next(i for i, x in enumerate(r.lines) if "h2 restarts and joins" in x)
    assert any(x.endswith("h2 joined") for x in r.lines[restart:]), r.text
    assert_nothing_lost(r)


@pytest.mark.slow
def test_graceful_leaves_of_the_hosts_of_supervisor_slam_and_executive_mission(tmp_path: Path) -> None:
    """tests/missions/leave.yaml + run-time choices: h4 joins (8 s), the host running SupervisorSLAM leaves
    (from 14 s), the host running ExecutiveMission leaves (from 30 s). Their agents are frozen and thawed
    elsewhere — no crash, no recovery — and the mission completes."""
    act = leave_host_of((14.0, "supervisor_slam"), (30.0, "executive_mission"))
    r = run_mission_file(MISSIONS / "leave.yaml", tmp_path / "out", act=act)
    assert_completed(r)
    for type_name, kind in (("supervisor_slam", "SupervisorSLAM"), ("executive_mission", "ExecutiveMission")):
        host = r.tap.fired.get(type_name)
        assert host, f"the host of {type_name} did not leave"
        left = next(i for i, x in enumerate(r.lines) if f"{host} has left" in x)
        retires = next(i for i, x in enumerate(r.lines) if f"{host} retires (graceful leave)" in x)
        moved = [x for x in r.lines[retires:left + 1] if f"({kind}) freezing on {host}" in x]
        assert moved, (kind, host, r.text)
        name = moved[0].split()[1]
        assert any(f"{name} ({kind}) thawed by" in x for x in r.lines[retires:]), (kind, r.text)
    assert "h4 joined" in r.text
    assert not re.search(r"crashed on|recovered by|failed on", r.text), r.text
    assert_nothing_lost(r)
