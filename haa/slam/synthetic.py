"""Synthetic recordings from a known trajectory — for tests, `bench slam` and `bench ap5.2` without haa.sim.

A rectangular room with box obstacles (line segments), landmarks on the walls, and avatars that drive a
closed loop of waypoints at constant speed. Odometry is the true motion with random-walk drift of the
avatar type (Table 6.2-3); sensors follow Table 6.2-4: five sonars (±90°, ±45°, 0°, 0.349 rad cone, 2 m,
σ = 3% of the range, one ray on the axis), a camera seeing landmarks within its field of view and range
with line of sight (σ_range = 9% of the range, σ_bearing = `sigma_bearing`), and a co-occupancy reading per
second; each sensor fires once a second (a sonar scan, a camera image, a co-occupancy reading) at its own
random phase.
Everything is drawn from one seed.

This is a stand-in for the simulator of the haa-sim issue (AP-5.1 uses that one, via haa.slam.explorer);
it is deliberately simple and shares no code with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from haa.slam.grid import GridSpec
from haa.slam.motion import DRIFT, odometry_prediction, wrap_angle
from haa.slam.recording import AvatarInfo, Recording, Track
from haa.slam.sensors import CooccupancyReading, LandmarkReading, Sighting, SonarEcho, SonarReading

SONAR_BEARINGS = (-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4, math.pi / 2)


@dataclass
class Room:
    width: float
    height: float
    segments: np.ndarray  # (M, 4) x0, y0, x1, y1
    landmarks: dict[int, tuple[float, float]]


def _box(cx: float, cy: float, w: float, h: float) -> list[tuple[float, float, float, float]]:
    x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - h / 2, cy + h / 2
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def room(width: float = 6.0, height: float = 4.0, boxes: int = 2, landmarks_per_wall: int = 4, seed: int = 0) -> Room:
    rng = np.random.default_rng(seed)
    segs = _box(width / 2, height / 2, width, height)
    for k in range(boxes):
        cx = width * (k + 1) / (boxes + 1)
        segs += _box(cx, height / 2 + (0.3 if k % 2 else -0.3), 0.5, 0.4)
    lms: dict[int, tuple[float, float]] = {}
    i = 0
    for j in range(landmarks_per_wall):
        f = (j + 0.5 + 0.3 * rng.uniform(-1, 1)) / landmarks_per_wall
        for pos in ((f * width, 0.0), (f * width, height), (0.0, f * height), (width, f * height)):
            lms[i] = pos
            i += 1
    return Room(width, height, np.asarray(segs, dtype=np.float64), lms)


def raycast(room: Room, x: float, y: float, ang: float, max_range: float) -> float | None:
    """Distance along the ray to the nearest segment, None beyond max_range."""
    s = room.segments
    dx, dy = math.cos(ang), math.sin(ang)
    ex, ey = s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((s[:, 0] - x) * ey - (s[:, 1] - y) * ex) / den
        u = ((s[:, 0] - x) * dy - (s[:, 1] - y) * dx) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (u >= 0) & (u <= 1)
    if not ok.any():
        return None
    d = float(t[ok].min())
    return d if d <= max_range else None


def _waypoints(room: Room, i: int, n: int) -> list[tuple[float, float]]:
    m = 0.5 + 0.25 * (i % 3)
    w, h = room.width, room.height
    pts = [(m, m), (w - m, m), (w - m, h - m), (m, h - m)]
    k = i % 4
    pts = pts[k:] + pts[:k]
    return pts if i % 2 == 0 else pts[::-1]


def synthetic_recording(
    avatars: int = 2,
    kind: str = "sweeper",
    duration: float = 60.0,
    seed: int = 0,
    dt: float = 0.05,
    prediction_period: float = 0.25,
    camera_period: float = 1.0,
    sonar_period: float = 1.0,
    speed: float = 0.3,
    sigma_bearing: float = 0.03,
    resolution: float = 0.1,
    width: float = 6.0,
    height: float = 4.0,
) -> Recording:
    """A recording of `avatars` avatars of `kind` looping in a synthetic room for `duration` seconds."""
    if kind not in DRIFT:
        raise ValueError(f"kind: unknown avatar type {kind!r} (known: {', '.join(DRIFT)})")
    rng = np.random.default_rng(seed)
    rm = room(width, height, seed=seed)
    spec = DRIFT[kind]
    rec = Recording(
        arena=f"synthetic {width}x{height}",
        team=f"{avatars} {kind}s",
        seed=seed,
        grid=GridSpec(width + 1.0, height + 1.0, resolution, -0.5, -0.5),
        avatars=[],
        landmarks=dict(rm.landmarks),
        duration=duration,
        driver="synthetic waypoint loop (haa.slam.synthetic)",
        landmark_range_frac=0.09,
        landmark_sigma_bearing=sigma_bearing,
    )
    steps_per_pred = round(prediction_period / dt)
    cam_every = max(1, round(camera_period / dt))
    sonar_every = max(1, round(sonar_period / dt))
    for i in range(avatars):
        name = f"a{i + 1}"
        wps = _waypoints(rm, i, avatars)
        x, y = wps[0]
        th = math.atan2(wps[1][1] - y, wps[1][0] - x)
        pose = (x, y, th)
        rec.avatars.append(AvatarInfo(name, kind, pose, spec))
        rec.truth[name] = Track()
        rec.odometry[name] = Track()
        odo = pose
        odo_prev, t_prev = odo, 0.0
        rec.truth[name].add(0.0, pose)
        rec.odometry[name].add(0.0, odo)
        wp = 1
        phase = rng.integers(0, [sonar_every, cam_every, sonar_every])  # each sensor's own firing phase, in steps
        lin_k = spec.linear_m_per_10m / math.sqrt(10.0)
        ang_k = spec.angular_rad_per_10rot / math.sqrt(10 * 2 * math.pi)
        for step in range(1, round(duration / dt) + 1):
            t = round(step * dt, 9)
            tx, ty = wps[wp]
            err = float(wrap_angle(math.atan2(ty - y, tx - x) - th))
            omega = max(-1.0, min(1.0, 2.0 * err))
            v = speed if abs(err) < 0.6 else 0.05
            if math.hypot(tx - x, ty - y) < 0.15:
                wp = (wp + 1) % len(wps)
            ds, dth = v * dt, omega * dt
            x += ds * math.cos(th + dth / 2)
            y += ds * math.sin(th + dth / 2)
            th = float(wrap_angle(th + dth))
            # odometry: the same step with random-walk drift
            ods = ds + lin_k * math.sqrt(ds) * rng.standard_normal()
            odth = (
                dth
                + ang_k * math.sqrt(abs(dth)) * rng.standard_normal()
                + 0.3 * lin_k * math.sqrt(ds) * rng.standard_normal()
            )
            ox, oy, oth = odo
            odo = (
                ox + ods * math.cos(oth + odth / 2),
                oy + ods * math.sin(oth + odth / 2),
                float(wrap_angle(oth + odth)),
            )
            fire_sonar = kind == "sweeper" and (step - phase[0]) % sonar_every == 0
            fire_cam = (step - phase[1]) % cam_every == 0
            fire_coocc = (step - phase[2]) % sonar_every == 0
            if step % steps_per_pred == 0 or fire_sonar or fire_cam or fire_coocc:
                # a prediction at every sensor time too, so the filter has the state when a reading arrives
                rec.predictions.append((name, odometry_prediction(t_prev, odo_prev, t, odo, spec)))
                odo_prev, t_prev = odo, t
                rec.truth[name].add(t, (x, y, th))
                rec.odometry[name].add(t, odo)
            if fire_sonar:
                echoes = []
                for b in SONAR_BEARINGS:
                    r = raycast(rm, x, y, th + b, 2.0)
                    if r is not None:
                        r = min(2.0, max(0.0, r + 0.03 * r * rng.standard_normal()))
                    echoes.append(SonarEcho(b, r))
                rec.readings.append(SonarReading(name, t, tuple(echoes), 0.349, 2.0))
            if fire_cam:
                _camera(rec, rm, name, t, (x, y, th), rng, sigma_bearing)
            if fire_coocc:
                rec.readings.append(CooccupancyReading(name, t, 0.15))
    rec.predictions.sort(key=lambda e: e[1].t)
    rec.readings.sort(key=lambda r: r.t)
    return rec


def _camera(
    rec: Recording,
    rm: Room,
    name: str,
    t: float,
    pose: tuple[float, float, float],
    rng: np.random.Generator,
    sigma_bearing: float,
    fov: float = 1.685,
    max_range: float = 4.0,
) -> None:
    x, y, th = pose
    seen = []
    for lid, (lx, ly) in rm.landmarks.items():
        d = math.hypot(lx - x, ly - y)
        b = float(wrap_angle(math.atan2(ly - y, lx - x) - th))
        if d > max_range or abs(b) > fov / 2 or d < 0.1:
            continue
        hit = raycast(rm, x, y, th + b, d + 1.0)
        if hit is not None and hit < d - 0.05:
            continue  # occluded
        rr = d + 0.09 * d * rng.standard_normal()
        bb = b + sigma_bearing * rng.standard_normal()
        if rr > 0:
            seen.append(Sighting(lid, rr, bb))
    rec.readings.append(LandmarkReading(name, t, tuple(seen)))
