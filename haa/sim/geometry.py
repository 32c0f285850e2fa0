"""Plane geometry of the simulator: polygons, edges and vectorised ray casting (numpy).

Everything is in metres and radians, in the arena frame: x to the right, y up, angles counter-clockwise from
+x. Static structure (walls, obstacles, the congregation post) is a set of convex polygons; every polygon
edge is kept as a segment with its outward normal, so that a ray hit says *which face* it struck (landmark
markers live on faces). Moving things (avatars, collectables) are circles.

`cast_segments` and `cast_circles` intersect many rays with many segments / circles at once
(rays x shapes arrays); the camera casts one ray per image column, the sonar a fan of rays per cone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

Point = tuple[float, float]


def polygon_area(poly: Sequence[Point]) -> float:
    """Signed area (shoelace): positive for counter-clockwise vertex order."""
    a = 0.0
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        a += x1 * y2 - x2 * y1
    return a / 2.0


def ccw(poly: Sequence[Point]) -> list[Point]:
    """The polygon with counter-clockwise vertex order."""
    pts = [(float(x), float(y)) for x, y in poly]
    return pts if polygon_area(pts) >= 0 else pts[::-1]


def is_convex(poly: Sequence[Point], eps: float = 1e-12) -> bool:
    """True when the (simple) polygon is strictly convex: every turn has the same sign, no zero-area turn."""
    n = len(poly)
    if n < 3:
        return False
    sign = 0
    for i in range(n):
        x0, y0 = poly[i]
        x1, y1 = poly[(i + 1) % n]
        x2, y2 = poly[(i + 2) % n]
        c = (x1 - x0) * (y2 - y1) - (y1 - y0) * (x2 - x1)
        if abs(c) <= eps:
            return False
        s = 1 if c > 0 else -1
        if sign == 0:
            sign = s
        elif s != sign:
            return False
    return True


def box_polygon(cx: float, cy: float, w: float, h: float, angle: float = 0.0) -> list[Point]:
    """Corners (counter-clockwise) of a w x h rectangle centred on (cx, cy), rotated by `angle`."""
    c, s = math.cos(angle), math.sin(angle)
    out = []
    for dx, dy in ((-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)):
        out.append((cx + c * dx - s * dy, cy + s * dx + c * dy))
    return out


def thick_segment(a: Point, b: Point, thickness: float) -> list[Point]:
    """The rectangle (counter-clockwise) covering segment a-b widened to `thickness` (ends not extended)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    n = math.hypot(dx, dy)
    ox, oy = -dy / n * thickness / 2, dx / n * thickness / 2
    return ccw([(a[0] - ox, a[1] - oy), (b[0] - ox, b[1] - oy), (b[0] + ox, b[1] + oy), (a[0] + ox, a[1] + oy)])


def point_in_polygon(x: float, y: float, poly: Sequence[Point]) -> bool:
    """Even-odd rule; points on the boundary may go either way."""
    inside = False
    n = len(poly)
    j = n - 1
    for i in range(n):
        xi, yi = poly[i]
        xj, yj = poly[j]
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            inside = not inside
        j = i
    return inside


def points_in_polygon(xy: np.ndarray, poly: Sequence[Point]) -> np.ndarray:
    """Vectorised even-odd test of points (k, 2) against one polygon -> bool (k,)."""
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), dtype=bool)
    n = len(poly)
    j = n - 1
    for i in range(n):
        xi, yi = poly[i]
        xj, yj = poly[j]
        if yi != yj:
            cond = ((yi > y) != (yj > y)) & (x < (xj - xi) * (y - yi) / (yj - yi) + xi)
            inside ^= cond
        j = i
    return inside


