"""AvatarSimulation (thesis App. III L3017-3039; Table 4.2-1 item 4): the avatar agent of a simulated robot.

The gateway between haa-sim's avatar API (the robot's hardware: actions, odometry, sonar, camera) and the
team, used only as a robot driver would use it — never the ground-truth service or the sim's Detect call.
One per avatar, spawned by the mission runner when the avatar joins (docs/team.md).

What it does:

* **Registration** (`ExecutiveAvatar ← Register avatar`): DDB key `avatars/<name>` with its agent id, type
  and status; the AddAvatar event of its particle filter (known start pose, thesis L1186) in `slam/log`.
* **Predictions** (thesis §5.1.3 L943-946, eq. 5.1-3): every `predict_period` simulated seconds the
  odometry since the last prediction becomes one prediction update (haa.slam.motion.odometry_prediction with
  the type's drift, Table 6.2-3), appended to `slam/log` together with `slam/anchor/<name>` (time and
  odometry pose of the last committed prediction, and the number of the last reading) in one atomic batch,
  so that a recovered instance continues the prediction chain exactly where the committed one ended (no
  gap, no overlap) and numbers its readings after the last committed one. Every batch this agent writes
  carries the anchor; a batch that fails puts the anchor and the reading number back (a write whose outcome
  is unknown — the host's timeout — makes it read the committed anchor again before the next prediction).
* **Readings**: a camera image every `capture_period` (the thesis' camera is "Manual", Table 6.2-4: we
  capture on a period), a co-occupancy reading every `cooc_period`, each sonar scan (sweepers, 1 s). Each
  is a DDB entry `slam/raw/<name>/<n>` (JSON) that SupervisorSLAM watches, written in the same batch as the
  predictions that cover its time (a reading is never newer than the filter's newest prediction). Frames
  stay here (no camera frames in the DDB): sensor agents fetch one with the request {"op": "frame", "n": k}.
* **Driving** (`AgentPathPlanner ↔ Avatar*`): a target from a supervisor ({"op": "target", ...}) goes to
  the avatar's AgentPathPlanner (its child, spawned at start); the planner answers with a path in the map
  frame; each waypoint is converted to the odometry frame with the current map→odometry transform (from the
  SLAM estimate `slam/est/<name>` and the odometry at the estimate's time) and driven with a MoveTo action.
  When the target is reached (or cannot be) the supervisor is told ({"op": "reached"|"unreachable"}).

Recovery (App. III: "Restore configuration and retrieve AgentPathPlanner status. Reassign target for
AgentPathPlanner if appropriate"): RECOVERY = "backup" — from its backup (config, planner id, current
target) and the committed anchor in the DDB (`slam/anchor/<name>`: the prediction chain goes on from the
anchor's time and odometry pose, readings from the anchor's number + 1); it re-attaches to its avatar in
haa-sim, re-sends the target to its planner and says so in the transcript ("resumed after a crash: ...").
What the crashed instance had not committed is lost: odometry since the anchor is covered by the first
prediction of the new one (the avatar's odometry is continuous in haa-sim), readings it had not written are
not taken again, and its camera frames are gone (a sensor agent asking for one gets "no longer kept" and the
processing counts as failed). A retired avatar (its streams end with UNAVAILABLE, as hardware that stopped
answering; or haa-sim refuses to re-attach a recovered instance to it) marks itself retired in the registry,
appends RemoveAvatar to `slam/log`, stops its planner and stops; the supervisors drop it (their bids are
withdrawn, ExecutiveAvatar releases the assignment).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import dataclasses
import json
import math
from collections import OrderedDict, deque
from typing import Any, Literal

import cv2
import grpc
import numpy as np
import pydantic

from haa.agents import team
from haa.agents.avatar_actions import AvatarActions, left_how
from haa.core.ddb import ops as ddbops
from haa.pb import sim_pb2 as spb
from haa.sdk.registry import register
from haa.slam import events as sev
from haa.slam.motion import DRIFT, DriftSpec, odometry_prediction, wrap_angle

Pose = tuple[float, float, float]


class AvatarConfig(team.TeamConfig):
    avatar: str = pydantic.Field(min_length=1, max_length=64)
    type: str = "seeker"
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    predict_period: float = pydantic.Field(0.25, gt=0, le=5)
    #: an image every half second (the thesis' camera is "Manual"): at 1 s only 14-60 % of the images hold a
    #: landmark and localization comes from landmarks alone (docs/slam.md "In the running team")
    capture_period: float = pydantic.Field(0.5, gt=0, le=60)
    cooc_period: float = pydantic.Field(1.0, gt=0, le=60)
    odometry_period: float = pydantic.Field(0.05, gt=0, le=1)
    #: frames kept for the sensor agents (JC-SLAM processes the newest first, so an old one may be asked for
    #: much later): 60 s of images at one a second, 14 MB of 320 x 240 frames, 55 MB of 640 x 480
    frames_kept: int = pydantic.Field(60, ge=1, le=600)
    #: share of the type's top speed used when driving (Table 6.2-3 speeds are maxima). 0.2 (0.4 m/s for a
    #: seeker): at 0.5 the odometry drifts further between landmark sightings; measured on AF-1 (seed 1,
    #: --speed 4, two runs each) 0.2 with an image every 0.5 s gave coverage 89.0 / 86.0 %, accuracy
    #: 94.0 / 92.5 %, position error 0.32 / 0.43 m against 84.6 / 78.8 %, 91.8 / 89.0 %, 0.51 / 0.29 m at
    #: 0.5 and 1 s, in the same mission time (docs/slam.md)
    cruise: float | Literal["physics"] = pydantic.Field(0.2)
    #: the shared map's cell (m), for `cruise: physics` (team.physics_cruise)
    map_cell: float = pydantic.Field(0.1, gt=0, le=10)

    @pydantic.field_validator("cruise")
    @classmethod
    def _share(cls, v: float | str) -> float | str:
        if isinstance(v, float | int) and not 0 < v <= 1:
            raise ValueError(f"cruise: a share of the top speed in (0, 1] or 'physics', got {v}")
        return v
    #: how near a waypoint counts as reached, m
    tolerance: float = pydantic.Field(0.12, gt=0, le=1)
    #: SLAM mode of the mission (Table 7.2-4); "delay": the avatar halts before each leg until every reading
    #: it made is processed (its `slam/raw/<avatar>/` entries are gone), at most `delay_max_s`
    slam: Literal["jc-slam", "discard", "delay"] = "jc-slam"
    delay_max_s: float = pydantic.Field(30.0, gt=0, le=3600)


#: the bumper's widening of the motion noise (AvatarSimulation.bump_sigma): m per contact begun, share of
#: the driving speed per second of contact, rad of turn per m of push
#: s of mission time without a word from the planner, while the avatar has a target and stands, after which
#: the target is sent again (AvatarSimulation._planner_watchdog)
PLANNER_SILENT_S = 8.0
BUMP_M = 0.05
BUMP_SLIDE = 0.5
BUMP_TURN_RAD = 0.5

#: bytes of frames carried in the transfer state, and their JPEG quality (95: ArUco corners survive it)
FRAMES_STATE_BYTES = 1_200_000
FRAME_JPEG_QUALITY = 95


def jpeg_frame(f: spb.CameraFrame) -> spb.CameraFrame:
    """A copy of a camera frame with its image JPEG-compressed (unchanged if it is not raw RGB)."""
    if f.encoding != spb.IMAGE_ENCODING_RAW_RGB:
        return f
    img = np.frombuffer(f.data, dtype=np.uint8).reshape(f.height, f.width, 3)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, FRAME_JPEG_QUALITY])
    if not ok:
        return f
    out = spb.CameraFrame()
    out.CopyFrom(f)
    out.data = buf.tobytes()
    out.encoding = spb.IMAGE_ENCODING_JPEG
    return out


def to_map(t_est: Pose, t_odo: Pose, p: Pose) -> Pose:
    """Odometry-frame pose -> map frame, with the estimate `t_est` and the odometry `t_odo` at one instant."""
    d = t_est[2] - t_odo[2]
    c, s = math.cos(d), math.sin(d)
    dx, dy = p[0] - t_odo[0], p[1] - t_odo[1]
    return (t_est[0] + c * dx - s * dy, t_est[1] + s * dx + c * dy, float(wrap_angle(p[2] + d)))


def to_odom(t_est: Pose, t_odo: Pose, x: float, y: float) -> tuple[float, float]:
    """Map-frame point -> odometry frame (inverse of `to_map`)."""
    d = t_est[2] - t_odo[2]
    c, s = math.cos(-d), math.sin(-d)
    dx, dy = x - t_est[0], y - t_est[1]
    return (t_odo[0] + c * dx - s * dy, t_odo[1] + s * dx + c * dy)


@register
class AvatarSimulation(team.TeamAgent, AvatarActions):
    TYPE = "avatar_simulation"
    CONFIG = AvatarConfig
    COST = 0.05
    RECOVERY = "backup"
    #: its streams to haa-sim (or its replica) are rebuilt on every move: the allocation should rather not
    TRANSFER_PENALTY = 0.5
    CPU_LIMIT = 1.0

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: AvatarConfig
        self.name_ = self.cfg.avatar
        self.planner: str = ""
        self.target: dict[str, Any] | None = None  # {"x","y","tid","sup"}
        self.n_readings = 0
        self.anchor: tuple[float, Pose] | None = None  # (t, odometry pose) of the last committed prediction
        self.info: spb.AvatarInfo | None = None
        self.odo: deque[tuple[float, Pose]] = deque(maxlen=4000)  # odometry history (t, pose)
        #: the bumper beside it: (t, pressed, bumps so far) per odometry reading (`bump_sigma`)
        self.bumper: deque[tuple[float, bool, int]] = deque(maxlen=4000)
        self.frames: OrderedDict[int, spb.CameraFrame] = OrderedDict()
        self.sonar_pending: list[Any] = []
        self.est: tuple[float, Pose] | None = None  # (t, estimated pose) last published by SupervisorSLAM
        self.link: team.SimLink | None = None
        self.tasks: list[asyncio.Task[Any]] = []
        self.drive_task: asyncio.Task[Any] | None = None
        #: mission time of the last message to or from the planner, and the target it has settled (reached or
        #: unreachable: nothing more to ask the planner until a new target) (`_planner_watchdog`)
        self.planner_heard = 0.0
        self.settled_tid: Any = None
        self.looked_tid: Any = None  # the target it last turned in place for (`_look_around`)
        self.look_arounds = 0
        self.path: list[list[float]] = []
        self.retired = False
        #: Forage: the team's ids of the collectables it carries (from the supervisor's pick_up commands), and
        #: its last drop {"item", "x", "y", "t"} (map frame, its own estimate) — in the registry entry, so a
        #: recovered SupervisorForage learns what happened while it was down
        self.cargo: list[int] = []
        self.last_drop: dict[str, Any] | None = None
        self.action_task: asyncio.Task[Any] | None = None
        #: the pick_up/drop in progress {"op", "item", "tid", "src"}, backed up before it starts (`_collect`)
        self.pending_action: dict[str, Any] | None = None
        self.delay_waits = 0  # SLAM mode "delay": legs started after waiting for readings, and the time waited
        self.delay_s = 0.0
        self.flushing = False
        #: a write whose outcome is unknown: read the committed anchor again before the next prediction
        self.resync = False

    # ------------------------------------------------------------------ life cycle

    def pack_backup(self) -> bytes:
        """The backup: planner, target and reading number (frames are not backed up: a crash loses them)."""
        return team.dumps({"planner": self.planner, "target": self.target, "n": self.n_readings,
                           "cargo": self.cargo, "last_drop": self.last_drop, "pending": self.pending_action})

    def pack_state(self) -> bytes:
        """The transfer state: the backup's fields and the frames still waiting for their processings, newest
        first, JPEG-compressed (quality `FRAME_JPEG_QUALITY`), at most `FRAMES_STATE_BYTES` of them — so a
        transfer of the avatar agent does not fail the sensor agents' pending requests for them (the state
        goes to every host by OAC: agenttable.MAX_STATE is 2 MiB)."""
        st = json.loads(self.pack_backup())
        frames, budget = [], FRAMES_STATE_BYTES
        for n in sorted(self.frames, reverse=True):
            data = jpeg_frame(self.frames[n]).SerializeToString()
            if len(data) > budget:
                break
            budget -= len(data)
            frames.append([n, base64.b64encode(data).decode()])
        st["frames"] = frames
        return team.dumps(st)

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        self.planner = st.get("planner", "")
        self.target = st.get("target")
        self.n_readings = int(st.get("n", 0))
        self.cargo = [int(c) for c in st.get("cargo", [])]
        self.last_drop = st.get("last_drop")
        self.pending_action = st.get("pending")
        for n, b64 in reversed(st.get("frames", [])):
            f = spb.CameraFrame()
            f.ParseFromString(base64.b64decode(b64))
            self.frames[int(n)] = f

    def recover(self, backup: bytes | None) -> None:
        if backup:
            self.unpack_state(backup)

    def on_stop(self) -> None:
        for t in self.tasks:
            t.cancel()
        if self.drive_task:
            self.drive_task.cancel()

    async def begin(self, how: str) -> None:
        fresh = how == "start"
        self.link = team.SimLink(self.cfg.sim, self.cfg.sim_token_file, self.name, tap=self._ctx.tap)
        try:
            reply = await self.link.avatar.Register(
                spb.RegisterRequest(type=self.cfg.type, avatar_id=self.name_), metadata=self.link.metadata
            )
        except grpc.aio.AioRpcError as e:
            if e.code() == grpc.StatusCode.UNAVAILABLE or "retired" in (e.details() or ""):
                await self._retired(f"cannot register: {e.details()}", left_how(e.details()))
                return
            raise
        self.info = reply.avatar
        if self.info.status != "active":
            await self._retired(f"avatar is {self.info.status}", left_how(self.info.status))
            return
        anchor = await self._read_anchor()
        if fresh or anchor is None:
            d = self.drift
            sp = self.info.start_pose
            ev = sev.AddAvatar(self.name_, self.cfg.type, (sp.x, sp.y, sp.theta), float(self.info.joined),
                                d, float(self.info.radius))
            reg = self._registration("active")
            await self.ddb_write([ddbops.log_append(team.K_SLAM_LOG, [sev.encode(ev)]),
                                  team.op_put_json(team.K_AVATARS + self.name_, reg)], atomic=True)
            if self.anchor is None:
                self.anchor = (float(self.info.joined), (sp.x, sp.y, sp.theta))
        else:
            reg = self._registration("active")
            await team.put_json(self, team.K_AVATARS + self.name_, reg)
        if fresh:
            await team.transcript(self, f"avatar {self.name_} ({self.cfg.type}) registered")
        if self.anchor is not None and not self.odo:
            # the history starts at the committed anchor: the map->odometry transform at an estimate of that time
            # is exact before the new odometry stream has said anything
            self.odo.append((self.anchor[0], tuple(self.anchor[1])))  # type: ignore[arg-type]
        self.watch(team.K_SLAM_EST + self.name_, self._on_est)
        # a reading whose processings are all done is deleted from slam/raw/: its frame is not needed any more
        self.watch(f"{team.K_SLAM_RAW}{self.name_}/", self._on_raw_removed)
        est = await team.get_json(self, team.K_SLAM_EST + self.name_)
        if est:
            self.est = (float(est["t"]), (est["x"], est["y"], est["theta"]))
        self.tasks = [asyncio.ensure_future(self._odometry_loop())]
        if self.info.sonars > 0:
            self.tasks.append(asyncio.ensure_future(self._sonar_loop()))
        self.every(self.cfg.predict_period, self._flush)
        self.planner_heard = self.now()
        self.every(PLANNER_SILENT_S / 4, self._planner_watchdog)
        self.every(self.cfg.capture_period, self._capture, first=self.random.uniform(0.1, self.cfg.capture_period))
        self.every(self.cfg.cooc_period, self._cooccupancy, first=self.random.uniform(0.1, self.cfg.cooc_period))
        if not self.planner:
            self.planner = await self.spawn_child(
                "path_planner",
                team.team_config(self, avatar=self.name_, avatar_agent=self.id, radius=float(self.info.radius)),
            )
            self.backup()
        elif self.target:
            self._send_planner({"op": "goto", **self.target})
        if self.pending_action is not None and not fresh:  # an action its previous life did not see end
            pend = self.pending_action
            self.action_task = asyncio.ensure_future(self._collect(str(pend.get("src", "")), pend, again=True))
            self.tasks.append(self.action_task)
        if how == "recover":
            t = self.anchor[0] if self.anchor else float("nan")
            tgt = f"target {self.target['tid']} re-sent to its planner" if self.target else "no target"
            await team.transcript(self, f"resumed after a crash: predictions from t={t:.2f} (the committed anchor), "
                                        f"readings from #{self.n_readings + 1}, {tgt}")

    def _registration(self, status: str) -> dict[str, Any]:
        """The registry entry `avatars/<avatar>`: agent id, type, status, and for Forage the capacity (from
        its hardware, haa-sim's AvatarInfo), what it carries and its last drop; its radius."""
        cap = int(self.info.capacity) if self.info is not None else team.CAPACITY.get(self.cfg.type, 0)
        reg = {"agent": self.id, "type": self.cfg.type, "status": status, "t": self.now(), "capacity": cap,
               "cargo": list(self.cargo), "last_drop": self.last_drop}
        if self.info is not None:  # the sonar agents tell echoes off this avatar from obstacles by it
            reg["radius"] = float(self.info.radius)
        return reg

    async def _read_anchor(self) -> dict[str, Any] | None:
        """The committed anchor (time, odometry pose, last reading number) into `anchor` / `n_readings`."""
        anchor = await team.get_json(self, f"slam/anchor/{self.name_}")
        if anchor:
            self.anchor = (float(anchor["t"]), tuple(anchor["pose"]))
            self.n_readings = max(self.n_readings, int(anchor.get("n", 0)))
        return anchor

    # ------------------------------------------------------------------ odometry and predictions

    async def _odometry_loop(self) -> None:
        assert self.link is not None
        req = spb.StreamRequest(avatar_id=self.name_, period=self.cfg.odometry_period)
        try:
            async for r in self.link.avatar.Odometry(req, metadata=self.link.metadata):
                self.odo.append((r.time, (r.pose.x, r.pose.y, r.pose.theta)))
                self.bumper.append((r.time, bool(r.bumper), int(r.bumps)))
        except asyncio.CancelledError:
            raise
        except grpc.aio.AioRpcError as e:
            if not self._left_sim(e, "odometry stream ended (UNAVAILABLE)"):
                self.log("odometry_error", level="warning", error=str(e))

    @property
    def drift(self) -> DriftSpec:
        """The odometry drift the avatar states to SLAM: what its simulator reports for it (AvatarInfo, so the
        motion model follows haa-sim's --drift model), else Table 6.2-3 as motion.DRIFT reads it."""
        if self.info is not None and self.info.linear_drift > 0 and self.info.angular_drift > 0:
            return DriftSpec(float(self.info.linear_drift), float(self.info.angular_drift))
        return DRIFT[self.cfg.type]

    def bump_sigma(self, t0: float, t1: float) -> float:
        """Std (m) of the push the wheels did not see over (t0, t1]: BUMP_M per contact begun and
        BUMP_SLIDE of the driving speed per second the bumper was pressed (a slide along what it touches).
        haa-sim moves an avatar only as its wheels measure, except in contact (docs/sim.md); a real robot's
        bumper or motor current tells it the same."""
        speed = self.cruise_speed() if self.info is not None else 0.5
        pressed_s, before, last = 0.0, None, None
        prev_t = t0
        for t, pressed, bumps in self.bumper:
            if t <= t0:
                before = bumps
                prev_t = t
                continue
            if t > t1 + 1e-9:
                break
            if pressed:
                pressed_s += t - prev_t
            prev_t, last = t, bumps
        new = 0 if last is None or before is None else max(0, last - before)
        return BUMP_M * new + BUMP_SLIDE * speed * pressed_s

    def odom_at(self, t: float) -> Pose | None:
        """Odometry pose at time t, interpolated (None before the history starts or after its end)."""
        h = self.odo
        if not h or t < h[0][0] - 1e-9 or t > h[-1][0] + 1e-9:
            return None
        lo, hi = 0, len(h) - 1
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if h[mid][0] <= t:
                lo = mid
            else:
                hi = mid - 1
        t0, p0 = h[lo]
        if lo + 1 >= len(h) or t0 >= t:
            return p0
        t1, p1 = h[lo + 1]
        a = (t - t0) / (t1 - t0)
        return (p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]),
                float(wrap_angle(p0[2] + a * wrap_angle(p1[2] - p0[2]))))

    def _prediction_ops(self, upto: float | None = None) -> list[Any]:
        """DDB ops appending the predictions from the anchor to the newest odometry (or `upto`)."""
        if self.anchor is None or not self.odo:
            return []
        t_end, p_end = self.odo[-1]
        if upto is not None and upto < t_end:
            p = self.odom_at(upto)
            if p is not None:
                t_end, p_end = upto, p
        t0, p0 = self.anchor
        if t_end <= t0 + 1e-6:
            return []
        pred = odometry_prediction(t0, p0, t_end, p_end, self.drift)
        slide = self.bump_sigma(t0, t_end)
        if slide > 0:  # widen the motion noise by what the bumper says the wheels may have missed
            dt = t_end - t0
            pred = dataclasses.replace(pred, sigma_xy=math.hypot(pred.sigma_xy, slide / dt),
                                       sigma_theta=math.hypot(pred.sigma_theta, BUMP_TURN_RAD * slide / dt))
        self.anchor = (t_end, p_end)
        return [ddbops.log_append(team.K_SLAM_LOG, [sev.encode(sev.Predict(self.name_, pred))])]

    def _committed(self) -> tuple[Any, int]:
        """What a failed write puts back: the anchor and the reading number before it."""
        return self.anchor, self.n_readings

    async def _write(self, ops: list[Any], before: tuple[Any, int]) -> None:
        """Write `ops` and the anchor (time, odometry pose, last reading number) in one atomic batch."""
        if not ops:
            return
        assert self.anchor is not None
        ops = [*ops, team.op_put_json(f"slam/anchor/{self.name_}", {
            "t": self.anchor[0], "pose": list(self.anchor[1]), "n": self.n_readings})]
        try:
            errs = await self.ddb_write(ops, atomic=True)
        except Exception:
            self.resync = True  # not known whether it committed: the committed anchor decides
            raise
        if any(errs):  # nothing was written: the chain goes on from the committed anchor
            self.anchor, self.n_readings = before
            self.log("ddb_write_failed", level="warning", errors=[e for e in errs if e])

    async def _flush(self) -> None:
        if self.retired:
            return
        if self.resync:
            self.resync = False
            await self._read_anchor()
        before = self._committed()
        ops = self._prediction_ops()
        # sonar scans whose time the committed predictions now cover
        t_anchor = self.anchor[0] if self.anchor else -1.0
        ready = [s for s in self.sonar_pending if s.time <= t_anchor]
        self.sonar_pending = [s for s in self.sonar_pending if s.time > t_anchor]
        for scan in ready:
            ops += self._raw_ops("sonar", scan.time, {
                "echoes": [[r.bearing, r.range if r.echo else None] for r in scan.readings],
                "fov": scan.readings[0].fov if scan.readings else 0.349,
                "max_range": scan.readings[0].max_range if scan.readings else 2.0})
        await self._write(ops, before)

    def _raw_ops(self, kind: str, t: float, body: dict[str, Any]) -> list[Any]:
        self.n_readings += 1
        n = self.n_readings
        rec = {"avatar": self.name_, "agent": self.id, "kind": kind, "t": t, "n": n, **body}
        return [team.op_put_json(f"{team.K_SLAM_RAW}{self.name_}/{n:08d}", rec),
                ddbops.add(team.K_STATS + "readings_generated", 1)]

    # ------------------------------------------------------------------ readings

    async def _capture(self) -> None:
        if self.retired or self.link is None or self.anchor is None or self.resync:
            return
        try:
            f = await self.link.avatar.Capture(spb.CaptureRequest(avatar_id=self.name_),
                                               metadata=self.link.metadata)
        except grpc.aio.AioRpcError as e:
            if e.code() == grpc.StatusCode.UNAVAILABLE:
                await self._retired("camera unavailable", left_how(e.details()))
            return
        # the frame's own odometry stamps the history, so the predictions can cover its time exactly
        if not self.odo or f.time > self.odo[-1][0]:
            self.odo.append((f.time, (f.odometry.x, f.odometry.y, f.odometry.theta)))
        before = self._committed()
        ops = self._prediction_ops(upto=f.time)
        if self.anchor is None or self.anchor[0] < f.time - 1e-6:
            await self._write(ops, before)  # cannot cover its time (odometry not there yet): skip this image
            return
        ops += self._raw_ops("camera", f.time, {"frame": self.n_readings + 1, "camera": f.camera})
        # `_raw_ops` numbered the reading: keep the frame under that number
        self.frames[self.n_readings] = f
        while len(self.frames) > self.cfg.frames_kept:
            self.frames.popitem(last=False)
        await self._write(ops, before)

    async def _cooccupancy(self) -> None:
        if self.retired or not self.odo or self.info is None or self.resync:
            return
        before = self._committed()
        ops = self._prediction_ops()
        if self.anchor is None:
            return
        ops += self._raw_ops("cooccupancy", self.anchor[0], {"radius": float(self.info.radius)})
        await self._write(ops, before)

    async def _sonar_loop(self) -> None:
        assert self.link is not None
        try:
            async for scan in self.link.avatar.Sonar(spb.StreamRequest(avatar_id=self.name_),
                                                     metadata=self.link.metadata):
                self.sonar_pending.append(scan)
        except asyncio.CancelledError:
            raise
        except grpc.aio.AioRpcError as e:
            if e.code() != grpc.StatusCode.UNAVAILABLE:
                self.log("sonar_error", level="warning", error=str(e))

    # ------------------------------------------------------------------ messages

    def _on_raw_removed(self, kind: str, key: str, value: bytes | None) -> None:
        if kind == "remove":
            with contextlib.suppress(ValueError):
                self.frames.pop(int(key.rsplit("/", 1)[1]), None)

    def _on_est(self, kind: str, key: str, value: bytes | None) -> None:
        if value:
            try:
                e = json.loads(value)
                self.est = (float(e["t"]), (float(e["x"]), float(e["y"]), float(e["theta"])))
            except (ValueError, KeyError, TypeError):
                pass

    def _send_planner(self, msg: dict[str, Any]) -> None:
        if self.planner:
            self.planner_heard = self.now()
            self.send(self.planner, team.dumps(msg))

    async def _planner_watchdog(self) -> None:
        """A target, not driving, and nothing from the planner for PLANNER_SILENT_S: send the target again.
        A message can be lost when the planner crashes or is recovered while it is in flight (its "hello"
        may reach this agent before it has resumed): without this the avatar would wait for ever."""
        if not (self.target and self.planner) or (self.drive_task is not None and not self.drive_task.done()):
            return
        if self.settled_tid is not None and self.settled_tid == self.target.get("tid"):
            return
        if self.now() - self.planner_heard > PLANNER_SILENT_S:
            self.log("planner_silent", target=self.target.get("tid"))
            self._send_planner({"op": "goto", **self.target})

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        op = msg.get("op")
        if op == "target":
            self.target = {"x": float(msg["x"]), "y": float(msg["y"]), "tid": msg.get("tid", 0),
                           "sup": msg.get("sup", src)}
            self.settled_tid = None
            self.log("target", tid=self.target["tid"], x=self.target["x"], y=self.target["y"],
                     sup=self.target["sup"])
            self.backup()
            self._stop_driving()
            self._send_planner({"op": "goto", **self.target})
        elif op in ("pick_up", "drop"):  # Forage (SupervisorForage): one collection action at a time
            self._stop_driving()
            if self.action_task is None or self.action_task.done():
                self.action_task = asyncio.ensure_future(self._collect(src, msg))
                self.tasks.append(self.action_task)
        elif op == "halt":
            self.target = None
            self._stop_driving()
        elif op == "hello" and src == self.planner and self.target:
            self._send_planner({"op": "goto", **self.target})
        elif op == "path" and self.target and msg.get("tid") == self.target.get("tid"):
            self.planner_heard = self.now()
            self._stop_driving()
            self.path = [list(w) for w in msg.get("waypoints", [])]
            self.drive_task = asyncio.ensure_future(self._drive(self.target["tid"], msg.get("final", True)))
        elif op == "unreachable" and self.target and msg.get("tid") == self.target.get("tid"):
            self.planner_heard = self.now()
            if msg.get("reason") == team.START_ENCLOSED and self.looked_tid != self.target.get("tid"):
                self.looked_tid = self.target.get("tid")
                self._stop_driving()
                self.drive_task = asyncio.ensure_future(self._look_around(self.target["tid"]))
                return
            self.settled_tid = self.target.get("tid")
            self.log("target_unreachable", level="warning", tid=self.target.get("tid"), reason=msg.get("reason"))
            self._tell_supervisor("unreachable")

    async def on_request(self, src: str, payload: bytes) -> bytes:
        msg = json.loads(payload)
        if msg.get("op") == "frame":
            f = self.frames.get(int(msg.get("n", -1)))
            if f is None:
                raise LookupError(f"frame {msg.get('n')} is no longer kept")
            return f.SerializeToString()
        if msg.get("op") == "pose":
            return team.dumps(self._pose_map())
        raise ValueError(f"unknown request {msg.get('op')!r}")

    def _pose_map(self) -> dict[str, Any]:
        if not self.odo:
            return {}
        t, p = self.odo[-1]
        m = self._map_pose(p)
        return {"t": t, "x": m[0], "y": m[1], "theta": m[2]}

    def _transform(self) -> tuple[Pose, Pose]:
        """(estimate, odometry) at the estimate's time; identity (start pose) before any estimate."""
        if self.est is not None:
            o = self.odom_at(self.est[0])
            if o is not None:
                return self.est[1], o
        if self.info is not None and not self.est:
            sp = self.info.start_pose
            return (sp.x, sp.y, sp.theta), (sp.x, sp.y, sp.theta)
        if self.odo and self.est is not None:  # estimate older than the odometry history: use its start
            return self.est[1], self.odo[0][1]
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)

    def _map_pose(self, p: Pose) -> Pose:
        e, o = self._transform()
        return to_map(e, o, p)

    def _tell_supervisor(self, what: str) -> None:
        if self.target and self.target.get("sup"):
            self.send(self.target["sup"], team.dumps({"op": what, "avatar": self.name_,
                                                      "tid": self.target.get("tid")}))

    # ------------------------------------------------------------------ driving

    def _stop_driving(self) -> None:
        if self.drive_task is not None:
            self.drive_task.cancel()
            self.drive_task = None

    async def _wait_for_readings(self) -> None:
        """SLAM mode "delay" (Table 7.2-4: "the avatar halts until all its readings are processed"): wait
        until none of this avatar's readings is left in `slam/raw/<avatar>/` (SupervisorSLAM deletes each
        when its processings are done), polling every 0.1 s of mission time, at most `delay_max_s`."""
        t0 = self.now()
        prefix = f"{team.K_SLAM_RAW}{self.name_}/"
        waited = False
        while self.now() - t0 < self.cfg.delay_max_s:
            if not await self.ddb_scan(prefix, limit=1):
                break
            waited = True
            await asyncio.sleep(self._ctx.clock.wall_delay(0.1))
        if waited:
            self.delay_waits += 1
            self.delay_s += self.now() - t0

    def cruise_speed(self) -> float:
        """m/s: `cruise` of its type's top speed, or with `cruise: physics` its sensing's (team.physics_cruise)."""
        assert self.info is not None
        top = float(self.info.max_speed)
        if self.cfg.cruise == "physics":
            sonar = float(self.info.sonar_period) if self.info.sonars > 0 else None
            return team.physics_cruise(top, self.cfg.map_cell, sonar, self.cfg.capture_period)
        return float(self.cfg.cruise) * top

    async def _drive(self, tid: Any, final: bool) -> None:
        assert self.link is not None and self.info is not None
        speed = self.cruise_speed()
        try:
            while self.path:
                if self.cfg.slam == "delay":
                    await self._wait_for_readings()
                wx, wy = self.path[0]
                e, o = self._transform()
                ox, oy = to_odom(e, o, wx, wy)
                req = spb.ActionRequest(avatar_id=self.name_, move_to=spb.MoveTo(
                    x=ox, y=oy, speed=speed, tolerance=self.cfg.tolerance), progress_period=0.5)
                last = None
                async for u in self.link.avatar.Act(req, metadata=self.link.metadata):
                    last = u
                if last is None or last.status != spb.ACTION_STATUS_SUCCEEDED:
                    why = last.reason if last is not None else "no outcome"
                    self.log("move_failed", tid=tid, reason=why, waypoint=[wx, wy])
                    self.send(self.planner, team.dumps({"op": "failed", "tid": tid, "reason": why,
                                                        "pose": self._pose_map()}))
                    return
                self.path.pop(0)
            self.send(self.planner, team.dumps({"op": "arrived", "tid": tid, "final": final,
                                                "pose": self._pose_map()}))
            if final and self.target and self.target.get("tid") == tid:
                self.settled_tid = tid
                self.log("target_reached", tid=tid)
                self._tell_supervisor("reached")
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):  # stop the avatar where it is; the new path follows
                await self.link.avatar.Cancel(spb.AvatarRef(avatar_id=self.name_), metadata=self.link.metadata)
            raise
        except grpc.aio.AioRpcError as e:
            if not self._left_sim(e, "actions unavailable"):
                self.log("drive_error", level="warning", error=str(e))
        except Exception as e:  # a task's exception is otherwise dropped unseen, and the avatar stands still
            self.log("drive_error", level="error", error=repr(e))

    # ------------------------------------------------------------------ retirement

    async def _retired(self, why: str, how: str = "retired") -> None:
        if self.retired:
            return
        self.retired = True
        self._stop_driving()
        for t in self.tasks:
            t.cancel()
        # Forage: how it left ("retired": haa-sim put its cargo down where it stood; "crashed": it keeps it) and
        # where it was by its own estimate (SupervisorForage fetches a put-down collectable from there)
        reg = {**self._registration("retired"), "why": why, "how": how, "pose": self._pose_map()}
        ops = [team.op_put_json(team.K_AVATARS + self.name_, reg),
               ddbops.log_append(team.K_SLAM_LOG, [sev.encode(sev.RemoveAvatar(self.name_))])]
        try:
            errs = await self.ddb_write(ops, atomic=True)
            if any(errs):
                self.log("retire_write_failed", level="warning", errors=[e for e in errs if e])
        except Exception as e:
            self.log("retire_write_failed", level="warning", error=str(e))
        await team.transcript(self, f"avatar {self.name_} retired ({why})")
        self._send_planner({"op": "stop"})
        self.stop()
