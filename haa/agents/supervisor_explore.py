"""SupervisorExplore (thesis App. III L3077-3083): directs the avatars it controls to unexplored regions.

"Carries out the exploration task by directing avatars to unexplored regions. Unexplored cells are divided
between avatars using an Expectation-Maximization (EM) algorithm. Once the cells are divided each avatar is
assign[ed] a target within their area." The split is haa.control.explore (hard EM over the unexplored
reachable cells, one region and one target per avatar; docs/control.md); `exploration: frontier` in the
mission file selects coordinated frontier exploration instead (haa.control.frontier, Burgard et al. 2005).

* Bidding: "SupervisorExplore by default places a low priority bid and gains control of each avatar"
  (L1510): priority `team.BID_EXPLORE` on every active avatar (haa.agents.team.SupervisorBase) but carriers:
  a carrier is never used to explore (Table 6.2-2, L1243: "The Carrier's function is to retrieve
  collectables"; `wants`).
* Cadence (thesis gap 7, ours): targets are computed again every `replan_s` simulated seconds for the
  avatars that are idle (no target, reached, unreachable) or whose target has been explored meanwhile, and
  for every avatar every `refresh_s`; at once when the controlled set changes. A target reported
  unreachable, or reached while its cells are still unexplored, is kept out of the split for `blocked_s`
  (cells within `blocked_radius` of it are treated as explored for this supervisor's purposes); so is a
  target the split puts within `blocked_radius` of its avatar (the split is made again without it). Without
  the last two an avatar standing at its region's centre got that very spot again and again — reached at
  once, the camera looking ahead, the cells around it never seen — several targets a second, the avatar
  never moving (seen in the quick mission from ~20 s on, and after an avatar agent's recovery).
  A spot blocked again (within `blocked_radius` of a spot blocked before) stays out `blocked_backoff` times
  longer each time (30, 90, 270 s by default). With a fixed 30 s, an avatar whose region was the scattered
  unexplored cells along a wall — cells its sensors never mark explored from where it can drive — toured
  them again each time the blocks expired and never took a share of the open region elsewhere (the
  tests/missions/hosts.yaml run that CI stopped at its time limit: one seeker spent 190 s in the explored
  south of the arena while 0.69 -> 0.75 explored took the other one alone).
* Status: `targets/<avatar>` in the DDB.

Recovery: "Restore configuration and retrieve Avatar* statuses, reassign targets if appropriate": RECOVERY =
"backup" — the backup holds the targets sent and the next target id (haa.agents.team.SupervisorBase); after
recovery the controlled set is read again from `assign/` and every avatar gets a target afresh (status
monitoring: "If failure occurs reassign target" — an avatar agent that was recovered re-sends its own target
to its planner, and a new assignment reaches it anyway). A thawed instance (a transfer) keeps its controlled
set, targets and blocked areas: it does not send every avatar a new target after each move. The blocked
areas are not in the backup (a hint: at worst an avatar is sent to such a spot once more).
"""

from __future__ import annotations

import json
import math
from typing import Any, Literal

import numpy as np
import pydantic

from haa.agents import team
from haa.control.explore import ExploreConfig, split_unexplored
from haa.control.frontier import FrontierConfig, assign_frontiers
from haa.control.pathplanner import PlannerConfig
from haa.sdk.registry import register
from haa.slam.replica import decode_map

#: spots remembered for the back-off of blocked targets (oldest forgotten first)
MAX_SPOTS = 400


class ExploreAgentConfig(team.TeamConfig):
    exploration: Literal["em", "frontier"] = "em"
    radius: float = pydantic.Field(0.12, gt=0, le=2)
    replan_s: float = pydantic.Field(2.0, gt=0, le=600)
    refresh_s: float = pydantic.Field(10.0, gt=0, le=3600)
    blocked_s: float = pydantic.Field(30.0, ge=0, le=3600)
    blocked_radius: float = pydantic.Field(0.3, ge=0, le=5)
    blocked_backoff: float = pydantic.Field(3.0, ge=1, le=100)
    camera_range: float = pydantic.Field(3.0, gt=0, le=50)


