"""Weights, effective particle count (eq. 5.1-1) and systematic resampling (§5.1.1, event (e) of §5.2.3).

* `normalize_log(log_w)` turns log weights into weights that sum to 1 (max-shifted, so it never overflows and
  never returns all zeros while one particle has a finite log weight).
* `n_eff(w)` is the thesis' estimate of the effective number of particles, 1 / Σ w², always in [1, N] for
  normalized weights.
* `systematic_resample(w, rng)` is the systematic scheme the thesis takes from [81]: one uniform draw
  u ~ U[0, 1/N), pointers u + k/N, k = 0..N-1, through the cumulative weights. Particle i gets either
  ⌊N w_i⌋ or ⌈N w_i⌉ children, and E[children_i] = N w_i (unbiased; tests/test_slam_resample.py checks
  both). It returns parent indices; the caller copies the states with fancy indexing, so children never
  share an array with their parents or with each other.
"""

from __future__ import annotations

import numpy as np


def normalize_log(log_w: np.ndarray) -> np.ndarray:
    """Weights ∝ exp(log_w), summing to 1. Raises ValueError if no log weight is finite."""
    m = np.max(log_w)
    if not np.isfinite(m):
        raise ValueError("log weights: no particle has a finite log weight")
    w = np.exp(log_w - m)
    return w / w.sum()


def n_eff(weights: np.ndarray) -> float:
    """Effective number of particles n*_eff = 1 / Σ w² (eq. 5.1-1); `weights` must sum to 1."""
    return float(1.0 / np.dot(weights, weights))


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Parent index of each of the N children (int64, non-decreasing), by systematic resampling."""
    n = weights.shape[0]
    if n == 0:
        raise ValueError("weights: empty")
    cdf = np.cumsum(weights)
    cdf /= cdf[-1]  # guard against a sum of 1 - 1e-16 leaving the last pointer past the end
    pointers = (rng.random() + np.arange(n)) / n
    idx = np.searchsorted(cdf, pointers, side="right")
    return np.minimum(idx, n - 1).astype(np.int64)
