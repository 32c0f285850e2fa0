"""AgentSensorFloorFinder (thesis App. III L2983-2993): the free floor in a camera image → a map update.

"Extracts the floor from an image by colour matching with an area sampled directly in front of the avatar,
following the strategy in [112]. The floor region is then transformed from image space to map space using a
planar homography transformation and used to generate a belief template for JC-SLAM." The image is fetched
from the avatar agent; haa.control.floorfinder finds the floor polygon (avatar frame); the replica applies
the FloorReading (haa.slam.sensors.FloorModel). The floor colour the agent learnt is its state (a restarted
agent learns it again from its next images). Protocol, recovery, per-host limit: haa.agents.team.SensorBase.
"""

from __future__ import annotations

from typing import Any

from haa.agents import team
from haa.agents.registry import register
from haa.control.floorfinder import FloorFinder


@register
class AgentSensorFloorFinder(team.SensorBase):
    TYPE = "sensor_floorfinder"
    COST = 0.2

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.finder = FloorFinder()

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        frame = await self.fetch_frame(reading)
        r = self.finder.reading(frame, reading["avatar"])
        return [] if r is None else [r]
