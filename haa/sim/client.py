"""A blocking client of haa-sim's three services (tests, tools, `haactl sim show --server`, the mission runner),
and the true state of a running haa-sim as pictures need it (`truth_from_server`)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import grpc
import numpy as np

from haa.pb import sim_pb2 as pb
from haa.pb import sim_pb2_grpc as pbg
from haa.sim.arena import parse_arena
from haa.sim.convert import MD_CALLER, MD_TOKEN, pose_msg
from haa.sim.render import AvatarView, TruthView
from haa.sim.simcore import DEFAULT_PERIOD
from haa.sim.world import CollectableState


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
