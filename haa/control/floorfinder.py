"""AgentSensorFloorFinder's core: the floor in a camera frame, by colour match, mapped to the ground plane.

Thesis App. III (L2983-2985): "Extracts the floor from an image by colour matching with an area sampled
directly in front of the avatar, following the strategy in [112]. The floor region is then transformed from
image space to map space using a planar homography transformation and used to generate a belief template
for JC-SLAM." Ours (docs/control.md):

1. **Reference.** A patch at the bottom centre of the image (`ref_rows` × `ref_cols` of the image size) —
   the floor just in front of the avatar — gives the floor colour: per-channel mean and standard deviation
   (at least `min_std` grey levels, the pixel noise). The thesis takes that patch to be floor; but a camera
   at 0.3 m with a 0.873 rad field of view sees no floor nearer than ~0.85 m, so near a wall the patch is
   wall. `FloorFinder` therefore keeps the floor colour it learnt (from its first patch, or a calibrated
   `prior`): a patch whose mean is not within tolerance of it is refused and the learnt colour is used
   instead; an accepted patch updates it slowly (exponential average, `learn`).
2. **Colour match.** A pixel below the horizon is floor when every channel is within `k` standard deviations
   of the reference mean. A morphological opening removes speckle.
3. **Free boundary.** Per image column, the floor is the run of floor pixels contiguous from the bottom row
   up (the first non-floor pixel above it is an obstacle's, a wall's or an avatar's foot — anything standing
   on the floor). Rows nearer the horizon than the camera's effective range (`frame.max_range`, Table 6.2-4)
   are not trusted: the boundary is clipped there.
4. **Homography.** The boundary pixels (every `step` columns) and the two bottom corners are mapped to the
   floor plane with the frame's floor homography (`CameraFrame.floor_points`: avatar frame, x forward,
   y left, metres): the polygon [bottom-left, boundary left → right ..., bottom-right] is the free floor
   seen, returned as a haa.slam `FloorReading` (the FloorModel turns it into a belief template).

If the reference patch itself is not floor-like (its colour spread is large, e.g. an obstacle right in front),
no reading is made (None): a free-space claim from a wrong reference would erase obstacles.

A finder whose first patch was a wall (a floor-finder agent restarted beside one, after a crash or when the
supervisor adds one) learnt the wall's colour: it matched walls as floor (free space through them) and
refused the floor. So the team shares one floor colour (`learnt` / `adopt`; the agent keeps it in the DDB):
a finder that has not learnt a colour it trusts starts from the team's, and one whose colour is refused
`RELEARN_AFTER` times in a row goes back to it.
Only the image, K, the mount and the time are used: the frame's true pose is not read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from haa.sim.camera import CameraFrame, floor_homography
from haa.slam.sensors import FloorReading

#: accepted patches before a learnt colour is shared with the team (`FloorFinder.confident`)
CONFIDENT_AFTER = 10
#: refusals in a row after which a finder that knows the team's colour takes it again
RELEARN_AFTER = 10


@dataclass(frozen=True)
class FloorConfig:
    ref_rows: float = 0.12  # share of the image height sampled at the bottom
    ref_cols: float = 0.3  # share of the image width sampled at the centre
    k: float = 4.0  # colour tolerance in standard deviations
    min_std: float = 3.0  # grey levels (the renderer's pixel noise is ±6)
    max_ref_std: float = 20.0  # a reference patch noisier than this is not one floor colour
    learn: float = 0.1  # weight of an accepted patch in the learnt floor colour
    step: int = 8  # columns between polygon vertices
    open_px: int = 3  # morphological opening kernel


@dataclass(frozen=True)
class FloorResult:
    polygon: list[tuple[float, float]]  # avatar frame, metres
    mask: np.ndarray  # (H, W) bool floor pixels after the colour match
    boundary: np.ndarray  # (W,) the first floor row of each column (H: no floor)
    columns: np.ndarray  # the columns used for the polygon
    ranges: np.ndarray  # horizontal distance (m) of the boundary at those columns


def reference_patch(image: np.ndarray, config: FloorConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) per channel of the bottom-centre patch."""
    cfg = config or FloorConfig()
    H, W = image.shape[:2]
    r0 = H - max(2, round(H * cfg.ref_rows))
    c0, c1 = round(W * (0.5 - cfg.ref_cols / 2)), round(W * (0.5 + cfg.ref_cols / 2))
    ref = image[r0:H, c0:c1].reshape(-1, image.shape[2] if image.ndim == 3 else 1).astype(np.float32)
    return ref.mean(axis=0), ref.std(axis=0)


