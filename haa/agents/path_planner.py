"""AgentPathPlanner (thesis App. III L2955-2969): plans an avatar's way to its target over the current map.

One per avatar, a child of its avatar agent (A1.1 of A1, L1413). "Accepts a target position and orientation
and attempts to plan a path through clear spaces using the available map data. The path uses a weighted
distance algorithm that penalizes routes that are too close to obstacles": haa.control.pathplanner
(scikit-image MCP_Geometric over a cost from the distance transform of the map; docs/control.md).

Protocol with its avatar agent (messages, JSON):

* avatar → planner {"op": "goto", "x", "y", "tid"}: plan from the avatar's pose (asked with the request
  {"op": "pose"}) to the target on the published map (`slam/map`), the other avatars (`slam/est/*`) as
  discs to avoid;
* planner → avatar {"op": "path", "tid", "waypoints": [[x, y], ...], "final": bool} ("Send action
  commands"): a receding horizon — the waypoints of the first `horizon_m` metres of the plan, cut into legs of
  at most `leg_m`; `final` when they end at the target. The map changes as the avatar explores, so the rest
  is planned again when this part is driven;
* avatar → planner {"op": "arrived", "tid", "final", "pose"} / {"op": "failed", "tid", "reason", "pose"}
  ("Send action updates"): plan the next part, or plan again after a blocked move (up to `max_failures` in a
  row, then the target is reported unreachable);
* planner → avatar {"op": "unreachable", "tid", "reason"}. A plan is first made `margin` wider than the
  avatar's radius; when that fails, at the radius itself. When that fails too and the avatar's centre can
  reach less than ENCLOSED_M2 from where it is, the reason is "start enclosed" (the avatar agent then turns
  in place once to look around, and asks again).

Recovery: "Restore configuration and wait for instructions" — RECOVERY = "restart": a restarted planner
says {"op": "hello"} to its avatar, which sends the current target again.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pydantic

from haa.agents import team
from haa.control.pathplanner import CostMap, PlannerConfig, plan_path
from haa.sdk.registry import register
from haa.slam.replica import decode_map

#: m²: an avatar whose centre can reach less than this is boxed in. Every passage of a mapped arena opens onto
#: more than a square metre; what closes a pocket smaller than that around an avatar is (mostly) an obstacle
#: that is not there any more: a teammate mapped where it stood, a sonar ghost
ENCLOSED_M2 = 1.0


def enclosed(cm: CostMap, start: tuple[float, float]) -> bool:
    """Whether the area the avatar's centre can reach from `start` on `cm` is under ENCLOSED_M2."""
    field = cm.cost_field(start)
    return float(np.isfinite(field).sum()) * cm.spec.resolution ** 2 < ENCLOSED_M2


class PlannerAgentConfig(team.TeamConfig):
    avatar: str = pydantic.Field(min_length=1)
    avatar_agent: str = pydantic.Field(min_length=1)
    radius: float = pydantic.Field(0.12, gt=0, le=2)
    #: m kept clear beyond the radius: the estimate the plan starts from is off by a few cm to a decimetre,
    #: and every bump is a push the wheels do not see (haa-sim "bump" events; docs/team.md)
    margin: float = pydantic.Field(0.08, ge=0, le=1)
    horizon_m: float = pydantic.Field(1.5, gt=0, le=50)
    leg_m: float = pydantic.Field(0.75, gt=0, le=10)
    max_failures: int = pydantic.Field(3, ge=1, le=100)


def cut_legs(start: tuple[float, float], waypoints: list[tuple[float, float]], horizon: float,
             leg: float) -> tuple[list[list[float]], bool]:
    """The waypoints of the first `horizon` metres of a path from `start`, with no leg longer than `leg`;
    and whether they reach the path's end."""
    out: list[list[float]] = []
    prev = start
    travelled = 0.0
    for i, w in enumerate(waypoints):
        d = math.dist(prev, w)
        n = max(1, math.ceil(d / leg - 1e-9))
        for k in range(1, n + 1):
            p = (prev[0] + (w[0] - prev[0]) * k / n, prev[1] + (w[1] - prev[1]) * k / n)
            out.append([round(p[0], 4), round(p[1], 4)])
            travelled += d / n
            if travelled >= horizon - 1e-9:
                return out, (i == len(waypoints) - 1 and k == n)
        prev = w
    return out, True


