"""Exactness of lazy belief propagation (thesis §5.2.1) and the five events of §5.2.3 (haa.slam.filter)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haa.slam.filter import NotYetPredicted, ParticleFilter, TooOld
from haa.slam.motion import Prediction

N = 64


def density(states: np.ndarray, cx: float, cy: float, sigma: float = 0.3) -> np.ndarray:
    """A made-up observation log density: a Gaussian around (cx, cy) on the particle positions."""
    return -((states[:, 0] - cx) ** 2 + (states[:, 1] - cy) ** 2) / (2 * sigma**2)


def moving_filter(n: int = N, steps: int = 20, seed: int = 0, **kw) -> ParticleFilter:
    pf = ParticleFilter(n, (0.0, 0.0, 0.0), 0.0, spread=(0.2, 0.2, 0.1), seed=seed, **kw)
    for k in range(1, steps + 1):
        pf.predict(Prediction(float(k), 0.3, 0.0, 0.1, 0.2, 0.05))
    return pf


def sequential_weights(w0: np.ndarray, log_gs: list[np.ndarray]) -> np.ndarray:
    """Eq. 5.1-4 applied once per observation, in the given order (the standard particle filter)."""
    w = w0.copy()
    for lg in log_gs:
        w = w * np.exp(lg)
        w = w / w.sum()
    return w


# ----- Strategy 1: delayed weight updates (eq. 5.2-3) ------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.0, 20.0), st.floats(-2, 8), st.floats(-2, 4)), min_size=1, max_size=12),
    st.randoms(use_true_random=False),
)
def test_strategy1_accumulated_equals_sequential_in_any_order(obs, rnd):
    pf = moving_filter()
    log_gs = [density(pf.states_at(t)[0], cx, cy) for t, cx, cy in obs]
    order = list(range(len(obs)))
    rnd.shuffle(order)
    for i in order:
        pf.correct(obs[i][0], log_gs[i])
    got = pf.estimate().weights
    # the standard filter in time order
    by_time = sorted(range(len(obs)), key=lambda i: obs[i][0])
    want = sequential_weights(np.full(N, 1 / N), [log_gs[i] for i in by_time])
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-15)  # below 1e-15: subnormal noise in the reference
    assert math.isclose(got.sum(), 1.0, rel_tol=1e-12)


def test_strategy1_weights_computed_once_for_many_observations():
    pf = moving_filter()
    for t in (3.0, 7.5, 1.0, 19.0):
        pf.correct(t, density(pf.states_at(t)[0], 1.0, 0.5))
    assert pf.weight_updates == 0
    pf.estimate()
    pf.estimate()  # nothing accumulated since: no recomputation
    assert pf.weight_updates == 1
    assert pf.obs_per_update == [4]
    assert pf.weight_requests == 2


# ----- Strategy 3: propagation through resampling (eq. 5.2-4, 5.2-5) ---------------------------------------


def build_resampled(seed: int = 1, resamples: int = 2) -> tuple[ParticleFilter, list[float]]:
    """A filter with `resamples` resampling events at t = 6, 12 (after some corrections)."""
    pf = ParticleFilter(N, (0.0, 0.0, 0.0), 0.0, spread=(0.3, 0.3, 0.1), seed=seed)
    times = [0.0]
    k = 0
    for r in range(resamples + 1):
        for _ in range(6):
            k += 1
            pf.predict(Prediction(float(k), 0.4, 0.05, 0.2, 0.25, 0.05))
            times.append(float(k))
        if r < resamples:
            t = float(k) - 1.5
            pf.correct(t, density(pf.states_at(t)[0], 0.4 * k, 0.1 * k))
            pf.resample()
    return pf, times


def unresampled_twin(pf: ParticleFilter, times: list[float]) -> ParticleFilter:
    """One block of the newest particles, each carrying its ancestors' history (the thesis' analogy)."""
    lineage = np.arange(pf.n)  # index into the current block, walked back through the parents
    rows: dict[float, np.ndarray] = {}
    for b in reversed(pf.blocks):
        for k in range(b.length):
            t = float(b.times[k])
            if t not in rows:
                rows[t] = b.states[k][lineage].astype(np.float64)
        if b.parents is not None:
            lineage = b.parents[lineage]
    twin = ParticleFilter(pf.n, (0.0, 0.0, 0.0), times[0], seed=99)
    twin.blocks[0].states[0] = rows[times[0]]
    for t in times[1:]:
        twin.insert(t, rows[t])
    return twin


@pytest.mark.parametrize("resamples", [1, 2])
def test_strategy3_propagation_equals_unresampled_filter_with_parent_histories(resamples):
    pf, times = build_resampled(resamples=resamples)
    assert len(pf.blocks) == resamples + 1
    twin = unresampled_twin(pf, times)
    # corrections after the last resampling only, in scrambled order: before (in block 0 and 1), after
    obs = [(2.5, 0.3, 0.1), (16.0, 5.5, 1.2), (8.0, 3.0, 0.6), (1.0, 0.2, 0.0), (13.2, 4.9, 1.1)]
    for t, cx, cy in obs:
        if t > pf.time:
            continue
        pf.correct(t, density(pf.states_at(t)[0], cx, cy))
        twin.correct(t, density(twin.states_at(t)[0], cx, cy))
    got = pf.estimate().weights
    want = twin.estimate().weights
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert not np.allclose(got, np.full(N, 1 / N))  # the densities did change the weights


def test_strategy3_catches_a_wrong_propagation(monkeypatch):
    """The equality above must break when densities skip the parents (children take g of the same index)."""
    pf, times = build_resampled(resamples=1)
    twin = unresampled_twin(pf, times)
    monkeypatch.setattr(ParticleFilter, "through_parents", staticmethod(lambda log_fwd, parents: log_fwd))
    for t in (2.5, 4.0):
        pf.correct(t, density(pf.states_at(t)[0], 0.3, 0.1))
        twin.correct(t, density(twin.states_at(t)[0], 0.3, 0.1))
    assert not np.allclose(pf.estimate().weights, twin.estimate().weights, rtol=1e-6)


def test_nfp_ignores_old_densities_for_current_weights():
    pf, _ = build_resampled(resamples=1)
    nfp, _ = build_resampled(resamples=1)
    nfp.forward_propagation = False
    for f in (pf, nfp):
        f.correct(2.0, density(f.states_at(2.0)[0], 0.3, 0.1))
    assert np.allclose(nfp.estimate().weights, 1 / N)
    assert not np.allclose(pf.estimate().weights, 1 / N)


def test_propagation_to_a_past_query_block_then_to_the_newest():
    """(d) at a past time propagates to that block only; a later estimate continues from the marker."""
    pf, times = build_resampled(resamples=2)
    twin = unresampled_twin(pf, times)
    pf.correct(2.0, density(pf.states_at(2.0)[0], 0.3, 0.1))
    twin.correct(2.0, density(twin.states_at(2.0)[0], 0.3, 0.1))
    mid = pf.estimate(8.0)
    assert mid.block == pf.blocks[1].index
    assert pf.marker == pf.blocks[1].index
    np.testing.assert_allclose(pf.estimate().weights, twin.estimate().weights, rtol=1e-9)
    assert pf.marker is None


# ----- the events and their errors --------------------------------------------------------------------------


def test_initialization_and_prediction_order():
    pf = ParticleFilter(10, (1.0, 2.0, 0.5), 0.0)
    assert np.allclose(pf.estimate().weights, 0.1)
    np.testing.assert_allclose(pf.estimate().pose, [1.0, 2.0, 0.5])
    pf.predict(Prediction(1.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(pf.estimate().pose, [1.0 + math.cos(0.5), 2.0 + math.sin(0.5), 0.5], atol=1e-6)
    with pytest.raises(ValueError, match=r"prediction\.t: predictions must be in time order"):
        pf.predict(Prediction(1.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(NotYetPredicted, match="after the newest prediction"):
        pf.correct(1.5, np.zeros(10))
    with pytest.raises(ValueError, match="log_g: shape"):
        pf.correct(0.5, np.zeros(3))
    with pytest.raises(ValueError, match="n: number of particles"):
        ParticleFilter(0, (0.0, 0.0, 0.0))


def test_states_between_predictions_are_interpolated():
    pf = ParticleFilter(4, (0.0, 0.0, 3.0), 0.0)
    pf.predict(Prediction(1.0, 1.0, 0.0, 0.4, 0.0, 0.0))  # heading crosses ±π
    s, _ = pf.states_at(0.5)
    assert np.allclose(s[:, 2], ((3.2 + math.pi) % (2 * math.pi)) - math.pi, atol=1e-5)
    s1, _ = pf.states_at(1.0)
    assert np.allclose(s[:, 0], 0.5 * s1[:, 0], atol=1e-6)


def test_horizon_prunes_blocks_and_rejects_old_readings_with_a_reason():
    pf = ParticleFilter(N, (0.0, 0.0, 0.0), 0.0, spread=(0.3, 0.3, 0.1), seed=3, horizon=5.0)
    ref = ParticleFilter(N, (0.0, 0.0, 0.0), 0.0, spread=(0.3, 0.3, 0.1), seed=3)
    for k in range(1, 31):
        for f in (pf, ref):
            f.predict(Prediction(float(k), 0.3, 0.0, 0.0, 0.2, 0.05))
            if k % 4 == 0:
                t = k - 0.5
                f.correct(t, density(f.states_at(t)[0], 0.3 * k, 0.0))
                f.resample()
        if k == 27:  # a late reading still inside the horizon, pending when pruning runs
            for f in (pf, ref):
                f.correct(23.5, density(f.states_at(23.5)[0], 7.0, 0.2))
        pf.prune()
    assert len(pf.blocks) < len(ref.blocks)
    np.testing.assert_allclose(pf.estimate().weights, ref.estimate().weights, rtol=1e-9)
    with pytest.raises(TooOld, match="older than the history horizon"):
        pf.correct(20.0, np.zeros(N))
    assert pf.memory_bytes() < ref.memory_bytes()


def test_weights_sum_to_one_and_neff_in_range_through_a_long_run():
    pf = moving_filter(steps=5)
    rng = np.random.default_rng(5)
    for k in range(6, 60):
        pf.predict(Prediction(float(k), 0.3, 0.0, 0.05, 0.2, 0.05))
        for _ in range(3):
            t = float(rng.uniform(0, k))
            pf.correct(t, density(pf.states_at(t)[0], rng.uniform(0, 5), rng.uniform(0, 2), 0.2))
        est, _ = pf.maybe_resample(0.5)
        assert math.isclose(est.weights.sum(), 1.0, rel_tol=1e-12)
        assert 1.0 - 1e-9 <= est.n_eff <= N + 1e-9
    assert pf.resamples > 0
