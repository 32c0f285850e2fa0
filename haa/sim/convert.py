"""haa-sim's messages from its world (proto/haa/pb/sim.proto): poses, avatar and camera descriptions, camera
frames (raw RGB, PNG or JPEG; `decode_frame` turns one back into pixels), events; and the metadata names of its
calls. Used by the service (haa.sim.simcore, haa.sim.servicer), its client (haa.sim.client) and the avatar agents
that decode frames."""

from __future__ import annotations

import cv2
import numpy as np

from haa.pb import sim_pb2 as pb
from haa.sim.camera import CameraFrame, floor_homography, intrinsics
from haa.sim.sensors import CAMERA_HEIGHT, SONAR_BEARINGS, SONAR_FOV, SONAR_PERIOD, SONAR_RANGE
from haa.sim.world import AvatarState, SimEvent, World

MD_TOKEN = "x-haa-token"
#: metadata naming the caller (an agent name, "runner", ...): ground-truth calls are counted per caller
MD_CALLER = "x-haa-caller"


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
