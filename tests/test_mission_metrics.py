"""haa.mission.metrics: map scores on synthetic maps, localization error, time averages, event counts, the
results table."""

import math

import numpy as np
import pytest

from haa.mission import metrics as mm
from haa.slam.grid import GridSpec


def arena_grid():
    """A 10 x 8 cell ideal map: walls around, one obstacle; the reachable cells are the free inside."""
    occ = np.zeros((10, 8), dtype=np.uint8)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = 1
    occ[4:6, 3:5] = 1
    ex = (occ == 0).astype(np.uint8)
    return occ, ex


def test_a_perfect_map_scores_one_and_a_blank_map_half():
    occ, ex = arena_grid()
    perfect = np.where(occ > 0, 0.99, 0.01).astype(np.float32)
    s = mm.map_scores(perfect, occ, ex)
    assert s.coverage == pytest.approx(0.98) and s.accuracy == pytest.approx(0.99)
    assert s.explored == 1.0 and s.reachable_cells == int(ex.sum())
    blank = np.full(occ.shape, 0.5, dtype=np.float32)
    b = mm.map_scores(blank, occ, ex)
    assert b.coverage == 0.0 and b.accuracy == pytest.approx(0.5) and b.explored == 0.0  # thesis L1476


def test_coverage_never_exceeds_one_and_wrong_cells_cost_accuracy():
    occ, ex = arena_grid()
    rng = np.random.default_rng(1)
    for _ in range(20):
        c = rng.random(occ.shape).astype(np.float32)
        s = mm.map_scores(c, occ, ex)
        assert 0.0 <= s.coverage <= 1.0 and 0.0 <= s.accuracy <= 1.0
    inverted = np.where(occ > 0, 0.0, 1.0).astype(np.float32)
    s = mm.map_scores(inverted, occ, ex)
    assert s.coverage == pytest.approx(1.0) and s.accuracy == pytest.approx(0.0)


def test_the_mission_region_is_the_reachable_cells_and_the_walls_around_them():
    occ = np.ones((7, 7), dtype=np.uint8)
    occ[1:4, 1:4] = 0  # a reachable room
    occ[5, 5] = 0  # a free pocket nobody reaches
    ex = np.zeros_like(occ)
    ex[1:4, 1:4] = 1
    region = mm.mission_region(occ, ex)
    assert region[1:4, 1:4].all()  # reachable
    assert region[0, 0:5].all() and region[0:5, 4].all()  # the walls around the room (8-neighbours)
    assert not region[5, 5] and not region[6, 6]  # the pocket and far walls are not in it
    assert region.sum() == 9 + 16


def test_a_published_map_is_sampled_at_the_ideal_cells():
    spec = GridSpec(1.0, 0.5, 0.1, x0=0.2, y0=0.0)  # 5 rows x 10 cols, shifted 0.2 m east
    prob = np.arange(50, dtype=np.float32).reshape(5, 10) / 100
    out = mm.align_to_grid(spec, prob, (6, 14), 0.1)
    assert out.shape == (6, 14)
    assert (out[:, :2] == 0.5).all() and (out[5, :] == 0.5).all() and (out[:, 12:] == 0.5).all()
    assert out[0, 2] == pytest.approx(prob[0, 0]) and out[4, 11] == pytest.approx(prob[4, 9])
    coarse = mm.align_to_grid(GridSpec(1.0, 1.0, 0.5), np.array([[0.1, 0.2], [0.3, 0.4]], np.float32), (4, 4), 0.25)
    assert coarse[0, 0] == pytest.approx(0.1) and coarse[3, 3] == pytest.approx(0.4)
    assert coarse[1, 2] == pytest.approx(0.2)


def test_the_fallback_map_codec_round_trips():
    spec = GridSpec(0.4, 0.3, 0.1, 1.0, 2.0)
    prob = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    s2, p2 = mm.fallback_decode_map(mm.fallback_encode_map(spec, prob))
    assert s2 == spec and np.array_equal(p2, prob)
    with pytest.raises(ValueError):
        mm.fallback_decode_map(b"no header")
    dec = mm.map_decoder()
    assert callable(dec)  # haa.slam.replica.decode_map once it exists, else the fallback


def test_expected_cells_counts_the_reachable_cells():
    _, ex = arena_grid()
    assert mm.expected_cells(ex) == 6 * 8 - 4


