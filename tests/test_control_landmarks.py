"""AgentSensorLandmark's core (haa.control.landmarks) on haa-sim's rendered frames, against the true markers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from haa.control.landmarks import LandmarkDetector
from haa.sim.world import World
from haa.slam.sensors import LandmarkReading


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def sweep(arena: str, kind: str, frames: int, seed: int):
    """Detections on random free poses, each matched with the true marker of its id."""
    w = World.from_arena(arena, seed=seed)
    det = LandmarkDetector.for_arena(w.arena)
    rng = np.random.default_rng(seed)
    errs, visible, found, n = [], 0, 0, 0
    while n < frames:
        x, y = rng.uniform(0, w.arena.width), rng.uniform(0, w.arena.height)
        if w.arena.clearance(x, y) < 0.3:
            continue
        th = float(rng.uniform(-math.pi, math.pi))
        aid = w.add_avatar(kind, (x, y, th))
        fr = w.capture(aid)
        vis = {lid for _, lid, d in w.visible_markers(aid, max_incidence=math.radians(60)) if d <= fr.max_range}
        reading = det.reading(fr)
        n += 1
        visible += len(vis)
        for s in reading.sightings:
            cands = [m.center for m in w.arena.markers if m.id == s.landmark_id]
            # the post of the congregation point has the same id on each face: the face nearest the estimate
            ex, ey = x + s.range * math.cos(th + s.bearing), y + s.range * math.sin(th + s.bearing)
            c = min(cands, key=lambda m: math.hypot(m[0] - ex, m[1] - ey))
            tr = math.hypot(c[0] - x, c[1] - y)
            tb = wrap(math.atan2(c[1] - y, c[0] - x) - th)
            errs.append((s.range - tr, wrap(s.bearing - tb), tr))
            found += s.landmark_id in vis
        w.retire(aid)
        w.step(0.5)
    return np.array(errs), found / max(visible, 1)


@pytest.mark.parametrize(("arena", "kind", "frames"), [("small", "seeker", 60), ("large", "enhanced_seeker", 30)])
def test_range_and_bearing_against_the_true_markers(arena, kind, frames):
    e, rate = sweep(arena, kind, frames, seed=3)
    assert len(e) >= 40
    dr, db, tr = e[:, 0], e[:, 1], e[:, 2]
    # every sighting is a real marker of that id (no gross errors), and the errors are small
    assert np.abs(dr).max() < 0.35 and np.abs(db).max() < 0.05
    assert np.abs(dr).mean() < 0.05  # measured ~0.02-0.03 m (docs/control.md)
    assert np.percentile(np.abs(dr / tr), 95) < 0.06  # within a few % of the range
    assert np.abs(db).mean() < 0.005  # measured ~0.001 rad
    assert tr.max() <= 4.0 + 1e-6
    assert rate > 0.6  # share of the markers in range, in view, facing within 60°, that are detected


def test_close_marker_facing_the_camera():
    w = World.from_arena("small", seed=1)
    # landmark 16 is on the south wall at (1.3, 0): look straight at it from 1 m
    aid = w.add_avatar("seeker", (1.3, 1.0, -math.pi / 2))
    fr = w.capture(aid)
    r = LandmarkDetector.for_arena(w.arena).reading(fr)
    assert isinstance(r, LandmarkReading) and r.avatar == aid and r.t == fr.time
    s = {g.landmark_id: g for g in r.sightings}
    assert 16 in s
    assert s[16].range == pytest.approx(1.0, abs=0.03)
    assert s[16].bearing == pytest.approx(0.0, abs=0.01)


def test_uses_no_ground_truth_from_the_frame():
    w = World.from_arena("small", seed=2)
    aid = w.add_avatar("enhanced_seeker", (1.7, 1.5, -1.2))
    fr = w.capture(aid)
    det = LandmarkDetector.for_arena(w.arena)
    a = det.reading(fr)
    b = det.reading(dataclasses.replace(fr, pose=(99.0, -5.0, 3.0), odometry=(0.0, 0.0, 0.0)))
    assert a == b and len(a.sightings) > 0


def test_filters():
    w = World.from_arena("small", seed=1)
    aid = w.add_avatar("enhanced_seeker", (1.7, 1.2, -math.pi / 2))
    fr = w.capture(aid)
    full = LandmarkDetector.for_arena(w.arena).detect(fr.image, fr.K, fr.mount)
    assert len(full) >= 2
    ids = {d.landmark_id for d in full}
    keep = min(ids)
    only = LandmarkDetector(w.arena.marker_dictionary, w.arena.marker_size, {keep}).detect(fr.image, fr.K, fr.mount)
    assert [d.landmark_id for d in only] == [keep]
    near = LandmarkDetector.for_arena(w.arena).detect(fr.image, fr.K, fr.mount, max_range=min(d.range for d in full))
    assert len(near) == 1
    blank = np.full_like(fr.image, 128)
    assert LandmarkDetector.for_arena(w.arena).detect(blank, fr.K, fr.mount) == []
    with pytest.raises(ValueError, match="dictionary"):
        LandmarkDetector("DICT_NOPE")
