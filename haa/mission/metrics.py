"""Mission metrics (issue 15 §3): the published map against the simulator's ideal map, localization error,
time averages of hosts, agents and CPU, and the team's counters.

Map. ExecutiveMission's team publishes its occupancy grid as the DDB blob `slam/map`
(`haa.slam.replica.encode_map`; docs/team.md). `decode_published_map` turns it into (GridSpec, p(C) per cell)
and `align_to_grid` samples it at the cells of haa-sim's ideal grid (GroundTruth.OccupancyGrid: origin (0, 0),
rows = y, cells of `map_resolution`), nearest cell, 0.5 (unknown) outside the published map.

    map coverage = Σ_region |c − 0.5| / Σ_region |c_ideal − 0.5|        (7.1-1)
    map accuracy = 1 − Σ_region |c − c_ideal| / (# cells of the region)   (7.1-2)

(haa.slam.metrics). The *mission region* (thesis gap 15: undefined) is the reachable cells (the explorable mask:
free cells 4-connected to a start pose) plus the occupied cells that border them (the walls and obstacle faces
the avatars can see) — `mission_region`. The ideal map is the simulator's true occupancy there, every cell a
surface passes through marked occupied (haa-sim's surface grid; docs/team.md, "Map metrics"): 0 or 1 in
every cell of the region, so coverage ≤ 1 and a blank map scores accuracy 0.5 (L1476). `explored_share` is
the mission's completion measure: the share of the *reachable* cells past the thresholds (p > 0.73 or
p < 0.27, L1186).

Localization. `PoseHistory` keeps the true poses polled from haa-sim; an estimate `slam/est/<avatar>` stamped
`t` is compared with the true pose interpolated at `t` (`pose_samples`), and `position_error` is the mean over
avatars of each avatar's mean error.

Time averages. `Samples` holds what the runner polled over mission time; `time_average` weights each polled
value by the simulated time until the next sample (step function), over [start, end].
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from haa.slam.grid import GridSpec
from haa.slam.metrics import explored, map_accuracy, map_coverage

# ---------------------------------------------------------------------------------------------- the map


def fallback_decode_map(data: bytes) -> tuple[GridSpec, np.ndarray]:
    """Stand-in for `haa.slam.replica.decode_map` while that module is absent: a JSON header line
    `{"width", "height", "resolution", "x0", "y0"}` then the float32 p(C) cells, row-major (rows = y).
    `fallback_encode_map` writes it (tests)."""
    import json

    head, sep, body = bytes(data).partition(b"\n")
    if not sep:
        raise ValueError("published map: no header line")
    h = json.loads(head)
    spec = GridSpec(float(h["width"]), float(h["height"]), float(h.get("resolution", 0.1)),
                    float(h.get("x0", 0.0)), float(h.get("y0", 0.0)))
    rows, cols = spec.shape
    prob = np.frombuffer(body, dtype=np.float32)
    if prob.size != rows * cols:
        raise ValueError(f"published map: {prob.size} cells, the header says {rows} x {cols}")
    return spec, prob.reshape(rows, cols).copy()


def fallback_encode_map(spec: GridSpec, prob: np.ndarray) -> bytes:
    import json

    head = {"width": spec.width, "height": spec.height, "resolution": spec.resolution, "x0": spec.x0, "y0": spec.y0}
    return json.dumps(head).encode() + b"\n" + np.ascontiguousarray(prob, dtype=np.float32).tobytes()


def map_decoder() -> Callable[[bytes], tuple[GridSpec, np.ndarray]]:
    """`haa.slam.replica.decode_map` when it exists, else `fallback_decode_map`."""
    try:
        from haa.slam.replica import decode_map  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        return fallback_decode_map
    return decode_map  # type: ignore[no-any-return,unused-ignore]


def decode_published_map(data: bytes) -> tuple[GridSpec, np.ndarray]:
    spec, prob = map_decoder()(data)
    return spec, np.asarray(prob, dtype=np.float32)


def align_to_grid(
    spec: GridSpec, prob: np.ndarray, shape: tuple[int, int], resolution: float, origin: tuple[float, float] = (0, 0)
) -> np.ndarray:
    """The published map sampled at the centres of the cells of another grid (`shape` rows x cols,
    `resolution`, lower-left corner `origin`): nearest published cell, 0.5 where the published map does not
    reach."""
    rows, cols = shape
    ys = origin[1] + (np.arange(rows) + 0.5) * resolution
    xs = origin[0] + (np.arange(cols) + 0.5) * resolution
    iy = np.floor((ys - spec.y0) / spec.resolution).astype(int)
    ix = np.floor((xs - spec.x0) / spec.resolution).astype(int)
    prow, pcol = prob.shape
    out = np.full((rows, cols), 0.5, dtype=np.float32)
    oky = (iy >= 0) & (iy < prow)
    okx = (ix >= 0) & (ix < pcol)
    out[np.ix_(oky, okx)] = prob[np.ix_(iy[oky], ix[okx])]
    return out


def mission_region(occupied: np.ndarray, explorable: np.ndarray) -> np.ndarray:
    """Reachable cells plus the occupied cells 8-adjacent to them (module docstring)."""
    reach = explorable.astype(bool)
    grown = reach.copy()
    padded = np.pad(reach, 1)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            grown |= padded[1 + dy : 1 + dy + reach.shape[0], 1 + dx : 1 + dx + reach.shape[1]]
    return reach | (grown & occupied.astype(bool))


@dataclass(frozen=True)
class MapScores:
    coverage: float
    accuracy: float
    explored: float  # share of the reachable cells explored
    region_cells: int
    reachable_cells: int


def map_scores(prob: np.ndarray, occupied: np.ndarray, explorable: np.ndarray) -> MapScores:
    """Eq. 7.1-1 / 7.1-2 over the mission region and the explored share of the reachable cells; `prob` is
    already on the ideal grid (`align_to_grid`)."""
    if prob.shape != occupied.shape or occupied.shape != explorable.shape:
        raise ValueError(f"shapes differ: map {prob.shape}, ideal {occupied.shape}, explorable {explorable.shape}")
    region = mission_region(occupied, explorable)
    ideal = occupied.astype(np.float32)
    reach = explorable.astype(bool)
    n_reach = int(reach.sum())
    share = float(explored(prob)[reach].sum()) / n_reach if n_reach else math.nan
    return MapScores(
        coverage=map_coverage(prob, ideal, region),
        accuracy=map_accuracy(prob, ideal, region),
        explored=share,
        region_cells=int(region.sum()),
        reachable_cells=n_reach,
    )


def expected_cells(explorable: np.ndarray) -> int:
    """What the operator tells ExecutiveMission about the arena: the number of reachable cells."""
    return int(np.count_nonzero(explorable))


# ---------------------------------------------------------------------------------------------- localization


@dataclass
class PoseHistory:
    """True poses of one avatar, (t, x, y, theta) in time order (duplicates of a time are dropped)."""

    t: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, t: float, x: float, y: float, theta: float) -> None:
        if self.t and t <= self.t[-1]:
            return
        self.t.append(t)
        self.poses.append((x, y, theta))

    def at(self, t: float, slack: float = 0.5) -> tuple[float, float, float] | None:
        """The pose at `t`, linearly interpolated (heading along the shorter arc); None outside the history
        (more than `slack` s before its first or after its last sample)."""
        if not self.t or t < self.t[0] - slack or t > self.t[-1] + slack:
            return None
        k = bisect.bisect_left(self.t, t)
        if k <= 0:
            return self.poses[0]
        if k >= len(self.t):
            return self.poses[-1]
        t0, t1 = self.t[k - 1], self.t[k]
        a, b = self.poses[k - 1], self.poses[k]
        f = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
        dth = (b[2] - a[2] + math.pi) % (2 * math.pi) - math.pi
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * dth)


@dataclass
class LocalizationLog:
    """Errors of the published estimates against the true poses, per avatar; each estimate counts once."""

    errors: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)  # avatar -> (t, pos, rot)
    _seen: dict[str, float] = field(default_factory=dict)

    def add(self, avatar: str, est: dict[str, Any], history: PoseHistory) -> bool:
        try:
            t = float(est["t"])
            x, y, th = float(est["x"]), float(est["y"]), float(est.get("theta", 0.0))
        except (KeyError, TypeError, ValueError):
            return False
        if self._seen.get(avatar) == t:
            return False
        truth = history.at(t)
        if truth is None:
            return False
        self._seen[avatar] = t
        pos = math.hypot(x - truth[0], y - truth[1])
        rot = abs((th - truth[2] + math.pi) % (2 * math.pi) - math.pi)
        self.errors.setdefault(avatar, []).append((t, pos, rot))
        return True

    def position_error(self) -> float | None:
        return mean_of_means({a: [e[1] for e in v] for a, v in self.errors.items()})

    def rotation_error(self) -> float | None:
        return mean_of_means({a: [e[2] for e in v] for a, v in self.errors.items()})


def mean_of_means(values: dict[str, Sequence[float]]) -> float | None:
    """Mean over the keys of each key's mean (keys without values are left out); None if nothing."""
    means = [sum(v) / len(v) for v in values.values() if v]
    return sum(means) / len(means) if means else None


