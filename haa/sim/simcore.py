"""The core of haa-sim's service: the world, its clock and the subscriptions of the stream handlers (haa.sim.service's
docstring, "Clock" and "Everything runs on one asyncio loop"). `SimCore.advance` steps the world in ticks and,
after each, produces the readings (odometry at each subscriber's period, sonar every `SONAR_PERIOD` of each
sweeper's life), action progress and events, queued to the handlers of haa.sim.servicer; `run_clock` drives it in
real or accelerated time (step mode: `SimControl.Step` does).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import grpc

from haa.pb import sim_pb2 as pb
from haa.sim import actions as act
from haa.sim.convert import encode_frame, event_msg, pose_msg
from haa.sim.groundtruth import explorable_area, explorable_grid, surface_grid
from haa.sim.sensors import SONAR_PERIOD
from haa.sim.world import ACTIVE, World

DEFAULT_TICK = 0.05
DEFAULT_PERIOD = 0.1
QUEUE_MAX = 10_000
_STATUS = {
    act.RUNNING: pb.ACTION_STATUS_RUNNING,
    act.SUCCEEDED: pb.ACTION_STATUS_SUCCEEDED,
    act.FAILED: pb.ACTION_STATUS_FAILED,
    act.CANCELLED: pb.ACTION_STATUS_CANCELLED,
}


def log(event: str, **kw: Any) -> None:
    """One JSON line on stderr (haa-sim's log)."""
    print(
        json.dumps({"ts": round(time.time(), 3), "service": "haa-sim", "event": event, **kw}),
        file=sys.stderr,
        flush=True,
    )


class End:
    """Queue sentinel: the stream ends (with an error status when `code` is set)."""

    def __init__(self, code: grpc.StatusCode | None = None, details: str = "") -> None:
        self.code = code
        self.details = details


@dataclass
class Sub:
    avatar: str
    period: float
    due: float
    queue: asyncio.Queue[Any]


@dataclass
class Watch:
    avatar: str
    action: act.Action
    queue: asyncio.Queue[Any]
    period: float
    due: float
    encoding: pb.ImageEncoding = pb.IMAGE_ENCODING_RAW_RGB


class SimCore:
    """World + clock + subscriptions. Only ever used from the asyncio loop's thread."""

    def __init__(
        self, world: World, arena_name: str, mode: str = "realtime", speed: float = 1.0, tick: float = DEFAULT_TICK
    ) -> None:
        self.world = world
        self.arena_name = arena_name
        self.mode = mode
        self.speed = speed
        self.tick = tick
        self.odo_subs: list[Sub] = []
        self.sonar_subs: list[Sub] = []
        self.watches: list[Watch] = []
        self.event_subs: list[asyncio.Queue[Any]] = []
        self.next_sonar: dict[str, float] = {}
        self.dropped = 0
        self._speed_samples: deque[tuple[float, float]] = deque(maxlen=200)
        self._grids: dict[float, pb.GridReply] = {}
        self.process_events()

    # ---------------------------------------------------------- queues
    def put(self, q: asyncio.Queue[Any], item: Any) -> None:
        if q.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                q.get_nowait()
            self.dropped += 1
        q.put_nowait(item)

    # ---------------------------------------------------------- time
    def advance(self, dt: float) -> None:
        """Advance simulated time by dt in ticks, producing readings and updates after each tick."""
        end = self.world.time + dt
        while self.world.time < end - 1e-9:
            self.world.step(min(self.tick, end - self.world.time))
            self.after_tick()

    def after_tick(self) -> None:
        w = self.world
        t = w.time
        self.process_events()
        for aid, due in list(self.next_sonar.items()):
            av = w.avatars.get(aid)
            if av is None or av.status != ACTIVE:
                del self.next_sonar[aid]
                continue
            if t >= due - 1e-9:
                scan = pb.SonarScan(avatar_id=aid, time=t)
                for r in w.sonar(aid):
                    scan.readings.add(
                        bearing=r.bearing,
                        echo=r.range is not None,
                        range=r.range or 0.0,
                        fov=r.fov,
                        max_range=r.max_range,
                    )
                for s in self.sonar_subs:
                    if s.avatar == aid:
                        self.put(s.queue, scan)
                nxt = due + SONAR_PERIOD
                self.next_sonar[aid] = nxt if nxt > t else t + SONAR_PERIOD
        for s in self.odo_subs:
            if t >= s.due - 1e-9:
                self.put(s.queue, self.odometry_msg(s.avatar))
                s.due += s.period
                if s.due <= t:
                    s.due = t + s.period
        self.flush_actions()
        self._speed_samples.append((time.monotonic(), t))

    def achieved_speed(self) -> float:
        if len(self._speed_samples) < 2:
            return 0.0
        (w0, s0), (w1, s1) = self._speed_samples[0], self._speed_samples[-1]
        return (s1 - s0) / (w1 - w0) if w1 > w0 else 0.0

    # ---------------------------------------------------------- events and subscriptions
    def process_events(self) -> None:
        w = self.world
        for e in w.drain_events():
            if e.kind == "joined":
                av = w.avatars[e.avatar]
                if av.spec.sonars:
                    self.next_sonar[e.avatar] = e.time + SONAR_PERIOD
                log("joined", avatar=e.avatar, type=av.kind, time=round(e.time, 3))
            elif e.kind in ("retired", "crashed"):
                self.next_sonar.pop(e.avatar, None)
                end = End(grpc.StatusCode.UNAVAILABLE, f"avatar {e.avatar} {e.kind}")
                for lst in (self.odo_subs, self.sonar_subs):
                    for s in [s for s in lst if s.avatar == e.avatar]:
                        self.put(s.queue, end)
                        lst.remove(s)
                log(e.kind, avatar=e.avatar, time=round(e.time, 3))
            elif e.kind == "schedule":
                log("schedule_error", time=round(e.time, 3), error=e.detail.get("error"))
            elif e.kind == "bump":
                x, y, th = e.detail["pose"]
                log("bump", avatar=e.avatar, time=round(e.time, 3), detail=e.detail["with"],
                    pose=[round(x, 3), round(y, 3), round(th, 3)])
            msg = event_msg(e, w)
            for q in self.event_subs:
                self.put(q, msg)
        self.flush_actions()

    def odometry_msg(self, aid: str) -> pb.OdometryReading:
        av = self.world.avatars[aid]
        return pb.OdometryReading(
            avatar_id=aid,
            time=self.world.time,
            pose=pose_msg(av.odo.pose),
            distance=av.odo.distance,
            rotation=av.odo.rotation,
            bumps=av.bumps,
            bumper=av.contacts > 0,
        )

    def update_msg(self, wt: Watch) -> pb.ActionUpdate:
        a = wt.action
        av = self.world.avatars[wt.avatar]
        m = pb.ActionUpdate(
            avatar_id=wt.avatar,
            action_id=a.id,
            kind=a.kind,
            status=_STATUS[a.status],
            progress=a.progress,
            reason=a.reason,
            time=self.world.time,
            odometry=pose_msg(av.odo.pose),
            collectable_id=a.result.get("collectable", "") or "",
            region_id=a.result.get("region", "") or "",
        )
        if "frame" in a.result:
            m.frame.CopyFrom(encode_frame(a.result["frame"], wt.encoding))
        return m

    def flush_actions(self) -> None:
        t = self.world.time
        for wt in list(self.watches):
            if wt.action.done:
                self.put(wt.queue, self.update_msg(wt))
                self.put(wt.queue, End())
                self.watches.remove(wt)
            elif t >= wt.due - 1e-9:
                self.put(wt.queue, self.update_msg(wt))
                wt.due += wt.period
                if wt.due <= t:
                    wt.due = t + wt.period

    def start_action(self, wt: Watch) -> None:
        self.world.start_action(wt.avatar, wt.action)
        if not wt.action.done:
            self.put(wt.queue, self.update_msg(wt))  # accepted
        self.watches.append(wt)
        self.process_events()

    def close_streams(self) -> None:
        """End every stream (the server is stopping)."""
        end = End(grpc.StatusCode.UNAVAILABLE, "haa-sim is stopping")
        for s in self.odo_subs + self.sonar_subs:
            self.put(s.queue, end)
        for wt in self.watches:
            self.put(wt.queue, end)
        for q in self.event_subs:
            self.put(q, end)

    # ---------------------------------------------------------- ground truth
    def grid(self, resolution: float) -> pb.GridReply:
        key = round(float(resolution), 6)
        if key not in self._grids:
            if len(self._grids) >= 8:
                self._grids.clear()
            g = self.world.ideal_grid(key)
            ex = explorable_grid(self.world.arena, key)
            self._grids[key] = pb.GridReply(
                width=g.grid.shape[1],
                height=g.grid.shape[0],
                resolution=key,
                origin=pb.Point(x=g.origin[0], y=g.origin[1]),
                cells=g.grid.tobytes(),
                explorable=ex.grid.tobytes(),
                explorable_area=explorable_area(self.world.arena, key),
                surface=surface_grid(self.world.arena, key).grid.tobytes(),
            )
        return self._grids[key]

    # ---------------------------------------------------------- clock
    async def run_clock(self) -> None:
        """Real-time / accelerated clock (not used in step mode)."""
        loop = asyncio.get_running_loop()
        wall0, sim0 = loop.time(), self.world.time
        while True:
            target = wall0 + (self.world.time + self.tick - sim0) / self.speed
            delay = target - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            else:
                await asyncio.sleep(0)
                if delay < -1.0:  # far behind (a slow machine, a long capture): do not try to catch up
                    wall0, sim0 = loop.time(), self.world.time
            self.advance(self.tick)
