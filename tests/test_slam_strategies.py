"""Reading schedulers (haa.slam.strategies): LIFO + OOO equals in-order with enough processing (Fig. 5.2-2),
and each strategy's behaviour when processing is short."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from haa.slam.replay import calibrate
from haa.slam.strategies import STRATEGIES, Capacity, discard_share, run, strategy
from haa.slam.synthetic import synthetic_recording
from haa.slam.system import SlamConfig, SlamSystem

COST = {"sonar": 1.0, "landmark": 0.3, "cooccupancy": 0.5, "floor": 0.5}


@pytest.fixture(scope="module")
def rec():
    return synthetic_recording(avatars=2, duration=40.0, seed=4)


def spaced(rec):
    """At most one reading per time (so with enough processing none waits for another)."""
    seen, out = set(), []
    for r in rec.readings:
        if r.t not in seen:
            seen.add(r.t)
            out.append(r)
    return dataclasses.replace(rec, readings=out)


def replay(rec, name, capacity, n=40, seed=0):
    s = strategy(name)
    system = SlamSystem(rec.grid, SlamConfig(n_particles=n, forward_propagation=s.forward_propagation), seed=seed)
    for a in rec.avatars:
        system.add_avatar(a.name, a.start, 0.0)
    stats = run(rec.events(1.0), s, capacity, system, seed=seed, keep_order=True)
    return system, stats


def state(system):
    w = {k: pf.estimate().weights for k, pf in system.filters.items()}
    lms = {k: (v.mean.copy(), v.cov.copy()) for k, v in system.landmarks.landmarks.items()}
    return w, system.grid.prob(), lms


def assert_same(a, b):
    wa, ga, la = a
    wb, gb, lb = b
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k])
    np.testing.assert_array_equal(ga, gb)
    assert la.keys() == lb.keys()
    for k in la:
        np.testing.assert_array_equal(la[k][0], lb[k][0])


def test_lifo_ooo_equals_in_order_with_enough_processing(rec):
    sp = spaced(rec)
    cap = Capacity(1, {k: 0.02 for k in COST}, jitter=0.0)  # each done before the next arrives (>= 0.05 s apart)
    runs = {name: replay(sp, name, cap) for name in ("jcslam", "fifo", "discard", "random")}
    ref_sys, ref_stats = runs["fifo"]
    assert ref_stats.processed + ref_stats.held_at_end == ref_stats.arrived == len(sp.readings)
    assert ref_stats.held_at_end <= 1  # the last one may still be in progress when the recording ends
    for name, (system, stats) in runs.items():
        assert stats.order == ref_stats.order, name  # same readings, same order, same times
        assert stats.out_of_order == 0
        assert_same(state(system), state(ref_sys))
    # with instantaneous processing every strategy is the Baseline, bit for bit
    base_sys, _ = replay(sp, "baseline", None)
    zero_sys, _ = replay(sp, "jcslam", Capacity(1, {k: 0.0 for k in COST}, jitter=0.0))
    assert_same(state(zero_sys), state(base_sys))


def test_equality_check_is_sensitive(rec):
    """The comparison above would notice a different processing: drop one reading and it differs."""
    sp = spaced(rec)
    cap = Capacity(1, {k: 0.02 for k in COST}, jitter=0.0)
    a, _ = replay(sp, "fifo", cap)
    b, _ = replay(dataclasses.replace(sp, readings=sp.readings[:-5] + sp.readings[-4:]), "fifo", cap)
    with pytest.raises(AssertionError):
        assert_same(state(a), state(b))


def test_constrained_strategies_behave_as_specified(rec):
    cap = calibrate(rec, 0.7, workers=2, cost_ms=COST, per_kind=False)  # one shared pool; Discard processes 70%
    out = {name: replay(rec, name, cap)[1] for name in ("baseline", "discard", "jcslam", "fifo", "random", "delay")}
    n = len(rec.readings)
    assert out["baseline"].processed == n and out["baseline"].delay_sum == 0
    d = out["discard"]
    assert d.dropped > 0 and d.processed + d.dropped + d.held_at_end == n and d.out_of_order == 0
    share = discard_share(rec.readings, cap)
    assert abs((d.processed + d.held_at_end) / n - share) < 1e-12 and abs(share - 0.7) < 0.05
    j, f, r = out["jcslam"], out["fifo"], out["random"]
    assert j.processed >= d.processed  # held readings are processed during lulls
    assert j.out_of_order > 0 and f.out_of_order == 0
    # overloaded: FIFO falls behind (its delay grows), LIFO keeps processing the newest readings
    over = calibrate(rec, 0.3, workers=2, cost_ms=COST, per_kind=False)
    j2, f2 = replay(rec, "jcslam", over)[1], replay(rec, "fifo", over)[1]
    assert j2.held_at_end > 0.2 * n and f2.held_at_end > 0.2 * n
    assert f2.delay_sum / f2.processed > 5 * (j2.delay_sum / j2.processed)
    assert r.out_of_order > 0
    dl = out["delay"]
    assert dl.dropped == 0 and dl.processed == n - dl.held_at_end and dl.waited > 0 and dl.out_of_order == 0


def test_per_kind_pools(rec):
    """Each kind has its own processors (and held readings); calibration hits each kind's share."""
    cap = calibrate(rec, 0.5, workers=1, cost_ms=COST)
    for kind in ("sonar", "landmark", "cooccupancy"):
        assert abs(discard_share(rec.readings, cap, kind) - 0.5) < 0.05, kind
    d = replay(rec, "discard", cap)[1]
    j = replay(rec, "jcslam", cap)[1]
    assert j.processed > d.processed and d.out_of_order == 0
    # a shared pool of the same size processes less: sonar scans block the landmark readings
    shared = Capacity(cap.workers, cap.cost, per_kind=False)
    assert shared.duration(rec.readings[0]) == cap.duration(rec.readings[0])  # a reading's cost is its own
    assert replay(rec, "discard", shared)[1].processed < d.processed


