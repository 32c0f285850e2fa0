"""Rendered camera frames: OpenCV finds the landmarks' ArUco markers, and a floor segmentation maps back to the
true free floor through the frame's ground-plane homography."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from haa.sim.camera import LABEL_FLOOR, LABEL_MARKER, floor_homography, intrinsics
from haa.sim.geometry import wrap_angle
from haa.sim.sensors import CAMERA_HEIGHT, CAMERAS
from haa.sim.world import World

DETECTOR = cv2.aruco.ArucoDetector(
    cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250), cv2.aruco.DetectorParameters()
)


def random_views(w: World, kind: str, n: int, seed: int):
    """n frames from random free poses (the avatar is re-placed for each)."""
    rng = np.random.default_rng(seed)
    aid = None
    for _ in range(n):
        while True:
            x = rng.uniform(0.3, w.arena.width - 0.3)
            y = rng.uniform(0.3, w.arena.height - 0.3)
            if w._pose_free(x, y, 0.25):
                break
        if aid is not None:
            w.retire(aid)
        aid = w.add_avatar(kind, (x, y, rng.uniform(-math.pi, math.pi)))
        yield aid


def fully_in_view(w: World, aid: str, marker_index: int) -> bool:
    """Both ends of the marker's plate are inside the horizontal field of view."""
    m = w.arena.markers[marker_index]
    e = w.arena.edges
    x, y, th = w.true_pose(aid)
    u = (e.b[m.edge] - e.a[m.edge]) / e.length[m.edge]
    fov = w.avatars[aid].camera.fov
    for s in (m.s0, m.s0 + m.plate):
        px, py = e.a[m.edge] + u * s
        if abs(wrap_angle(math.atan2(py - y, px - x) - th)) > fov / 2 * 0.97:
            return False
    return True


@pytest.mark.parametrize(("arena", "kind"), [("small", "seeker"), ("small", "sweeper"), ("large", "enhanced_seeker")])
def test_opencv_finds_the_landmarks_in_rendered_frames(arena: str, kind: str) -> None:
    """Recall over markers within range and field of view, facing the camera within 60 degrees and not
    occluded; and no marker is reported that the camera cannot see at all."""
    w = World.from_arena(arena, seed=2)
    expected = found = 0
    for aid in random_views(w, kind, 60, seed=3):
        gray = cv2.cvtColor(w.capture(aid).image, cv2.COLOR_RGB2GRAY)
        _, ids, _ = DETECTOR.detectMarkers(gray)
        got = set() if ids is None else {int(i) for i in ids.ravel()}
        strict = {lid for mi, lid, _ in w.visible_markers(aid, math.radians(60)) if fully_in_view(w, aid, mi)}
        expected += len(strict)
        found += len(strict & got)
        # anything detected is a landmark in view (any range, any incidence short of edge-on)
        anywhere = {lid for _, lid, _ in _visible_any_range(w, aid)}
        assert got <= anywhere, f"false detections {got - anywhere}"
    assert expected >= 50
    assert found / expected >= 0.88, f"recall {found}/{expected}"


def _visible_any_range(w: World, aid: str):
    av = w.avatars[aid]
    saved = av.camera
    av.camera = replace(saved, max_range=100.0)
    try:
        return w.visible_markers(aid, math.radians(89))
    finally:
        av.camera = saved


def test_detected_corners_match_the_projected_marker() -> None:
    """The marker's true centre projected with the frame's K lands on the detected marker's centre."""
    w = World.from_arena("small", seed=0)
    aid = w.add_avatar("seeker", (2.0, 1.2, math.pi / 2))  # sees markers 26 and 28
    f = w.capture(aid)
    corners, ids, _ = DETECTOR.detectMarkers(cv2.cvtColor(f.image, cv2.COLOR_RGB2GRAY))
    assert ids is not None
    x, y, th = f.pose
    checked = 0
    for c, lid in zip(corners, ids.ravel(), strict=True):
        lx, ly = w.arena.landmarks[int(lid)]
        # avatar frame: X forward, Y left; camera: x right = -Y, y down = -(Z - h), z = X
        dx, dy = lx - x, ly - y
        X = math.cos(th) * dx + math.sin(th) * dy
        Y = -math.sin(th) * dx + math.cos(th) * dy
        p = f.K @ np.array([-Y, -(w.arena.marker_height - CAMERA_HEIGHT), X])
        u, v = p[:2] / p[2]
        cu, cv = c[0].mean(axis=0)
        assert math.hypot(u - cu, v - cv) < 2.0, (lid, (u, v), (cu, cv))
        checked += 1
    assert checked >= 2


