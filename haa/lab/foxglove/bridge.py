"""A cluster's mirror stream as Foxglove messages on a Foxglove WebSocket server (foxglove-sdk).

`FoxgloveBridge(hub)` starts a `foxglove` WebSocket server on its own `foxglove.Context` and publishes what the
dashboard's `Hub` (haa.lab.dashboard.sources) knows — the DDB replica a host's mirror stream keeps up to date, the
ground truth polled from haa-sim, the agent timeline — decoded by the dashboard's model (haa.lab.dashboard.model:
`DdbMirror.map_view`, `overlay_view`, `particles`). Every message is in frame `map` (the arena's metres, the
frame the team's SLAM estimates are in), stamped with the wall time it was published. Topics (schemas are
Foxglove's well-known ones, protobuf-encoded by the SDK; `/mission/status` is JSON):

    /map                      foxglove.Grid         the team's occupancy grid `slam/map`: one uint8 field
                                                    `occupancy`, 0..254 = p(occupied) × 254 (127: unknown)
    /obstacles                foxglove.Grid         the arena's true obstacles (haa-sim, display only): 254 = solid
    /avatars/estimated        foxglove.PosesInFrame every avatar's estimated pose (`slam/est/<avatar>`)
    /avatars/true             foxglove.PosesInFrame every avatar's true pose (haa-sim ground truth)
    /avatars/<id>/estimated   foxglove.PoseInFrame  one avatar's estimated pose (and /avatars/<id>/true)
    /avatars/<id>/particles   foxglove.PointCloud   its particles in the latest SLAM checkpoint (x, y, z float32)
    /landmarks                foxglove.SceneUpdate  landmark estimates (`slam/landmarks`: a sphere of radius
                                                    2σ and a label each) and, when known, the true landmarks
    /paths                    foxglove.SceneUpdate  estimated path of each avatar, planned paths, targets
    /transcript               foxglove.Log          the mission transcript (`mission/events`), one line each, as
                                                    the transcript prints it: "00:31 A1 (ExecutiveMission) ..."
    /agents/events            foxglove.Log          the agent timeline: spawning, active, freezing, crashed, ...
    /mission/status           JSON                  `mission/status` (state, explored, ...) for plots

The WebSocket protocol does not keep messages for late subscribers, so the state topics behave as latched: when
a client subscribes, the current state of every state topic is published again; the two log topics replay
their last `BACKLOG` lines to the first subscriber only (later ones would see them twice otherwise).

`run(backend, ...)` follows a running cluster (the dashboard's sources) until interrupted; `haactl foxglove`
parses arguments and calls it.
"""

from __future__ import annotations

import base64
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import foxglove
import numpy as np
from foxglove import channels as fch
from foxglove import messages as fm
from foxglove.websocket import ServerListener

from haa.lab.dashboard.sources import Changes, Hub
from haa.mission.transcript import Line, mission_lines

log = logging.getLogger("haa.lab.foxglove")

FRAME = "map"
#: the loop's minimum period, seconds (changes within it are published together)
TICK = 0.05
#: log lines replayed to a log topic's first subscriber
BACKLOG = 200
#: transcript lines published per tick at most (a long mission's transcript on a fresh snapshot)
MAX_LINES_PER_TICK = 500
LOG_TOPICS = ("/transcript", "/agents/events")
TIMELINE_LEVELS = {"crashed": fm.LogLevel.Error, "failed": fm.LogLevel.Error, "backoff": fm.LogLevel.Warning,
                   "recovering": fm.LogLevel.Warning, "removed": fm.LogLevel.Warning}


def _stamp(t: float | None = None) -> fm.Timestamp:
    return fm.Timestamp.from_epoch_secs(time.time() if t is None else t)


def _pose(x: float, y: float, theta: float = 0.0, z: float = 0.0) -> fm.Pose:
    """A planar pose: position (x, y, z), heading theta about +z."""
    return fm.Pose(position=fm.Vector3(x=x, y=y, z=z),
                   orientation=fm.Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2)))


