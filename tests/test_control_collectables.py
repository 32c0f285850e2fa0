"""The Forage sensor's core (haa.control.collectables) on haa-sim's rendered frames, against the true collectables.

The accuracy checks (`problems`) are strict enough to catch a broken detector: `test_a_broken_detector_fails`
runs the same checks on deliberately broken variants — the colour threshold on BGR instead of RGB (the red
becomes blue: nothing found), the bearing's sign flipped (the floor plane's y axis mirrored), the homography
used the wrong way round (forward instead of inverse), the centre put on the near face (the radius
forgotten: range 5 cm short) — and each must be reported. The tests read ground truth; the detector does not.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from collectables_sweep import Tally, sweep

import haa.control.collectables as col
from haa.control.collectables import (
    CollectableDetector,
    CollectableReading,
    CollectableSighting,
    colour_threshold,
    to_map,
)
from haa.sim.arena import CollectableSpec, compile_arena, load_arena
from haa.sim.camera import AVATAR_COLOUR, COLLECTABLE_COLOUR, FLOOR, KIND_COLOURS, NOISE, SKY
from haa.sim.world import World


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def problems(t: Tally, min_visible: int = 25) -> list[str]:
    """What is wrong with a sweep's result (empty: the detector is fine). Bounds: measured values
    (docs/control.md) with room, and per sighting one foot row of range quantization."""
    out = []
    e = t.err()
    if t.visible < min_visible:
        out.append(f"too few collectables in view ({t.visible}) to judge")
    rate = t.found / max(t.visible, 1)
    if rate < 0.9:  # measured 0.98-1.0
        out.append(f"detection rate {rate:.2f} < 0.9")
    if t.false > 0.02 * t.frames:  # measured 0
        out.append(f"{t.false} false detections in {t.frames} frames")
    clean = e[e[:, 5] == 0]  # leave out collectables whose columns a nearer one shares (renderer artefact)
    if len(clean) < min_visible:
        out.append(f"only {len(clean)} matched sightings")
        return out
    dr, db, tr = clean[:, 0], clean[:, 1], clean[:, 2]
    if abs(dr.mean()) > 0.01:  # measured ±0.1 cm
        out.append(f"range bias {dr.mean():+.3f} m")
    # one foot row is z²/(f·h) of depth: 9 cm at 3 m (basic, f 343), 19 cm at 4 m (enhanced, f 285)
    row = tr**2 / (285 * 0.3)
    if (bad := np.abs(dr) > 0.01 + row / 2).any():
        out.append(f"{bad.sum()} range errors beyond half a foot row, worst {np.abs(dr).max():.3f} m")
    if np.abs(db).mean() > 0.002 or np.abs(db).max() > 0.006:  # measured 0.5 / 2.1 mrad
        out.append(f"bearing errors mean {np.abs(db).mean():.4f} max {np.abs(db).max():.4f} rad")
    return out


@pytest.mark.parametrize(
    ("arena", "camera", "frames"),
    [("small", "basic", 50), ("small", "enhanced", 30), ("large", "basic", 100), ("large", "enhanced", 60)],
)
def test_detection_rate_and_errors_on_seeded_frames(arena, camera, frames):
    t = sweep(arena, camera, frames, seed=5)
    assert problems(t) == []


def _bgr(self, image):
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    return cv2.inRange(hsv, (0, math.ceil(self.s_min * 255), math.ceil(self.v_min * 255)), (8, 255, 255))


class _NearFace(CollectableDetector):
    def _centre(self, *a, **k):
        c = super()._centre(*a, **k)
        return None if c is None else c * (1 - self.radius / float(np.hypot(*c)))


MUTANTS = {
    "threshold on BGR": lambda mp: mp.setattr(col.ColourThreshold, "mask", _bgr),
    "bearing sign": lambda mp: mp.setattr(col, "_to_plane", lambda Hi, u, v: _plane(Hi, u, v) * [1.0, -1.0]),
    "homography forward": lambda mp: mp.setattr(col, "_to_plane", lambda Hi, u, v: _plane(np.linalg.inv(Hi), u, v)),
    "radius forgotten": None,
}
_plane = col._to_plane


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_a_broken_detector_fails(mutant, monkeypatch):
    patch = MUTANTS[mutant]
    if patch is not None:
        patch(monkeypatch)
    det = _NearFace() if mutant == "radius forgotten" else None
    t = sweep("small", "enhanced", 30, seed=5, detector=det)
    assert problems(t) != []


def test_the_colour_window_comes_from_the_palette():
    th = colour_threshold()
    assert th.hue == pytest.approx(2.0, abs=0.1)
    assert th.hue_tol == pytest.approx((35.6 - 2.0) / 2, abs=0.2)  # half way to the floor's hue
    assert th.s_min == pytest.approx((0.86 + 0.381) / 2, abs=0.01)
    assert th.v_min == pytest.approx(214 / 255 / 2, abs=0.01)
    # the red within the pixel noise is inside; every other colour drawn (structures at every shade) outside
    offs = [np.array(o) for o in np.ndindex(3, 3, 3)]
    reds = [np.clip(np.array(COLLECTABLE_COLOUR) + (o - 1) * NOISE, 0, 255) for o in offs]
    others = [FLOOR, SKY, AVATAR_COLOUR, (20, 20, 20), (235, 235, 235)]
    others += [tuple(np.array(c) * s) for c in KIND_COLOURS.values() for s in np.linspace(0.55, 1.0, 10)]
    noisy = [np.clip(np.array(c) + (o - 1) * NOISE, 0, 255) for c in others for o in offs]
    img = np.array([reds + noisy], dtype=np.uint8)
    m = th.mask(img)[0] > 0
    assert m[: len(reds)].all() and not m[len(reds) :].any()


def world_with(points, arena="small", seed=0) -> World:
    a = load_arena(arena)
    specs = [CollectableSpec(id=f"t{i}", pos=(round(x, 4), round(y, 4))) for i, (x, y) in enumerate(points)]
    return World(compile_arena(a.spec.model_copy(update={"collectables": specs}), "test arena"), seed=seed)


POSE = (0.3, 1.2, 0.0)  # small arena, looking east along 3.1 m of open floor


def ahead(r: float, b: float, pose=POSE) -> tuple[float, float]:
    x, y, th = pose
    return (x + r * math.cos(th + b), y + r * math.sin(th + b))


def look(points, kind="seeker", pose=POSE, **kw) -> tuple[list[CollectableSighting], object]:
    w = world_with(points)
    aid = w.add_avatar(kind, pose)
    fr = w.capture(aid)
    return CollectableDetector(**kw).sightings(fr), fr


@pytest.mark.parametrize(("r", "b"), [(1.0, 0.0), (1.5, 0.2), (2.2, -0.3), (2.9, 0.1)])
def test_a_single_collectable(r, b):
    s, _ = look([ahead(r, b)])
    assert len(s) == 1
    assert s[0].range == pytest.approx(r, abs=0.01 + r * r / (343 * 0.3) / 2)
    assert s[0].bearing == pytest.approx(b, abs=0.003)  # left of the heading is positive
    assert s[0].edge == "bottom" and not s[0].partial
    assert s[0].xy == pytest.approx((s[0].range * math.cos(s[0].bearing), s[0].range * math.sin(s[0].bearing)))


def test_nearer_than_the_floor_in_view_uses_the_top_edge():
    # basic camera: the floor shows from 0.86 m, a collectable's top from 0.57 m
    s, fr = look([ahead(0.7, 0.05)])
    assert len(s) == 1 and s[0].edge == "top"
    assert s[0].box[3] == fr.height - 1
    assert s[0].range == pytest.approx(0.7, abs=0.01) and s[0].bearing == pytest.approx(0.05, abs=0.005)
    assert look([ahead(0.45, 0.0)])[0] == []  # below the image altogether


def test_cut_by_the_image_border():
    half = 0.873 / 2
    s, fr = look([ahead(2.0, half - 0.01)])  # centre just inside the left border: about half of it in view
    assert len(s) == 1 and s[0].partial and s[0].box[0] == 0
    assert s[0].bearing == pytest.approx(half - 0.01, abs=0.004)
    assert s[0].range == pytest.approx(2.0, abs=0.04)
    s, _ = look([ahead(2.0, -half + 0.02)])
    assert len(s) == 1 and s[0].partial and s[0].box[2] == fr.width - 1
    assert s[0].bearing == pytest.approx(-half + 0.02, abs=0.004)


def test_two_collectables_that_overlap_in_the_image():
    # one behind the other, a little to the left: one blob, split into the whole nearer one and the rest
    near, far = ahead(1.5, 0.0), ahead(2.0, 0.04)
    s, _ = look([near, far])
    assert len(s) == 2
    got = to_map(s, POSE)
    assert math.dist(got[0], near) < 0.02 and not s[0].partial
    assert math.dist(got[1], far) < 0.04 and s[1].partial
    # side by side at the same depth, touching: one blob two widths wide, laid out from the left
    a, b = ahead(2.5, 0.021), ahead(2.5, -0.021)
    s, _ = look([a, b])
    assert len(s) == 2
    got = sorted(to_map(s, POSE), key=lambda p: -p[1])
    assert math.dist(got[0], a) < 0.05 and math.dist(got[1], b) < 0.05


def test_a_collectable_behind_an_avatar_edge():
    # a sweeper (green, nearer) hides the collectable's right half: the left edge and the foot place it
    w = world_with([ahead(2.4, 0.0)])
    w.add_avatar("sweeper", (*ahead(1.2, -0.17), 0.0))
    aid = w.add_avatar("seeker", POSE)
    fr = w.capture(aid, labels=True)
    assert (fr.labels == 5).any()
    s = CollectableDetector().sightings(fr)
    assert len(s) == 1 and s[0].partial
    assert s[0].bearing == pytest.approx(0.0, abs=0.004) and s[0].range == pytest.approx(2.4, abs=0.05)


def test_max_range_and_no_ground_truth():
    w = world_with([ahead(1.2, 0.1), ahead(2.6, -0.2)])
    aid = w.add_avatar("enhanced_seeker", POSE)
    fr = w.capture(aid)
    det = CollectableDetector()
    a = det.reading(fr)
    assert isinstance(a, CollectableReading) and a.avatar == aid and a.t == fr.time and len(a.sightings) == 2
    b = det.reading(dataclasses.replace(fr, pose=(99.0, -5.0, 3.0), odometry=(0.0, 0.0, 0.0)))
    assert a == b
    near = det.sightings(dataclasses.replace(fr, max_range=2.0))
    assert [round(x.range, 1) for x in near] == [1.2]


def test_nothing_red_nothing_seen():
    w = world_with([])
    w.add_avatar("sweeper", (*ahead(1.5, 0.1), 1.0))
    aid = w.add_avatar("enhanced_seeker", POSE)
    fr = w.capture(aid, labels=True)
    assert (fr.labels == 5).any()  # a green avatar in view
    assert CollectableDetector().sightings(fr) == []
    assert CollectableDetector().detect(np.full_like(fr.image, 128), fr.K, fr.mount) == []


def test_red_things_of_the_wrong_shape_are_not_collectables():
    _, fr = look([])
    img = fr.image.copy()
    cy = int(fr.K[1, 2])
    img[cy + 30 : cy + 90, 100:120] = COLLECTABLE_COLOUR  # foot at ~1.7 m but 3x as tall as a collectable
    img[cy - 40 : cy - 20, 200:215] = COLLECTABLE_COLOUR  # above the horizon: not on the floor
    assert CollectableDetector().detect(img, fr.K, fr.mount) == []
    img[cy + 60 : cy + 90, 250:280] = COLLECTABLE_COLOUR  # ~1.1 m, the height of a 10 cm cylinder there
    assert len(CollectableDetector().detect(img, fr.K, fr.mount)) == 1


def test_to_map():
    s = CollectableSighting(2.0, 0.0, (0, 0, 1, 1), (2.0, 0.0), "bottom", False, 4)
    assert to_map([s], (1.0, 2.0, math.pi / 2)) == [pytest.approx((1.0, 4.0))]
    assert to_map([(1.0, math.pi / 2)], (0.0, 0.0, math.pi / 2)) == [pytest.approx((-1.0, 0.0))]
    assert to_map([], (0.0, 0.0, 0.0)) == []
    # against the truth: a seen collectable lands within a few cm of its true place (true pose here)
    p = ahead(1.8, -0.25)
    s2, fr = look([p])
    assert math.dist(to_map(s2, fr.pose)[0], p) < 0.03
    with pytest.raises(ValueError, match="pose"):
        to_map([s], (0.0, 0.0))
    with pytest.raises(ValueError, match="pose"):
        to_map([s], (0.0, math.nan, 0.0))
    with pytest.raises(ValueError, match="range"):
        to_map([(-1.0, 0.0)], (0.0, 0.0, 0.0))


def test_bad_input_is_a_value_error():
    _, fr = look([])
    det = CollectableDetector()
    for bad, what in [
        (np.zeros((0, 0, 3), np.uint8), "empty"),
        (np.zeros((240, 320), np.uint8), "shape"),
        (np.zeros((240, 320, 4), np.uint8), "shape"),
        (np.zeros((240, 320, 3), np.float32), "dtype"),
        ([[0, 0, 0]], "numpy array"),
    ]:
        with pytest.raises(ValueError, match=what):
            det.detect(bad, fr.K, fr.mount)
    with pytest.raises(ValueError, match="K"):
        det.detect(fr.image, np.eye(2), fr.mount)
    with pytest.raises(ValueError, match="mount"):
        det.detect(fr.image, fr.K, (0.0, 0.0, -0.3, 0.0))
    with pytest.raises(ValueError, match="radius"):
        CollectableDetector(radius=0.0)
