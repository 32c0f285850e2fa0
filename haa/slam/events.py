"""The SLAM event log's items (`slam/log` in the DDB; docs/team.md, docs/slam.md "The SLAM state in the DDB").

The team's SLAM state is a deterministic function of a checkpoint and the log items after it, applied in
index order by a `haa.slam.replica.SlamReplica`. An item is one protobuf `SlamEvent` (proto/haa/pb/slam.proto)
holding one of

| event         | producer       | JC-SLAM (§5.2.3)                  | Python                                          |
|---------------|----------------|-----------------------------------|-------------------------------------------------|
| add_avatar    | avatar agent   | (a) a filter at the known pose    | AddAvatar(name, kind, pose, t0, drift, radius)  |
| predict       | avatar agent   | (b) odometry prediction           | Predict(avatar, prediction)                     |
| observe       | sensor agent   | (c) a processed reading           | Observe(reading, processor)                     |
| request       | SupervisorSLAM | (d) weight request + (e) resample | Request(avatar)                                 |
| remove_avatar | SupervisorSLAM | the avatar left the team          | RemoveAvatar(name)                              |

The Python events are frozen dataclasses over the library's own types (`haa.slam.motion.Prediction`, the
readings of `haa.slam.sensors`); `encode(event) -> bytes` and `decode(data) -> event`. Constructing an event
validates it (the readings and the prediction validate themselves), so `decode` of bytes that are not a
well-formed event — not protobuf, no event set, a non-finite number, an empty name, a reading beyond the
size bounds below — raises `EventError` with a one-line reason, and `encode` refuses what `decode` would
refuse. Whether the avatar exists, or the reading is too old for the history, is not a decoding matter: the
replica decides (and counts) that.

The bounds keep one event's cost on every replica bounded (a floor polygon of a kilometre, or a sonar cone
of 1 km, would build a template of millions of points for each of N particles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

from google.protobuf.message import DecodeError

from haa.pb import slam_pb2 as pb
from haa.slam.motion import DriftSpec, Prediction
from haa.slam.sensors import (
    CollectablesReading,
    CooccupancyReading,
    FloorReading,
    LandmarkReading,
    RangeBearing,
    Reading,
    Sighting,
    SonarEcho,
    SonarReading,
)

#: largest encoded event (a landmark image with 1,000 sightings is ~30 KB)
MAX_EVENT_BYTES = 64 * 1024
MAX_NAME = 128  # characters of an avatar or processor name
MAX_ECHOES = 64  # sonars in one scan
MAX_SIGHTINGS = 1024  # landmarks in one image
MAX_POLYGON = 256  # vertices of one floor region
MAX_SONAR_RANGE = 20.0  # m
MAX_FLOOR_EXTENT = 20.0  # m, |x| and |y| of a floor vertex in the avatar frame
MAX_RADIUS = 2.0  # m, an avatar footprint (co-occupancy) or its stated radius
MAX_COLLECTABLE_SIGHTINGS = 256  # collectables in one image (each costs O(particles + identified ones))
MAX_COLLECTABLE_RANGE = 20.0  # m (the cameras see 3-4 m: Table 6.2-4)


NO_DRIFT = DriftSpec(0.0, 0.0)


class EventError(ValueError):
    """Not a well-formed SLAM event; `reason` says why in one line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _name(what: str, v: object) -> None:
    if not isinstance(v, str) or not v:
        raise EventError(f"{what}: must be a non-empty string, got {v!r}")
    if len(v) > MAX_NAME:
        raise EventError(f"{what}: longer than {MAX_NAME} characters ({len(v)})")


