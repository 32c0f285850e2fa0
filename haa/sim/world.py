"""The simulated world: an arena, avatars driven through pymunk, their sensors, and the ground truth.

This is the library API (in-process, no gRPC) that haa-sim serves and that SLAM experiments use directly:

```python
from haa.sim.world import World
w = World.from_arena("small", seed=0)          # "small" | "large" | path to a YAML arena file
aid = w.add_avatar("sweeper")                    # next free start pose; returns the avatar id
w.set_velocity(aid, 0.5, 0.2)                    # m/s, rad/s, clipped to the type's limits
w.step(0.1)                                      # advance simulated time; w.time
w.true_pose(aid), w.odometry(aid)                # (x, y, theta): truth, and what the wheels believe
w.sonar(aid)                                     # [SonarReading] (sweepers: 5)
w.landmark_observations(aid)                     # [LandmarkObservation] the camera's detected landmarks
w.capture(aid)                                   # CameraFrame: a rendered RGB image + intrinsics
w.ideal_grid(0.05)                               # (grid 1=occupied, origin, resolution)
```

Physics: a pymunk space with the arena's walls and obstacles as static polygons and each avatar as a
circle body. As in pymunk's tank example, each avatar is steered through a kinematic *control body* joined
to it by a pivot joint and a gear joint with their error correction off (`max_bias = 0`): every step the
control body gets the commanded velocities (forward speed along the heading, turn rate), and the joints
drag the avatar along with a bounded force, so walls, obstacles and other avatars stop it. Physics runs in
sub-steps of at most `physics_dt` (default 0.02 s); `step(dt)` is deterministic for a given seed and
sequence of calls, and splits at schedule times (haa.sim.schedule).

Randomness: every avatar has its own generators seeded from (seed, avatar serial number, stream): its
systematic drift, odometry noise, sonar noise, camera noise and image noise are independent streams, so
asking one sensor more often never changes another's readings.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pymunk

from haa.sim.actions import CANCELLED, FAILED, REACH, Action
from haa.sim.arena import COLLECTABLE_HEIGHT, COLLECTABLE_RADIUS, Arena, load_arena
from haa.sim.avatars import DRIFT_MODELS, AvatarSpec, NormalStream, Odometry, avatar_spec
from haa.sim.camera import LABEL_AVATAR, LABEL_COLLECTABLE, CameraFrame, Renderer, intrinsics
from haa.sim.geometry import cast_circles, cast_segments, point_in_polygon, wrap_angle
from haa.sim.groundtruth import IdealGrid, explorable_grid, ideal_grid
from haa.sim.schedule import ScheduleEntry
from haa.sim.sensors import (
    BEARING_SIGMA,
    CAMERA_HEIGHT,
    CAMERAS,
    MAX_INCIDENCE,
    SONAR_BEARINGS,
    SONAR_FOV,
    SONAR_RANGE,
    SONAR_RAYS,
    SONAR_SIGMA,
    CameraSpec,
    CollectableObservation,
    LandmarkObservation,
    SonarReading,
)

ACTIVE, RETIRED, CRASHED = "active", "retired", "crashed"
#: random streams of an avatar
_DRIFT, _SONAR, _CAMERA, _IMAGE = 1, 2, 3, 4
_AVATAR_SHAPE = 1  # pymunk collision type of the avatars' shapes (bump detection)
#: joint strengths: force per kg and torque per kg m^2 the wheels can exert
_FORCE_PER_KG = 60.0
_TORQUE_PER_INERTIA = 600.0
#: room kept between a new avatar and others at a start pose
_START_GAP = 0.05


class AvatarUnavailable(RuntimeError):
    """The avatar is retired or crashed (or unknown): it does not answer."""


@dataclass
class SimEvent:
    """Something that happened: kind is joined, retired, crashed, picked, dropped, deposited, bump or
    schedule."""

    time: float
    kind: str
    avatar: str
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass
class CollectableState:
    id: str
    x: float
    y: float
    state: str  # "floor" | "carried" | "deposited"
    carrier: str | None = None
    region: str | None = None


class AvatarState:
    """One avatar: its pymunk bodies, commands, odometry, random streams, current action."""

    def __init__(self, world: World, aid: str, kind: str, serial: int, pose: tuple[float, float, float]) -> None:
        self.id = aid
        self.kind = kind
        self.spec: AvatarSpec = avatar_spec(kind)
        self.serial = serial
        self.status = ACTIVE
        self.joined = world.time
        self.left: float | None = None
        self.cmd_v = 0.0
        self.cmd_w = 0.0
        self.last_speed = 0.0
        self.action: Action | None = None
        self.carrying: list[str] = []
        self.start_pose = pose
        seed = world.seed
        params = self.spec.drift_params_for(world.drift)
        #: (linear, angular) drift figures of its type in the world's drift model (what AvatarInfo reports)
        self.drift_figures = self.spec.drift_figures(world.drift)
        self.bumps = 0  # contacts begun with a wall, an obstacle or another avatar (a "bump" event each)
        self.contacts = 0  # contacts now (its bumper is pressed while > 0)
        self.odo = Odometry(params, pose, np.random.default_rng([seed, serial, _DRIFT]))
        self.sonar_noise = NormalStream(np.random.default_rng([seed, serial, _SONAR]), 512)
        self.camera_noise = NormalStream(np.random.default_rng([seed, serial, _CAMERA]), 512)
        self.image_rng = np.random.default_rng([seed, serial, _IMAGE])
        self.camera: CameraSpec = CAMERAS[self.spec.camera]
        s = self.spec
        moment = pymunk.moment_for_circle(s.mass, 0, s.radius)
        self.body = pymunk.Body(s.mass, moment)
        self.body.position = pose[0], pose[1]
        self.body.angle = pose[2]
        self.shape = pymunk.Circle(self.body, s.radius)
        self.shape.friction = 0.0
        self.shape.elasticity = 0.0
        self.shape.collision_type = _AVATAR_SHAPE
        self.control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.control.position = pose[0], pose[1]
        self.control.angle = pose[2]
        self.pivot = pymunk.PivotJoint(self.control, self.body, (0, 0), (0, 0))
        self.pivot.max_bias = 0
        self.pivot.max_force = _FORCE_PER_KG * s.mass
        self.gear = pymunk.GearJoint(self.control, self.body, 0.0, 1.0)
        self.gear.max_bias = 0
        self.gear.max_force = _TORQUE_PER_INERTIA * moment
        self.prev = (pose[0], pose[1], pose[2])

    @property
    def pose(self) -> tuple[float, float, float]:
        p = self.body.position
        return (float(p.x), float(p.y), wrap_angle(float(self.body.angle)))

    def parts(self) -> tuple[Any, ...]:
        return (self.body, self.shape, self.control, self.pivot, self.gear)


class World:
    """An arena with avatars; see the module docstring."""

    def __init__(
        self,
        arena: Arena,
        seed: int = 0,
        physics_dt: float = 0.02,
        schedule: list[ScheduleEntry] | None = None,
        max_events: int = 100_000,
        drift: str = "thesis",
    ) -> None:
        if not (0 < physics_dt <= 0.1):
            raise ValueError(f"physics_dt: {physics_dt} s is outside (0, 0.1]")
        if drift not in DRIFT_MODELS:
            raise ValueError(f"drift: {drift!r} is not one of {', '.join(DRIFT_MODELS)}")
        self.drift = drift  # odometry drift model of every avatar (haa.sim.avatars, docs/sim.md)
        self.arena = arena
        self.seed = int(seed)
        self.physics_dt = physics_dt
        self.time = 0.0
        self.space = pymunk.Space()
        self.space.gravity = (0, 0)
        self.space.iterations = 10
        self.space.collision_slop = 0.002
        self._solid_names: dict[pymunk.Shape, str] = {}  # static shape -> what an avatar bumps into
        for s in arena.structures:
            shape = pymunk.Poly(self.space.static_body, s.polygon)
            shape.friction = 0.0
            shape.elasticity = 0.0
            self.space.add(shape)
            self._solid_names[shape] = s.id
        self.avatars: dict[str, AvatarState] = {}
        self._by_shape: dict[pymunk.Shape, AvatarState] = {}
        self._begun: list[tuple[AvatarState, str]] = []  # contacts begun in the current physics step
        self.space.on_collision(_AVATAR_SHAPE, None, begin=self._contact_begins, separate=self._contact_ends)
        self._serial = 0
        self._per_kind: dict[str, int] = {}
        self._action_seq = 0
        self.events: deque[SimEvent] = deque(maxlen=max_events)
        self.collectables: dict[str, CollectableState] = {
            cid: CollectableState(cid, x, y, "floor") for cid, (x, y) in arena.collectables.items()
        }
        self._renderer: Renderer | None = None
        self._grids: dict[float, IdealGrid] = {}
        ms = arena.markers
        self._m_id = np.array([m.id for m in ms], dtype=int)
        self._m_xy = np.array([m.center for m in ms], dtype=float).reshape(-1, 2)
        self._m_n = np.array([m.normal for m in ms], dtype=float).reshape(-1, 2)
        entries = list(arena.spec.schedule) if schedule is None else list(schedule)
        self._schedule = sorted(entries, key=lambda e: e.at)  # stable: same-time entries keep file order
        self._next = 0
        self._apply_schedule()

    @classmethod
    def from_arena(cls, arena: str | Path | Arena, seed: int = 0, **kw: Any) -> World:
        """World from "small", "large", a YAML path, or an Arena (raises ArenaError on a bad file)."""
        return cls(arena if isinstance(arena, Arena) else load_arena(arena), seed=seed, **kw)

    # ------------------------------------------------------------------ avatars
    def _get(self, aid: str, active: bool = True) -> AvatarState:
        av = self.avatars.get(aid)
        if av is None:
            raise AvatarUnavailable(f"no avatar {aid!r}")
        if active and av.status != ACTIVE:
            raise AvatarUnavailable(f"avatar {aid!r} is {av.status}")
        return av

    def _bodies(self, exclude: str | None = None) -> list[AvatarState]:
        """Avatars that are physically in the arena (active or crashed)."""
        return [a for a in self.avatars.values() if a.status != RETIRED and a.id != exclude]

    def _pose_free(self, x: float, y: float, radius: float) -> bool:
        if self.arena.clearance(x, y) < radius:
            return False
        for a in self._bodies():
            ax, ay, _ = a.pose
            if math.hypot(ax - x, ay - y) < radius + a.spec.radius + _START_GAP:
                return False
        return True

    def free_start_pose(self, kind: str) -> tuple[float, float, float] | None:
        r = avatar_spec(kind).radius
        for p in self.arena.start_poses:
            if self._pose_free(p[0], p[1], r):
                return p
        return None

    def add_avatar(
        self, kind: str, pose: tuple[float, float, float] | int | None = None, avatar_id: str | None = None
    ) -> str:
        """Add an avatar of `kind` at `pose` (x, y, theta), at start pose number `pose`, or (None) at the
        first free start pose. Returns its id (`avatar_id`, or "<kind>-<n>"). Raises ValueError."""
        spec = avatar_spec(kind)
        if avatar_id is not None and avatar_id in self.avatars:
            raise ValueError(f"avatar id {avatar_id!r} is taken")
        if pose is None:
            p = self.free_start_pose(kind)
            if p is None:
                raise ValueError(f"no free start pose for a {kind} (all {len(self.arena.start_poses)} are occupied)")
        elif isinstance(pose, int):
            if not 0 <= pose < len(self.arena.start_poses):
                raise ValueError(f"pose: no start pose {pose} (the arena has {len(self.arena.start_poses)})")
            p = self.arena.start_poses[pose]
            if not self._pose_free(p[0], p[1], spec.radius):
                raise ValueError(f"pose: start pose {pose} is occupied")
        else:
            p = (float(pose[0]), float(pose[1]), float(pose[2]))
            if not self._pose_free(p[0], p[1], spec.radius):
                raise ValueError(f"pose: ({p[0]:.2f}, {p[1]:.2f}) is not free for a {kind} (radius {spec.radius} m)")
        if avatar_id is None:
            n = self._per_kind.get(kind, 0)
            while True:
                n += 1
                avatar_id = f"{kind}-{n}"
                if avatar_id not in self.avatars:
                    break
            self._per_kind[kind] = n
        self._serial += 1
        av = AvatarState(self, avatar_id, kind, self._serial, p)
        self.space.add(*av.parts())
        self.avatars[avatar_id] = av
        self._by_shape[av.shape] = av
        self.events.append(SimEvent(self.time, "joined", avatar_id, {"type": kind, "pose": p}))
        return avatar_id

    def retire(self, aid: str) -> None:
        """Graceful leave: the avatar drives out of the arena (removed); what it carries is put down."""
        av = self._get(aid)
        self._end_action(av, "retired")
        x, y, _ = av.pose
        for cid in av.carrying:
            c = self.collectables[cid]
            c.x, c.y, c.state, c.carrier = x, y, "floor", None
        av.carrying = []
        self.space.remove(*av.parts())
        av.status = RETIRED
        av.left = self.time
        self.events.append(SimEvent(self.time, "retired", aid, {"pose": (x, y, av.pose[2])}))

    def crash(self, aid: str) -> None:
        """The avatar stops answering and stays where it is (an obstacle), holding what it carries."""
        av = self._get(aid)
        self._end_action(av, "crashed")
        av.status = CRASHED
        av.left = self.time
        self.events.append(SimEvent(self.time, "crashed", aid, {"pose": av.pose}))

    def _end_action(self, av: AvatarState, reason: str) -> None:
        if av.action is not None and not av.action.done:
            av.action.finish(self, av, FAILED, reason)
        av.cmd_v = av.cmd_w = 0.0

    def set_velocity(self, aid: str, v: float, omega: float) -> None:
        """Commanded forward speed (m/s) and turn rate (rad/s), clipped to the type's limits; kept until
        changed. Pre-empts a running action."""
        av = self._get(aid)
        if av.action is not None and not av.action.done:
            av.action.finish(self, av, CANCELLED, "preempted")
        s = av.spec
        av.cmd_v = max(-s.max_speed, min(s.max_speed, float(v)))
        av.cmd_w = max(-s.max_turn, min(s.max_turn, float(omega)))

    # ------------------------------------------------------------------ actions
    def start_action(self, aid: str, action: Action) -> Action:
        """Start an action (haa.sim.actions) on the avatar; a running one is cancelled ("preempted")."""
        av = self._get(aid)
        if av.action is not None and not av.action.done:
            av.action.finish(self, av, CANCELLED, "preempted")
        self._action_seq += 1
        action.id = self._action_seq
        action.started = self.time
        av.action = action
        action.start(self, av)
        return action

    def action(self, aid: str) -> Action | None:
        """The avatar's current (or last) action."""
        return self._get(aid, active=False).action

    def cancel_action(self, aid: str) -> None:
        av = self._get(aid)
        if av.action is not None and not av.action.done:
            av.action.finish(self, av, CANCELLED, "cancelled")

    # ------------------------------------------------------------------ time
    def step(self, dt: float) -> None:
        """Advance simulated time by dt seconds (physics sub-steps of at most physics_dt)."""
        if not (dt >= 0) or not math.isfinite(dt):
            raise ValueError(f"dt: {dt} must be a finite number >= 0")
        end = self.time + dt
        while self.time < end - 1e-12:
            seg_end = end
            if self._next < len(self._schedule):
                seg_end = min(end, max(self.time, self._schedule[self._next].at))
            seg = seg_end - self.time
            if seg > 1e-12:
                n = max(1, math.ceil(seg / self.physics_dt - 1e-9))
                h = seg / n
                for _ in range(n):
                    self._substep(h)
            self.time = seg_end
            self._apply_schedule()
        self.time = round(end, 9)  # no drift from summing sub-steps: 30 steps of 0.1 s end at 3.0

    def _substep(self, h: float) -> None:
        avs = [a for a in self.avatars.values() if a.status != RETIRED]
        for av in avs:
            if av.status == ACTIVE:
                if av.action is not None and not av.action.done:
                    av.action.update(self, av, h)
                v, w = av.cmd_v, av.cmd_w
            else:
                v = w = 0.0
            b = av.body
            th = b.angle
            c = av.control
            c.position = b.position
            c.angle = th
            # along the chord of the arc the avatar drives next, as a differential drive moves and as the
            # odometry integrates it (the mid heading). Chipmunk moves bodies *before* it solves the joints, so
            # the velocity solved now moves the avatar in the next sub-step, from th + w h to th + 2 w h: its mid
            # heading is th + 1.5 w h. With the start heading the avatar slid sideways by v h (w h) on every
            # sub-step of a turn, unseen by the wheels (0.3 m of dead-reckoning error per seeker in 176 s)
            mid = th + 1.5 * w * h
            c.velocity = (v * math.cos(mid), v * math.sin(mid))
            c.angular_velocity = w
        self.space.step(h)
        self.time += h
        for av in avs:
            p = av.body.position
            x, y, a = float(p.x), float(p.y), float(av.body.angle)
            px, py, pa = av.prev
            dth = a - pa
            mid = pa + 0.5 * dth
            ds = (x - px) * math.cos(mid) + (y - py) * math.sin(mid)
            av.prev = (x, y, a)
            av.last_speed = abs(ds) / h
            if av.status == ACTIVE:
                av.odo.update(ds, dth)
        for av, what in self._begun:
            if av.status == ACTIVE:
                av.bumps += 1
                self.events.append(SimEvent(self.time, "bump", av.id, {"with": what, "pose": av.pose}))
        self._begun.clear()

    def _contact_begins(self, arb: pymunk.Arbiter, _space: pymunk.Space, _data: Any) -> None:
        """Chipmunk's begin callback for an avatar's shape: a "bump" for each avatar in the contact (after
        the step, `_substep`) — a push its wheels do not see (its odometry misses the slide), so a control
        system that bumps loses track of where it is."""
        a, b = arb.shapes
        for me, other in ((a, b), (b, a)):
            av = self._by_shape.get(me)
            if av is not None:
                av.contacts += 1
                o = self._by_shape.get(other)
                self._begun.append((av, f"avatar {o.id}" if o is not None else self._solid_names.get(other, "?")))

    def _contact_ends(self, arb: pymunk.Arbiter, _space: pymunk.Space, _data: Any) -> None:
        for sh in arb.shapes:
            av = self._by_shape.get(sh)
            if av is not None:
                av.contacts = max(0, av.contacts - 1)

    def _apply_schedule(self) -> None:
        while self._next < len(self._schedule) and self._schedule[self._next].at <= self.time + 1e-12:
            e = self._schedule[self._next]
            self._next += 1
            try:
                if e.join is not None:
                    self.add_avatar(e.join.type, e.join.start, e.join.id)
                elif e.retire is not None:
                    self.retire(e.retire)
                elif e.crash is not None:
                    self.crash(e.crash)
            except (ValueError, AvatarUnavailable) as err:
                self.events.append(SimEvent(self.time, "schedule", "", {"error": str(err), "entry": e.kind}))

    def drain_events(self) -> list[SimEvent]:
        out = list(self.events)
        self.events.clear()
        return out

    # ------------------------------------------------------------------ state
    def true_pose(self, aid: str) -> tuple[float, float, float]:
        return self._get(aid, active=False).pose

    def odometry(self, aid: str) -> tuple[float, float, float]:
        return self._get(aid).odo.pose

    def status(self, aid: str) -> str:
        return self._get(aid, active=False).status

    def _occluders(self, exclude: str) -> tuple[np.ndarray, np.ndarray]:
        bodies = self._bodies(exclude)
        if not bodies:
            return np.zeros((0, 2)), np.zeros(0)
        xy = np.array([[a.body.position.x, a.body.position.y] for a in bodies])
        return xy, np.array([a.spec.radius for a in bodies])

    # ------------------------------------------------------------------ sensors
    def sonar(self, aid: str) -> list[SonarReading]:
        """One reading of each of the avatar's sonars (none for types without sonar); see haa.sim.sensors."""
        av = self._get(aid)
        if av.spec.sonars == 0:
            return []
        x, y, th = av.pose
        offs = np.linspace(-SONAR_FOV / 2, SONAR_FOV / 2, SONAR_RAYS)
        bear = np.asarray(SONAR_BEARINGS[: av.spec.sonars])
        ang = th + (bear[:, None] + offs[None, :]).ravel()
        dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        e = self.arena.edges
        t, _, _ = cast_segments(x, y, dirs, e.a, e.b, SONAR_RANGE)
        oxy, orr = self._occluders(aid)
        if len(orr):
            tc, _ = cast_circles(x, y, dirs, oxy, orr, SONAR_RANGE)
            t = np.minimum(t, tc)
        d = t.reshape(len(bear), SONAR_RAYS).min(axis=1)
        out = []
        for b, di in zip(bear.tolist(), d.tolist(), strict=True):
            if di <= SONAR_RANGE:
                r = max(0.0, di + SONAR_SIGMA * di * av.sonar_noise())
                out.append(SonarReading(b, r, time=self.time))
            else:
                out.append(SonarReading(b, None, time=self.time))
        return out

    def visible_markers(self, aid: str, max_incidence: float = MAX_INCIDENCE) -> list[tuple[int, int, float]]:
        """True (noise-free) visibility: [(marker index, landmark id, distance to the marker centre)] of every
        marker within the camera's range and field of view, facing it within `max_incidence`, unoccluded."""
        av = self._get(aid, active=False)
        cam = av.camera
        x, y, th = av.pose
        if len(self._m_id) == 0:
            return []
        v = self._m_xy - np.array([x, y])
        d = np.hypot(v[:, 0], v[:, 1])
        bearing = np.arctan2(v[:, 1], v[:, 0]) - th
        bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
        facing = -(v[:, 0] * self._m_n[:, 0] + v[:, 1] * self._m_n[:, 1]) / np.maximum(d, 1e-9)
        ok = (d <= cam.max_range) & (np.abs(bearing) <= cam.fov / 2) & (facing >= math.cos(max_incidence))
        cand = np.nonzero(ok)[0]
        if len(cand) == 0:
            return []
        dirs = v[cand] / d[cand, None]
        e = self.arena.edges
        t, _, _ = cast_segments(x, y, dirs, e.a, e.b)
        ok = t >= d[cand] - 0.01
        oxy, orr = self._occluders(aid)
        if len(orr):
            tc, _ = cast_circles(x, y, dirs, oxy, orr)
            ok &= tc >= d[cand]
        return [(int(i), int(self._m_id[i]), float(d[i])) for i in cand[ok]]

    def landmark_observations(self, aid: str) -> list[LandmarkObservation]:
        """The camera's detected landmarks (within FOV/range, facing it, in line of sight), with noise
        sigma 0.09 x range on the range and BEARING_SIGMA on the bearing; sorted by landmark id."""
        av = self._get(aid)
        x, y, th = av.pose
        ids = sorted({lid for _, lid, _ in self.visible_markers(aid)})
        out = []
        for lid in ids:
            lx, ly = self.arena.landmarks[lid]
            r = math.hypot(lx - x, ly - y)
            b = wrap_angle(math.atan2(ly - y, lx - x) - th)
            rn = max(0.0, r + av.camera.sigma * r * av.camera_noise())
            bn = wrap_angle(b + BEARING_SIGMA * av.camera_noise())
            out.append(LandmarkObservation(lid, rn, bn, self.time))
        return out

    def collectable_observations(self, aid: str) -> list[CollectableObservation]:
        """Collectables on the floor the camera sees (range, FOV, line of sight), same noise as landmarks."""
        av = self._get(aid)
        cam = av.camera
        x, y, th = av.pose
        cands = []
        for c in self.collectables.values():
            if c.state != "floor":
                continue
            r = math.hypot(c.x - x, c.y - y)
            b = wrap_angle(math.atan2(c.y - y, c.x - x) - th)
            if r <= cam.max_range and abs(b) <= cam.fov / 2 and r > 1e-6:
                cands.append((c, r, b))
        if not cands:
            return []
        dirs = np.array([[math.cos(th + b), math.sin(th + b)] for _, _, b in cands])
        rr = np.array([r for _, r, _ in cands])
        e = self.arena.edges
        t, _, _ = cast_segments(x, y, dirs, e.a, e.b)
        ok = t >= rr
        oxy, orr = self._occluders(aid)
        if len(orr):
            tc, _ = cast_circles(x, y, dirs, oxy, orr)
            ok &= tc >= rr - COLLECTABLE_RADIUS
        out = []
        for (c, r, b), good in zip(cands, ok.tolist(), strict=True):
            if good:
                rn = max(0.0, r + cam.sigma * r * av.camera_noise())
                bn = wrap_angle(b + BEARING_SIGMA * av.camera_noise())
                out.append(CollectableObservation(c.id, rn, bn, self.time))
        out.sort(key=lambda o: o.collectable_id)
        return out

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.arena, self.seed)
        return self._renderer

    def scene_objects(self, exclude: str | None = None) -> np.ndarray:
        """Short cylinders the camera draws: (x, y, radius, height, label) of other avatars and collectables."""
        rows = [
            (a.body.position.x, a.body.position.y, a.spec.radius, a.spec.height, LABEL_AVATAR)
            for a in self._bodies(exclude)
        ]
        rows += [
            (c.x, c.y, COLLECTABLE_RADIUS, COLLECTABLE_HEIGHT, LABEL_COLLECTABLE)
            for c in self.collectables.values()
            if c.state == "floor"
        ]
        return np.array(rows, dtype=float).reshape(-1, 5)

    def capture(self, aid: str, labels: bool = False) -> CameraFrame:
        """Render what the avatar's camera sees now (haa.sim.camera); `labels` adds a per-pixel label image."""
        av = self._get(aid)
        cam = av.camera
        pose = av.pose
        r = self.renderer
        oy = int(av.image_rng.integers(0, r.noise.shape[0] - cam.height + 1))
        ox = int(av.image_rng.integers(0, r.noise.shape[1] - cam.width + 1))
        img, lab = r.render(pose, cam, self.scene_objects(aid), (oy, ox), labels)
        return CameraFrame(
            image=img,
            camera=cam.name,
            K=intrinsics(cam),
            fov=cam.fov,
            max_range=cam.max_range,
            mount=(0.0, 0.0, CAMERA_HEIGHT, 0.0),
            time=self.time,
            avatar=aid,
            pose=pose,
            odometry=av.odo.pose,
            labels=lab,
        )

    # ------------------------------------------------------------------ collectables
    def _collectable_xy(self, c: CollectableState) -> tuple[float, float]:
        if c.state == "carried" and c.carrier is not None:
            x, y, _ = self.avatars[c.carrier].pose
            return (x, y)
        return (c.x, c.y)

    def collectable_states(self) -> list[CollectableState]:
        """Ground truth of every collectable (a carried one is where its carrier is)."""
        out = []
        for c in self.collectables.values():
            x, y = self._collectable_xy(c)
            out.append(CollectableState(c.id, x, y, c.state, c.carrier, c.region))
        return out

    def pick_up(self, aid: str, cid: str | None = None) -> tuple[bool, str]:
        """(True, collectable id) or (False, reason: capacity_full | out_of_reach)."""
        av = self._get(aid)
        if len(av.carrying) >= av.spec.capacity:
            return False, "capacity_full"
        x, y, _ = av.pose
        reach = av.spec.radius + REACH + COLLECTABLE_RADIUS
        best, best_d = None, math.inf
        for c in self.collectables.values():
            if c.state != "floor" or (cid is not None and c.id != cid):
                continue
            d = math.hypot(c.x - x, c.y - y)
            if d <= reach and d < best_d:
                best, best_d = c, d
        if best is None:
            return False, "out_of_reach"
        best.state, best.carrier = "carried", aid
        av.carrying.append(best.id)
        self.events.append(SimEvent(self.time, "picked", aid, {"collectable": best.id}))
        return True, best.id

    def drop(self, aid: str, cid: str | None = None) -> tuple[bool, str, str | None]:
        """(True, collectable id, region or None) or (False, reason: nothing_carried, None)."""
        av = self._get(aid)
        if not av.carrying or (cid is not None and cid not in av.carrying):
            return False, "nothing_carried", None
        cid = cid if cid is not None else av.carrying[-1]
        av.carrying.remove(cid)
        x, y, th = av.pose
        d = av.spec.radius + COLLECTABLE_RADIUS + 0.01
        px, py = x + d * math.cos(th), y + d * math.sin(th)
        if self.arena.clearance(px, py) < COLLECTABLE_RADIUS:
            px, py = x, y
        c = self.collectables[cid]
        c.x, c.y, c.carrier = px, py, None
        region = next((rid for rid, poly in self.arena.regions.items() if point_in_polygon(px, py, poly)), None)
        if region is not None:
            c.state, c.region = "deposited", region
            self.events.append(SimEvent(self.time, "deposited", aid, {"collectable": cid, "region": region}))
        else:
            c.state = "floor"
            self.events.append(SimEvent(self.time, "dropped", aid, {"collectable": cid}))
        return True, cid, region

    # ------------------------------------------------------------------ ground truth
    def ideal_grid(self, resolution: float) -> IdealGrid:
        """(grid, origin, resolution): the ideal occupancy grid, 1 occupied / 0 free (haa.sim.groundtruth)."""
        key = float(resolution)
        if key not in self._grids:
            if len(self._grids) >= 8:
                self._grids.clear()
            self._grids[key] = ideal_grid(self.arena, key)
        return self._grids[key]

    def explorable_grid(self, resolution: float) -> IdealGrid:
        """1 for free cells reachable from the start poses (the thesis' "reachable cells")."""
        return explorable_grid(self.arena, resolution)
