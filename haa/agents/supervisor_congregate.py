"""SupervisorCongregate (thesis App. III L3059-3075; Table 6.2-1 L1190): gathers the team around the
congregation point.

"When the congregation point is identified SupervisorCongregate requests control of all avatars and assigns
them targets at equally spaced intervals around the congregation point." ExecutiveMission spawns it when the
congregation point's landmark is in the map (`slam/landmarks`); it bids `team.BID_CONGREGATE` (10, above
SupervisorExplore's 1: docs/team.md) on every active avatar, so it gains control of all of them.

Slots (thesis gap 8, ours): `n` points on a circle of `radius_m` around the landmark's estimate, equally
spaced. The mission ends when the last avatar is on its slot, so the ring's turn and the matching of avatars
to slots minimise the longest drive (a bottleneck assignment; ties by the total), measured along the path
planner's weighted paths on the published map (`CostMap.cost_field`, one search per avatar), not in straight
lines: among the rings whose every slot is a passable cell, turned from the team's centroid in steps of a
twelfth of the slot spacing (widened only if none fits), the one whose matching ends soonest. An avatar
is on its slot when it reports the slot reached or its estimate is within `tolerance_m`; when all are, it
writes `congregate/status` {"done": true} and ExecutiveMission ends the mission. Slots are placed again when
the landmark's estimate moves by more than `replace_m`, the team changes or an avatar finds its slot
unreachable.

Recovery: "Restore configuration and retrieve Avatar* statuses, reassign targets if appropriate": RECOVERY =
"backup" (the targets sent, the next target id; haa.agents.team.SupervisorBase) — after recovery the
controlled set is read again from `assign/` and every controlled avatar gets its slot again; a thawed one
(a transfer) keeps its controlled set and its targets.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pydantic
from scipy.optimize import linear_sum_assignment

from haa.agents import team
from haa.control.pathplanner import CostMap, PlannerConfig
from haa.sdk.registry import register
from haa.slam.replica import decode_map


class CongregateConfig(team.TeamConfig):
    landmark: int
    radius_m: float = pydantic.Field(0.6, gt=0, le=10)
    tolerance_m: float = pydantic.Field(0.15, gt=0, le=2)
    check_s: float = pydantic.Field(1.0, gt=0, le=60)
    #: the avatars' radius (the largest of the team): a slot must be a passable cell for it
    avatar_radius: float = pydantic.Field(0.12, gt=0, le=2)
    #: the slots are placed again when the congregation point's estimate moves farther than this
    replace_m: float = pydantic.Field(0.3, gt=0, le=10)


def slots(centre: tuple[float, float], n: int, radius: float,
          towards: tuple[float, float], turn: float = 0.0) -> list[tuple[float, float]]:
    """`n` equally spaced points on the circle around `centre`, the first in the direction of `towards`
    turned by `turn` rad."""
    a0 = math.atan2(towards[1] - centre[1], towards[0] - centre[0]) + turn
    return [(centre[0] + radius * math.cos(a0 + 2 * math.pi * k / n),
             centre[1] + radius * math.sin(a0 + 2 * math.pi * k / n)) for k in range(n)]


def bottleneck_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a perfect matching of a square cost matrix that minimises the largest cost, and among
    those the total (an entry may be inf: never chosen while a finite matching exists). The least threshold t
    for which the entries <= t hold a perfect matching is found by bisection over the sorted entries, each
    test a linear assignment of 0/1 costs; then the least total within t."""
    n = cost.shape[0]
    if n == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    finite = np.isfinite(cost)
    values = np.unique(cost[finite])
    if len(values) == 0:
        return linear_sum_assignment(np.zeros_like(cost))

    def feasible(t: float) -> bool:
        over = np.where(finite & (cost <= t), 0.0, 1.0)
        r, c = linear_sum_assignment(over)
        return float(over[r, c].sum()) == 0.0

    lo, hi = 0, len(values) - 1
    if not feasible(values[hi]):  # no finite perfect matching: the least total of what is finite
        big = float(values[-1]) * 10 * n + 1.0
        return linear_sum_assignment(np.where(finite, cost, big))
    while lo < hi:
        mid = (lo + hi) // 2
        if feasible(values[mid]):
            hi = mid
        else:
            lo = mid + 1
    t = values[lo]
    big = float(values[-1]) * 10 * n + 1.0
    return linear_sum_assignment(np.where(finite & (cost <= t), cost, big))


