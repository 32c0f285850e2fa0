"""AgentPathPlanner on a DDB (haa.agents.path_planner): a plan that fails at the avatar's radius plus the margin
is made at the radius itself; an avatar boxed in gets "start enclosed" (its avatar agent then turns in place to
look around), a target merely out of reach gets "unreachable"."""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from test_slam_exactly_once import Bus

from haa.agents import team
from haa.agents.path_planner import ENCLOSED_M2, AgentPathPlanner, enclosed
from haa.control.pathplanner import CostMap, PlannerConfig
from haa.core.ddb import ops as ddbops
from haa.slam.grid import GridSpec
from haa.slam.replica import encode_map

SPEC = GridSpec(4.0, 4.0, 0.1)


def free_map() -> np.ndarray:
    p = np.full(SPEC.shape, 0.05)
    p[0, :] = p[-1, :] = p[:, 0] = p[:, -1] = 1.0  # the arena's walls
    return p


def ask(prob: np.ndarray, start: tuple[float, float], goal: tuple[float, float]) -> tuple[dict[str, Any], Bus]:
    bus = Bus()
    ests = {"w1": {"t": bus.t, "x": start[0], "y": start[1], "theta": 0.0}}
    bus.ddb.apply(ddbops.encode_batch([ddbops.put(team.K_SLAM_MAP, "blob", encode_map(SPEC, prob)),
                                       team.op_put_json(team.K_SLAM_ESTIMATES, ests),
                                       team.op_put_json(team.K_SLAM_EST + "w1", ests["w1"])]))
    planner = bus.start(AgentPathPlanner, "P", {"avatar": "w1", "avatar_agent": "A", "radius": 0.2, "margin": 0.08})
    asyncio.run(planner.on_message("A", team.dumps({"op": "goto", "x": goal[0], "y": goal[1], "tid": 7})))
    return [m for _, dst, m in bus.sent if dst == "A"][-1], bus


def test_a_passage_wider_than_the_avatar_but_not_its_margin_is_taken_at_the_radius() -> None:
    p = free_map()
    p[20, :] = 1.0
    p[20, 18:23] = 0.05  # a 0.5 m gap: 0.1 m either side of a 0.2 m avatar, less than radius + margin (0.28)
    msg, bus = ask(p, (2.0, 1.0), (2.0, 3.0))
    assert msg["op"] == "path" and msg["tid"] == 7, msg
    assert any(ev == "plan_without_margin" for _, ev, _ in bus.logs)


def test_a_boxed_in_avatar_is_told_start_enclosed_a_walled_off_target_unreachable() -> None:
    p = free_map()
    p[8:13, 8] = p[8:13, 12] = p[8, 8:13] = p[12, 8:13] = 1.0  # a 0.5 m box around (1.05, 1.05), say a ghost
    msg, _ = ask(p, (1.05, 1.05), (3.0, 3.0))
    assert (msg["op"], msg["reason"]) == ("unreachable", team.START_ENCLOSED), msg
    q = free_map()
    q[25:, 25] = q[25, 25:] = 1.0  # the target's corner walled off; the avatar has the rest of the arena
    msg, _ = ask(q, (1.0, 1.0), (3.5, 3.5))
    assert (msg["op"], msg["reason"]) == ("unreachable", "unreachable"), msg


def test_enclosed_is_the_reachable_area_under_a_square_metre() -> None:
    assert not enclosed(CostMap(free_map(), SPEC, PlannerConfig(radius=0.2)), (2.0, 2.0))

    def boxed(inner_cells: int) -> bool:
        p = free_map()
        a, b = 5, 5 + inner_cells + 1
        p[a:b + 1, a] = p[a:b + 1, b] = p[a, a:b + 1] = p[b, a:b + 1] = 1.0
        centre = 0.1 * (a + b + 1) / 2
        area = float(np.isfinite(CostMap(p, SPEC, PlannerConfig(radius=0.2)).cost_field((centre, centre))).sum())
        assert (area * 0.01 < ENCLOSED_M2) == enclosed(CostMap(p, SPEC, PlannerConfig(radius=0.2)), (centre, centre))
        return area * 0.01 < ENCLOSED_M2

    assert boxed(8) and not boxed(16)  # 0.8 m inside: 0.4 m x 0.4 m for the centre; 1.6 m: 1.2 m x 1.2 m
