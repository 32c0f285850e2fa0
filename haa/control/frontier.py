"""Coordinated frontier exploration (Burgard, Moors, Stachniss, Schneider 2005, "Coordinated multi-robot
exploration", IEEE T-RO 21(3)): the second exploration strategy of issue 15, beside the thesis' EM split
(App. III L3077-3079, haa.control.explore).

* **Frontier cells**: known-free cells (p < 0.27, haa.slam.metrics) with an unknown 8-neighbour
  (0.27 ≤ p ≤ 0.73) that the avatars can reach (haa.control.explore.reachable_mask). The cells under the
  avatars count as free (co-occupancy, thesis L2973: where an avatar is there is no obstacle), so a blank map
  at mission start has frontiers around each avatar.
* **Cost** V_i(t): the travel cost from avatar i to frontier cell t over the path planner's weighted cost
  grid (haa.control.pathplanner: obstacle-closeness penalty, unknown-cell factor), one Dijkstra sweep per
  avatar (scikit-image `MCP_Geometric.find_costs` without ends).
* **Utility** U_t: 1 for every frontier cell at the start of an assignment round.
* **Assignment** (the paper's Table I): repeat until every avatar has a target — pick the pair
  (i, t) = argmax over unassigned avatars and frontier cells of U_t − β V_i(t); give t to i; lower the
  utility of every frontier cell t' by P(‖t − t'‖), with P(d) = 1 − d / range for d < range, else 0
  (the paper's linear estimate of the chance that t' is seen from t; `range` the camera's effective range,
  Table 6.2-4). Costs are normalised to [0, 1] by the largest finite cost of any avatar to any frontier cell,
  so that β = 1 weighs "a fresh frontier" against "the farthest frontier" equally (the paper leaves the
  scale of V to the implementation).
An avatar that reaches no frontier cell gets None.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from skimage.graph import MCP_Geometric

from haa.control.explore import reachable_mask
from haa.control.pathplanner import CostMap, PlannerConfig, as_probabilities
from haa.slam.grid import GridSpec, OccupancyGrid
from haa.slam.metrics import EXPLORED_HIGH, EXPLORED_LOW

XY = tuple[float, float]


@dataclass(frozen=True)
class FrontierConfig:
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    beta: float = 1.0  # weight of the (normalised) cost against the utility
    range: float = 3.0  # m: utility reduction radius (basic camera's effective range, Table 6.2-4)
    coordinate: bool = True  # False: no utility reduction (every avatar picks its own best frontier)


@dataclass
class FrontierAssignment:
    targets: dict[str, XY | None]
    frontier: np.ndarray  # (rows, cols) bool: the frontier cells
    count: int

    @property
    def done(self) -> bool:
        return self.count == 0


def frontier_cells(p: np.ndarray, cm: CostMap, positions: list[XY], reach: np.ndarray | None = None) -> np.ndarray:
    """Known-free reachable cells next to unknown ones (the avatars' own cells count as free)."""
    free = p < EXPLORED_LOW
    res = cm.spec.resolution
    rows, cols = p.shape
    rr, cc = np.ogrid[0:rows, 0:cols]
    for x, y in positions:
        k = (cm.cfg.radius + 0.5 * res) / res
        r0, c0 = (y - cm.spec.y0) / res - 0.5, (x - cm.spec.x0) / res - 0.5
        free |= ((rr - r0) ** 2 + (cc - c0) ** 2 <= k * k) & ~cm.obstacle
    unknown = (p >= EXPLORED_LOW) & (p <= EXPLORED_HIGH)
    near_unknown = cv2.dilate(unknown.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if reach is None:
        reach = reachable_mask(cm, positions)
    return free & near_unknown & reach


def assign_frontiers(
    prob: np.ndarray | OccupancyGrid,
    avatars: dict[str, XY],
    spec: GridSpec | None = None,
    config: FrontierConfig | None = None,
) -> FrontierAssignment:
    """One target per avatar by coordinated frontier exploration (see the module docstring)."""
    cfg = config or FrontierConfig()
    p, spec = as_probabilities(prob, spec)
    cm = CostMap(p, spec, cfg.planner)
    names = list(avatars)
    pos = [(float(avatars[a][0]), float(avatars[a][1])) for a in names]
    front = frontier_cells(p, cm, pos)
    fr, fc = np.nonzero(front)
    targets: dict[str, XY | None] = {a: None for a in names}
    if len(fr) == 0 or not names:
        return FrontierAssignment(targets, front, len(fr))
    res = cm.spec.resolution
    fxy = np.c_[cm.spec.x0 + (fc + 0.5) * res, cm.spec.y0 + (fr + 0.5) * res]
    # V_i(t): one Dijkstra sweep per avatar over the planner's costs
    V = np.full((len(names), len(fr)), np.inf)
    for i, (x, y) in enumerate(pos):
        s = cm.cell(x, y)
        if s is None:
            continue
        s2 = cm._snap(s, cm.passable)
        if s2 is None:
            continue
        costs = np.where(cm.passable, cm.base_cost, np.inf)
        cum, _ = MCP_Geometric(costs, fully_connected=True).find_costs([s2])
        V[i] = cum[fr, fc] * res
    finite = np.isfinite(V)
    if not finite.any():
        return FrontierAssignment(targets, front, len(fr))
    Vn = np.where(finite, V / max(float(V[finite].max()), 1e-9), np.inf)
    U = np.ones(len(fr))
    left = set(range(len(names)))
    while left:
        best, bi, bt = -math.inf, -1, -1
        for i in sorted(left):
            score = U - cfg.beta * Vn[i]
            t = int(np.argmax(score))
            if score[t] > best:
                best, bi, bt = float(score[t]), i, t
        if bi < 0 or not math.isfinite(best):
            break  # the avatars left reach no frontier
        targets[names[bi]] = (float(fxy[bt, 0]), float(fxy[bt, 1]))
        left.discard(bi)
        if cfg.coordinate:
            d = np.hypot(fxy[:, 0] - fxy[bt, 0], fxy[:, 1] - fxy[bt, 1])
            U = U - np.where(d < cfg.range, 1.0 - d / cfg.range, 0.0)
    return FrontierAssignment(targets, front, len(fr))
