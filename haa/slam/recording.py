"""Recordings of exploration runs for offline SLAM replays: in memory (`Recording`) and as MCAP + protobuf.

A `Recording` is everything the SLAM system was given during a run — each avatar's predictions (eq. 5.1-3
velocities and uncertainties, as the avatar agent sends them) and sensor readings, with their times — plus
what is needed to evaluate it: true poses, the avatars' own dead-reckoning poses (the "uncorrected
localization" of Table 7.2-1), true landmark positions, and the map rectangle.

On disk it is an MCAP file with protobuf schemas (haa/pb/slam.proto), so it opens in Foxglove; each message
is logged at its simulated time. Topics:

    /slam/info (SlamRunInfo, once)   /slam/prediction (SlamPrediction)   /slam/truth, /slam/odometry (SlamPose)
    /slam/sonar (SlamSonar)  /slam/landmark (SlamLandmark)  /slam/cooccupancy (SlamCooccupancy)
    /slam/floor (SlamFloor)  /slam/ideal_grid (SlamGrid, optional)

`save(rec, path)` / `load(path)` round-trip exactly (tests/test_slam_recording.py). `Recording.events()`
turns it into the time-ordered stream haa.slam.strategies replays, adding each avatar's weight requests;
`recording_events(rec)` into the SLAM event log a Baseline run would write (haa.slam.events).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from google.protobuf.message import Message

from haa.pb import slam_pb2 as pb
from haa.slam.events import AddAvatar, Observe, Predict, Request, SlamEvent, reading_message
from haa.slam.grid import GridSpec
from haa.slam.motion import DriftSpec, Prediction
from haa.slam.sensors import (
    CooccupancyReading,
    FloorReading,
    LandmarkReading,
    Reading,
    Sighting,
    SonarEcho,
    SonarReading,
)
from haa.slam.strategies import PREDICTION, READING, REQUEST, StreamEvent

NS = 1_000_000_000


@dataclass
class AvatarInfo:
    name: str
    kind: str
    start: tuple[float, float, float]
    drift: DriftSpec
    radius: float = 0.15


@dataclass
class Track:
    """Poses over time: times (T,), poses (T, 3)."""

    times: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, t: float, pose: tuple[float, float, float]) -> None:
        self.times.append(t)
        self.poses.append(pose)

    def at(self, t: float) -> np.ndarray:
        """Pose at time t (the last recorded at or before t)."""
        k = int(np.searchsorted(np.asarray(self.times), t, side="right")) - 1
        return np.asarray(self.poses[max(k, 0)], dtype=np.float64)


@dataclass
class Recording:
    arena: str
    team: str
    seed: int
    grid: GridSpec
    avatars: list[AvatarInfo]
    landmarks: dict[int, tuple[float, float]]
    duration: float
    driver: str = ""
    landmark_range_frac: float = 0.09
    landmark_sigma_bearing: float = 0.05
    sonar_mount_radius: float = 0.0
    predictions: list[tuple[str, Prediction]] = field(default_factory=list)
    readings: list[Reading] = field(default_factory=list)
    truth: dict[str, Track] = field(default_factory=dict)
    odometry: dict[str, Track] = field(default_factory=dict)
    ideal_grid: np.ndarray | None = None  # (rows, cols) p(C), from the simulator
    region: np.ndarray | None = None  # (rows, cols) bool mission region

    def reading_counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.readings:
            out[r.kind] = out.get(r.kind, 0) + 1
        return out

    def events(self, request_period: float = 1.0) -> list[StreamEvent]:
        """Time-ordered replay stream: predictions, readings, and a weight request per avatar every period.

        An avatar's requests fall half a period after its sensor times (its first reading + (k + 1/2) ·
        period), snapped to its next prediction, so that a reading and a request never coincide: with
        instantaneous processing a reading is always in the next estimate, and any processing latency
        shows. At equal times predictions come first, then readings, then requests.
        """
        if not request_period > 0:
            raise ValueError(f"request_period: must be > 0, got {request_period}")
        evs: list[tuple[float, int, int, StreamEvent]] = []
        seq = 0
        for name, p in self.predictions:
            evs.append((p.t, PREDICTION, seq, StreamEvent(p.t, PREDICTION, name, p)))
            seq += 1
        first_reading: dict[str, float] = {}
        for r in self.readings:
            evs.append((r.t, READING, seq, StreamEvent(r.t, READING, r.avatar, r)))
            first_reading.setdefault(r.avatar, r.t)
            seq += 1
        by_avatar: dict[str, list[float]] = {}
        for name, p in self.predictions:
            by_avatar.setdefault(name, []).append(p.t)
        for a in self.avatars:
            times = by_avatar.get(a.name, [])
            if not times:
                continue
            nxt = first_reading.get(a.name, times[0]) + request_period / 2
            for t in times:
                if t + 1e-9 >= nxt:
                    evs.append((t, REQUEST, seq, StreamEvent(t, REQUEST, a.name)))
                    seq += 1
                    nxt += request_period * (math.floor((t + 1e-9 - nxt) / request_period) + 1)
        evs.sort(key=lambda e: (e[0], e[1], e[2]))
        return [e[3] for e in evs]


def _ns(t: float) -> int:
    return max(0, round(t * NS))


def save(rec: Recording, path: Path | str) -> Path:
    """Write `rec` to an MCAP file with protobuf schemas."""
    from mcap_protobuf.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    info = pb.SlamRunInfo(
        arena=rec.arena,
        team=rec.team,
        seed=rec.seed,
        x0=rec.grid.x0,
        y0=rec.grid.y0,
        width=rec.grid.width,
        height=rec.grid.height,
        resolution=rec.grid.resolution,
        duration=rec.duration,
        driver=rec.driver,
        landmark_range_frac=rec.landmark_range_frac,
        landmark_sigma_bearing=rec.landmark_sigma_bearing,
        sonar_mount_radius=rec.sonar_mount_radius,
    )
    for a in rec.avatars:
        info.avatars.append(
            pb.SlamAvatarInfo(
                name=a.name,
                kind=a.kind,
                x=a.start[0],
                y=a.start[1],
                theta=a.start[2],
                drift_linear=a.drift.linear_m_per_10m,
                drift_angular=a.drift.angular_rad_per_10rot,
                drift_inflate=a.drift.inflate,
                radius=a.radius,
            )
        )
    for lid, (x, y) in sorted(rec.landmarks.items()):
        info.landmarks.append(pb.SlamLandmarkTruth(id=lid, x=x, y=y))
    msgs: list[tuple[float, int, str, object]] = []
    k = 0
    for name, p in rec.predictions:
        msgs.append(
            (
                p.t,
                k,
                "/slam/prediction",
                pb.SlamPrediction(
                    avatar=name, t=p.t, vx=p.vx, vy=p.vy, omega=p.omega, sigma_xy=p.sigma_xy, sigma_theta=p.sigma_theta
                ),
            )
        )
        k += 1
    for topic, tracks in (("/slam/truth", rec.truth), ("/slam/odometry", rec.odometry)):
        for name, tr in tracks.items():
            for t, (x, y, th) in zip(tr.times, tr.poses, strict=True):
                msgs.append((t, k, topic, pb.SlamPose(avatar=name, t=t, x=x, y=y, theta=th)))
                k += 1
    for r in rec.readings:
        m: object
        kind, m = reading_message(r)
        topic = f"/slam/{kind}"
        msgs.append((r.t, k, topic, m))
        k += 1
    msgs.sort(key=lambda e: (e[0], e[1]))
    with path.open("wb") as f:
        w = Writer(f)
        w.write_message("/slam/info", info, log_time=0, publish_time=0)
        if rec.ideal_grid is not None:
            g = pb.SlamGrid(
                rows=rec.ideal_grid.shape[0],
                cols=rec.ideal_grid.shape[1],
                resolution=rec.grid.resolution,
                x0=rec.grid.x0,
                y0=rec.grid.y0,
                p=rec.ideal_grid.reshape(-1).tolist(),
            )
            if rec.region is not None:
                g.region.extend(rec.region.reshape(-1).tolist())
            w.write_message("/slam/ideal_grid", g, log_time=0, publish_time=0)
        for t, seq, topic, m in msgs:
            w.write_message(topic, m, log_time=_ns(t), publish_time=_ns(t), sequence=seq)
        w.finish()
    return path


def load(path: Path | str) -> Recording:
    """Read a recording written by `save`. A file that is not one raises ValueError naming the path."""
    from mcap.reader import make_reader

    path = Path(path)
    classes: dict[str, type[Message]] = {
        "/slam/info": pb.SlamRunInfo,
        "/slam/prediction": pb.SlamPrediction,
        "/slam/truth": pb.SlamPose,
        "/slam/odometry": pb.SlamPose,
        "/slam/sonar": pb.SlamSonar,
        "/slam/landmark": pb.SlamLandmark,
        "/slam/cooccupancy": pb.SlamCooccupancy,
        "/slam/floor": pb.SlamFloor,
        "/slam/ideal_grid": pb.SlamGrid,
    }
    rec: Recording | None = None
    grid_msg = None
    body: list[tuple[str, object]] = []
    with path.open("rb") as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            cls = classes.get(channel.topic)
            if cls is None:
                continue
            m = cls.FromString(message.data)
            if channel.topic == "/slam/info":
                rec = _info_to_recording(m)
            elif channel.topic == "/slam/ideal_grid":
                grid_msg = m
            else:
                body.append((channel.topic, m))
    if rec is None:
        raise ValueError(f"recording {path}: no /slam/info message (not a SLAM recording)")
    for topic, m in body:
        if topic == "/slam/prediction":
            rec.predictions.append(
                (m.avatar, Prediction(m.t, m.vx, m.vy, m.omega, m.sigma_xy, m.sigma_theta))  # type: ignore[attr-defined]
            )
        elif topic in ("/slam/truth", "/slam/odometry"):
            tracks = rec.truth if topic == "/slam/truth" else rec.odometry
            tracks.setdefault(m.avatar, Track()).add(m.t, (m.x, m.y, m.theta))  # type: ignore[attr-defined]
        elif topic == "/slam/sonar":
            echoes = tuple(SonarEcho(e.bearing, e.range if e.HasField("range") else None) for e in m.echoes)  # type: ignore[attr-defined]
            rec.readings.append(SonarReading(m.avatar, m.t, echoes, m.fov, m.max_range))  # type: ignore[attr-defined]
        elif topic == "/slam/landmark":
            sightings = tuple(Sighting(g.landmark_id, g.range, g.bearing) for g in m.sightings)  # type: ignore[attr-defined]
            rec.readings.append(LandmarkReading(m.avatar, m.t, sightings))  # type: ignore[attr-defined]
        elif topic == "/slam/cooccupancy":
            rec.readings.append(CooccupancyReading(m.avatar, m.t, m.radius))  # type: ignore[attr-defined]
        elif topic == "/slam/floor":
            rec.readings.append(FloorReading(m.avatar, m.t, tuple(zip(m.xs, m.ys, strict=True))))  # type: ignore[attr-defined]
    if grid_msg is not None:
        g = grid_msg
        rec.ideal_grid = np.asarray(g.p, dtype=np.float64).reshape(g.rows, g.cols)
        if len(g.region):
            rec.region = np.asarray(g.region, dtype=bool).reshape(g.rows, g.cols)
    return rec


def _info_to_recording(m: pb.SlamRunInfo) -> Recording:
    return Recording(
        arena=m.arena,
        team=m.team,
        seed=m.seed,
        grid=GridSpec(m.width, m.height, m.resolution, m.x0, m.y0),
        avatars=[
            AvatarInfo(
                a.name,
                a.kind,
                (a.x, a.y, a.theta),
                DriftSpec(a.drift_linear, a.drift_angular, a.drift_inflate),
                a.radius,
            )
            for a in m.avatars
        ],
        landmarks={lm.id: (lm.x, lm.y) for lm in m.landmarks},
        duration=m.duration,
        driver=m.driver,
        landmark_range_frac=m.landmark_range_frac,
        landmark_sigma_bearing=m.landmark_sigma_bearing,
        sonar_mount_radius=m.sonar_mount_radius,
    )


# ----- a recording as an event stream -----------------------------------------------------------------


def recording_events(rec: Recording, request_period: float = 1.0, processor: str = "replay") -> list[SlamEvent]:
    """A recording as the log a Baseline run would write (haa.slam.events): every avatar's AddAvatar at t=0,
    then its time-ordered stream (`Recording.events`): predictions, each reading processed as it arrives,
    weight requests."""
    out: list[SlamEvent] = [AddAvatar(a.name, a.kind, a.start, 0.0, a.drift, a.radius) for a in rec.avatars]
    for ev in rec.events(request_period):
        if ev.kind == PREDICTION:
            out.append(Predict(ev.avatar, ev.payload))
        elif ev.kind == READING:
            out.append(Observe(ev.payload, processor))
        elif ev.kind == REQUEST:
            out.append(Request(ev.avatar))
    return out
