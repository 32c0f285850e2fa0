"""AF-2's scenario on real processes, short (tests/missions/congregate.yaml): the explore supervisor gives way
to SupervisorCongregate once the congregation point's landmark is in the map, both seekers end on the ring
around the true point, on different slots, and the mission says why it finished."""

from __future__ import annotations

import json
import math
from pathlib import Path

from haa.mission import load_mission
from haa.mission import runner as rn

HERE = Path(__file__).resolve().parent
POINT = (2.4, 6.0)  # haa/sim/arenas/small.yaml: congregation landmark 200


def test_two_seekers_gather_on_the_ring_around_the_point(tmp_path: Path) -> None:
    m = load_mission(HERE / "missions" / "congregate.yaml")
    r = rn.run_mission(m, None, tmp_path / "out")
    assert r["completed"], r["reason"]
    assert "slot" in r["reason"]
    transcript = (tmp_path / "out" / "transcript.txt").read_text()
    assert "congregation point found" in transcript
    assert "every avatar on its slot (2)" in transcript
    # where the seekers really are at the end (the simulator's truth, recorded for the metrics)
    truth = json.loads((tmp_path / "out" / "samples.json").read_text())["truth"]
    ends = {a: tuple(poses[-1][1:3]) for a, poses in truth.items()}
    assert set(ends) == {"s1", "s2"}
    radius, tol = m.spec.congregation.radius_m, m.spec.congregation.tolerance_m
    for a, p in ends.items():
        # on the ring: its estimate was within the tolerance of a slot placed on the estimated point; allow
        # for the point's and the avatar's estimation errors (a few cm each in this mission) on top
        assert abs(math.dist(p, POINT) - radius) <= tol + 0.2, (a, p)
    # on different slots: two slots of a ring of two are a diameter apart
    assert math.dist(ends["s1"], ends["s2"]) >= 2 * radius - 2 * (tol + 0.2)
    assert r["sim_truth_calls"] == {}, r["sim_truth_calls"]  # found with the camera, not told