# ---------------------------------------------------------------------------------------------- time averages


@dataclass
class Samples:
    """What the mission runner's polling collected, as (simulated mission time, value) series: the group size,
    the active agents, the machine's CPU, the active agents per host, the explored share."""

    hosts: list[tuple[float, float]] = field(default_factory=list)
    agents: list[tuple[float, float]] = field(default_factory=list)
    cpu: list[tuple[float, float]] = field(default_factory=list)
    per_host: list[tuple[float, dict[str, int]]] = field(default_factory=list)
    explored: list[tuple[float, float]] = field(default_factory=list)


def time_average(samples: Iterable[tuple[float, float]], start: float, end: float) -> float | None:
    """Time-weighted average over [start, end] of a step function given by (t, value) samples in time
    order: each value holds until the next sample. Before the first sample nothing is known (that part of the
    interval is left out). None if no sample covers any of the interval."""
    pts = sorted(samples, key=lambda s: s[0])
    if not pts or end <= start:
        return pts[-1][1] if pts and end <= start else None
    total = 0.0
    weight = 0.0
    for i, (t, v) in enumerate(pts):
        t_next = pts[i + 1][0] if i + 1 < len(pts) else end
        a, b = max(t, start), min(t_next, end)
        if b > a:
            total += v * (b - a)
            weight += b - a
    return total / weight if weight > 0 else None


