"""AgentPathPlanner's core: a weighted-distance path over the current occupancy map.

Thesis App. III (L2955-2957): "Accepts a target position and orientation and attempts to plan a path through
clear spaces using the available map data. The path uses a weighted distance algorithm that penalizes
routes that are too close to obstacles." The cost function, grid and replanning rate are not given (thesis
gap 10); ours, documented in docs/control.md:

1. **Cells.** A cell with p(C) ≥ `occupied` is an obstacle; p(C) ≤ `free` is known free; anything between is
   unknown. Other avatars (the planner "requests the list of avatars" from ExecutiveAvatar, L2965) can be
   passed as discs and count as obstacles.
2. **Distance.** d = distance (m) from each cell centre to the nearest obstacle cell (OpenCV's exact
   Euclidean distance transform of the obstacle mask; the arena's outside counts as obstacle).
3. **Inflation.** A cell with d < `radius` (the avatar's radius) cannot hold the avatar's centre: it is
   impassable. Exception: the avatar has to be able to leave where it is, so the inflated cells within
   `radius` of the start are passable (at the highest penalty).
4. **Penalty.** A passable cell costs per metre travelled
   `1 + clearance_weight · ((clearance − (d − radius)) / clearance)²` while d − radius < `clearance`, else 1:
   a route near obstacles is longer in cost, so the planner takes a wide passage over a narrow one unless
   the detour is long.
5. **Unknown cells** (the documented rule): passable, with the cost multiplied by `unknown_factor`
   (default 1.5): exploration targets lie in unexplored space, so an optimistic planner is needed, but
   known-free routes are preferred. `unknown="blocked"` makes unknown cells impassable (a cautious mode).
   Unknown cells never count as obstacles for the distance transform.
6. **Search.** scikit-image's `MCP_Geometric` (Dijkstra on the 8-connected grid; a move costs the mean of its
   two cells times its length), from the start cell to the target cell.
7. **Target.** A target on an impassable cell is moved to the nearest passable cell within `snap` metres
   (reported in `Plan.target`); farther, the plan fails with reason "target blocked".
8. **Simplification.** The cell path is string-pulled: from each waypoint the next is the farthest path cell
   whose straight segment crosses no cell costlier than the costliest cell of the original path between
   them — so the simplified route never runs closer to obstacles than the cell path did. Waypoints are cell
   centres in metres, the last one the (snapped) target itself.

An unreachable target is a result (`Plan.ok` False with a reason), never an exception.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from skimage.graph import MCP_Geometric

from haa.slam.grid import GridSpec, OccupancyGrid

XY = tuple[float, float]


@dataclass(frozen=True)
class PlannerConfig:
    radius: float = 0.12  # m: the avatar's radius (haa.sim.avatars: seeker 0.12, sweeper 0.20)
    clearance: float = 0.3  # m beyond the radius over which closeness to obstacles is penalized
    clearance_weight: float = 8.0  # cost added per metre at zero clearance
    occupied: float = 0.65  # p(C) at or above: obstacle
    free: float = 0.35  # p(C) at or below: known free
    unknown: Literal["penalize", "blocked"] = "penalize"
    unknown_factor: float = 1.5
    snap: float = 0.3  # m: how far a blocked target may be moved to a passable cell
    avoid_margin: float = 0.05  # m added around other avatars' discs

    def __post_init__(self) -> None:
        if not (self.radius >= 0 and self.clearance >= 0 and self.clearance_weight >= 0):
            raise ValueError("PlannerConfig: radius, clearance and clearance_weight must be >= 0")
        if not 0 < self.free < self.occupied <= 1:
            raise ValueError("PlannerConfig: need 0 < free < occupied <= 1")
        if self.unknown_factor < 1:
            raise ValueError("PlannerConfig.unknown_factor: must be >= 1")


@dataclass(frozen=True)
class Plan:
    ok: bool
    reason: str  # "" when ok; else "start outside the map", "target outside the map", "target blocked", ...
    waypoints: list[XY] = field(default_factory=list)  # metres, after the start, ending at `target`
    target: XY | None = None  # the target used (snapped when the requested one was blocked)
    heading: float | None = None  # the requested final orientation, passed through
    length: float = 0.0  # m along the waypoints from the start
    cost: float = math.inf  # weighted cost of the cell path
    cells: int = 0  # cells on the unsimplified path
    seconds: float = 0.0  # planning time


def as_probabilities(prob: np.ndarray | OccupancyGrid, spec: GridSpec | None) -> tuple[np.ndarray, GridSpec | None]:
    """(cell occupancy probabilities, grid spec) of a grid or a probability array (`spec` wins if given)."""
    if isinstance(prob, OccupancyGrid):
        return prob.prob(), prob.spec if spec is None else spec
    return np.asarray(prob, dtype=float), spec


class CostMap:
    """The planner's cost grid for one map state (reuse it for several plans on the same map)."""

    def __init__(
        self,
        prob: np.ndarray | OccupancyGrid,
        spec: GridSpec | None = None,
        config: PlannerConfig | None = None,
        avoid: list[tuple[float, float, float]] | None = None,
    ) -> None:
        if isinstance(prob, OccupancyGrid):
            spec = prob.spec if spec is None else spec
            p = prob.prob()
        else:
            p = np.asarray(prob, dtype=float)
        if spec is None:
            raise ValueError("CostMap: give the GridSpec of a probability array")
        if p.ndim != 2 or p.shape != spec.shape:
            raise ValueError(f"CostMap: map shape {p.shape} does not match the grid {spec.shape}")
        self.spec = spec
        self.cfg = cfg = config or PlannerConfig()
        res = spec.resolution
        self.obstacle = p >= cfg.occupied
        self.unknown = (p > cfg.free) & ~self.obstacle
        obst = self.obstacle.copy()
        if avoid:
            rr, cc = np.mgrid[0 : p.shape[0], 0 : p.shape[1]]
            cx, cy = spec.x0 + (cc + 0.5) * res, spec.y0 + (rr + 0.5) * res
            for ax, ay, ar in avoid:
                obst |= np.hypot(cx - ax, cy - ay) <= ar + cfg.avoid_margin
        # distance (m) from each cell centre to the nearest obstacle cell's near edge (centre to centre less
        # half a cell: an obstacle may fill its cell up to the edge; a thin panel or the arena's wall does);
        # the outside of the map is obstacle
        padded = np.pad((~obst).astype(np.uint8), 1, constant_values=0)
        self.dist = np.maximum(
            cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1] * res - 0.5 * res, 0.0)
        slack = self.dist - cfg.radius
        pen = np.zeros_like(slack)
        if cfg.clearance > 0:
            s = np.clip((cfg.clearance - slack) / cfg.clearance, 0.0, 1.0)
            pen = cfg.clearance_weight * s * s
        cost = 1.0 + pen
        if cfg.unknown == "penalize":
            cost = np.where(self.unknown, cost * cfg.unknown_factor, cost)
        self.passable = (slack >= 0) & ~obst
        if cfg.unknown == "blocked":
            self.passable &= ~self.unknown
        self.max_cost = float((1.0 + cfg.clearance_weight) * (cfg.unknown_factor if cfg.unknown == "penalize" else 1))
        self.base_cost = cost
        self.free_space = ~obst  # cells the avatar's centre may be in when escaping the inflation

    def cell(self, x: float, y: float) -> tuple[int, int] | None:
        s = self.spec
        c = math.floor((x - s.x0) / s.resolution)
        r = math.floor((y - s.y0) / s.resolution)
        rows, cols = s.shape
        return (r, c) if 0 <= r < rows and 0 <= c < cols else None

    def centre(self, r: int, c: int) -> XY:
        s = self.spec
        return (s.x0 + (c + 0.5) * s.resolution, s.y0 + (r + 0.5) * s.resolution)

    def _snap(self, rc: tuple[int, int], passable: np.ndarray) -> tuple[int, int] | None:
        if passable[rc]:
            return rc
        k = math.ceil(self.cfg.snap / self.spec.resolution)
        r0, c0 = rc
        rows, cols = passable.shape
        lo_r, hi_r, lo_c, hi_c = max(0, r0 - k), min(rows, r0 + k + 1), max(0, c0 - k), min(cols, c0 + k + 1)
        win = passable[lo_r:hi_r, lo_c:hi_c]
        if not win.any():
            return None
        rr, cc = np.nonzero(win)
        d2 = (rr + lo_r - r0) ** 2 + (cc + lo_c - c0) ** 2
        i = int(np.argmin(d2))
        if d2[i] * self.spec.resolution**2 > self.cfg.snap**2 + 1e-12:
            return None
        return (int(rr[i] + lo_r), int(cc[i] + lo_c))

    def _from(self, s: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(passable, cost) for a search from cell `s`: the inflated (not occupied) cells within one radius of
        the start become passable at the highest penalty when the start itself is not (rule 3's escape)."""
        passable = self.passable
        cost = self.base_cost
        if not passable[s]:
            rows, cols = passable.shape
            rr, cc = np.ogrid[0:rows, 0:cols]
            k = (self.cfg.radius + self.spec.resolution) / self.spec.resolution
            near = (rr - s[0]) ** 2 + (cc - s[1]) ** 2 <= k * k
            passable = passable | (near & self.free_space & (~self.unknown if self.cfg.unknown == "blocked" else True))
            cost = np.where(near & ~self.passable, self.max_cost, cost)
        return passable, cost

    def cost_field(self, start: XY) -> np.ndarray:
        """The weighted cost of the best path from `start` to every cell, in metres (a clear, known-free cell
        costs 1 per metre; rules 4-5 weigh the rest): the same search as `plan`, to all cells at once (one
        Dijkstra for many targets). inf where no path leads, everywhere when the start is outside the map or
        on an obstacle."""
        s = self.cell(*start)
        if s is None or self.obstacle[s]:
            return np.full(self.spec.shape, np.inf)
        passable, cost = self._from(s)
        cum, _ = MCP_Geometric(np.where(passable, cost, np.inf), fully_connected=True).find_costs([s])
        return np.asarray(cum) * self.spec.resolution

    def plan(self, start: XY, target: XY, heading: float | None = None) -> Plan:
        """A path from `start` to `target` (metres, arena frame); see the module docstring."""
        t0 = time.perf_counter()
        done = lambda ok, why, **kw: Plan(ok, why, heading=heading, seconds=time.perf_counter() - t0, **kw)  # noqa: E731
        s = self.cell(*start)
        if s is None:
            return done(False, "start outside the map")
        g = self.cell(*target)
        if g is None:
            return done(False, "target outside the map")
        if self.obstacle[s]:
            return done(False, "start on an obstacle")
        passable, cost = self._from(s)
        gs = self._snap(g, passable)
        if gs is None:
            return done(False, "target blocked")
        costs = np.where(passable, cost, np.inf)
        mcp = MCP_Geometric(costs, fully_connected=True)
        cum, _ = mcp.find_costs([s], [gs], find_all_ends=True)
        total = float(cum[gs])
        if not math.isfinite(total):
            return done(False, "unreachable")
        path = [(int(p[0]), int(p[1])) for p in mcp.traceback(gs)]
        tgt = target if gs == g else self.centre(*gs)
        pts = self._simplify(path, costs)
        wps = [self.centre(*rc) for rc in pts[1:-1]] + [(float(tgt[0]), float(tgt[1]))]
        length, prev = 0.0, (float(start[0]), float(start[1]))
        for w in wps:
            length += math.dist(prev, w)
            prev = w
        return done(
            True, "", waypoints=wps, target=(float(tgt[0]), float(tgt[1])), length=length, cost=total, cells=len(path)
        )

    def _line(self, a: tuple[int, int], b: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Cells a straight segment between two cell centres passes (dense sampling, both ends included)."""
        n = 2 * max(abs(b[0] - a[0]), abs(b[1] - a[1])) + 1
        t = np.linspace(0.0, 1.0, n + 1)
        r = np.floor(a[0] + 0.5 + t * (b[0] - a[0])).astype(int)
        c = np.floor(a[1] + 0.5 + t * (b[1] - a[1])).astype(int)
        # a segment that passes exactly through a cell corner touches the diagonal neighbours too
        r2 = np.floor(a[0] + 0.5 + t * (b[0] - a[0]) - 1e-9).astype(int)
        c2 = np.floor(a[1] + 0.5 + t * (b[1] - a[1]) - 1e-9).astype(int)
        return np.r_[r, r2, r, r2], np.r_[c, c2, c2, c]

    def _simplify(self, path: list[tuple[int, int]], costs: np.ndarray) -> list[tuple[int, int]]:
        if len(path) <= 2:
            return path
        pc = np.array([costs[rc] for rc in path])
        out = [path[0]]
        i = 0
        n = len(path)
        while i < n - 1:
            j = i + 1
            run_max = max(pc[i], pc[j])
            best = j
            while j + 1 < n:
                j += 1
                run_max = max(run_max, pc[j])
                r, c = self._line(path[i], path[j])
                if np.max(costs[r, c]) > run_max + 1e-9:
                    break
                best = j
            out.append(path[best])
            i = best
        return out


def plan_path(
    prob: np.ndarray | OccupancyGrid,
    start: XY,
    target: XY,
    heading: float | None = None,
    spec: GridSpec | None = None,
    config: PlannerConfig | None = None,
    avoid: list[tuple[float, float, float]] | None = None,
) -> Plan:
    """One plan on a map (an OccupancyGrid, or p(C) per cell with its GridSpec); see CostMap."""
    return CostMap(prob, spec, config, avoid).plan(start, target, heading)
