"""haa-sim's gRPC servicer: AvatarSim (what avatar agents use, a hardware stand-in), GroundTruth (what metrics
need) and SimControl (step mode, join / retire / crash on demand) on one `SimCore` (haa.sim.simcore); haa.sim.service's
docstring describes the calls. Every call is checked for the token before its request is decoded (haa.rpcguard).
"""

from __future__ import annotations

import asyncio
import functools
import hmac
import inspect
import math
import traceback
from collections.abc import AsyncIterator, Callable
from typing import Any

import grpc
from grpc import aio

from haa import rpcguard
from haa.pb import sim_pb2 as pb
from haa.pb import sim_pb2_grpc as pbg
from haa.sim import actions as act
from haa.sim.avatars import AVATAR_TYPES
from haa.sim.convert import MD_CALLER, MD_TOKEN, avatar_info, encode_frame, pose_msg
from haa.sim.sensors import SONAR_PERIOD
from haa.sim.simcore import DEFAULT_PERIOD, QUEUE_MAX, End, SimCore, Sub, Watch, log
from haa.sim.world import ACTIVE, AvatarState, World


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
        wt = Watch(request.avatar_id, action, q, period, self.world.time + period, enc)
        self.core.start_action(wt)
        while True:
            item = await q.get()
            if isinstance(item, End):
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
        return self.core.update_msg(Watch(av.id, a, asyncio.Queue(), 0, 0))

    @authed
    async def SetVelocity(self, request: pb.VelocityCommand, context: aio.ServicerContext) -> pb.CommandReply:
        av = await self.active(request.avatar_id, context)
        if not (math.isfinite(request.v) and math.isfinite(request.omega)):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "v, omega: must be finite")
        self.world.set_velocity(av.id, request.v, request.omega)
        self.core.flush_actions()
        return pb.CommandReply(time=self.world.time)

    async def _stream(self, sub: Sub, lst: list[Sub], context: aio.ServicerContext) -> AsyncIterator[Any]:
        lst.append(sub)
        try:
            while True:
                item = await sub.queue.get()
                if isinstance(item, End):
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
        sub = Sub(av.id, period, self.world.time + period, asyncio.Queue(QUEUE_MAX))
        sub.queue.put_nowait(self.core.odometry_msg(av.id))
        async for item in self._stream(sub, self.core.odo_subs, context):
            yield item

    @authed
    async def Sonar(self, request: pb.StreamRequest, context: aio.ServicerContext) -> AsyncIterator[Any]:
        av = await self.active(request.avatar_id, context)
        if av.spec.sonars == 0:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, f"avatar {av.id} ({av.kind}) has no sonar")
        sub = Sub(av.id, SONAR_PERIOD, 0.0, asyncio.Queue(QUEUE_MAX))
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
                if isinstance(item, End):
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