def segment_distance(p: Point, a: Point, b: Point) -> tuple[float, float]:
    """(distance from p to segment a-b, parameter of the closest point along a-b in metres from a)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    L2 = dx * dx + dy * dy
    t = ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / L2 if L2 else 0.0
    t = min(1.0, max(0.0, t))
    qx, qy = a[0] + t * dx, a[1] + t * dy
    return math.hypot(p[0] - qx, p[1] - qy), t * math.sqrt(L2)


@dataclass(frozen=True)
class Edges:
    """All faces of the static structure as arrays (n = number of edges).

    `a`, `b`: end points (n, 2); `normal`: outward unit normals (n, 2); `length`: (n,);
    `owner`: index of the polygon the edge belongs to (n,); `kind`: structure kind code of that polygon (n,).
    """

    a: np.ndarray
    b: np.ndarray
    normal: np.ndarray
    length: np.ndarray
    owner: np.ndarray
    kind: np.ndarray

    @staticmethod
    def from_polygons(polys: Sequence[Sequence[Point]], kinds: Sequence[int]) -> Edges:
        a, b, own, kind = [], [], [], []
        for i, poly in enumerate(polys):
            p = ccw(poly)
            for k in range(len(p)):
                a.append(p[k])
                b.append(p[(k + 1) % len(p)])
                own.append(i)
                kind.append(kinds[i])
        A = np.asarray(a, dtype=float).reshape(-1, 2)
        B = np.asarray(b, dtype=float).reshape(-1, 2)
        d = B - A
        length = np.hypot(d[:, 0], d[:, 1])
        # counter-clockwise polygon: the outside is to the right of each edge
        normal = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.where(length > 0, length, 1.0)[:, None]
        return Edges(A, B, normal, length, np.asarray(own, dtype=int), np.asarray(kind, dtype=int))

    def __len__(self) -> int:
        return len(self.a)


def cast_segments(
    ox: float, oy: float, dirs: np.ndarray, a: np.ndarray, b: np.ndarray, max_range: float = math.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays from (ox, oy) with unit directions `dirs` (m, 2) against segments a-b (n, 2).

    Returns (t, index, s): distance along each ray (inf when nothing within `max_range`), the segment hit
    (-1 for none) and the hit's parameter along that segment in [0, 1].
    """
    m = len(dirs)
    if len(a) == 0:
        return np.full(m, np.inf), np.full(m, -1), np.zeros(m)
    ex = (b[:, 0] - a[:, 0])[None, :]
    ey = (b[:, 1] - a[:, 1])[None, :]
    dx = dirs[:, 0][:, None]
    dy = dirs[:, 1][:, None]
    px = (a[:, 0] - ox)[None, :]
    py = (a[:, 1] - oy)[None, :]
    denom = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / denom
        t = (px * ey - py * ex) * inv
        s = (px * dy - py * dx) * inv
    ok = (denom != 0) & (t >= 0) & (s >= 0) & (s <= 1) & (t <= max_range)
    t = np.where(ok, t, np.inf)
    idx = np.argmin(t, axis=1)
    rows = np.arange(m)
    tbest = t[rows, idx]
    hit = np.isfinite(tbest)
    return tbest, np.where(hit, idx, -1), np.where(hit, s[rows, idx], 0.0)


def cast_circles(
    ox: float, oy: float, dirs: np.ndarray, centres: np.ndarray, radii: np.ndarray, max_range: float = math.inf
) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays with circles (k, 2)/(k,); circles containing the origin are ignored.

    Returns (t, index) like `cast_segments` (no parameter).
    """
    m = len(dirs)
    if len(centres) == 0:
        return np.full(m, np.inf), np.full(m, -1)
    cx = (centres[:, 0] - ox)[None, :]
    cy = (centres[:, 1] - oy)[None, :]
    proj = dirs[:, 0][:, None] * cx + dirs[:, 1][:, None] * cy
    d2 = cx * cx + cy * cy - proj * proj
    r2 = (radii * radii)[None, :]
    disc = r2 - d2
    with np.errstate(invalid="ignore"):
        t = proj - np.sqrt(disc)
    outside = (cx * cx + cy * cy) > r2
    ok = (disc >= 0) & (t >= 0) & outside & (t <= max_range)
    t = np.where(ok, t, np.inf)
    idx = np.argmin(t, axis=1)
    rows = np.arange(m)
    tbest = t[rows, idx]
    return tbest, np.where(np.isfinite(tbest), idx, -1)


def wrap_angle(a: float) -> float:
    """Angle in (-pi, pi]."""
    a = math.fmod(a + math.pi, 2 * math.pi)
    if a <= 0:
        a += 2 * math.pi
    return a - math.pi
