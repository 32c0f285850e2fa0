"""Arena files: the YAML schema (pydantic), its validation, and the compiled `Arena` the world is built from.

An arena is a rectangle `size: [width, height]` (metres, origin at its lower-left inner corner, x right,
y up) closed by outer walls, plus:

* `walls`: interior walls, segments `start`-`end` with a `thickness`;
* `obstacles`: convex polygons (`polygon: [[x, y], ...]`) or rotated boxes (`box: {center, size, angle}`);
* `landmarks`: `{id, pos}`; each one is an ArUco marker (dictionary `marker_dictionary`, side
  `marker_size`, centred at `marker_height` above the floor) printed on the wall or obstacle face that
  `pos` lies on (within 2 cm); the face's outward normal is the direction it can be seen from;
* `congregation`: the optional congregation-point landmark of the Congregate scenario, a free-standing
  square post of side `size` with the same marker on all four faces;
* `collectables`: `{id, pos}` small cylinders on the floor (Forage);
* `collection_regions`: `{id, polygon | box}` where collectables are deposited;
* `start_poses`: `[x, y, theta]` where avatars appear (in order);
* `schedule`: avatars joining, retiring or crashing at given times (haa.sim.schedule).

`load_arena("small" | "large" | path)` validates the file and returns an `Arena`; a bad file raises
`ArenaError` with one line naming the field and the reason (e.g.
`arena foo.yaml: landmarks[3].pos: not on a wall or obstacle face (nearest is 0.31 m away)`). The file is
read by `haa.files` (at most 1 MiB, 64 levels, 100,000 nodes, no duplicate keys) and the schema bounds
every list (`MAX_WALLS`, `MAX_OBSTACLES`, ... below; docs/limits.md), so that no file keeps the
simulator busy for long before it starts.
The two thesis arenas ship in `haa/sim/arenas/` (designed by `haa.sim.arenas.design`; docs/sim.md).
"""

from __future__ import annotations

import errno
import itertools
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, model_validator

from haa import files
from haa.sim.geometry import (
    Edges,
    Point,
    box_polygon,
    ccw,
    is_convex,
    point_in_polygon,
    polygon_area,
    segment_distance,
    thick_segment,
)
from haa.sim.schedule import MAX_ENTRIES, ScheduleEntry

BUILTIN = ("small", "large")

#: structure kinds (Edges.kind)
OUTER_WALL, WALL, OBSTACLE, POST = 0, 1, 2, 3
KIND_NAMES = {OUTER_WALL: "outer wall", WALL: "wall", OBSTACLE: "obstacle", POST: "congregation post"}

#: ArUco dictionaries we accept and their sizes (ids must be below the size)
DICTIONARIES = {"DICT_4X4_50": 50, "DICT_4X4_100": 100, "DICT_4X4_250": 250, "DICT_4X4_1000": 1000}
#: a marker is printed with a white margin of one cell on each side: 4x4 bits + black border = 6 cells, +2
PLATE_CELLS = 8
MARKER_CELLS = 6
#: a landmark's `pos` must be this close to a face
ON_FACE_TOL = 0.02
#: free space a start pose needs around it (the largest avatar radius plus a margin)
START_CLEARANCE = 0.25
COLLECTABLE_RADIUS = 0.05
COLLECTABLE_HEIGHT = 0.10

#: the most elements an arena file may hold (the compile checks are walls x landmarks and the like)
MAX_WALLS = 100
MAX_OBSTACLES = 100
MAX_POLYGON_POINTS = 16
MAX_LANDMARKS = 1000  # the largest marker dictionary has 1000 ids
MAX_COLLECTABLES = 1000
MAX_REGIONS = 32
MAX_START_POSES = 100
MAX_ID_CHARS = 64
MAX_DESCRIPTION_CHARS = 10_000
MAX_SIDE = 100.0


class ArenaError(ValueError):
    """An arena file is invalid; the message is one line naming the field and the reason."""


#: coordinates are finite (no inf or NaN); an arena side is at most MAX_SIDE metres
XY = tuple[FiniteFloat, FiniteFloat]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class BoxSpec(_Model):
    center: XY
    size: XY = Field(description="width (along x before rotation), height")
    angle: FiniteFloat = Field(0.0, description="rotation, radians counter-clockwise")

    @model_validator(mode="after")
    def _positive(self) -> BoxSpec:
        if min(self.size) <= 0:
            raise ValueError("size must be positive")
        return self


Id = Annotated[str, Field(min_length=1, max_length=MAX_ID_CHARS)]


