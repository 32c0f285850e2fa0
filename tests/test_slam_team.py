"""SupervisorSLAM and the sensor agents in the running team (docs/slam.md "In the running team"): the
dispatch of processings, several processings in flight per sensor agent, the delay mode's dedicated agents,
and the floor finder's obstacle feet. The agents run on a stand-in context (no host, no DDB cluster)."""

from __future__ import annotations

import asyncio
import json
import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from helpers import until

from haa.agents import team
from haa.agents.sensor_cooccupancy import AgentSensorCooccupancy
from haa.agents.sensor_floorfinder import floor_reading
from haa.agents.supervisor_slam import SupervisorSLAM
from haa.sdk import registry


class FakeCtx:
    """What AgentBase asks of its context, recorded: messages sent, DDB writes, spawns, timers (not run)."""

    def __init__(self, config: dict[str, Any], agent_id: str = "sup", name: str = "A1") -> None:
        self.agent_id, self.name, self.parent, self.epoch, self.host = agent_id, name, None, 1, "h1"
        self.config = json.dumps(config).encode()
        self.clock = SimpleNamespace(now=lambda: self.t)
        self.t = 100.0
        self.sent: list[tuple[str, dict[str, Any]]] = []
        self.writes: list[list[Any]] = []
        self.spawned: list[tuple[str, dict[str, Any]]] = []
        self.stopped = False
        self.release = asyncio.Event()  # DDB writes wait for it when `hold` is set
        self.hold = False

    def send(self, to: str, payload: bytes) -> None:
        self.sent.append((to, json.loads(payload)))

    def log(self, event: str, level: str, fields: dict[str, Any]) -> None:
        pass

    def timer(self, fn: Any, delay: float, period: float | None) -> Any:
        return SimpleNamespace(cancel=lambda: None)

    def backup(self, data: bytes) -> None:
        pass

    def request_stop(self) -> None:
        self.stopped = True

    async def ddb_write(self, ops: Any, atomic: bool, timeout: float) -> list[str]:
        ops = list(ops)
        self.writes.append(ops)
        if self.hold:
            await self.release.wait()
        return [""] * len(ops)

    async def spawn_child(self, type_name: str, config: bytes, timeout: float, key: str | None = None) -> str:
        self.spawned.append((type_name, json.loads(config)))
        return f"{type_name}-{len(self.spawned)}"

    async def ddb_get(self, key: str, timeout: float) -> bytes | None:
        return None  # no processing marker (tests/test_slam_exactly_once.py runs on a DDB replica)

    async def ddb_scan(self, prefix: str, limit: int, timeout: float) -> dict[str, bytes]:
        return {}


def supervisor(mode: str = "jc-slam", **cfg: Any) -> tuple[SupervisorSLAM, FakeCtx]:
    ctx = FakeCtx({"mode": mode, **cfg})
    return SupervisorSLAM(ctx), ctx  # type: ignore[arg-type]


def reading(sup: SupervisorSLAM, avatar: str, n: int, kind: str = "cooccupancy") -> str:
    key = f"{team.K_SLAM_RAW}{avatar}/{n:08d}"
    rec = {"avatar": avatar, "agent": "av-" + avatar, "kind": kind, "t": float(n), "n": n, "radius": 0.12}
    sup._add_reading(key, json.dumps(rec).encode())
    return key


def hello(sup: SupervisorSLAM, agent: str, proc: str, avatar: str = "") -> None:
    asyncio.run(sup.on_message(agent, team.dumps({"op": "hello", "proc": proc, "avatar": avatar})))


def processes(ctx: FakeCtx, agent: str) -> list[str]:
    return [m["key"] for to, m in ctx.sent if to == agent and m.get("op") == "process"]


def test_a_sensor_agent_gets_several_processings_newest_first() -> None:
    """One processing at a time per agent made the agent's latency (frame request, DDB commit: 0.2-0.6 s of
    wall time at --speed 4, for 2-3 ms of CPU) the team's capacity: AF-1 left 176 of 528 readings
    unprocessed. Up to `jobs_per_agent` are out at once, still newest first (LIFO)."""
    sup, ctx = supervisor(jobs_per_agent=3)
    hello(sup, "c1", "sensor_cooccupancy")
    keys = [reading(sup, "s1", n) for n in range(1, 6)]
    sup._dispatch()
    assert processes(ctx, "c1") == keys[::-1][:3]
    assert sup.stacks["sensor_cooccupancy"] == keys[:2]
    # one done: the next newest goes out
    asyncio.run(sup.on_message("c1", team.dumps({"op": "done", "key": keys[4], "proc": "sensor_cooccupancy",
                                                  "ok": True, "n": 1})))
    assert processes(ctx, "c1")[-1] == keys[1]


def test_one_at_a_time_when_jobs_per_agent_is_1() -> None:
    sup, ctx = supervisor(jobs_per_agent=1)
    hello(sup, "c1", "sensor_cooccupancy")
    keys = [reading(sup, "s1", n) for n in range(1, 4)]
    sup._dispatch()
    assert processes(ctx, "c1") == [keys[-1]]