def _finite(*vals: Any) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in vals)
    except (TypeError, ValueError):
        return False


def grid_message(view: dict[str, Any], stamp: fm.Timestamp) -> fm.Grid:
    """A dashboard grid view (`map_view`: base64 uint8 cells, row 0 the lowest y) as a foxglove.Grid."""
    cells = base64.b64decode(view["cells"])
    res = float(view["res"])
    return fm.Grid(timestamp=stamp, frame_id=FRAME, pose=_pose(float(view["x0"]), float(view["y0"])),
                   column_count=int(view["w"]), cell_size=fm.Vector2(x=res, y=res), row_stride=int(view["w"]),
                   cell_stride=1, fields=[fm.PackedElementField(name="occupancy", offset=0,
                                                                type=fm.PackedElementFieldNumericType.Uint8)],
                   data=cells)


def point_cloud(points: list[list[float]], stamp: fm.Timestamp) -> fm.PointCloud:
    """Planar points [[x, y], ...] as a foxglove.PointCloud of float32 x, y, z (z = 0)."""
    arr = np.zeros((len(points), 3), dtype="<f4")
    if points:
        arr[:, :2] = np.asarray(points, dtype=np.float64)[:, :2]
    f32 = fm.PackedElementFieldNumericType.Float32
    fields = [fm.PackedElementField(name=n, offset=4 * i, type=f32) for i, n in enumerate("xyz")]
    return fm.PointCloud(timestamp=stamp, frame_id=FRAME, pose=_pose(0.0, 0.0), point_stride=12, fields=fields,
                         data=arr.tobytes())