class WallSpec(_Model):
    id: Id
    start: XY
    end: XY
    thickness: float = Field(0.05, gt=0, le=1.0)

    @model_validator(mode="after")
    def _length(self) -> WallSpec:
        if math.dist(self.start, self.end) < 1e-6:
            raise ValueError("start and end are the same point")
        return self


class ShapeSpec(_Model):
    """A convex polygon, or a box."""

    id: Id
    polygon: list[XY] | None = Field(None, max_length=MAX_POLYGON_POINTS)
    box: BoxSpec | None = None

    @model_validator(mode="after")
    def _one_shape(self) -> ShapeSpec:
        if (self.polygon is None) == (self.box is None):
            raise ValueError("give exactly one of polygon or box")
        if self.polygon is not None:
            if len(self.polygon) < 3:
                raise ValueError("polygon needs at least 3 points")
            if not is_convex(self.polygon):
                raise ValueError("polygon must be convex (split a concave shape into several obstacles)")
        return self

    def points(self) -> list[Point]:
        if self.box is not None:
            b = self.box
            return box_polygon(b.center[0], b.center[1], b.size[0], b.size[1], b.angle)
        assert self.polygon is not None
        return ccw(self.polygon)


class LandmarkSpec(_Model):
    id: int = Field(ge=0)
    pos: XY


class CongregationSpec(_Model):
    id: int = Field(ge=0)
    pos: XY
    size: float = Field(0.3, gt=0, le=1.0, description="side of the square post, m")


class CollectableSpec(_Model):
    id: Id
    pos: XY


class ArenaSpec(_Model):
    """The arena file (YAML) as validated by pydantic; `compile_arena` adds the geometric checks."""

    name: Id
    description: str = Field("", max_length=MAX_DESCRIPTION_CHARS)
    size: tuple[Annotated[float, Field(le=MAX_SIDE)], Annotated[float, Field(le=MAX_SIDE)]]
    wall_height: float = Field(0.6, gt=0, le=5)
    outer_wall_thickness: float = Field(0.05, gt=0, le=1)
    marker_dictionary: Literal["DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000"] = "DICT_4X4_250"
    marker_size: float = Field(0.2, gt=0.01, le=2.0, description="side of the black marker square, m")
    marker_height: float = Field(
        0.3, gt=0, allow_inf_nan=False, description="height of the marker centres above the floor, m"
    )
    walls: list[WallSpec] = Field([], max_length=MAX_WALLS)
    obstacles: list[ShapeSpec] = Field([], max_length=MAX_OBSTACLES)
    landmarks: list[LandmarkSpec] = Field([], max_length=MAX_LANDMARKS)
    congregation: CongregationSpec | None = None
    collectables: list[CollectableSpec] = Field([], max_length=MAX_COLLECTABLES)
    collection_regions: list[ShapeSpec] = Field([], max_length=MAX_REGIONS)
    start_poses: list[tuple[FiniteFloat, FiniteFloat, FiniteFloat]] = Field(min_length=1, max_length=MAX_START_POSES)
    schedule: list[ScheduleEntry] = Field([], max_length=MAX_ENTRIES)

    @model_validator(mode="after")
    def _sizes(self) -> ArenaSpec:
        if min(self.size) <= 0:
            raise ValueError("size: width and height must be positive")
        return self


@dataclass(frozen=True)
class Marker:
    """One printed marker: landmark `id` on face `edge`, plate from `s0` to `s0 + plate` metres along it."""

    id: int
    edge: int
    s0: float
    plate: float
    center: Point
    normal: Point


@dataclass(frozen=True)
class Structure:
    """A static polygon of the arena (outer wall, wall, obstacle or the congregation post)."""

    id: str
    kind: int
    polygon: list[Point]