def _finite(what: str, v: object) -> float:
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise EventError(f"{what}: must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise EventError(f"{what}: must be finite, got {v!r}")
    return f


@dataclass(frozen=True)
class AddAvatar:
    """Event (a): a filter for avatar `name`, started at its known pose at time t0."""

    name: str
    kind: str
    pose: tuple[float, float, float]
    t0: float = 0.0
    drift: DriftSpec = NO_DRIFT  # what the avatar states (Table 6.2-3); the filter does not use it
    radius: float = 0.15  # m, footprint
    KIND: ClassVar[str] = "add_avatar"

    def __post_init__(self) -> None:
        _name("add_avatar.name", self.name)
        if not isinstance(self.kind, str) or len(self.kind) > MAX_NAME:
            raise EventError(f"add_avatar.kind: must be a string of at most {MAX_NAME} characters")
        if len(self.pose) != 3:
            raise EventError(f"add_avatar.pose: must be (x, y, theta), got {self.pose!r}")
        pose = tuple(_finite(f"add_avatar.pose[{i}]", v) for i, v in enumerate(self.pose))
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "t0", _finite("add_avatar.t0", self.t0))
        if not isinstance(self.drift, DriftSpec):
            raise EventError(f"add_avatar.drift: must be a DriftSpec, got {type(self.drift).__name__}")
        for attr in ("linear_m_per_10m", "angular_rad_per_10rot", "inflate"):
            v = getattr(self.drift, attr)
            _finite(f"add_avatar.drift.{attr}", v)
            if v < 0:
                raise EventError(f"add_avatar.drift.{attr}: must be >= 0, got {v}")
        _finite("add_avatar.radius", self.radius)
        if not 0 < self.radius <= MAX_RADIUS:
            raise EventError(f"add_avatar.radius: must be in (0, {MAX_RADIUS}] m, got {self.radius}")


@dataclass(frozen=True)
class Predict:
    """Event (b): one odometry prediction of avatar `avatar` (eq. 5.1-3)."""

    avatar: str
    prediction: Prediction
    KIND: ClassVar[str] = "predict"

    def __post_init__(self) -> None:
        _name("predict.avatar", self.avatar)
        if not isinstance(self.prediction, Prediction):
            raise EventError(f"predict.prediction: must be a Prediction, got {type(self.prediction).__name__}")


@dataclass(frozen=True)
class Observe:
    """Event (c): one reading, processed by the sensor agent `processor` (SlamSystem.process on the replica)."""

    reading: Reading
    processor: str = ""
    KIND: ClassVar[str] = "observe"

    def __post_init__(self) -> None:
        r = self.reading
        if not isinstance(r, (SonarReading, LandmarkReading, CooccupancyReading, FloorReading, CollectablesReading)):
            raise EventError(f"observe.reading: must be a reading, got {type(r).__name__}")
        _name("observe.reading.avatar", r.avatar)
        if not isinstance(self.processor, str) or len(self.processor) > MAX_NAME:
            raise EventError(f"observe.processor: must be a string of at most {MAX_NAME} characters")
        if isinstance(r, SonarReading):
            if len(r.echoes) > MAX_ECHOES:
                raise EventError(f"observe.sonar.echoes: more than {MAX_ECHOES} ({len(r.echoes)})")
            if r.max_range > MAX_SONAR_RANGE:
                raise EventError(f"observe.sonar.max_range: must be <= {MAX_SONAR_RANGE} m, got {r.max_range}")
        elif isinstance(r, LandmarkReading):
            if len(r.sightings) > MAX_SIGHTINGS:
                raise EventError(f"observe.landmark.sightings: more than {MAX_SIGHTINGS} ({len(r.sightings)})")
        elif isinstance(r, CooccupancyReading):
            if r.radius > MAX_RADIUS:
                raise EventError(f"observe.cooccupancy.radius: must be <= {MAX_RADIUS} m, got {r.radius}")
        elif isinstance(r, CollectablesReading):
            _collectables_bounds(len(r.sightings), max((g.range for g in r.sightings), default=0.0))
        else:
            if len(r.polygon) > MAX_POLYGON:
                raise EventError(f"observe.floor.polygon: more than {MAX_POLYGON} vertices ({len(r.polygon)})")
            if any(abs(v) > MAX_FLOOR_EXTENT for xy in r.polygon for v in xy):
                raise EventError(f"observe.floor.polygon: a vertex beyond {MAX_FLOOR_EXTENT} m of the avatar")

    @property
    def avatar(self) -> str:
        return self.reading.avatar


def _collectables_bounds(n: int, max_range: float) -> None:
    if n > MAX_COLLECTABLE_SIGHTINGS:
        raise EventError(f"observe.collectables.sightings: more than {MAX_COLLECTABLE_SIGHTINGS} ({n})")
    if max_range > MAX_COLLECTABLE_RANGE:
        raise EventError(f"observe.collectables.range: must be <= {MAX_COLLECTABLE_RANGE} m, got {max_range}")


