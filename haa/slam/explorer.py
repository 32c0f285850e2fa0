"""Record exploration runs from the haa.sim world for the offline SLAM experiments (AP-5.1, AP-5.2).

The three teams of Table 7.2-1:

| scenario   | team       | arena                | thesis mission time |
|------------|------------|----------------------|---------------------|
| basic      | 4 seekers  | small (3.4 × 7.2 m)  | 2:56                |
| advanced_a | 4 sweepers | large (18 × 18 m)    | 27:05               |
| advanced_b | 8 sweepers | large (18 × 18 m)    | 15:22               |

The driver is *not* the control system: it is a simple frontier-ish explorer that uses the simulator's
**true map and true poses** (the issue allows it for recording): every avatar heads for the nearest cell of
the reachable area that no avatar has passed within `SEEN_RADIUS` yet and that no other avatar is heading
for, along a breadth-first path on the reachable cells that no solid touches (thin panels fall out of the
50 % ideal grid) shrunk by the avatar's radius (the grid's edge counts as wall), steering with a
proportional heading controller at half its top speed; it waits for an avatar ahead and, held up, plans a
way around it; when it stalls it picks another goal. It never scrapes a wall or bumps into an avatar: a
push the wheels do not see would put an error into the odometry that no drift model states (docs/sim.md). The SLAM
system never sees any of this — it gets only what an avatar agent would send: predictions from the wheel
odometry (`haa.slam.motion.odometry_prediction`, the avatar type's drift spec), and sensor readings.

Sensors, each at its own random phase per avatar, once a second (Table 6.2-4 gives 1 s for the sonar; the
camera is "manual" in the thesis, we take an image a second): a sonar scan of the ring (sweepers), the
landmarks the camera detects (`World.landmark_observations`), and a co-occupancy reading (the avatar's
footprint). Predictions are sent every 0.25 s and at every sensor time. Camera floor regions are not
recorded (finding the floor in an image is the FloorFinder agent's job, not the simulator's).

`record(scenario, duration, seed)` returns a `Recording` (haa.slam.recording), with the true and odometry
poses at every prediction, the true landmark positions, the simulator's ideal grid and reachable-cell mask.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from haa.slam.grid import GridSpec
from haa.slam.motion import DriftSpec, odometry_prediction, wrap_angle
from haa.slam.recording import AvatarInfo, Recording, Track
from haa.slam.sensors import CooccupancyReading, LandmarkReading, Sighting, SonarEcho, SonarReading

SEEN_RADIUS = 1.0  # m: cells this close to an avatar's path count as visited by the driver
CRUISE = 0.5  # share of the avatar type's top speed
STOP_GAP = 0.25  # m between two avatars' edges: closer, with the other ahead, an avatar stops
BLOCKED_S = 1.5  # s stopped for another avatar before planning around it
AVOID_RADIUS = 0.5  # m around an avatar in the way that the plan around it keeps clear of


@dataclass(frozen=True)
class Scenario:
    key: str
    name: str
    arena: str
    kind: str
    count: int
    mission_s: float  # Table 7.2-1


SCENARIOS: dict[str, Scenario] = {
    "basic": Scenario("basic", "Basic", "small", "seeker", 4, 176.0),
    "advanced_a": Scenario("advanced_a", "Advanced A", "large", "sweeper", 4, 1625.0),
    "advanced_b": Scenario("advanced_b", "Advanced B", "large", "sweeper", 8, 922.0),
}


def scenario(key: str) -> Scenario:
    s = SCENARIOS.get(key)
    if s is None:
        raise ValueError(f"scenario: unknown {key!r} (known: {', '.join(SCENARIOS)})")
    return s


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """`mask` grown by k cells (4-neighbour steps); beyond the array counts as set (the arena's outer walls)."""
    out = np.pad(mask, k, constant_values=True)
    for _ in range(k):
        m = out.copy()
        m[1:, :] |= out[:-1, :]
        m[:-1, :] |= out[1:, :]
        m[:, 1:] |= out[:, :-1]
        m[:, :-1] |= out[:, 1:]
        out = m
    return out[k : out.shape[0] - k, k : out.shape[1] - k]


class Explorer:
    """Goal choice and path following for one team on the true map (see the module docstring)."""

    def __init__(self, free: np.ndarray, resolution: float, radius: float, rng: np.random.Generator) -> None:
        self.res = resolution
        self.free = free & ~_dilate(~free, math.ceil((radius + 0.04) / resolution))
        self.visited = np.zeros_like(free)
        self.rng = rng
        self.goals: dict[str, tuple[int, int]] = {}
        self.paths: dict[str, list[tuple[float, float]]] = {}
        self.check: dict[str, tuple[float, float, float]] = {}  # aid -> (t, x, y) of the last progress check
        self.blocked: dict[str, float] = {}  # aid -> since when an avatar is in its way
        r = math.ceil(SEEN_RADIUS / resolution)
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        self._disc = (xx**2 + yy**2) <= r * r
        self._r = r

    def cell(self, x: float, y: float) -> tuple[int, int]:
        rows, cols = self.free.shape
        return min(max(int(y / self.res), 0), rows - 1), min(max(int(x / self.res), 0), cols - 1)

    def mark(self, x: float, y: float) -> None:
        cy, cx = self.cell(x, y)
        r = self._r
        rows, cols = self.visited.shape
        y0, y1, x0, x1 = max(cy - r, 0), min(cy + r + 1, rows), max(cx - r, 0), min(cx + r + 1, cols)
        self.visited[y0:y1, x0:x1] |= self._disc[y0 - cy + r : y1 - cy + r, x0 - cx + r : x1 - cx + r]

    def plan(self, aid: str, x: float, y: float, avoid: tuple[tuple[float, float], ...] = ()) -> None:
        """BFS from the avatar to the nearest unvisited, unclaimed free cell; store the waypoints.

        `avoid`: positions of avatars in the way; the cells within AVOID_RADIUS of them are not entered."""
        start = self.cell(x, y)
        rows, cols = self.free.shape
        free = self.free
        if avoid:
            free = free.copy()
            k = math.ceil(AVOID_RADIUS / self.res)
            for ox, oy in avoid:
                oy_, ox_ = self.cell(ox, oy)
                free[max(oy_ - k, 0) : oy_ + k + 1, max(ox_ - k, 0) : ox_ + k + 1] = False
            free[start] = True
        if not self.free[start]:  # pushed into the inflated margin: search from the nearest free cell
            fy, fx = np.nonzero(self.free)
            k = int(np.argmin((fy - start[0]) ** 2 + (fx - start[1]) ** 2))
            start = (int(fy[k]), int(fx[k]))
        others = [g for a, g in self.goals.items() if a != aid]
        claim = (2 * SEEN_RADIUS / self.res) ** 2
        parent = {start: start}
        q = deque([start])
        goal = None
        while q:
            c = q.popleft()
            if not self.visited[c] and all((c[0] - g[0]) ** 2 + (c[1] - g[1]) ** 2 > claim for g in others):
                goal = c
                break
            for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                n = (c[0] + dy, c[1] + dx)
                if 0 <= n[0] < rows and 0 <= n[1] < cols and free[n] and n not in parent:
                    parent[n] = c
                    q.append(n)
        if goal is None:  # everything seen: wander to a random reachable cell
            cells = list(parent)
            goal = cells[int(self.rng.integers(len(cells)))]
        path = [goal]
        while path[-1] != start:
            path.append(parent[path[-1]])
        path.reverse()
        pts = [*path[:: max(1, round(0.3 / self.res))], goal]
        self.goals[aid] = goal
        self.paths[aid] = [((c[1] + 0.5) * self.res, (c[0] + 0.5) * self.res) for c in pts]

    def control(
        self,
        aid: str,
        t: float,
        pose: tuple[float, float, float],
        max_speed: float,
        max_turn: float,
        others: tuple[tuple[float, float], ...] = (),
        radius: float = 0.0,
    ) -> tuple[float, float]:
        """(v, omega) for one avatar; `others`: the other avatars' positions (it stops for one ahead of it
        and, held up for BLOCKED_S, plans a way around: bumping into avatars slides them sideways, which
        their wheel odometry never sees)."""
        x, y, th = pose
        self.mark(x, y)
        ahead = [
            (ox, oy) for ox, oy in others
            if math.hypot(ox - x, oy - y) < 2 * radius + STOP_GAP
            and abs(float(wrap_angle(math.atan2(oy - y, ox - x) - th))) < 1.2
        ]
        chk = self.check.get(aid)
        if chk is None or t - chk[0] > 3.0:
            stalled = chk is not None and math.hypot(x - chk[1], y - chk[2]) < 0.1
            self.check[aid] = (t, x, y)
            if stalled:
                g = self.goals.get(aid)
                if g is not None:
                    self.visited[g] = True
                self.paths.pop(aid, None)
        path = self.paths.get(aid)
        while path and math.hypot(path[0][0] - x, path[0][1] - y) < 0.25:
            path.pop(0)
        if not path:  # goal reached (or none yet): the next frontier goal
            self.plan(aid, x, y)
            path = self.paths[aid]
        if ahead:
            since = self.blocked.setdefault(aid, t)
            if t - since > BLOCKED_S:
                self.plan(aid, x, y, tuple(others))
                self.blocked[aid] = t
                path = self.paths[aid]
        else:
            self.blocked.pop(aid, None)
        tx, ty = path[0]
        err = float(wrap_angle(math.atan2(ty - y, tx - x) - th))
        omega = max(-0.6 * max_turn, min(0.6 * max_turn, 2.5 * err))
        v = CRUISE * max_speed * max(0.0, math.cos(err)) if abs(err) < 0.9 else 0.0
        if ahead and abs(err) < 1.2:
            v = 0.0  # turn towards the path but wait for the avatar ahead
        return v, omega


def _pool2(mask: np.ndarray) -> np.ndarray:
    """2×2 blocks that are entirely True (a coarser planning grid)."""
    r, c = mask.shape[0] // 2 * 2, mask.shape[1] // 2 * 2
    m = mask[:r, :c]
    return m[0::2, 0::2] & m[1::2, 0::2] & m[0::2, 1::2] & m[1::2, 1::2]


def record(
    key: str,
    duration: float,
    seed: int = 0,
    *,
    dt: float = 0.05,
    prediction_period: float = 0.25,
    sensor_period: float = 1.0,
    resolution: float = 0.1,
    drift: str = "thesis",
) -> Recording:
    """Drive the scenario's team for `duration` simulated seconds and record what SLAM would be given."""
    from haa.sim.avatars import avatar_spec
    from haa.sim.groundtruth import coverage
    from haa.sim.sensors import BEARING_SIGMA, CAMERAS
    from haa.sim.world import World

    sc = scenario(key)
    if not duration > 0:
        raise ValueError(f"duration: must be > 0 s, got {duration}")
    rng = np.random.default_rng(seed)
    w = World.from_arena(sc.arena, seed=seed, drift=drift)
    spec = avatar_spec(sc.kind)
    # the avatar states its drift (motion.DriftSpec): the random walk the drift model draws; the harsher
    # systematic model is not a random walk, so its σ's are widened 1.5x (docs/slam.md)
    lin, ang = spec.drift_figures(drift)
    drift_spec = DriftSpec(lin, ang, 1.5 if drift == "systematic" else 1.0)
    aids = [w.add_avatar(sc.kind) for _ in range(sc.count)]
    ideal = w.ideal_grid(resolution)
    reach = w.explorable_grid(resolution).grid.astype(bool)
    # plan on the cells no solid touches: the ideal grid's 50 % rule leaves out thin panels (4 cm in a 10 cm
    # cell), which the driver would otherwise push against (a sideways slide its wheels never see)
    clear = reach & (coverage(w.arena, resolution) == 0)
    explorer = Explorer(_pool2(clear), 2 * resolution, spec.radius, rng)  # plans on 2x coarser cells
    cam = CAMERAS[spec.camera]
    rec = Recording(
        arena=sc.arena,
        team=sc.name,
        seed=seed,
        grid=GridSpec(w.arena.width, w.arena.height, resolution, 0.0, 0.0),
        avatars=[AvatarInfo(a, sc.kind, w.true_pose(a), drift_spec, spec.radius) for a in aids],
        landmarks={int(k): (float(v[0]), float(v[1])) for k, v in w.arena.landmarks.items()},
        duration=duration,
        driver=f"frontier-ish explorer on the true map and poses at {CRUISE:g}× top speed (haa.slam.explorer)",
        landmark_range_frac=cam.sigma,
        landmark_sigma_bearing=BEARING_SIGMA,
        sonar_mount_radius=0.0,
        ideal_grid=ideal.grid.astype(np.float64),
        region=reach,
    )
    per_pred = max(1, round(prediction_period / dt))
    per_sensor = max(1, round(sensor_period / dt))
    phase = {a: rng.integers(0, per_sensor, size=3) for a in aids}  # sonar, camera, co-occupancy
    last = {a: (0.0, w.odometry(a)) for a in aids}
    for a in aids:
        rec.truth[a] = Track()
        rec.odometry[a] = Track()
        rec.truth[a].add(0.0, w.true_pose(a))
        rec.odometry[a].add(0.0, w.odometry(a))
    steps = round(duration / dt)
    for step in range(1, steps + 1):
        poses = {a: w.true_pose(a) for a in aids}
        for a in aids:
            others = tuple((p[0], p[1]) for b, p in poses.items() if b != a)
            v, om = explorer.control(a, w.time, poses[a], spec.max_speed, spec.max_turn, others, spec.radius)
            w.set_velocity(a, v, om)
        w.step(dt)
        t = round(step * dt, 9)
        for a in aids:
            ph = phase[a]
            sonar = spec.sonars > 0 and (step - ph[0]) % per_sensor == 0
            camera = (step - ph[1]) % per_sensor == 0
            coocc = (step - ph[2]) % per_sensor == 0
            if step % per_pred and not (sonar or camera or coocc):
                continue
            odo = w.odometry(a)
            t0, odo0 = last[a]
            rec.predictions.append((a, odometry_prediction(t0, odo0, t, odo, drift_spec)))
            last[a] = (t, odo)
            rec.truth[a].add(t, w.true_pose(a))
            rec.odometry[a].add(t, odo)
            if sonar:
                scan = w.sonar(a)
                # the simulator's noise can push an echo just past max_range: clamp it to the sensor's limit
                echoes = tuple(
                    SonarEcho(s.bearing, None if s.range is None else min(s.range, s.max_range)) for s in scan
                )
                rec.readings.append(SonarReading(a, t, echoes, scan[0].fov, scan[0].max_range))
            if camera:
                obs = w.landmark_observations(a)
                rec.readings.append(
                    LandmarkReading(
                        a, t, tuple(Sighting(o.landmark_id, o.range, o.bearing) for o in obs if o.range > 0)
                    )
                )
            if coocc:
                rec.readings.append(CooccupancyReading(a, t, spec.radius))
    return rec


def explored_by_driver(rec: Recording) -> float:
    """Share of the reachable cells the driver's avatars passed within SEEN_RADIUS (a coverage check)."""
    if rec.region is None:
        return math.nan
    ex = Explorer(rec.region, rec.grid.resolution, 0.0, np.random.default_rng(0))
    for tr in rec.truth.values():
        for x, y, _ in tr.poses:
            ex.mark(x, y)
    return float((ex.visited & rec.region).sum() / max(int(rec.region.sum()), 1))
