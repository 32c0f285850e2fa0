"""Sensor models (thesis Table 6.2-4): sonar, and the cameras' landmark and collectable detections.

| sensor          | period  | field of view | effective range | noise sigma (of the distance) | thesis' avg. error |
|-----------------|---------|---------------|-----------------|-------------------------------|--------------------|
| basic camera    | manual  | 0.873 rad     | 3.0 m           | 0.09                          | ±0.14 m            |
| enhanced camera | manual  | 1.685 rad     | 4.0 m           | 0.09                          | ±0.18 m            |
| sonar           | 1.0 s   | 0.349 rad     | 2.0 m           | 0.03                          | ±0.03 m            |

"Artificial noise is added to each sensor reading as a percentage of the reading distance following a normal
distribution": a reading of true distance d is d + N(0, (sigma d)^2). That reproduces the table's average
errors: with targets spread evenly over the sensed area (distance density ∝ d up to the range r, mean 2r/3),
E|error| = sigma sqrt(2/pi) 2r/3 = 0.144, 0.192 and 0.032 m.

* Sonar: a Sweeper carries 5, at bearings -90°, -45°, 0°, 45°, 90° from its heading (our layout). A reading is
  the first echo within the 0.349 rad cone, found by casting `SONAR_RAYS` rays across the cone against the
  true geometry (walls, obstacles, other avatars); None when nothing is within 2.0 m. Ranges are measured
  from the avatar's centre.
* Cameras: `landmark_observations` is the "detected landmarks" convenience of a camera: every landmark whose
  marker is within range and field of view, faces the camera (incidence below `MAX_INCIDENCE`) and is in
  line of sight, with the range noise above and a small bearing noise (`BEARING_SIGMA`, ours: the thesis
  gives none). The real image a camera renders is haa.sim.camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SONAR_PERIOD = 1.0
SONAR_FOV = 0.349
SONAR_RANGE = 2.0
SONAR_SIGMA = 0.03
SONAR_BEARINGS = (-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4, math.pi / 2)
SONAR_RAYS = 9

CAMERA_SIGMA = 0.09
BEARING_SIGMA = 0.01
MAX_INCIDENCE = math.radians(75)
#: camera mounting: at the avatar's centre, this high, looking along the heading, horizontal (no pitch)
CAMERA_HEIGHT = 0.30


@dataclass(frozen=True)
class CameraSpec:
    name: str
    fov: float  # horizontal field of view, rad (Table 6.2-4)
    max_range: float  # m (Table 6.2-4)
    sigma: float  # noise sigma as a fraction of the distance (Table 6.2-4)
    width: int  # image size, px (ours)
    height: int

    @property
    def focal(self) -> float:
        """Focal length in pixels (square pixels)."""
        return (self.width / 2) / math.tan(self.fov / 2)


CAMERAS: dict[str, CameraSpec] = {
    "basic": CameraSpec("basic", 0.873, 3.0, CAMERA_SIGMA, 320, 240),
    "enhanced": CameraSpec("enhanced", 1.685, 4.0, CAMERA_SIGMA, 640, 480),
}


@dataclass(frozen=True)
class SonarReading:
    """One sonar's reading: `range` (m, noisy) or None when nothing is within `max_range`."""

    bearing: float  # rad, relative to the heading
    range: float | None
    fov: float = SONAR_FOV
    max_range: float = SONAR_RANGE
    time: float = 0.0


@dataclass(frozen=True)
class LandmarkObservation:
    """A landmark seen by the camera: noisy range (m) and bearing (rad, relative to the heading)."""

    landmark_id: int
    range: float
    bearing: float
    time: float = 0.0


@dataclass(frozen=True)
class CollectableObservation:
    """A collectable on the floor seen by the camera (same noise model as landmarks)."""

    collectable_id: str
    range: float
    bearing: float
    time: float = 0.0
