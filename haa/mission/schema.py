"""Mission files: the YAML schema of issue 15 §1 (pydantic v2), its cross-checks, and one-line errors.

A mission names a scenario of thesis Table 6.2-1 (L1182-1196), an arena of §6.2.1 (L1180, L1200), the SLAM
control variant of Table 7.2-4 (L1749-1754), the completion criterion (95 % of the reachable cells
explored in every experiment: L1376, L1551, L1756, L1784, L1842; a cell is explored when p > 0.73 or
p < 0.27, L1186), the host group and its changes (AF-1: "every odd minute one host gracefully retires and
every even minute a host joins", §7.1.1 L1372-1474) and the avatars with their joins and retirements
(AF-1: "after 2 minutes one seeker retires ... after 2.5 minutes two additional seekers join").

```yaml
name: af1
scenario: explore              # explore | congregate | forage
arena: small                   # small | large | a path to an arena YAML (relative: to the mission file)
seed: 1
slam: jc-slam                  # jc-slam | discard | delay
particles: 100
complete: {explored: 0.95, time_limit_s: 900}
hosts:
  start: 4                     # h1..h4
  schedule:
    - {at_s: 60, leave: h4}    # leave | join | kill | restart
    - {at_s: 120, join: h5}
avatars:
  - {name: s1, type: seeker, pose: [0.5, 0.5, 0.0]}
  - {name: s3, type: seeker, pose: [2.9, 0.5, 1.57], leave_at_s: 120}
  - {name: s4, type: seeker, pose: [2.5, 6.7, -1.57], join_at_s: 150}
```

Extras (ours, all optional): `description`, `exploration: em | frontier` (SupervisorExplore's EM split of
App. III L3079, or coordinated frontier exploration after Burgard et al. 2005), `speed` (simulated seconds
per wall second), `chaos` (a chaos plan file, relative to the mission file), `map_resolution` (m per grid
cell), `congregation: {radius_m, tolerance_m}` (thesis gap 8: the geometry of "equally spaced intervals
surrounding the congregation point", L1190, is not given). docs/missions.md documents every key.

`load_mission(path)` reads the file through `haa.files` (size, depth, node and duplicate-key limits), then
validates it; anything wrong raises `MissionError`, whose `str()` is one line
`<file>: <field path>: <reason>`, e.g. `af1.yaml: avatars[2].pose: (3.30, 0.50) is 0.10 m from an obstacle
or wall; a seeker needs 0.12 m`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    ValidationError,
    field_validator,
    model_validator,
)

from haa import files

#: bounds that keep a file from asking for something absurd (docs/missions.md)
MAX_HOSTS = 64
MAX_AVATARS = 64
MAX_SCHEDULE = 1000
MAX_PARTICLES = 10_000
MAX_TIME_LIMIT_S = 7 * 24 * 3600.0
MAX_NAME_CHARS = 64
MAX_SPEED = 1000.0

HOST_NAME = re.compile(r"^h[1-9][0-9]{0,3}$")
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _check_name(v: str) -> str:
    if not NAME.match(v):
        raise ValueError(f"letters, digits, '_', '.', '-' and a letter or digit first (got {v!r})")
    return v

AvatarType = Literal["seeker", "enhanced_seeker", "sweeper", "carrier"]
HOST_ACTIONS = ("leave", "join", "kill", "restart")


class MissionError(ValueError):
    """A mission file cannot be used. `str()` is one line `<file>: <field>: <reason>`."""

    def __init__(self, path: str | os.PathLike[str], field: str, reason: str) -> None:
        self.path = files.one_line(str(path))
        self.field = files.one_line(field)
        self.reason = files.one_line(reason)
        super().__init__(f"{self.path}: {self.field}: {self.reason}" if self.field else f"{self.path}: {self.reason}")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=False)


Name = Annotated[str, Field(min_length=1, max_length=MAX_NAME_CHARS), AfterValidator(_check_name)]
Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class Complete(_Model):
    """Completion criterion: share of the reachable cells explored (L1186), and a time limit (ours)."""

    explored: float = Field(0.95, description="share of reachable cells with p > 0.73 or p < 0.27, in (0, 1]")
    time_limit_s: float = Field(900.0, gt=0, le=MAX_TIME_LIMIT_S, allow_inf_nan=False)

    @field_validator("explored")
    @classmethod
    def _share(cls, v: float) -> float:
        if not (math.isfinite(v) and 0 < v <= 1):
            raise ValueError(f"must be in (0, 1], got {v}")
        return v


class HostEvent(_Model):
    """One change of the host group, `at_s` simulated seconds after the mission starts."""

    at_s: Seconds
    leave: str | None = Field(None, description="graceful leave: the host freezes and hands over its agents")
    join: str | None = Field(None, description="a host that is not in the group joins (new, or one that left)")
    kill: str | None = Field(None, description="crash: the host's process is killed (agents recovered elsewhere)")
    restart: str | None = Field(None, description="a killed host starts again under its name and rejoins")

    @model_validator(mode="after")
    def _one(self) -> HostEvent:
        given = [a for a in HOST_ACTIONS if getattr(self, a) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of {', '.join(HOST_ACTIONS)} (got {', '.join(given) or 'none'})")
        host = getattr(self, given[0])
        if not HOST_NAME.match(host):
            raise ValueError(f"{given[0]}: host names are h1, h2, ... (got {host!r})")
        return self

    @property
    def action(self) -> str:
        return next(a for a in HOST_ACTIONS if getattr(self, a) is not None)

    @property
    def host(self) -> str:
        return str(getattr(self, self.action))


class Hosts(_Model):
    start: int = Field(4, ge=1, le=MAX_HOSTS, description="hosts h1..hN at mission start")
    schedule: list[HostEvent] = Field([], max_length=MAX_SCHEDULE)

    @property
    def initial(self) -> list[str]:
        return [f"h{i}" for i in range(1, self.start + 1)]

    def events(self) -> list[HostEvent]:
        """The schedule in time order (entries with the same time keep file order)."""
        return sorted(self.schedule, key=lambda e: e.at_s)


class Avatar(_Model):
    name: Name
    type: AvatarType
    pose: tuple[FiniteFloat, FiniteFloat, FiniteFloat] = Field(description="x, y (m), heading (rad)")
    join_at_s: Seconds | None = Field(None, description="joins this long after mission start (default: at start)")
    leave_at_s: Seconds | None = Field(None, description="retires gracefully this long after mission start")

    @model_validator(mode="after")
    def _times(self) -> Avatar:
        if self.leave_at_s is not None and self.leave_at_s <= (self.join_at_s or 0.0):
            raise ValueError(f"leave_at_s ({self.leave_at_s}) must come after join_at_s ({self.join_at_s or 0.0})")
        return self


class Congregation(_Model):
    """Thesis gap 8 (L1190 gives no geometry): slots on a circle of `radius_m` around the point."""

    radius_m: float = Field(0.6, gt=0, le=10, allow_inf_nan=False)
    tolerance_m: float = Field(0.15, gt=0, le=2, allow_inf_nan=False)


class AgentFault(_Model):
    """An operator action on an agent during the mission (ours; the chaos plans of the chaos issue generalise
    it): at `at_s` simulated seconds from mission start, `kill` (SIGKILL, as `haactl agent kill`: recovered by
    its host, Alg. 7/8) the agent named — an agent type (the first live agent of it, e.g. supervisor_explore,
    path_planner) or a display name (A2.3)."""

    at_s: float = Field(ge=0, allow_inf_nan=False)
    kill: str = Field(min_length=1, max_length=128, pattern=r"^[A-Za-z][A-Za-z0-9_.\-]*$")


class MissionSpec(_Model):
    """The mission file as validated by pydantic; `check_mission` adds the cross-checks against the arena."""

    name: Name
    description: str = Field("", max_length=10_000)
    scenario: Literal["explore", "congregate", "forage"]
    arena: str = Field(min_length=1, max_length=4096)
    seed: int = Field(0, ge=0, le=2**63 - 1)
    slam: Literal["jc-slam", "discard", "delay"] = "jc-slam"
    particles: int = Field(100, ge=1, le=MAX_PARTICLES)
    #: haa-sim's odometry drift model (docs/sim.md "Odometry drift"): thesis (default; the seeker drifts 0.122 m
    #: per 10 m), table (Table 6.2-3 as printed: 1.22 m) or systematic (table + per-avatar scale and bias)
    drift: Literal["thesis", "table", "systematic"] = "thesis"
    #: share of each avatar type's top speed (Table 6.2-3) the avatars drive at (docs/missions.md): the thesis
    #: gives top speeds only; missions/af1.yaml picks the share that makes AF-1 last as long as the thesis' run.
    #: "physics": each type at the speed its own sensing allows (haa.agents.team.physics_cruise, docs/team.md)
    cruise: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] | Literal["physics"] = 0.2
    complete: Complete = Complete()
    hosts: Hosts = Hosts()
    avatars: list[Avatar] = Field(min_length=1, max_length=MAX_AVATARS)
    exploration: Literal["em", "frontier"] = "em"
    speed: float = Field(1.0, gt=0, le=MAX_SPEED, allow_inf_nan=False)
    chaos: str | None = Field(None, min_length=1, max_length=4096)
    #: extra haa-hostd arguments for every host of the mission's own cluster, e.g. ["--agent-hang-timeout", "1"]
    #: (missions/r1.yaml); `haa-hostd --help` lists them
    hostd_args: list[Annotated[str, Field(max_length=256)]] = Field(default_factory=list, max_length=32)
    #: AgentPlayback (docs/playback.md): record every agent's inputs and outputs; a folder (relative to the
    #: run's output folder) or true (`<out>/recording`). `haactl mission run --record DIR` overrides it
    record: bool | Annotated[str, Field(min_length=1, max_length=4096)] = False
    map_resolution: float = Field(0.1, ge=0.02, le=1.0, allow_inf_nan=False)
    congregation: Congregation = Congregation()
    agent_faults: list[AgentFault] = Field(default_factory=list, max_length=1000)


@dataclass(frozen=True)
class Mission:
    """A loaded, checked mission: the spec, where it came from, and its arena (haa.sim.arena.Arena)."""

    spec: MissionSpec
    path: Path | None
    arena: Any  # haa.sim.arena.Arena (kept Any so that importing the schema stays cheap)

    def avatars_at_start(self) -> list[Avatar]:
        return [a for a in self.spec.avatars if a.join_at_s is None or a.join_at_s == 0]

    def sim_schedule(self) -> list[Any]:
        """The avatar joins and retirements as haa.sim schedule entries (haa.sim.schedule.ScheduleEntry),
        for a simulator that applies them at the mission's simulated times."""
        from haa.sim.schedule import JoinSpec, ScheduleEntry

        out = []
        for a in self.spec.avatars:
            out.append(ScheduleEntry(at=a.join_at_s or 0.0, join=JoinSpec(type=a.type, id=a.name, start=a.pose)))
            if a.leave_at_s is not None:
                out.append(ScheduleEntry(at=a.leave_at_s, retire=a.name))
        return sorted(out, key=lambda e: e.at)

    def host_timeline(self) -> list[tuple[float, frozenset[str]]]:
        """[(time, live hosts from then on)], starting with (0, h1..hN)."""
        live = set(self.spec.hosts.initial)
        out = [(0.0, frozenset(live))]
        for e in self.spec.hosts.events():
            if e.action in ("join", "restart"):
                live.add(e.host)
            else:
                live.discard(e.host)
            out.append((e.at_s, frozenset(live)))
        return out


