"""Ground truth derived from the arena: the ideal occupancy grid and the explorable (reachable) area.

The thesis measures map coverage and accuracy against an "ideal" map generated with zero localization
error (eq. 7.1-1, 7.1-2). `ideal_grid(arena, resolution)` is that map: cell (iy, ix) covers
[ox + ix r, ox + (ix+1) r) x [oy + iy r, oy + (iy+1) r) with origin (ox, oy) = (0, 0), the arena's inner
lower-left corner; it is 1 (occupied) when at least half of the cell is inside a wall, obstacle or the
congregation post (estimated on a 4 x 4 supersampling of each cell), else 0. Rows are y, columns x
(grid[iy, ix]), so `np.flipud(grid)` shows it north up. It decides which cells an avatar can reach.

`surface_grid` is 1 where any solid lies in the cell (at least one of the 4 x 4 samples): a range sensor with
zero localization error marks every cell a surface passes through, the 4 cm panels and the edge cells of
walls included, which the half-cell rule leaves free. The mission metrics score maps against it (docs/team.md,
"Map metrics").

`explorable_grid` marks the free cells reachable from the start poses (4-connected flood fill): the
"reachable cells" of the exploration threshold. Its area is the arena's explorable area (thesis: 24.2 m^2
small, 216 m^2 large).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from haa.sim.arena import Arena

SUPERSAMPLE = 4


class IdealGrid(NamedTuple):
    grid: np.ndarray  # (ny, nx) uint8, 1 occupied, 0 free
    origin: tuple[float, float]  # arena coordinates of the grid's lower-left corner
    resolution: float  # m per cell


def _check_resolution(resolution: float) -> None:
    if not (0.005 <= resolution <= 2.0) or not math.isfinite(resolution):
        raise ValueError(f"resolution: {resolution} m is outside 0.005..2 m")


def coverage(arena: Arena, resolution: float) -> np.ndarray:
    """Fraction (0..1) of each cell inside a solid, from SUPERSAMPLE x SUPERSAMPLE samples per cell."""
    _check_resolution(resolution)
    nx = math.ceil(arena.width / resolution - 1e-9)
    ny = math.ceil(arena.height / resolution - 1e-9)
    k = SUPERSAMPLE
    sub = resolution / k
    fine = np.zeros((ny * k, nx * k), dtype=np.uint8)
    xs = (np.arange(nx * k) + 0.5) * sub
    ys = (np.arange(ny * k) + 0.5) * sub
    for poly in arena.solid_polygons():
        # every solid is a convex counter-clockwise polygon: a sample is inside when it is left of every edge
        px = [p[0] for p in poly]
        py = [p[1] for p in poly]
        j0, j1 = np.searchsorted(xs, [min(px), max(px)])
        i0, i1 = np.searchsorted(ys, [min(py), max(py)])
        if j0 >= j1 or i0 >= i1:
            continue
        X = xs[None, j0:j1]
        Y = ys[i0:i1, None]
        inside = np.ones((i1 - i0, j1 - j0), dtype=bool)
        n = len(poly)
        for q in range(n):
            (ax, ay), (bx, by) = poly[q], poly[(q + 1) % n]
            inside &= (bx - ax) * (Y - ay) - (by - ay) * (X - ax) >= 0
        fine[i0:i1, j0:j1] |= inside.astype(np.uint8)
    # cells beyond the arena (last row/column when the size is not a multiple) count as occupied
    fine[:, xs > arena.width] = 1
    fine[ys > arena.height, :] = 1
    return fine.reshape(ny, k, nx, k).mean(axis=(1, 3))


def ideal_grid(arena: Arena, resolution: float) -> IdealGrid:
    frac = coverage(arena, resolution)
    return IdealGrid((frac >= 0.5).astype(np.uint8), (0.0, 0.0), resolution)


def surface_grid(arena: Arena, resolution: float) -> IdealGrid:
    """1 where any solid lies in the cell (module docstring), else 0."""
    frac = coverage(arena, resolution)
    return IdealGrid((frac > 0.0).astype(np.uint8), (0.0, 0.0), resolution)


def explorable_grid(arena: Arena, resolution: float) -> IdealGrid:
    """1 for free cells reachable from any start pose (4-connected), else 0."""
    g = ideal_grid(arena, resolution)
    free = (g.grid == 0).astype(np.uint8)
    _n, lab = cv2.connectedComponents(free, connectivity=4)
    keep = set()
    for x, y, _ in arena.start_poses:
        ix, iy = int(x / resolution), int(y / resolution)
        if 0 <= iy < lab.shape[0] and 0 <= ix < lab.shape[1] and lab[iy, ix] > 0:
            keep.add(int(lab[iy, ix]))
    out = np.isin(lab, sorted(keep)).astype(np.uint8) if keep else np.zeros_like(free)
    return IdealGrid(out, g.origin, resolution)


def explorable_area(arena: Arena, resolution: float = 0.05) -> float:
    """m^2 of free floor reachable from the start poses.

    Counted as the free fraction of the reachable cells and of the cells around them (so that a cell half
    covered by an obstacle counts half, whichever way the 50 % rule of the grid decided it)."""
    reach = explorable_grid(arena, resolution).grid
    near = cv2.dilate(reach, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=np.uint8))
    frac = coverage(arena, resolution)
    return float(((1.0 - frac) * near).sum()) * resolution * resolution
