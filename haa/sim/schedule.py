"""Avatar schedules: avatars that join, retire or crash at given simulated times.

The thesis' experiments change the team while a mission runs (AF-1: "after 2 minutes one seeker retires and
after 2.5 minutes two additional seekers join"; R-2: an enhanced seeker crashes after two minutes, one
retires after five, two carriers join after five). A schedule is a list in the arena file (key `schedule`)
or in a separate mission file given to `haa-sim --schedule FILE` (only its `schedule` key is read):

```yaml
schedule:
  - {at: 0, join: {type: seeker, id: s1}}           # next free start pose
  - {at: 0, join: {type: seeker, id: s2, start: 3}} # start pose index 3 of the arena
  - {at: 120, retire: s1}                            # graceful: leaves the arena, event "retired"
  - {at: 150, join: {type: seeker, id: s4, start: [1.0, 0.5, 1.57]}}
  - {at: 200, crash: s2}                             # stops responding, stays where it is, event "crashed"
```

The world applies every entry exactly at its time (a `World.step` that spans it is split there); entries
with the same time apply in file order. The gRPC API can do the same on demand (haa.sim.service).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

AvatarTypeName = Literal["seeker", "enhanced_seeker", "sweeper", "carrier"]


class JoinSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: AvatarTypeName
    id: str | None = Field(None, min_length=1, max_length=64)
    start: int | tuple[float, float, float] | None = Field(
        None, description="start pose index of the arena, or [x, y, theta]; none: the next free start pose"
    )


class ScheduleEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    at: float = Field(ge=0, description="simulated time, s")
    join: JoinSpec | None = None
    retire: str | None = None
    crash: str | None = None

    @model_validator(mode="after")
    def _one(self) -> ScheduleEntry:
        if sum(x is not None for x in (self.join, self.retire, self.crash)) != 1:
            raise ValueError("give exactly one of join, retire or crash")
        return self

    @property
    def kind(self) -> str:
        return "join" if self.join is not None else "retire" if self.retire is not None else "crash"


def check_schedule(entries: list[ScheduleEntry], start_poses: int) -> tuple[str, str] | None:
    """(field, reason) of the first problem: unknown start pose, duplicate id, retire/crash of no one."""
    order = sorted(range(len(entries)), key=lambda i: (entries[i].at, i))
    joined: set[str] = set()
    gone: set[str] = set()
    for i in order:
        e = entries[i]
        if e.join is not None:
            if isinstance(e.join.start, int) and not 0 <= e.join.start < start_poses:
                return f"schedule[{i}].join.start", f"no start pose {e.join.start} (the arena has {start_poses})"
            if e.join.id is not None:
                if e.join.id in joined:
                    return f"schedule[{i}].join.id", f"{e.join.id!r} joins twice"
                joined.add(e.join.id)
        else:
            who = e.retire if e.retire is not None else e.crash
            assert who is not None
            if who not in joined:
                return f"schedule[{i}].{e.kind}", f"{who!r} has not joined by t={e.at:g} s"
            if who in gone:
                return f"schedule[{i}].{e.kind}", f"{who!r} has already retired or crashed"
            gone.add(who)
    return None


class ScheduleError(ValueError):
    """A schedule file is invalid (one line naming the field and the reason)."""


def load_schedule(path: str | Path, start_poses: int) -> list[ScheduleEntry]:
    """The `schedule` list of a mission (or arena) file, validated; raises ScheduleError."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except FileNotFoundError:
        raise ScheduleError(f"schedule {path}: no such file") from None
    except yaml.YAMLError as e:
        raise ScheduleError(f"schedule {p.name}: not valid YAML: {getattr(e, 'problem', None) or e}") from None
    if not isinstance(data, dict) or "schedule" not in data:
        raise ScheduleError(f"schedule {p.name}: expected a mapping with a `schedule` list")
    raw = data["schedule"] or []
    if not isinstance(raw, list):
        raise ScheduleError(f"schedule {p.name}: schedule: expected a list")
    entries = []
    for i, item in enumerate(raw):
        try:
            entries.append(ScheduleEntry.model_validate(item))
        except ValidationError as e:
            err = e.errors()[0]
            loc = "".join(f".{x}" if isinstance(x, str) else f"[{x}]" for x in err["loc"])
            msg = str(err["msg"]).removeprefix("Value error, ")
            raise ScheduleError(f"schedule {p.name}: schedule[{i}]{loc}: {msg}") from None
    problem = check_schedule(entries, start_poses)
    if problem:
        raise ScheduleError(f"schedule {p.name}: {problem[0]}: {problem[1]}")
    return entries
