"""Probabilistic occupancy grid (thesis §5.1.2) with the Bayes update of eq. 5.1-2, held as log-odds.

Each cell C holds p(C), the probability that it is occupied (0.5: unknown). A sensor reading s with a
sensor model value p(s|C) updates it by Bayes' rule

    p(C|s) = p(s|C) p(C) / (p(C) p(s|C) + (1 - p(C)) (1 - p(s|C)))                      (5.1-2)

which in log-odds l = log(p / (1 - p)) is l ← l + logit(p(s|C)): additive, so map updates commute (up to
rounding). Log-odds are clamped to ±`clamp` (default logit 0.999) so a cell can still change its mind.

With a particle filter "the sensor model is simply applied at each particle and adjusted by the particle
weight" (§5.1.4). We read that as a mixture: particle i proposes p_i(s|C) for the cells of its belief
template (a cell outside particle i's template gets 0.5, "no information"), and the cell is updated once
with p(s|C) = Σ_i w_i p_i(s|C) = 0.5 + Σ_i w_i (p_i(s|C) − 0.5). `mixture_update` does this for all
particles and cells at once with `np.bincount` (no Python loop).

The observation density of the same reading for particle i is the Bayes normalizer of eq. 5.1-2 over its
template — how probable the reading is under the current map if the avatar were where particle i says:

    log g_i = τ Σ_k log(2 (m_k p_ik + (1 − m_k)(1 − p_ik)))

(m_k the map's p(C) at the template cell; the factor 2 makes an unknown cell contribute exactly 0).
τ ∈ (0, 1] tempers the product, because neighbouring cells are not independent evidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def logit(p: np.ndarray | float) -> np.ndarray | float:
    return np.log(p) - np.log1p(-p)


@dataclass(frozen=True)
class GridSpec:
    """Grid geometry: cells of `resolution` m covering [x0, x0 + width) × [y0, y0 + height)."""

    width: float
    height: float
    resolution: float = 0.1
    x0: float = 0.0
    y0: float = 0.0

    def __post_init__(self) -> None:
        for name in ("width", "height", "resolution"):
            if not getattr(self, name) > 0:
                raise ValueError(f"grid.{name}: must be > 0, got {getattr(self, name)}")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) = (y cells, x cells)."""
        return (math.ceil(self.height / self.resolution - 1e-9), math.ceil(self.width / self.resolution - 1e-9))


