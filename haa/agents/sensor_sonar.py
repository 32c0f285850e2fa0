"""AgentSensorSonar (thesis App. III L3005-3015): belief templates from sonar scans.

"Generates belief templates from sonar readings. The belief templates are used [to] create map and
observation density updates for JC-SLAM." A raw scan (the ring's bearings and echo ranges, as the avatar's
hardware reported them) becomes a haa.slam SonarReading; its template (haa.slam.sensors.SonarModel: the
free cone up to the echo, the occupied arc at it) gives the observation density and the map update when the
replica applies the Observe event. Echoes that are not finite or not within (0, max_range] are dropped here
(a sensor glitch is not a reading).

**Teammates are not obstacles** (ours; the thesis does not say, docs/slam.md "Teammate echoes"): a sonar
echoes off another avatar as off a wall, and an avatar that was mapped where it stood stays in the shared
map as an obstacle after it has gone — until a sonar cone sweeps the cell again, and the five cones of a
sweeper's front ring leave gaps a stationary avatar never sees. Such phantoms shut passages: a carrying
sweeper stood 5 minutes of a forage mission beside one, its every target "unreachable". So an echo whose cone
reaches another avatar's disc (its last estimate in `slam/estimates`, its radius from its registry entry,
plus `TEAMMATE_TOLERANCE_M`) at the echo's range is dropped from the scan (`teammate_echo`): no occupied arc,
and no free cone either (the cone may be right up to the teammate; dropping loses only this echo's evidence).
Without an estimate of this avatar no echo is dropped. Protocol, recovery and the per-host limit:
haa.agents.team.SensorBase.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Sequence
from typing import Any

from haa.agents import team
from haa.sdk.registry import register
from haa.slam.sensors import SonarEcho, SonarReading

#: m added to a teammate's radius: its estimate and this avatar's are each a few cm off (docs/slam.md: mean
#: position error 0.03-0.14 m), and both moved (≤ 0.1 m at cruise) between the scan and the estimates read
TEAMMATE_TOLERANCE_M = 0.15
#: an estimate older than this (s of mission time) than the scan does not place its avatar for it
TEAMMATE_MAX_AGE_S = 5.0
#: radius (m) of a teammate whose registry entry does not give one: the largest type's (sweeper, carrier)
DEFAULT_RADIUS_M = 0.2


def teammate_echo(pose: Sequence[float], bearing: float, rng: float, fov: float,
                  others: Sequence[tuple[float, float, float]], tolerance: float = TEAMMATE_TOLERANCE_M) -> bool:
    """Whether an echo at range `rng` of the sonar at `bearing` (cone `fov` wide) of an avatar at `pose` (x, y,
    θ) can come from one of `others` (x, y, radius): the echo's arc meets the disc of radius + tolerance."""
    x, y, th = pose
    axis = th + bearing
    for ox, oy, r in others:
        reach = r + tolerance
        d = math.hypot(ox - x, oy - y)
        if abs(d - rng) > reach:
            continue
        if d <= reach:
            return True
        off = abs(math.remainder(math.atan2(oy - y, ox - x) - axis, math.tau))
        if off <= fov / 2 + math.asin(min(1.0, reach / d)):
            return True
    return False


@register
class AgentSensorSonar(team.SensorBase):
    TYPE = "sensor_sonar"
    COST = 0.05

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.teammate_echoes = 0  # echoes dropped as teammates, for the log

    async def _teammates(self, avatar: str, t: float) -> tuple[tuple[float, float, float] | None,
                                                              list[tuple[float, float, float]]]:
        """(this avatar's estimate (x, y, θ) or None, the others' (x, y, radius)) at scan time `t`."""
        ests = await team.get_json(self, team.K_SLAM_ESTIMATES, {}) or {}
        regs: dict[str, Any] = {}
        if len(ests) > 1:
            for key, data in (await self.ddb_scan(team.K_AVATARS)).items():
                with contextlib.suppress(ValueError):
                    regs[key[len(team.K_AVATARS):]] = json.loads(data)
        own, others = None, []
        for a, e in ests.items():
            try:
                et, ex, ey, eth = float(e["t"]), float(e["x"]), float(e["y"]), float(e["theta"])
            except (KeyError, TypeError, ValueError):
                continue
            if abs(et - t) > TEAMMATE_MAX_AGE_S:
                continue
            if a == avatar:
                own = (ex, ey, eth)
            else:
                got = regs.get(a)
                reg: dict[str, Any] = got if isinstance(got, dict) else {}
                if reg.get("status", "active") != "active":  # a crashed avatar stays where it is: an obstacle
                    continue
                others.append((ex, ey, float(reg.get("radius") or DEFAULT_RADIUS_M)))
        return own, others

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        max_range = float(reading.get("max_range", 2.0))
        fov = float(reading.get("fov", 0.349))
        avatar, t = reading["avatar"], float(reading["t"])
        own: tuple[float, float, float] | None = None
        others: list[tuple[float, float, float]] = []
        if any(rng is not None for _, rng in reading["echoes"]):
            own, others = await self._teammates(avatar, t)
        echoes = []
        for bearing, rng in reading["echoes"]:
            if rng is not None and not (math.isfinite(rng) and 0 < rng <= max_range):
                continue
            if rng is not None and own is not None and others and teammate_echo(own, float(bearing), float(rng),
                                                                                  fov, others):
                self.teammate_echoes += 1
                continue
            echoes.append(SonarEcho(float(bearing), None if rng is None else float(rng)))
        if not echoes:
            return []
        return [SonarReading(avatar, t, tuple(echoes), fov=fov, max_range=max_range)]


#: one avatar's own sensor_sonar agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorSonarDedicated = register(team.dedicated_type(AgentSensorSonar))
