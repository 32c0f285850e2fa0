"""SupervisorCongregate (thesis App. III L3059-3075; Table 6.2-1 L1190): gathers the team around the
congregation point.

"When the congregation point is identified SupervisorCongregate requests control of all avatars and assigns
them targets at equally spaced intervals around the congregation point." ExecutiveMission spawns it when the
congregation point's landmark is in the map (`slam/landmarks`); it bids `team.BID_CONGREGATE` (10, above
SupervisorExplore's 1: docs/team.md) on every active avatar, so it gains control of all of them.

Slots (thesis gap 8, ours): `n` points on a circle of `radius_m` around the landmark's estimate, the first
towards the team's centroid, equally spaced; avatars are matched to slots by least total distance
(Hungarian). An avatar is on its slot when its estimate is within `tolerance_m`; when all are, it writes
`congregate/status` {"done": true} and ExecutiveMission ends the mission. Slots are recomputed when the
landmark estimate moves by more than `tolerance_m` or the team changes.

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
from haa.agents.registry import register
from haa.control.pathplanner import CostMap, PlannerConfig
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


def placeable_ring(centre: tuple[float, float], n: int, radius: float, towards: tuple[float, float],
                   ok: Callable[[tuple[float, float]], bool], steps: int = 12,
                   grow: tuple[float, ...] = (0.0, 0.15, 0.3)) -> list[tuple[float, float]]:
    """The ring of `slots` whose every slot `ok` accepts (a passable cell of the map, not where an avatar
    found its slot unreachable): the ring is turned by fractions of the slot spacing, then widened, in that
    order (the first fit is the one nearest the plain ring); the plain ring if none fits."""
    best: tuple[int, list[tuple[float, float]]] | None = None
    for extra in grow:
        for k in range(steps):
            # 0, +1/steps, -1/steps, +2/steps, ... of the spacing: the least turn first
            j = (k + 1) // 2 * (1 if k % 2 else -1)
            turn = 2 * math.pi / n * j / steps
            ring = slots(centre, n, radius + extra, towards, turn)
            good = sum(1 for p in ring if ok(p))
            if good == n:
                return ring
            if best is None or good > best[0]:
                best = (good, ring)
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

    def priority(self, avatar: str) -> float:
        return team.BID_CONGREGATE

    async def on_start(self) -> None:
        await self._begin()

    async def on_resume(self, how: str) -> None:
        if how == "recover":  # every controlled avatar gets its slot again (a thaw keeps what it had sent)
            self.targets = {}
        await self._begin(announce=how != "thaw")

    async def _begin(self, announce: bool = True) -> None:
        team.use_mission_clock(self, self.cfg)
        if announce:
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

        def ok(p: tuple[float, float]) -> bool:
            if any(math.dist(p, b) < 0.2 for b in self.bad):
                return False
            if cm is None:
                return True
            cell = cm.cell(*p)
            return cell is not None and bool(cm.passable[cell])

        return ok

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
            pts = placeable_ring(c, len(names), self.cfg.radius_m, (float(mean[0]), float(mean[1])), ok)
            cost = np.array([[math.dist(pos[a], p) for p in pts] for a in names])
            rows, cols = linear_sum_assignment(cost)
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
