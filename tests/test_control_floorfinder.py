"""AgentSensorFloorFinder's core (haa.control.floorfinder) on haa-sim's frames, against the true free space."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from haa.control.floorfinder import FloorConfig, FloorFinder, find_floor
from haa.sim.geometry import cast_circles, cast_segments
from haa.sim.world import World
from haa.slam.sensors import FloorReading, points_in_polygon


def sweep(arena: str, kind: str, frames: int, others: int, seed: int):
    w = World.from_arena(arena, seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(others):  # other avatars stand on the floor and must not count as free
        while True:
            try:
                w.add_avatar("sweeper", (rng.uniform(0, w.arena.width), rng.uniform(0, w.arena.height), 0.0))
                break
            except ValueError:
                pass
    # calibration: the first frame at a start pose (free space ahead), as an avatar agent would at mission start
    cal = w.add_avatar(kind, w.arena.start_poses[0])
    ff = FloorFinder()
    assert ff.reference(w.capture(cal).image) is not None
    w.retire(cal)
    w.step(0.5)
    errs, occupied, inside, n, empty = [], 0, 0, 0, 0
    while n < frames:
        x, y = rng.uniform(0, w.arena.width), rng.uniform(0, w.arena.height)
        th = float(rng.uniform(-math.pi, math.pi))
        try:
            aid = w.add_avatar(kind, (x, y, th))
        except ValueError:
            continue
        fr = w.capture(aid)
        n += 1
        res = ff.find(fr)
        reading = ff.reading(fr)
        H = fr.image.shape[0]
        if res is None or not (res.boundary < H).any():
            empty += 1
            assert reading is None
        else:
            assert isinstance(reading, FloorReading) and reading.avatar == aid and reading.t == fr.time
            has = res.boundary[res.columns] < H
            ang = np.arctan2(fr.K[0, 2] - res.columns[has], fr.K[0, 0])
            dirs = np.stack([np.cos(th + ang), np.sin(th + ang)], axis=1)
            e = w.arena.edges
            t, _, _ = cast_segments(x, y, dirs, e.a, e.b)
            objs = w.scene_objects(aid)
            if len(objs):
                t = np.minimum(t, cast_circles(x, y, dirs, objs[:, :2], objs[:, 2])[0])
            errs.extend((res.ranges[has] - np.minimum(t, fr.max_range / np.cos(ang))).tolist())
            poly = np.array(reading.polygon)
            q = rng.uniform(poly.min(axis=0), poly.max(axis=0), (120, 2))
            q = q[points_in_polygon(q[:, 0], q[:, 1], poly)]
            c, s = math.cos(th), math.sin(th)
            for px, py in zip(x + c * q[:, 0] - s * q[:, 1], y + s * q[:, 0] + c * q[:, 1], strict=True):
                inside += 1
                solid = w.arena.inside_solid(px, py) or not (0 < px < w.arena.width and 0 < py < w.arena.height)
                occupied += solid or any(math.hypot(px - o[0], py - o[1]) < o[2] for o in objs)
        w.retire(aid)
        w.step(0.5)
    return np.array(errs), occupied / max(inside, 1), empty / frames


@pytest.mark.parametrize(
    ("arena", "kind", "others"), [("small", "seeker", 0), ("small", "enhanced_seeker", 2), ("large", "sweeper", 3)]
)
def test_floor_polygon_against_the_true_free_space(arena, kind, others):
    e, occupied_share, empty_share = sweep(arena, kind, 30, others, seed=5)
    assert len(e) > 200
    assert occupied_share < 0.01  # what the reading calls free is free (measured <= 0.1 %)
    assert np.abs(e).mean() < 0.10  # the free boundary is where the wall or avatar stands (measured 4-6 cm)
    assert np.percentile(np.abs(e), 95) < 0.3
    assert empty_share < 0.3


def test_a_wall_in_front_is_not_taken_for_floor():
    w = World.from_arena("small", seed=1)
    cal = w.add_avatar("seeker", w.arena.start_poses[0])
    ff = FloorFinder()
    ff.reference(w.capture(cal).image)
    w.retire(cal)
    w.step(0.5)
    # 0.4 m from the west wall, facing it: the camera sees no floor at all (nearest floor row is ~0.85 m away)
    aid = w.add_avatar("seeker", (0.4, 3.1, math.pi))
    fr = w.capture(aid)
    assert ff.reading(fr) is None and ff.refused == 1
    # without the learnt colour, the thesis' literal rule (the patch in front is floor) claims the wall is free
    naive = find_floor(fr.image, fr.K, fr.mount, fr.max_range)
    assert naive is not None and float(naive.ranges.max()) > 0.5


def test_open_view_and_no_ground_truth_read():
    w = World.from_arena("small", seed=2)
    aid = w.add_avatar("enhanced_seeker", (1.7, 0.5, math.pi / 2))
    fr = w.capture(aid)
    a = FloorFinder().reading(fr)
    b = FloorFinder().reading(dataclasses.replace(fr, pose=(50.0, 50.0, 1.0), odometry=(0.0, 0.0, 0.0)))
    assert a == b and a is not None
    poly = np.array(a.polygon)
    # ahead of the avatar the floor runs to panel-a at y = 2.18 (1.68 m ahead) and no farther than 4 m
    assert 1.5 < poly[:, 0].max() <= 4.0 + 1e-6
    area = 0.5 * abs(np.dot(poly[:, 0], np.roll(poly[:, 1], -1)) - np.dot(poly[:, 1], np.roll(poly[:, 0], -1)))
    assert area > 1.0


def test_bad_reference_patch_gives_no_reading():
    img = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    K = np.array([[342.0, 0, 159.5], [0, 342.0, 119.5], [0, 0, 1]])
    assert find_floor(img, K, config=FloorConfig()) is None
    assert FloorFinder().reference(img) is None


def test_a_finder_that_first_saw_a_wall_recovers_with_the_team_colour():
    """A floor finder (re)started facing a wall learns the wall's colour, then matches walls as floor and
    refuses the floor; with the team's colour (`adopt`) it starts right, and one already wrong goes back to it
    after RELEARN_AFTER refusals in a row."""
    from haa.control.floorfinder import RELEARN_AFTER

    w = World.from_arena("small", seed=1)
    open_view = w.add_avatar("seeker", (1.7, 0.5, math.pi / 2))  # facing north along the arena
    good = FloorFinder()
    frames = []
    for _ in range(12):
        frames.append(w.capture(open_view))
        assert good.reading(frames[-1]) is not None
        w.step(0.1)
    assert good.confident() and good.learnt() is not None
    w.retire(open_view)
    w.step(0.5)
    wall = w.capture(w.add_avatar("seeker", (0.4, 3.1, math.pi)))  # 0.4 m from the west wall, facing it
    wrong = FloorFinder()
    wrong.reference(wall.image)  # its first image: the wall's colour is learnt
    assert all(wrong.reading(f) is None for f in frames[:3])  # the floor is refused
    assert not wrong.confident()
    # a new finder that takes the team's colour first reads the open view as the good one does
    fresh = FloorFinder()
    assert fresh.adopt(good.learnt()) and fresh.reading(frames[0]) is not None
    # the wrong one, told the team's colour, is not confident in its own: it takes the team's at once
    assert wrong.adopt(good.learnt()) and wrong.reading(frames[0]) is not None
    # a confident finder keeps its own colour but falls back to the team's after RELEARN_AFTER refusals
    stubborn = FloorFinder()
    stubborn.reference(wall.image)
    stubborn.accepted = 50  # pretend it trusted the wall colour
    assert stubborn.adopt(good.learnt()) and stubborn.reading(frames[0]) is None
    for f in (frames * 2)[:RELEARN_AFTER]:
        stubborn.reading(f)
    assert stubborn.reading(frames[0]) is not None
    assert not FloorFinder().adopt({"mean": [1, 2], "std": [1, 2, 3]}) and not FloorFinder().adopt(None)