class FoxgloveBridge(ServerListener):
    """Publishes a `Hub`'s state on a Foxglove WebSocket server (module docstring). `start()`, then call
    `step()` in a loop (or `run_forever()`), `stop()` at the end."""

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 8765, name: str = "HAA") -> None:
        self.hub = hub
        self.host = host
        self.port = port
        self.name = name
        self.ctx = foxglove.Context()
        self.server: Any = None
        self.published: dict[str, int] = {}  # topic -> messages published
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._resend = True  # publish the whole state at the next step
        self._replay: set[str] = set()  # log topics whose first subscriber wants their backlog
        self._subs: dict[str, int] = {}
        self._dyn: dict[str, Any] = {}  # per-avatar channels by topic
        self._lines: dict[str, deque[tuple[int, fm.Log]]] = {t: deque(maxlen=BACKLOG) for t in LOG_TOPICS}
        self._events_next = 0  # the next `mission/events` index to publish
        self._last_status: Any = None
        c = self.ctx
        self.map = fch.GridChannel("/map", context=c)
        self.obstacles = fch.GridChannel("/obstacles", context=c)
        self.est_all = fch.PosesInFrameChannel("/avatars/estimated", context=c)
        self.true_all = fch.PosesInFrameChannel("/avatars/true", context=c)
        self.landmarks = fch.SceneUpdateChannel("/landmarks", context=c)
        self.paths = fch.SceneUpdateChannel("/paths", context=c)
        self.transcript = fch.LogChannel("/transcript", context=c)
        self.agent_events = fch.LogChannel("/agents/events", context=c)
        self.status = foxglove.Channel("/mission/status", context=c)

    # ------------------------------------------------------------------ server
    def start(self) -> str:
        """Start the WebSocket server; returns its ws:// URL (port 0 takes a free one). OSError if it cannot."""
        try:
            self.server = foxglove.start_server(name=self.name, host=self.host, port=self.port, context=self.ctx,
                                                server_listener=self)
        except RuntimeError as e:  # the SDK's FoxgloveError, e.g. "Failed to bind port: Address already in use"
            raise OSError(str(e).removeprefix("FoxgloveError: ")) from None
        self.port = int(self.server.port)
        self.hub.set_waker(self._wake.set)
        return f"ws://{self.host}:{self.port}"

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    # foxglove.websocket.ServerListener (called on the SDK's threads)
    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            n = self._subs.get(channel.topic, 0)
            self._subs[channel.topic] = n + 1
            if channel.topic in LOG_TOPICS and n == 0:
                self._replay.add(channel.topic)
            self._resend = True
        self._wake.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self._subs[channel.topic] = max(0, self._subs.get(channel.topic, 0) - 1)

    # ------------------------------------------------------------------ loop
    def run_forever(self, stop: threading.Event | None = None, tick: float = TICK) -> None:
        stop = stop or threading.Event()
        while not stop.is_set():
            self._wake.wait(1.0)
            self._wake.clear()
            self.step()
            stop.wait(tick)

    def step(self) -> None:
        """Publish what changed in the hub since the last step (everything after a new subscription)."""
        with self._lock:
            resend, self._resend = self._resend, False
            replay, self._replay = self._replay, set()
        ch = self.hub.take()
        now = time.time()
        stamp = _stamp(now)
        with self.hub.lock:  # the sources write the replica under this lock
            m = self.hub.mirror
            mapv = m.map_view() if resend or ch.map else None
            overlay = m.overlay_view() if resend or ch.overlay else None
            events = self._new_transcript(m) if resend or ch.ddb_all or "mission/events" in ch.ddb_keys else []
            truth = dict(self.hub.truth) if resend or ch.truth else None
            arena = dict(self.hub.arena) if resend or ch.arena else None
            true_landmarks = list(self.hub.arena.get("landmarks") or [])
            est_landmarks = m.json("slam/landmarks") if overlay is None and arena else None
        if mapv is not None:
            self._log(self.map, grid_message(mapv, stamp))
        if arena and arena.get("obstacles"):
            self._log(self.obstacles, grid_message(arena["obstacles"], stamp))
        if overlay is not None:
            self._overlay(overlay, stamp, true_landmarks, resend)
        elif arena:  # the true landmarks arrived: publish them with the estimates
            self._landmarks(est_landmarks if isinstance(est_landmarks, dict) else {}, true_landmarks, stamp)
        if truth is not None and truth.get("avatars"):
            self._truth(truth, stamp)
        for line in events:
            self._log_line("/transcript", self.transcript, line, now)
        self._timeline(ch)
        for topic in replay:
            ch_ = self.transcript if topic == "/transcript" else self.agent_events
            for t_ns, msg in list(self._lines[topic]):
                ch_.log(msg, log_time=t_ns)

    # ------------------------------------------------------------------ publishing
    def _log(self, channel: Any, msg: Any, log_time: int | None = None) -> None:
        channel.log(msg, log_time=log_time if log_time is not None else time.time_ns())
        t = channel.topic()
        self.published[t] = self.published.get(t, 0) + 1

    def _channel(self, topic: str, cls: Callable[..., Any]) -> Any:
        c = self._dyn.get(topic)
        if c is None:
            c = self._dyn[topic] = cls(topic, context=self.ctx)
        return c

    def _overlay(self, ov: dict[str, Any], stamp: fm.Timestamp, true_landmarks: list[Any], resend: bool) -> None:
        poses = []
        for avatar, e in sorted(ov["estimates"].items()):
            if not _finite(e.get("x"), e.get("y"), e.get("theta", 0.0)):
                continue
            p = _pose(float(e["x"]), float(e["y"]), float(e.get("theta", 0.0)))
            poses.append(p)
            self._log(self._channel(f"/avatars/{avatar}/estimated", fch.PoseInFrameChannel),
                      fm.PoseInFrame(timestamp=stamp, frame_id=FRAME, pose=p))
        if poses:
            self._log(self.est_all, fm.PosesInFrame(timestamp=stamp, frame_id=FRAME, poses=poses))
        for avatar, part in sorted(ov["particles"].items()):
            pts = [q for q in part.get("points") or [] if _finite(*q[:2])]
            self._log(self._channel(f"/avatars/{avatar}/particles", fch.PointCloudChannel), point_cloud(pts, stamp))
        self._landmarks(ov["landmarks"], true_landmarks, stamp)
        self._paths(ov, stamp)
        status = ov.get("status")
        if isinstance(status, dict) and (resend or status != self._last_status):
            self._last_status = status
            self._log(self.status, status)

    def _landmarks(self, est: dict[str, Any], true: list[Any], stamp: fm.Timestamp) -> None:
        spheres, texts = [], []
        for lid, v in sorted(est.items()):
            if not isinstance(v, list | tuple) or len(v) < 2 or not _finite(*v[:2]):
                continue
            std = float(v[2]) if len(v) > 2 and _finite(v[2]) else 0.05
            d = max(0.05, 4 * std)  # a sphere of radius 2 sigma
            spheres.append(fm.SpherePrimitive(pose=_pose(float(v[0]), float(v[1])), size=fm.Vector3(x=d, y=d, z=d),
                                              color=fm.Color(r=1.0, g=0.55, b=0.0, a=0.6)))
            texts.append(fm.TextPrimitive(pose=_pose(float(v[0]), float(v[1]), z=0.15), billboard=True, font_size=12,
                                          scale_invariant=True, color=fm.Color(r=1, g=1, b=1, a=1), text=f"L{lid}"))
        entities = [fm.SceneEntity(timestamp=stamp, frame_id=FRAME, id="landmarks/estimated", spheres=spheres,
                                   texts=texts)]
        ts = [fm.SpherePrimitive(pose=_pose(float(lm["x"]), float(lm["y"])), size=fm.Vector3(x=0.08, y=0.08, z=0.08),
                                 color=fm.Color(r=0.1, g=0.8, b=0.2, a=0.9))
              for lm in true if _finite(lm.get("x"), lm.get("y"))]
        if ts:
            entities.append(fm.SceneEntity(timestamp=stamp, frame_id=FRAME, id="landmarks/true", spheres=ts))
        self._log(self.landmarks, fm.SceneUpdate(entities=entities))

    def _paths(self, ov: dict[str, Any], stamp: fm.Timestamp) -> None:
        entities = []

        def line(pts: list[Any], color: fm.Color) -> fm.LinePrimitive:
            return fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(0.0, 0.0), thickness=2.0,
                                    scale_invariant=True, color=color,
                                    points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=0.01) for p in pts
                                            if _finite(*p[:2])])

        for avatar, pts in sorted(ov["paths"].items()):
            if len(pts) >= 2:
                entities.append(fm.SceneEntity(timestamp=stamp, frame_id=FRAME, id=f"path/{avatar}",
                                               lines=[line(pts, fm.Color(r=0.2, g=0.5, b=1.0, a=1.0))]))
        for avatar, pts in sorted(ov["planned"].items()):
            if len(pts) >= 2:
                entities.append(fm.SceneEntity(timestamp=stamp, frame_id=FRAME, id=f"planned/{avatar}",
                                               lines=[line(pts, fm.Color(r=0.9, g=0.2, b=0.9, a=1.0))]))
        for avatar, t in sorted(ov["targets"].items()):
            if _finite(t.get("x"), t.get("y")):
                entities.append(fm.SceneEntity(
                    timestamp=stamp, frame_id=FRAME, id=f"target/{avatar}",
                    spheres=[fm.SpherePrimitive(pose=_pose(float(t["x"]), float(t["y"])),
                                                size=fm.Vector3(x=0.1, y=0.1, z=0.1),
                                                color=fm.Color(r=1.0, g=0.1, b=0.1, a=0.9))],
                    texts=[fm.TextPrimitive(pose=_pose(float(t["x"]), float(t["y"]), z=0.15), billboard=True,
                                            font_size=12, scale_invariant=True, color=fm.Color(r=1, g=1, b=1, a=1),
                                            text=f"{avatar}: {t.get('task') or 'target'}")]))
        if entities:
            self._log(self.paths, fm.SceneUpdate(entities=entities))

    def _truth(self, truth: dict[str, Any], stamp: fm.Timestamp) -> None:
        poses = []
        for aid, a in sorted(truth["avatars"].items()):
            if a.get("status", "active") != "active" or not _finite(a.get("x"), a.get("y"), a.get("theta")):
                continue
            p = _pose(float(a["x"]), float(a["y"]), float(a["theta"]))
            poses.append(p)
            self._log(self._channel(f"/avatars/{aid}/true", fch.PoseInFrameChannel),
                      fm.PoseInFrame(timestamp=stamp, frame_id=FRAME, pose=p))
        self._log(self.true_all, fm.PosesInFrame(timestamp=stamp, frame_id=FRAME, poses=poses))

    def _new_transcript(self, m: Any) -> list[Line]:
        """`mission/events` lines not published yet (all of them again if the log started over), as the mission
        transcript reads them (haa.mission.transcript.mission_lines)."""
        o = m.get("mission/events")
        if o is None or o.type_name != "log":
            return []
        v = o.value
        first, items = int(v["first"]), list(v["items"])
        end = first + len(items)
        if end < self._events_next:  # another mission's log (a new snapshot): start over
            self._events_next = 0
        start = max(self._events_next, first, end - MAX_LINES_PER_TICK)
        self._events_next = end
        return mission_lines(bytes(item) for item in items[start - first:])

    def _log_line(self, topic: str, channel: Any, line: Line, now: float) -> None:
        msg = fm.Log(timestamp=_stamp(now), level=fm.LogLevel.Info, message=line.format(),
                     name=line.agent or "mission")
        t_ns = int(now * 1e9)
        self._lines[topic].append((t_ns, msg))
        self._log(channel, msg, t_ns)

    def _timeline(self, ch: Changes) -> None:
        for e in ch.timeline:
            t = float(e.get("t") or time.time())
            detail = f": {e['detail']}" if e.get("detail") else ""
            msg = fm.Log(timestamp=_stamp(t), level=TIMELINE_LEVELS.get(e.get("event", ""), fm.LogLevel.Info),
                         message=f"{e.get('name') or e.get('agent', '')[:8]} {e.get('event')} on {e.get('host')}"
                                 f"{detail}", name=str(e.get("host") or ""))
            t_ns = int(t * 1e9)
            self._lines["/agents/events"].append((t_ns, msg))
            self._log(self.agent_events, msg, t_ns)


