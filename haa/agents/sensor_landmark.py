"""AgentSensorLandmark (thesis App. III L2995-3003): landmarks in camera images → localization updates.

"Scans images to locate landmarks building on the algorithm described in [113]. Landmarks are then used to
generate localization updates." The image is fetched from the avatar agent that took it (no frames in the
DDB) and scanned with OpenCV's ArUco detector (haa.control.landmarks: range and bearing of each marker from
its corners, the intrinsics and the camera mount — never the frame's true pose); the sightings become a
haa.slam LandmarkReading, applied by the replica (observation density, landmark map). The marker dictionary,
size and the ids of the arena's landmarks are mission parameters (what the team knows of its artificial
landmarks; not where they are). Protocol, recovery, per-host limit: haa.agents.team.SensorBase.
"""

from __future__ import annotations

from typing import Any

import pydantic

from haa.agents import team
from haa.control.landmarks import LandmarkDetector
from haa.sdk.registry import register


class LandmarkSensorConfig(team.SensorConfig):
    landmark_ids: list[int] = []
    marker_dictionary: str = pydantic.Field(min_length=1)
    marker_size: float = pydantic.Field(gt=0, le=10)


@register
class AgentSensorLandmark(team.SensorBase):
    TYPE = "sensor_landmark"
    CONFIG = LandmarkSensorConfig
    COST = 0.2
    cfg: LandmarkSensorConfig

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.detector = LandmarkDetector(self.cfg.marker_dictionary, self.cfg.marker_size,
                                         set(self.cfg.landmark_ids) or None)

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        frame = await self.fetch_frame(reading)
        r = await self.compute(self.detector.reading, frame, reading["avatar"])
        return [r] if r.sightings else []


#: one avatar's own sensor_landmark agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorLandmarkDedicated = register(team.dedicated_type(AgentSensorLandmark))
