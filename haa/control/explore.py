"""SupervisorExplore's core: the EM split of the unexplored reachable cells, one target per avatar.

Thesis App. III (L3077-3079): "Carries out the exploration task by directing avatars to unexplored regions.
Unexplored cells are divided between avatars using an Expectation-Maximization (EM) algorithm. Once the cells
are divided each avatar is assign[ed] a target within their area." The features, K, initialisation, cell set,
target choice and cadence are not given (thesis gap 7); ours (docs/control.md):

* **Cells.** Unexplored = 0.27 ≤ p(C) ≤ 0.73 (the complement of "explored", L1186; haa.slam.metrics).
  Reachable = in a connected component of the planner's passable cells (not known-occupied, clear of known
  obstacles by the avatar radius; haa.control.pathplanner) that holds an avatar. Only unexplored reachable
  cells are split: a region behind a closed wall or in a gap too narrow for the avatar is nobody's.
* **EM.** Hard EM of a Gaussian mixture over the cells' (x, y) centres with K = the number of avatars,
  isotropic equal covariances and equal weights — i.e. k-means (Lloyd): E-step, each cell to the nearest
  component mean; M-step, each mean to its cells' centroid; until no cell changes. The means start at the
  avatars' positions (avatars at the same spot are nudged apart by one cell). We tried soft EM with full
  covariances first: with free mixing weights it settles in very unequal regions (one avatar with 89 % of
  the large arena when the team starts in a row), with fixed weights it needs ~150 iterations and can still
  empty a middle component; the hard, isotropic form gives compact regions of similar size in 2-40
  iterations. The regions are then matched to the avatars by least total avatar-to-region-mean distance
  (Hungarian), since a mean may have drifted nearer another avatar.
* **Target.** Within avatar k's region: the region's cell nearest to the region's mean (its centre of
  mass; the mean itself may be on an obstacle or in another region), or with `target="nearest"` the region's
  cell nearest to the avatar. Either way the target is a passable, reachable, unexplored cell.
* **Cadence** is the agent's business (the supervisor recomputes when an avatar reaches its target, when the
  team changes, or periodically); this function is stateless and deterministic.

An avatar whose region is empty (fewer unexplored cells than avatars) gets no target (None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment  # scipy comes with scikit-image

from haa.control.pathplanner import CostMap, PlannerConfig, as_probabilities
from haa.slam.grid import GridSpec, OccupancyGrid
from haa.slam.metrics import EXPLORED_HIGH, EXPLORED_LOW

XY = tuple[float, float]


@dataclass(frozen=True)
class ExploreConfig:
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    max_iter: int = 300
    max_cells: int = 8_000  # EM is fitted on at most this many cells (a deterministic regular subsample)
    target: Literal["centroid", "nearest"] = "centroid"


@dataclass(frozen=True)
class Region:
    avatar: str
    cells: int  # unexplored reachable cells assigned
    mean: XY | None
    target: XY | None


@dataclass
class Split:
    regions: dict[str, Region]
    labels: np.ndarray  # (rows, cols) int: avatar index per unexplored reachable cell, -1 elsewhere
    unexplored: int  # unexplored reachable cells in all
    iterations: int
    avatars: list[str] = field(default_factory=list)

    @property
    def done(self) -> bool:
        """Nothing reachable is left to explore."""
        return self.unexplored == 0

    def targets(self) -> dict[str, XY | None]:
        return {a: r.target for a, r in self.regions.items()}


def reachable_mask(cm: CostMap, positions: list[XY]) -> np.ndarray:
    """Passable cells connected (8-neighbours) to an avatar's cell (or to the passable cell nearest it)."""
    passable = cm.passable.astype(np.uint8)
    _n, lab = cv2.connectedComponents(passable, connectivity=8)
    keep: set[int] = set()
    for x, y in positions:
        rc = cm.cell(x, y)
        if rc is None:
            continue
        snapped = cm._snap(rc, cm.passable)  # an avatar inside the inflation still reaches its component
        if snapped is not None:
            keep.add(int(lab[snapped]))
    keep.discard(0)
    return np.isin(lab, sorted(keep)) & cm.passable


