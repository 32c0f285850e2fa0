"""Offline replays of a recording through one strategy (experiments AP-5.1 and AP-5.2, thesis §7.2.5).

`replay(rec, strategy, capacity, n_particles, seed)` builds a fresh `SlamSystem` (one filter per avatar,
started at the known start poses), runs the recording's event stream through `haa.slam.strategies.run`
and measures

* localization error: at every weight request, the distance between the avatar's weighted estimate and its
  true pose (mean over all requests of all avatars; the heading error likewise), next to the uncorrected
  (dead-reckoning) error at the same instants;
* readings processed, share processed out of order, mean processing delay, resampling and processing rates
  (from `RunStats`);
* observations per weight update (AP-5.2) and the landmark error and covariance;
* map coverage and accuracy (eq. 7.1-1, 7.1-2) against the ideal map: the same sensor models run on the
  true poses ("an ideal map generated with zero localization error", §7.1), cached per recording.

Processing capacity (`calibrate`): `WORKERS` processors per reading kind (the thesis' system runs sensor
processing agents per type); each kind costs its measured per-reading cost at `REF_PARTICLES` particles
(`COST_MS`, from `haactl bench slam` on the development machine) times a factor of its own, found by
bisection so that Discard processes the wanted share of that kind's readings (0.9 nominal, 0.5
constrained, as in §7.2.5.1). The same capacity is then used for every strategy and particle count of that
scenario, as the thesis did. The clock is simulated, so results do not depend on the machine's load.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from haa.slam.filter import Estimate, ParticleFilter
from haa.slam.metrics import explored_fraction, map_accuracy, map_coverage, pose_error
from haa.slam.recording import Recording
from haa.slam.sensors import LandmarkModel, SonarModel
from haa.slam.strategies import Capacity, discard_share, run, strategy
from haa.slam.system import SlamConfig, SlamSystem

#: per-reading processing cost in ms at REF_PARTICLES particles, measured by `haactl bench slam` (thread CPU
#: time, 2-core dev machine): a 5-echo sonar scan, a camera image's landmark sightings, a co-occupancy
#: reading; the floor region is not in the recordings (an estimate: a template twice the co-occupancy's)
COST_MS: dict[str, float] = {"sonar": 2.0, "landmark": 0.27, "cooccupancy": 0.48, "floor": 1.0}
REF_PARTICLES = 500
WORKERS = 2  # processors per reading kind


def config_for(rec: Recording, n_particles: int, forward_propagation: bool = True) -> SlamConfig:
    """The SLAM configuration a recording is replayed with (sensor noise as the recording states)."""
    return SlamConfig(
        n_particles=n_particles,
        forward_propagation=forward_propagation,
        sonar=SonarModel(resolution=rec.grid.resolution, mount_radius=rec.sonar_mount_radius),
        landmark=LandmarkModel(range_frac=rec.landmark_range_frac, sigma_bearing=rec.landmark_sigma_bearing),
    )


def _bisect(share_at: Callable[[float], float], share: float) -> float:
    """Factor at which `share_at` (decreasing, a step function) is closest to `share`."""
    lo, hi = 1e-3, 1e7  # factor: lo processes everything, hi almost nothing
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if share_at(mid) > share:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.0005:
            break
    return lo if abs(share_at(lo) - share) <= abs(share_at(hi) - share) else hi


def calibrate(
    rec: Recording,
    share: float,
    workers: int = WORKERS,
    cost_ms: dict[str, float] | None = None,
    per_kind: bool = True,
) -> Capacity:
    """Capacity under which Discard processes `share` of the readings.

    per_kind (default): each kind has `workers` processors and its cost is its measured cost times a factor of
    its own, so that Discard processes `share` of that kind's readings; otherwise one shared pool and one
    factor for all. The share is a step function of the factor (arrivals are periodic): the closer side of
    the step is taken.
    """
    if not 0 < share < 1:
        raise ValueError(f"share: must be in (0, 1), got {share}")
    base = {k: v / 1000.0 for k, v in (cost_ms or COST_MS).items()}
    arrivals = rec.readings
    for kind in {r.kind for r in arrivals}:
        if kind not in base:
            raise ValueError(f"cost_ms: no cost for reading kind {kind!r}")
    if not per_kind:
        shared = Capacity(workers, base, per_kind=False)
        return shared.scaled(_bisect(lambda f: discard_share(arrivals, shared.scaled(f)), share))
    cost = dict(base)
    for kind in sorted({r.kind for r in arrivals}):

        def share_at(f: float, kind: str = kind) -> float:
            return discard_share(arrivals, Capacity(workers, {**cost, kind: base[kind] * f}), kind)

        cost[kind] = base[kind] * _bisect(share_at, share)
    return Capacity(workers, cost)


_IDEAL: dict[tuple[Any, ...], np.ndarray] = {}


def ideal_map(rec: Recording) -> np.ndarray:
    """The map the same sensor models make from the true poses (zero localization error), cached."""
    key = (rec.arena, rec.team, rec.seed, rec.duration, rec.grid, len(rec.readings), len(rec.predictions))
    if key in _IDEAL:
        return _IDEAL[key]
    system = SlamSystem(rec.grid, config_for(rec, 1), seed=0)
    for a in rec.avatars:
        pf = ParticleFilter(1, a.start, 0.0, name=a.name)
        tr = rec.truth[a.name]
        for t, pose in zip(tr.times, tr.poses, strict=True):
            if t > pf.time:
                pf.insert(t, np.asarray([pose], dtype=np.float64))
        system.filters[a.name] = pf
    for r in sorted(rec.readings, key=lambda r: r.t):
        system.process(r)
    if len(_IDEAL) > 8:
        _IDEAL.clear()
    _IDEAL[key] = system.grid.prob()
    return _IDEAL[key]


@dataclass
class ReplayResult:
    scenario: str
    strategy: str
    condition: str  # nominal | constrained | unlimited
    n_particles: int
    seed: int
    loc_error: float  # m, mean over weight requests
    heading_error: float  # rad
    uncorrected_error: float  # m, dead reckoning at the same instants
    stats: dict[str, Any] = field(default_factory=dict)
    obs_per_update: float = math.nan
    landmark: dict[str, float] = field(default_factory=dict)
    map_coverage: float = math.nan
    map_accuracy: float = math.nan
    explored: float = math.nan
    wall_s: float = 0.0

    def row(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "strategy": self.strategy,
            "condition": self.condition,
            "n_particles": self.n_particles,
            "seed": self.seed,
            "loc_error_m": self.loc_error,
            "heading_error_rad": self.heading_error,
            "uncorrected_error_m": self.uncorrected_error,
            "obs_per_update": self.obs_per_update,
            "map_coverage": self.map_coverage,
            "map_accuracy": self.map_accuracy,
            "explored": self.explored,
            "wall_s": self.wall_s,
            **self.landmark,
            **self.stats,
        }


def replay(
    rec: Recording,
    strategy_name: str,
    capacity: Capacity | None,
    n_particles: int,
    seed: int = 0,
    *,
    condition: str = "",
    request_period: float = 1.0,
    with_map: bool = True,
) -> ReplayResult:
    """Replay `rec` through one strategy; see the module docstring for what is measured."""
    strat = strategy(strategy_name)
    t0 = time.perf_counter()
    system = SlamSystem(rec.grid, config_for(rec, n_particles, strat.forward_propagation), seed=seed)
    for a in rec.avatars:
        system.add_avatar(a.name, a.start, 0.0)
    errs: list[float] = []
    herrs: list[float] = []
    unc: list[float] = []

    def on_request(avatar: str, t: float, est: Estimate, resampled: bool) -> None:
        truth = rec.truth[avatar].at(t)
        e, h = pose_error(est.pose, truth)
        errs.append(e)
        herrs.append(h)
        unc.append(pose_error(rec.odometry[avatar].at(t), truth)[0])

    stats = run(rec.events(request_period), strat, capacity, system, seed=seed, on_request=on_request)
    obs = [m for pf in system.filters.values() for m in pf.obs_per_update]
    counts = {
        "corrections": sum(pf.corrections for pf in system.filters.values()),
        "weight_updates": sum(pf.weight_updates for pf in system.filters.values()),
        "weight_requests": sum(pf.weight_requests for pf in system.filters.values()),
        "obs_in_updates": int(sum(obs)),
    }
    res = ReplayResult(
        scenario=rec.team,
        strategy=strategy_name,
        condition=condition or ("unlimited" if capacity is None else "custom"),
        n_particles=n_particles,
        seed=seed,
        loc_error=float(np.mean(errs)) if errs else math.nan,
        heading_error=float(np.mean(herrs)) if herrs else math.nan,
        uncorrected_error=float(np.mean(unc)) if unc else math.nan,
        stats={**stats.row(), **counts},
        obs_per_update=float(np.mean(obs)) if obs else math.nan,
        landmark=system.landmarks.errors(rec.landmarks),
    )
    if with_map:
        ideal = ideal_map(rec)
        c = system.grid.prob()
        region = rec.region if rec.region is not None else None
        res.map_coverage = map_coverage(c, ideal, region)
        res.map_accuracy = map_accuracy(c, ideal, region)
        res.explored = explored_fraction(c, region)
    res.wall_s = time.perf_counter() - t0
    return res
