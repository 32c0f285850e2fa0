"""AgentSensorLandmark's core: ArUco markers in a camera frame → landmark sightings (id, range, bearing).

Thesis App. III (L2995-2997): "Scans images to locate landmarks building on the algorithm described in [113]
[self-similar landmarks]. Landmarks are then used to generate localization updates." haa-sim prints ArUco
markers on its landmarks (haa/sim/camera.py: the job of the thesis' self-similar landmarks — many distinct,
cheaply detected and identified artificial landmarks — is what ArUco does in OpenCV), so the detector is
OpenCV's `cv2.aruco.ArucoDetector` with the arena's dictionary.

Per detected marker:

* **Pose.** `cv2.solvePnP` (IPPE_SQUARE) of the four corners against a square of the marker's side (the black
  square, `marker_size` of the arena file) with the frame's intrinsics K (no distortion) gives the marker
  centre in the camera frame (x right, y down, z forward).
* **Avatar frame.** The camera sits at `mount` = (mx, my, height, pitch) in the avatar frame (x forward,
  y left); for pitch 0 the centre is at X = mx + z, Y = my − x.
* **Range** = hypot(X, Y), the horizontal distance from the avatar's centre to the marker centre (what
  haa.slam's LandmarkModel expects); **bearing** = atan2(Y, X), relative to the heading.
* Sightings farther than the camera's effective range (`frame.max_range`, Table 6.2-4) are dropped (the
  thesis' sensor spec), and so are ids not in `known_ids` when it is given (false detections).
* The same id seen twice in one frame (the congregation post has its marker on every face) is kept once,
  the nearer sighting.

Only the image, K, the mount and the time are used: the frame's true pose is ground truth and is not read.
docs/control.md reports the range and bearing errors against the simulator's true marker positions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from haa.slam.sensors import LandmarkReading, Sighting

if TYPE_CHECKING:
    from haa.sim.arena import Arena
    from haa.sim.camera import CameraFrame


@dataclass(frozen=True)
class Detection:
    landmark_id: int
    range: float
    bearing: float
    corners: np.ndarray  # (4, 2) pixels
    xy: tuple[float, float]  # marker centre in the avatar frame (x forward, y left), m


class LandmarkDetector:
    """ArUco detection with one arena's dictionary and marker size (reuse it for every frame)."""

    def __init__(
        self, dictionary: str = "DICT_4X4_250", marker_size: float = 0.2, known_ids: set[int] | None = None
    ) -> None:
        if not hasattr(cv2.aruco, dictionary):
            raise ValueError(f"dictionary: {dictionary!r} is not an OpenCV ArUco dictionary")
        if not marker_size > 0:
            raise ValueError(f"marker_size: must be > 0, got {marker_size}")
        self.dictionary = dictionary
        self.marker_size = marker_size
        self.known_ids = known_ids
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)
        s = marker_size / 2
        # ArUco corner order: top-left, top-right, bottom-right, bottom-left (marker frame x right, y up)
        self._obj = np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], dtype=np.float64)

    @classmethod
    def for_arena(cls, arena: Arena) -> LandmarkDetector:
        """A detector for a haa.sim Arena (its dictionary, marker size and landmark ids)."""
        ids = set(arena.landmarks)
        return cls(arena.marker_dictionary, arena.marker_size, ids)

    def detect(
        self,
        image: np.ndarray,
        K: np.ndarray,
        mount: tuple[float, float, float, float] = (0.0, 0.0, 0.3, 0.0),
        max_range: float = math.inf,
    ) -> list[Detection]:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        corners, ids, _ = self._det.detectMarkers(gray)
        if ids is None:
            return []
        mx, my, _mh, pitch = mount
        cp, sp = math.cos(pitch), math.sin(pitch)
        best: dict[int, Detection] = {}
        for c, i in zip(corners, ids.ravel().tolist(), strict=True):
            if self.known_ids is not None and i not in self.known_ids:
                continue
            pts = c.reshape(4, 2).astype(np.float64)
            ok, _rvec, tvec = cv2.solvePnP(self._obj, pts, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            if not ok:
                continue
            x, y, z = (float(v) for v in tvec.ravel())
            # camera (x right, y down, z forward) pitched down by `pitch` -> avatar frame (X forward, Y left)
            X = mx + z * cp - y * sp
            Y = my - x
            r = math.hypot(X, Y)
            if not (0 < r <= max_range):
                continue
            mid = int(i)
            d = Detection(mid, r, math.atan2(Y, X), pts, (X, Y))
            if mid not in best or r < best[mid].range:
                best[mid] = d
        return [best[i] for i in sorted(best)]

    def reading(self, frame: CameraFrame, avatar: str | None = None) -> LandmarkReading:
        """The LandmarkReading of a haa.sim CameraFrame (image, K, mount, max_range, time, avatar)."""
        f = frame
        dets = self.detect(f.image, f.K, f.mount, f.max_range)
        return LandmarkReading(
            avatar if avatar is not None else f.avatar,
            float(f.time),
            tuple(Sighting(d.landmark_id, d.range, d.bearing) for d in dets),
        )
