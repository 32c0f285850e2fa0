"""The avatar agent's actions besides driving its planner's path (AvatarSimulation, haa/agents/avatar_simulation.py):
the collection actions SupervisorForage asks for (pick_up, drop; App. III L3017 "Assign target and collection
actions" / "Send action updates"), and turning in place to look around when the planner finds it boxed in.

A mixin of AvatarSimulation: it uses the agent's link to haa-sim (`link`, `info`), its records (`cargo`,
`last_drop`, `pending_action`, `target`), and its methods `_pose_map`, `_registration`, `_retired`,
`_send_planner`; nothing here runs on its own.
"""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING, Any

import grpc

from haa.agents import team
from haa.pb import sim_pb2 as spb

#: s of mission time a boxed-in avatar waits, after turning in place, for its readings to reach the map
LOOK_WAIT_S = 10.0


def left_how(details: str | None) -> str:
    """"crashed" if haa-sim's UNAVAILABLE details say the avatar crashed ("avatar s2 crashed"), else "retired"
    (a graceful leave, or haa-sim stopping)."""
    return "crashed" if "crashed" in (details or "") else "retired"



class AvatarActions:
    """Collection actions and looking around (module docstring)."""

    if TYPE_CHECKING:  # what the mixin uses of AvatarSimulation (and AgentBase)
        cfg: Any
        name_: str
        link: team.SimLink | None
        info: spb.AvatarInfo | None
        cargo: list[int]
        last_drop: dict[str, Any] | None
        pending_action: dict[str, Any] | None
        target: dict[str, Any] | None
        look_arounds: int
        _ctx: Any

        def _pose_map(self) -> dict[str, Any]: ...
        def _registration(self, status: str) -> dict[str, Any]: ...
        async def _retired(self, why: str, how: str = "retired") -> None: ...
        def _send_planner(self, msg: dict[str, Any]) -> None: ...
        def backup(self) -> None: ...
        def send(self, to: str, payload: bytes) -> None: ...
        def log(self, event: str, *, level: str = "info", **fields: Any) -> None: ...
        def now(self) -> float: ...
        def call_later(self, delay: float, fn: Any) -> Any: ...
        async def ddb_scan(self, prefix: str, limit: int = ...) -> dict[str, bytes]: ...
        async def ddb_put_json(self, key: str, value: Any) -> None: ...

    def _left_sim(self, e: grpc.aio.AioRpcError, why: str) -> bool:
        """Whether haa-sim's error `e` says the avatar is gone (UNAVAILABLE: it crashed, retired, or haa-sim
        stopped); then the agent retires (`why`), soon, outside the caller's stream."""
        if e.code() != grpc.StatusCode.UNAVAILABLE:
            return False
        how = left_how(e.details())
        self.call_later(0, lambda: self._retired(why, how))
        return True

    async def _look_around(self, tid: Any) -> None:
        """Boxed in (the planner's "start enclosed", haa.agents.path_planner.enclosed): turn once in place, so
        that the sonar ring and the camera sweep what the avatar stands beside, wait until those readings are in
        the map (its `slam/raw/<avatar>/` entries processed, at most LOOK_WAIT_S), and ask the planner again.
        What boxes an avatar in is most often an obstacle that has gone (a teammate mapped where it stood) in
        the blind sectors of its sensors; a real trap is reported unreachable after this one turn."""
        assert self.link is not None
        self.look_arounds += 1
        self.log("look_around", tid=tid)
        try:
            req = spb.ActionRequest(avatar_id=self.name_, rotate=spb.Rotate(angle=2 * math.pi), progress_period=0.5)
            async for _ in self.link.avatar.Act(req, metadata=self.link.metadata):
                pass
            t0 = self.now()
            prefix = f"{team.K_SLAM_RAW}{self.name_}/"
            while self.now() - t0 < LOOK_WAIT_S and await self.ddb_scan(prefix, limit=1):
                await asyncio.sleep(self._ctx.clock.wall_delay(0.2))
        except asyncio.CancelledError:
            raise
        except grpc.aio.AioRpcError as e:
            if self._left_sim(e, "actions unavailable"):
                return
            self.log("drive_error", level="warning", error=str(e))
        if self.target and self.target.get("tid") == tid:
            self._send_planner({"op": "goto", **self.target})

    async def _collect(self, src: str, msg: dict[str, Any], again: bool = False) -> None:
        """A pick_up or drop action for SupervisorForage (App. III: "Assign target and collection actions" /
        "Send action updates"): the outcome updates `cargo` / `last_drop` in the registry (committed before
        the answer), then {"op": "picked"|"dropped", "avatar", "tid", "item", "ok", "reason", "pose"} goes
        to the supervisor. A pick_up takes the nearest collectable in reach: the team's id is the supervisor's
        (haa-sim's own ids are not the team's business).

        **An action its agent did not see end** (moved or crashed while it ran: the gripper closed, the answer
        was lost with the old instance) would leave the hardware carrying what no record says — both
        supervisors then saw "carries something else" to the end of a CI mission. The action is backed up
        (`pending_action`) before it starts, and a resumed agent runs it `again`: the actions are idempotent
        by their outcome — a pick_up answered `capacity_full` while the records hold less than the capacity
        means the first one took it; a drop answered `nothing_carried` while the records hold the item means
        the first one put it down (here: the avatar stood still since)."""
        assert self.link is not None
        op, item = str(msg["op"]), int(msg.get("item", -1))
        self.pending_action = {"op": op, "item": item, "tid": msg.get("tid"), "src": src}
        self.backup()
        if op == "pick_up":
            req = spb.ActionRequest(avatar_id=self.name_, pick_up=spb.PickUp(), progress_period=0.5)
        else:
            req = spb.ActionRequest(avatar_id=self.name_, drop=spb.Drop(), progress_period=0.5)
        last = None
        try:
            async for u in self.link.avatar.Act(req, metadata=self.link.metadata):
                last = u
        except grpc.aio.AioRpcError as e:
            if self._left_sim(e, "actions unavailable"):
                return
            last = None
        ok = last is not None and last.status == spb.ACTION_STATUS_SUCCEEDED
        reason = "" if ok else (last.reason if last is not None else "no outcome")
        capacity = int(self.info.capacity) if self.info is not None else team.CAPACITY.get(self.cfg.type, 0)
        if again and not ok and ((op == "pick_up" and reason == "capacity_full" and len(self.cargo) < capacity
                                  and item not in self.cargo)
                                 or (op == "drop" and reason == "nothing_carried" and item in self.cargo)):
            self.log("action_completed_unseen", op=op, item=item)
            ok, reason = True, ""
        pose = self._pose_map()
        if ok and op == "pick_up":
            if item not in self.cargo:
                self.cargo.append(item)
        elif ok:
            self.cargo = [c for c in self.cargo if c != item]
            self.last_drop = {"item": item, "x": pose.get("x"), "y": pose.get("y"),
                              "theta": pose.get("theta"), "t": round(self.now(), 3)}
        self.pending_action = None
        self.backup()
        if ok:
            await self.ddb_put_json(team.K_AVATARS + self.name_, self._registration("active"))
        if src:
            self.send(src, team.dumps({"op": "picked" if op == "pick_up" else "dropped", "avatar": self.name_,
                                       "tid": msg.get("tid"), "item": item, "ok": ok, "reason": reason,
                                       "pose": pose}))
