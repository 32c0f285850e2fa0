"""The robot-team agents' pure logic (issue 15): frames, legs, bids, slots, completion. The agents themselves
run in tests/test_mission_run.py on real processes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haa.agents.avatar_simulation import to_map, to_odom
from haa.agents.executive_avatar import decide
from haa.agents.executive_mission import explored_share
from haa.agents.path_planner import cut_legs
from haa.agents.supervisor_congregate import placeable_ring, slots


def test_map_and_odometry_frames_are_inverse() -> None:
    est, odo = (2.0, 1.0, 0.5), (1.7, 1.4, 0.2)  # the estimate and the odometry at one instant
    assert to_map(est, odo, odo) == pytest.approx(est)
    for p in [(0.0, 0.0), (3.0, -1.0), (1.7, 1.4)]:
        m = to_map(est, odo, (p[0], p[1], 0.0))
        assert to_odom(est, odo, m[0], m[1]) == pytest.approx(p)
    # a drift of 0.3 rad: one metre forward in odometry is one metre at heading +0.3 in the map
    m0, m1 = to_map(est, odo, (1.7, 1.4, 0.2)), to_map(est, odo, (1.7 + math.cos(0.2), 1.4 + math.sin(0.2), 0.2))
    assert math.atan2(m1[1] - m0[1], m1[0] - m0[0]) == pytest.approx(0.5)


def test_cut_legs_horizon_and_leg_length() -> None:
    wps, final = cut_legs((0.0, 0.0), [(3.0, 0.0), (3.0, 2.0)], horizon=1.5, leg=0.75)
    assert wps == [[0.75, 0.0], [1.5, 0.0]] and not final
    wps, final = cut_legs((0.0, 0.0), [(1.0, 0.0)], horizon=1.5, leg=0.75)
    assert wps == [[0.5, 0.0], [1.0, 0.0]] and final
    wps, final = cut_legs((0.0, 0.0), [(1.5, 0.0), (1.5, 1.0)], horizon=1.5, leg=2.0)
    assert wps == [[1.5, 0.0]] and not final


def test_highest_bid_wins_ties_to_the_lower_id_and_only_active_avatars() -> None:
    reg = {"s1": {"status": "active"}, "s2": {"status": "active"}, "s3": {"status": "retired"}}
    bids = {"s1": {"b-explore": {"priority": 1, "task": "explore"}, "a-cong": {"priority": 10, "task": "congregate"}},
            "s2": {"b": {"priority": 1}, "a": {"priority": 1}},
            "s3": {"x": {"priority": 5}}}
    d = decide(reg, bids)
    assert d["s1"]["supervisor"] == "a-cong" and d["s2"]["supervisor"] == "a" and "s3" not in d


def test_slots_are_equally_spaced_and_face_the_team() -> None:
    pts = slots((1.0, 1.0), 4, 0.5, towards=(3.0, 1.0))
    assert pts[0] == pytest.approx((1.5, 1.0))
    assert all(math.dist(p, (1.0, 1.0)) == pytest.approx(0.5) for p in pts)
    gaps = [math.dist(pts[k], pts[(k + 1) % 4]) for k in range(4)]
    assert max(gaps) - min(gaps) < 1e-9


def test_explored_share_counts_known_free_cells_against_the_explorable_area() -> None:
    p = np.full((10, 10), 0.5)
    p[:5] = 0.1  # 50 free cells
    p[5] = 0.9  # explored but occupied: not reachable, not counted
    assert explored_share(p, 100) == pytest.approx(0.5)
    assert explored_share(p, 40) == 1.0


def test_the_ring_of_slots_turns_and_widens_to_fit_the_map() -> None:
    centre, towards = (2.4, 6.0), (2.4, 3.0)  # the team south of the point, a wall at x = 2.9
    below_wall = lambda p: p[0] < 2.9  # noqa: E731
    plain = slots(centre, 3, 0.6, towards)
    assert not all(below_wall(p) for p in plain)  # the plain ring puts a slot into the wall
    ring = placeable_ring(centre, 3, 0.6, towards, below_wall)
    assert all(below_wall(p) for p in ring) and len(ring) == 3
    assert all(math.dist(p, centre) == pytest.approx(math.dist(ring[0], centre)) for p in ring)
    # nothing fits: the plain ring (the avatars report unreachable slots, the supervisor tries again)
    assert placeable_ring(centre, 3, 0.6, towards, lambda p: False) == plain