def test_random_is_reproducible_from_its_seed(rec):
    cap = Capacity(1, {k: 0.3 * c for k, c in COST.items()})
    a = replay(rec, "random", cap, seed=3)
    b = replay(rec, "random", cap, seed=3)
    assert a[1].order == b[1].order
    assert_same(state(a[0]), state(b[0]))


def test_strategy_and_capacity_errors(rec):
    with pytest.raises(ValueError, match="strategy: unknown 'lilo'"):
        strategy("lilo")
    with pytest.raises(ValueError, match=r"capacity\.workers"):
        Capacity(0, COST)
    with pytest.raises(ValueError, match=r"capacity\.jitter"):
        Capacity(1, COST, jitter=-1.0)
    system = SlamSystem(rec.grid, SlamConfig(n_particles=10), seed=0)
    with pytest.raises(ValueError, match="forward_propagation: must be False"):
        run([], STRATEGIES["nfp"], Capacity(1, COST), system)
    with pytest.raises(ValueError, match="needs a processing capacity"):
        run([], STRATEGIES["jcslam"], None, system)


def _logged_replay(rec, name, capacity, n=40):
    """Replay with every correction logged and, at each weight request of the newest block, the weights
    recomputed from the log by brute force: the un-resampled-twin reading of eq. 5.2-4 / 5.2-5 (a density
    applied to block b while block c was the newest counts for c's particles through their ancestors in b;
    once c is resampled its weights carry it, so it counts no further). Returns (stats, checks, max |Δw|)."""
    from haa.slam.filter import ParticleFilter
    from haa.slam.resample import normalize_log

    s = strategy(name)
    system = SlamSystem(rec.grid, SlamConfig(n_particles=n, forward_propagation=s.forward_propagation), seed=0)
    for a in rec.avatars:
        system.add_avatar(a.name, a.start, 0.0)
    worst = [0.0, 0]
    for pf in system.filters.values():
        log: list[tuple[int, int, np.ndarray]] = []  # (block, newest block when applied, log g)

        def correct(t, log_g, pf=pf, log=log):
            idx = ParticleFilter.correct(pf, t, log_g)
            log.append((idx, pf.last.index, log_g.copy()))
            return idx

        def estimate(t=None, pf=pf, log=log):
            est = ParticleFilter.estimate(pf, t)
            if t is None:
                cur = pf.last
                anc = {cur.index: np.arange(pf.n)}
                b = cur
                while b.parents is not None:
                    anc[b.index - 1] = b.parents[anc[b.index]]
                    b = pf.block(b.index - 1)
                total = np.zeros(pf.n)
                for idx, newest, lg in log:
                    if newest == cur.index:
                        total += lg if idx == cur.index else lg[anc[idx]]
                worst[0] = max(worst[0], float(np.max(np.abs(normalize_log(total) - est.weights))))
                worst[1] += 1
            return est

        pf.correct, pf.estimate = correct, estimate
    stats = run(rec.events(1.0), s, capacity, system, seed=0)
    return stats, worst[1], worst[0]


def test_lazy_propagation_exact_in_a_constrained_lifo_replay(rec):
    """AP-5.1 investigation (docs/slam.md): under JC-SLAM at constrained capacity, with late readings applied
    to closed blocks in any order, the current weights at every request equal the brute-force recomputation
    from all densities applied so far (§5.2.1 Strategy 3, eq. 5.2-4 / 5.2-5) — so the filter is not where
    JC-SLAM loses to Discard in the 4-sweeper runs."""
    cap = calibrate(rec, 0.5, workers=2, cost_ms=COST)
    stats, checks, worst = _logged_replay(rec, "jcslam", cap)
    assert stats.out_of_order > 0 and stats.resamples >= 8 and checks > 50
    assert worst < 1e-9


def test_lazy_propagation_check_is_sensitive(rec, monkeypatch):
    """The same check fails when the parent mapping of eq. 5.2-4 is broken (densities not re-indexed)."""
    from haa.slam.filter import ParticleFilter

    monkeypatch.setattr(ParticleFilter, "through_parents", staticmethod(lambda log_fwd, parents: log_fwd))
    cap = calibrate(rec, 0.5, workers=2, cost_ms=COST)
    _, _, worst = _logged_replay(rec, "jcslam", cap)
    assert worst > 1e-3