def run(backend: Any, port: int = 8765, bind: str = "127.0.0.1", host: str | None = None, sim: Any = None,
        truth: bool = True, on_ready: Callable[[str], None] | None = None) -> None:
    """Bridge `backend`'s cluster to Foxglove on `bind:port` until interrupted (KeyboardInterrupt). `host`: follow
    this host's mirror stream (default: the first alive member); `sim`: the haa-sim whose ground truth to show
    (a `haa.lab.dashboard.sources.SimTarget`; default: the local cluster's mission, else `mission/params`);
    `truth=False`: none."""
    from haa.lab.dashboard.sources import MirrorFollower, TimelineFeed, TruthPoller

    hub = Hub(backend.describe())
    bridge = FoxgloveBridge(hub, bind, port, name=f"HAA: {backend.describe()}")
    url = bridge.start()
    srcs: list[Any] = [MirrorFollower(hub, backend, host), TimelineFeed(hub, backend)]
    if truth:
        srcs.append(TruthPoller(hub, backend, sim))
    for s in srcs:
        s.start()
    if on_ready is not None:
        on_ready(url)
    stop = threading.Event()
    try:
        bridge.run_forever(stop)
    finally:
        stop.set()
        for s in srcs:
            s.stop()
        for s in srcs:
            s.join(2.0)
        with contextlib.suppress(Exception):
            bridge.stop()


__all__ = ["FoxgloveBridge", "grid_message", "point_cloud", "run"]
