"""Sensor models: each reading gives a map update and a per-particle observation density g(y | x) (§5.1.4).

Readings (plain frozen dataclasses, validated on construction with a one-line error naming the field):

* `SonarReading` — one scan of the sonar ring: an echo per sonar (bearing on the avatar, range or None for
  no echo within max_range), the cone's field of view and max range (Table 6.2-4: 0.349 rad, 2 m).
* `LandmarkReading` — the landmarks found in one camera image: (id, range, bearing) sightings (noise ∝
  range, Table 6.2-4).

A reading is the unit of processing the strategies schedule (one sensor-processing job in the thesis'
system: a sonar scan, a camera image, ...); it gives one observation density, the sum of its parts' log
densities.
* `CooccupancyReading` — "if the area is occupied by the avatar it is not occupied by an obstacle"
  (AgentSensorCooccupancy): the disc under the avatar is free.
* `FloorReading` — a floor region found in a camera image and already mapped to the ground plane (the
  FloorFinder's output): a polygon in the avatar frame whose inside is free.
* `CollectablesReading` — the collectables (Forage) found in one camera image: (range, bearing) of each
  one's centre, no id. It gives no density and no grid update: the team's collectable map
  (haa.slam.collectables) places and identifies them with the avatar's estimated pose at the reading's time.

Grid sensors use *belief templates*: a fixed set of sample points in the avatar frame, one per cell area
(polar sampling for cones), each with a sensor model value p(s|C). Per reading the template is moved to
every particle's pose at the reading time (an (N, K) array operation), then
`OccupancyGrid.log_likelihood` gives log g per particle (computed against the map *before* this reading is
added, so a reading never confirms itself) and `OccupancyGrid.mixture_update` applies the template at each
particle adjusted by its weight.

The sonar template follows the idea of Howard & Kitchen (thesis ref. [85], "Generating sonar maps in highly
specular environments"): the cone in front of the echo is evidence of free space, strongest on the axis
and fading to the cone's edges; the arc at the echo range is evidence of occupancy, but weaker than the
free evidence because only one point of the arc reflected; a reading with no echo is weak evidence of free
space only (in a specular environment a missing echo often means a glancing reflection, not empty space).
The sonar density is, by default, the template's agreement with the map (`OccupancyGrid.log_likelihood`)
tempered to τ = 0.05; `density="endpoint"` gives a likelihood-field alternative (distance from the echo arc
to the nearest mapped obstacle). Co-occupancy and floor regions penalize particles that would put a seen-free
region on mapped obstacles (`OccupancyGrid.occupancy_penalty`). docs/slam.md reports how much these grid
densities help on the simulator's recordings (little: the landmarks carry the localization).

Landmarks are point features with a shared estimate per id (mean and 2×2 covariance, `LandmarkMap`) — the
thesis reports "landmark error" and "landmark covariance". For a sighting, particle i implies the landmark
at p_i = (x_i + r cos(θ_i + b), y_i + r sin(θ_i + b)) with the sensor covariance R_i (range σ_r, bearing
σ_b, rotated to the world); log g_i is the Gaussian log density of p_i − μ under Σ_L + R_i. The estimate is
then updated (Kalman) with the weighted mixture of the p_i: mean Σ w_i p_i, covariance the weighted
scatter plus R. A first sighting only creates the estimate (no density: nothing to compare with).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from haa.slam.grid import OccupancyGrid


def _finite(obj: object, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if not math.isfinite(v):
            raise ValueError(f"{type(obj).__name__}.{name}: must be finite, got {v}")


@dataclass(frozen=True)
class SonarEcho:
    """One sonar of a scan: its bearing on the avatar and the echo range (None: nothing within max_range)."""

    bearing: float  # rad, relative to the avatar heading
    range: float | None  # m


@dataclass(frozen=True)
class SonarReading:
    """One scan of an avatar's sonar ring (Table 6.2-4: period 1 s), processed as one reading."""

    avatar: str
    t: float
    echoes: tuple[SonarEcho, ...]
    fov: float = 0.349
    max_range: float = 2.0
    kind: str = field(default="sonar", init=False)

    def __post_init__(self) -> None:
        _finite(self, "t", "fov", "max_range")
        if not 0 < self.fov < math.pi:
            raise ValueError(f"SonarReading.fov: must be in (0, π), got {self.fov}")
        if not self.max_range > 0:
            raise ValueError(f"SonarReading.max_range: must be > 0, got {self.max_range}")
        if not self.echoes:
            raise ValueError("SonarReading.echoes: needs at least one echo")
        for i, e in enumerate(self.echoes):
            if not math.isfinite(e.bearing):
                raise ValueError(f"SonarReading.echoes[{i}].bearing: must be finite, got {e.bearing}")
            if e.range is not None and not (math.isfinite(e.range) and 0 <= e.range <= self.max_range):
                raise ValueError(
                    f"SonarReading.echoes[{i}].range: must be in [0, max_range={self.max_range}] or None, got {e.range}"
                )


