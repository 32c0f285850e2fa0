"""AgentSensorCooccupancy (thesis App. III L2971-2981): map updates from where the avatar is.

"Uses avatar position information to generate map updates, following the logic that if the area is occupied
by the avatar it is not occupied by an obstacle." A raw co-occupancy reading (avatar, time, footprint
radius) becomes a haa.slam CooccupancyReading; the free disc is applied at every particle of the avatar's
filter when the replica applies the Observe event (haa.slam.sensors.CooccupancyModel). Protocol, recovery
and the per-host limit: haa.agents.team.SensorBase.
"""

from __future__ import annotations

from typing import Any

from haa.agents import team
from haa.sdk.registry import register
from haa.slam.sensors import CooccupancyReading


@register
class AgentSensorCooccupancy(team.SensorBase):
    TYPE = "sensor_cooccupancy"
    COST = 0.02

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        return [CooccupancyReading(reading["avatar"], float(reading["t"]), float(reading["radius"]))]


#: one avatar's own sensor_cooccupancy agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorCooccupancyDedicated = register(team.dedicated_type(AgentSensorCooccupancy))
