"""AgentSensorLandmark (thesis App. III L2995-3003): landmarks in camera images → localization updates.

"Scans images to locate landmarks building on the algorithm described in [113]. Landmarks are then used to
generate localization updates." The image is fetched from the avatar agent that took it (no frames in the
DDB) and scanned with OpenCV's ArUco detector (haa.control.landmarks: range and bearing of each marker from
its corners, the intrinsics and the camera mount — never the frame's true pose); the sightings become a
haa.slam LandmarkReading, applied by the replica (observation density, landmark map). The marker dictionary,
size and the ids of the arena's landmarks are mission parameters (what the team knows of its artificial
landmarks; not where they are). Protocol, recovery, per-host limit: haa.agents.team.SensorBase.

**Collectables** (Forage: the thesis' "collectable landmarks", Table 6.2-1 scenario 3). With `collectables`
set (SupervisorSLAM's config, from the mission) the same frame is also scanned for red collectables
(haa.control.collectables.CollectableDetector: range and bearing from the image, K and mount only), and
their sightings are a second reading of the processing, a haa.slam CollectablesReading after the landmark
reading in the same atomic batch: the replica places them with the avatar's estimated pose at the frame's
time and identifies them (haa.slam.collectables). Off by default: explore and congregate missions write
exactly what they wrote before.
"""

from __future__ import annotations

from typing import Any

import pydantic

from haa.agents import team
from haa.control.collectables import CollectableDetector
from haa.control.landmarks import LandmarkDetector
from haa.sdk.registry import register
from haa.slam.sensors import CollectablesReading, LandmarkReading, RangeBearing


class LandmarkSensorConfig(team.SensorConfig):
    landmark_ids: list[int] = []
    marker_dictionary: str = pydantic.Field(min_length=1)
    marker_size: float = pydantic.Field(gt=0, le=10)
    #: also report the collectables in the frame (Forage)
    collectables: bool = False


def frame_readings(
    landmarks: LandmarkDetector, collectables: CollectableDetector | None, frame: Any, avatar: str
) -> list[LandmarkReading | CollectablesReading]:
    """The readings of one camera frame: its landmark sightings, then (with a collectable detector) its
    collectable sightings — each only if it has any. Reads the image, K, mount, max_range and time of the
    frame, never a pose."""
    out: list[LandmarkReading | CollectablesReading] = []
    r = landmarks.reading(frame, avatar)
    if r.sightings:
        out.append(r)
    if collectables is not None:
        seen = collectables.sightings(frame)
        if seen:
            out.append(
                CollectablesReading(avatar, float(frame.time), tuple(RangeBearing(s.range, s.bearing) for s in seen))
            )
    return out


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
        self.collectables = CollectableDetector() if self.cfg.collectables else None

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        frame = await self.fetch_frame(reading)
        return await self.compute(frame_readings, self.detector, self.collectables, frame, reading["avatar"])


#: one avatar's own sensor_landmark agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorLandmarkDedicated = register(team.dedicated_type(AgentSensorLandmark))
