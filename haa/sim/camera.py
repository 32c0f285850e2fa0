"""Camera frames rendered from the 2D world by a column ray-caster, with ArUco markers on the landmarks.

The camera is a horizontal pinhole (no pitch, no roll) `CAMERA_HEIGHT` above the floor at the avatar's
centre, looking along its heading. For such a camera every image column is a vertical plane through the
camera, so one ray per column finds the nearest wall or obstacle face at depth z (distance along the optical
axis), and the face spans the rows

    v_top = cy - f (wall_height - camera_height) / z,    v_bottom = cy + f camera_height / z

exactly as a full 3D pinhole would draw it (square pixels, principal point at the image centre, pixel
centres on integer coordinates as in OpenCV). Above the walls is the dark "room", below them the floor.
Markers are textured onto their faces with exact perspective (per column depth is constant, so the
texture row of a pixel is a function of its height above the floor). Collectables (red cylinders) and other
avatars (green cylinders, shorter than the walls) are drawn in front of the walls where they are nearer;
only the nearest one per column is drawn (a simplification: a short object behind another short object in
the same column is not shown). Pixel noise (triangular over 0-6 grey levels below the true colour, 3 below on
average) comes from a seeded tile.

Landmarks carry ArUco markers (`cv2.aruco`, dictionary from the arena file, default DICT_4X4_250, one
white cell of margin): the thesis used self-similar landmarks [113], whose job — many distinct, cheaply
detected and identified, rotation- and scale-tolerant artificial landmarks — is what ArUco does in OpenCV.

Because the camera is horizontal, the floor is a plane seen through a homography. `CameraFrame.floor_homography`
maps floor points in the avatar frame (X forward, Y left, metres) to pixels; `floor_points` maps pixels back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from haa.sim.arena import MARKER_CELLS, OBSTACLE, OUTER_WALL, PLATE_CELLS, POST, WALL, Arena
from haa.sim.geometry import cast_circles, cast_segments
from haa.sim.sensors import CAMERA_HEIGHT, CameraSpec

SKY = (38, 40, 48)
FLOOR = (168, 142, 104)
KIND_COLOURS = {
    OUTER_WALL: (205, 205, 200),
    WALL: (190, 186, 168),
    OBSTACLE: (72, 108, 158),
    POST: (222, 196, 58),
}
COLLECTABLE_COLOUR = (214, 36, 30)
AVATAR_COLOUR = (46, 150, 70)
NOISE = 6  # pixel noise amplitude, grey levels

#: per-pixel labels of `render(..., labels=True)`
LABEL_SKY, LABEL_FLOOR, LABEL_STRUCTURE, LABEL_MARKER, LABEL_COLLECTABLE, LABEL_AVATAR = range(6)


@dataclass
class CameraFrame:
    """A captured image (H x W x 3 uint8, RGB) with everything needed to interpret it.

    `K`: 3x3 intrinsics; `mount`: camera position in the avatar frame (x forward, y left, z up, m) and its
    pitch (0: horizontal); `pose`: the avatar's true pose when it was taken; `odometry`: its odometry then.
    """

    image: np.ndarray
    camera: str
    K: np.ndarray
    fov: float
    max_range: float
    mount: tuple[float, float, float, float]
    time: float
    avatar: str
    pose: tuple[float, float, float]
    odometry: tuple[float, float, float]
    labels: np.ndarray | None = field(default=None, repr=False)

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    def floor_homography(self) -> np.ndarray:
        """3x3 H with [u, v, 1] ~ H [X, Y, 1] for floor points (X forward, Y left, m, avatar frame)."""
        return floor_homography(self.K, self.mount)

    def floor_points(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (k, 2) below the horizon -> floor points (k, 2) in the avatar frame (X forward, Y left)."""
        Hinv = np.linalg.inv(self.floor_homography())
        p = np.c_[np.asarray(uv, dtype=float), np.ones(len(uv))] @ Hinv.T
        return p[:, :2] / p[:, 2:3]

    def to_world(self, xy: np.ndarray, pose: tuple[float, float, float] | None = None) -> np.ndarray:
        """Points in the avatar frame -> arena frame, using `pose` (default: the true pose at capture)."""
        x, y, th = pose if pose is not None else self.pose
        c, s = math.cos(th), math.sin(th)
        xy = np.asarray(xy, dtype=float)
        return np.c_[x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]]


