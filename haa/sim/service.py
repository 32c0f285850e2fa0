"""haa-sim: the avatar simulator as a gRPC service (proto/haa/pb/sim.proto), and a small blocking client.

```
haa-sim --arena small|large|FILE --listen HOST:PORT --seed S [--speed X | --step] [--schedule FILE]
        [--token-file FILE] [--tick 0.05] [--drift thesis|table|systematic] [--metrics-port P]
```

* Clock. Real time by default; `--speed X` runs X simulated seconds per wall second (as fast as it can when
  X is more than the machine manages; `Info.achieved_speed` says what it gets); `--step` freezes the clock
  so that only `SimControl.Step(dt)` advances it — deterministic for a given seed and call sequence, for
  tests. Time advances in ticks of `--tick` simulated seconds (physics sub-steps inside, haa.sim.world).
* Everything runs on one asyncio loop: the world is only touched between ticks, so no locks. Readings are
  produced inside the tick (synchronously, hence deterministically) and queued to the stream handlers:
  odometry at each subscriber's period, sonar every 1.0 s of each sweeper's life (whether anyone listens or
  not, so readings do not depend on subscribers), action progress at the requested period.
* AvatarSim is what avatar agents use (hardware stand-in): Register (create, or attach to an avatar that
  joined by schedule), Release (retire), Act (an AvatarBase action; the stream ends with its outcome),
  Cancel, SetVelocity, Odometry and Sonar streams, Capture (a rendered frame: raw RGB, PNG or JPEG), Detect (the
  camera's landmark and collectable detections), Events (joined / retired / crashed / picked / dropped /
  deposited). A retired or crashed avatar's streams end with UNAVAILABLE, like hardware that stopped
  answering; calls about it get UNAVAILABLE too.
* GroundTruth serves what metrics need: Info (arena YAML, time, mode), Poses (true and odometry), the ideal
  OccupancyGrid with the explorable mask (eq. 7.1-1/7.1-2), Landmarks, Collectables.
* SimControl: Step (step mode only), Join / Retire / Crash on demand (the schedule's actions).

With `--token-file`, every call must carry the token in metadata `x-haa-token` (else UNAUTHENTICATED, checked
before the request is decoded: haa.rpcguard); a request that does not parse is INVALID_ARGUMENT, and no call
ends in UNKNOWN. Requests up to gRPC's default 4 MiB are accepted (larger: RESOURCE_EXHAUSTED), replies up
to 32 MiB (a raw 640x480 capture is 0.9 MiB).
Logs are JSON lines on stderr; the first is {"event": "listening", "address": ..., "port": ..., "metrics": URL}.
With `--metrics-port P` (or HAA_METRICS_PORT) it serves Prometheus metrics on http://<listen host>:P/metrics
(haa.sim.metrics, docs/metrics.md: simulated time, avatars by status, streams, refused calls, CPU).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import hmac
import inspect
import json
import math
import os
import signal
import sys
import time
import traceback
from collections import deque
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import grpc
import numpy as np
from grpc import aio

from haa import files, rpcguard
from haa.pb import sim_pb2 as pb
from haa.pb import sim_pb2_grpc as pbg
from haa.sim import actions as act
from haa.sim.arena import ArenaError, load_arena, parse_arena
from haa.sim.avatars import AVATAR_TYPES, DRIFT_MODELS
from haa.sim.camera import CameraFrame, floor_homography, intrinsics
from haa.sim.groundtruth import explorable_area, explorable_grid, surface_grid
from haa.sim.render import AvatarView, TruthView
from haa.sim.schedule import ScheduleError, load_schedule
from haa.sim.sensors import CAMERA_HEIGHT, SONAR_BEARINGS, SONAR_FOV, SONAR_PERIOD, SONAR_RANGE
from haa.sim.world import ACTIVE, AvatarState, CollectableState, SimEvent, World

MD_TOKEN = "x-haa-token"
#: metadata naming the caller (an agent name, "runner", ...): ground-truth calls are counted per caller
MD_CALLER = "x-haa-caller"
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
    print(
        json.dumps({"ts": round(time.time(), 3), "service": "haa-sim", "event": event, **kw}),
        file=sys.stderr,
        flush=True,
    )


# --------------------------------------------------------------------------- conversions
def pose_msg(p: tuple[float, float, float]) -> pb.Pose:
    return pb.Pose(x=p[0], y=p[1], theta=p[2])


def camera_info(av: AvatarState) -> pb.CameraInfo:
    c = av.camera
    return pb.CameraInfo(
        name=c.name,
        fov=c.fov,
        max_range=c.max_range,
        noise_sigma=c.sigma,
        width=c.width,
        height=c.height,
        K=intrinsics(c).ravel().tolist(),
        mount=pb.Mount(x=0.0, y=0.0, z=CAMERA_HEIGHT, pitch=0.0),
    )


def avatar_info(av: AvatarState) -> pb.AvatarInfo:
    s = av.spec
    return pb.AvatarInfo(
        avatar_id=av.id,
        type=av.kind,
        status=av.status,
        max_speed=s.max_speed,
        max_turn=s.max_turn,
        radius=s.radius,
        capacity=s.capacity,
        sonars=s.sonars,
        linear_drift=av.drift_figures[0],
        angular_drift=av.drift_figures[1],
        camera=camera_info(av),
        start_pose=pose_msg(av.start_pose),
        joined=av.joined,
        sonar_bearings=list(SONAR_BEARINGS[: s.sonars]),
        sonar_fov=SONAR_FOV,
        sonar_range=SONAR_RANGE,
        sonar_period=SONAR_PERIOD,
    )


def encode_frame(f: CameraFrame, encoding: pb.ImageEncoding) -> pb.CameraFrame:
    if encoding == pb.IMAGE_ENCODING_RAW_RGB:
        data = np.ascontiguousarray(f.image).tobytes()
    else:
        bgr = cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR)
        if encoding == pb.IMAGE_ENCODING_JPEG:
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        else:
            ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RuntimeError("image encoding failed")
        data = buf.tobytes()
    return pb.CameraFrame(
        avatar_id=f.avatar,
        time=f.time,
        camera=f.camera,
        width=f.width,
        height=f.height,
        encoding=encoding,
        data=data,
        K=f.K.ravel().tolist(),
        mount=pb.Mount(x=f.mount[0], y=f.mount[1], z=f.mount[2], pitch=f.mount[3]),
        fov=f.fov,
        max_range=f.max_range,
        odometry=pose_msg(f.odometry),
        floor_homography=floor_homography(f.K, f.mount).ravel().tolist(),
    )


def decode_frame(m: pb.CameraFrame) -> np.ndarray:
    """CameraFrame message -> H x W x 3 uint8 RGB."""
    if m.encoding == pb.IMAGE_ENCODING_RAW_RGB:
        return np.frombuffer(m.data, dtype=np.uint8).reshape(m.height, m.width, 3).copy()
    img = cv2.imdecode(np.frombuffer(m.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError("cannot decode the frame")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def event_msg(e: SimEvent, world: World) -> pb.SimEvent:
    av = world.avatars.get(e.avatar)
    d = e.detail
    m = pb.SimEvent(
        time=e.time,
        kind=e.kind,
        avatar_id=e.avatar,
        type=av.kind if av else "",
        collectable_id=d.get("collectable", ""),
        region_id=d.get("region", "") or "",
    )
    if "pose" in d:
        m.pose.CopyFrom(pose_msg(d["pose"]))
    if "error" in d:
        m.detail = str(d["error"])
    elif "with" in d:  # a bump: what the avatar ran into
        m.detail = str(d["with"])
    return m


# --------------------------------------------------------------------------- the simulation core
class _End:
    """Queue sentinel: the stream ends (with an error status when `code` is set)."""

    def __init__(self, code: grpc.StatusCode | None = None, details: str = "") -> None:
        self.code = code
        self.details = details


@dataclass
class _Sub:
    avatar: str
    period: float
    due: float
    queue: asyncio.Queue[Any]


@dataclass
class _Watch:
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
        self.odo_subs: list[_Sub] = []
        self.sonar_subs: list[_Sub] = []
        self.watches: list[_Watch] = []
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
                end = _End(grpc.StatusCode.UNAVAILABLE, f"avatar {e.avatar} {e.kind}")
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

    def update_msg(self, wt: _Watch) -> pb.ActionUpdate:
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
                self.put(wt.queue, _End())
                self.watches.remove(wt)
            elif t >= wt.due - 1e-9:
                self.put(wt.queue, self.update_msg(wt))
                wt.due += wt.period
                if wt.due <= t:
                    wt.due = t + wt.period

    def start_action(self, wt: _Watch) -> None:
        self.world.start_action(wt.avatar, wt.action)
        if not wt.action.done:
            self.put(wt.queue, self.update_msg(wt))  # accepted
        self.watches.append(wt)
        self.process_events()

    def close_streams(self) -> None:
        """End every stream (the server is stopping)."""
        end = _End(grpc.StatusCode.UNAVAILABLE, "haa-sim is stopping")
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


# --------------------------------------------------------------------------- the gRPC servicer
def authed(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Check the token (if the server has one) before the handler runs."""
    if inspect.isasyncgenfunction(fn):

        @functools.wraps(fn)
        async def gen(self: SimService, request: Any, context: aio.ServicerContext) -> AsyncIterator[Any]:
            await self.check_token(context)
            async for item in fn(self, request, context):
                yield item

        return gen

    @functools.wraps(fn)
    async def unary(self: SimService, request: Any, context: aio.ServicerContext) -> Any:
        await self.check_token(context)
        return await fn(self, request, context)

    return unary


