"""SupervisorForage (thesis App. III L3085-3087; §7.1.3 L1545-1549): brings one collectable to a collection region.

"Each SupervisorForage agent is assigned a single collectible to pick up and deposit in a collection region. The
SupervisorForage bids on suitable avatar resources until it gains control of an avatar." With its avatar it
moves to the collectable, picks it up, moves to the *nearest* collection region, drops it off, and "is finished
and retires" (L1545-1547). Config: the team's id of the collectable (`forage/collectables`, written by
SupervisorSLAM) and the collection regions (predefined: the operator knows them, like the arena's bounds).

* **Bids** (docs/team.md "Forage: SupervisorForage"): only on *suitable* avatars — carrying capacity >= 1 in
  the avatar registry (`team.capacity`: sweeper, carrier) — at `team.forage_priority(d)` = BID_FORAGE_BASE +
  BID_FORAGE_RANGE / (1 + d), d the path planner's weighted path length (m) on the published map from the
  collectable's estimate to the avatar's (straight line where the map gives none): above SupervisorExplore's
  1, below SupervisorCongregate's 10, the nearer the higher (L1549: "adjust their priority based on the
  distance between the avatar and the collectable"). Bids are written again when an avatar's priority moves
  by more than `rebid_delta`.
* **One avatar.** When it controls avatars it keeps the nearest, claims the collectable with it and withdraws
  its other bids in one atomic batch; the bid on the avatar it holds becomes BID_FORAGE_HOLD (9), above any
  forage bid, so no other SupervisorForage takes it over (no thrashing as distances change) and only
  SupervisorCongregate could (it then waits, still holding the claim and its bid).
* **Steps**, each written to `forage/state/<id>` = {"state", "holder", "avatar", "x", "y", "t", ...}:
  seen (bidding) -> claimed (driving to it; pick_up) -> carried (driving to the drop point; drop) ->
  deposited (with the deletion of its bids, in one atomic batch; then it stops). The first write is a
  compare-and-set "must not exist": a second SupervisorForage of the same collectable finds another holder
  and stops without doing anything. Drop point: a passable cell at least `region_margin` inside a
  region, the one of least path cost from the avatar's estimate (so the nearest region by path).
* **Failures.** Its avatar retires carrying it: haa-sim puts it down where the avatar stood; the avatar agent
  writes its last pose estimate and cargo in its registry entry, and the collectable is "seen" again at that
  pose (the supervisor bids anew, fetching it from there). Its avatar crashes carrying it: the collectable
  stays on the crashed avatar — "lost" (terminal). Its avatar leaves before the pick-up: "seen", bid again.
  A pick-up that finds nothing in reach is tried at `pick_attempts` points around the estimate, then the
  avatar is released for `retry_s`.

Recovery ("Restore configuration and retrieve Avatar* status, reassign target if appropriate"): RECOVERY =
"backup"; the backup holds the step and the avatar; `forage/state/<id>` and the avatar's registry entry
(cargo, last drop, how it left) decide what happened while it was down (`_check_avatar`): a collectable in the
avatar's cargo is carried on to the region, a drop recorded after the claim is accounted (deposited when its
point is inside a region), a deposited or lost collectable ends the agent at once. A thawed instance keeps
everything.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pydantic

from haa.agents import team
from haa.control.pathplanner import CostMap, PlannerConfig
from haa.core.ddb import ops as ddbops
from haa.sdk.registry import register
from haa.slam.replica import decode_map

XY = tuple[float, float]

#: phases -> the `forage/state/<id>` state they are written as
STATE_OF = {"bidding": "seen", "fetch": "claimed", "pick": "claimed", "carry": "carried", "drop": "carried",
            "clear": "deposited"}


class ForageConfig(team.TeamConfig):
    collectable: int = pydantic.Field(ge=0)
    #: collection regions, map frame: id -> polygon [[x, y], ...]
    regions: dict[str, list[tuple[float, float]]] = pydantic.Field(min_length=1)
    #: the radius of the largest avatar that may take part (sweeper, carrier: 0.20 m): drop points are passable
    avatar_radius: float = pydantic.Field(0.2, gt=0, le=2)
    check_s: float = pydantic.Field(1.0, gt=0, le=60)
    rebid_s: float = pydantic.Field(2.0, gt=0, le=600)
    rebid_delta: float = pydantic.Field(0.1, ge=0, le=10)
    #: how far inside a region the avatar stops to drop (the collectable lands ~0.26 m in front of a sweeper)
    region_margin: float = pydantic.Field(0.5, ge=0, le=5)
    #: a pick_up or drop without an answer after this long: the avatar's registry entry decides, else again
    action_timeout_s: float = pydantic.Field(30.0, gt=0, le=3600)
    pick_attempts: int = pydantic.Field(5, ge=1, le=20)
    #: offset of the 2nd.. pick-up points around the estimate (haa-sim's reach: 0.15 m beyond the rim)
    search_m: float = pydantic.Field(0.2, ge=0, le=2)
    retry_s: float = pydantic.Field(20.0, ge=0, le=3600)
    #: driving to a point, the avatar's estimate has not moved `stall_m` for this long: the step is sent again
    #: (a new target id). An answer ("reached"/"unreachable") lost with a crashed or moved agent would otherwise
    #: leave both waiting for good
    stall_s: float = pydantic.Field(60.0, gt=0, le=3600)
    stall_m: float = pydantic.Field(0.2, gt=0, le=10)
    #: after the deposit the avatar is driven this far out of every region before the supervisor retires (an
    #: idle avatar left standing in a region — a carrier has nothing else to do — shut the drop points of every
    #: later delivery); 0: retire at once
    clear_m: float = pydantic.Field(0.5, ge=0, le=10)
    clear_timeout_s: float = pydantic.Field(60.0, gt=0, le=3600)
    #: searches (rounds of `pick_attempts` points) that found nothing, without a sighting of the collectable in
    #: between, after which it is "missing" (terminal): a ghost id must not hold the mission to its time limit
    missing_after: int = pydantic.Field(2, ge=1, le=100)


def inside(p: XY, poly: Sequence[Sequence[float]]) -> bool:
    """Whether point p lies inside polygon `poly` (ray casting)."""
    x, y = p
    n, c = len(poly), False
    for i in range(n):
        (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % n]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            c = not c
    return c


def edge_distance(p: XY, poly: Sequence[Sequence[float]]) -> float:
    """Distance from p to the nearest edge of `poly`."""
    best = math.inf
    for i in range(len(poly)):
        (x1, y1), (x2, y2) = poly[i], poly[(i + 1) % len(poly)]
        dx, dy = x2 - x1, y2 - y1
        L2 = dx * dx + dy * dy
        t = 0.0 if L2 == 0 else max(0.0, min(1.0, ((p[0] - x1) * dx + (p[1] - y1) * dy) / L2))
        best = min(best, math.hypot(p[0] - x1 - t * dx, p[1] - y1 - t * dy))
    return best


def drop_candidates(poly: Sequence[Sequence[float]], margin: float, step: float = 0.1) -> list[XY]:
    """Points of a `step` lattice inside `poly` at least `margin` from its edges (less if the region is too
    small: then the innermost ones)."""
    xs = [p[0] for p in poly]
    ys = [p[1] for p in poly]
    pts = [(float(x), float(y)) for x in np.arange(min(xs) + step / 2, max(xs), step)
           for y in np.arange(min(ys) + step / 2, max(ys), step) if inside((float(x), float(y)), poly)]
    if not pts:
        return [(sum(xs) / len(xs), sum(ys) / len(ys))]
    dist = [edge_distance(p, poly) for p in pts]
    need = min(margin, max(dist))
    return [p for p, d in zip(pts, dist, strict=True) if d >= need - 1e-9]


def fetch_point(pos: XY, attempts: int, search_m: float) -> XY:
    """Where the `attempts`-th pick-up of a collectable estimated at `pos` is tried: the estimate, then points
    `search_m` east, north, west, south of it."""
    if attempts == 0 or search_m <= 0:
        return pos
    ang = (attempts - 1) * math.pi / 2
    return (pos[0] + search_m * math.cos(ang), pos[1] + search_m * math.sin(ang))


def landing_point(pose: dict[str, Any], radius: float) -> XY:
    """Where a collectable dropped by an avatar of `radius` at `pose` (x, y, theta) lands: in front of it, as
    haa-sim and a gripper put it."""
    x, y = float(pose.get("x") or 0.0), float(pose.get("y") or 0.0)
    th = float(pose.get("theta") or 0.0)
    return (x + (radius + 0.06) * math.cos(th), y + (radius + 0.06) * math.sin(th))


def drop_point(cm: CostMap | None, start: XY, regions: dict[str, list[tuple[float, float]]], margin: float,
               blocked: Sequence[XY], others: Sequence[XY], radius: float) -> list[Any] | None:
    """[x, y, region]: a passable point `margin` inside a region, of least path cost from `start` on `cm` (the
    nearest region by path; straight lines without a map), not within 0.3 m of a `blocked` one; None if none.
    Points within 2 `radius` + 0.1 m of another avatar (`others`: where the team last saw them) are skipped
    unless every point is: an idle avatar parked in a region shuts every drop point within its radius plus the
    planner's inflation, and the planner answers each "unreachable" (a carrying avatar then stood still to the
    end of a CI mission)."""
    field = cm.cost_field(start) if cm is not None else None
    if field is not None and not np.isfinite(field).any():
        field = None
    near = 2 * radius + 0.1
    points = [(rid, p) for rid, poly in sorted(regions.items()) for p in drop_candidates(poly, margin)]
    skip_near = bool(others) and not all(any(math.dist(p, q) < near for q in others) for _, p in points)
    best: tuple[float, list[Any]] | None = None
    for rid, p in points:
        if any(math.dist(p, b) < 0.3 for b in blocked) or (skip_near and any(math.dist(p, q) < near for q in others)):
            continue
        c = None
        if cm is not None and field is not None:
            cell = cm.cell(*p)
            if cell is None or not cm.passable[cell]:
                continue
            c = float(field[cell])
        cost = c if c is not None else math.dist(start, p)
        if math.isfinite(cost) and (best is None or cost < best[0]):
            best = (cost, [round(p[0], 3), round(p[1], 3), rid])
    return best[1] if best else None


def clear_point(cm: CostMap, start: XY, regions: dict[str, list[tuple[float, float]]], clear_m: float,
                others: Sequence[XY], radius: float) -> XY | None:
    """The passable cell of least path cost from `start` on `cm` that lies `clear_m` outside every region and
    2 `radius` + 0.1 m from the other avatars (None without a way out)."""
    field = np.where(cm.passable, cm.cost_field(start), np.inf)
    finite = np.flatnonzero(np.isfinite(field))
    near = 2 * radius + 0.1
    for i in finite[np.argsort(field.flat[finite], kind="stable")]:
        r, c = np.unravel_index(int(i), field.shape)
        p = cm.centre(int(r), int(c))
        if any(inside(p, poly) or edge_distance(p, poly) < clear_m for poly in regions.values()):
            continue
        if any(math.dist(p, q) < near for q in others):
            continue
        return p
    return None


@register
class SupervisorForage(team.SupervisorBase):
    TYPE = "supervisor_forage"
    TASK = "forage"
    CONFIG = ForageConfig
    COST = 0.01
    RECOVERY = "backup"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: ForageConfig
        self.item = int(self.cfg.collectable)
        self.phase = "bidding"  # bidding | fetch | pick | carry | drop | done
        self.held: str | None = None  # the avatar it holds (claimed with)
        self.pos: XY | None = None  # where the collectable is, as the team knows it
        self.moved = False  # pos is where an avatar put it down (not forage/collectables' estimate)
        self.attempts = 0
        self.since = 0.0  # mission time the current phase began
        self.drop_at: list[Any] | None = None  # [x, y, region id]
        self.blocked: list[XY] = []  # drop points found unreachable
        self.resume_at = 0.0  # no bids before (after a failed pick-up)
        self.last_seen: dict[str, XY] = {}  # avatar -> its last estimate seen
        self.dist: dict[str, float] = {}  # avatar -> path distance to the collectable
        self.bid_sent: dict[str, float] = {}  # avatar -> priority last written
        self._field_key: Any = None
        self._field: np.ndarray | None = None
        self._costmap: CostMap | None = None
        self._map_digest = b""
        self._last_rebid = -math.inf
        self.result = ""
        self.progress: tuple[float, XY] | None = None  # (since, where) the held avatar was last seen moving
        self.stalls = 0
        self.seen_t: float | None = None  # the collectable's last sighting (forage/collectables t_last)
        self.misses = 0  # searches that found nothing since its last sighting
        self.miss_seen_t: float | None = None  # its last sighting when the last search failed

    # ------------------------------------------------------------------ state

    def _forage_state(self) -> dict[str, Any]:
        return {"phase": self.phase, "held": self.held, "pos": self.pos, "moved": self.moved,
                "attempts": self.attempts, "since": self.since, "drop_at": self.drop_at, "blocked": self.blocked,
                "resume_at": self.resume_at, "last_seen": self.last_seen, "result": self.result,
                "misses": self.misses, "miss_seen_t": self.miss_seen_t}

    def pack_state(self) -> bytes:
        return team.dumps({**json.loads(super().pack_state()), **self._forage_state()})

    def pack_backup(self) -> bytes:
        return team.dumps({**json.loads(super().pack_backup()), **self._forage_state()})

    def unpack_state(self, data: bytes) -> None:
        super().unpack_state(data)
        st = json.loads(data)
        self.phase = str(st.get("phase", "bidding"))
        self.held = st.get("held")
        self.pos = tuple(st["pos"]) if st.get("pos") else None
        self.moved = bool(st.get("moved", False))
        self.attempts = int(st.get("attempts", 0))
        self.since = float(st.get("since", 0.0))
        self.drop_at = st.get("drop_at")
        self.blocked = [(float(x), float(y)) for x, y in st.get("blocked", [])]
        self.resume_at = float(st.get("resume_at", 0.0))
        self.last_seen = {a: (float(p[0]), float(p[1])) for a, p in st.get("last_seen", {}).items()}
        self.result = str(st.get("result", ""))
        self.misses = int(st.get("misses", 0))
        self.miss_seen_t = st.get("miss_seen_t")

    @property
    def key(self) -> str:
        return f"{team.K_FORAGE_STATE}{self.item}"

    def _state_value(self, state: str, **extra: Any) -> dict[str, Any]:
        v: dict[str, Any] = {"state": state, "holder": self.id, "avatar": self.held, "t": round(self.now(), 3)}
        if self.pos is not None:
            v["x"], v["y"] = round(self.pos[0], 3), round(self.pos[1], 3)
        if self.moved:
            v["moved"] = True
        v.update(extra)
        return v

    def _state_op(self, state: str | None = None, **extra: Any) -> Any:
        return team.op_put_json(self.key, self._state_value(state or STATE_OF.get(self.phase, "seen"), **extra))

    async def _write(self, ops: list[Any]) -> None:
        """`ops` in one atomic batch (a state change with the bids that go with it); if the batch aborts (a
        bid deleted meanwhile), each op on its own."""
        errs = await self.ddb_write(ops, atomic=True)
        if any(errs):
            self.log("forage_batch_retry", level="warning", errors=[e for e in errs if e])
            for op in ops:
                await self.ddb_write([op])

    # ------------------------------------------------------------------ bidding

    def suitable(self, avatar: str) -> bool:
        reg = self.registry.get(avatar)
        return reg is not None and reg.get("status") == "active" and team.capacity(reg) >= 1

    def wants(self, avatar: str) -> bool:
        if self.phase == "done" or not self.suitable(avatar):
            return False
        if self.held is not None:
            return avatar == self.held
        return self.pos is not None and self.now() >= self.resume_at

    def priority(self, avatar: str) -> float:
        if self.held is not None and avatar == self.held:
            return team.BID_FORAGE_HOLD
        return team.forage_priority(self.dist.get(avatar))

    def _bid_op(self, a: str) -> Any:
        self.bid_sent[a] = self.priority(a)
        return super()._bid_op(a)

    async def _rebid(self) -> None:
        """Write the bids whose priority moved by more than `rebid_delta` (and place missing ones)."""
        ops = [self._bid_op(a) for a in sorted(self.registry) if self.wants(a)
               and abs(self.priority(a) - self.bid_sent.get(a, -1.0)) > self.cfg.rebid_delta]
        if ops:
            await self.ddb_write(ops)

    async def _read_collectable(self) -> None:
        if self.moved:
            return
        est = (await team.get_json(self, team.K_FORAGE_COLLECTABLES, {}) or {}).get(str(self.item))
        if est is not None:
            self.pos = (float(est["x"]), float(est["y"]))
            if est.get("t_last") is not None:
                self.seen_t = float(est["t_last"])

    async def _read_map(self) -> CostMap | None:
        data = await self.ddb_get(team.K_SLAM_MAP)
        if data is None:
            self._costmap = None
            return None
        digest = hashlib.blake2b(data, digest_size=16).digest()
        if digest != self._map_digest or self._costmap is None:
            spec, prob = decode_map(data)
            self._costmap = CostMap(prob, spec, PlannerConfig(radius=self.cfg.avatar_radius))
            self._map_digest = digest
            self._field_key = None
        return self._costmap

    async def _update_distances(self) -> None:
        """`dist`: each suitable avatar's path distance to the collectable (one search from the collectable on
        the published map; the straight line where it gives none)."""
        ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {}) or {}
        for a, e in ests.items():
            self.last_seen[a] = (float(e["x"]), float(e["y"]))
        if self.pos is None:
            return
        cm = await self._read_map()
        field = None
        if cm is not None:
            if self._field_key != self.pos:
                self._field = cm.cost_field(self.pos)
                self._field_key = self.pos
            field = self._field if self._field is not None and np.isfinite(self._field).any() else None
        self.dist = {}
        for a in self.registry:
            if not self.suitable(a) or a not in ests:
                continue
            p = self.last_seen[a]
            cell = cm.cell(*p) if cm is not None and field is not None else None
            d = float(field[cell]) if field is not None and cell is not None else math.inf
            self.dist[a] = d if math.isfinite(d) else math.dist(p, self.pos)

    # ------------------------------------------------------------------ life cycle

    async def begin(self, how: str) -> None:
        if how != "thaw":
            if how == "recover":
                self.targets = {}  # every step's target is sent again
            if not await self._load(how):
                self.phase = "done"
                self.stop()
                return
            await self._read_registry()
            await self._read_collectable()
            await self._update_distances()  # the first bids are the right ones
        if how == "start":
            where = f" at ({self.pos[0]:.2f}, {self.pos[1]:.2f})" if self.pos else ""
            await team.transcript(self, f"collectable {self.item}{where}: bidding for a carrier")
        elif how == "recover":
            await team.transcript(self, f"resumed after a crash: collectable {self.item} {STATE_OF.get(self.phase)}"
                                        + (f" with {self.held}" if self.held else ""))
        await self.start_bidding()
        self.every(self.cfg.check_s, self._tick)

    async def _read_registry(self) -> None:
        for key, data in (await self.ddb_scan(team.K_AVATARS)).items():
            self.registry[key[len(team.K_AVATARS):]] = json.loads(data)

    async def _load(self, how: str) -> bool:
        """Take up (start) or read back (recover) the collectable's forage state; False: nothing to do (another
        supervisor holds it, or it is deposited or lost)."""
        st = await team.get_json(self, self.key)
        if st is None:
            errs = await self.ddb_write([ddbops.cas(self.key, 0, "json", self._state_value("seen"))], atomic=True)
            if any(errs):
                st = await team.get_json(self, self.key)
        if isinstance(st, dict):
            if st.get("holder") not in (None, self.id):
                await team.transcript(self, f"collectable {self.item} is handled by {st.get('holder')}: retiring")
                return False
            if st.get("state") in ("deposited", "lost", "missing"):
                self.result = str(st["state"])
                await self._withdraw_mine()  # the hold bid of phase "clear", if it went down then
                await team.transcript(self, f"collectable {self.item} is {st['state']} already: retiring")
                return False
            if st.get("moved") and "x" in st:
                self.pos, self.moved = (float(st["x"]), float(st["y"])), True
            state = st.get("state", "seen")
            if state in ("claimed", "carried") and st.get("avatar"):
                self.held = str(st["avatar"])
                if state == "carried" and self.phase not in ("carry", "drop"):
                    self.phase = "carry"
                elif state == "claimed" and self.phase not in ("fetch", "pick"):
                    self.phase = "fetch"
            elif state == "seen":
                self.held, self.phase = None, "bidding"
        if how == "recover":  # an action in flight when it crashed: its outcome is in the avatar's registry entry
            self.phase = {"pick": "fetch", "drop": "carry"}.get(self.phase, self.phase)
        if self.held is not None:
            await self._read_registry()
            await self._check_avatar()
        return self.phase != "done"

    # ------------------------------------------------------------------ the avatar

    async def on_avatars_changed(self) -> None:
        if self.phase == "done":
            return
        if self.phase == "clear":
            if self.held not in self.controlled:
                await self._retire()
            return
        if self.held is None:
            cands = [a for a in self.controlled if self.wants(a)]
            if cands:
                await self._claim(min(cands, key=lambda a: (self.dist.get(a, math.inf), a)))
            return
        if self.held in self.controlled:
            if self.held not in self.targets and self.phase in ("fetch", "carry"):
                await self._send_step()
            return
        reg = self.registry.get(self.held)
        if reg is None or reg.get("status") != "active":
            await self._check_avatar()
            return
        # outbid. By SupervisorCongregate: the claim and the hold bid stay; the step goes on when it is back. By
        # another SupervisorForage's hold bid: both claimed it (each won it before the other's hold bid was in:
        # ExecutiveAvatar decides per avatar from the bids it has), and the tie of two hold bids goes to the lower
        # supervisor id for good — the other one releases it and bids anew, else it would wait forever
        await self._yield_to_holder()

    async def _yield_to_holder(self) -> None:
        """Release the held avatar if `assign/<avatar>` gives it to another SupervisorForage's hold bid that wins
        the tie for good (on_avatars_changed)."""
        a = self.held
        if a is None or a in self.controlled:
            return
        st = await team.get_json(self, team.K_ASSIGN + a)
        if not (isinstance(st, dict) and st.get("task") == self.TASK and str(st.get("supervisor")) < self.id):
            return
        # its bid, not the assignment's priority (written when the winner changes, not when its bid rises)
        bid = await team.get_json(self, f"{team.K_BIDS}{a}/{st['supervisor']}")
        if isinstance(bid, dict) and float(bid.get("priority", 0)) >= team.BID_FORAGE_HOLD:
            await self._release(f"{a} is held by another SupervisorForage")

    async def _claim(self, avatar: str) -> None:
        self.held, self.phase, self.attempts, self.since = avatar, "fetch", 0, self.now()
        others = sorted((await self._my_bids()) - {avatar})
        await self._write([self._state_op(), self._bid_op(avatar),
                           *[self._unbid_op(a) for a in others]])
        for a in others:
            self.bid_sent.pop(a, None)
        d = self.dist.get(avatar)
        await team.transcript(self, f"collectable {self.item} claimed with {avatar}"
                                    + (f" ({d:.1f} m away)" if d is not None else ""))
        self.backup()
        if avatar in self.controlled:
            await self._send_step()

    async def _release(self, why: str, wait: float = 0.0) -> None:
        """Back to "seen" without an avatar (bids on every suitable avatar again, after `wait` s)."""
        held = self.held
        self.held, self.phase, self.attempts, self.since = None, "bidding", 0, self.now()
        self.resume_at = self.now() + wait
        mine = await self._my_bids()
        ops = [self._state_op("seen")]
        if held is not None and held in mine:
            ops.append(self._unbid_op(held))
            self.bid_sent.pop(held, None)
        await self._write(ops)
        if held:
            self.targets.pop(held, None)
        await team.transcript(self, f"collectable {self.item} released ({why})")
        self.backup()
        if wait <= 0:
            await self._bid_all()

    async def _finish(self, state: str, why: str) -> None:
        """Deposited or lost: the state and the withdrawal of every bid in one atomic batch — but the hold bid on
        the avatar that deposited it, which is first driven out of the regions (phase "clear", `clear_m`); then
        retire."""
        a = self.held
        p = None
        if state == "deposited" and a is not None and a in self.controlled and self.cfg.clear_m > 0:
            p = await self._clear_point()
        self.phase, self.result, self.bidding = ("clear" if p is not None else "done"), state, False
        mine = await self._my_bids()
        keep = {a} if p is not None else set()
        await self._write([self._state_op(state, why=why),
                           *[self._unbid_op(b) for b in sorted(mine - keep)]])
        self.backup()
        await team.transcript(self, f"collectable {self.item} {state} ({why}): finished, retiring")
        if a is not None and p is not None:
            self.since = self.now()
            self.targets.pop(a, None)
            self.send_target(a, p[0], p[1])
            self.log("forage_clear", avatar=a, x=round(p[0], 3), y=round(p[1], 3))
            self.backup()
            return
        await self._retire()

    async def _retire(self) -> None:
        """Withdraw what bids are left (the hold bid of phase "clear") and stop."""
        self.phase, self.bidding = "done", False
        await self._withdraw_mine()
        self.backup()
        self.stop()

    async def _clear_point(self) -> XY | None:
        """`clear_point` for the held avatar from its estimate on the published map."""
        a = self.held
        start = self.last_seen.get(a) if a else None
        cm = await self._read_map()
        if start is None or cm is None:
            return None
        others = [q for b, q in self.last_seen.items() if b != a]
        return clear_point(cm, start, self.cfg.regions, self.cfg.clear_m, others, self.cfg.avatar_radius)

    async def _check_avatar(self) -> None:
        """What happened to the collectable, from the held avatar's registry entry (cargo, last drop, status,
        how it left, its last pose): after a recovery, a lost control, an action without an answer."""
        a = self.held
        if a is None:
            return
        reg = self.registry.get(a) or {}
        cargo = [int(c) for c in reg.get("cargo", [])] if "cargo" in reg else None
        last = reg.get("last_drop") or {}
        carrying = self.item in cargo if cargo is not None else self.phase in ("carry", "drop")
        if reg.get("status") != "active":
            if carrying:
                if reg.get("how") == "crashed":
                    await self._finish("lost", f"{a} crashed carrying it")
                    return
                pose = reg.get("pose") or {}
                p = (pose["x"], pose["y"]) if "x" in pose else self.last_seen.get(a, self.pos)
                if p is not None:
                    self.pos, self.moved = (float(p[0]), float(p[1])), True
                await self._release(f"{a} {reg.get('how', 'retired')} carrying it: put down at its last pose")
                return
            if self.phase in ("carry", "drop") and last.get("item") == self.item:
                await self._dropped_at(last)
                return
            await self._release(f"{a} left")
            return
        if carrying:
            if self.phase in ("fetch", "pick"):
                await self._carry()
        elif self.phase in ("carry", "drop") and cargo is not None:
            if last.get("item") == self.item:
                await self._dropped_at(last)
            else:  # not carried, no drop of it recorded: fetch it where the avatar is
                p = self.last_seen.get(a)
                if p is not None:
                    self.pos, self.moved = p, True
                self.phase, self.since = "fetch", self.now()
                await self._write([self._state_op()])
        elif self.phase == "pick":
            self.phase, self.since = "fetch", self.now()
            self.targets.pop(a, None)

    # ------------------------------------------------------------------ steps

    async def _send_step(self) -> None:
        a = self.held
        if a is None or a not in self.controlled:
            return
        if self.phase == "fetch" and self.pos is not None:
            p = fetch_point(self.pos, self.attempts, self.cfg.search_m)
        elif self.phase == "carry":
            if self.drop_at is None:
                self.drop_at = await self._drop_point()
            if self.drop_at is None:
                return
            p = (float(self.drop_at[0]), float(self.drop_at[1]))
        else:
            return
        self.send_target(a, p[0], p[1])
        self.progress = None  # the stall clock starts with the step
        self.log("forage_step", phase=self.phase, avatar=a, tid=self.targets[a]["tid"], x=round(p[0], 3),
                 y=round(p[1], 3))
        await self.ddb_write([team.op_put_json(team.K_TARGETS + a, {**self.targets[a], "supervisor": self.id,
                                                                     "task": self.TASK})])
        self.backup()

    async def _drop_point(self) -> list[Any] | None:
        """[x, y, region] (`drop_point`) from the held avatar's estimate on the published map; the drop points
        found unreachable are skipped until every one has been."""
        a = self.held
        start = self.last_seen.get(a) if a else None
        if start is None:
            ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {}) or {}
            if a in ests:
                start = (float(ests[a]["x"]), float(ests[a]["y"]))
        if start is None:
            start = self.pos
        if start is None:
            return None
        cm = await self._read_map()
        others = [q for b, q in self.last_seen.items() if b != a]
        best = drop_point(cm, start, self.cfg.regions, self.cfg.region_margin, self.blocked, others,
                          self.cfg.avatar_radius)
        if best is None and self.blocked:  # every point tried: start over
            self.blocked = []
            best = drop_point(cm, start, self.cfg.regions, self.cfg.region_margin, [], others, self.cfg.avatar_radius)
        return best

    async def _carry(self) -> None:
        self.phase, self.since, self.attempts, self.drop_at = "carry", self.now(), 0, None
        await self._write([self._state_op()])
        await team.transcript(self, f"collectable {self.item} picked up by {self.held}")
        if self.held is not None:
            self.targets.pop(self.held, None)
        await self._send_step()

    async def _dropped_at(self, pose: dict[str, Any]) -> None:
        """The avatar dropped it at `pose` (its estimate): deposited if the point it lands on — in front of the
        avatar, as haa-sim and a gripper put it — is inside a region, else it is seen there (fetched again)."""
        p = landing_point(pose, self.cfg.avatar_radius)
        region = next((rid for rid, poly in sorted(self.cfg.regions.items()) if inside(p, poly)), None)
        if region is not None:
            self.pos = p
            await self._finish("deposited", f"by {self.held} in region {region}")
            return
        self.pos, self.moved = p, True
        self.phase, self.since, self.attempts, self.drop_at = "fetch", self.now(), 0, None
        await self._write([self._state_op()])
        await team.transcript(self, f"collectable {self.item} dropped outside the regions at ({p[0]:.2f}, "
                                    f"{p[1]:.2f}): fetching it again")
        if self.held is not None:
            self.targets.pop(self.held, None)
        await self._send_step()

    def _command(self, op: str) -> None:
        a = self.held
        agent = self.controlled.get(a) if a else None
        if not agent:
            return
        t = self.targets.get(a, {}) if a else {}
        self.send(agent, team.dumps({"op": op, "tid": t.get("tid"), "sup": self.id, "item": self.item}))

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        op, a = msg.get("op"), msg.get("avatar")
        if self.phase == "done" or a is None or a != self.held:
            return
        t = self.targets.get(a)
        if self.phase == "clear":
            if op in ("reached", "unreachable") and t is not None and msg.get("tid") == t.get("tid"):
                await self._retire()
            return
        self.log("forage_answer", op=op, avatar=a, tid=msg.get("tid"), phase=self.phase,
                 ok=msg.get("ok"), reason=msg.get("reason"))
        if op in ("reached", "unreachable"):
            if t is None or msg.get("tid") != t.get("tid"):
                return
            if op == "reached" and self.phase in ("fetch", "carry"):
                self.phase = "pick" if self.phase == "fetch" else "drop"
                self.since = self.now()
                self._command("pick_up" if self.phase == "pick" else "drop")
                self.backup()
            elif op == "unreachable" and self.phase == "fetch":
                await self._missed("its point is unreachable")
            elif op == "unreachable" and self.phase == "carry":
                if self.drop_at is not None:
                    self.blocked.append((float(self.drop_at[0]), float(self.drop_at[1])))
                self.drop_at = None
                self.targets.pop(a, None)
                await self._send_step()
        elif op == "picked" and self.phase in ("fetch", "pick"):
            if msg.get("ok"):
                await self._carry()
            elif msg.get("reason") == "capacity_full":
                reg = self.registry.get(a, {})
                if self.item in [int(c) for c in reg.get("cargo", [])]:
                    await self._carry()
                else:
                    await self._release(f"{a} carries something else", wait=self.cfg.retry_s)
            else:
                await self._missed(str(msg.get("reason") or "not picked up"))
        elif op == "dropped" and self.phase in ("carry", "drop"):
            if msg.get("ok"):
                await self._dropped_at(msg.get("pose") or {})
            else:
                await self._check_avatar()

    def _stalled(self) -> bool:
        """Whether the held avatar's estimate has stayed within `stall_m` for `stall_s` (and restart the clock
        when it has)."""
        p = self.last_seen.get(self.held) if self.held else None
        if p is None:
            return False
        if self.progress is None or math.dist(p, self.progress[1]) > self.cfg.stall_m:
            self.progress = (self.now(), p)
            return False
        if self.now() - self.progress[0] < self.cfg.stall_s:
            return False
        self.progress = (self.now(), p)
        return True

    async def _missed(self, why: str) -> None:
        """A pick-up point that gave nothing: the next point around the estimate, or release the avatar."""
        self.attempts += 1
        if self.attempts >= self.cfg.pick_attempts:
            if self.seen_t is not None and self.miss_seen_t is not None and self.seen_t > self.miss_seen_t:
                self.misses = 0  # seen again since the last search: that one was no evidence against it
            self.misses += 1
            self.miss_seen_t = self.seen_t
            if self.misses >= self.cfg.missing_after:
                await self._finish("missing", f"not found at its estimate in {self.misses} searches")
                return
            await self._release(f"not found in reach after {self.attempts} tries ({why})", wait=self.cfg.retry_s)
            return
        self.phase, self.since = "fetch", self.now()
        if self.held is not None:
            self.targets.pop(self.held, None)
        await self._send_step()

    async def _tick(self) -> None:
        if self.phase == "done":
            return
        if self.phase == "clear":  # out of the region, or given up: retire
            if self.held not in self.controlled or self.now() - self.since > self.cfg.clear_timeout_s:
                await self._retire()
            return
        await self._read_collectable()
        if self.phase == "bidding":
            if self.now() - self._last_rebid >= self.cfg.rebid_s:
                self._last_rebid = self.now()
                await self._update_distances()
                await self._rebid()
            return
        ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {}) or {}
        for a, e in ests.items():
            self.last_seen[a] = (float(e["x"]), float(e["y"]))
        if self.held is None:
            return
        if self.held not in self.controlled:
            if (self.registry.get(self.held) or {}).get("status") == "active":
                await self._yield_to_holder()
            return
        if self.phase in ("fetch", "carry") and self.held in self.targets:
            # the avatar's target is another supervisor's (it sent one while it briefly controlled the avatar, as
            # two SupervisorForage that both claimed it do): the avatar drives that one, or nothing, and never
            # answers ours — send ours again
            cur = await team.get_json(self, team.K_TARGETS + self.held)
            if isinstance(cur, dict) and cur.get("supervisor") not in (None, self.id):
                self.log("forage_target_replaced", level="warning", avatar=self.held, by=cur.get("supervisor"))
                self.targets.pop(self.held, None)
        if self.phase in ("fetch", "carry") and self.held in self.targets and self._stalled():
            self.stalls += 1
            self.log("forage_stalled", level="warning", avatar=self.held, phase=self.phase,
                     tid=self.targets[self.held].get("tid"))
            self.targets.pop(self.held, None)
        if self.phase in ("fetch", "carry") and self.held not in self.targets:
            await self._send_step()
        elif self.phase in ("pick", "drop") and self.now() - self.since > self.cfg.action_timeout_s:
            before = self.phase
            reg = await team.get_json(self, team.K_AVATARS + self.held)
            if isinstance(reg, dict):
                self.registry[self.held] = reg
            await self._check_avatar()
            if self.phase == before:  # nothing changed: ask again
                self.since = self.now()
                self._command("pick_up" if before == "pick" else "drop")