def test_a_restarted_agent_gets_again_what_it_no_longer_has() -> None:
    """A restarted agent is asked what it has in flight (a sync); what it had and no longer has is handed out
    again, what it still has (sent while it was down, kept by its host) is not (tests/test_slam_exactly_once.py)."""
    sup, ctx = supervisor(jobs_per_agent=4)
    hello(sup, "c1", "sensor_cooccupancy")
    keys = [reading(sup, "s1", n) for n in range(1, 4)]
    sup._dispatch()
    assert sorted(sup.sensors["sensor_cooccupancy"]["c1"]["jobs"]) == sorted(keys)
    ctx.sent.clear()
    hello(sup, "c1", "sensor_cooccupancy")  # restarted: asked first, nothing handed out yet
    (sync,) = [m for to, m in ctx.sent if to == "c1" and m.get("op") == "sync"]
    assert processes(ctx, "c1") == []
    asyncio.run(sup.on_message("c1", team.dumps({"op": "synced", "proc": "sensor_cooccupancy",
                                                  "sync": sync["sync"], "busy": [keys[0]]})))
    assert sorted(processes(ctx, "c1")) == sorted(keys[1:])


def test_the_supervisor_does_not_wait_for_the_commit_of_a_finished_reading() -> None:
    """A finished reading's delete + counter went through `await ddb_write` in the mailbox, holding up the
    log events and the other reports behind the commit."""
    sup, ctx = supervisor()

    async def go() -> None:
        await sup.on_message("c1", team.dumps({"op": "hello", "proc": "sensor_cooccupancy"}))
        k = reading(sup, "s1", 1)
        sup._dispatch()
        ctx.hold = True
        await asyncio.wait_for(sup.on_message("c1", team.dumps(
            {"op": "done", "key": k, "proc": "sensor_cooccupancy", "ok": True})), 1.0)
        await asyncio.sleep(0)
        assert any(op for w in ctx.writes for op in w)  # the write was made ...
        ctx.release.set()  # ... and is committed later
        await asyncio.gather(*sup.tasks)

    asyncio.run(go())


def test_delay_mode_gives_each_avatar_its_own_agents() -> None:
    """Table 7.2-4 'delay': one agent of each type per avatar, each avatar's readings to its own agents only,
    oldest first; the dedicated agents are types of their own without the per-host limit."""
    sup, ctx = supervisor("delay", jobs_per_agent=1)

    async def go() -> None:
        ka = [reading(sup, "s1", n) for n in (1, 2)]
        kb = [reading(sup, "s2", n) for n in (3,)]
        sup._dispatch()
        await asyncio.gather(*sup.tasks)
        types = sorted((t, c["avatar"]) for t, c in ctx.spawned)
        assert types == [("sensor_cooccupancy_dedicated", "s1"), ("sensor_cooccupancy_dedicated", "s2")]
        for aid, avatar in (("d1", "s1"), ("d2", "s2")):
            await sup.on_message(aid, team.dumps({"op": "hello", "proc": "sensor_cooccupancy", "avatar": avatar}))
        assert processes(ctx, "d1") == [ka[0]]  # in order, one at a time (jobs_per_agent=1)
        assert processes(ctx, "d2") == kb
        # a second reading of s1 never goes to s2's idle agent
        await sup.on_message("d2", team.dumps({"op": "done", "key": kb[0], "proc": "sensor_cooccupancy", "ok": True}))
        assert processes(ctx, "d2") == kb

    asyncio.run(go())
    cls = registry.get("sensor_cooccupancy_dedicated")
    assert cls.MAX_PER_HOST == 0 and cls.PROC == "sensor_cooccupancy"
    assert registry.get("sensor_cooccupancy").MAX_PER_HOST == 1


def test_a_sensor_agent_runs_its_processings_side_by_side() -> None:
    ctx = FakeCtx({"supervisor": "sup"}, agent_id="c1")
    agent = AgentSensorCooccupancy(ctx)  # type: ignore[arg-type]

    async def go() -> None:
        ctx.hold = True  # the DDB commits wait
        for n in (1, 2, 3):
            rec = {"avatar": "s1", "agent": "a", "kind": "cooccupancy", "t": float(n), "n": n, "radius": 0.12}
            await asyncio.wait_for(agent.on_message("sup", team.dumps(
                {"op": "process", "key": f"k{n}", "proc": "sensor_cooccupancy", "reading": rec})), 1.0)
        await until(lambda: len(ctx.writes) == 3, what="the three processings at their DDB writes, side by side")
        assert not [m for _, m in ctx.sent if m.get("op") == "done"]
        ctx.release.set()
        await asyncio.gather(*agent.jobs)
        done = [m for _, m in ctx.sent if m.get("op") == "done"]
        assert sorted(m["key"] for m in done) == ["k1", "k2", "k3"] and all(m["ok"] and m["n"] == 1 for m in done)

    asyncio.run(go())


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