class OccupancyGrid:
    """Log-odds occupancy grid; `prob()` gives p(C) per cell (rows = y, cols = x).

    Internally the arrays have a one-cell border that always stays 0.5 ("unknown"): a template point
    outside the map is clipped onto it, so it contributes nothing and no validity mask is needed in the
    hot paths. Flat cell indices (`cells`) refer to the padded array.
    """

    def __init__(self, spec: GridSpec, clamp: float = float(logit(0.999)), map_particles: int = 256) -> None:
        self.spec = spec
        self.map_particles = map_particles  # mixture updates use at most this many particles (0: all)
        self.rows, self.cols = spec.shape
        self.clamp = clamp
        self.prow = self.cols + 2  # padded row length
        self._lo = np.zeros((self.rows + 2) * self.prow)  # log-odds, padded, flat
        self._p = np.full((self.rows + 2) * self.prow, 0.5, dtype=np.float32)  # p(C) kept in step
        border = np.ones((self.rows + 2, self.prow), dtype=bool)
        border[1:-1, 1:-1] = False
        self._border = np.flatnonzero(border)
        self.updates = 0
        self._df: np.ndarray | None = None
        self._df_version = -1

    @property
    def padded_size(self) -> int:
        return self._lo.shape[0]

    @property
    def log_odds(self) -> np.ndarray:
        """(rows, cols) view of the log-odds."""
        return self._lo.reshape(self.rows + 2, self.prow)[1:-1, 1:-1]

    def prob(self) -> np.ndarray:
        """p(C) per cell, (rows, cols) float64 copy."""
        return self._p.reshape(self.rows + 2, self.prow)[1:-1, 1:-1].astype(np.float64)

    def set_prob(self, p: np.ndarray) -> None:
        """Overwrite the map with p(C) values (rows, cols), e.g. an ideal map."""
        if p.shape != (self.rows, self.cols):
            raise ValueError(f"p: shape must be {(self.rows, self.cols)}, got {p.shape}")
        pc = np.clip(p, 1e-6, 1 - 1e-6)
        self.log_odds[:] = np.clip(logit(pc), -self.clamp, self.clamp)
        self._p[:] = 1.0 / (1.0 + np.exp(-self._lo))
        self.updates += 1

    def cell_units(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World -> padded cell coordinates (continuous): the cell is (floor(u), floor(v))."""
        s = self.spec
        return (np.asarray(x) - s.x0) / s.resolution + 1.0, (np.asarray(y) - s.y0) / s.resolution + 1.0

    def flat_from_units(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Flat padded indices from continuous padded cell coordinates; outside points land on the border."""
        ix = np.clip(u, 0.0, self.cols + 1.5).astype(np.int32)
        iy = np.clip(v, 0.0, self.rows + 1.5).astype(np.int32)
        return iy * self.prow + ix

    def cells(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Flat padded cell indices of world points (any equal shapes)."""
        u, v = self.cell_units(x, y)
        return self.flat_from_units(u, v)

    def bayes_update(self, flat: np.ndarray, p_s_given_c: np.ndarray) -> None:
        """Eq. 5.1-2 on the given cells (each listed once) with sensor model values p(s|C) in (0, 1)."""
        new = np.clip(self._lo[flat] + logit(p_s_given_c), -self.clamp, self.clamp)
        self._lo[flat] = new
        self._p[flat] = 1.0 / (1.0 + np.exp(-new))
        self.updates += 1

    def mixture_update(self, flat: np.ndarray, p: np.ndarray, weights: np.ndarray) -> None:
        """Apply a belief template at every particle, adjusted by the particle weights (§5.1.4).

        flat: (N, K) cells of particle i's template points; p: (K,) or (N, K) p_i(s|C); weights: (N,).
        With more than `map_particles` particles the mixture is taken over that many drawn by weight
        (deterministic systematic pointers at (k + ½)/M, equal weights): the same mixture in expectation, at a
        fraction of the cost for 1000 particles.
        """
        n = flat.shape[0]
        if self.map_particles and n > self.map_particles:
            m = self.map_particles
            cdf = np.cumsum(weights)
            idx = np.minimum(np.searchsorted(cdf / cdf[-1], (np.arange(m) + 0.5) / m, side="right"), n - 1)
            flat = flat[idx]
            p = p[idx] if np.ndim(p) == 2 else p
            weights = np.full(m, 1.0 / m)
        contrib = weights[:, None] * (np.broadcast_to(p, flat.shape) - 0.5)
        delta = np.bincount(flat.reshape(-1), weights=contrib.reshape(-1), minlength=self.padded_size)
        delta[self._border] = 0.0
        touched = np.flatnonzero(delta)
        if touched.size == 0:
            return
        ps = np.clip(0.5 + delta[touched], 1e-6, 1 - 1e-6)
        self.bayes_update(touched, ps)

    def log_likelihood(self, flat: np.ndarray, p: np.ndarray, temper: float = 1.0) -> np.ndarray:
        """Per-particle log g of a belief template against the current map (the normalizer of eq. 5.1-2).

        2 (m p + (1 − m)(1 − p)) = a + b m with a = 2 (1 − p), b = 2 (2p − 1), per template point.
        """
        p32 = np.asarray(p, dtype=np.float32)
        a, b = 2.0 * (1.0 - p32), 2.0 * (2.0 * p32 - 1.0)
        m = self._p[flat]
        agree = a + b * m
        return temper * np.log(agree).sum(axis=1, dtype=np.float64)

    def prob_flat_at(self, flat: np.ndarray) -> np.ndarray:
        return self._p[flat]

    def occupancy_penalty(self, flat: np.ndarray, temper: float = 1.0) -> np.ndarray:
        """Per-particle log g of "these cells are free": τ Σ_k min(0, log(2 (1 − m_k))).

        Cells known free or unknown cost nothing; a cell more likely occupied than not costs in proportion to
        how sure the map is (an avatar cannot stand on an obstacle). Used by the co-occupancy and floor models.
        """
        m = self._p[flat]
        return temper * np.minimum(0.0, np.log(2.0 * (1.0 - m) + 1e-6)).sum(axis=1, dtype=np.float64)

    def distance_field(self, occupied: float = 0.7) -> np.ndarray:
        """Flat padded distance (m, float32) from each cell to the nearest cell with p(C) > `occupied`.

        Recomputed (OpenCV distance transform) only when the map changed since the last call; +inf everywhere
        while nothing is occupied.
        """
        if self._df is None or self._df_version != self.updates:
            import cv2

            occ = self._p > occupied
            if not occ.any():
                self._df = np.full(self._p.shape, np.inf, dtype=np.float32)
            else:
                free = (~occ).astype(np.uint8).reshape(self.rows + 2, self.prow)
                self._df = (cv2.distanceTransform(free, cv2.DIST_L2, 5) * self.spec.resolution).reshape(-1)
            self._df_version = self.updates
        return self._df

    def copy(self) -> OccupancyGrid:
        g = OccupancyGrid(self.spec, self.clamp, self.map_particles)
        g._lo = self._lo.copy()
        g._p = self._p.copy()
        g.updates = self.updates
        return g