class SimService(pbg.AvatarSimServicer, pbg.GroundTruthServicer, pbg.SimControlServicer):
    """AvatarSim + GroundTruth + SimControl on one SimCore."""

    def __init__(self, core: SimCore, token: str | None = None) -> None:
        self.core = core
        self.token = token
        self.rejected = 0
        self.malformed = 0
        self.errors = 0
        #: ground-truth / Detect calls per "<caller>/<method>" (SimInfo.truth_calls)
        self.truth_calls: dict[str, int] = {}

    def count_truth(self, method: str, context: aio.ServicerContext) -> None:
        """Count a ground-truth or geometric-shortcut call by its caller (metadata x-haa-caller): the agents
        of a mission must make none (issue 15: "haa-sim counts such calls per caller")."""
        caller = str(dict(context.invocation_metadata() or ()).get(MD_CALLER, ""))[:64]
        key = f"{caller}/{method}"
        self.truth_calls[key] = self.truth_calls.get(key, 0) + 1

    def add_to_server(self, server: aio.Server) -> None:
        """Register the three services with raw requests (haa.rpcguard): the token is checked before a request
        is decoded (UNAUTHENTICATED), a request that does not parse is INVALID_ARGUMENT, and an exception
        escaping a handler gets a proper status (INVALID_ARGUMENT for a ValueError, INTERNAL for a bug), never
        UNKNOWN."""
        guard = rpcguard.Guard(authenticate=self._token_ok, on_event=self._guard_event)
        handlers = tuple(
            rpcguard.guarded_handler(pb.DESCRIPTOR.services_by_name[name], self, guard)
            for name in ("AvatarSim", "GroundTruth", "SimControl")
        )
        server.add_generic_rpc_handlers(handlers)

    def _token_ok(self, context: aio.ServicerContext) -> bool:
        if self.token is None:
            return True
        tok = dict(context.invocation_metadata() or ()).get(MD_TOKEN)
        return isinstance(tok, str) and hmac.compare_digest(tok.encode(), self.token.encode())

    def _guard_event(self, kind: str, method: str, detail: str, exc: BaseException | None) -> None:
        if kind == "unauthenticated":
            self.rejected += 1
        elif kind == "malformed":
            self.malformed += 1
        else:
            self.errors += 1
            internal = detail.startswith("INTERNAL")
            if internal or self.errors <= 100:  # refusals of bad requests: the first 100 are enough to see
                log("rpc_error", method=method, detail=detail[:300],
                    trace="".join(traceback.format_exception(exc))[-2000:] if internal and exc else "")

    @property
    def world(self) -> World:
        return self.core.world

    async def check_token(self, context: aio.ServicerContext) -> None:
        if not self._token_ok(context):
            self.rejected += 1
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong x-haa-token")

    async def active(self, aid: str, context: aio.ServicerContext) -> AvatarState:
        av = self.world.avatars.get(aid)
        if av is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no avatar {aid!r}")
        assert av is not None
        if av.status != ACTIVE:
            await context.abort(grpc.StatusCode.UNAVAILABLE, f"avatar {aid} {av.status}")
        return av

    async def _create(self, type_: str, avatar_id: str, req: Any, context: aio.ServicerContext) -> AvatarState:
        pose: Any = None
        if req.HasField("pose"):
            pose = (req.pose.x, req.pose.y, req.pose.theta)
        elif req.HasField("start_index"):
            pose = int(req.start_index)
        try:
            aid = self.world.add_avatar(type_, pose, avatar_id or None)
        except ValueError as e:
            code = (
                grpc.StatusCode.RESOURCE_EXHAUSTED
                if "no free start pose" in str(e)
                else grpc.StatusCode.INVALID_ARGUMENT
            )
            await context.abort(code, str(e))
            raise  # unreachable: abort raises
        self.core.process_events()
        return self.world.avatars[aid]

    # ---------------------------------------------------------- AvatarSim
    @authed
    async def Register(self, request: pb.RegisterRequest, context: aio.ServicerContext) -> pb.RegisterReply:
        if request.avatar_id and request.avatar_id in self.world.avatars:
            av = await self.active(request.avatar_id, context)
            if request.type and request.type != av.kind:
                await context.abort(
                    grpc.StatusCode.INVALID_ARGUMENT, f"avatar {av.id} is a {av.kind}, not a {request.type}"
                )
            log("attached", avatar=av.id)
            return pb.RegisterReply(avatar=avatar_info(av), attached=True)
        if not request.type:
            await context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                "type: required (seeker, enhanced_seeker, "
                "sweeper or carrier) unless avatar_id names an existing avatar",
            )
        av = await self._create(request.type, request.avatar_id, request, context)
        return pb.RegisterReply(avatar=avatar_info(av), attached=False)

    async def _retire(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.AvatarInfo:
        av = await self.active(request.avatar_id, context)
        self.world.retire(av.id)
        self.core.process_events()
        return avatar_info(av)

    @authed
    async def Release(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.AvatarInfo:
        return await self._retire(request, context)

    def _action(self, req: pb.ActionRequest) -> act.Action:
        which = req.WhichOneof("action")
        if which == "wait":
            return act.Wait(duration=req.wait.duration)
        if which == "move_to":
            m = req.move_to
            return act.MoveTo(
                x=m.x,
                y=m.y,
                theta=m.theta if m.HasField("theta") else None,
                speed=m.speed or None,
                tolerance=m.tolerance or act.POS_TOL,
            )
        if which == "move_by":
            return act.MoveBy(distance=req.move_by.distance, speed=req.move_by.speed or None)
        if which == "velocity":
            v = req.velocity
            return act.Velocity(v=v.v, omega=v.omega, duration=v.duration or math.inf)
        if which == "rotate":
            r = req.rotate
            return act.Rotate(angle=r.angle, relative=not r.absolute, speed=r.speed or None)
        if which == "capture":
            return act.Capture()
        if which == "pick_up":
            return act.PickUp(collectable=req.pick_up.collectable_id or None)
        if which == "drop":
            return act.Drop(collectable=req.drop.collectable_id or None)
        raise ValueError("action: none given (wait, move_to, move_by, velocity, rotate, capture, pick_up, drop)")

    @authed
    async def Act(self, request: pb.ActionRequest, context: aio.ServicerContext) -> AsyncIterator[pb.ActionUpdate]:
        await self.active(request.avatar_id, context)
        try:
            action = self._action(request)
            for name in ("duration", "distance", "angle", "v", "omega", "x", "y", "speed", "tolerance"):
                val = getattr(action, name, 0.0)
                if isinstance(val, float) and math.isnan(val):
                    raise ValueError(f"{name}: not a number")
        except ValueError as e:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
            return
        period = request.progress_period if request.progress_period > 0 else DEFAULT_PERIOD
        q: asyncio.Queue[Any] = asyncio.Queue(QUEUE_MAX)
        enc = request.capture.encoding if request.WhichOneof("action") == "capture" else pb.IMAGE_ENCODING_RAW_RGB
        wt = _Watch(request.avatar_id, action, q, period, self.world.time + period, enc)
        self.core.start_action(wt)
        while True:
            item = await q.get()
            if isinstance(item, _End):
                if item.code is not None:
                    await context.abort(item.code, item.details)
                return
            yield item

    @authed
    async def Cancel(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.ActionUpdate:
        av = await self.active(request.avatar_id, context)
        self.world.cancel_action(av.id)
        self.core.flush_actions()
        a = av.action
        if a is None:
            return pb.ActionUpdate(avatar_id=av.id, time=self.world.time)
        return self.core.update_msg(_Watch(av.id, a, asyncio.Queue(), 0, 0))

    @authed
    async def SetVelocity(self, request: pb.VelocityCommand, context: aio.ServicerContext) -> pb.CommandReply:
        av = await self.active(request.avatar_id, context)
        if not (math.isfinite(request.v) and math.isfinite(request.omega)):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "v, omega: must be finite")
        self.world.set_velocity(av.id, request.v, request.omega)
        self.core.flush_actions()
        return pb.CommandReply(time=self.world.time)

    async def _stream(self, sub: _Sub, lst: list[_Sub], context: aio.ServicerContext) -> AsyncIterator[Any]:
        lst.append(sub)
        try:
            while True:
                item = await sub.queue.get()
                if isinstance(item, _End):
                    if item.code is not None:
                        await context.abort(item.code, item.details)
                    return
                yield item
        finally:
            if sub in lst:
                lst.remove(sub)

    @authed
    async def Odometry(self, request: pb.StreamRequest, context: aio.ServicerContext) -> AsyncIterator[Any]:
        av = await self.active(request.avatar_id, context)
        period = request.period if request.period > 0 else DEFAULT_PERIOD
        sub = _Sub(av.id, period, self.world.time + period, asyncio.Queue(QUEUE_MAX))
        sub.queue.put_nowait(self.core.odometry_msg(av.id))
        async for item in self._stream(sub, self.core.odo_subs, context):
            yield item

    @authed
    async def Sonar(self, request: pb.StreamRequest, context: aio.ServicerContext) -> AsyncIterator[Any]:
        av = await self.active(request.avatar_id, context)
        if av.spec.sonars == 0:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, f"avatar {av.id} ({av.kind}) has no sonar")
        sub = _Sub(av.id, SONAR_PERIOD, 0.0, asyncio.Queue(QUEUE_MAX))
        async for item in self._stream(sub, self.core.sonar_subs, context):
            yield item

    @authed
    async def Capture(self, request: pb.CaptureRequest, context: aio.ServicerContext) -> pb.CameraFrame:
        av = await self.active(request.avatar_id, context)
        return encode_frame(self.world.capture(av.id), request.encoding)

    @authed
    async def Detect(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.Detections:
        self.count_truth("Detect", context)
        av = await self.active(request.avatar_id, context)
        d = pb.Detections(avatar_id=av.id, time=self.world.time)
        for o in self.world.landmark_observations(av.id):
            d.landmarks.add(landmark_id=o.landmark_id, range=o.range, bearing=o.bearing)
        for c in self.world.collectable_observations(av.id):
            d.collectables.add(collectable_id=c.collectable_id, range=c.range, bearing=c.bearing)
        return d

    @authed
    async def Events(self, request: pb.EventsRequest, context: aio.ServicerContext) -> AsyncIterator[pb.SimEvent]:
        q: asyncio.Queue[Any] = asyncio.Queue(QUEUE_MAX)
        if request.replay:
            for av in self.world.avatars.values():
                if av.status == ACTIVE:
                    q.put_nowait(
                        pb.SimEvent(
                            time=av.joined, kind="joined", avatar_id=av.id, type=av.kind, pose=pose_msg(av.pose)
                        )
                    )
        self.core.event_subs.append(q)
        try:
            while True:
                item = await q.get()
                if isinstance(item, _End):
                    await context.abort(item.code or grpc.StatusCode.UNAVAILABLE, item.details)
                    return
                yield item
        finally:
            self.core.event_subs.remove(q)

    # ---------------------------------------------------------- GroundTruth
    @authed
    async def Info(self, request: pb.InfoRequest, context: aio.ServicerContext) -> pb.SimInfo:
        self.count_truth("Info", context)
        c = self.core
        return pb.SimInfo(
            arena=c.arena_name,
            arena_yaml=self.world.arena.to_yaml(),
            truth_calls=self.truth_calls,
            seed=self.world.seed,
            time=self.world.time,
            mode=c.mode,
            speed=c.speed if c.mode == "realtime" else 0.0,
            achieved_speed=c.achieved_speed(),
            tick=c.tick,
            avatar_types=list(AVATAR_TYPES),
        )

    @authed
    async def Poses(self, request: pb.PosesRequest, context: aio.ServicerContext) -> pb.PosesReply:
        self.count_truth("Poses", context)
        r = pb.PosesReply(time=self.world.time)
        for av in self.world.avatars.values():
            r.avatars.add(
                avatar_id=av.id,
                type=av.kind,
                status=av.status,
                pose=pose_msg(av.pose),
                odometry=pose_msg(av.odo.pose),
                carrying=list(av.carrying),
                joined=av.joined,
                left=av.left or 0.0,
                radius=av.spec.radius,
                bumps=av.bumps,
            )
        return r

    @authed
    async def OccupancyGrid(self, request: pb.GridRequest, context: aio.ServicerContext) -> pb.GridReply:
        self.count_truth("OccupancyGrid", context)
        if not (0.01 <= request.resolution <= 2.0):
            await context.abort(
                grpc.StatusCode.INVALID_ARGUMENT, f"resolution: {request.resolution} m is outside 0.01..2 m"
            )
        return self.core.grid(request.resolution)

    @authed
    async def Landmarks(self, request: pb.InfoRequest, context: aio.ServicerContext) -> pb.LandmarksReply:
        self.count_truth("Landmarks", context)
        a = self.world.arena
        r = pb.LandmarksReply(marker_size=a.marker_size, marker_height=a.marker_height, dictionary=a.marker_dictionary)
        normals = {m.id: m.normal for m in a.markers if m.id != a.congregation_id}
        for lid, (x, y) in sorted(a.landmarks.items()):
            n = normals.get(lid, (0.0, 0.0))
            r.landmarks.add(
                id=lid,
                position=pb.Point(x=x, y=y),
                normal=pb.Point(x=n[0], y=n[1]),
                congregation=lid == a.congregation_id,
            )
        return r

    @authed
    async def Collectables(self, request: pb.InfoRequest, context: aio.ServicerContext) -> pb.CollectablesReply:
        self.count_truth("Collectables", context)
        r = pb.CollectablesReply(time=self.world.time)
        for c in self.world.collectable_states():
            r.collectables.add(
                id=c.id, position=pb.Point(x=c.x, y=c.y), state=c.state, carrier=c.carrier or "", region=c.region or ""
            )
        for rid, poly in self.world.arena.regions.items():
            r.regions.add(id=rid, polygon=[pb.Point(x=x, y=y) for x, y in poly])
        return r

    # ---------------------------------------------------------- SimControl
    @authed
    async def Step(self, request: pb.StepRequest, context: aio.ServicerContext) -> pb.StepReply:
        if self.core.mode != "step":
            await context.abort(
                grpc.StatusCode.FAILED_PRECONDITION, "Step: the server runs its own clock (start haa-sim with --step)"
            )
        dt = request.dt
        if not (math.isfinite(dt) and 0 <= dt <= 3600):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"dt: {dt} is outside 0..3600 s")
        end = self.world.time + dt
        while self.world.time < end - 1e-9:
            self.core.advance(min(1.0, end - self.world.time))
            await asyncio.sleep(0)  # let the stream handlers drain their queues
        return pb.StepReply(time=self.world.time)

    @authed
    async def Join(self, request: pb.JoinRequest, context: aio.ServicerContext) -> pb.AvatarInfo:
        if request.avatar_id and request.avatar_id in self.world.avatars:
            await context.abort(grpc.StatusCode.ALREADY_EXISTS, f"avatar id {request.avatar_id!r} is taken")
        av = await self._create(request.type, request.avatar_id, request, context)
        return avatar_info(av)

    @authed
    async def Retire(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.AvatarInfo:
        return await self._retire(request, context)

    @authed
    async def Crash(self, request: pb.AvatarRef, context: aio.ServicerContext) -> pb.AvatarInfo:
        av = await self.active(request.avatar_id, context)
        self.world.crash(av.id)
        self.core.process_events()
        return avatar_info(av)


# --------------------------------------------------------------------------- server process
@dataclass
class Settings:
    arena: str
    listen: str
    seed: int
    speed: float
    step: bool
    tick: float
    schedule: Path | None
    token_file: Path | None
    drift: str = "thesis"
    metrics_port: int = 0


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(prog="haa-sim", description="HAA avatar simulator service (docs/sim.md).")
    p.add_argument("--arena", default="small", help='"small", "large" or an arena YAML file (default small)')
    p.add_argument("--listen", default="127.0.0.1:7100", help="HOST:PORT to serve on (port 0: any free port)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random thing (default 0)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--step", action="store_true", help="step mode: time advances only by SimControl.Step")
    p.add_argument("--tick", type=float, default=DEFAULT_TICK, help=f"simulated seconds per tick ({DEFAULT_TICK})")
    p.add_argument("--schedule", type=Path, help="mission file whose `schedule` makes avatars join/retire/crash")
    p.add_argument("--token-file", type=Path, help="require this token in metadata x-haa-token")
    p.add_argument(
        "--drift",
        choices=DRIFT_MODELS,
        default="thesis",
        help="odometry drift model: thesis (random walk, default), table (the same with Table 6.2-3's seeker"
        " drift as printed, 10x the default's) or systematic (table + scale and heading bias)",
    )
    p.add_argument("--metrics-port", default=os.environ.get("HAA_METRICS_PORT") or "0",
                   help="serve Prometheus metrics on http://<listen host>:PORT/metrics (haa.metrics; env "
                   "HAA_METRICS_PORT; 0 = off, the default)")
    a = p.parse_args(argv)

    def fail(msg: str) -> None:
        p.exit(2, f"haa-sim: error: {msg}\n")

    if not str(a.metrics_port).isdigit() or int(a.metrics_port) > 65535:
        fail(f"--metrics-port: {a.metrics_port!r} is not a port number (0..65535)")

    if not (a.speed > 0 and math.isfinite(a.speed)):
        fail(f"--speed: {a.speed} must be a positive number")
    if not (0.001 <= a.tick <= 1.0):
        fail(f"--tick: {a.tick} s is outside 0.001..1")
    if a.seed < 0:
        fail(f"--seed: {a.seed} must be >= 0")
    host, sep, port = a.listen.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        fail(f"--listen: {a.listen!r} is not HOST:PORT")
    return Settings(a.arena, a.listen, a.seed, a.speed, a.step, a.tick, a.schedule, a.token_file, a.drift,
                    int(a.metrics_port))


def build(s: Settings) -> tuple[SimCore, str | None]:
    """World and core from settings; raises ArenaError / ScheduleError / OSError with one-line messages."""
    arena = load_arena(s.arena)
    schedule = None
    if s.schedule is not None:
        schedule = list(arena.spec.schedule) + load_schedule(s.schedule, len(arena.start_poses))
    world = World(arena, seed=s.seed, schedule=schedule, drift=s.drift)
    token = None
    if s.token_file is not None:
        try:
            token = files.read_token(s.token_file)
        except files.FileError as e:
            raise OSError(f"--token-file: {e}") from None
    core = SimCore(world, arena.name, "step" if s.step else "realtime", s.speed, s.tick)
    return core, token


async def serve(core: SimCore, listen: str, token: str | None, stop: asyncio.Event | None = None,
                metrics_port: int = 0) -> None:
    server = aio.server(options=[("grpc.max_send_message_length", 32 << 20)])
    svc = SimService(core, token)
    svc.add_to_server(server)
    port = server.add_insecure_port(listen)
    if port == 0:
        raise RuntimeError(f"cannot bind {listen}")
    metrics = None
    if metrics_port:  # Prometheus /metrics on the same loop (haa.sim.metrics, docs/metrics.md)
        from haa.metrics.http import MetricsServer, metrics_bind_host
        from haa.sim.metrics import sim_registry

        metrics = MetricsServer(sim_registry(core, svc, asyncio.get_running_loop()), metrics_bind_host(listen),
                                metrics_port)
        try:
            metrics.start()
        except OSError as e:
            raise RuntimeError(f"--metrics-port: cannot listen on {metrics.host}:{metrics_port}: "
                               f"{e.strerror or e}") from None
    await server.start()
    host = listen.rpartition(":")[0]
    log(
        "listening",
        address=f"{host}:{port}",
        port=port,
        arena=core.arena_name,
        mode=core.mode,
        speed=core.speed,
        seed=core.world.seed,
        tick=core.tick,
        metrics=metrics.url if metrics is not None else "",
    )
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    clock = asyncio.create_task(core.run_clock()) if core.mode == "realtime" else None
    try:
        await stop.wait()
    finally:
        if clock is not None:
            clock.cancel()
        core.close_streams()
        await asyncio.sleep(0.1)
        await server.stop(grace=1.0)
        if metrics is not None:
            await asyncio.to_thread(metrics.stop)
        log("stopped", time=round(core.world.time, 3), dropped=core.dropped, rejected=svc.rejected,
            malformed=svc.malformed, errors=svc.errors)


def main(argv: list[str] | None = None) -> None:
    s = parse_args(argv)
    try:
        core, token = build(s)
    except (ArenaError, ScheduleError) as e:
        print(f"haa-sim: error: {e}", file=sys.stderr)
        sys.exit(2)
    except OSError as e:
        print(f"haa-sim: error: {e.strerror or e}", file=sys.stderr)
        sys.exit(2)
    try:
        asyncio.run(serve(core, s.listen, token, metrics_port=s.metrics_port))
    except RuntimeError as e:
        print(f"haa-sim: error: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        pass


# --------------------------------------------------------------------------- client
class SimClient:
    """Blocking client of the three services (tests, tools, `haactl sim show --server`)."""

    def __init__(self, address: str, token: str | None = None, timeout: float = 10.0, caller: str = "") -> None:
        self.address = address
        self.timeout = timeout
        self.channel = grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", 32 << 20)])
        md = [(MD_TOKEN, token)] if token else []
        if caller:
            md.append((MD_CALLER, caller))
        self.md = tuple(md)
        self.avatars = pbg.AvatarSimStub(self.channel)
        self.truth = pbg.GroundTruthStub(self.channel)
        self.control = pbg.SimControlStub(self.channel)

    def __enter__(self) -> SimClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.channel.close()

    def _call(self, fn: Any, req: Any, timeout: float | None = None) -> Any:
        return fn(req, metadata=self.md, timeout=timeout or self.timeout)

    def _stream(self, fn: Any, req: Any, timeout: float | None = None) -> Any:
        return fn(req, metadata=self.md, timeout=timeout)

    def wait_ready(self, timeout: float = 10.0) -> pb.SimInfo:
        grpc.channel_ready_future(self.channel).result(timeout=timeout)
        return self.info()

    def info(self) -> pb.SimInfo:
        return self._call(self.truth.Info, pb.InfoRequest())

    def register(
        self,
        type_: str = "",
        avatar_id: str = "",
        pose: tuple[float, float, float] | None = None,
        start_index: int | None = None,
    ) -> pb.RegisterReply:
        r = pb.RegisterRequest(type=type_, avatar_id=avatar_id)
        if pose is not None:
            r.pose.CopyFrom(pose_msg(pose))
        if start_index is not None:
            r.start_index = start_index
        return self._call(self.avatars.Register, r)

    def release(self, avatar_id: str) -> pb.AvatarInfo:
        return self._call(self.avatars.Release, pb.AvatarRef(avatar_id=avatar_id))

    def act(self, request: pb.ActionRequest, timeout: float | None = None) -> Iterator[pb.ActionUpdate]:
        return self._stream(self.avatars.Act, request, timeout)

    def cancel(self, avatar_id: str) -> pb.ActionUpdate:
        return self._call(self.avatars.Cancel, pb.AvatarRef(avatar_id=avatar_id))

    def set_velocity(self, avatar_id: str, v: float, omega: float) -> pb.CommandReply:
        return self._call(self.avatars.SetVelocity, pb.VelocityCommand(avatar_id=avatar_id, v=v, omega=omega))

    def odometry(self, avatar_id: str, period: float = DEFAULT_PERIOD, timeout: float | None = None) -> Any:
        return self._stream(self.avatars.Odometry, pb.StreamRequest(avatar_id=avatar_id, period=period), timeout)

    def sonar(self, avatar_id: str, timeout: float | None = None) -> Any:
        return self._stream(self.avatars.Sonar, pb.StreamRequest(avatar_id=avatar_id), timeout)

    def capture(self, avatar_id: str, encoding: pb.ImageEncoding = pb.IMAGE_ENCODING_RAW_RGB) -> pb.CameraFrame:
        return self._call(self.avatars.Capture, pb.CaptureRequest(avatar_id=avatar_id, encoding=encoding))

    def detect(self, avatar_id: str) -> pb.Detections:
        return self._call(self.avatars.Detect, pb.AvatarRef(avatar_id=avatar_id))

    def events(self, replay: bool = False, timeout: float | None = None) -> Any:
        return self._stream(self.avatars.Events, pb.EventsRequest(replay=replay), timeout)

    def poses(self) -> pb.PosesReply:
        return self._call(self.truth.Poses, pb.PosesRequest())

    def grid(self, resolution: float) -> tuple[np.ndarray, np.ndarray, pb.GridReply]:
        """(occupancy, explorable, reply): uint8 arrays [iy, ix], row 0 at the lowest y."""
        r = self._call(self.truth.OccupancyGrid, pb.GridRequest(resolution=resolution))
        occ = np.frombuffer(r.cells, dtype=np.uint8).reshape(r.height, r.width)
        ex = np.frombuffer(r.explorable, dtype=np.uint8).reshape(r.height, r.width)
        return occ, ex, r

    def landmarks(self) -> pb.LandmarksReply:
        return self._call(self.truth.Landmarks, pb.InfoRequest())

    def collectables(self) -> pb.CollectablesReply:
        return self._call(self.truth.Collectables, pb.InfoRequest())

    def step(self, dt: float, timeout: float | None = None) -> float:
        return self._call(self.control.Step, pb.StepRequest(dt=dt), timeout or max(self.timeout, 10 + dt)).time

    def join(self, type_: str, avatar_id: str = "", pose: tuple[float, float, float] | None = None) -> pb.AvatarInfo:
        r = pb.JoinRequest(type=type_, avatar_id=avatar_id)
        if pose is not None:
            r.pose.CopyFrom(pose_msg(pose))
        return self._call(self.control.Join, r)

    def retire(self, avatar_id: str) -> pb.AvatarInfo:
        return self._call(self.control.Retire, pb.AvatarRef(avatar_id=avatar_id))

    def crash(self, avatar_id: str) -> pb.AvatarInfo:
        return self._call(self.control.Crash, pb.AvatarRef(avatar_id=avatar_id))


def truth_from_server(client: SimClient) -> tuple[Any, TruthView]:
    """(Arena, TruthView) of a running haa-sim, for pictures of its true state."""
    info = client.info()
    arena = parse_arena(info.arena_yaml, f"arena {info.arena}")
    poses = client.poses()
    avs = [
        AvatarView(a.avatar_id, a.status, a.pose.x, a.pose.y, a.pose.theta, a.radius, bool(a.carrying))
        for a in poses.avatars
        if a.status != "retired"
    ]
    cs = [
        CollectableState(c.id, c.position.x, c.position.y, c.state, c.carrier or None, c.region or None)
        for c in client.collectables().collectables
    ]
    return arena, TruthView(poses.time, avs, cs)


if __name__ == "__main__":
    main()