@dataclass(frozen=True)
class Sighting:
    """A landmark found in a camera image: id, range (m), bearing (rad, relative to the heading)."""

    landmark_id: int
    range: float
    bearing: float


@dataclass(frozen=True)
class LandmarkReading:
    """The landmarks found in one camera image (possibly none), processed as one reading."""

    avatar: str
    t: float
    sightings: tuple[Sighting, ...]
    kind: str = field(default="landmark", init=False)

    def __post_init__(self) -> None:
        _finite(self, "t")
        for i, g in enumerate(self.sightings):
            if not (math.isfinite(g.range) and g.range > 0):
                raise ValueError(f"LandmarkReading.sightings[{i}].range: must be > 0, got {g.range}")
            if not math.isfinite(g.bearing):
                raise ValueError(f"LandmarkReading.sightings[{i}].bearing: must be finite, got {g.bearing}")


@dataclass(frozen=True)
class CooccupancyReading:
    avatar: str
    t: float
    radius: float = 0.15  # m, the avatar's footprint
    kind: str = field(default="cooccupancy", init=False)

    def __post_init__(self) -> None:
        _finite(self, "t", "radius")
        if not self.radius > 0:
            raise ValueError(f"CooccupancyReading.radius: must be > 0, got {self.radius}")


@dataclass(frozen=True)
class FloorReading:
    avatar: str
    t: float
    polygon: tuple[tuple[float, float], ...]  # avatar frame (x forward, y left), metres
    #: per vertex (or empty): the floor ends there at something standing on it — an obstacle's foot, the
    #: first non-floor pixel above the floor run — rather than at the camera's range limit or the image bottom
    occupied: tuple[bool, ...] = ()
    kind: str = field(default="floor", init=False)

    def __post_init__(self) -> None:
        _finite(self, "t")
        if len(self.polygon) < 3:
            raise ValueError(f"FloorReading.polygon: needs at least 3 vertices, got {len(self.polygon)}")
        if not all(len(v) == 2 and math.isfinite(v[0]) and math.isfinite(v[1]) for v in self.polygon):
            raise ValueError("FloorReading.polygon: vertices must be finite (x, y) pairs")
        if self.occupied and len(self.occupied) != len(self.polygon):
            raise ValueError(f"FloorReading.occupied: {len(self.occupied)} flags for {len(self.polygon)} vertices")


@dataclass(frozen=True)
class RangeBearing:
    """Where something is seen from the avatar's centre: range (m), bearing (rad, relative to the heading)."""

    range: float
    bearing: float


@dataclass(frozen=True)
class CollectablesReading:
    """The collectables found in one camera image (haa.control.collectables), processed as one reading."""

    avatar: str
    t: float
    sightings: tuple[RangeBearing, ...]
    kind: str = field(default="collectables", init=False)

    def __post_init__(self) -> None:
        _finite(self, "t")
        for i, g in enumerate(self.sightings):
            if not isinstance(g, RangeBearing):
                raise ValueError(f"CollectablesReading.sightings[{i}]: must be a RangeBearing, got {type(g).__name__}")
            if not (math.isfinite(g.range) and g.range > 0):
                raise ValueError(f"CollectablesReading.sightings[{i}].range: must be > 0, got {g.range}")
            if not math.isfinite(g.bearing):
                raise ValueError(f"CollectablesReading.sightings[{i}].bearing: must be finite, got {g.bearing}")


Reading = SonarReading | LandmarkReading | CooccupancyReading | FloorReading | CollectablesReading


