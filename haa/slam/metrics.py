"""Map metrics of §7.1 against an ideal map, the exploration threshold, and localization error.

    map coverage = Σ_region |c − 0.5| / Σ_region |c_ideal − 0.5|                        (7.1-1)
    map accuracy = 1 − Σ_region |c − c_ideal| / (# of cells)                             (7.1-2)

c is a cell's p(C), c_ideal the same cell of the "ideal" map (the thesis: generated with zero localization
error; `haa.slam.replay` builds it by running the same sensor models on the true poses; the simulator's
`ideal_grid` can be used too), the sums run over the mission region (a boolean mask, default every cell).
An empty map has accuracy 1 − mean|0.5 − c_ideal| (0.5 for a fully decided ideal map), as the thesis notes.

A cell is *explored* when p(C) > 0.73 or p(C) < 0.27 (§6.2.1); `explored_fraction` is the share of the
region's cells explored — the missions end at 95% of the reachable cells.
"""

from __future__ import annotations

import math

import numpy as np

EXPLORED_HIGH = 0.73
EXPLORED_LOW = 0.27


def _region(c: np.ndarray, ideal: np.ndarray | None, region: np.ndarray | None) -> np.ndarray:
    if ideal is not None and ideal.shape != c.shape:
        raise ValueError(f"ideal: shape {ideal.shape} differs from the map's {c.shape}")
    if region is None:
        return np.ones(c.shape, dtype=bool)
    if region.shape != c.shape:
        raise ValueError(f"region: shape {region.shape} differs from the map's {c.shape}")
    return region.astype(bool)


def map_coverage(c: np.ndarray, ideal: np.ndarray, region: np.ndarray | None = None) -> float:
    """Eq. 7.1-1."""
    m = _region(c, ideal, region)
    den = float(np.abs(ideal[m] - 0.5).sum())
    return float(np.abs(c[m] - 0.5).sum()) / den if den > 0 else math.nan


def map_accuracy(c: np.ndarray, ideal: np.ndarray, region: np.ndarray | None = None) -> float:
    """Eq. 7.1-2."""
    m = _region(c, ideal, region)
    n = int(m.sum())
    return 1.0 - float(np.abs(c[m] - ideal[m]).sum()) / n if n else math.nan


def explored(c: np.ndarray) -> np.ndarray:
    """Cells past the exploration threshold (> 0.73 or < 0.27)."""
    return (c > EXPLORED_HIGH) | (c < EXPLORED_LOW)


def explored_fraction(c: np.ndarray, region: np.ndarray | None = None) -> float:
    m = _region(c, None, region)
    n = int(m.sum())
    return float(explored(c)[m].sum()) / n if n else math.nan


def pose_error(estimate: np.ndarray, truth: tuple[float, float, float] | np.ndarray) -> tuple[float, float]:
    """(position error [m], absolute heading error [rad]) of a pose estimate."""
    dx, dy = float(estimate[0] - truth[0]), float(estimate[1] - truth[1])
    dth = (float(estimate[2] - truth[2]) + math.pi) % (2 * math.pi) - math.pi
    return math.hypot(dx, dy), abs(dth)
