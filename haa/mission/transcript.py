"""The mission transcript of Fig. 7.1-3 (thesis L1417-1462): one time-ordered list of what happened, times as
mm:ss of simulated mission time.

    00:00 h1 joined
    00:02 Mission started
    00:02 A1 (ExecutiveMission) spawned by h2
    00:51 A3 (AvatarSimulation) freezing on h4
    01:00 h4 retires (graceful leave)
    03:58 Mission finished: 95.1 % explored

Sources, merged by `merge` (`mission_transcript` makes a mission's from all three):

* the team's own lines, DDB log `mission/events` (docs/team.md: `{"t": sim s, "agent": name, "type": type,
  "text": str}`) — `mission_lines`;
* the hosts' agent timelines (every host logs `agent_<event>` JSON lines with the agent's id, display name and a
  detail: created, spawning, active, freezing, frozen, thawing, thawed, crashed, backoff, failed, recovering,
  recovered, removed; haa.hostd.agentdriver) — `host_agent_lines`, stamped in wall time and put on the
  simulated clock by a `ClockMap` of (wall, sim) pairs the runner sampled;
* the runner's own lines: host group changes it made or saw, avatars joining and leaving the arena, the
  mission starting and finishing — `Line`s made by the runner.

Events that every member reports for the same table change (created, removed, failed, and "crashed" at a host's
removal) are shown once; a crash reported with its cause by the host that ran the agent wins over the members'
bare reports.
"""

from __future__ import annotations

import bisect
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

#: agent type names (docs/team.md) -> the thesis' class names shown in the transcript
TYPE_NAMES = {
    "executive_mission": "ExecutiveMission",
    "executive_avatar": "ExecutiveAvatar",
    "supervisor_explore": "SupervisorExplore",
    "supervisor_slam": "SupervisorSLAM",
    "supervisor_congregate": "SupervisorCongregate",
    "supervisor_forage": "SupervisorForage",
    "avatar_simulation": "AvatarSimulation",
    "path_planner": "AgentPathPlanner",
    "sensor_landmark": "AgentSensorLandmark",
    "sensor_floorfinder": "AgentSensorFloorFinder",
    "sensor_cooccupancy": "AgentSensorCooccupancy",
    "sensor_sonar": "AgentSensorSonar",
}

#: events every member reports once for the same committed table change
TABLE_EVENTS = frozenset({"created", "removed", "failed"})
DEDUP_WINDOW = 3.0  # wall seconds


def class_name(type_name: str) -> str:
    """`sensor_sonar` -> `AgentSensorSonar` (known types), else CamelCase of the type name."""
    if type_name in TYPE_NAMES:
        return TYPE_NAMES[type_name]
    return "".join(p[:1].upper() + p[1:] for p in type_name.replace("-", "_").split("_") if p) or type_name


def clock(t: float) -> str:
    """Simulated seconds -> mm:ss (minutes keep counting past 59)."""
    s = max(0, int(t))
    return f"{s // 60:02d}:{s % 60:02d}"


@dataclass
class Line:
    """One transcript line at simulated mission time `t`."""

    t: float
    text: str
    source: str = "runner"  # mission | host | runner
    event: str = ""  # the agent event (freezing, thawed, ...), "mission", "host", "avatar", ...
    agent: str = ""  # agent display name (A1.2) when the line is about an agent
    host: str = ""
    wall: float = 0.0  # wall time of a host event (0: not from a host)

    def format(self) -> str:
        return f"{clock(self.t)} {self.text}"

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["clock"] = clock(self.t)
        return d


def format_lines(lines: Iterable[Line]) -> list[str]:
    return [ln.format() for ln in lines]


def merge(*sources: Iterable[Line]) -> list[Line]:
    """All lines in time order; lines of the same time keep the order of `sources`, then their own."""
    out = [(ln.t, i, k, ln) for i, src in enumerate(sources) for k, ln in enumerate(src)]
    out.sort(key=lambda x: (x[0], x[1], x[2]))
    return [x[3] for x in out]


# ---------------------------------------------------------------------------------------------- clock map


