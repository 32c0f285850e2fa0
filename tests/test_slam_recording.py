"""MCAP + protobuf recordings (haa.slam.recording): exact round trip, replay stream order."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from haa.slam.recording import load, save
from haa.slam.sensors import FloorReading
from haa.slam.strategies import PREDICTION, READING, REQUEST
from haa.slam.synthetic import synthetic_recording


def test_round_trip(tmp_path):
    rec = synthetic_recording(avatars=2, duration=10.0, seed=2)
    rec.readings.append(FloorReading("a1", 5.0, ((0.2, -0.3), (1.0, -0.6), (1.0, 0.6))))
    rec.ideal_grid = np.random.default_rng(0).random(rec.grid.shape).astype(np.float32).astype(np.float64)
    rec.region = rec.ideal_grid > 0.5
    path = save(rec, tmp_path / "run.mcap")
    back = load(path)
    assert back.avatars == rec.avatars and back.landmarks == rec.landmarks and back.grid == rec.grid
    assert back.predictions == rec.predictions
    key = lambda r: (r.t, r.kind, r.avatar, str(r))  # noqa: E731
    assert sorted(back.readings, key=key) == sorted(rec.readings, key=key)
    assert any(r.kind == "sonar" and any(e.range is None for e in r.echoes) for r in back.readings)  # optional
    assert any(r.kind == "landmark" and len(r.sightings) > 1 for r in back.readings)
    for name in rec.truth:
        assert back.truth[name] == rec.truth[name] and back.odometry[name] == rec.odometry[name]
    np.testing.assert_array_equal(back.ideal_grid, rec.ideal_grid)
    np.testing.assert_array_equal(back.region, rec.region)
    # the file is a normal MCAP with protobuf schemas
    from mcap.reader import make_reader

    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"protobuf"}
    assert "/slam/sonar" in {c.topic for c in summary.channels.values()}


def test_not_a_recording(tmp_path):
    from mcap.writer import Writer

    p = tmp_path / "empty.mcap"
    with p.open("wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    with pytest.raises(ValueError, match="no /slam/info message"):
        load(p)


def test_events_are_time_ordered_and_requests_avoid_readings():
    rec = synthetic_recording(avatars=2, duration=6.0, seed=2)
    evs = rec.events(1.0)
    assert [e.t for e in evs] == sorted(e.t for e in evs)
    for a, b in itertools.pairwise(evs):
        if a.t == b.t:
            assert a.kind <= b.kind  # predictions, then readings, then requests
    req = [e for e in evs if e.kind == REQUEST]
    per = {a.name: [e.t for e in req if e.avatar == a.name] for a in rec.avatars}
    assert all(4 <= len(v) <= 6 for v in per.values())
    own = {(r.avatar, r.t) for r in rec.readings}
    assert not any((e.avatar, e.t) in own for e in req)  # a request never coincides with its avatar's reading
    assert sum(e.kind == PREDICTION for e in evs) == len(rec.predictions)
    assert sum(e.kind == READING for e in evs) == len(rec.readings)
    with pytest.raises(ValueError, match="request_period"):
        rec.events(0.0)