# ---------------------------------------------------------------------------------------------- host events

#: counted from the hosts' agent timelines (haa.hostd: `agent_<event>` log lines, AgentEvents)
TRANSFER_EVENT = "thawed"
RECOVERY_EVENT = "recovered"
FAILURE_EVENTS = ("crashed", "failed")
#: events every member reports for one table change, and crash reports of one failure by several hosts, are
#: merged when they are this close (wall seconds)
DEDUP_WINDOW = 3.0


def agent_event_counts(events: Iterable[dict[str, Any]]) -> dict[str, int]:
    """transfers / recoveries / agent_failures from agent timeline events
    `{"time": wall s, "agent": id, "event": ..., "host": ...}` of every host: a transfer is a thaw, a
    recovery a completed recovery (Alg. 8), a failure a crash (or a give-up, "failed") of an agent — the
    reports of one crash by the host that ran it and by every member at a host's removal count once."""
    transfers = recoveries = failures = 0
    last_fail: dict[str, float] = {}
    for e in sorted(events, key=lambda e: float(e.get("time", 0.0))):
        kind = e.get("event")
        if kind == TRANSFER_EVENT:
            transfers += 1
        elif kind == RECOVERY_EVENT:
            recoveries += 1
        elif kind in FAILURE_EVENTS:
            agent = str(e.get("agent", ""))
            t = float(e.get("time", 0.0))
            prev = last_fail.get(agent)
            last_fail[agent] = t
            if prev is None or t - prev > DEDUP_WINDOW:
                failures += 1
    return {"transfers": transfers, "recoveries": recoveries, "agent_failures": failures}


#: team counters (docs/team.md, `stats/*`) -> results keys
STATS_KEYS = {
    "readings_generated": "readings_generated",
    "readings_processed": "readings_processed",
    "processings": "processings",
    "readings_discarded": "readings_discarded",
}


def stats_counters(stats: dict[str, Any]) -> dict[str, int | None]:
    """`stats/<name>` counters (key without the prefix -> value) as results fields (None when absent)."""
    out: dict[str, int | None] = {}
    for src, dst in STATS_KEYS.items():
        v = stats.get(src)
        out[dst] = int(v) if isinstance(v, int | float) else None
    return out


