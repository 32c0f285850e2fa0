"""Avatar types (thesis Table 6.2-3) and the odometry drift model.

| type            | speed m/s | drift after 10 m | drift after 10 turns | carries | sensors                   |
|-----------------|-----------|------------------|----------------------|---------|---------------------------|
| seeker          | 2.0       | 1.22 m (*)       | 0.08 rad             | 0       | basic camera              |
| enhanced_seeker | 2.0       | 0.25 m           | 0.016 rad            | 0       | enhanced camera           |
| sweeper         | 1.0       | 0.12 m           | 0.016 rad            | 1       | enhanced camera, 5 sonars |
| carrier         | 1.5       | 0.12 m           | 0.016 rad            | 1       | enhanced camera           |

(*) 0.122 m in the default drift model (below). Turn-rate limits, radii and masses are not in the thesis;
ours are in `AVATAR_TYPES` (docs/sim.md).

Odometry ("what the wheels believe") integrates the wheel increments of every physics step with errors of
two kinds, both drawn from the avatar's own seeded streams:

* systematic, drawn once per avatar: a distance scale error `e_s` (wheel radius), a heading bias per metre
  driven `b` (unequal wheels: a straight drive curves), a rotation scale error `e_r` (wheel base);
* random walk: along-track noise with variance `sa^2` per metre, heading noise `sh^2` per metre driven,
  rotation noise `sr^2` per radian turned.

Per increment (ds, dtheta) of the true motion:

    ds'     = ds (1 + e_s) + sa sqrt(|ds|) n1
    dtheta' = dtheta (1 + e_r) + sr sqrt(|dtheta|) n2 + b ds + sh sqrt(|ds|) n3

Three drift models share this code (`DRIFT_MODELS`, docs/sim.md "Odometry drift"):

* "thesis" (the default): noise added to every odometry increment and nothing else — "an appropriate noise
  signal was added to most inputs, including the avatar odometry model" (thesis L1354) — i.e. a random walk,
  e_s = b = e_r = 0. After D = 10 m straight the squared position error is sa^2 D (along track) +
  sh^2 D^3/3 (across), half of L^2 each (L = the linear drift); after R = 10 rotations in place
  sr^2 R = A^2. The seeker's L is 0.122 m, not the 1.22 m printed in Table 6.2-3: the thesis' own
  measurements (Table 7.2-1: 0.123 m of mean dead-reckoning error for four seekers exploring the small arena
  for 2:56; AF-1's 0.057 m localization error) are out of reach of 1.22 m per 10 m for any seeker that
  explores at all, and fit 0.122 m (docs/sim.md "What Table 6.2-3 and Table 7.2-1 say").
* "table": the same random walk with Table 6.2-3's figures as printed (a seeker drifts 1.22 m per 10 m).
* "systematic" (harsher; real robots): Table 6.2-3 as printed and the systematic terms as well. The squared
  position error after 10 m is e_s^2 D^2 + sa^2 D + b^2 D^4/4 + sh^2 D^3/3, a quarter of L^2 each; after
  R = 10 rotations e_r^2 R^2 + sr^2 R, half of A^2 each.

All read the drifts as RMS errors after 10 m / 10 rotations; tests/test_sim_world.py checks them
statistically for each model. Beyond 10 m the systematic model grows faster (its terms grow like D and D^2
where the random walk's grow like sqrt(D) and D^1.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: drift models: "thesis" (random walk only, the default), "table" (the same with Table 6.2-3's seeker drift as
#: printed) and "systematic" (Table 6.2-3 as printed + per-avatar scale and bias errors)
DRIFT_MODELS = ("thesis", "table", "systematic")

#: reference distance and rotation of Table 6.2-3
DRIFT_DISTANCE = 10.0
DRIFT_ROTATION = 10 * 2 * math.pi


@dataclass(frozen=True)
class AvatarSpec:
    name: str
    max_speed: float  # m/s (Table 6.2-3)
    max_turn: float  # rad/s (ours)
    linear_drift: float  # RMS position error after 10 m straight, m (Table 6.2-3; seeker: see the docstring)
    angular_drift: float  # RMS heading error after 10 rotations in place, rad (Table 6.2-3)
    capacity: int  # collectables carried at once (Table 6.2-3)
    camera: str  # "basic" | "enhanced" (Table 6.2-3, 6.2-4)
    sonars: int  # (Table 6.2-3)
    radius: float  # m (ours)
    mass: float  # kg (ours)
    height: float  # m, as the cameras see other avatars (ours)
    #: Table 6.2-3's linear drift as printed, where the "thesis" model reads it otherwise (the seeker)
    table_linear_drift: float | None = None

    @property
    def drift_params(self) -> DriftParams:
        return DriftParams.calibrated(self.linear_drift, self.angular_drift)

    def drift_figures(self, model: str = "thesis") -> tuple[float, float]:
        """(linear m after 10 m, angular rad after 10 rotations) of this type in drift model `model`."""
        if model not in DRIFT_MODELS:
            raise ValueError(f"drift model {model!r} is not one of {', '.join(DRIFT_MODELS)}")
        if model == "thesis" or self.table_linear_drift is None:
            return self.linear_drift, self.angular_drift
        return self.table_linear_drift, self.angular_drift

    def drift_params_for(self, model: str) -> DriftParams:
        return DriftParams.calibrated(*self.drift_figures(model), model)


AVATAR_TYPES: dict[str, AvatarSpec] = {
    "seeker": AvatarSpec("seeker", 2.0, 3.0, 0.122, 0.08, 0, "basic", 0, 0.12, 3.0, 0.25, table_linear_drift=1.22),
    "enhanced_seeker": AvatarSpec("enhanced_seeker", 2.0, 3.0, 0.25, 0.016, 0, "enhanced", 0, 0.12, 3.0, 0.25),
    "sweeper": AvatarSpec("sweeper", 1.0, 1.5, 0.12, 0.016, 1, "enhanced", 5, 0.20, 10.0, 0.35),
    "carrier": AvatarSpec("carrier", 1.5, 2.0, 0.12, 0.016, 1, "enhanced", 0, 0.20, 8.0, 0.35),
}


def avatar_spec(kind: str) -> AvatarSpec:
    try:
        return AVATAR_TYPES[kind]
    except KeyError:
        raise ValueError(f"avatar type {kind!r} is not one of {', '.join(AVATAR_TYPES)}") from None


@dataclass(frozen=True)
class DriftParams:
    """Standard deviations of the drift model (see the module docstring)."""

    scale: float  # e_s ~ N(0, scale)
    along: float  # sa, m per sqrt(m)
    bias: float  # b ~ N(0, bias), rad per m
    heading: float  # sh, rad per sqrt(m)
    rot_scale: float  # e_r ~ N(0, rot_scale)
    rot: float  # sr, rad per sqrt(rad)

    @staticmethod
    def calibrated(linear: float, angular: float, model: str = "thesis") -> DriftParams:
        D, R = DRIFT_DISTANCE, DRIFT_ROTATION
        if model in ("thesis", "table"):  # random walk only: half of L^2 along track, half across; all of A^2
            return DriftParams(
                scale=0.0,
                along=linear / math.sqrt(2 * D),
                bias=0.0,
                heading=math.sqrt(1.5) * linear / D**1.5,
                rot_scale=0.0,
                rot=angular / math.sqrt(R),
            )
        if model != "systematic":
            raise ValueError(f"drift model {model!r} is not one of {', '.join(DRIFT_MODELS)}")
        return DriftParams(
            scale=linear / (2 * D),
            along=linear / (2 * math.sqrt(D)),
            bias=linear / D**2,
            heading=math.sqrt(3) / 2 * linear / D**1.5,
            rot_scale=angular / (math.sqrt(2) * R),
            rot=angular / math.sqrt(2 * R),
        )


class NormalStream:
    """Standard normal variates from a seeded generator, drawn in blocks (cheap per value)."""

    def __init__(self, rng: np.random.Generator, block: int = 4096) -> None:
        self.rng = rng
        self.block = block
        self._buf: list[float] = []
        self._i = 0

    def __call__(self) -> float:
        if self._i >= len(self._buf):
            self._buf = self.rng.standard_normal(self.block).tolist()
            self._i = 0
        v = self._buf[self._i]
        self._i += 1
        return v


class Odometry:
    """Dead reckoning from wheel increments with the avatar's drift (systematic + random walk)."""

    def __init__(self, params: DriftParams, pose: tuple[float, float, float], rng: np.random.Generator) -> None:
        self.params = params
        sysdraw = rng.standard_normal(3)
        self.e_s = float(sysdraw[0]) * params.scale
        self.b = float(sysdraw[1]) * params.bias
        self.e_r = float(sysdraw[2]) * params.rot_scale
        self.noise = NormalStream(rng, 2048)
        self.x, self.y, self.theta = pose
        self.distance = 0.0  # |ds| summed, m
        self.rotation = 0.0  # |dtheta| summed, rad

    @property
    def pose(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.theta)

    def update(self, ds: float, dtheta: float) -> None:
        """Integrate one true increment: ds along the heading (m), dtheta (rad)."""
        p = self.params
        n = self.noise
        ads, adt = abs(ds), abs(dtheta)
        ds_o = ds * (1.0 + self.e_s)
        dt_o = dtheta * (1.0 + self.e_r)
        if ads > 0.0:
            r = math.sqrt(ads)
            ds_o += p.along * r * n()
            dt_o += self.b * ds + p.heading * r * n()
        if adt > 0.0:
            dt_o += p.rot * math.sqrt(adt) * n()
        mid = self.theta + 0.5 * dt_o
        self.x += ds_o * math.cos(mid)
        self.y += ds_o * math.sin(mid)
        self.theta = math.remainder(self.theta + dt_o, 2 * math.pi)
        self.distance += ads
        self.rotation += adt