def intrinsics(spec: CameraSpec) -> np.ndarray:
    f = spec.focal
    return np.array([[f, 0.0, (spec.width - 1) / 2], [0.0, f, (spec.height - 1) / 2], [0.0, 0.0, 1.0]])


def floor_homography(K: np.ndarray, mount: tuple[float, float, float, float]) -> np.ndarray:
    """Homography floor (avatar frame X fwd, Y left) -> pixel for a camera at `mount` = (mx, my, height, pitch).

    Camera axes (OpenCV): x right = -Y, y down = -Z, z forward = X. Only pitch 0 is rendered by this
    simulator; the general form is kept so that a mounting with pitch reads the same way.
    """
    mx, my, hc, pitch = mount
    cp, sp = math.cos(pitch), math.sin(pitch)
    # rotation world(avatar) -> camera for a camera pitched down by `pitch`
    R = np.array([[0.0, -1.0, 0.0], [-sp, 0.0, -cp], [cp, 0.0, -sp]])
    t = -R @ np.array([mx, my, hc])
    # floor points have Z = 0: [X, Y, 1] -> R[:, :2] [X, Y] + t
    M = np.c_[R[:, 0], R[:, 1], t]
    return K @ M


def marker_plate(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker's cells with a white margin: (PLATE_CELLS, PLATE_CELLS) uint8, 0 black / 255 white."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    m = cv2.aruco.generateImageMarker(d, marker_id, MARKER_CELLS)
    margin = (PLATE_CELLS - MARKER_CELLS) // 2
    plate = np.full((PLATE_CELLS, PLATE_CELLS), 255, dtype=np.uint8)
    plate[margin : margin + MARKER_CELLS, margin : margin + MARKER_CELLS] = m
    return plate


#: colour codes of the uint8 code image (a 256-entry look-up table turns codes into RGB)
_C_SKY, _C_FLOOR, _C_BLACK, _C_WHITE, _C_COLLECTABLE, _C_AVATAR = range(6)
_SHADES = 48
_C_STRUCT = 8  # first structure code: _C_STRUCT + kind * _SHADES + shade


def _lookup_tables() -> tuple[np.ndarray, np.ndarray]:
    rgb = np.zeros((256, 3), dtype=float)
    lab = np.zeros(256, dtype=np.uint8)
    rgb[_C_SKY], lab[_C_SKY] = SKY, LABEL_SKY
    rgb[_C_FLOOR], lab[_C_FLOOR] = FLOOR, LABEL_FLOOR
    rgb[_C_BLACK], lab[_C_BLACK] = (20, 20, 20), LABEL_MARKER
    rgb[_C_WHITE], lab[_C_WHITE] = (235, 235, 235), LABEL_MARKER
    rgb[_C_COLLECTABLE], lab[_C_COLLECTABLE] = COLLECTABLE_COLOUR, LABEL_COLLECTABLE
    rgb[_C_AVATAR], lab[_C_AVATAR] = AVATAR_COLOUR, LABEL_AVATAR
    for kind, base in KIND_COLOURS.items():
        for sh in range(_SHADES):
            c = _C_STRUCT + kind * _SHADES + sh
            rgb[c] = np.asarray(base, dtype=float) * (0.55 + 0.45 * sh / (_SHADES - 1))
            lab[c] = LABEL_STRUCTURE
    # leave room for the pixel noise that is added afterwards
    lut = np.clip(np.round(rgb) - NOISE, 0, 255 - 2 * NOISE).astype(np.uint8).reshape(1, 256, 3)
    return lut, lab


class Renderer:
    """Renders camera frames of one arena (precomputes edge data, marker textures, colour tables, noise)."""

    def __init__(self, arena: Arena, seed: int = 0) -> None:
        self.arena = arena
        e = arena.edges
        self.a, self.b = e.a, e.b
        self.mid = (e.a + e.b) / 2
        self.half = e.length / 2
        self.normal = e.normal
        self.length = e.length
        self.kind_code = (_C_STRUCT + e.kind * _SHADES).astype(np.int32)
        self.wall_height = arena.wall_height
        ms = arena.markers
        self.m_edge = np.array([m.edge for m in ms], dtype=int)
        self.m_s0 = np.array([m.s0 for m in ms], dtype=float)
        self.m_plate = np.array([m.plate for m in ms], dtype=float)
        plates: dict[int, np.ndarray] = {}
        for m in ms:
            if m.id not in plates:
                plates[m.id] = marker_plate(arena.marker_dictionary, m.id)
        tex = np.stack([plates[m.id] for m in ms]) if ms else np.zeros((0, PLATE_CELLS, PLATE_CELLS), np.uint8)
        self.m_flat = np.where(tex > 127, _C_WHITE, _C_BLACK).astype(np.uint8).ravel()
        self.has_marker = np.zeros(len(e), dtype=bool)
        self.has_marker[self.m_edge] = True
        lut, self.label_lut = _lookup_tables()
        self.luts = [np.ascontiguousarray(lut[0, :, i]) for i in range(3)]
        rng = np.random.default_rng([seed, 0x5EED])
        # noise tile 2x the largest frame; a frame takes a window at a seeded offset
        half = NOISE // 2
        size = (960, 1280, 3)
        self.noise = rng.integers(0, half + 1, size, dtype=np.uint8) + rng.integers(
            0, NOISE - half + 1, size, dtype=np.uint8
        )
        self._rays: dict[tuple[int, int, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _columns(self, spec: CameraSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (spec.width, spec.height, spec.fov)
        if key not in self._rays:
            cx = (spec.width - 1) / 2
            a = np.arctan2(cx - np.arange(spec.width), spec.focal)
            self._rays[key] = (a, np.cos(a), np.arange(spec.height, dtype=np.int32)[:, None])
        return self._rays[key]

    def _front_edges(self, x: float, y: float, th: float, fov: float) -> np.ndarray:
        """Indices of edges that can be the first hit: facing the camera and not wholly behind it."""
        rx, ry = self.mid[:, 0] - x, self.mid[:, 1] - y
        facing = self.normal[:, 0] * rx + self.normal[:, 1] * ry < 0
        ahead = math.cos(th) * rx + math.sin(th) * ry > -self.half - 1e-6
        return np.nonzero(facing & ahead)[0]

    def render(
        self,
        pose: tuple[float, float, float],
        spec: CameraSpec,
        objects: np.ndarray | None = None,
        noise_offset: tuple[int, int] | None = None,
        labels: bool = False,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Image (H, W, 3) uint8 RGB seen from `pose`, and optionally the label image (LABEL_*).

        `objects`: short cylinders in front of the walls, rows (x, y, radius, height, label) with label
        LABEL_COLLECTABLE or LABEL_AVATAR (leave out the capturing avatar itself).
        """
        W, H = spec.width, spec.height
        f = spec.focal
        cy = (H - 1) / 2
        hc = CAMERA_HEIGHT
        x, y, th = pose
        ang, cosa, R = self._columns(spec)
        dirs = np.stack([np.cos(th + ang), np.sin(th + ang)], axis=1)
        cand = self._front_edges(x, y, th, spec.fov)
        t, ei, s = cast_segments(x, y, dirs, self.a[cand], self.b[cand])
        hit = ei >= 0
        e0 = cand[np.where(hit, ei, 0)] if len(cand) else np.zeros(W, dtype=int)
        z = np.maximum(np.where(hit, t, 1e6) * cosa, 1e-3)
        r_top = np.clip(np.ceil(cy - f * (self.wall_height - hc) / z), 0, H).astype(np.int32)
        r_bot = np.clip(np.floor(cy + f * hc / z) + 1, 0, H).astype(np.int32)  # first floor row
        # wall colour: the kind's colour shaded by the angle of incidence
        inc = np.abs(dirs[:, 0] * self.normal[e0, 0] + dirs[:, 1] * self.normal[e0, 1])
        wcode = (self.kind_code[e0] + np.round(inc * (_SHADES - 1)).astype(np.int32)).astype(np.uint8)
        wcode[~hit] = _C_SKY
        code = np.where(
            r_top[None, :] > R, np.uint8(_C_SKY), np.where(r_bot[None, :] > R, wcode[None, :], np.uint8(_C_FLOOR))
        )

        # markers on the faces hit
        mcols = np.nonzero(hit & self.has_marker[e0])[0]
        if len(mcols) and len(self.m_edge):
            sm = s[mcols] * self.length[e0[mcols]]
            rel = sm[:, None] - self.m_s0[None, :]
            on = (self.m_edge[None, :] == e0[mcols][:, None]) & (rel >= 0) & (rel < self.m_plate[None, :])
            has = on.any(axis=1)
            mcols = mcols[has]
            if len(mcols):
                mi = np.argmax(on[has], axis=1)
                plate = self.m_plate[mi]
                tc = np.clip((rel[has, mi] / plate * PLATE_CELLS).astype(np.int32), 0, PLATE_CELLS - 1)
                top = self.arena.marker_height + plate / 2
                # texture row of pixel row r (exact for this column's depth): trf = c0 + c1 r, in [0, PLATE_CELLS)
                k = PLATE_CELLS / plate
                c1 = z[mcols] / f * k
                c0 = (top - hc) * k - cy * c1
                lo = np.maximum(np.ceil(-c0 / c1), r_top[mcols]).astype(np.int32)
                hi = np.minimum(np.ceil((PLATE_CELLS - c0) / c1), r_bot[mcols]).astype(np.int32)
                rlo, rhi = max(0, int(lo.min())), min(H, int(hi.max()))
                if rhi > rlo:
                    Rb = R[rlo:rhi]
                    trf = c0.astype(np.float32)[None, :] + c1.astype(np.float32)[None, :] * Rb
                    tr = np.clip(trf.astype(np.int32), 0, PLATE_CELLS - 1)
                    flat = (mi * PLATE_CELLS * PLATE_CELLS + tc)[None, :] + tr * PLATE_CELLS
                    val = np.take(self.m_flat, flat)
                    inside = (Rb >= lo[None, :]) & (Rb < hi[None, :])
                    block = code[rlo:rhi, mcols]
                    code[rlo:rhi, mcols] = np.where(inside, val, block)

        # short objects (collectables, other avatars) nearer than the wall
        if objects is not None and len(objects):
            to, oi = cast_circles(x, y, dirs, objects[:, :2], objects[:, 2])
            near = (oi >= 0) & (to < np.where(hit, t, np.inf))
            ocols = np.nonzero(near)[0]
            if len(ocols):
                oo = objects[oi[ocols]]
                zo = np.maximum(to[ocols] * cosa[ocols], 1e-3)
                o_top = np.ceil(cy - f * (oo[:, 3] - hc) / zo).astype(np.int32)
                o_bot = np.floor(cy + f * hc / zo).astype(np.int32) + 1
                m = (o_top[None, :] <= R) & (o_bot[None, :] > R)
                ocode = np.where(oo[:, 4].astype(int) == LABEL_COLLECTABLE, _C_COLLECTABLE, _C_AVATAR).astype(np.uint8)
                code[:, ocols] = np.where(m, ocode[None, :], code[:, ocols])

        img = cv2.merge([cv2.LUT(code, lut) for lut in self.luts])
        if noise_offset is not None:
            oy, ox = noise_offset
            img = cv2.add(img, np.ascontiguousarray(self.noise[oy : oy + H, ox : ox + W]))
        else:
            img += NOISE
        lab = self.label_lut[code] if labels else None
        return img, lab
