"""The action interface of AvatarBase (thesis Appendix III): wait, move, rotate, capture image, pick up, drop.

Every avatar runs at most one action. Starting a new one pre-empts the running one (it ends `cancelled`,
reason `preempted`), as a path planner re-planning expects. An action reports `progress` (0..1) while it
runs and ends `succeeded`, `failed` (with a reason) or `cancelled`. The controllers steer with the
avatar's *odometry* — what the robot believes — never with its true pose: targets of `MoveTo` and an
absolute `Rotate` are in the odometry frame (which starts at the avatar's true start pose).

Failure reasons: `blocked` (a move made less than a quarter of the commanded progress for `BLOCKED_AFTER`
seconds: a wall, an obstacle or another avatar is in the way), `timeout`, `out_of_reach` (no free
collectable within `REACH` of the avatar's rim), `capacity_full` (carrying its capacity already; seekers
carry nothing), `nothing_carried`, `retired`, `crashed`, `cancelled`/`preempted`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from haa.sim.geometry import wrap_angle

if TYPE_CHECKING:
    from haa.sim.avatars import AvatarSpec, Odometry
    from haa.sim.camera import CameraFrame


class ActionWorld(Protocol):
    """What an action needs of the world that runs it (haa.sim.world.World): its time, and the three
    operations of the non-moving actions."""

    time: float

    def capture(self, aid: str, labels: bool = False) -> CameraFrame: ...

    def pick_up(self, aid: str, cid: str | None = None) -> tuple[bool, str]: ...

    def drop(self, aid: str, cid: str | None = None) -> tuple[bool, str, str | None]: ...


class ActionAvatar(Protocol):
    """What an action needs of the avatar it steers (haa.sim.world.AvatarState): its id, type figures, odometry
    (the controllers steer with what the robot believes), the commanded velocities and the measured speed."""

    id: str
    spec: AvatarSpec
    odo: Odometry
    cmd_v: float
    cmd_w: float
    last_speed: float

RUNNING, SUCCEEDED, FAILED, CANCELLED = "running", "succeeded", "failed", "cancelled"
BLOCKED_AFTER = 0.5  # s
REACH = 0.15  # m beyond the avatar's radius
POS_TOL = 0.05  # m
ANG_TOL = 0.02  # rad


@dataclass
class Action:
    """Base class: subclasses implement `start` and `update` (called every physics step)."""

    kind: str = field(init=False, default="action")
    id: int = field(init=False, default=0)
    status: str = field(init=False, default=RUNNING)
    progress: float = field(init=False, default=0.0)
    reason: str = field(init=False, default="")
    started: float = field(init=False, default=0.0)
    finished: float | None = field(init=False, default=None)
    result: dict[str, Any] = field(init=False, default_factory=dict)

    @property
    def done(self) -> bool:
        return self.status != RUNNING

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        pass

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        pass

    def finish(self, world: ActionWorld, av: ActionAvatar, status: str, reason: str = "") -> None:
        if self.done:
            return
        self.status = status
        self.reason = reason
        self.finished = world.time
        if status == SUCCEEDED:
            self.progress = 1.0
        av.cmd_v = av.cmd_w = 0.0


def _clip(x: float, lim: float) -> float:
    return max(-lim, min(lim, x))


class _Motion(Action):
    """Shared stall (blocked) detection and timeout for the moving actions."""

    _stall: float = 0.0
    _deadline: float = math.inf

    def check_stall(self, world: ActionWorld, av: ActionAvatar, h: float) -> bool:
        want = abs(av.cmd_v)
        if want > 0.05 and av.last_speed < 0.25 * want:
            self._stall += h
            if self._stall >= BLOCKED_AFTER:
                self.finish(world, av, FAILED, "blocked")
                return True
        else:
            self._stall = 0.0
        if world.time >= self._deadline:
            self.finish(world, av, FAILED, "timeout")
            return True
        return False


@dataclass
class Wait(_Motion):
    duration: float = 0.0

    def __post_init__(self) -> None:
        self.kind = "wait"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        av.cmd_v = av.cmd_w = 0.0
        if self.duration <= 0:
            self.finish(world, av, SUCCEEDED)

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        av.cmd_v = av.cmd_w = 0.0
        el = world.time - self.started
        self.progress = min(1.0, el / self.duration)
        if el >= self.duration - 1e-9:
            self.finish(world, av, SUCCEEDED)


@dataclass
class Velocity(_Motion):
    """Drive at (v, omega), clipped to the type's limits, for `duration` seconds (inf: until pre-empted)."""

    v: float = 0.0
    omega: float = 0.0
    duration: float = math.inf

    def __post_init__(self) -> None:
        self.kind = "velocity"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        if self.duration <= 0:
            self.finish(world, av, SUCCEEDED)

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        av.cmd_v = _clip(self.v, av.spec.max_speed)
        av.cmd_w = _clip(self.omega, av.spec.max_turn)
        el = world.time - self.started
        if math.isfinite(self.duration):
            self.progress = min(1.0, el / self.duration)
        if el >= self.duration - 1e-9:
            self.finish(world, av, SUCCEEDED)
            return
        self.check_stall(world, av, h)