def em_split(X: np.ndarray, seeds: np.ndarray, max_iter: int = 300) -> tuple[np.ndarray, np.ndarray, int]:
    """Hard EM of an isotropic, equal-weight Gaussian mixture (k-means, Lloyd) of points X (n, 2) from means
    `seeds` (K, 2): E-step, each point to its nearest mean; M-step, each mean to its points' centroid; until
    no point changes component. A component left without points restarts at the point farthest from its
    mean (so every avatar keeps a region while there are enough cells). Returns (labels, means, iterations).
    """
    mu = seeds.astype(float).copy()
    lab: np.ndarray | None = None
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` is returned
        d = ((X[:, None, :] - mu[None]) ** 2).sum(axis=2)
        new = d.argmin(axis=1)
        if lab is not None and np.array_equal(new, lab):
            break
        lab = new
        for k in range(len(mu)):
            m = lab == k
            if m.any():
                mu[k] = X[m].mean(axis=0)
            else:
                far = int(d[np.arange(len(X)), lab].argmax())
                mu[k] = X[far]
                lab[far] = k
    assert lab is not None
    return lab, mu, it


def split_unexplored(
    prob: np.ndarray | OccupancyGrid,
    avatars: dict[str, XY],
    spec: GridSpec | None = None,
    config: ExploreConfig | None = None,
    costmap: CostMap | None = None,
) -> Split:
    """Divide the unexplored reachable cells between `avatars` (name → (x, y)) and pick one target each."""
    cfg = config or ExploreConfig()
    p, spec = as_probabilities(prob, spec)
    cm = costmap or CostMap(p, spec, cfg.planner)
    names = list(avatars)
    pos = [(float(avatars[a][0]), float(avatars[a][1])) for a in names]
    labels = np.full(p.shape, -1, dtype=int)
    if not names:
        return Split({}, labels, 0, 0, [])
    reach = reachable_mask(cm, pos)
    unexplored = (p >= EXPLORED_LOW) & (p <= EXPLORED_HIGH) & reach
    rr, cc = np.nonzero(unexplored)
    n = len(rr)
    res = cm.spec.resolution
    X = np.c_[cm.spec.x0 + (cc + 0.5) * res, cm.spec.y0 + (rr + 0.5) * res]
    if n == 0:
        return Split({a: Region(a, 0, None, None) for a in names}, labels, 0, 0, names)
    # avatars at the same spot: nudge them apart (one cell, in distinct directions) so the components can split
    seeds = np.array(pos, dtype=float)
    for k in range(1, len(seeds)):
        while any(np.allclose(seeds[k], seeds[j], atol=1e-6) for j in range(k)):
            ang = 2.0 * math.pi * k / len(seeds)
            seeds[k] += res * np.array([math.cos(ang), math.sin(ang)])
    if len(names) == 1:
        lab, its = np.zeros(n, dtype=int), 0
    else:
        # fit on a regular subsample of at most max_cells cells, then label every cell by its nearest mean
        step = max(1, math.ceil(n / cfg.max_cells))
        _, mu, its = em_split(X[::step], seeds, cfg.max_iter)
        lab = ((X[:, None, :] - mu[None]) ** 2).sum(axis=2).argmin(axis=1)
        # region k goes to the avatar it suits best: least total avatar-to-region-mean distance
        used = np.unique(lab)
        cost = np.full((len(names), len(mu)), 1e9)
        cost[:, used] = np.hypot(*(np.asarray(pos)[:, None, :] - mu[None, used]).transpose(2, 0, 1))
        rows, cols = linear_sum_assignment(cost)
        perm = np.empty(len(mu), dtype=int)
        perm[cols] = rows
        lab = perm[lab]
    labels[rr, cc] = lab
    regions: dict[str, Region] = {}
    for k, a in enumerate(names):
        m = lab == k
        cnt = int(m.sum())
        if cnt == 0:
            regions[a] = Region(a, 0, None, None)
            continue
        pts = X[m]
        mean = pts.mean(axis=0)
        ref = mean if cfg.target == "centroid" else np.asarray(pos[k])
        i = int(np.argmin(((pts - ref) ** 2).sum(axis=1)))
        regions[a] = Region(a, cnt, (float(mean[0]), float(mean[1])), (float(pts[i, 0]), float(pts[i, 1])))
    return Split(regions, labels, n, its, names)
