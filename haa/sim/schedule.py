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

A schedule file is read by `haa.files` (at most 1 MiB, 64 levels, 100,000 nodes, no duplicate keys) and holds
at most `MAX_ENTRIES` entries (docs/limits.md).

The world applies every entry exactly at its time (a `World.step` that spans it is split there); entries
with the same time apply in file order. The gRPC API can do the same on demand (haa.sim.servicer).
"""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, model_validator

from haa import files

#: the most entries a schedule (file or arena) may hold
MAX_ENTRIES = 1000
#: avatar ids are at most this long
MAX_ID_CHARS = 64

AvatarTypeName = Literal["seeker", "enhanced_seeker", "sweeper", "carrier"]


class JoinSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    type: AvatarTypeName
    id: str | None = Field(None, min_length=1, max_length=MAX_ID_CHARS)
    start: int | tuple[FiniteFloat, FiniteFloat, FiniteFloat] | None = Field(
        None, description="start pose index of the arena, or [x, y, theta]; none: the next free start pose"
    )


class ScheduleEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    at: float = Field(ge=0, description="simulated time, s")
    join: JoinSpec | None = None
    retire: str | None = Field(None, max_length=MAX_ID_CHARS)
    crash: str | None = Field(None, max_length=MAX_ID_CHARS)

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
    name = files.one_line(p.name)
    try:
        data = files.load_yaml(p, what="schedule file")
    except files.FileError as e:
        if e.os_errno == errno.ENOENT:
            raise ScheduleError(f"schedule {files.one_line(str(path))}: no such file") from None
        raise ScheduleError(f"schedule {name}: {e.reason}") from None
    if not isinstance(data, dict) or "schedule" not in data:
        raise ScheduleError(f"schedule {name}: expected a mapping with a `schedule` list")
    raw = data["schedule"] or []
    if not isinstance(raw, list):
        raise ScheduleError(f"schedule {name}: schedule: expected a list")
    if len(raw) > MAX_ENTRIES:
        raise ScheduleError(f"schedule {name}: schedule: more than {MAX_ENTRIES} entries")
    entries = []
    for i, item in enumerate(raw):
        try:
            entries.append(ScheduleEntry.model_validate(item))
        except ValidationError as e:
            err = e.errors()[0]
            loc = "".join(f".{x}" if isinstance(x, str) else f"[{x}]" for x in err["loc"])
            msg = str(err["msg"]).removeprefix("Value error, ")
            raise ScheduleError(files.one_line(f"schedule {name}: schedule[{i}]{loc}: {msg}", 500)) from None
    problem = check_schedule(entries, start_poses)
    if problem:
        raise ScheduleError(files.one_line(f"schedule {name}: {problem[0]}: {problem[1]}", 500))
    return entries
