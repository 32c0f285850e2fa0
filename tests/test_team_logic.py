"""The robot-team agents' pure logic: frames, legs, bids, slots, completion. The agents themselves
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


def test_explored_share_counts_seen_free_cells_and_marks_next_to_them() -> None:
    p = np.full((10, 10), 0.5)
    p[:5] = 0.1  # 50 free cells
    p[5] = 0.9  # obstacle marks next to seen floor: 10 explored (reachable in front of the obstacle)
    p[7] = 0.9  # marks with no seen-free neighbour: an obstacle's inside, not counted
    assert explored_share(p, 100) == pytest.approx(0.6)
    assert explored_share(p, 40) == 1.0
    p[5] = 0.5
    assert explored_share(p, 100) == pytest.approx(0.5)


def test_the_ring_of_slots_turns_and_widens_to_fit_the_map() -> None:
    centre, towards = (2.4, 6.0), (2.4, 3.0)  # the team south of the point, a wall at x = 2.9
    below_wall = lambda p: p[0] < 2.9  # noqa: E731
    plain = slots(centre, 3, 0.6, towards)
    assert not all(below_wall(p) for p in plain)  # the plain ring puts a slot into the wall
    ring = placeable_ring(centre, 3, 0.6, towards, below_wall)
    assert all(below_wall(p) for p in ring) and len(ring) == 3
    assert all(math.dist(p, centre) == pytest.approx(math.dist(ring[0], centre)) for p in ring)
    # nothing fits: the ring with the most good slots, its bad slots moved out along their rays to a good point
    far = lambda p: math.dist(p, centre) > 0.75  # noqa: E731  (e.g. the point's post is larger than thought)
    ring = placeable_ring(centre, 3, 0.6, towards, far, grow=(0.0,))
    assert [round(math.dist(p, centre), 6) for p in ring] == [0.8, 0.8, 0.8]
    # nothing good anywhere: the ring as it was (the avatars report unreachable slots, the supervisor tries again)
    assert placeable_ring(centre, 3, 0.6, towards, lambda p: False) == plain


def test_frames_travel_with_a_transfer_jpeg_compressed_within_their_budget() -> None:
    """A moved avatar agent keeps the frames its readings still wait for (sensor agents ask for them after the
    move); a backup carries none."""
    import json
    from collections import OrderedDict
    from types import SimpleNamespace

    import numpy as np

    from haa.agents import avatar_simulation as av
    from haa.agents.team import frame_from_pb
    from haa.pb import sim_pb2 as spb

    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    img[60:180, 100:220] = 0  # something with edges
    frames = OrderedDict()
    for n in (3, 7, 9):
        frames[n] = spb.CameraFrame(avatar_id="s1", time=float(n), width=320, height=240, data=img.tobytes(),
                                    encoding=spb.IMAGE_ENCODING_RAW_RGB, K=[200, 0, 160, 0, 200, 120, 0, 0, 1])
    obj = SimpleNamespace(planner="p", target={"x": 1.0}, n_readings=9, frames=frames, cargo=[4], last_drop=None,
                          pending_action={"op": "drop", "item": 4, "tid": 2, "src": "F1"})
    obj.pack_backup = lambda: av.AvatarSimulation.pack_backup(obj)
    state = av.AvatarSimulation.pack_state(obj)
    assert "frames" not in json.loads(obj.pack_backup())
    assert len(state) < av.FRAMES_STATE_BYTES + 10_000
    new = SimpleNamespace(frames=OrderedDict())
    av.AvatarSimulation.unpack_state(new, state)
    assert list(new.frames) == [3, 7, 9] and new.planner == "p" and new.n_readings == 9 and new.cargo == [4]
    assert new.pending_action == obj.pending_action  # an action in progress moves with it
    got = frame_from_pb(new.frames[7], "s1")
    assert got.image.shape == (240, 320, 3) and got.time == 7.0
    assert np.abs(got.image[60:180, 100:220].astype(int)).mean() < 10  # the JPEG kept the picture
    # the budget: only the newest frames that fit
    old = av.FRAMES_STATE_BYTES
    try:
        av.FRAMES_STATE_BYTES = len(av.jpeg_frame(frames[9]).SerializeToString()) + 10
        new = SimpleNamespace(frames=OrderedDict())
        av.AvatarSimulation.unpack_state(new, av.AvatarSimulation.pack_state(obj))
        assert list(new.frames) == [9]
    finally:
        av.FRAMES_STATE_BYTES = old


def test_the_bumper_widens_the_motion_noise_by_what_the_wheels_may_have_missed() -> None:
    """AvatarSimulation.bump_sigma: BUMP_M per contact begun in (t0, t1] plus BUMP_SLIDE of the driving
    speed per second the bumper was pressed; nothing without contact."""
    from collections import deque
    from types import SimpleNamespace

    from haa.agents import avatar_simulation as av

    me = SimpleNamespace(cfg=SimpleNamespace(cruise=0.2), info=SimpleNamespace(max_speed=2.0), bumper=deque())
    me.cruise_speed = lambda: av.AvatarSimulation.cruise_speed(me)
    for k in range(21):  # odometry every 0.05 s; the bumper pressed from 0.30 to 0.50 s, one contact
        t = round(0.05 * k, 2)
        me.bumper.append((t, 0.30 <= t <= 0.50, 0 if t < 0.30 else 1))
    sigma = av.AvatarSimulation.bump_sigma
    assert sigma(me, 0.0, 0.25) == 0.0
    assert sigma(me, 0.6, 1.0) == 0.0  # pressed before, released since: nothing new
    speed = 0.2 * 2.0
    assert sigma(me, 0.25, 0.55) == pytest.approx(av.BUMP_M + av.BUMP_SLIDE * speed * 0.25)
    assert sigma(me, 0.35, 0.45) == pytest.approx(av.BUMP_SLIDE * speed * 0.10)  # in contact, none begun
    # cruise "physics": the speed its sensing allows (a seeker: one 0.1 m cell per 0.5 s image)
    me.cfg = SimpleNamespace(cruise="physics", map_cell=0.1, capture_period=0.5)
    me.info = SimpleNamespace(max_speed=2.0, sonars=0, sonar_period=1.0)
    assert sigma(me, 0.35, 0.45) == pytest.approx(av.BUMP_SLIDE * 0.2 * 0.10)


def test_physics_cruise_is_a_map_cell_per_reading_of_the_mapping_sensor_capped_at_the_top_speed() -> None:
    from haa.agents.team import physics_cruise

    assert physics_cruise(1.0, 0.1, 1.0, 0.5) == pytest.approx(0.1)  # sweeper: sonar every 1 s
    assert physics_cruise(1.5, 0.1, None, 0.5) == pytest.approx(0.2)  # carrier: camera every 0.5 s
    assert physics_cruise(2.0, 0.05, None, 0.5) == pytest.approx(0.1)  # a finer map: slower
    assert physics_cruise(0.15, 0.1, None, 0.5) == pytest.approx(0.15)  # never above the top speed


def test_bottleneck_assignment_minimises_the_longest_drive_then_the_total() -> None:
    """The congregation ends with its last avatar: brute force over every matching agrees on random costs,
    with unreachable (inf) entries among them."""
    import itertools

    from haa.agents.supervisor_congregate import bottleneck_assignment

    rng = np.random.default_rng(7)
    for trial in range(300):
        n = int(rng.integers(1, 6))
        cost = rng.uniform(0, 10, (n, n)).round(1)
        if trial % 3 == 0:
            cost[rng.uniform(size=(n, n)) < 0.3] = np.inf
        best = None
        for perm in itertools.permutations(range(n)):
            c = [cost[i, perm[i]] for i in range(n)]
            key = (max(c), sum(c))
            best = key if best is None or key < best else best
        r, k = bottleneck_assignment(cost)
        assert sorted(r.tolist()) == list(range(n)) and sorted(k.tolist()) == list(range(n))
        got = (cost[r, k].max(), cost[r, k].sum())
        if math.isfinite(best[0]):
            assert got[0] == best[0] and got[1] == pytest.approx(best[1]), (trial, cost)
    # least total drive would send the far avatar (row 1) 9 m; the bottleneck matching 6 m at most
    cost = np.array([[1.0, 5.0], [6.0, 9.0]])
    r, k = bottleneck_assignment(cost)
    assert cost[r, k].max() == 6.0


def test_the_ring_is_turned_to_end_the_congregation_soonest() -> None:
    centre, towards = (2.4, 6.0), (2.4, 3.0)
    score = lambda ring: max(p[0] for p in ring)  # noqa: E731  (e.g. the team waits in the west)
    ring = placeable_ring(centre, 3, 0.6, towards, lambda p: True, score=score)
    assert score(ring) < score(slots(centre, 3, 0.6, towards)) - 0.05
    # equal scores: the least turn (the plain ring) as without a score
    assert placeable_ring(centre, 3, 0.6, towards, lambda p: True, score=lambda r: 0) == slots(centre, 3, 0.6, towards)
