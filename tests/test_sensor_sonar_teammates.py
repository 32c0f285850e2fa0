"""AgentSensorSonar drops echoes off teammates (haa.agents.sensor_sonar, docs/slam.md "Teammate echoes"): the
geometry of `teammate_echo`, and the agent on a DDB with `slam/estimates` and the avatar registry."""

from __future__ import annotations

import asyncio
import math

from test_slam_exactly_once import Bus

from haa.agents import team
from haa.agents.sensor_sonar import AgentSensorSonar, teammate_echo
from haa.core.ddb import ops as ddbops
from haa.slam.sensors import SonarReading

FOV = 0.349


def test_an_echo_at_a_teammates_range_in_its_direction_is_the_teammate() -> None:
    me = (0.0, 0.0, 0.0)
    mate = [(1.0, 0.0, 0.2)]
    assert teammate_echo(me, 0.0, 0.8, FOV, mate)  # its near rim, straight ahead
    assert teammate_echo(me, 0.0, 0.75, FOV, mate)  # a few cm short of it: the estimates are a few cm off
    assert not teammate_echo(me, 0.0, 1.6, FOV, mate)  # a wall behind it
    assert not teammate_echo(me, 0.0, 0.3, FOV, mate)  # something between us
    assert not teammate_echo(me, math.pi / 2, 0.8, FOV, mate)  # the sonar looks elsewhere
    # the cone's edge meets its disc: the sonar's axis passes beside it
    off = FOV / 2 + math.asin(0.3 / 1.0) - 0.02
    assert teammate_echo(me, off, 0.85, FOV, mate)
    assert not teammate_echo(me, off + 0.1, 0.85, FOV, mate)
    assert not teammate_echo(me, 0.0, 0.8, FOV, [])


def test_a_teammate_closer_than_its_radius_counts_at_any_bearing_within_range() -> None:
    assert teammate_echo((0.0, 0.0, 0.0), 2.5, 0.1, FOV, [(0.25, 0.0, 0.2)])


def _bus(ests: dict[str, dict[str, float]], regs: dict[str, dict[str, object]]) -> Bus:
    bus = Bus()
    ops = [team.op_put_json(team.K_SLAM_ESTIMATES, ests)]
    ops += [team.op_put_json(team.K_AVATARS + a, r) for a, r in regs.items()]
    bus.ddb.apply(ddbops.encode_batch(ops))
    return bus


def _scan(bus: Bus, echoes: list[list[float | None]], t: float = 100.0) -> list[SonarReading]:
    agent = bus.start(AgentSensorSonar, "s1", {"supervisor": "sup"})
    return asyncio.run(agent.process({"avatar": "w1", "t": t, "echoes": echoes, "fov": FOV, "max_range": 2.0}))


def test_the_agent_drops_the_echo_off_an_active_teammate_and_keeps_the_rest() -> None:
    ests = {"w1": {"t": 99.0, "x": 1.0, "y": 1.0, "theta": 0.0}, "s1": {"t": 99.5, "x": 2.0, "y": 1.0, "theta": 3.1}}
    bus = _bus(ests, {"w1": {"status": "active", "radius": 0.2}, "s1": {"status": "active", "radius": 0.12}})
    out = _scan(bus, [[0.0, 0.88], [math.pi / 2, 1.2], [-math.pi / 2, None]])
    assert [(e.bearing, e.range) for e in out[0].echoes] == [(math.pi / 2, 1.2), (-math.pi / 2, None)]
    assert bus.agents["s1"].teammate_echoes == 1


def test_a_crashed_teammate_is_an_obstacle_and_stale_or_missing_estimates_filter_nothing() -> None:
    ests = {"w1": {"t": 99.0, "x": 1.0, "y": 1.0, "theta": 0.0}, "s1": {"t": 99.5, "x": 2.0, "y": 1.0, "theta": 3.1}}
    crashed = _bus(ests, {"s1": {"status": "retired", "how": "crashed", "radius": 0.12}})
    assert len(_scan(crashed, [[0.0, 0.88]])[0].echoes) == 1
    stale = _bus({**ests, "s1": {**ests["s1"], "t": 80.0}}, {"s1": {"status": "active"}})
    assert len(_scan(stale, [[0.0, 0.88]])[0].echoes) == 1
    unplaced = _bus({"s1": ests["s1"]}, {"s1": {"status": "active"}})  # no estimate of this avatar yet
    assert len(_scan(unplaced, [[0.0, 0.88]])[0].echoes) == 1
    # a registry entry without a radius: the largest type's (0.2 m) — the echo 0.08 m short of a 0.12 m rim
    assert _scan(_bus(ests, {"s1": {"status": "active"}}), [[0.0, 0.8]]) == []