def placeable_ring(centre: tuple[float, float], n: int, radius: float, towards: tuple[float, float],
                   ok: Callable[[tuple[float, float]], bool], steps: int = 12,
                   grow: tuple[float, ...] = (0.0, 0.15, 0.3),
                   score: Callable[[list[tuple[float, float]]], Any] | None = None) -> list[tuple[float, float]]:
    """The ring of `slots` whose every slot `ok` accepts (a passable cell of the map, not where an avatar
    found its slot unreachable): the ring is turned by fractions of the slot spacing, then widened, in that
    order. Without `score` the first fit is taken (the one nearest the plain ring); with it, the fit of the
    least radius with the least `score` (ties: the least turn). None fits: the ring with the most good slots,
    each bad one moved out along its ray."""
    best: tuple[int, list[tuple[float, float]]] | None = None
    for extra in grow:
        fits: list[tuple[Any, list[tuple[float, float]]]] = []
        for k in range(steps):
            # 0, +1/steps, -1/steps, +2/steps, ... of the spacing: the least turn first
            j = (k + 1) // 2 * (1 if k % 2 else -1)
            turn = 2 * math.pi / n * j / steps
            ring = slots(centre, n, radius + extra, towards, turn)
            good = sum(1 for p in ring if ok(p))
            if good == n:
                if score is None:
                    return ring
                fits.append((score(ring), ring))
            if best is None or good > best[0]:
                best = (good, ring)
        if fits:
            return min(fits, key=lambda f: f[0])[1]  # min keeps the first (least turn) of equal scores
    # no ring fits: the one with the most good slots, each bad slot moved out along its ray (up to 0.6 m
    # farther) to the first point that is good
    assert best is not None
    out = []
    for p in best[1]:
        q = p
        if not ok(p):
            d = math.dist(p, centre) or 1.0
            ux, uy = (p[0] - centre[0]) / d, (p[1] - centre[1]) / d
            for step in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6):
                cand = (p[0] + ux * step, p[1] + uy * step)
                if ok(cand):
                    q = cand
                    break
        out.append(q)
    return out


