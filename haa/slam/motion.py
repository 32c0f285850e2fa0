"""Prediction step: the velocity model of eq. 5.1-3 with the avatar's own uncertainty (§5.1.3).

    x_t^i = x_{t-1}^i + (ẋ_{t-1}^i + N(0, σ²)) Δt                                        (5.1-3)

The avatar (not the filter) states its motion and how sure it is: a `Prediction` carries the time, the body
frame velocities (forward `vx`, lateral `vy`, turn rate `omega`) over the interval since its previous
prediction, and the standard deviations `sigma_xy` (m/s, on each world axis) and `sigma_theta` (rad/s) of
the velocity noise. For particle i with heading θ_i the world velocity is the body velocity rotated by the
heading at mid-interval, so a noise-free particle follows exactly the path the avatar's odometry reports,
seen from the particle's own pose.

Where the σ come from (the thesis leaves it to "the physical hardware"): `DriftSpec` holds the drift of
Table 6.2-3 (position drift after 10 m, heading drift after 10 rotations) and turns a step of length s and
turn a into the random walk haa-sim's default drift model draws (see `DriftSpec`), each σ divided by Δt to
become a velocity noise as eq. 5.1-3 wants. `inflate` widens it (1.0 by default; a filter that is too sure
of its motion loses the truth, §5.2.1's own caution about underestimated errors).

`odometry_prediction(t0, pose0, t1, pose1, spec)` turns two dead-reckoning poses into a `Prediction`;
`propagate(states, p, dt, rng)` applies eq. 5.1-3 to all particles at once (no Python loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped to [-π, π)."""
    return (a + math.pi) % TWO_PI - math.pi


@dataclass(frozen=True)
class DriftSpec:
    """Odometry drift of an avatar type (Table 6.2-3): std after 10 m travelled and after 10 rotations.

    `sigmas` is the random walk haa-sim's default ("thesis") drift model draws (haa.sim.avatars; noise added
    to every odometry increment, thesis L1354): along-track variance L²/(2·10 m) per metre, heading
    variance 1.5·L²/(10 m)³ per metre driven and A²/(20π) per radian turned — half of L² along track and
    half across after 10 m, A² after 10 rotations. The position noise is put on both world axes (eq. 5.1-3
    has no along/across split), which over-covers the along-track part by a factor of 2 in variance.
    `inflate` widens both: 1.0 for the thesis' random-walk drift; the harsher "systematic" drift (scale
    error and heading bias, not a random walk) needs more (docs/slam.md "Motion model").
    """

    linear_m_per_10m: float
    angular_rad_per_10rot: float
    inflate: float = 1.0

    def sigmas(self, dist: float, turn: float, dt: float) -> tuple[float, float]:
        """(sigma_xy [m/s], sigma_theta [rad/s]) of eq. 5.1-3 for a step of `dist` m and `turn` rad in `dt` s."""
        if dt <= 0:
            raise ValueError(f"dt: must be > 0, got {dt}")
        L, A, s = self.linear_m_per_10m, self.angular_rad_per_10rot, abs(dist)
        pos = L * math.sqrt(s / 20.0)
        ang = math.sqrt(1.5 * L * L * s / 1000.0 + A * A * abs(turn) / (10 * TWO_PI))
        return self.inflate * pos / dt, self.inflate * ang / dt


# Table 6.2-3 (approx. linear drift after 10 m, approx. angular drift after 10 rotations) as haa-sim's default
# ("thesis") drift model reads it: the seeker's 1.22 m as 0.122 m (haa.sim.avatars, docs/sim.md). An avatar
# agent states what its simulator reports (AvatarInfo.linear_drift / angular_drift); this table is the default.
DRIFT: dict[str, DriftSpec] = {
    "seeker": DriftSpec(0.122, 0.08),
    "enhanced_seeker": DriftSpec(0.25, 0.016),
    "sweeper": DriftSpec(0.12, 0.016),
    "carrier": DriftSpec(0.12, 0.016),
}


@dataclass(frozen=True)
class Prediction:
    """One prediction update <t, ẋ, σ> from an avatar (event (b) of §5.2.3)."""

    t: float
    vx: float  # forward body velocity over (t_prev, t], m/s
    vy: float  # lateral body velocity, m/s (0 for a differential drive; odometry may report some)
    omega: float  # turn rate, rad/s
    sigma_xy: float  # std of the world-frame velocity noise on x and on y, m/s
    sigma_theta: float  # std of the turn-rate noise, rad/s

    def __post_init__(self) -> None:
        for name in ("t", "vx", "vy", "omega", "sigma_xy", "sigma_theta"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"prediction.{name}: must be finite, got {getattr(self, name)}")
        if self.sigma_xy < 0 or self.sigma_theta < 0:
            raise ValueError("prediction.sigma_xy/sigma_theta: must be >= 0")


def odometry_prediction(
    t0: float, pose0: tuple[float, float, float], t1: float, pose1: tuple[float, float, float], spec: DriftSpec
) -> Prediction:
    """The prediction an avatar sends for the odometry step pose0 (at t0) -> pose1 (at t1)."""
    dt = t1 - t0
    if dt <= 0:
        raise ValueError(f"odometry: t1 must be after t0, got {t0} -> {t1}")
    dx, dy = pose1[0] - pose0[0], pose1[1] - pose0[1]
    c, s = math.cos(pose0[2]), math.sin(pose0[2])
    fwd, lat = c * dx + s * dy, -s * dx + c * dy
    dth = float(wrap_angle(pose1[2] - pose0[2]))
    # body displacement measured in the frame of pose0; propagate() rotates by the mid-interval heading
    cm, sm = math.cos(dth / 2), math.sin(dth / 2)
    fwd, lat = cm * fwd + sm * lat, -sm * fwd + cm * lat
    sxy, sth = spec.sigmas(math.hypot(dx, dy), dth, dt)
    return Prediction(t1, fwd / dt, lat / dt, dth / dt, sxy, sth)


def propagate(states: np.ndarray, p: Prediction, dt: float, rng: np.random.Generator) -> np.ndarray:
    """Eq. 5.1-3 for all particles: (N, 3) float64 states at t_prev -> new (N, 3) array at p.t."""
    n = states.shape[0]
    noise = rng.standard_normal((n, 3))
    omega = p.omega + p.sigma_theta * noise[:, 2]
    th = states[:, 2]
    mid = th + 0.5 * omega * dt
    c, s = np.cos(mid), np.sin(mid)
    out = np.empty_like(states)
    out[:, 0] = states[:, 0] + (c * p.vx - s * p.vy + p.sigma_xy * noise[:, 0]) * dt
    out[:, 1] = states[:, 1] + (s * p.vx + c * p.vy + p.sigma_xy * noise[:, 1]) * dt
    out[:, 2] = wrap_angle(th + omega * dt)
    return out
