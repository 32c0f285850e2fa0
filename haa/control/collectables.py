"""The Forage sensor's core: red collectables in a camera frame → sightings (range, bearing, pixel box).

haa-sim draws a collectable as a red cylinder (`COLLECTABLE_COLOUR`, radius r = 5 cm, height h = 10 cm,
haa/sim/arena.py) standing on the floor; the camera is a pinhole at `mount` = (mx, my, height, pitch) in the
avatar frame (x forward, y left). `CollectableDetector` finds them the way `haa.control.landmarks` finds
markers: from the image, the intrinsics K, the mount and the time only — the frame's true pose is ground
truth and is never read. docs/control.md ("Collectables") reports its detection rate and errors.

1. **Colour.** A pixel is the collectable's red when its HSV colour lies in a window derived from the
   renderer's palette (`colour_threshold`, not tuned on frames): hue within half the hue distance to the
   nearest other colour of the scene that has a hue at all (the floor, 35.6° against the red's 2.0°:
   ±16.8°), saturation above the midpoint between the red's and that colour's (0.86 and 0.38: ≥ 0.62),
   value above half the red's (≥ 0.42: shading down to 50 % still passes, and the dark pixels — sky, black
   marker cells — whose hue the 6 grey-level pixel noise turns into any colour, are out). The red with the
   renderer's noise stays inside (hue 0-3.9°, saturation ≥ 0.86); every other palette colour, at every shade
   and with the noise, stays outside (tests). Avatars are green, the post yellow, obstacles blue: nothing
   else in haa-sim is red.
2. **Blobs.** 8-connected components of the mask (`cv2.connectedComponentsWithStats`); a blob under 2 × 2
   pixels has no edge to measure and is dropped (a collectable at the effective range is ≥ 7 × 7 px: 2rf/R
   and hf/R for both cameras). Per image column the blob's bottom row is the cylinder's foot on the floor
   and its top row the cylinder's top, both at the depth of its near face (how haa-sim draws it).
3. **Range.** A bottom row v maps, through `CameraFrame.floor_homography()`, from pixel (u, v + ½) — the
   foot lies between the last red pixel centre and the next one; pixel centres are on integer coordinates —
   to the floor point where the column's ray meets the near face; the collectable's centre is r farther
   along the ray through its centre. A blob that reaches the bottom image row (a collectable nearer than the
   floor the camera sees: 0.86 m basic, 0.36 m enhanced) has no foot in the image: its top edge (u, v − ½)
   is mapped instead through the homography of the plane at height h (a camera at height − h over the
   floor), down to the range where the top leaves the image too (0.57 m basic, 0.24 m enhanced). (haa-sim
   draws the top at the near face's depth, like the foot; a true 3D view would show the top disc, whose far
   rim is 2r deeper: this fallback is tied to the renderer.) A blob whose top row and bottom row both touch
   the image border has no edge and is dropped; so is one whose edge maps behind the camera (above the
   horizon: not standing on the floor).
4. **Bearing.** The blob's side edges (u0 − ½, u1 + ½) are the rays tangent to the cylinder; the bearing
   of its centre bisects them (exact for a circle). A side is *hidden* when it touches the left or right
   image border, or when the neighbouring column has something nearer than the collectable below its foot:
   any pixel from the foot's row down to the image bottom that is not floor-coloured, the floor colour
   being the mean of the pixels just below the blob (within 2 × the noise amplitude: the floor is flat in
   haa-sim and every other palette colour, at any shade, is ≥ 24 grey levels from it on some channel). In
   the top-edge case the foot is out of sight: only the border counts, and a side where the top edge is at
   its lowest is hidden by the image's bottom (a cylinder's top edge rises towards its tangent sides; one
   very near shows as two "horns" whose middle is below the image). With one side
   hidden the centre is solved from the other (tangent) side and the foot at the column nearest the centre
   (the circle at distance r from the tangent ray through that foot point); with both hidden, from the
   nearest foot (the nearest point of a circle lies on the line to its centre) if it is inside the blob,
   else from the middle of the blob if at least half the expected width 2·asin(r/R) shows (then off by at
   most half the hidden width, ≤ r/2 across the ray), else the blob is dropped (the centre may be out of
   sight). `partial` marks these sightings. Two sightings
   whose centres are closer than r (two horns of one collectable) are kept once, the larger.
5. **Checks.** The blob's top row must match a 10 cm object at the measured range (within 2 px + 25 %: a red
   thing of another size is not a collectable); sightings farther than the camera's effective range
   (`frame.max_range`, Table 6.2-4) are dropped, like the thesis' sensor spec; the rest is sorted by range.

**Two collectables that overlap in the image.** haa-sim draws only the nearest short object per column, so
the nearer one is whole and the farther one shows only beside it: when their rows overlap they form one
blob. The blob is split greedily: the nearest foot gives a circle (centre r behind it), the columns that
circle spans (± 1 px) are one collectable, the columns left over on either side (≥ 2 px wide) are others,
each measured with its side toward the nearer one hidden. Two at the same depth side by side at long range
(feet on the same row) are laid out from the left, one width each. A farther one whose rows do not overlap
the nearer one's is its own blob with the side toward the nearer one hidden (the nearer one's red is below
its foot in the neighbouring column). A farther collectable wholly behind a nearer one is not seen at all.

The range is quantized by whole pixels: the foot row moves one pixel per z²/(f·height) metres of depth, 8.7
cm at 3 m (basic) and 18.7 cm at 4 m (enhanced): the range error grows with the square of the distance.
`to_map` turns sightings and an avatar pose *estimate* into arena-frame points.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from haa.sim.arena import COLLECTABLE_HEIGHT, COLLECTABLE_RADIUS
from haa.sim.camera import (
    AVATAR_COLOUR,
    COLLECTABLE_COLOUR,
    FLOOR,
    KIND_COLOURS,
    NOISE,
    SKY,
    CameraFrame,
    floor_homography,
)

RGB = tuple[int, int, int]
Mount = tuple[float, float, float, float]

#: every colour haa-sim draws besides the collectables' red (structures are shaded, which keeps hue and
#: saturation; marker cells are (20, 20, 20) and (235, 235, 235))
SCENE_COLOURS: tuple[RGB, ...] = (
    FLOOR,
    SKY,
    AVATAR_COLOUR,
    *KIND_COLOURS.values(),
    (20, 20, 20),
    (235, 235, 235),
)


@dataclass(frozen=True)
class ColourThreshold:
    """An HSV window: hue (degrees) within `hue_tol` of `hue`, saturation ≥ `s_min`, value ≥ `v_min` (0..1)."""

    hue: float
    hue_tol: float
    s_min: float
    v_min: float

    def mask(self, image: np.ndarray) -> np.ndarray:
        """uint8 mask (255 in the window) of an RGB uint8 image."""
        hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)  # H in [0, 180) (2° units), S and V in [0, 255]
        h0, tol = self.hue / 2, self.hue_tol / 2
        s, v = math.ceil(self.s_min * 255), math.ceil(self.v_min * 255)
        lo, hi = math.ceil(h0 - tol), math.floor(h0 + tol)
        m = np.zeros(image.shape[:2], dtype=np.uint8)
        for a, b in ((lo, hi), (lo + 180, hi + 180), (lo - 180, hi - 180)):
            a, b = max(a, 0), min(b, 179)
            if a <= b:
                m = cv2.bitwise_or(m, cv2.inRange(hsv, (a, s, v), (b, 255, 255)))
        return m


def _hsv(c: Sequence[float]) -> tuple[float, float, float]:
    h, s, v = colorsys.rgb_to_hsv(*(float(x) / 255 for x in c))
    return h * 360, s, v


def _hue_dist(a: float, b: float) -> float:
    d = abs(a - b) % 360
    return min(d, 360 - d)


def colour_threshold(
    target: Sequence[float] = COLLECTABLE_COLOUR,
    others: Iterable[Sequence[float]] = SCENE_COLOURS,
    noise: float = NOISE,
) -> ColourThreshold:
    """The HSV window of `target` against the other colours of the scene (see the module docstring).

    A colour "has a hue" when its saturation exceeds what pixel noise of ±`noise` grey levels gives a grey of
    its brightness (2·noise / max channel). The window reaches half way to the nearest such colour in hue and
    in saturation; the value threshold is half the target's.
    """
    h, s, v = _hsv(target)
    hued = []
    for c in others:
        hc, sc, _ = _hsv(c)
        if sc > 2 * noise / max(max(c), 1):
            hued.append((_hue_dist(h, hc), sc))
    if not hued:
        return ColourThreshold(h, 30.0, s / 2, v / 2)
    dist, s_near = min(hued)
    return ColourThreshold(h, dist / 2, (s + s_near) / 2, v / 2)


@dataclass(frozen=True)
class CollectableSighting:
    range: float  # m, from the avatar's centre to the collectable's centre
    bearing: float  # rad, relative to the heading (left positive)
    box: tuple[int, int, int, int]  # the blob's pixels: u0, v0, u1, v1 (inclusive)
    xy: tuple[float, float]  # the collectable's centre in the avatar frame (x forward, y left), m
    edge: str  # "bottom": range from the foot on the floor; "top": from the top edge (foot below the image)
    partial: bool  # a side hidden (image border, something nearer): the bearing is from the other side
    pixels: int  # red pixels of the blob (of its share, for a split blob)


@dataclass(frozen=True)
class CollectableReading:
    """The collectables seen in one camera frame (avatar frame), at the frame's time."""

    avatar: str
    t: float
    sightings: tuple[CollectableSighting, ...]


