"""SupervisorSLAM and the sensor agents in the running team (docs/slam.md "In the running team"): the
dispatch of processings, several processings in flight per sensor agent, the delay mode's dedicated agents,
and the floor finder's obstacle feet. The agents run on a stand-in context (no host, no DDB cluster)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haa.agents.sensor_floorfinder import floor_reading


def test_the_floor_finder_flags_obstacle_feet_within_centimetres() -> None:
    """Seekers have no sonar: before the flags the camera only ever marked free space. A frame facing panel-a
    (y = 2.2, x 0.6-1.8) from 1.2 m: the flagged vertices lie on the panel's foot."""
    from haa.control.floorfinder import FloorFinder
    from haa.sim.world import World
    from haa.slam.sensors import FloorModel

    w = World.from_arena("small", seed=1)
    aid = w.add_avatar("seeker", (1.2, 1.0, math.pi / 2), "x")
    r = floor_reading(FloorFinder(), w.capture(aid), "x")
    assert r is not None and len(r.occupied) == len(r.polygon)
    assert not r.occupied[0] and not r.occupied[-1]  # the bottom corners
    pts = FloorModel().obstacle_points(r)
    assert len(pts) > 10
    wy = 1.0 + pts[:, 0]  # facing +y: forward is +y
    near = np.abs(wy - 2.18) < 0.08  # the panel's near face, plus the half cell the points are pushed in
    assert near.mean() > 0.9

def test_floor_obstacle_feet_round_trip_and_map_only_when_enabled() -> None:
    from haa.slam import events as sev
    from haa.slam.grid import GridSpec, OccupancyGrid
    from haa.slam.sensors import FloorModel, FloorReading

    feet = tuple((2.0, y) for y in np.round(np.arange(-0.6, 0.61, 0.1), 2))  # a wall 2 m ahead, 1.2 m wide
    poly = ((0.8, -0.4), *feet, (0.8, 0.4))
    r = FloorReading("s1", 1.0, poly, (False, *[True] * len(feet), False))
    assert sev.decode(sev.encode(sev.Observe(r))).reading == r
    with pytest.raises(ValueError, match="occupied"):
        FloorReading("s1", 1.0, poly, (True,))
    states, w = np.array([[1.0, 1.0, 0.0]]), np.array([1.0])

    def run(model: FloorModel, reading: FloorReading) -> np.ndarray:
        g = OccupancyGrid(GridSpec(4.0, 4.0, 0.1))
        model.apply(reading, states, w, g)
        return g.prob()

    plain = run(FloorModel(), FloorReading("s1", 1.0, poly))
    assert np.array_equal(run(FloorModel(), r), plain)  # p_occ None (default): the flags change nothing
    marked = run(FloorModel(p_occ=0.7), r)
    wall = marked[4:17, 30:32]  # x = 3.0-3.2 (the feet at 2.0 m + 0.05 from x = 1.0), y = 0.4-1.6
    assert (wall > 0.6).sum() >= 10 and (marked > 0.6).sum() == (wall > 0.6).sum() and plain.max() <= 0.5