@register
class AgentPathPlanner(team.TeamAgent):
    TYPE = "path_planner"
    CONFIG = PlannerAgentConfig
    COST = 0.03
    RECOVERY = "restart"
    CPU_LIMIT = 1.0

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: PlannerAgentConfig
        self.goal: dict[str, Any] | None = None
        self.failures = 0
        self.plans = 0

    async def begin(self, how: str) -> None:
        if how == "start":
            self.send(self.cfg.avatar_agent, team.dumps({"op": "hello"}))

    def pack_state(self) -> bytes:
        return team.dumps({"goal": self.goal, "failures": self.failures})

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        self.goal, self.failures = st.get("goal"), int(st.get("failures", 0))

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        op = msg.get("op")
        if op == "stop":
            self.stop()
            return
        if op == "goto":
            self.goal = {"x": float(msg["x"]), "y": float(msg["y"]), "tid": msg.get("tid")}
            self.failures = 0
            await self._plan(None)
        elif self.goal is None or msg.get("tid") != self.goal["tid"]:
            return
        elif op == "arrived":
            if not msg.get("final"):
                await self._plan(msg.get("pose"))
        elif op == "failed":
            self.failures += 1
            if self.failures >= self.cfg.max_failures:
                self._unreachable(f"blocked {self.failures} times ({msg.get('reason')})")
            else:
                await self._plan(msg.get("pose"))

    def _unreachable(self, why: str) -> None:
        assert self.goal is not None
        self.log("target_unreachable", level="warning", tid=self.goal["tid"], reason=why)
        self.send(self.cfg.avatar_agent, team.dumps({"op": "unreachable", "tid": self.goal["tid"], "reason": why}))
        self.goal = None

    async def _plan(self, pose: dict[str, Any] | None) -> None:
        assert self.goal is not None
        if not pose:
            try:
                pose = json.loads(await self.request(self.cfg.avatar_agent, team.dumps({"op": "pose"})))
            except Exception as e:
                self.log("pose_request_failed", level="warning", error=str(e))
                pose = None
        if not pose:
            est = await team.get_json(self, team.K_SLAM_EST + self.cfg.avatar)
            if not est:
                self._unreachable("no pose estimate yet")
                return
            pose = est
        data = await self.ddb_get(team.K_SLAM_MAP)
        if data is None:
            self._unreachable("no map yet")
            return
        spec, prob = decode_map(data)
        # the other avatars, as discs to keep clear of (App. III: "Request list of avatars")
        others = await team.get_json(self, team.K_SLAM_ESTIMATES, {})
        avoid = [(float(e["x"]), float(e["y"]), self.cfg.radius) for a, e in others.items() if a != self.cfg.avatar]
        start = (float(pose["x"]), float(pose["y"]))
        goal = (self.goal["x"], self.goal["y"])
        plan = plan_path(prob, start, goal, spec=spec,
                         config=PlannerConfig(radius=self.cfg.radius + self.cfg.margin), avoid=avoid or None)
        self.plans += 1
        if not plan.ok and self.cfg.margin > 0:  # the margin is a preference, the radius the avatar's body
            tight = CostMap(prob, spec, PlannerConfig(radius=self.cfg.radius), avoid or None)
            first = plan.reason
            plan = tight.plan(start, goal)
            if plan.ok:
                self.log("plan_without_margin", tid=self.goal["tid"], reason=first)
            elif plan.reason in ("unreachable", "start on an obstacle") and enclosed(tight, start):
                plan = dataclasses.replace(plan, reason=team.START_ENCLOSED)
        if not plan.ok:
            self._unreachable(plan.reason)
            return
        wps, final = cut_legs(start, plan.waypoints, self.cfg.horizon_m, self.cfg.leg_m)
        self.send(self.cfg.avatar_agent, team.dumps({"op": "path", "tid": self.goal["tid"], "waypoints": wps,
                                                     "final": final}))