@register
class SupervisorCongregate(team.SupervisorBase):
    TYPE = "supervisor_congregate"
    TASK = "congregate"
    CONFIG = CongregateConfig
    COST = 0.02
    RECOVERY = "backup"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: CongregateConfig
        self.centre: tuple[float, float] | None = None
        self.done = False
        self.bad: list[tuple[float, float]] = []  # slots an avatar found unreachable
        self.extent: tuple[float, float, float, float] | None = None  # the map's x0, y0, width, height
        self.arrived: dict[str, Any] = {}  # avatar -> tid of the slot it reported reached
        self.costmap: CostMap | None = None  # the planner's costs on the map last read (_slot_test)

    def priority(self, avatar: str) -> float:
        return team.BID_CONGREGATE

    async def begin(self, how: str) -> None:
        if how == "recover":  # every controlled avatar gets its slot again (a thaw keeps what it had sent)
            self.targets = {}
        if how != "thaw":
            await team.transcript(self, "requesting control of all avatars")
        await self.start_bidding()
        self.every(self.cfg.check_s, self._check)

    async def on_avatars_changed(self) -> None:
        self.centre = None  # recompute the slots for the new team
        await self._check()

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        a = msg.get("avatar")
        t = self.targets.get(a)
        if t is None or msg.get("tid") != t.get("tid"):
            return
        if msg.get("op") == "reached":
            self.arrived[a] = t["tid"]
            await team.transcript(self, f"{a} reached its slot")
        elif msg.get("op") == "unreachable":
            await team.transcript(self, f"{a} cannot reach its slot ({t['x']:.2f}, {t['y']:.2f})")
            self.bad.append((t["x"], t["y"]))  # place the ring where this slot is not
            self.targets.pop(a, None)
            self.centre = None

    def _inside(self, x: float, y: float) -> tuple[float, float]:
        if self.extent is None:
            return (x, y)
        x0, y0, w, h = self.extent
        m = min(self.cfg.radius_m, w / 2, h / 2)
        return (min(max(x, x0 + m), x0 + w - m), min(max(y, y0 + m), y0 + h - m))

    async def _slot_test(self) -> Callable[[tuple[float, float]], bool]:
        """Whether a point can be a slot: a passable cell of the published map for the avatars' radius (inside
        the arena, clear of known obstacles) and not near a slot found unreachable."""
        data = await self.ddb_get(team.K_SLAM_MAP)
        cm = None
        if data is not None:
            spec, prob = decode_map(data)
            self.extent = (spec.x0, spec.y0, spec.width, spec.height)
            cm = CostMap(prob, spec, PlannerConfig(radius=self.cfg.avatar_radius))
        self.costmap = cm

        def ok(p: tuple[float, float]) -> bool:
            if any(math.dist(p, b) < 0.2 for b in self.bad):
                return False
            if cm is None:
                return True
            cell = cm.cell(*p)
            return cell is not None and bool(cm.passable[cell])

        return ok

    def _drive_cost(self, starts: list[tuple[float, float]]
                    ) -> Callable[[list[tuple[float, float]]], np.ndarray]:
        """cost(points)[i, k]: how far avatar i drives to point k — the path planner's weighted path length
        on the map last read (one search from each avatar), the straight line where there is no map or
        an avatar's estimate is off it (a point no path reaches costs inf)."""
        cm = self.costmap
        fields = [cm.cost_field(s) if cm is not None else None for s in starts]
        fields = [f if f is not None and np.isfinite(f).any() else None for f in fields]  # off the map: a line

        def cost(points: list[tuple[float, float]]) -> np.ndarray:
            out = np.empty((len(starts), len(points)))
            for i, s in enumerate(starts):
                f = fields[i]
                for k, p in enumerate(points):
                    cell = cm.cell(*p) if cm is not None and f is not None else None
                    out[i, k] = f[cell] if f is not None and cell is not None else math.dist(s, p)
            return out

        return cost

    async def _check(self) -> None:
        if self.done or not self.controlled:
            return
        lms = await team.get_json(self, team.K_SLAM_LANDMARKS, {})
        lm = lms.get(str(self.cfg.landmark))
        ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {})
        pos = {a: (ests[a]["x"], ests[a]["y"]) for a in self.controlled if a in ests}
        if lm is None or not pos:
            return
        # an estimate outside the arena is wrong: the point is inside, at least a slot radius from the walls
        # when the arena allows (the map's extent is the arena's)
        ok = await self._slot_test()  # reads the map (and the arena's extent from it)
        c = self._inside(float(lm[0]), float(lm[1]))
        if self.centre is None or math.dist(c, self.centre) > self.cfg.replace_m or set(pos) != set(self.targets):
            self.centre = c
            names = sorted(pos)
            mean = tuple(np.mean([pos[a] for a in names], axis=0))
            drive = self._drive_cost([pos[a] for a in names])

            def makespan(ring: list[tuple[float, float]]) -> tuple[float, float]:
                cost = drive(ring)
                r, k = bottleneck_assignment(cost)
                return (float(cost[r, k].max()), float(cost[r, k].sum()))

            pts = placeable_ring(c, len(names), self.cfg.radius_m, (float(mean[0]), float(mean[1])), ok,
                                 score=makespan)
            cost = drive(pts)
            rows, cols = bottleneck_assignment(cost)
            for r, k in zip(rows, cols, strict=True):
                self.send_target(names[r], *pts[k])
            await team.transcript(self, "slots around ({:.2f}, {:.2f}): ".format(*c) + ", ".join(
                f"{a} to ({self.targets[a]['x']:.2f}, {self.targets[a]['y']:.2f})" for a in names))
            await self.ddb_write([team.op_put_json(team.K_TARGETS + a, {**self.targets[a], "supervisor": self.id,
                                                                        "task": self.TASK}) for a in names])
            self.backup()
        # on its slot: the avatar drove there (it reported the slot reached) or its estimate is within tolerance
        on_slot = [a for a, t in self.targets.items() if a in pos
                   and (self.arrived.get(a) == t["tid"] or math.dist(pos[a], (t["x"], t["y"])) <= self.cfg.tolerance_m)]
        if self.targets and len(on_slot) == len(self.controlled):
            self.done = True
            await team.transcript(self, f"every avatar on its slot ({len(on_slot)})")
            await team.put_json(self, "congregate/status", {"done": True, "t": round(self.now(), 3),
                                                            "avatars": sorted(on_slot)})