@dataclass(frozen=True)
class Request:
    """Events (d) + (e): a weight request for avatar `avatar` at its newest time; resampling if n_eff dropped."""

    avatar: str
    KIND: ClassVar[str] = "request"

    def __post_init__(self) -> None:
        _name("request.avatar", self.avatar)


@dataclass(frozen=True)
class RemoveAvatar:
    """Avatar `name` left the team: its filter is dropped (the map keeps what it contributed)."""

    name: str
    KIND: ClassVar[str] = "remove_avatar"

    def __post_init__(self) -> None:
        _name("remove_avatar.name", self.name)


SlamEvent = AddAvatar | Predict | Observe | Request | RemoveAvatar


def event_avatar(ev: SlamEvent) -> str:
    """The avatar an event is about."""
    if isinstance(ev, (AddAvatar, RemoveAvatar)):
        return ev.name
    return ev.avatar


# ----- encoding -----------------------------------------------------------------------------------------


def _reading_to_pb(r: Reading, m: pb.SlamObserve) -> None:
    if isinstance(r, SonarReading):
        s = m.sonar
        s.avatar, s.t, s.fov, s.max_range = r.avatar, r.t, r.fov, r.max_range
        for e in r.echoes:
            pe = s.echoes.add(bearing=e.bearing)
            if e.range is not None:
                pe.range = e.range
    elif isinstance(r, LandmarkReading):
        g = m.landmark
        g.avatar, g.t = r.avatar, r.t
        for s_ in r.sightings:
            g.sightings.add(landmark_id=s_.landmark_id, range=s_.range, bearing=s_.bearing)
    elif isinstance(r, CooccupancyReading):
        m.cooccupancy.avatar, m.cooccupancy.t, m.cooccupancy.radius = r.avatar, r.t, r.radius
    elif isinstance(r, CollectablesReading):
        c = m.collectables
        c.avatar, c.t = r.avatar, r.t
        for g in r.sightings:
            c.sightings.add(range=g.range, bearing=g.bearing)
    else:
        m.floor.avatar, m.floor.t = r.avatar, r.t
        m.floor.xs.extend(v[0] for v in r.polygon)
        m.floor.ys.extend(v[1] for v in r.polygon)
        m.floor.occupied.extend(r.occupied)


def reading_message(r: Reading) -> tuple[str, Any]:
    """(kind, message) of a reading in its proto form — the SlamObserve field ("sonar", "landmark",
    "cooccupancy", "floor", "collectables") and its SlamSonar / SlamLandmark / ... message; the event log and
    the recordings (haa.slam.recording, topic /slam/<kind>) share it."""
    m = pb.SlamObserve()
    _reading_to_pb(r, m)
    kind = m.WhichOneof("reading")
    return kind, getattr(m, kind)


def to_pb(ev: SlamEvent) -> pb.SlamEvent:
    m = pb.SlamEvent()
    if isinstance(ev, AddAvatar):
        a = m.add_avatar.avatar
        a.name, a.kind = ev.name, ev.kind
        a.x, a.y, a.theta = (float(v) for v in ev.pose)
        a.drift_linear, a.drift_angular = ev.drift.linear_m_per_10m, ev.drift.angular_rad_per_10rot
        a.drift_inflate, a.radius = ev.drift.inflate, ev.radius
        m.add_avatar.t0 = ev.t0
    elif isinstance(ev, Predict):
        p = ev.prediction
        m.predict.CopyFrom(
            pb.SlamPrediction(
                avatar=ev.avatar, t=p.t, vx=p.vx, vy=p.vy, omega=p.omega, sigma_xy=p.sigma_xy, sigma_theta=p.sigma_theta
            )
        )
    elif isinstance(ev, Observe):
        _reading_to_pb(ev.reading, m.observe)
        m.observe.processor = ev.processor
    elif isinstance(ev, Request):
        m.request.avatar = ev.avatar
    elif isinstance(ev, RemoveAvatar):
        m.remove_avatar.name = ev.name
    else:
        raise EventError(f"event: unknown type {type(ev).__name__}")
    return m