def test_floor_homography_is_the_pinhole_projection() -> None:
    spec = CAMERAS["enhanced"]
    K = intrinsics(spec)
    H = floor_homography(K, (0.0, 0.0, CAMERA_HEIGHT, 0.0))
    for X, Y in ((1.0, 0.0), (2.0, 0.5), (0.7, -0.3)):
        p = H @ np.array([X, Y, 1.0])
        u, v = p[:2] / p[2]
        assert u == pytest.approx(K[0, 2] - K[0, 0] * Y / X)
        assert v == pytest.approx(K[1, 2] + K[1, 1] * CAMERA_HEIGHT / X)
    # a mounting with pitch (not rendered, but the formula must hold): the principal ray hits the floor at h/tan
    Hp = floor_homography(K, (0.1, 0.0, 0.5, 0.3))
    p = Hp @ np.array([0.1 + 0.5 / math.tan(0.3), 0.0, 1.0])
    assert p[:2] / p[2] == pytest.approx(K[:2, 2])


@pytest.mark.parametrize("kind", ["seeker", "sweeper"])
def test_floor_segmentation_maps_to_the_true_free_floor(kind: str) -> None:
    """Floor found by colour matching against a patch in front of the avatar (the thesis' FloorFinder), mapped
    through the homography with the true pose, lands on free floor; and covers the floor the camera sees.

    Frames whose sample patch is not floor (a wall closer than where the horizontal camera starts to see the
    floor: 0.86 m basic, 0.36 m enhanced) are skipped, as a FloorFinder must."""
    w = World.from_arena("small", seed=1)
    g, _, res = w.ideal_grid(0.02)
    precision, recall = [], []
    for aid in random_views(w, kind, 24, seed=9):
        f = w.capture(aid, labels=True)
        assert f.labels is not None
        img = f.image.astype(np.int16)
        Himg, Wimg = img.shape[:2]
        if not np.all(f.labels[Himg - 12 :, Wimg // 2 - 20 : Wimg // 2 + 20] == LABEL_FLOOR):
            continue
        patch = img[Himg - 12 :, Wimg // 2 - 20 : Wimg // 2 + 20].reshape(-1, 3)
        ref = np.median(patch, axis=0)
        mask = np.all(np.abs(img - ref) <= 14, axis=2)
        mask[: Himg // 2 + 2] = False  # the floor is below the horizon (horizontal camera)
        vs, us = np.nonzero(mask)
        if len(us) < 50:
            continue
        pts = f.to_world(f.floor_points(np.c_[us, vs]))
        ix = np.clip((pts[:, 0] / res).astype(int), 0, g.shape[1] - 1)
        iy = np.clip((pts[:, 1] / res).astype(int), 0, g.shape[0] - 1)
        inside = (pts[:, 0] > 0) & (pts[:, 0] < w.arena.width) & (pts[:, 1] > 0) & (pts[:, 1] < w.arena.height)
        free = inside & (g[iy, ix] == 0)
        precision.append(free.mean())
        truth = f.labels == LABEL_FLOOR
        recall.append((mask & truth).sum() / max(1, truth.sum()))
    assert len(precision) >= 8
    assert min(precision) >= 0.97 and np.mean(precision) >= 0.99
    assert np.mean(recall) >= 0.97


def test_labels_and_image_agree_on_markers() -> None:
    w = World.from_arena("small", seed=0)
    aid = w.add_avatar("seeker", (1.7, 1.0, math.pi / 2))
    f = w.capture(aid, labels=True)
    assert f.labels is not None and f.labels.shape == f.image.shape[:2]
    marker = f.labels == LABEL_MARKER
    assert marker.sum() > 100
    grey = f.image.mean(axis=2)
    # marker pixels are black or white
    assert np.all((grey[marker] < 40) | (grey[marker] > 215))
