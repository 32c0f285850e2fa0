"""AvatarSimulation's pick_up / drop when its agent did not see the action end (moved or crashed while it ran):
the action is backed up before it starts and a resumed agent runs it again; an outcome that says the first one
happened (`capacity_full` with room in the records, `nothing_carried` with the item in them) is recorded as
done (haa.agents.avatar_simulation `_collect`). haa-sim's gripper is stood in for by a counter that answers as
haa-sim's World.pick_up / drop do."""

from __future__ import annotations

import asyncio
import json
from types import SimpleNamespace
from typing import Any

from test_slam_exactly_once import Bus as _Bus
from test_slam_exactly_once import Ctx

from haa.agents import team
from haa.agents.avatar_simulation import AvatarSimulation
from haa.core.ddb import ops as ddbops
from haa.pb import sim_pb2 as spb


class PutCtx(Ctx):
    async def ddb_put(self, key: str, data: bytes, kind: str, timeout: float) -> None:
        self.bus.ddb.apply(ddbops.encode_batch([ddbops.put(key, kind, json.loads(data))]))


class Bus(_Bus):
    def ctx(self, agent_id: str, config: dict[str, Any]) -> Ctx:
        return PutCtx(self, agent_id, config)


class Gripper:
    """Act(pick_up|drop) of one avatar of capacity 1 with a collectable in reach (haa.sim.world's answers)."""

    def __init__(self) -> None:
        self.load = 0
        self.calls: list[str] = []

    def Act(self, req: Any, metadata: Any = ()) -> Any:
        kind = req.WhichOneof("action")
        self.calls.append(kind)

        async def updates() -> Any:
            if kind == "pick_up":
                ok, why = (self.load < 1), "capacity_full"
                self.load += ok
            else:
                ok, why = (self.load > 0), "nothing_carried"
                self.load -= ok
            st = spb.ACTION_STATUS_SUCCEEDED if ok else spb.ACTION_STATUS_FAILED
            yield spb.ActionUpdate(status=st, reason="" if ok else why)

        return updates()


def avatar(bus: Bus, grip: Gripper, aid: str = "A3") -> AvatarSimulation:
    a = bus.start(AvatarSimulation, aid, {"avatar": "w1", "type": "sweeper"})
    a.link = SimpleNamespace(avatar=grip, metadata=())
    a.info = SimpleNamespace(capacity=1, radius=0.2)
    return a


def answer(bus: Bus) -> dict[str, Any]:
    return [m for _, dst, m in bus.sent if dst == "F1"][-1]


def registry(bus: Bus) -> dict[str, Any]:
    o = bus.ddb.get(team.K_AVATARS + "w1")
    assert o is not None
    return dict(json.loads(o.data))


def test_a_pick_up_whose_end_the_agent_missed_is_recorded_when_it_runs_again() -> None:
    async def main() -> None:
        bus, grip = Bus(), Gripper()
        first = avatar(bus, grip)
        cmd = {"op": "pick_up", "tid": 4, "item": 2}
        # the first life: the gripper closes, the agent is gone before it hears so (a transfer, a host crash)
        first.pending_action = {**cmd, "src": "F1"}
        first.backup()
        await grip.Act(spb.ActionRequest(pick_up=spb.PickUp())).__anext__()
        assert grip.load == 1 and bus.backups["A3"]
        # the next life resumes from the backup and runs it again: capacity_full, nothing in its records
        second = avatar(bus, grip)
        second.recover(bus.backups["A3"])
        assert second.pending_action is not None
        await second._collect("F1", second.pending_action, again=True)
        assert second.cargo == [2] and registry(bus)["cargo"] == [2] and second.pending_action is None
        assert answer(bus) == {**answer(bus), "op": "picked", "ok": True, "item": 2, "tid": 4}
        assert json.loads(bus.backups["A3"])["pending"] is None
        # a first pick_up of a full gripper is an answer, not a guess
        await second._collect("F1", {"op": "pick_up", "tid": 5, "item": 3})
        assert answer(bus)["ok"] is False and answer(bus)["reason"] == "capacity_full" and second.cargo == [2]

    asyncio.run(main())


def test_a_drop_whose_end_the_agent_missed_is_recorded_and_an_unstarted_one_is_done() -> None:
    async def main() -> None:
        bus, grip = Bus(), Gripper()
        grip.load = 1
        a = avatar(bus, grip)
        a.cargo = [2]
        grip.load = 0  # the first life's drop happened
        await a._collect("F1", {"op": "drop", "tid": 6, "item": 2}, again=True)
        assert a.cargo == [] and a.last_drop is not None and a.last_drop["item"] == 2
        assert answer(bus)["op"] == "dropped" and answer(bus)["ok"] is True
        # a pending drop that never reached the hardware: done now
        b = avatar(Bus(), Gripper(), "A4")
        b.cargo = [1]
        b.link.avatar.load = 1  # type: ignore[union-attr]
        await b._collect("F1", {"op": "drop", "tid": 7, "item": 1}, again=True)
        assert b.cargo == [] and b.link.avatar.load == 0  # type: ignore[union-attr]

    asyncio.run(main())