@register
class SupervisorExplore(team.SupervisorBase):
    TYPE = "supervisor_explore"
    TASK = "explore"
    CONFIG = ExploreAgentConfig
    COST = 0.05
    RECOVERY = "backup"
    CPU_LIMIT = 1.0

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: ExploreAgentConfig
        self.blocked: list[tuple[float, float, float]] = []  # (x, y, until)
        self.spots: list[list[float]] = []  # [x, y, times blocked before] of every spot blocked (the back-off)
        self.splits = 0

    def priority(self, avatar: str) -> float:
        return team.BID_EXPLORE

    def wants(self, avatar: str) -> bool:
        """Not a carrier (Table 6.2-2: "The Carrier's function is to retrieve collectables"): seekers and
        sweepers explore."""
        return self.registry.get(avatar, {}).get("type") != "carrier"

    def pack_state(self) -> bytes:
        st = json.loads(super().pack_state())
        st["blocked"] = self.blocked
        st["spots"] = self.spots
        return team.dumps(st)

    def unpack_state(self, data: bytes) -> None:
        super().unpack_state(data)
        st = json.loads(data)
        self.blocked = [(float(x), float(y), float(u)) for x, y, u in st.get("blocked", [])]
        self.spots = [[float(x), float(y), float(n)] for x, y, n in st.get("spots", [])]

    async def begin(self, how: str) -> None:
        await self.start_bidding()
        self.every(self.cfg.replan_s, self._tick)

    async def on_avatars_changed(self) -> None:
        await self._replan(everyone=True)

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        op, a = msg.get("op"), msg.get("avatar")
        if op == "abandon":  # ExecutiveMission: the congregation point is found (L1512)
            await self.withdraw_bids()
            await team.transcript(self, "exploration abandoned")
            return
        t = self.targets.get(a)
        if t is None or t.get("tid") != msg.get("tid"):
            return
        if op == "reached":
            t["state"] = "reached"
        elif op == "unreachable":
            t["state"] = "unreachable"
        # going there again gives nothing new: keep it out of the split for a while (module docstring)
        self._add_block(t["x"], t["y"], self.now())
        self.call_later(0.05, self._tick)

    def _add_block(self, x: float, y: float, now: float) -> None:
        """Keep (x, y) out of the split for `blocked_s`, `blocked_backoff` times longer for each earlier block
        of the same spot (module docstring)."""
        n = 0.0
        near = [s for s in self.spots if math.dist((s[0], s[1]), (x, y)) < self.cfg.blocked_radius]
        for s in near:
            s[2] += 1.0
            n = max(n, s[2])
        if not near:
            self.spots.append([x, y, 0.0])
            del self.spots[:-MAX_SPOTS]
        self.blocked.append((x, y, now + self.cfg.blocked_s * self.cfg.blocked_backoff ** min(n, 8.0)))

    def _block(self, p: np.ndarray, spec: Any, x: float, y: float) -> None:
        """Mark the cells within `blocked_radius` of (x, y) explored in the supervisor's copy `p` of the map."""
        r0, c0 = (y - spec.y0) / spec.resolution, (x - spec.x0) / spec.resolution
        rr, cc = np.ogrid[0:p.shape[0], 0:p.shape[1]]
        k = self.cfg.blocked_radius / spec.resolution
        p[((rr - r0) ** 2 + (cc - c0) ** 2) <= k * k] = 0.0

    def _split(self, p: np.ndarray, spec: Any, pos: dict[str, tuple[float, float]]) -> dict[str, Any]:
        planner = PlannerConfig(radius=self.cfg.radius)
        self.splits += 1
        if self.cfg.exploration == "em":
            return split_unexplored(p, pos, spec=spec, config=ExploreConfig(planner=planner)).targets()
        return assign_frontiers(p, pos, spec=spec,
                                config=FrontierConfig(planner=planner, range=self.cfg.camera_range)).targets

    async def _tick(self) -> None:
        await self._replan(everyone=False)

    async def _replan(self, everyone: bool) -> None:
        if not self.controlled:
            return
        data = await self.ddb_get(team.K_SLAM_MAP)
        if data is None:
            return
        spec, prob = decode_map(data)
        ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {})
        pos = {a: (float(ests[a]["x"]), float(ests[a]["y"])) for a in self.controlled if a in ests}
        if not pos:
            return
        now = self.now()
        self.blocked = [b for b in self.blocked if b[2] > now]
        p = np.array(prob, dtype=float)
        for bx, by, _ in self.blocked:  # a target reached or found unreachable: not a target again for a while
            self._block(p, spec, bx, by)
        targets = self._split(p, spec, pos)
        # a target on the avatar's own spot is reached at once and shows nothing new: block it, split again
        for _ in range(2):
            near = [a for a, tgt in targets.items() if tgt is not None and a in pos
                    and math.dist(tgt, pos[a]) < self.cfg.blocked_radius]
            if not near:
                break
            for a in near:
                tx, ty = targets[a]
                self._add_block(tx, ty, now)
                self._block(p, spec, tx, ty)
            targets = self._split(p, spec, pos)
        sent = []
        for a, tgt in targets.items():
            cur = self.targets.get(a)
            if tgt is None:
                continue
            stale = cur is None or cur.get("state") != "driving" or everyone
            if cur is not None and cur.get("state") == "driving":
                # still unexplored where it is going? (else a new target)
                r = int((cur["y"] - spec.y0) / spec.resolution)
                c = int((cur["x"] - spec.x0) / spec.resolution)
                inside = 0 <= r < p.shape[0] and 0 <= c < p.shape[1]
                explored = (not inside) or not (0.27 <= p[r, c] <= 0.73)
                old = now - float(cur.get("since", now)) > self.cfg.refresh_s
                stale = stale or explored or old
                if not stale or math.dist((cur["x"], cur["y"]), tgt) < 0.2:
                    continue
            if a in pos and math.dist(tgt, pos[a]) < self.cfg.blocked_radius:
                continue  # still on its spot after two more splits: nothing better now (next tick)
            self.send_target(a, tgt[0], tgt[1])
            sent.append(a)
        if sent:
            ops = [team.op_put_json(team.K_TARGETS + a, {**self.targets[a], "supervisor": self.id,
                                                         "task": self.TASK}) for a in sent]
            await self.ddb_write(ops)
            self.backup()