class ClockMap:
    """Wall time -> simulated time, from (wall, sim) pairs sampled while the mission ran (haa-sim's clock may
    run slower than asked on a busy machine, so a fixed speed would drift). Between samples: linear; before
    the first and after the last: extrapolated at `speed`."""

    def __init__(self, speed: float = 1.0) -> None:
        self.speed = speed
        self.wall: list[float] = []
        self.sim: list[float] = []

    def add(self, wall: float, sim: float) -> None:
        if self.wall and (wall <= self.wall[-1] or sim < self.sim[-1]):
            return
        self.wall.append(wall)
        self.sim.append(sim)

    def __bool__(self) -> bool:
        return bool(self.wall)

    def to_sim(self, wall: float) -> float:
        if not self.wall:
            raise ValueError("no clock samples")
        k = bisect.bisect_left(self.wall, wall)
        if k <= 0:
            return self.sim[0] + (wall - self.wall[0]) * self.speed
        if k >= len(self.wall):
            return self.sim[-1] + (wall - self.wall[-1]) * self.speed
        w0, w1 = self.wall[k - 1], self.wall[k]
        s0, s1 = self.sim[k - 1], self.sim[k]
        return s0 + (s1 - s0) * (wall - w0) / (w1 - w0)

    def to_json(self) -> list[list[float]]:
        return [[w, s] for w, s in zip(self.wall, self.sim, strict=True)]


# ---------------------------------------------------------------------------------------------- sources


def mission_lines(entries: Iterable[Any]) -> list[Line]:
    """`mission/events` entries (dicts, or JSON bytes/str) -> lines "A6 (ExecutiveMission) <text>" (just the
    text when the entry names no agent). Entries that do not parse are skipped."""
    out = []
    for raw in entries:
        e = raw
        if isinstance(raw, bytes | bytearray | str):
            try:
                e = json.loads(raw)
            except ValueError:
                continue
        if not isinstance(e, dict) or "text" not in e:
            continue
        try:
            t = float(e.get("t", 0.0))
        except (TypeError, ValueError):
            continue
        agent = str(e.get("agent") or "")
        typ = str(e.get("type") or "")
        who = f"{agent} ({class_name(typ)})" if agent and typ else agent
        text = str(e["text"])
        out.append(Line(t, f"{who} {text}" if who else text, "mission", "mission", agent))
    return out


