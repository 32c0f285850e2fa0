"""The chaos plan: a YAML file validated by a pydantic schema (docs/chaos.md, "Plans").

    name: r1-extreme
    seed: 7
    duration_s: 120            # omitted in a plan a mission names (`chaos: FILE`): until the mission ends
    hosts: 5                   # local cluster size (3..10)
    workload: ddb-writes       # or counters; none: faults only
    agents: 3                  # workload agents (writers, or counter pairs); period_s: 0.2 between writes
    settle_s: 30               # after the faults, the most seconds to wait for the group to settle
    hostd_args: []             # extra haa-hostd arguments for every host (local cluster only)
    mutation: late-commit      # optional: every host a broken variant (haa.lab.chaos.mutations; local only)
    faults:
      - {at_s: 20, action: kill, target: host h3}
      - {at_s: 30, action: pause, target: host h2, for_s: 5}
      - {at_s: 40, action: restart, target: host h3}
      - {life_s: [30, 90], action: hang, target: agents, hang_s: 30}
      - {every_s: 25, action: kill, target: random-agent}
      - {at_s: 60, action: partition, target: [h1, h2], for_s: 10}   # --compose only

A fault has exactly one schedule: `at_s` (once), `every_s` (periodically, first at `at_s` or at `every_s`)
or `life_s: [lo, hi]` (the thesis' failure model: every targeted agent instance draws its failure time
uniformly in the window after it starts, and draws again after each recovery). Targets: `host NAME`,
`random-host`, `agent NAME`, `agent-type TYPE`, `random-agent`, `agents`, and for `partition` a list of hosts.

Inside a mission (the mission file's `chaos: FILE`) the plan's times are the mission's simulated seconds
(`hang_s` too), `duration_s` may be left out (the chaos lasts until the mission ends), the cluster is the
mission's (`hosts`, `workload`, `settle_s` and `hostd_args` do not apply: `mission_problems` refuses a
workload, a partition and hosts the mission never runs).

`load_plan` raises `PlanError` whose text is one line naming the file, the field and the reason; nothing
is started for a bad plan.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from haa import files
from haa.lab.chaos.mutations import MUTATIONS

#: the actions and which targets they take
HOST_ACTIONS = frozenset({"kill", "pause", "restart"})
AGENT_ACTIONS = frozenset({"kill", "hang"})
ACTIONS = ("kill", "pause", "restart", "hang", "partition")
WORKLOADS = ("ddb-writes", "counters")
#: longest run, seconds
MAX_DURATION = 24 * 3600.0
MAX_PLAN_BYTES = 256 * 1024

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
_HOST = re.compile(r"^h([1-9][0-9]?)$")


class PlanError(Exception):
    """A plan that cannot run; `str()` is one line."""


class Target(BaseModel):
    """A parsed target: kind is host | random-host | agent | agent-type | random-agent | agents | hosts."""

    model_config = ConfigDict(frozen=True)

    kind: str
    value: str = ""
    hosts: tuple[str, ...] = ()

    @property
    def is_host(self) -> bool:
        return self.kind in ("host", "random-host", "hosts")

    def text(self) -> str:
        if self.kind == "hosts":
            return ", ".join(self.hosts)
        return f"{self.kind} {self.value}" if self.value else self.kind


def parse_target(raw: Any) -> Target:
    """`host h3`, `random-host`, `agent A1.2`, `agent-type counter`, `random-agent`, `agents` or a list of
    host names; ValueError with the reason otherwise."""
    if isinstance(raw, list):
        if not raw or not all(isinstance(h, str) and _HOST.match(h) for h in raw):
            raise ValueError("a list target names hosts h1..h99, e.g. [h1, h2]")
        if len(set(raw)) != len(raw):
            raise ValueError("a host is named twice")
        return Target(kind="hosts", hosts=tuple(raw))
    if not isinstance(raw, str):
        raise ValueError(f"must be a string or a list of hosts, not {type(raw).__name__}")
    parts = raw.split()
    if len(parts) == 1 and parts[0] in ("random-host", "random-agent", "agents"):
        return Target(kind=parts[0])
    if len(parts) == 2 and parts[0] in ("host", "agent", "agent-type"):
        kind, value = parts
        if kind == "host" and not _HOST.match(value):
            raise ValueError(f"host names are h1..h99, not {value!r}")
        if not _NAME.match(value):
            raise ValueError(f"{value!r} is not a valid {kind} name")
        return Target(kind=kind, value=value)
    raise ValueError(
        f"unknown target {raw!r} (host NAME, random-host, agent NAME, agent-type TYPE, random-agent, agents, "
        "or a list of hosts)"
    )


Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class Fault(BaseModel):
    """One line of `faults` (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    action: Literal["kill", "pause", "restart", "hang", "partition"]
    target: Target
    at_s: Seconds | None = None
    every_s: Positive | None = None
    life_s: tuple[Positive, Positive] | None = None
    for_s: Positive | None = None
    hang_s: Positive | None = None

    @field_validator("target", mode="before")
    @classmethod
    def _target(cls, v: Any) -> Target:
        if isinstance(v, dict):  # a plan written back as JSON (plan.json of a run directory)
            return Target.model_validate(v)
        return v if isinstance(v, Target) else parse_target(v)

    @field_validator("life_s")
    @classmethod
    def _life(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and v[0] > v[1]:
            raise ValueError(f"the window [{v[0]:g}, {v[1]:g}] is empty (lo > hi)")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Fault:
        t, a = self.target, self.action
        if self.at_s is None and self.every_s is None and self.life_s is None:
            raise ValueError("needs a schedule: at_s, every_s or life_s")
        if self.life_s is not None and (self.at_s is not None or self.every_s is not None):
            raise ValueError("life_s is a schedule of its own: not with at_s or every_s")
        if a == "partition":
            if t.kind != "hosts":
                raise ValueError("partition takes a list of hosts, e.g. target: [h1, h2]")
        elif t.kind == "hosts":
            raise ValueError(f"a list of hosts is a partition's target, not {a}'s")
        if t.is_host and a not in HOST_ACTIONS | {"partition"}:
            raise ValueError(f"{a} applies to agents, not to {t.text()} (hosts take kill, pause, restart)")
        if not t.is_host and a not in AGENT_ACTIONS:
            raise ValueError(f"{a} applies to hosts, not to {t.text()} (agents take kill, hang)")
        if self.life_s is not None and t.kind not in ("agents", "agent", "agent-type"):
            raise ValueError("life_s draws a failure time per agent: target agents, agent NAME or agent-type TYPE")
        if a in ("pause", "partition") and self.for_s is None:
            raise ValueError(f"{a} needs for_s (how long)")
        if a not in ("pause", "partition") and self.for_s is not None:
            raise ValueError(f"for_s is for pause and partition, not {a}")
        if a == "hang" and self.hang_s is None:
            raise ValueError("hang needs hang_s (how long the agent's event loop stays blocked)")
        if a != "hang" and self.hang_s is not None:
            raise ValueError(f"hang_s is for hang, not {a}")
        return self

    def describe(self) -> str:
        when = (
            f"at {self.at_s:g} s" if self.at_s is not None and self.every_s is None
            else f"every {self.every_s:g} s" + (f" from {self.at_s:g} s" if self.at_s is not None else "")
            if self.every_s is not None
            else f"life {self.life_s[0]:g}-{self.life_s[1]:g} s" if self.life_s else ""
        )
        extra = f" for {self.for_s:g} s" if self.for_s else f" {self.hang_s:g} s" if self.hang_s else ""
        return f"{self.action} {self.target.text()}{extra} {when}"


class Plan(BaseModel):
    """A whole plan (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(pattern=_NAME.pattern)
    seed: int = 0
    #: None: until the mission ends (a plan named by a mission file only; `haactl chaos run` needs it)
    duration_s: Annotated[float, Field(gt=0, le=MAX_DURATION, allow_inf_nan=False)] | None = None
    hosts: Annotated[int, Field(ge=3, le=10)] = 5
    workload: Literal["ddb-writes", "counters"] | None = None
    #: workload agents (writers, or counter pairs)
    agents: Annotated[int, Field(ge=1, le=20)] = 3
    #: seconds between two writes of one writer (ddb-writes) or two pings of a counter
    period_s: Annotated[float, Field(ge=0.02, le=60, allow_inf_nan=False)] = 0.2
    #: after the last fault: the most seconds to wait for the group to settle (recoveries, rejoins) before
    #: the checks
    settle_s: Annotated[float, Field(gt=0, le=600, allow_inf_nan=False)] = 30.0
    #: extra haa-hostd arguments for every host (e.g. ["--agent-start-grace", "1"])
    hostd_args: Annotated[list[Annotated[str, Field(max_length=256)]], Field(max_length=32)] = Field(
        default_factory=list)
    faults: list[Fault] = Field(default_factory=list)
    #: run every host as a deliberately broken variant (haa.lab.chaos.mutations; local cluster only): the check
    #: it targets must fail
    mutation: str | None = None

    @field_validator("mutation")
    @classmethod
    def _mutation(cls, v: str | None) -> str | None:
        if v is not None and v not in MUTATIONS:
            raise ValueError(f"unknown mutation {v!r} (one of {', '.join(MUTATIONS)})")
        return v

    @model_validator(mode="after")
    def _fits(self) -> Plan:
        for i, f in enumerate(self.faults):
            where = f"faults[{i}]"
            names = [f.target.value] if f.target.kind == "host" else list(f.target.hosts)
            for n in names:
                if int(n[1:]) > self.hosts:
                    raise ValueError(f"{where}.target: {n} is not a host of this plan (hosts: h1..h{self.hosts})")
            if self.duration_s is None:
                continue
            if f.at_s is not None and f.at_s >= self.duration_s:
                raise ValueError(f"{where}.at_s: {f.at_s:g} is not before duration_s {self.duration_s:g}")
            if f.life_s is not None and f.life_s[0] >= self.duration_s:
                raise ValueError(f"{where}.life_s: the window starts after duration_s {self.duration_s:g}")
        return self


def mission_problems(plan: Plan, hosts: set[str]) -> list[str]:
    """What a plan asks that a mission cannot do (module docstring), one line each; `hosts` are the host names
    the mission runs at some time."""
    out = []
    if plan.workload is not None:
        out.append(f"workload: {plan.workload} is for `haactl chaos run`; a mission's agents are its workload")
    if plan.mutation is not None:
        out.append("mutation: for `haactl chaos run` on a local cluster, not inside a mission")
    for i, f in enumerate(plan.faults):
        if f.action == "partition":
            out.append(f"faults[{i}]: partition is not available on a mission's local cluster (its hosts share "
                       "loopback and there is no link to cut without root)")
        names = [f.target.value] if f.target.kind == "host" else list(f.target.hosts)
        for n in names:
            if n not in hosts:
                out.append(f"faults[{i}].target: {n} is not a host of this mission ({', '.join(sorted(hosts))})")
    return out


def _loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for p in loc:
        if isinstance(p, int):
            out += f"[{p}]"
        elif p in ("function-after[_consistent()]",) or str(p).startswith(("function-", "constrained-")):
            continue
        else:
            out += ("." if out else "") + str(p)
    return out


def error_line(e: ValidationError) -> str:
    """The first error of a validation, as `field: reason`."""
    err = e.errors()[0]
    msg = str(err.get("msg", "invalid"))
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    where = _loc(tuple(err.get("loc", ())))
    if err.get("type") == "extra_forbidden":
        msg = "unknown key"
    elif err.get("type") == "missing":
        msg = "required"
    return f"{where}: {msg}" if where else msg


def parse_plan(data: Any, source: str = "plan") -> Plan:
    """Validate a plan already parsed from YAML/JSON."""
    if not isinstance(data, dict):
        raise PlanError(f"{source}: the top level must be a mapping (name:, duration_s:, faults:)")
    try:
        return Plan.model_validate(data)
    except ValidationError as e:
        raise PlanError(f"{source}: {error_line(e)}") from None


def load_plan(path: Path) -> Plan:
    """Read and validate a plan file (PlanError with one line if it cannot run)."""
    try:
        data = files.load_yaml(path, what="chaos plan", max_bytes=MAX_PLAN_BYTES)
    except files.FileError as e:
        raise PlanError(f"chaos plan {e.path}: {e.reason}") from None
    return parse_plan(data, f"chaos plan {path}")
