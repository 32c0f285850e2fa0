"""AgentSensorSonar (thesis App. III L3005-3015): belief templates from sonar scans.

"Generates belief templates from sonar readings. The belief templates are used [to] create map and
observation density updates for JC-SLAM." A raw scan (the ring's bearings and echo ranges, as the avatar's
hardware reported them) becomes a haa.slam SonarReading; its template (haa.slam.sensors.SonarModel: the
free cone up to the echo, the occupied arc at it) gives the observation density and the map update when the
replica applies the Observe event. Echoes that are not finite or not within (0, max_range] are dropped here
(a sensor glitch is not a reading). Protocol, recovery and the per-host limit: haa.agents.team.SensorBase.
"""

from __future__ import annotations

import math
from typing import Any

from haa.agents import team
from haa.sdk.registry import register
from haa.slam.sensors import SonarEcho, SonarReading


@register
class AgentSensorSonar(team.SensorBase):
    TYPE = "sensor_sonar"
    COST = 0.05

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        max_range = float(reading.get("max_range", 2.0))
        echoes = []
        for bearing, rng in reading["echoes"]:
            if rng is not None and not (math.isfinite(rng) and 0 < rng <= max_range):
                continue
            echoes.append(SonarEcho(float(bearing), None if rng is None else float(rng)))
        if not echoes:
            return []
        return [SonarReading(reading["avatar"], float(reading["t"]), tuple(echoes),
                             fov=float(reading.get("fov", 0.349)), max_range=max_range)]


#: one avatar's own sensor_sonar agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorSonarDedicated = register(team.dedicated_type(AgentSensorSonar))