@dataclass
class Rotate(_Motion):
    """Turn in place by `angle` (relative) or to heading `angle` (absolute, odometry frame)."""

    angle: float = 0.0
    relative: bool = True
    speed: float | None = None
    _total: float = field(init=False, default=0.0)

    def __post_init__(self) -> None:
        self.kind = "rotate"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        th = av.odo.theta
        self._unwrapped = 0.0  # rotation done so far (odometry), rad
        self._last = th
        self._total = self.angle if self.relative else wrap_angle(self.angle - th)
        wmax = min(self.speed or av.spec.max_turn, av.spec.max_turn)
        self._deadline = world.time + abs(self._total) / wmax * 3 + 5.0
        if abs(self._total) < ANG_TOL:
            self.finish(world, av, SUCCEEDED)

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        th = av.odo.theta
        self._unwrapped += wrap_angle(th - self._last)
        self._last = th
        rem = self._total - self._unwrapped
        self.progress = max(0.0, min(1.0, 1 - abs(rem) / abs(self._total)))
        if abs(rem) < ANG_TOL:
            self.finish(world, av, SUCCEEDED)
            return
        wmax = min(self.speed or av.spec.max_turn, av.spec.max_turn)
        w = _clip(3.0 * rem, wmax)
        if abs(w) < 0.15:
            w = math.copysign(0.15, rem)
        av.cmd_v, av.cmd_w = 0.0, w
        if world.time >= self._deadline:
            self.finish(world, av, FAILED, "timeout")


@dataclass
class MoveTo(_Motion):
    """Go to (x, y) of the odometry frame, then turn to `theta` if given."""

    x: float = 0.0
    y: float = 0.0
    theta: float | None = None
    speed: float | None = None
    tolerance: float = POS_TOL
    _d0: float = field(init=False, default=0.0)
    _turning: Rotate | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.kind = "move_to"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        ox, oy, _ = av.odo.pose
        self._d0 = math.hypot(self.x - ox, self.y - oy)
        vmax = min(self.speed or av.spec.max_speed, av.spec.max_speed)
        self._deadline = world.time + (self._d0 / vmax + 2 * math.pi / av.spec.max_turn) * 3 + 5.0

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        if self._turning is not None:
            self._turning.update(world, av, h)
            if self._turning.done:
                self.finish(world, av, self._turning.status, self._turning.reason)
            return
        ox, oy, oth = av.odo.pose
        dx, dy = self.x - ox, self.y - oy
        dist = math.hypot(dx, dy)
        self.progress = 0.0 if self._d0 <= 0 else max(0.0, min(0.99, 1 - dist / self._d0))
        if dist <= self.tolerance:
            if self.theta is None:
                self.finish(world, av, SUCCEEDED)
            else:
                self._turning = Rotate(self.theta, relative=False)
                self._turning.started = world.time
                self._turning.start(world, av)
                if self._turning.done:
                    self.finish(world, av, SUCCEEDED)
            return
        err = wrap_angle(math.atan2(dy, dx) - oth)
        vmax = min(self.speed or av.spec.max_speed, av.spec.max_speed)
        if abs(err) > 0.5:
            av.cmd_v = 0.0
        else:
            av.cmd_v = min(vmax, 1.5 * dist + 0.05) * math.cos(err)
        av.cmd_w = _clip(2.5 * err, av.spec.max_turn)
        self.check_stall(world, av, h)


@dataclass
class MoveBy(_Motion):
    """Drive straight by `distance` metres (negative: backwards), measured by odometry, holding the heading."""

    distance: float = 0.0
    speed: float | None = None

    def __post_init__(self) -> None:
        self.kind = "move_by"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        self._x0, self._y0, self._th0 = av.odo.pose
        vmax = min(self.speed or av.spec.max_speed, av.spec.max_speed)
        self._deadline = world.time + abs(self.distance) / vmax * 3 + 5.0
        if abs(self.distance) < POS_TOL / 5:
            self.finish(world, av, SUCCEEDED)

    def update(self, world: ActionWorld, av: ActionAvatar, h: float) -> None:
        ox, oy, oth = av.odo.pose
        c, s = math.cos(self._th0), math.sin(self._th0)
        along = (ox - self._x0) * c + (oy - self._y0) * s
        rem = self.distance - along
        self.progress = max(0.0, min(1.0, along / self.distance))
        if abs(rem) < POS_TOL / 5 or (rem * self.distance) < 0:
            self.finish(world, av, SUCCEEDED)
            return
        vmax = min(self.speed or av.spec.max_speed, av.spec.max_speed)
        av.cmd_v = math.copysign(min(vmax, 1.5 * abs(rem) + 0.05), rem)
        av.cmd_w = _clip(2.5 * wrap_angle(self._th0 - oth), av.spec.max_turn)
        self.check_stall(world, av, h)


@dataclass
class Capture(Action):
    """Take a camera frame now; `result["frame"]` is the CameraFrame."""

    def __post_init__(self) -> None:
        self.kind = "capture"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        self.result["frame"] = world.capture(av.id)
        self.finish(world, av, SUCCEEDED)


@dataclass
class PickUp(Action):
    """Pick up collectable `collectable` (or the nearest one) within reach; `result["collectable"]`."""

    collectable: str | None = None

    def __post_init__(self) -> None:
        self.kind = "pick_up"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        ok, what = world.pick_up(av.id, self.collectable)
        if ok:
            self.result["collectable"] = what
            self.finish(world, av, SUCCEEDED)
        else:
            self.finish(world, av, FAILED, what)


@dataclass
class Drop(Action):
    """Put down what the avatar carries (the last one picked); deposited when it lands in a collection region."""

    collectable: str | None = None

    def __post_init__(self) -> None:
        self.kind = "drop"

    def start(self, world: ActionWorld, av: ActionAvatar) -> None:
        ok, what, region = world.drop(av.id, self.collectable)
        if ok:
            self.result["collectable"] = what
            self.result["region"] = region
            self.finish(world, av, SUCCEEDED)
        else:
            self.finish(world, av, FAILED, what)


ACTION_KINDS = {
    "wait": Wait,
    "velocity": Velocity,
    "rotate": Rotate,
    "move_to": MoveTo,
    "move_by": MoveBy,
    "capture": Capture,
    "pick_up": PickUp,
    "drop": Drop,
}