def host_agent_events(records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Host JSON log records (haa.hostd.logs: ts, host, event, fields) -> agent timeline events
    `{"time", "agent", "name", "event", "host", "detail"}` (the `agent_<event>` lines of the timeline)."""
    kinds = {"created", "spawning", "active", "freezing", "frozen", "thawing", "thawed", "crashed", "backoff",
             "failed", "recovering", "recovered", "removed"}
    out: list[dict[str, Any]] = []
    for r in records:
        ev = str(r.get("event", ""))
        if not ev.startswith("agent_") or ev[6:] not in kinds:
            continue
        f = r.get("fields") or {}
        if not isinstance(f, dict) or "agent" not in f:
            continue
        out.append({"time": float(r.get("ts", 0.0)), "agent": str(f.get("agent", "")),
                    "name": str(f.get("name", "")), "event": ev[6:], "host": str(r.get("host", "")),
                    "detail": str(f.get("detail", "") or "")})
    out.sort(key=lambda e: e["time"])
    return out


def dedup_agent_events(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Drop the repeats: a table event (created, removed, failed) reported by every member, and the members'
    bare "crashed" when the host that ran the agent reported the crash with its cause (or another member
    already reported it) within `DEDUP_WINDOW` seconds."""
    out = []
    shown: dict[tuple[str, str], float] = {}
    evs = sorted(events, key=lambda e: e["time"])
    for i, e in enumerate(evs):
        kind, agent, t = e["event"], e["agent"], e["time"]
        if kind in TABLE_EVENTS or kind == "crashed":
            if kind == "crashed" and not e["detail"] and any(
                x["agent"] == agent and x["event"] == "crashed" and x["detail"] and abs(x["time"] - t) < DEDUP_WINDOW
                for x in evs[max(0, i - 50) : i + 50]
            ):
                continue
            last = shown.get((agent, kind))
            if last is not None and t - last < DEDUP_WINDOW:
                continue
            shown[(agent, kind)] = t
        out.append(e)
    return out


def describe_agent_event(e: dict[str, Any], types: dict[str, str], runs_on: dict[str, str]) -> str:
    """The transcript text of one agent event (Fig. 7.1-3 wording: requested by, spawned by, freezing on,
    thawed by, crashed, recovered by, removed)."""
    kind, host, d = e["event"], e["host"], e["detail"]
    typ = types.get(e["agent"], "")
    name = e["name"] or e["agent"][:8]
    who = f"{name} ({class_name(typ)})" if typ else name
    if kind == "created":
        parent = name.rsplit(".", 1)[0] if "." in name else ""
        return f"{who} requested by {parent if parent else 'the operator'}"
    if kind == "spawning":
        return f"{who} spawning on {host}"
    if kind == "active":
        return f"{who} spawned by {host}"
    if kind == "freezing":
        return f"{who} freezing on {host}" + (f" ({d})" if d else "")
    if kind == "frozen":
        return f"{who} frozen on {host}"
    if kind == "thawing":
        return f"{who} thawing on {host}"
    if kind == "thawed":
        return f"{who} thawed by {host}"
    if kind == "crashed":
        if d:
            return f"{who} crashed on {host}: {d}"
        last = runs_on.get(e["agent"])
        return f"{who} crashed" + (f" on {last}" if last else "")
    if kind == "recovering":
        return f"{who} recovering on {host}"
    if kind == "recovered":
        return f"{who} recovered by {host}" + (f" ({d})" if d else "")
    if kind == "removed":
        return f"{who} removed"
    if kind == "backoff":
        return f"{who} could not start: {d}"
    if kind == "failed":
        # with a reason: the table gave up on it (start failures in a row; recovery.py); without: the agent
        # failure itself was applied (its process died), and the crash report follows
        return f"{who} failed, not recovered any more: {d}" if d else f"{who} failed on {host}"
    return f"{who} {kind} on {host}" + (f" ({d})" if d else "")


def host_agent_lines(events: list[dict[str, Any]], clock_map: ClockMap, t0: float = 0.0,
                     skip: frozenset[str] = frozenset({"spawning", "frozen", "thawing", "recovering"})) -> list[Line]:
    """Agent timeline events (`host_agent_events`) -> lines on the mission clock (simulated time minus `t0`).
    The intermediate phases in `skip` are left out as in Fig. 7.1-3 (requested, spawned, freezing, thawed,
    crashed, recovered, removed remain)."""
    types: dict[str, str] = {}
    runs_on: dict[str, str] = {}
    names: dict[str, str] = {}  # agent id -> display name (a host's "removed" names it by its id's first part)
    out = []
    for e in dedup_agent_events(events):
        if e["name"] and not e["agent"].startswith(e["name"]):
            names[e["agent"]] = e["name"]
        elif e["agent"] in names:
            e = {**e, "name": names[e["agent"]]}
        if e["event"] == "created" and e["detail"]:
            types[e["agent"]] = e["detail"]
        text = describe_agent_event(e, types, runs_on)
        if e["event"] in ("active", "thawed", "recovered"):
            runs_on[e["agent"]] = e["host"]
        if e["event"] in skip:
            continue
        t = clock_map.to_sim(e["time"]) - t0 if clock_map else 0.0
        out.append(Line(t, text, "host", e["event"], e["name"], e["host"], e["time"]))
    return out


def mission_transcript(runner_lines: Iterable[Line], events: Iterable[Any], records: Iterable[dict[str, Any]],
                       clock_map: ClockMap, t0: float = 0.0, status: dict[str, Any] | None = None,
                       since: float | None = None) -> tuple[list[Line], list[dict[str, Any]]]:
    """A mission's transcript (module docstring) and the agent timeline events it was made from: the runner's
    own lines, the team's `mission/events` entries, and the agent events among the hosts' log `records` (those
    from wall time `since` on, when given: a cluster the operator runs has older ones), on the mission clock
    (`clock_map`'s simulated time minus `t0`). "Mission started" and "Mission finished" come from the last
    `mission/status` when the team's own lines do not say so."""
    agent_events = host_agent_events(records)
    if since is not None:
        agent_events = [e for e in agent_events if e["time"] >= since]
    host_lines = host_agent_lines(agent_events, clock_map, t0) if clock_map else []
    team = mission_lines(events)
    own = list(runner_lines)
    texts = " ".join(ln.text.lower() for ln in team)
    st = status if isinstance(status, dict) else {}
    if "mission started" not in texts and isinstance(st.get("started_t"), int | float):
        own.append(Line(float(st["started_t"]) - t0, "Mission started", "runner", "mission"))
    if "mission finished" not in texts and isinstance(st.get("finished_t"), int | float):
        reason = f": {st['reason']}" if st.get("reason") else ""
        own.append(Line(float(st["finished_t"]) - t0, f"Mission finished{reason}", "runner", "mission"))
    return merge(own, team, host_lines), agent_events