def _reason(err: dict[str, Any], model: type[BaseModel] | None) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        return "unknown field" + (f" (allowed: {', '.join(model.model_fields)})" if model is not None else "")
    if kind == "missing":
        return "required field is missing"
    msg = str(err["msg"]).removeprefix("Value error, ")
    if "input" in err and kind not in ("value_error", "assertion_error"):
        shown = files.one_line(repr(err["input"]), 60)
        msg += f" (got {shown})"
    return msg


def _model_at(loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The model that holds the last field of `loc` (to list its allowed fields)."""
    model: Any = MissionSpec
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        f = model.model_fields.get(part) if isinstance(model, type) and issubclass(model, BaseModel) else None
        if f is None:
            return None
        ann = f.annotation
        args = getattr(ann, "__args__", ())
        nxt = next((a for a in (ann, *args) if isinstance(a, type) and issubclass(a, BaseModel)), None)
        if nxt is None:
            return None
        model = nxt
    return model if isinstance(model, type) and issubclass(model, BaseModel) else None


def parse_mission(data: Any, label: str, base: Path | None = None) -> Mission:
    """Validate parsed YAML `data` (`label` names the file in errors; `base`: folder for relative paths)."""
    if not isinstance(data, dict):
        raise MissionError(label, "", "expected a mapping at the top level (name, scenario, arena, ...)")
    try:
        spec = MissionSpec.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = tuple(err["loc"])
        if err["type"] == "missing" and loc and isinstance(loc[-1], int):
            # a short tuple (a pose of two numbers): name the tuple, not its absent element
            missing = f"too few items (item {loc[-1]} is missing)"
            raise MissionError(label, files.field_path(loc[:-1]), missing) from None
        raise MissionError(label, files.field_path(loc) or "(file)", _reason(dict(err), _model_at(loc))) from None
    arena = check_mission(spec, label, base)
    return Mission(spec, None, arena)


def load_mission(path: str | os.PathLike[str]) -> Mission:
    """Read and check a mission file (see the module docstring); MissionError on anything wrong."""
    label = str(path)
    try:
        data = files.load_yaml(path, what="mission file")
    except files.FileError as e:
        raise MissionError(label, "", e.reason) from None
    m = parse_mission(data, label, Path(path).parent)
    return Mission(m.spec, Path(path), m.arena)


def resolve(base: Path | None, value: str) -> Path:
    p = Path(value)
    return p if p.is_absolute() or base is None else base / p


def check_mission(spec: MissionSpec, label: str, base: Path | None = None) -> Any:
    """The checks pydantic cannot do alone; returns the compiled arena. MissionError on the first problem."""
    from haa.sim.arena import BUILTIN, ArenaError, load_arena
    from haa.sim.avatars import avatar_spec

    def fail(field: str, reason: str) -> NoReturn:
        raise MissionError(label, field, reason)

    # arena: a built-in name or a file (relative to the mission file)
    try:
        arena = load_arena(spec.arena if spec.arena in BUILTIN else resolve(base, spec.arena))
    except ArenaError as e:
        fail("arena", str(e))
    if spec.scenario == "congregate" and arena.congregation_point is None:
        fail("scenario", f"congregate needs an arena with a congregation point; arena {arena.name!r} has none")
    if spec.scenario == "forage":
        # L1194: collectables to find and "specified collection regions" to deposit them in; an avatar that
        # can carry one (Table 6.2-3: capacity >= 1, sweeper and carrier) — else no SupervisorForage could act
        missing = [what for what, have in (("collectables", arena.collectables), ("collection regions", arena.regions))
                   if not have]
        if missing:
            fail("scenario", f"forage needs an arena with collectables and collection regions; arena {arena.name!r} "
                             f"has no {' and no '.join(missing)}")
        if not any(avatar_spec(a.type).capacity >= 1 for a in spec.avatars):
            kinds = ", ".join(sorted({a.type for a in spec.avatars}))
            fail("avatars", f"forage needs an avatar that can carry a collectable (sweeper or carrier); "
                            f"the team has only {kinds}")
    limit = spec.complete.time_limit_s

    # avatars: unique names, poses in free space, joins and leaves within the time limit
    seen: dict[str, int] = {}
    for i, a in enumerate(spec.avatars):
        if a.name in seen:
            fail(f"avatars[{i}].name", f"{a.name!r} is already the name of avatars[{seen[a.name]}]")
        seen[a.name] = i
        x, y, _ = a.pose
        r = avatar_spec(a.type).radius
        if not (0 < x < arena.width and 0 < y < arena.height):
            fail(f"avatars[{i}].pose", f"({x:.2f}, {y:.2f}) is outside the {arena.width} x {arena.height} m arena")
        if arena.inside_solid(x, y):
            fail(f"avatars[{i}].pose", f"({x:.2f}, {y:.2f}) is inside an obstacle or wall")
        c = arena.clearance(x, y)
        if c < r:
            fail(
                f"avatars[{i}].pose",
                f"({x:.2f}, {y:.2f}) is {c:.2f} m from an obstacle or wall; a {a.type} needs {r} m",
            )
        for t, key in ((a.join_at_s, "join_at_s"), (a.leave_at_s, "leave_at_s")):
            if t is not None and t >= limit:
                fail(f"avatars[{i}].{key}", f"{t} s is not before complete.time_limit_s ({limit} s)")
    if not any(a.join_at_s is None or a.join_at_s == 0 for a in spec.avatars):
        fail("avatars", "no avatar is there at the start (every one has join_at_s > 0)")
    # avatars that appear at the same instant must not overlap
    for i, a in enumerate(spec.avatars):
        for j in range(i):
            b = spec.avatars[j]
            if (a.join_at_s or 0.0) != (b.join_at_s or 0.0):
                continue
            gap = math.hypot(a.pose[0] - b.pose[0], a.pose[1] - b.pose[1])
            need = avatar_spec(a.type).radius + avatar_spec(b.type).radius
            if gap < need:
                fail(f"avatars[{i}].pose", f"overlaps avatars[{j}] ({b.name}): {gap:.2f} m apart, need {need:.2f} m")

    # hosts: replay the schedule; each action must make sense for the group at that time
    live = set(spec.hosts.initial)
    killed: set[str] = set()
    ever = set(live)
    order = sorted(range(len(spec.hosts.schedule)), key=lambda k: spec.hosts.schedule[k].at_s)
    for k in order:
        e = spec.hosts.schedule[k]
        where = f"hosts.schedule[{k}].{e.action}"
        h = e.host
        if e.at_s >= limit:
            fail(f"hosts.schedule[{k}].at_s", f"{e.at_s} s is not before complete.time_limit_s ({limit} s)")
        if e.action in ("leave", "kill"):
            if h not in live:
                fail(where, f"{h} is not in the host group at {e.at_s} s")
            if live == {h}:
                fail(where, f"{h} is the last host at {e.at_s} s; a mission needs at least one")
            live.discard(h)
            if e.action == "kill":
                killed.add(h)
        elif e.action == "join":
            if h in live:
                fail(where, f"{h} is already in the host group at {e.at_s} s")
            if h in killed:
                fail(where, f"{h} was killed; use restart: {h}")
            live.add(h)
            ever.add(h)
        else:  # restart
            if h not in killed:
                fail(where, f"{h} was not killed before {e.at_s} s (restart brings a killed host back)")
            killed.discard(h)
            live.add(h)
        if len(ever) > MAX_HOSTS:
            fail(where, f"more than {MAX_HOSTS} distinct hosts")

    for k, f in enumerate(spec.agent_faults):
        if f.at_s >= limit:
            fail(f"agent_faults[{k}].at_s", f"{f.at_s} s is not before complete.time_limit_s ({limit} s)")
    if spec.hostd_args:
        from haa.hostd.daemon import build_parser

        known = build_parser()._option_string_actions
        own = {"--name", "--listen", "--peers", "--core", "--advertise", "--data-dir", "--token-file", "--config"}
        for k, a in enumerate(spec.hostd_args):
            opt = a.split("=", 1)[0]
            if a.startswith("-") and opt not in known:
                fail(f"hostd_args[{k}]", f"{opt!r} is not an haa-hostd option (haa-hostd --help)")
            if opt in own:
                fail(f"hostd_args[{k}]", f"{opt} is set by the mission runner itself")
    if spec.chaos is not None:
        from haa.mission.extensions import ExtensionMissing, extension

        p = resolve(base, spec.chaos)
        if not p.is_file():
            fail("chaos", f"no such file {str(p)!r}")
        try:
            chaos = extension("chaos")
            plan = chaos.load(p)
        except (ExtensionMissing, ValueError) as e:
            fail("chaos", str(e))
        problems = chaos.problems(plan, ever)
        if problems:
            fail("chaos", f"{p}: {problems[0]}")
    return arena
