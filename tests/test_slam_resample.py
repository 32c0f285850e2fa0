"""Systematic resampling and n_eff (haa.slam.resample; thesis eq. 5.1-1, §5.1.1)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from haa.slam.filter import ParticleFilter
from haa.slam.motion import Prediction
from haa.slam.resample import n_eff, normalize_log, systematic_resample

log_weights = arrays(np.float64, st.integers(1, 200), elements=st.floats(-700, 50))


@settings(max_examples=200, deadline=None)
@given(log_weights)
def test_weights_sum_to_one_and_neff_in_range(lw):
    w = normalize_log(lw)
    assert abs(w.sum() - 1.0) < 1e-12
    assert np.all(w >= 0)
    assert 1.0 - 1e-9 <= n_eff(w) <= len(w) * (1 + 1e-9)


@settings(max_examples=200, deadline=None)
@given(log_weights, st.integers(0, 2**32 - 1))
def test_systematic_counts_are_floor_or_ceil_of_n_w(lw, seed):
    w = normalize_log(lw)
    n = len(w)
    idx = systematic_resample(w, np.random.default_rng(seed))
    assert idx.shape == (n,) and idx.min() >= 0 and idx.max() < n
    assert np.all(np.diff(idx) >= 0)
    counts = np.bincount(idx, minlength=n)
    assert np.all(counts >= np.floor(n * w - 1e-9)) and np.all(counts <= np.ceil(n * w + 1e-9))


def _max_z(resampler, w: np.ndarray, draws: int = 4000) -> float:
    """Largest |mean children − N w_i| in standard errors over `draws` resamplings."""
    rng = np.random.default_rng(7)
    n = len(w)
    counts = np.zeros((draws, n))
    for k in range(draws):
        counts[k] = np.bincount(resampler(w, rng), minlength=n)
    mean = counts.mean(axis=0)
    se = np.maximum(counts.std(axis=0, ddof=1) / np.sqrt(draws), 1e-3)
    return float((np.abs(mean - n * w) / se).max())


def test_systematic_resampling_is_unbiased():
    """E[children of i] = N w_i: mean counts over many draws within 4.5 standard errors."""
    w = np.random.default_rng(3).dirichlet(np.full(50, 0.5))
    assert _max_z(systematic_resample, w) < 4.5

    def fixed_offset(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:  # the same pointers every time
        n = len(w)
        return np.minimum(np.searchsorted(np.cumsum(w), (0.5 + np.arange(n)) / n, side="right"), n - 1)

    assert _max_z(fixed_offset, w) > 4.5  # the test does catch a biased scheme


def test_resampled_particles_never_share_arrays():
    pf = ParticleFilter(20, (0.0, 0.0, 0.0), 0.0, spread=(0.5, 0.5, 0.2), seed=1)
    pf.predict(Prediction(1.0, 0.5, 0.0, 0.0, 0.1, 0.01))
    pf.correct(1.0, -(pf.states_at(1.0)[0][:, 0] ** 2) * 20)
    old = pf.last
    parents = pf.resample()
    new = pf.last
    assert len(set(parents.tolist())) < 20  # some particles were duplicated
    assert not np.shares_memory(new.states, old.states)
    assert not np.shares_memory(new.states, pf._current)
    # duplicated children evolve independently
    pf.predict(Prediction(2.0, 0.5, 0.0, 0.0, 0.1, 0.01))
    s = pf.states_at(2.0)[0]
    dup = [i for i in range(20) if (parents == parents[i]).sum() > 1]
    assert len({tuple(s[i]) for i in dup}) == len(dup)
    # the new block starts where the parents were, with equal weights
    np.testing.assert_array_equal(new.states[0], old.states[old.length - 1][parents])
    assert np.allclose(new.weights, 1 / 20)