# ---------------------------------------------------------------------------------------------- results table

#: the rows of Tables 7.1-1 / 7.1-2 (thesis L1390-1403, L1514-1527): (title, results key, scale). "Average #
#: Hosts" counts the simulation computer as the thesis does (hosts_avg_thesis = control hosts + 1); the
#: landmark rows: the team's `slam/landmarks` against the true landmarks (runner.landmark_scores).
THESIS_ROWS: tuple[tuple[str, str, float], ...] = (
    ("Mission Duration [min]", "duration_s", 1 / 60),
    ("Map Coverage [%]*", "coverage", 100.0),
    ("Map Accuracy [%]*", "accuracy", 100.0),
    ("Localization Positional Err [m]", "position_error_m", 1.0),
    ("Localization Rotational Err [rad]", "rotation_error_rad", 1.0),
    ("Landmark Err [m]", "landmark_error_m", 1.0),
    ("Landmark Covariance [m]", "landmark_covariance_m", 1.0),
    ("Average # Hosts", "hosts_avg_thesis", 1.0),
    ("Average # Agents", "agents_avg", 1.0),
    ("Average CPU Usage [%]", "cpu_percent", 1.0),
    ("DDB Size [MB]", "ddb_mb", 1.0),
)
#: ours, below the thesis' rows
EXTRA_ROWS: tuple[tuple[str, str, float], ...] = (
    ("Control hosts (avg)", "hosts_avg", 1.0),
    ("Wall time [min]", "wall_s", 1 / 60),
    ("Uncorrected (dead-reckoning) err [m]", "uncorrected_error_m", 1.0),
    ("Bumps (avatar contacts)", "bumps", 1.0),
    ("Explored share [%]", "explored", 100.0),
    ("Readings generated", "readings_generated", 1.0),
    ("Readings processed", "readings_processed", 1.0),
    ("Processings", "processings", 1.0),
    ("Readings discarded", "readings_discarded", 1.0),
    ("Transfers", "transfers", 1.0),
    ("Recoveries", "recoveries", 1.0),
    ("Agent failures", "agent_failures", 1.0),
)
TABLE_ROWS = THESIS_ROWS + EXTRA_ROWS
#: Forage (Table 7.1-3 adds "Cargo Collected", L1564-1578), then ours; a dotted key reads into a dict
FORAGE_ROWS: tuple[tuple[str, str, float], ...] = (
    ("Cargo Collected", "cargo_collected", 1.0),
    ("Collectables identified", "collectables_identified", 1.0),
    ("Collectables lost", "collectables_lost", 1.0),
    ("Collectables not found", "collectables_missing", 1.0),
    ("SupervisorForage lifetime [min]", "forage_lifetime_s.mean", 1 / 60),
)


def rows_for(results: Sequence[dict[str, Any]]) -> tuple[tuple[str, str, float], ...]:
    """The table's rows for these runs: the forage rows after the thesis' when any run is a forage mission."""
    forage = any("collectables_total" in r for r in results)
    return THESIS_ROWS + (FORAGE_ROWS[:1] if forage else ()) + EXTRA_ROWS + (FORAGE_ROWS[1:] if forage else ())


def scaled(results: dict[str, Any], key: str, scale: float) -> float | None:
    v: Any = results
    for part in key.split("."):
        v = v.get(part) if isinstance(v, dict) else None
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v) * scale


def fmt(v: float | None, title: str = "") -> str:
    """A table cell: '—' for no value; counts as integers; others with 4 significant decimals."""
    if v is None:
        return "—"
    if title and title[0].isupper() and title.split(" ")[0] in ("Readings", "Processings", "Transfers",
                                                                 "Recoveries", "Agent"):
        return f"{v:.0f}"
    if abs(v) >= 100:
        return f"{v:.1f}"
    if abs(v) >= 1:
        return f"{v:.3f}"
    return f"{v:.5f}"


def results_rows(results: dict[str, Any]) -> list[tuple[str, str]]:
    """One run's results as (title, value) rows in the shape of Table 7.1-1 (then our extra rows)."""
    return [(title, fmt(scaled(results, key, scale), title)) for title, key, scale in rows_for([results])]