def test_pose_history_interpolates_and_refuses_outside():
    h = mm.PoseHistory()
    h.add(0.0, 0.0, 0.0, math.pi - 0.1)
    h.add(1.0, 1.0, 2.0, -math.pi + 0.1)  # heading wraps: the short way round
    h.add(1.0, 9.0, 9.0, 0.0)  # same time again: ignored
    x, y, th = h.at(0.5)
    assert (x, y) == pytest.approx((0.5, 1.0))
    assert abs((th - math.pi + math.pi) % (2 * math.pi) - math.pi) < 1e-9  # ±pi
    assert h.at(-1.0) is None and h.at(2.0) is None and h.at(1.3) == (1.0, 2.0, -math.pi + 0.1)


def test_position_error_is_the_mean_over_avatars_of_each_avatars_mean():
    hist = {"a": mm.PoseHistory(), "b": mm.PoseHistory()}
    for t in range(5):
        hist["a"].add(float(t), float(t), 0.0, 0.0)
        hist["b"].add(float(t), 0.0, 0.0, 0.0)
    log = mm.LocalizationLog()
    assert log.add("a", {"t": 1.0, "x": 1.1, "y": 0.0, "theta": 0.0}, hist["a"])
    assert not log.add("a", {"t": 1.0, "x": 5.0, "y": 0.0}, hist["a"])  # the same estimate again
    assert log.add("a", {"t": 2.0, "x": 2.3, "y": 0.0}, hist["a"])
    assert log.add("b", {"t": 1.5, "x": 0.0, "y": 1.0, "theta": 0.5}, hist["b"])
    assert not log.add("b", {"t": 99.0, "x": 0.0, "y": 0.0}, hist["b"])  # no truth then
    assert not log.add("b", {"x": 0.0}, hist["b"])  # malformed
    assert log.position_error() == pytest.approx(((0.1 + 0.3) / 2 + 1.0) / 2)
    assert log.rotation_error() == pytest.approx((0.0 + 0.5) / 2)
    assert mm.LocalizationLog().position_error() is None


def test_time_average_weights_values_by_how_long_they_held():
    s = [(0.0, 4.0), (10.0, 5.0), (30.0, 4.0)]
    assert mm.time_average(s, 0.0, 40.0) == pytest.approx((40 + 100 + 40) / 40)
    assert mm.time_average(s, 5.0, 20.0) == pytest.approx((5 * 4 + 10 * 5) / 15)
    assert mm.time_average([(10.0, 2.0)], 0.0, 20.0) == pytest.approx(2.0)  # before the first sample: unknown
    assert mm.time_average([], 0.0, 1.0) is None
    assert mm.time_average([(0.0, 3.0)], 5.0, 5.0) == 3.0


def test_transfers_recoveries_and_failures_from_the_timelines():
    ev = [
        {"time": 1.0, "agent": "x", "event": "freezing"},
        {"time": 2.0, "agent": "x", "event": "thawed"},
        {"time": 3.0, "agent": "y", "event": "crashed", "detail": "killed"},
        {"time": 3.5, "agent": "y", "event": "crashed"},  # another member's report of the same crash
        {"time": 4.0, "agent": "y", "event": "recovered"},
        {"time": 20.0, "agent": "y", "event": "crashed"},  # a second crash
        {"time": 21.0, "agent": "z", "event": "failed"},
    ]
    assert mm.agent_event_counts(ev) == {"transfers": 1, "recoveries": 1, "agent_failures": 3}


def test_stats_counters_and_the_results_table():
    assert mm.stats_counters({"readings_generated": 10, "processings": 25, "other": 1}) == {
        "readings_generated": 10, "readings_processed": None, "processings": 25, "readings_discarded": None}
    rows = dict(mm.results_rows({"duration_s": 228.0, "coverage": 0.9107, "accuracy": 0.5, "position_error_m": 0.05737,
                                 "hosts_avg_thesis": 4.5, "transfers": 12, "readings_generated": 300}))
    assert list(rows)[:11] == [r[0] for r in mm.THESIS_ROWS]  # Table 7.1-1's rows, in its order
    assert rows["Mission Duration [min]"] == "3.800" and rows["Map Coverage [%]*"] == "91.070"
    assert rows["Localization Positional Err [m]"] == "0.05737" and rows["Landmark Err [m]"] == "—"
    assert rows["Transfers"] == "12" and rows["Readings generated"] == "300"
