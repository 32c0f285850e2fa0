"""AgentSensorFloorFinder (thesis App. III L2983-2993): the free floor in a camera image → a map update.

"Extracts the floor from an image by colour matching with an area sampled directly in front of the avatar,
following the strategy in [112]. The floor region is then transformed from image space to map space using a
planar homography transformation and used to generate a belief template for JC-SLAM." The image is fetched
from the avatar agent; haa.control.floorfinder finds the floor polygon (avatar frame); the replica applies
the FloorReading (haa.slam.sensors.FloorModel). The floor colour is shared by the team (`slam/floor_colour`):
an agent that starts or restarts takes it as its prior before its first image — one that learnt its colour
from a first image of a wall matched walls as floor and refused the floor (a host crash's restarted agents
erased the map's obstacles in tests/missions/hosts.yaml) — and an agent that learnt a colour it trusts
(haa.control.floorfinder.FloorFinder.confident) writes it there, again when it has moved by
`PUBLISH_DELTA` grey levels. Protocol, recovery, per-host limit: haa.agents.team.SensorBase.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from haa.agents import team
from haa.control.floorfinder import FloorFinder
from haa.sdk.registry import register
from haa.slam.sensors import FloorReading

#: the team's floor colour (FloorFinder.learnt(): {"mean": [b, g, r], "std": [...]})
K_FLOOR_COLOUR = "slam/floor_colour"
#: grey levels the learnt colour moves (any channel) before it is written again
PUBLISH_DELTA = 4.0


@register
class AgentSensorFloorFinder(team.SensorBase):
    TYPE = "sensor_floorfinder"
    COST = 0.2

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.finder = FloorFinder()
        self.published: list[float] | None = None  # the mean last written to K_FLOOR_COLOUR

    async def begin(self, how: str) -> None:
        await self._team_colour()
        await super().begin(how)

    async def _team_colour(self) -> None:
        colour = await team.get_json(self, K_FLOOR_COLOUR, None)
        if colour is not None and self.finder.adopt(colour):
            self.published = list(colour["mean"])

    async def _share_colour(self) -> None:
        """Write the learnt colour for the team when it is trusted and new (module docstring)."""
        colour = self.finder.learnt()
        if colour is None or not self.finder.confident():
            return
        if self.published is not None and max(abs(a - b) for a, b in zip(colour["mean"], self.published,
                                                                           strict=True)) < PUBLISH_DELTA:
            return
        self.published = colour["mean"]
        await self.ddb_write([team.op_put_json(K_FLOOR_COLOUR, colour)])

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        frame = await self.fetch_frame(reading)
        r = await self.compute(floor_reading, self.finder, frame, reading["avatar"])
        await self._share_colour()
        return [] if r is None else [r]


def floor_reading(finder: FloorFinder, frame: Any, avatar: str) -> FloorReading | None:
    """The FloorReading of one frame with its obstacle feet flagged (FloorReading.occupied).

    haa.control.floorfinder gives the free floor polygon [bottom-left, the floor's boundary every `step`
    columns, bottom-right] and, per column, the first floor row from the bottom (`boundary`). Where the floor
    run ends below the rows the camera's range allows (`v_far`, the same cut as the finder's) and above the
    image bottom, the pixel above it is something standing on the floor — a wall, an obstacle, another
    avatar: that vertex is an obstacle's foot. A run cut at the range limit, or a column with no floor at its
    bottom (something nearer than the nearest visible floor: where, the image does not say), is not flagged.
    Without the flags the team's map only ever learnt free space from the camera: seekers have no sonar, so
    walls and obstacles were never marked (docs/slam.md "In the running team")."""
    res = finder.find(frame)
    if res is None or float(np.max(res.ranges)) <= 0:
        return None
    H = frame.image.shape[0]
    if bool((res.boundary >= H).all()):
        return None
    f, cy = float(frame.K[1, 1]), float(frame.K[1, 2])
    mount = frame.mount
    v_far = max(0, min(H - 1, math.ceil(cy + f * mount[2] / frame.max_range))) if mount[3] == 0 else 0
    b = res.boundary[res.columns]
    flags = [False, *((b > v_far) & (b < H)).tolist(), False]
    poly = list(res.polygon)
    if len(poly) != len(flags):
        return FloorReading(avatar, float(frame.time), tuple(poly))
    # find_floor makes the polygon counter-clockwise: it runs from image column 0 (the avatar's left, y > 0)
    # to the last one, or the other way round
    if poly[1][1] < poly[-2][1]:
        flags.reverse()
    return FloorReading(avatar, float(frame.time), tuple(poly), tuple(bool(x) for x in flags))


#: one avatar's own sensor_floorfinder agent (SupervisorSLAM's delay mode; haa.agents.team.dedicated_type)
AgentSensorFloorFinderDedicated = register(team.dedicated_type(AgentSensorFloorFinder))