def _check_inputs(image: object, K: object, mount: object) -> tuple[np.ndarray, np.ndarray, Mount]:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image: expected a numpy array (H, W, 3) RGB uint8, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected shape (H, W, 3) RGB, got {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"image: expected dtype uint8, got {image.dtype}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise ValueError(f"image: empty or degenerate, shape {image.shape}")
    Km = np.asarray(K, dtype=float)
    if Km.shape != (3, 3) or not np.isfinite(Km).all() or not Km[0, 0] > 0 or not Km[1, 1] > 0:
        raise ValueError("K: expected 3x3 finite intrinsics with positive focal lengths")
    try:
        m = tuple(float(x) for x in mount)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError(f"mount: expected (x, y, height, pitch), got {mount!r}") from None
    if len(m) != 4 or not all(math.isfinite(x) for x in m) or not m[2] > 0:
        raise ValueError(f"mount: expected (x, y, height > 0, pitch), finite, got {mount}")
    return np.ascontiguousarray(image), Km, (m[0], m[1], m[2], m[3])


def _dedupe(sightings: list[CollectableSighting], radius: float) -> list[CollectableSighting]:
    """Sightings of one collectable seen as two blobs (centres closer than `radius`: two real ones are at
    least 2 radius apart) are kept once, the one with more pixels; sorted by range."""
    keep: list[CollectableSighting] = []
    for s in sorted(sightings, key=lambda s: -s.pixels):
        if all(math.hypot(s.xy[0] - k.xy[0], s.xy[1] - k.xy[1]) >= radius for k in keep):
            keep.append(s)
    keep.sort(key=lambda s: s.range)
    return keep


def _to_plane(Hinv: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    p = np.c_[u, v, np.ones(len(u))] @ Hinv.T
    return p[:, :2] / p[:, 2:3]


class CollectableDetector:
    """Red-cylinder detection (reuse one per camera: the colour window is computed once)."""

    def __init__(
        self,
        radius: float = COLLECTABLE_RADIUS,
        height: float = COLLECTABLE_HEIGHT,
        threshold: ColourThreshold | None = None,
        size_tolerance: float = 0.25,
    ) -> None:
        if not (radius > 0 and height > 0):
            raise ValueError(f"radius, height: must be > 0, got {radius}, {height}")
        self.radius = radius
        self.height = height
        self.threshold = threshold or colour_threshold()
        self.size_tolerance = size_tolerance

    # ------------------------------------------------------------------ public
    def detect(
        self, image: np.ndarray, K: np.ndarray, mount: Mount = (0.0, 0.0, 0.3, 0.0), max_range: float = math.inf
    ) -> list[CollectableSighting]:
        """Sightings in an RGB uint8 image (H, W, 3) taken with intrinsics K from `mount`, sorted by range."""
        img, Km, mnt = _check_inputs(image, K, mount)
        mask = self.threshold.mask(img)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if n <= 1:
            return []
        H0 = floor_homography(Km, mnt)
        Hs = {"bottom": (H0, np.linalg.inv(H0))}
        if mnt[2] > self.height:
            Ht = floor_homography(Km, (mnt[0], mnt[1], mnt[2] - self.height, mnt[3]))
            Hs["top"] = (Ht, np.linalg.inv(Ht))
        out: list[CollectableSighting] = []
        for k in range(1, n):
            x0, y0, w, h, _area = (int(v) for v in stats[k])
            if w < 2 or h < 2:
                continue
            sub = lab[y0 : y0 + h, x0 : x0 + w] == k
            out += self._blob(img, sub, x0, y0, Hs, mnt, max_range)
        return _dedupe(out, self.radius)

    def sightings(self, frame: CameraFrame) -> list[CollectableSighting]:
        """`detect` on a haa.sim CameraFrame (its image, K, mount and max_range; never its pose)."""
        return self.detect(frame.image, frame.K, frame.mount, frame.max_range)

    def reading(self, frame: CameraFrame, avatar: str | None = None) -> CollectableReading:
        return CollectableReading(
            avatar if avatar is not None else frame.avatar, float(frame.time), tuple(self.sightings(frame))
        )

    # ------------------------------------------------------------------ one blob
    def _blob(
        self,
        img: np.ndarray,
        sub: np.ndarray,
        x0: int,
        y0: int,
        Hs: dict[str, tuple[np.ndarray, np.ndarray]],
        mount: Mount,
        max_range: float,
    ) -> list[CollectableSighting]:
        Himg = img.shape[0]
        h, w = sub.shape
        top = y0 + np.argmax(sub, axis=0)  # first red row per column
        bot = y0 + h - 1 - np.argmax(sub[::-1], axis=0)  # last red row per column
        cols = x0 + np.arange(w)
        if bot.max() < Himg - 1:
            edge, rows = "bottom", bot + 0.5
        elif "top" in Hs and top.min() > 0:
            edge, rows = "top", top - 0.5
        else:
            return []  # neither the foot nor the top edge is in the image
        Hm, Hinv = Hs[edge]
        cam = np.array(mount[:2])
        Q = _to_plane(Hinv, cols.astype(float), rows)  # near-face points in the avatar frame
        rel = Q - cam
        dist = np.hypot(rel[:, 0], rel[:, 1])
        if not (np.isfinite(dist).all() and (rel[:, 0] > 0).all()):
            return []  # above the horizon of that plane: not something on the floor
        Q1 = _to_plane(Hinv, cols.astype(float), rows - 1.0) - cam  # one row up: farther, on either plane
        far = np.hypot(Q1[:, 0], Q1[:, 1])
        step = np.where(np.isfinite(far) & (Q1[:, 0] > 0), np.abs(far - dist), np.inf)
        # tangent angles of the column borders (u - 1/2), from the camera, on this plane
        edges_uv = np.r_[cols - 0.5, cols[-1] + 0.5]
        erow = np.r_[rows, rows[-1]]
        B = _to_plane(Hinv, edges_uv, erow) - cam
        border_ang = np.arctan2(B[:, 1], B[:, 0])  # decreasing with u (left is positive)
        floor_ref = self._floor_ref(img, cols, bot)

        def angle_to_col(a: float) -> float:
            # column (fractional) whose ray has angle a on the plane
            p = Hm @ np.array([cam[0] + math.cos(a), cam[1] + math.sin(a), 1.0])
            return float(p[0] / p[2])

        out = []
        for lo, hi, hid_l, hid_r in self._split(dist, step, border_ang):
            n_px = int(sub[:, lo : hi + 1].sum())
            left_ok = not hid_l and (lo > 0 or self._side_visible(img, int(cols[0]) - 1, int(bot[0]), floor_ref))
            right_ok = not hid_r and (hi < w - 1 or self._side_visible(img, int(cols[-1]) + 1, int(bot[-1]), floor_ref))
            if edge == "top":
                # a cylinder's top edge rises towards its tangent sides; a side where it is lowest goes on below
                # the image (the near face is lowest in the middle: one this near can show as two "horns")
                tt = top[lo : hi + 1]
                low = int(tt.max()) > int(tt.min())
                left_ok &= not (low and int(tt[0]) == int(tt.max()))
                right_ok &= not (low and int(tt[-1]) == int(tt.max()))
            c = self._centre(dist, step, rel, border_ang, lo, hi, left_ok, right_ok, angle_to_col, x0)
            if c is None:
                continue
            C = cam + c
            rng = float(math.hypot(C[0], C[1]))
            if not rng <= max_range:
                continue
            if edge == "bottom" and "top" in Hs and not self._size_ok(Hs, c, cam, top, lo, hi, x0):
                continue
            box = (int(cols[lo]), int(top[lo : hi + 1].min()), int(cols[hi]), int(bot[lo : hi + 1].max()))
            out.append(
                CollectableSighting(
                    rng,
                    math.atan2(C[1], C[0]),
                    box,
                    (float(C[0]), float(C[1])),
                    edge,
                    not (left_ok and right_ok),
                    n_px,
                )
            )
        return out

    def _split(self, dist: np.ndarray, step: np.ndarray, border_ang: np.ndarray) -> list[tuple[int, int, bool, bool]]:
        """(lo, hi, left hidden, right hidden): column ranges (inclusive, blob-relative) of the collectables in
        one blob, with the sides that a nearer one of the same blob hides.

        `dist`: the near-face distance measured in each column, `step`: how much farther the foot would be one
        pixel row up (the foot lies in [dist - step/2, dist + step/2]: whole pixels)."""
        r = self.radius
        px = abs(float(border_ang[0] - border_ang[-1])) / len(dist)  # one column's angle
        todo = [(0, len(dist) - 1, False, False)]
        out = []
        while todo:
            lo, hi, hid_l, hid_r = todo.pop()
            d, sd = dist[lo : hi + 1], step[lo : hi + 1]
            # columns whose foot could be the nearest one, given whole-pixel rows
            near = np.nonzero(d - sd / 2 <= float((d + sd / 2).min()))[0]
            alpha = math.asin(min(1.0, r / (float(d.min()) + r)))
            a_lo, a_hi = float(border_ang[lo + near[0]]), float(border_ang[lo + near[-1] + 1])
            if border_ang[lo] - border_ang[hi + 1] <= 2 * alpha + 2 * px:
                out.append((lo, hi, hid_l, hid_r))  # one collectable wide: no split
                continue
            if a_lo - a_hi > 2 * alpha + 2 * px:
                centre = a_lo - alpha  # nearest feet wider than one collectable: lay them out from the left
            else:
                centre = (a_lo + a_hi) / 2
            mid_ang = (border_ang[lo : hi + 1] + border_ang[lo + 1 : hi + 2]) / 2
            inside = np.nonzero(np.abs(mid_ang - centre) <= alpha + px)[0]
            if len(inside) == 0:
                inside = near
            s0, s1 = lo + int(inside[0]), lo + int(inside[-1])
            # a boundary within 2 columns of a depth step (more than 2 foot rows) moves onto the step: the
            # predicted span is only as good as the range it comes from
            s0, s1 = self._snap(dist, step, lo, hi, s0, left=True), self._snap(dist, step, lo, hi, s1, left=False)
            # leftovers narrower than 2 columns belong to this one (quantization at its rim); wider ones are
            # farther collectables, hidden on the side of this (nearer) one, whose side there is its own
            seg_l, seg_r = hid_l, hid_r
            if s0 - lo < 2:
                s0 = lo
            else:
                todo.append((lo, s0 - 1, hid_l, True))
                seg_l = False
            if hi - s1 < 2:
                s1 = hi
            else:
                todo.append((s1 + 1, hi, True, hid_r))
                seg_r = False
            out.append((s0, s1, seg_l, seg_r))
        out.sort()
        return out

    @staticmethod
    def _snap(dist: np.ndarray, step: np.ndarray, lo: int, hi: int, s: int, left: bool) -> int:
        # boundary between columns j and j + 1, for the columns around it
        js = [j for j in range(s - 3, s + 3) if lo <= j < hi]
        if not js:
            return s
        jumps = [abs(float(dist[j + 1] - dist[j])) - 2 * float(min(step[j], step[j + 1])) for j in js]
        best = int(np.argmax(jumps))
        if jumps[best] <= 0:
            return s
        return js[best] + 1 if left else js[best]

    def _centre(
        self,
        dist: np.ndarray,
        step: np.ndarray,
        rel: np.ndarray,
        border_ang: np.ndarray,
        lo: int,
        hi: int,
        left_ok: bool,
        right_ok: bool,
        angle_to_col: Callable[[float], float],
        x0: int,
    ) -> np.ndarray | None:
        """The collectable's centre relative to the camera (floor plane), or None when it cannot be placed."""
        r = self.radius

        def col_index(a: float) -> int:
            u = angle_to_col(a) - x0
            return int(min(max(round(u), lo), hi))

        def unit(a: float) -> np.ndarray:
            return np.array([math.cos(a), math.sin(a)])

        aL, aR = float(border_ang[lo]), float(border_ang[hi + 1])
        if left_ok and right_ok:
            a = (aL + aR) / 2
            return unit(a) * (float(dist[col_index(a)]) + r)
        if left_ok or right_ok:
            # tangent ray at angle at; the centre is r from it on the blob's side, and r from a foot point
            at = aL if left_ok else aR
            side = -1.0 if left_ok else 1.0  # towards smaller angles (right) from the left edge
            e = unit(at)
            nrm = side * np.array([-e[1], e[0]])
            R = float(dist[lo : hi + 1].min()) + r
            C = unit(at) * R
            for _ in range(2):
                alpha = math.asin(min(1.0, r / max(R, r)))
                k = col_index(at + side * alpha)
                q = rel[k] - r * nrm
                along = float(q @ e)
                perp2 = float(q @ q) - along * along
                C = along * e + math.sqrt(max(0.0, r * r - perp2)) * e + r * nrm
                R = float(np.hypot(*C))
            return C
        d, sd = dist[lo : hi + 1], step[lo : hi + 1]
        near = np.nonzero(d - sd / 2 <= float((d + sd / 2).min()))[0]
        if near[0] == 0 or near[-1] == len(d) - 1:
            # the nearest foot is at a hidden side: the centre may be out of sight. If at least half the
            # width shows, the middle of what shows is off by at most half the hidden width (≤ r/2 across)
            R = float(d.min()) + r
            if aL - aR < math.asin(min(1.0, r / R)):
                return None
            return unit((aL + aR) / 2) * R
        k = int(near[np.argmin(d[near])])
        a = (float(border_ang[lo + near[0]]) + float(border_ang[lo + near[-1] + 1])) / 2
        return unit(a) * (float(d[k]) + r)

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _floor_ref(img: np.ndarray, cols: np.ndarray, bot: np.ndarray) -> np.ndarray | None:
        """Mean colour of the floor just below the blob's foot (None when the foot is at the image bottom)."""
        Himg = img.shape[0]
        pts = [(int(b) + dv, int(u)) for u, b in zip(cols, bot, strict=True) for dv in (1, 2) if b + dv < Himg]
        if not pts:
            return None
        rr, cc = np.array(pts).T
        return np.asarray(img[rr, cc].mean(axis=0))

    @staticmethod
    def _side_visible(img: np.ndarray, u: int, foot: int, floor_ref: np.ndarray | None) -> bool:
        """Is the blob's side next to column u its true silhouette (nothing nearer in column u)?"""
        if not 0 <= u < img.shape[1]:
            return False  # cut by the image border
        if floor_ref is None:
            return True  # foot below the image: only the border can be told
        below = img[foot + 1 :, u].astype(float)
        return bool((np.abs(below - floor_ref).max(axis=1, initial=0.0) <= 2 * NOISE).all()) if len(below) else True

    def _size_ok(
        self,
        Hs: dict[str, tuple[np.ndarray, np.ndarray]],
        c: np.ndarray,
        cam: np.ndarray,
        top: np.ndarray,
        lo: int,
        hi: int,
        x0: int,
    ) -> bool:
        """The top row at the centre column is where a cylinder of `height` at that range has its top."""
        R = float(np.hypot(*c))
        near = np.array([*(cam + c * (R - self.radius) / R), 1.0])  # near face on the ray through the centre
        pt, pb = Hs["top"][0] @ near, Hs["bottom"][0] @ near
        u, v_top, v_foot = pt[0] / pt[2], pt[1] / pt[2], pb[1] / pb[2]
        k = int(min(max(round(u - x0), lo), hi))
        return abs((float(top[k]) - 0.5) - v_top) <= 2.0 + self.size_tolerance * abs(v_foot - v_top)


def to_map(
    sightings: Iterable[CollectableSighting | tuple[float, float]], pose: Sequence[float]
) -> list[tuple[float, float]]:
    """Arena-frame positions of sightings (or (range, bearing) pairs) seen from an avatar pose estimate
    (x, y, theta): (x + range cos(theta + bearing), y + range sin(theta + bearing)). Pure; no ground truth."""
    if len(pose) != 3 or not all(math.isfinite(float(v)) for v in pose):
        raise ValueError(f"pose: expected finite (x, y, theta), got {tuple(pose)}")
    x, y, th = (float(v) for v in pose)
    out = []
    for s in sightings:
        r, b = (s.range, s.bearing) if isinstance(s, CollectableSighting) else (float(s[0]), float(s[1]))
        if not (math.isfinite(r) and math.isfinite(b) and r >= 0):
            raise ValueError(f"sighting: range must be finite and >= 0 and bearing finite, got ({r}, {b})")
        out.append((x + r * math.cos(th + b), y + r * math.sin(th + b)))
    return out