@dataclass
class Template:
    """Belief template: sample points in the avatar frame and their p(s|C)."""

    points: np.ndarray  # (K, 2)
    p: np.ndarray  # (K,)
    #: for a cached template, the arguments it was built from (a cache key is rounded, the template is not):
    #: the replica's checkpoint rebuilds the caches from these (haa.slam.replica)
    origin: tuple[float, ...] | None = field(default=None, repr=False)


def place(states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World coordinates (N, K) of avatar-frame points for every particle state (N, 3)."""
    c, s = np.cos(states[:, 2])[:, None], np.sin(states[:, 2])[:, None]
    px, py = points[None, :, 0], points[None, :, 1]
    return states[:, 0:1] + c * px - s * py, states[:, 1:2] + s * px + c * py


def template_cells(grid: OccupancyGrid, states: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Flat cell indices (N, K) of the template points placed at every particle (float32 arithmetic)."""
    res = grid.spec.resolution
    u0, v0 = grid.cell_units(states[:, 0], states[:, 1])
    th = states[:, 2]
    c = np.cos(th).astype(np.float32)[:, None]
    s = np.sin(th).astype(np.float32)[:, None]
    qx = (points[:, 0] / res).astype(np.float32)[None, :]
    qy = (points[:, 1] / res).astype(np.float32)[None, :]
    u = u0.astype(np.float32)[:, None] + (c * qx - s * qy)
    v = v0.astype(np.float32)[:, None] + (s * qx + c * qy)
    return grid.flat_from_units(u, v)


def apply_template(
    grid: OccupancyGrid, states: np.ndarray, weights: np.ndarray, tpl: Template, temper: float, update: bool = True
) -> np.ndarray:
    """log g per particle against the current map, then (optionally) the weighted map update."""
    flat = template_cells(grid, states, tpl.points)
    log_g = grid.log_likelihood(flat, tpl.p, temper)
    if update:
        grid.mixture_update(flat, tpl.p, weights)
    return log_g


def apply_free_region(
    grid: OccupancyGrid, states: np.ndarray, weights: np.ndarray, tpl: Template, temper: float
) -> np.ndarray:
    """A region seen free: log g penalizes particles that put it on mapped obstacles; then the map update."""
    flat = template_cells(grid, states, tpl.points)
    log_g = grid.occupancy_penalty(flat, temper)
    grid.mixture_update(flat, tpl.p, weights)
    return log_g


def _cone_points(d_min: float, d_max: float, half: float, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Polar samples (distance, angle) of a cone, about one per cell area."""
    n_r = max(1, math.ceil((d_max - d_min) / res))
    ds = d_min + (np.arange(n_r) + 0.5) * (d_max - d_min) / n_r
    dd, aa = [], []
    for d in ds:
        n_a = max(1, math.ceil(2 * half * d / res))
        dd.append(np.full(n_a, d))
        aa.append(((np.arange(n_a) + 0.5) / n_a * 2 - 1) * half)
    return np.concatenate(dd), np.concatenate(aa)


@dataclass
class SonarModel:
    """Cone belief template for one sonar echo (see the module docstring)."""

    resolution: float = 0.1
    p_free: float = 0.30  # on the axis, inside the echo range
    p_occ: float = 0.72  # on the axis, at the echo range
    p_free_no_echo: float = 0.42  # on the axis, for a reading without an echo
    arc_width: float = 0.1  # m, thickness of the occupied arc
    mount_radius: float = 0.0  # m, sonar distance from the avatar centre along its bearing
    density: str = "template"  # "template" (map agreement) | "endpoint" (likelihood field of the echo arcs)
    temper: float = 0.05  # for density="template" (docs/slam.md: why so small)
    sigma_hit: float = 0.08  # m, for density="endpoint" (plus 3% of the range)
    max_miss: float = 0.4  # m, an echo farther than this from any mapped obstacle counts as this far
    arc_samples: int = 5
    _cache: OrderedDict = field(default_factory=OrderedDict, repr=False)

    def echo_template(self, e: SonarEcho, fov: float, max_range: float) -> Template:
        """The belief template of one echo (cached by quantized range, bearing and cone)."""
        rq = None if e.range is None else round(e.range / (self.resolution / 4))
        key = (rq, round(e.bearing, 4), round(fov, 4), round(max_range, 3))
        tpl = self._cache.get(key)
        if tpl is not None:
            self._cache.move_to_end(key)
            return tpl
        half = fov / 2
        res = self.resolution
        if rq is None:
            d, a = _cone_points(0.0, max_range, half, res)
            fall = 1.0 - 0.5 * (a / half) ** 2
            p = 0.5 - (0.5 - self.p_free_no_echo) * fall
        else:
            rng = rq * (self.resolution / 4)
            d_free_end = max(0.0, rng - self.arc_width / 2)
            pts_d, pts_a, pts_p = [], [], []
            if d_free_end > 0:
                d, a = _cone_points(0.0, d_free_end, half, res)
                fall = 1.0 - 0.5 * (a / half) ** 2
                pts_d.append(d)
                pts_a.append(a)
                pts_p.append(0.5 - (0.5 - self.p_free) * fall)
            d, a = _cone_points(d_free_end, min(rng + self.arc_width / 2, max_range + self.arc_width / 2), half, res)
            fall = 1.0 - 0.5 * (a / half) ** 2
            pts_d.append(d)
            pts_a.append(a)
            pts_p.append(0.5 + (self.p_occ - 0.5) * fall)
            d, a, p = np.concatenate(pts_d), np.concatenate(pts_a), np.concatenate(pts_p)
        ang = e.bearing + a
        mx, my = self.mount_radius * math.cos(e.bearing), self.mount_radius * math.sin(e.bearing)
        pts = np.stack([mx + d * np.cos(ang), my + d * np.sin(ang)], axis=1)
        tpl = Template(pts, p, (math.nan if e.range is None else e.range, e.bearing, fov, max_range))
        self._cache[key] = tpl
        if len(self._cache) > 4096:
            self._cache.popitem(last=False)
        return tpl

    def template(self, r: SonarReading) -> Template:
        """The scan's template: its echoes' templates side by side (one array operation per scan)."""
        parts = [self.echo_template(e, r.fov, r.max_range) for e in r.echoes]
        if len(parts) == 1:
            return parts[0]
        return Template(np.concatenate([t.points for t in parts]), np.concatenate([t.p for t in parts]))

    def arc_points(self, r: SonarReading) -> tuple[np.ndarray, np.ndarray]:
        """Avatar-frame points on the echo arcs (E·S, 2) and each echo's σ (E,); only echoes with a range."""
        hits = [e for e in r.echoes if e.range is not None]
        if not hits:
            return np.zeros((0, 2)), np.zeros(0)
        half = r.fov / 2
        offs = np.linspace(-half, half, self.arc_samples)
        pts = []
        for e in hits:
            assert e.range is not None
            a = e.bearing + offs
            mx, my = self.mount_radius * math.cos(e.bearing), self.mount_radius * math.sin(e.bearing)
            pts.append(np.stack([mx + e.range * np.cos(a), my + e.range * np.sin(a)], axis=1))
        sig = np.array([math.hypot(self.sigma_hit, 0.03 * e.range) for e in hits if e.range is not None])
        return np.concatenate(pts), sig

    def endpoint_log_g(self, r: SonarReading, states: np.ndarray, grid: OccupancyGrid) -> np.ndarray:
        """Likelihood field: −d²/2σ² per echo, d = distance from the echo arc to the nearest mapped obstacle."""
        pts, sig = self.arc_points(r)
        if len(sig) == 0:
            return np.zeros(states.shape[0])
        df = grid.distance_field()
        d = df[template_cells(grid, states, pts)].reshape(states.shape[0], len(sig), self.arc_samples).min(axis=2)
        d = np.minimum(d, self.max_miss)
        return -((d / sig) ** 2).sum(axis=1, dtype=np.float64) / 2.0

    def apply(self, r: SonarReading, states: np.ndarray, weights: np.ndarray, grid: OccupancyGrid) -> np.ndarray:
        if self.density == "template":
            return apply_template(grid, states, weights, self.template(r), self.temper)
        log_g = self.endpoint_log_g(r, states, grid)  # against the map before this reading
        tpl = self.template(r)
        grid.mixture_update(template_cells(grid, states, tpl.points), tpl.p, weights)
        return log_g


@dataclass
class CooccupancyModel:
    """The disc under the avatar is free."""

    resolution: float = 0.1
    p_free: float = 0.25
    temper: float = 1.0
    #: "free": particles that put the disc on mapped obstacles are penalized (the default); "none": map only
    #: (docs/slam.md "In the team, the obstacle marks": with the floor finder's marks mapped, the one-sided
    #: penalty pulled AF-1's seekers off their true poses — a disc touching a thin panel overlaps its cell)
    density: Literal["free", "none"] = "free"
    _cache: dict = field(default_factory=dict, repr=False)

    def template(self, radius: float) -> Template:
        key = round(radius, 3)
        tpl = self._cache.get(key)
        if tpl is None:
            res = self.resolution
            k = math.ceil(radius / res)
            g = np.arange(-k, k + 1) * res
            xx, yy = np.meshgrid(g, g)
            inside = xx**2 + yy**2 <= radius**2
            pts = np.stack([xx[inside], yy[inside]], axis=1)
            tpl = Template(pts, np.full(len(pts), self.p_free), (radius,))
            self._cache[key] = tpl
        return tpl

    def apply(self, r: CooccupancyReading, states: np.ndarray, weights: np.ndarray, grid: OccupancyGrid) -> np.ndarray:
        tpl = self.template(r.radius)
        if self.density == "none":
            grid.mixture_update(template_cells(grid, states, tpl.points), tpl.p, weights)
            return np.zeros(len(states))
        return apply_free_region(grid, states, weights, tpl, self.temper)


def points_in_polygon(px: np.ndarray, py: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule, vectorized over the points."""
    inside = np.zeros(px.shape, dtype=bool)
    x0, y0 = poly[-1]
    for x1, y1 in poly:
        crosses = (y1 > py) != (y0 > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = x1 + (py - y1) * (x0 - x1) / (y0 - y1)
        inside ^= crosses & (px < xint)
        x0, y0 = x1, y1
    return inside


@dataclass
class FloorModel:
    """A floor polygon (avatar frame) from the camera: its inside is free; where the reading flags vertices
    as an obstacle's foot (`FloorReading.occupied`), the polygon's edges between two flagged vertices (no
    longer than `max_edge`: a longer one spans a depth jump, an occlusion, not a wall) and lone flagged
    vertices are occupied (`p_occ`), sampled once per cell length and placed `occ_offset` beyond the foot,
    along the ray from the avatar, so that they fall in the obstacle's cell rather than in the last floor cell.

    Density: particles that would put the free region on mapped obstacles are penalized (as co-occupancy);
    with occupied points, also particles that would put the obstacle's foot on mapped free space — the
    two-sided agreement a range reading gives: τ Σ_free min(0, log 2(1 − m)) + τ Σ_occ min(0, log 2m).
    Without flags (`occupied` empty), or with `p_occ` None (the default), the template and the density are
    exactly the free-region ones: measured on AF-1 logs replayed with the flags (docs/slam.md "In the running
    team"), the obstacle marks lower map coverage and accuracy (0.85 / 0.92 → 0.79 / 0.87) and the density
    worsens localization (0.51 → 0.75 m) while the avatars are 0.3-0.5 m off — the marks land in front of
    the walls, in reachable cells. Turn them on (p_occ 0.7) once localization is at the thesis' level.
    `density` says what the reading does to the particles: "free" (the free region's one-sided penalty;
    the default), "two-sided" (as described above, with obstacle feet) or "none" (the map only; the running
    team's choice with the marks on, docs/slam.md "In the team, the obstacle marks")."""

    resolution: float = 0.1
    p_free: float = 0.35
    temper: float = 0.5
    p_occ: float | None = None
    max_edge: float = 0.3  # m
    occ_offset: float = 0.05  # m
    #: what the reading says about the particles: "free" (its free region must not lie on mapped obstacles;
    #: the default), "two-sided" (and its obstacle feet not on mapped free floor) or "none" (map only)
    density: Literal["free", "two-sided", "none"] = "free"

    def template(self, r: FloorReading) -> Template:
        poly = np.asarray(r.polygon, dtype=np.float64)
        res = self.resolution
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        gx = np.arange(lo[0] + res / 2, hi[0], res)
        gy = np.arange(lo[1] + res / 2, hi[1], res)
        xx, yy = np.meshgrid(gx, gy)
        inside = points_in_polygon(xx, yy, poly)
        pts = np.stack([xx[inside], yy[inside]], axis=1)
        return Template(pts, np.full(len(pts), self.p_free))

    def obstacle_points(self, r: FloorReading) -> np.ndarray:
        """(K, 2) avatar-frame points on the obstacles' feet the reading flags (module docstring)."""
        if not any(r.occupied):
            return np.zeros((0, 2))
        poly = np.asarray(r.polygon, dtype=np.float64)
        occ = np.asarray(r.occupied, dtype=bool)
        n = len(poly)
        out: list[np.ndarray] = []
        alone = occ.copy()
        for i in range(n):
            j = (i + 1) % n
            if not (occ[i] and occ[j]):
                continue
            a, b = poly[i], poly[j]
            length = float(np.hypot(*(b - a)))
            if length > self.max_edge:
                continue
            alone[i] = alone[j] = False
            k = max(1, math.ceil(length / self.resolution))
            f = (np.arange(k) + 0.5)[:, None] / k
            out.append(a + f * (b - a))
        if alone.any():
            out.append(poly[alone])
        pts = np.concatenate(out)
        d = np.hypot(pts[:, 0], pts[:, 1])
        return pts * ((d + self.occ_offset) / np.maximum(d, 1e-9))[:, None]

    def apply(self, r: FloorReading, states: np.ndarray, weights: np.ndarray, grid: OccupancyGrid) -> np.ndarray:
        tpl = self.template(r)
        occ = self.obstacle_points(r) if self.p_occ is not None else np.zeros((0, 2))
        if len(occ) == 0 and self.density != "none":
            return apply_free_region(grid, states, weights, tpl, self.temper)
        flat_free = template_cells(grid, states, tpl.points)
        flat_occ = template_cells(grid, states, occ)
        if self.density == "none":
            log_g = np.zeros(len(states))
        else:
            log_g = grid.occupancy_penalty(flat_free, self.temper)
        if self.density == "two-sided":
            m = grid.prob_flat_at(flat_occ)
            log_g = log_g + self.temper * np.minimum(0.0, np.log(2.0 * m + 1e-6)).sum(axis=1, dtype=np.float64)
        if len(occ) == 0:
            grid.mixture_update(flat_free, tpl.p, weights)
            return log_g
        p = np.concatenate([tpl.p, np.full(len(occ), self.p_occ)])
        grid.mixture_update(np.concatenate([flat_free, flat_occ], axis=1), p, weights)
        return log_g


@dataclass
class Contribution:
    """One source's sightings of one landmark, in information form (see `LandmarkMap`).

    info = Σ W_i, vec = Σ W_i z_i with W_i = (sighting i's covariance)⁻¹; pose_w = Σ tr W_i and pose_sum =
    Σ tr W_i · s_i, where s_i is the std of the pose part of sighting i (the particle scatter of the implied
    landmark positions). The source's estimate is m = info⁻¹ vec with covariance info⁻¹ + s̄² I, s̄ =
    pose_sum / pose_w: its pose errors are treated as fully correlated, so they do not average out.
    """

    info_xx: float = 0.0
    info_xy: float = 0.0
    info_yy: float = 0.0
    vec_x: float = 0.0
    vec_y: float = 0.0
    pose_w: float = 0.0
    pose_sum: float = 0.0

    def add(self, z: tuple[float, float], cov: tuple[float, float, float], pose_std: float) -> None:
        cxx, cyy, cxy = cov
        det = cxx * cyy - cxy * cxy
        wxx, wyy, wxy = cyy / det, cxx / det, -cxy / det
        self.info_xx += wxx
        self.info_yy += wyy
        self.info_xy += wxy
        self.vec_x += wxx * z[0] + wxy * z[1]
        self.vec_y += wxy * z[0] + wyy * z[1]
        tr = wxx + wyy
        self.pose_w += tr
        self.pose_sum += tr * pose_std

    def estimate(self) -> tuple[float, float, float, float, float]:
        """(mx, my, cxx, cyy, cxy) of this source's estimate."""
        det = self.info_xx * self.info_yy - self.info_xy * self.info_xy
        cxx, cyy, cxy = self.info_yy / det, self.info_xx / det, -self.info_xy / det
        mx = cxx * self.vec_x + cxy * self.vec_y
        my = cxy * self.vec_x + cyy * self.vec_y
        p = self.pose_sum / self.pose_w
        return mx, my, cxx + p * p, cyy + p * p, cxy


@dataclass
class Landmark:
    mean: np.ndarray  # (2,)
    cov: np.ndarray  # (2, 2)
    sightings: int = 1
    sources: dict[tuple[str, int], Contribution] = field(default_factory=dict)


class LandmarkMap:
    """Landmark position estimates (mean, covariance) by id, shared by all avatars.

    **Honest uncertainty** (issue 16; docs/slam.md "Landmark map"). A sighting's implied position has two
    error parts: the sensor's (range and bearing noise: independent from sighting to sighting) and the
    observer's pose error (the particle scatter), which one avatar's sightings *share* — fusing them as
    independent measurements (a plain Kalman update) made the map ten to a hundred times too sure of itself.
    So the map keeps one `Contribution` per *source* — an avatar (default `window=inf`), or an avatar within
    a time window of `window` seconds (by the sighting's time, so the result does not depend on the
    processing order) — in which sightings
    are accumulated in information form but the pose part is treated as fully correlated (a floor that
    does not shrink with more sightings), and the landmark estimate is the information-weighted fusion of
    its sources' estimates, which are taken as independent (different avatars, or one avatar minutes
    apart, have largely independent pose errors). With `window=None` every sighting is its own source:
    the plain Kalman fusion the library used before. `gate`: a chi-square threshold on the innovation
    (z − mean under the sighting's + the estimate's covariance); a sighting beyond it is not fused
    (counted in `gated`).

    The map is still one shared map of the team (thesis §5.2.3, kept in the DDB by the control system):
    a source's contribution is a small record (seven numbers) written by one avatar's SLAM agent, and the
    estimate is their fusion, recomputed by whoever reads a landmark.
    """

    def __init__(self, window: float | None = math.inf, gate: float | None = None) -> None:
        if window is not None and not window > 0:
            raise ValueError(f"window: must be > 0 s or None, got {window}")
        if gate is not None and not gate > 0:
            raise ValueError(f"gate: must be > 0 or None, got {gate}")
        self.window = window
        self.gate = gate
        self.gated = 0  # sightings not fused: innovation beyond the gate
        self.landmarks: dict[int, Landmark] = {}
        self._n = 0

    def __len__(self) -> int:
        return len(self.landmarks)

    def get(self, lid: int) -> Landmark | None:
        return self.landmarks.get(lid)

    def fuse(
        self,
        lid: int,
        mean: np.ndarray,
        cov: np.ndarray,
        pose_std: float = 0.0,
        avatar: str = "",
        t: float = 0.0,
    ) -> None:
        """Add one sighting's implied position (mean, cov; `pose_std` of it is the observer's pose part)."""
        if self.window is None:  # every sighting independent, its pose part already in cov: plain Kalman
            self._n += 1
            key = ("", self._n)
            pose_std = 0.0
        elif math.isinf(self.window):
            key = (avatar, 0)
        else:
            key = (avatar, math.floor(t / self.window))
        z = (float(mean[0]), float(mean[1]))
        c = (float(cov[0, 0]), float(cov[1, 1]), float(cov[0, 1]))
        lm = self.landmarks.get(lid)
        if lm is None:
            src = Contribution()
            src.add(z, c, pose_std)
            mx, my, cxx, cyy, cxy = src.estimate()
            self.landmarks[lid] = Landmark(np.array([mx, my]), np.array([[cxx, cxy], [cxy, cyy]]), 1, {key: src})
            return
        if self.gate is not None:  # chi-square gate on the innovation (2 dof)
            ex, ey = z[0] - float(lm.mean[0]), z[1] - float(lm.mean[1])
            sxx, syy, sxy = c[0] + float(lm.cov[0, 0]), c[1] + float(lm.cov[1, 1]), c[2] + float(lm.cov[0, 1])
            if (syy * ex * ex - 2 * sxy * ex * ey + sxx * ey * ey) / (sxx * syy - sxy * sxy) > self.gate:
                self.gated += 1
                return
        src = lm.sources.get(key)
        if src is None:
            src = lm.sources[key] = Contribution()
        src.add(z, c, pose_std)
        ixx = ixy = iyy = vx = vy = 0.0
        for sc in lm.sources.values():
            mx, my, cxx, cyy, cxy = sc.estimate()
            det = cxx * cyy - cxy * cxy
            wxx, wyy, wxy = cyy / det, cxx / det, -cxy / det
            ixx += wxx
            iyy += wyy
            ixy += wxy
            vx += wxx * mx + wxy * my
            vy += wxy * mx + wyy * my
        det = ixx * iyy - ixy * ixy
        cxx, cyy, cxy = iyy / det, ixx / det, -ixy / det
        lm.mean = np.array([cxx * vx + cxy * vy, cxy * vx + cyy * vy])
        lm.cov = np.array([[cxx, cxy], [cxy, cyy]])
        lm.sightings += 1

    def errors(self, truth: dict[int, tuple[float, float]]) -> dict[str, float]:
        """Landmark error (mean distance to the truth) and covariance (mean sqrt(trace Σ)), §7.1 tables."""
        ids = [i for i in self.landmarks if i in truth]
        if not ids:
            return {"landmarks": 0, "landmark_error": math.nan, "landmark_cov": math.nan}
        err = [float(np.hypot(*(self.landmarks[i].mean - np.asarray(truth[i])))) for i in ids]
        cov = [math.sqrt(float(np.trace(self.landmarks[i].cov))) for i in ids]
        return {"landmarks": len(ids), "landmark_error": float(np.mean(err)), "landmark_cov": float(np.mean(cov))}


@dataclass
class LandmarkModel:
    """Range/bearing landmark sightings: σ_range = range_frac · range (≥ min_sigma), σ_bearing."""

    range_frac: float = 0.09
    sigma_bearing: float = 0.05
    min_sigma: float = 0.02

    def sensor_cov(self, g: Sighting, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-frame covariance (xx, yy, xy) of the implied landmark position, per direction phi."""
        sr = max(self.range_frac * g.range, self.min_sigma) ** 2
        st = max(g.range * self.sigma_bearing, self.min_sigma) ** 2
        c, s = np.cos(phi), np.sin(phi)
        return sr * c * c + st * s * s, sr * s * s + st * c * c, (sr - st) * c * s

    def apply_sighting(
        self,
        g: Sighting,
        states: np.ndarray,
        weights: np.ndarray,
        landmarks: LandmarkMap,
        avatar: str = "",
        t: float = 0.0,
    ) -> np.ndarray | None:
        """log g of one sighting (None for a first sighting), then the landmark estimate's update."""
        phi = states[:, 2] + g.bearing
        px = states[:, 0] + g.range * np.cos(phi)
        py = states[:, 1] + g.range * np.sin(phi)
        rxx, ryy, rxy = self.sensor_cov(g, phi)
        lm = landmarks.get(g.landmark_id)
        log_g = None
        if lm is not None:
            sxx, syy, sxy = lm.cov[0, 0] + rxx, lm.cov[1, 1] + ryy, lm.cov[0, 1] + rxy
            det = sxx * syy - sxy * sxy
            ex, ey = px - lm.mean[0], py - lm.mean[1]
            maha = (syy * ex * ex - 2 * sxy * ex * ey + sxx * ey * ey) / det
            log_g = -0.5 * maha - 0.5 * np.log(det)
        # map update: the weighted mixture of the positions the particles imply
        mx, my = float(weights @ px), float(weights @ py)
        dx, dy = px - mx, py - my
        pxx, pyy = float(weights @ (dx * dx)), float(weights @ (dy * dy))  # pose part: the particle scatter
        cxx = pxx + float(weights @ rxx)
        cyy = pyy + float(weights @ ryy)
        cxy = float(weights @ (dx * dy + rxy))
        pose_std = math.sqrt(0.5 * (pxx + pyy))
        landmarks.fuse(g.landmark_id, np.array([mx, my]), np.array([[cxx, cxy], [cxy, cyy]]), pose_std, avatar, t)
        return log_g

    def apply(
        self, r: LandmarkReading, states: np.ndarray, weights: np.ndarray, landmarks: LandmarkMap
    ) -> np.ndarray | None:
        """The image's sightings in turn; log g is their sum (None if none had an estimate to compare with)."""
        total: np.ndarray | None = None
        for g in r.sightings:
            lg = self.apply_sighting(g, states, weights, landmarks, r.avatar, r.t)
            if lg is not None:
                total = lg if total is None else total + lg
        return total