def find_floor(
    image: np.ndarray,
    K: np.ndarray,
    mount: tuple[float, float, float, float] = (0.0, 0.0, 0.3, 0.0),
    max_range: float = 3.0,
    config: FloorConfig | None = None,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
) -> FloorResult | None:
    """The free floor polygon of one image; `reference` (mean, std) overrides the bottom patch's colour.
    None when the patch is not one colour and no reference is given."""
    cfg = config or FloorConfig()
    H, W = image.shape[:2]
    if reference is None:
        mean, std = reference_patch(image, cfg)
        if float(std.max()) > cfg.max_ref_std:
            return None
    else:
        mean, std = (np.asarray(v, dtype=np.float32) for v in reference)
    tol = cfg.k * np.maximum(std, cfg.min_std)
    # rows nearer the horizon than max_range are not trusted; the horizon row itself maps to infinity
    f, cy = float(K[1, 1]), float(K[1, 2])
    hc = mount[2]
    v_far = max(0, min(H - 1, math.ceil(cy + f * hc / max_range))) if mount[3] == 0 else 0
    img = image[v_far:].astype(np.float32)
    if img.ndim == 2:
        img = img[..., None]
    mask = np.zeros((H, W), dtype=bool)
    mask[v_far:] = (np.abs(img - mean) <= tol).all(axis=2)
    if cfg.open_px > 1:
        kern = np.ones((cfg.open_px, cfg.open_px), np.uint8)
        mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kern).astype(bool)
    Hm = floor_homography(K, mount)
    # per column: the floor run contiguous from the bottom row (cumulative product upwards)
    run = np.cumprod(mask[::-1, :], axis=0)[::-1, :]
    depth = run.sum(axis=0)  # floor rows from the bottom
    boundary = H - depth  # first floor row; H when the bottom pixel is not floor
    cols = np.unique(np.r_[np.arange(0, W, max(1, cfg.step)), W - 1])
    Hinv = np.linalg.inv(Hm)

    def to_floor(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        p = np.c_[u, v, np.ones(len(u))] @ Hinv.T
        return p[:, :2] / p[:, 2:3]

    # the boundary pixel's lower edge (v + 0.5) is where the floor ends; a column without floor ends at the
    # image bottom (nothing free seen in it)
    vb = np.minimum(boundary[cols].astype(float), H - 1) + 0.5
    pts = to_floor(cols.astype(float), vb)
    bottom = to_floor(np.array([0.0, W - 1.0]), np.array([H - 0.5, H - 0.5]))
    poly = [tuple(map(float, bottom[0])), *[tuple(map(float, p)) for p in pts], tuple(map(float, bottom[1]))]
    # the polygon runs right to left in the image = y decreasing; keep it counter-clockwise in the avatar frame
    poly_arr = np.array(poly)
    area2 = float(np.sum(poly_arr[:, 0] * np.roll(poly_arr[:, 1], -1) - np.roll(poly_arr[:, 0], -1) * poly_arr[:, 1]))
    if area2 < 0:
        poly = poly[::-1]
    ranges = np.hypot(pts[:, 0] - mount[0], pts[:, 1] - mount[1])
    return FloorResult([(x, y) for x, y in poly], mask, boundary, cols, ranges)


class FloorFinder:
    """The floor finder of one avatar's camera: keeps the learnt floor colour between frames (state that an
    agent packs with its configuration)."""

    def __init__(
        self, config: FloorConfig | None = None, prior: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    ) -> None:
        self.cfg = config or FloorConfig()
        self.mean: np.ndarray | None = None if prior is None else np.asarray(prior[0], dtype=np.float32)
        self.std: np.ndarray | None = None if prior is None else np.asarray(prior[1], dtype=np.float32)
        self.refused = 0  # patches that did not look like the learnt floor
        self.accepted = 0  # patches that did (the first one included)
        self.refused_run = 0  # refusals since the last accepted patch
        #: the team's floor colour (`adopt`): where a colour that keeps being refused falls back to
        self.team: tuple[np.ndarray, np.ndarray] | None = None

    def confident(self) -> bool:
        """The learnt colour matched many patches and most of them: worth sharing with the team."""
        return self.mean is not None and self.accepted >= CONFIDENT_AFTER and self.refused <= self.accepted

    def learnt(self) -> dict[str, list[float]] | None:
        """The learnt colour as JSON-able data (`adopt` takes it back)."""
        if self.mean is None or self.std is None:
            return None
        return {"mean": [round(float(x), 2) for x in self.mean], "std": [round(float(x), 2) for x in self.std]}

    def adopt(self, colour: dict[str, Any] | None) -> bool:
        """Take the team's floor colour (another floor finder's `learnt()`, shared through the DDB) as the
        prior of a finder that has not learnt one it trusts; it is also what a colour refused
        `RELEARN_AFTER` times in a row falls back to. False when `colour` is not one."""
        try:
            mean = np.asarray(colour["mean"], dtype=np.float32)  # type: ignore[index]
            std = np.asarray(colour["std"], dtype=np.float32)  # type: ignore[index]
        except (TypeError, KeyError, ValueError):
            return False
        if mean.shape != (3,) or std.shape != (3,) or not (np.isfinite(mean).all() and np.isfinite(std).all()):
            return False
        self.team = (mean, std)
        if not self.confident():
            self.mean, self.std = mean.copy(), std.copy()
            self.accepted, self.refused, self.refused_run = 0, 0, 0
        return True

    def reference(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The colour to match in `image`: its patch when it looks like floor, else the learnt colour."""
        cfg = self.cfg
        mean, std = reference_patch(image, cfg)
        one_colour = float(std.max()) <= cfg.max_ref_std
        if self.mean is None or self.std is None:
            if not one_colour:
                return None
            self.mean, self.std = mean, std
            self.accepted = 1
            return mean, std
        tol = cfg.k * np.maximum(self.std, cfg.min_std)
        if one_colour and bool((np.abs(mean - self.mean) <= tol).all()):
            a = cfg.learn
            self.mean = (1 - a) * self.mean + a * mean
            self.std = (1 - a) * self.std + a * std
            self.accepted += 1
            self.refused_run = 0
        else:
            self.refused += 1
            self.refused_run += 1
            if self.refused_run >= RELEARN_AFTER and self.team is not None:
                # most likely learnt from a wall (a first patch facing one): back to the team's colour
                self.mean, self.std = self.team[0].copy(), self.team[1].copy()
                self.accepted, self.refused, self.refused_run = 0, 0, 0
        return self.mean, self.std

    def find(self, frame: CameraFrame) -> FloorResult | None:
        f = frame
        ref = self.reference(f.image)
        if ref is None:
            return None
        return find_floor(f.image, f.K, f.mount, f.max_range, self.cfg, ref)

    def reading(self, frame: CameraFrame, avatar: str | None = None) -> FloorReading | None:
        """The FloorReading of a haa.sim CameraFrame (image, K, mount, max_range, time, avatar); None when no
        floor is seen (the polygon would have no area)."""
        res = self.find(frame)
        if res is None or float(np.max(res.ranges)) <= 0 or bool((res.boundary >= frame.image.shape[0]).all()):
            return None
        return FloorReading(
            avatar if avatar is not None else frame.avatar,
            float(frame.time),
            tuple(res.polygon),
        )