def encode(ev: SlamEvent) -> bytes:
    """The log item of an event (a serialized `SlamEvent`). Raises EventError for what decode would refuse."""
    data = to_pb(ev).SerializeToString()
    if len(data) > MAX_EVENT_BYTES:
        raise EventError(f"event: {len(data)} bytes encoded, more than {MAX_EVENT_BYTES}")
    return data


def _from_pb(m: pb.SlamEvent) -> SlamEvent:
    which = m.WhichOneof("event")
    if which == "add_avatar":
        a = m.add_avatar.avatar
        drift = DriftSpec(a.drift_linear, a.drift_angular, a.drift_inflate)
        return AddAvatar(a.name, a.kind, (a.x, a.y, a.theta), m.add_avatar.t0, drift, a.radius)
    if which == "predict":
        p = m.predict
        _name("predict.avatar", p.avatar)
        return Predict(p.avatar, Prediction(p.t, p.vx, p.vy, p.omega, p.sigma_xy, p.sigma_theta))
    if which == "observe":
        o = m.observe
        kind = o.WhichOneof("reading")
        r: Reading
        if kind == "sonar":
            s = o.sonar
            if len(s.echoes) > MAX_ECHOES:
                raise EventError(f"observe.sonar.echoes: more than {MAX_ECHOES} ({len(s.echoes)})")
            echoes = tuple(SonarEcho(e.bearing, e.range if e.HasField("range") else None) for e in s.echoes)
            r = SonarReading(s.avatar, s.t, echoes, s.fov, s.max_range)
        elif kind == "landmark":
            g = o.landmark
            r = LandmarkReading(g.avatar, g.t, tuple(Sighting(x.landmark_id, x.range, x.bearing) for x in g.sightings))
        elif kind == "cooccupancy":
            c = o.cooccupancy
            r = CooccupancyReading(c.avatar, c.t, c.radius)
        elif kind == "floor":
            f = o.floor
            if len(f.xs) != len(f.ys):
                raise EventError(f"observe.floor: {len(f.xs)} xs but {len(f.ys)} ys")
            if len(f.xs) > MAX_POLYGON:
                raise EventError(f"observe.floor.polygon: more than {MAX_POLYGON} vertices ({len(f.xs)})")
            if f.occupied and len(f.occupied) != len(f.xs):
                raise EventError(f"observe.floor.occupied: {len(f.occupied)} flags for {len(f.xs)} vertices")
            r = FloorReading(f.avatar, f.t, tuple(zip(f.xs, f.ys, strict=True)), tuple(f.occupied))
        elif kind == "collectables":
            c = o.collectables
            if len(c.sightings) > MAX_COLLECTABLE_SIGHTINGS:  # before building them
                raise EventError(
                    f"observe.collectables.sightings: more than {MAX_COLLECTABLE_SIGHTINGS} ({len(c.sightings)})"
                )
            r = CollectablesReading(c.avatar, c.t, tuple(RangeBearing(x.range, x.bearing) for x in c.sightings))
        else:
            raise EventError("observe: no reading set")
        return Observe(r, o.processor)
    if which == "request":
        return Request(m.request.avatar)
    if which == "remove_avatar":
        return RemoveAvatar(m.remove_avatar.name)
    raise EventError("event: no event set (not a SlamEvent)")


def decode(data: bytes) -> SlamEvent:
    """The event of a log item. Raises EventError (one-line reason) for anything but a well-formed event."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise EventError(f"event: must be bytes, got {type(data).__name__}")
    if len(data) > MAX_EVENT_BYTES:
        raise EventError(f"event: {len(data)} bytes, more than {MAX_EVENT_BYTES}")
    try:
        m = pb.SlamEvent.FromString(bytes(data))
    except (DecodeError, ValueError) as e:  # invalid wire format, invalid UTF-8 in a string
        why = str(e).splitlines()[0] if str(e) else "decode error"
        raise EventError(f"event: not a SlamEvent protobuf ({why})") from None
    try:
        return _from_pb(m)
    except EventError:
        raise
    except (ValueError, TypeError, OverflowError) as e:  # the library's own validation (Prediction, readings)
        raise EventError(str(e).splitlines()[0] if str(e) else type(e).__name__) from None
