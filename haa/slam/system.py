"""JC-SLAM state of a team: one particle filter per avatar, one shared occupancy grid and landmark map.

`SlamSystem` is what the SLAM agents of the control system (and the offline replays) call:

* `add_avatar(name, pose, t0, drift)` — event (a) for that avatar's filter (known start pose, §6.2);
* `predict(name, prediction)` — event (b);
* `process(reading)` — one sensor reading: the particle states at the reading's time are taken from the
  history, the sensor model gives log g per particle against the current map (event (c)) and then updates
  the map at each particle, adjusted by the weights last computed for that block (§5.1.4; weights are not
  recomputed just for a map update — that is what Strategy 1 saves);
* `process(CollectablesReading)` — no density and no map update: the sightings are placed with the particles
  at the reading's time and identified in the collectable map (`collectables`, haa.slam.collectables);
* `request(name)` — a weight request: event (d) at the newest time, then event (e) if n_eff dropped below
  `resample_threshold · N`.

Readings the history cannot serve raise `haa.slam.filter.HistoryError` (too old for the horizon, or newer
than the avatar's newest prediction) and change nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from haa.slam.collectables import GATE, CollectableMap
from haa.slam.filter import Estimate, ParticleFilter
from haa.slam.grid import GridSpec, OccupancyGrid
from haa.slam.motion import Prediction
from haa.slam.resample import normalize_log
from haa.slam.sensors import (
    CollectablesReading,
    CooccupancyModel,
    CooccupancyReading,
    FloorModel,
    FloorReading,
    LandmarkMap,
    LandmarkModel,
    LandmarkReading,
    Reading,
    SonarModel,
    SonarReading,
)


@dataclass
class SlamConfig:
    n_particles: int = 500
    resample_threshold: float = 0.5  # resample when n_eff < threshold · N
    horizon: float = math.inf  # seconds of history kept (readings older are rejected)
    forward_propagation: bool = True  # False: the thesis' NFP variant
    initial_spread: tuple[float, float, float] = (0.02, 0.02, 0.01)  # known start pose, small spread
    sonar: SonarModel = field(default_factory=SonarModel)
    landmark: LandmarkModel = field(default_factory=LandmarkModel)
    cooccupancy: CooccupancyModel = field(default_factory=CooccupancyModel)
    floor: FloorModel = field(default_factory=FloorModel)
    #: seconds within which one avatar's landmark sightings share their pose error (LandmarkMap; inf: one
    #: source per avatar; None: the plain Kalman fusion of every sighting as independent, the library's
    #: model before issue 16). 60 s windows let a 27-min mission pile up ~100 sources per landmark and made
    #: the map overconfident again (docs/slam.md), so the default is one source per avatar.
    landmark_window: float | None = math.inf
    #: chi-square (2 dof) gate on a sighting's innovation before it is fused into the landmark map (None:
    #: off); 13.82 = the 99.9 % quantile. With honest covariances a sighting beyond it comes from a lost
    #: avatar (its density is still applied: it is what re-localizes the avatar)
    landmark_gate: float | None = 13.82
    #: m: a collectable sighting within this distance of an identified collectable's estimate is that one
    #: (the nearest), else a new one — half the arenas' minimum collectable spacing (haa.slam.collectables)
    collectable_gate: float = GATE

    def __post_init__(self) -> None:
        if self.n_particles < 1:
            raise ValueError(f"n_particles: must be >= 1, got {self.n_particles}")
        if not 0 < self.resample_threshold <= 1:
            raise ValueError(f"resample_threshold: must be in (0, 1], got {self.resample_threshold}")
        if not (math.isfinite(self.collectable_gate) and self.collectable_gate > 0):
            raise ValueError(f"collectable_gate: must be a finite distance > 0 m, got {self.collectable_gate}")


@dataclass
class Applied:
    """What processing one reading did."""

    avatar: str
    t: float
    kind: str
    block: int
    density: bool  # False when the reading only updated the map (e.g. a landmark's first sighting)


class SlamSystem:
    """Filters, grid and landmark map of one team (see the module docstring)."""

    def __init__(self, grid: GridSpec, config: SlamConfig | None = None, seed: int = 0) -> None:
        self.config = config or SlamConfig()
        self.grid = OccupancyGrid(grid)
        for m in (self.config.sonar, self.config.cooccupancy, self.config.floor):
            m.resolution = grid.resolution
        self.landmarks = LandmarkMap(self.config.landmark_window, self.config.landmark_gate)
        self.collectables = CollectableMap(self.config.collectable_gate)
        self.filters: dict[str, ParticleFilter] = {}
        self.seed = seed
        self.processed: dict[str, int] = {}

    def add_avatar(
        self, name: str, pose: tuple[float, float, float], t0: float = 0.0, *, seed: int | None = None
    ) -> ParticleFilter:
        """Event (a) for `name`. The filter's noise seed is `seed`, by default seed · 1009 + the number of
        filters (the replica passes its own count of avatars ever added, so that a removal does not make two
        filters share a seed)."""
        if name in self.filters:
            raise ValueError(f"avatar: {name!r} already has a filter")
        c = self.config
        pf = ParticleFilter(
            c.n_particles,
            pose,
            t0,
            spread=c.initial_spread,
            seed=self.seed * 1009 + len(self.filters) if seed is None else seed,
            horizon=c.horizon,
            forward_propagation=c.forward_propagation,
            name=name,
        )
        self.filters[name] = pf
        return pf

    def filter(self, name: str) -> ParticleFilter:
        pf = self.filters.get(name)
        if pf is None:
            raise KeyError(f"avatar: no filter for {name!r}")
        return pf

    def predict(self, name: str, p: Prediction) -> None:
        self.filter(name).predict(p)

    def process(self, r: Reading) -> Applied:
        pf = self.filter(r.avatar)
        states, block = pf.states_at(r.t)  # raises HistoryError before anything changes
        w = block.weights
        log_g: np.ndarray | None
        if isinstance(r, SonarReading):
            log_g = self.config.sonar.apply(r, states, w, self.grid)
        elif isinstance(r, LandmarkReading):
            log_g = self.config.landmark.apply(r, states, w, self.landmarks)
        elif isinstance(r, CooccupancyReading):
            log_g = self.config.cooccupancy.apply(r, states, w, self.grid)
        elif isinstance(r, FloorReading):
            log_g = self.config.floor.apply(r, states, w, self.grid)
        elif isinstance(r, CollectablesReading):
            if np.any(block.log_acc):  # the densities applied to the block so far, folded into a temporary
                with np.errstate(divide="ignore"):
                    w = normalize_log(np.log(w) + block.log_acc)
            self.collectables.apply(r, states, w)
            log_g = None
        else:
            raise TypeError(f"reading: unknown type {type(r).__name__}")
        if log_g is not None:
            pf.correct(r.t, log_g)
        self.processed[r.kind] = self.processed.get(r.kind, 0) + 1
        return Applied(r.avatar, r.t, r.kind, block.index, log_g is not None)

    def request(self, name: str) -> tuple[Estimate, bool]:
        """A weight request for avatar `name` now: estimate (event d), resample if needed (event e)."""
        return self.filter(name).maybe_resample(self.config.resample_threshold)

    def prune(self) -> None:
        for pf in self.filters.values():
            pf.prune()

    def memory_bytes(self) -> int:
        return sum(pf.memory_bytes() for pf in self.filters.values())