@dataclass
class Arena:
    """A validated, compiled arena (see the module docstring for the file format)."""

    name: str
    spec: ArenaSpec
    width: float
    height: float
    wall_height: float
    marker_size: float
    marker_height: float
    marker_dictionary: str
    structures: list[Structure]
    edges: Edges
    markers: list[Marker]
    landmarks: dict[int, Point]
    congregation_id: int | None
    collectables: dict[str, Point]
    regions: dict[str, list[Point]]
    start_poses: list[tuple[float, float, float]]
    source: str = ""
    _marker_by_edge: dict[int, list[Marker]] = field(default_factory=dict, repr=False)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the inside of the outer walls."""
        return (0.0, 0.0, self.width, self.height)

    @property
    def walls(self) -> list[Structure]:
        return [s for s in self.structures if s.kind in (OUTER_WALL, WALL)]

    @property
    def obstacles(self) -> list[Structure]:
        return [s for s in self.structures if s.kind == OBSTACLE]

    @property
    def congregation_point(self) -> Point | None:
        return None if self.congregation_id is None else self.landmarks[self.congregation_id]

    @property
    def plate_size(self) -> float:
        return self.marker_size * PLATE_CELLS / MARKER_CELLS

    def markers_on_edge(self, edge: int) -> list[Marker]:
        return self._marker_by_edge.get(edge, [])

    def solid_polygons(self) -> list[list[Point]]:
        """Polygons of everything solid (walls, obstacles, post), inside or around the bounds."""
        return [s.polygon for s in self.structures]

    def inside_solid(self, x: float, y: float) -> bool:
        return any(point_in_polygon(x, y, p) for p in self.solid_polygons())

    def clearance(self, x: float, y: float) -> float:
        """Distance from (x, y) to the nearest face (0 inside a solid)."""
        if self.inside_solid(x, y) or not (0 < x < self.width and 0 < y < self.height):
            return 0.0
        e = self.edges
        p = np.array([x, y])
        d = e.b - e.a
        L2 = np.maximum((d * d).sum(axis=1), 1e-18)
        t = np.clip(((p - e.a) * d).sum(axis=1) / L2, 0, 1)
        q = e.a + t[:, None] * d
        return float(np.min(np.hypot(*(q - p).T)))

    def to_yaml(self) -> str:
        return dump_spec(self.spec)


def dump_spec(spec: ArenaSpec) -> str:
    data = spec.model_dump(mode="json", exclude_none=True)
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


def builtin_path(name: str) -> Path:
    return Path(str(resources.files("haa.sim") / "arenas" / f"{name}.yaml"))


def load_arena(arena: str | Path) -> Arena:
    """Load "small", "large" or a YAML file; raises ArenaError (one line) when it is missing or invalid."""
    if isinstance(arena, str) and arena in BUILTIN:
        path = builtin_path(arena)
    else:
        path = Path(arena)
    label = f"arena {files.one_line(str(arena))}"  # as the user named it
    try:
        text = files.read_text(path, what="arena file")
    except files.FileError as e:
        if e.os_errno == errno.ENOENT:
            raise ArenaError(f"{label}: no such file (built-in arenas: {', '.join(BUILTIN)})") from None
        raise ArenaError(f"{label}: {e.reason}") from None
    return parse_arena(text, label)


def parse_arena(text: str, label: str = "arena") -> Arena:
    """Validate and compile arena YAML text (`label` starts the error lines); raises ArenaError."""
    try:
        data = files.parse_yaml(text, label)
    except files.FileError as e:
        raise ArenaError(str(e)) from None
    if not isinstance(data, dict):
        raise ArenaError(f"{label}: expected a mapping at the top level")
    try:
        spec = ArenaSpec.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        msg = str(err["msg"]).removeprefix("Value error, ")
        where = files.field_path(tuple(err["loc"])) or "(file)"
        raise ArenaError(files.one_line(f"{label}: {where}: {msg}", 500)) from None
    arena = compile_arena(spec, label)
    arena.source = text
    return arena


def compile_arena(spec: ArenaSpec, label: str = "arena") -> Arena:
    """Geometry of a validated spec, with the checks pydantic cannot do (placement, overlaps, ids)."""

    def fail(loc: str, msg: str) -> None:
        raise ArenaError(f"{label}: {loc}: {msg}")

    W, H = spec.size
    t = spec.outer_wall_thickness
    inside = lambda p: -1e-9 <= p[0] <= W + 1e-9 and -1e-9 <= p[1] <= H + 1e-9  # noqa: E731

    structures: list[Structure] = [
        Structure("outer-south", OUTER_WALL, ccw([(-t, -t), (W + t, -t), (W + t, 0), (-t, 0)])),
        Structure("outer-east", OUTER_WALL, ccw([(W, 0), (W + t, 0), (W + t, H), (W, H)])),
        Structure("outer-north", OUTER_WALL, ccw([(-t, H), (W + t, H), (W + t, H + t), (-t, H + t)])),
        Structure("outer-west", OUTER_WALL, ccw([(-t, 0), (0, 0), (0, H), (-t, H)])),
    ]
    ids: set[str] = set()
    for i, w in enumerate(spec.walls):
        if w.id in ids:
            fail(f"walls[{i}].id", f"duplicate id {w.id!r}")
        ids.add(w.id)
        poly = thick_segment(w.start, w.end, w.thickness)
        if not all(inside(p) for p in poly):
            fail(f"walls[{i}]", "outside the arena bounds")
        structures.append(Structure(w.id, WALL, poly))
    for i, o in enumerate(spec.obstacles):
        if o.id in ids:
            fail(f"obstacles[{i}].id", f"duplicate id {o.id!r}")
        ids.add(o.id)
        poly = o.points()
        if not all(inside(p) for p in poly):
            fail(f"obstacles[{i}]", "outside the arena bounds")
        structures.append(Structure(o.id, OBSTACLE, poly))
    if spec.congregation is not None:
        c = spec.congregation
        poly = box_polygon(c.pos[0], c.pos[1], c.size, c.size)
        if not all(inside(p) for p in poly):
            fail("congregation", "outside the arena bounds")
        for s in structures[4:]:
            if any(point_in_polygon(x, y, s.polygon) for x, y in poly) or point_in_polygon(*c.pos, s.polygon):
                fail("congregation.pos", f"the post overlaps {KIND_NAMES[s.kind]} {s.id!r}")
        structures.append(Structure("congregation", POST, poly))

    edges = Edges.from_polygons([s.polygon for s in structures], [s.kind for s in structures])
    plate = spec.marker_size * PLATE_CELLS / MARKER_CELLS
    if spec.marker_height - plate / 2 < 0 or spec.marker_height + plate / 2 > spec.wall_height:
        fail(
            "marker_height",
            f"a {plate:.3f} m marker plate centred at {spec.marker_height} m does not fit on "
            f"{spec.wall_height} m walls",
        )
    dict_size = DICTIONARIES[spec.marker_dictionary]

    # Two prefilters keep the checks below linear in practice (a file may hold 1000 landmarks and 2000
    # edges): both return a superset of what the exact scalar tests accept, in index order, so the
    # results are those of testing everything.
    edge_d = edges.b - edges.a
    edge_l2 = (edge_d * edge_d).sum(axis=1)
    edge_l2_safe = np.where(edge_l2 > 0, edge_l2, 1.0)
    box_lo = np.array([np.min(s.polygon, axis=0) for s in structures]) - 1e-9
    box_hi = np.array([np.max(s.polygon, axis=0) for s in structures]) + 1e-9

    def near_edges(p: XY) -> list[int]:
        """The edges within 1 um of the nearest one to p."""
        rel = np.asarray(p, dtype=float) - edges.a
        t = np.clip(np.where(edge_l2 > 0, (rel * edge_d).sum(axis=1) / edge_l2_safe, 0.0), 0.0, 1.0)
        dist = np.hypot(*(rel - t[:, None] * edge_d).T)
        return np.nonzero(dist <= dist.min() + 1e-6)[0].tolist() if len(dist) else []

    def solids_near(x: float, y: float) -> list[Structure]:
        """The structures whose bounding box holds (x, y)."""
        hit = (box_lo[:, 0] <= x) & (x <= box_hi[:, 0]) & (box_lo[:, 1] <= y) & (y <= box_hi[:, 1])
        return [structures[i] for i in np.nonzero(hit)[0]]

    markers: list[Marker] = []
    landmarks: dict[int, Point] = {}
    for i, lm in enumerate(spec.landmarks):
        if lm.id in landmarks:
            fail(f"landmarks[{i}].id", f"duplicate id {lm.id}")
        if lm.id >= dict_size:
            fail(f"landmarks[{i}].id", f"{lm.id} is not in {spec.marker_dictionary} (ids 0..{dict_size - 1})")
        best, best_d, best_s = -1, math.inf, 0.0
        for k in near_edges(lm.pos):
            d, s = segment_distance(lm.pos, tuple(edges.a[k]), tuple(edges.b[k]))
            if d < best_d:
                best, best_d, best_s = k, d, s
        if best_d > ON_FACE_TOL:
            fail(f"landmarks[{i}].pos", f"not on a wall or obstacle face (nearest is {best_d:.2f} m away)")
        L = float(edges.length[best])
        if best_s - plate / 2 < -1e-9 or best_s + plate / 2 > L + 1e-9:
            fail(f"landmarks[{i}].pos", f"the {plate:.3f} m marker plate does not fit on its {L:.2f} m face")
        n = (float(edges.normal[best, 0]), float(edges.normal[best, 1]))
        a = edges.a[best]
        u = (edges.b[best] - a) / L
        centre = (float(a[0] + u[0] * best_s), float(a[1] + u[1] * best_s))
        probe = (centre[0] + n[0] * 0.05, centre[1] + n[1] * 0.05)
        if not inside(probe) or any(point_in_polygon(*probe, s.polygon) for s in solids_near(*probe)):
            fail(f"landmarks[{i}].pos", "its face is not visible from free space")
        markers.append(Marker(lm.id, best, best_s - plate / 2, plate, centre, n))
        landmarks[lm.id] = centre
    congregation_id = None
    if spec.congregation is not None:
        c = spec.congregation
        if c.id in landmarks:
            fail("congregation.id", f"{c.id} is also a landmark id")
        if c.id >= dict_size:
            fail("congregation.id", f"{c.id} is not in {spec.marker_dictionary} (ids 0..{dict_size - 1})")
        if c.size < plate:
            fail("congregation.size", f"the post ({c.size} m) is narrower than a marker plate ({plate:.3f} m)")
        post = len(structures) - 1
        for k in np.nonzero(edges.owner == post)[0]:
            L = float(edges.length[k])
            mid = (edges.a[k] + edges.b[k]) / 2
            markers.append(
                Marker(
                    c.id,
                    int(k),
                    L / 2 - plate / 2,
                    plate,
                    (float(mid[0]), float(mid[1])),
                    (float(edges.normal[k, 0]), float(edges.normal[k, 1])),
                )
            )
        landmarks[c.id] = (float(c.pos[0]), float(c.pos[1]))
        congregation_id = c.id
    by_edge: dict[int, list[Marker]] = {}
    for m in markers:
        by_edge.setdefault(m.edge, []).append(m)
    for ms in by_edge.values():
        ms.sort(key=lambda m: m.s0)
        for m1, m2 in itertools.pairwise(ms):
            if m2.s0 < m1.s0 + m1.plate - 1e-9:
                fail("landmarks", f"markers {m1.id} and {m2.id} overlap on the same face")

    def solid_at(x: float, y: float) -> Structure | None:
        for s in solids_near(x, y):
            if point_in_polygon(x, y, s.polygon):
                return s
        return None

    collectables: dict[str, Point] = {}
    for i, c in enumerate(spec.collectables):
        if c.id in collectables:
            fail(f"collectables[{i}].id", f"duplicate id {c.id!r}")
        if not (
            COLLECTABLE_RADIUS <= c.pos[0] <= W - COLLECTABLE_RADIUS
            and COLLECTABLE_RADIUS <= c.pos[1] <= H - COLLECTABLE_RADIUS
        ):
            fail(f"collectables[{i}].pos", "outside the arena bounds")
        s = solid_at(*c.pos)
        if s is not None:
            fail(f"collectables[{i}].pos", f"inside {KIND_NAMES[s.kind]} {s.id!r}")
        collectables[c.id] = (float(c.pos[0]), float(c.pos[1]))
    regions: dict[str, list[Point]] = {}
    for i, r in enumerate(spec.collection_regions):
        if r.id in regions:
            fail(f"collection_regions[{i}].id", f"duplicate id {r.id!r}")
        poly = r.points()
        if not all(inside(p) for p in poly):
            fail(f"collection_regions[{i}]", "outside the arena bounds")
        if polygon_area(poly) <= 0:
            fail(f"collection_regions[{i}]", "has no area")
        regions[r.id] = poly

    arena = Arena(
        name=spec.name,
        spec=spec,
        width=float(W),
        height=float(H),
        wall_height=spec.wall_height,
        marker_size=spec.marker_size,
        marker_height=spec.marker_height,
        marker_dictionary=spec.marker_dictionary,
        structures=structures,
        edges=edges,
        markers=markers,
        landmarks=landmarks,
        congregation_id=congregation_id,
        collectables=collectables,
        regions=regions,
        start_poses=[(float(x), float(y), float(th)) for x, y, th in spec.start_poses],
        _marker_by_edge=by_edge,
    )
    for i, (x, y, _th) in enumerate(arena.start_poses):
        c = arena.clearance(x, y)
        if c < START_CLEARANCE:
            fail(f"start_poses[{i}]", f"needs {START_CLEARANCE} m of free space around it (has {c:.2f} m)")
        for j in range(i):
            xj, yj, _ = arena.start_poses[j]
            if math.hypot(x - xj, y - yj) < 2 * START_CLEARANCE:
                fail(f"start_poses[{i}]", f"closer than {2 * START_CLEARANCE} m to start_poses[{j}]")
    from haa.sim.schedule import check_schedule

    problem = check_schedule(spec.schedule, len(arena.start_poses))
    if problem:
        fail(*problem)
    return arena
