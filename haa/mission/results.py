"""A mission run's results (issue 15 §3): what the runner measures while the mission runs, and what it makes of
it at the end.

`Tally` keeps the measurements: the samples of the group size, the active agents (all and per host), the
machine's CPU and the explored share over mission time (`metrics.Samples`); every avatar's true path, its
odometry's distance from the truth and its bumps; the team's pose estimates against the truth
(`metrics.LocalizationLog`); the ideal maps haa-sim gives and the team's published map, scored against them.
haa.mission.runner.MissionRun keeps one (`run.tally`) and fills it as it polls. At the end `Tally.results`
makes the results dict (REQUIRED_KEYS and more; `provenance` says where the numbers come from) and
`Tally.write` the run folder: transcript.txt and .jsonl, chaos.json, map.png and allocation.png
(haa.mission.plots), map.npz, samples.json and results.json.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from haa.mission import metrics as mm
from haa.mission import plots
from haa.mission import transcript as tr
from haa.mission.plan import mission_duration
from haa.mission.schema import Mission

#: results keys that must be there (issue 15 §3)
REQUIRED_KEYS = (
    "completed", "reason", "duration_s", "wall_s", "coverage", "accuracy", "position_error_m", "hosts_avg",
    "agents_avg", "readings_generated", "readings_processed", "transfers", "recoveries", "agent_failures",
)


@dataclass
class Tally:
    """What a run of `mission` has measured so far (module docstring); maps in cells of `grid_res` m."""

    mission: Mission
    grid_res: float
    samples: mm.Samples = field(default_factory=mm.Samples)
    histories: dict[str, mm.PoseHistory] = field(default_factory=dict)
    #: avatar -> (t, distance between its odometry (dead reckoning) and its true pose), every 0.5 s
    uncorrected: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    #: avatar -> contacts begun with walls, obstacles or avatars (haa-sim "bump"s: pushes odometry misses)
    bumps: dict[str, int] = field(default_factory=dict)
    loc: mm.LocalizationLog = field(default_factory=mm.LocalizationLog)
    occ: np.ndarray | None = None  # the ideal map (surface rule)
    occ_half: np.ndarray | None = None  # cells at least half inside a solid
    explorable: np.ndarray | None = None
    expected: int = 0  # reachable cells
    map_prob: np.ndarray | None = None  # the team's published map on the ideal map's cells
    map_scores: mm.MapScores | None = None
    map_scores_half: mm.MapScores | None = None
    files: dict[str, str] = field(default_factory=dict)  # the run folder's files (after `write`)

    # ------------------------------------------------------------------ while it runs
    def ideal_map(self, occ: np.ndarray, explorable: np.ndarray, surface: bytes) -> None:
        """haa-sim's grid at `grid_res` (GroundTruth.OccupancyGrid: half-cell occupancy, the explorable mask,
        the surface cells)."""
        # the ideal map of eq. 7.1-1/7.1-2: every cell a surface passes through (docs/team.md, "Map metrics");
        # the half-cell rule's map is scored too (`accuracy_half_cells`)
        self.occ_half, self.explorable = occ.copy(), explorable.copy()
        cells = np.frombuffer(surface, dtype=np.uint8)
        self.occ = cells.reshape(occ.shape).copy() if cells.size == occ.size else occ.copy()
        self.expected = mm.expected_cells(explorable)

    def avatar_pose(self, t: float, a: Any) -> int:
        """An active avatar at haa-sim time `t` (sim_pb2 AvatarState: true pose, odometry, bumps); its bump
        count if it bumped into something since the last call, else 0."""
        self.histories.setdefault(a.avatar_id, mm.PoseHistory()).add(t, a.pose.x, a.pose.y, a.pose.theta)
        bumped = 0
        if a.bumps > self.bumps.get(a.avatar_id, 0):
            bumped = self.bumps[a.avatar_id] = a.bumps
        unc = self.uncorrected.setdefault(a.avatar_id, [])
        # haa-sim's odometry starts at the start pose: the same frame as the truth
        if a.HasField("odometry") and (not unc or t >= unc[-1][0] + 0.5):
            unc.append((round(t, 3), round(math.hypot(a.odometry.x - a.pose.x, a.odometry.y - a.pose.y), 4)))
        return bumped

    def estimates(self, ests: dict[str, Any]) -> None:
        """The team's estimates `slam/est/<avatar>` ({avatar: value}) against the true paths."""
        for avatar, est in ests.items():
            if isinstance(est, dict) and avatar in self.histories:
                self.loc.add(avatar, est, self.histories[avatar])

    def score_map(self, data: bytes) -> str:
        """The team's published map `slam/map`, scored against the ideal maps; '' or why it could not be read."""
        assert self.occ is not None and self.explorable is not None
        try:
            spec, prob = mm.decode_published_map(data)
        except Exception as e:
            return str(e)
        self.map_prob = mm.align_to_grid(spec, prob, self.occ.shape, self.grid_res)
        self.map_scores = mm.map_scores(self.map_prob, self.occ, self.explorable)
        if self.occ_half is not None:
            self.map_scores_half = mm.map_scores(self.map_prob, self.occ_half, self.explorable)
        return ""

    # ------------------------------------------------------------------ at the end
    def results(self, completed: bool, reason: str, *, status: dict[str, Any], start_t: float, end_t: float,
                now: float, speed: float, stats: dict[str, Any], agent_events: list[dict[str, Any]],
                ddb_size: int | None, truth_calls: dict[str, int] | None,
                landmarks: tuple[float | None, float | None], chaos: dict[str, Any] | None, errors: list[str],
                wall_start: float) -> dict[str, Any]:
        """The results dict: `status` is the last `mission/status` ({} if none), [start_t, end_t] the mission
        time the averages are over, `now` haa-sim's clock, `stats` the team's counters (`stats/*`),
        `agent_events` the hosts' agent timeline, `landmarks` (mean error, mean standard deviation) of the
        team's landmark estimates, `chaos` the chaos plan's summary; `errors` is the run's list, shared (what
        `write` adds to it is in results.json)."""
        spec = self.mission.spec
        sc = self.map_scores
        hosts_avg = mm.time_average(self.samples.hosts, start_t, end_t)
        agents_avg = mm.time_average(self.samples.agents, start_t, end_t)
        cpu = mm.time_average(self.samples.cpu, start_t, end_t)
        lm_err, lm_std = landmarks
        return {
            "mission": spec.name,
            "scenario": spec.scenario,
            "completed": bool(completed),
            "reason": reason,
            "duration_s": round(mission_duration(status or None, now), 3),
            "wall_s": round(time.time() - wall_start, 3),
            "speed": speed,
            "seed": spec.seed,
            "coverage": rounded(sc.coverage if sc else None),
            "accuracy": rounded(sc.accuracy if sc else None),
            "accuracy_half_cells": rounded(self.map_scores_half.accuracy if self.map_scores_half else None),
            "explored": rounded(sc.explored if sc else status.get("explored")),
            "explored_reported": status.get("explored"),
            "position_error_m": rounded(self.loc.position_error()),
            "rotation_error_rad": rounded(self.loc.rotation_error()),
            "bumps": sum(self.bumps.values()),
            "uncorrected_error_m": rounded(mm.mean_of_means({a: [e[1] for e in v]
                                                             for a, v in self.uncorrected.items()})),
            "landmark_error_m": rounded(lm_err),
            "landmark_covariance_m": rounded(lm_std),
            "hosts_avg": rounded(hosts_avg),
            "hosts_avg_thesis": rounded(hosts_avg + 1 if hosts_avg is not None else None),
            "agents_avg": rounded(agents_avg),
            "cpu_percent": rounded(cpu),
            **mm.stats_counters(stats),
            **mm.agent_event_counts(agent_events),
            "ddb_mb": rounded(ddb_size / 1e6 if ddb_size is not None else None),
            "sim_truth_calls": truth_calls,
            "chaos": chaos,
            "expected_cells": self.expected,
            "region_cells": sc.region_cells if sc else None,
            "estimates": sum(len(v) for v in self.loc.errors.values()),
            "status": status or None,
            "errors": errors,
            "provenance": provenance(self.mission),
            "cpu_count": os.cpu_count(),
        }

    def write(self, out: Path, results: dict[str, Any], lines: Sequence[tr.Line], *, chaos: dict[str, Any] | None,
              clock: tr.ClockMap, members: list[str], runner_lines: Sequence[tr.Line]) -> None:
        """The run folder `out`: the transcript `lines`, `chaos` (chaos.json), the PNGs (with the group
        `members` and the runner's own `runner_lines` on the timeline), map.npz, samples.json (with the `clock`)
        and results.json; `results` gets their paths as "files"."""
        (out / "transcript.txt").write_text("".join(ln.format() + "\n" for ln in lines))
        if chaos is not None:
            (out / "chaos.json").write_text(json.dumps(chaos, indent=1) + "\n")
        with open(out / "transcript.jsonl", "w") as f:
            for ln in lines:
                f.write(json.dumps(ln.to_json()) + "\n")
        self.files = {"transcript": str(out / "transcript.txt")}
        spec = self.mission.spec
        try:
            self.files["map_png"] = str(plots.plot_maps(
                out / "map.png", self.occ, self.explorable, self.map_prob, self.grid_res, self.map_scores,
                self.histories, self.loc.errors, f"mission {spec.name} (seed {spec.seed})"))
            self.files["timeline_png"] = str(plots.plot_timeline(out / "allocation.png", self.samples, members,
                                                                 runner_lines, spec.name))
        except ImportError as e:  # matplotlib missing
            results["errors"].append(f"no PNGs: {e}")
        # the final map beside the ideal one, for offline scoring and plots (a map implies the ideal one)
        if self.map_prob is not None and self.occ is not None and self.explorable is not None:
            np.savez_compressed(out / "map.npz", prob=self.map_prob, ideal=self.occ, explorable=self.explorable,
                                ideal_half_cells=self.occ_half if self.occ_half is not None else self.occ,
                                resolution=self.grid_res)
            self.files["map_npz"] = str(out / "map.npz")
        results["files"] = dict(self.files)
        (out / "samples.json").write_text(json.dumps(self.samples_json(clock)))
        (out / "results.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
        results["files"]["results"] = str(out / "results.json")

    def samples_json(self, clock: tr.ClockMap) -> dict[str, Any]:
        """samples.json: the polled samples, the clock map, and per avatar over mission time the SLAM estimate's
        position error, the odometry's, and the true poses (one per 0.25 s of haa-sim time), for plots."""
        loc = {a: [[round(t, 3), round(pos, 4)] for t, pos, _rot in v] for a, v in self.loc.errors.items()}
        unc = {a: [list(e) for e in v] for a, v in self.uncorrected.items()}
        truth: dict[str, list[list[float]]] = {}
        for a, h in self.histories.items():
            rows = truth.setdefault(a, [])
            for t, (x, y, th) in zip(h.t, h.poses, strict=True):
                if not rows or t >= rows[-1][0] + 0.25:
                    rows.append([round(t, 3), round(x, 4), round(y, 4), round(th, 4)])
        return {"samples": dataclasses.asdict(self.samples), "clock": clock.to_json(), "position_error": loc,
                "uncorrected_error": unc, "truth": truth}


def landmark_scores(est: Any, truth: dict[int, tuple[float, float]]) -> tuple[float | None, float | None]:
    """(mean distance of the team's landmark estimates `slam/landmarks` ({id: [x, y, sd, ...]}) from the true
    landmarks, mean of their published standard deviations): the thesis' "Landmark Err" and "Landmark
    Covariance" rows of Table 7.1-1, over the landmarks the team has estimated. (None, None) when there are
    none."""
    if not isinstance(est, dict) or not est:
        return None, None
    errs, stds = [], []
    for lid, v in est.items():
        try:
            x, y, sd = (float(a) for a in v[:3])
            true = truth[int(lid)]
        except (ValueError, TypeError, KeyError, IndexError):
            continue
        errs.append(math.dist((x, y), true))
        stds.append(sd)
    if not errs:
        return None, None
    return sum(errs) / len(errs), sum(stds) / len(stds)


def rounded(v: Any, digits: int = 6) -> Any:
    """A float rounded to `digits` (None if not finite); anything else as it is."""
    if isinstance(v, float):
        return round(v, digits) if math.isfinite(v) else None
    return v


def provenance(mission: Mission) -> dict[str, Any]:
    """Where the numbers come from: commit, mission file hash, seed, machine."""
    repo = Path(__file__).resolve().parents[2]
    commit = dirty = None
    try:
        commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip() or None
        dirty = bool(subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                                    capture_output=True, text=True, timeout=5, check=True).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        pass
    if mission.path is not None and Path(mission.path).is_file():
        digest = hashlib.sha256(Path(mission.path).read_bytes()).hexdigest()
    else:
        digest = hashlib.sha256(mission.spec.model_dump_json().encode()).hexdigest()
    return {
        "commit": commit,
        "dirty": dirty,
        "mission_file": str(mission.path) if mission.path else None,
        "mission_sha256": digest,
        "seed": mission.spec.seed,
        "machine": {
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
    }
