"""The motion model (eq. 5.1-3) covers the drift haa-sim draws (docs/slam.md "Motion model")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haa.slam.motion import DRIFT, Prediction, propagate

sim = pytest.importorskip("haa.sim.avatars")


@pytest.mark.parametrize("kind", ["seeker", "sweeper"])
def test_particle_spread_matches_the_simulated_drift(kind: str) -> None:
    """10 m straight in 0.25 m steps: haa-sim's default (random-walk) odometry error over 400 avatars, and
    the spread of 4000 particles moved by the predictions the avatar states (DriftSpec.sigmas). Heading:
    equal within 15 %; position: the model puts the along-track noise on both axes, so its spread is
    larger, but by less than 1.5x (a filter whose noise is too small or far too large fails this)."""
    spec, drift = sim.AVATAR_TYPES[kind], DRIFT[kind]
    errs, heads = [], []
    for i in range(400):
        o = sim.Odometry(spec.drift_params, (0.0, 0.0, 0.0), np.random.default_rng([21, i]))
        for _ in range(40):
            for _ in range(5):
                o.update(0.05, 0.0)
        errs.append(math.hypot(o.x - 10.0, o.y))
        heads.append(o.theta)
    states = np.zeros((4000, 3))
    rng = np.random.default_rng(5)
    dt = 0.25
    sxy, sth = drift.sigmas(0.25, 0.0, dt)
    for k in range(40):
        states = propagate(states, Prediction((k + 1) * dt, 1.0, 0.0, 0.0, sxy, sth), dt, rng)
    spread = math.sqrt(np.mean((states[:, 0] - 10.0) ** 2 + states[:, 1] ** 2))
    rms = math.sqrt(np.mean(np.square(errs)))
    assert rms <= spread < 1.5 * rms
    assert np.std(states[:, 2]) == pytest.approx(math.sqrt(np.mean(np.square(heads))), rel=0.15)
