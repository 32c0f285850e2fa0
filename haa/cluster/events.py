"""The allocation timeline of a cluster, from what every host persisted (issue 18 §3, "the merged timeline must
be true first").

Every host logs each entry of its allocation timeline (haa.hostd.agentdriver.on_timeline) as one JSON line
`agent_<event>` with the fields `agent` (id), `name` (display name) and `detail`, to its data dir
(`<data dir>/<name>.jsonl`, local clusters) or to stderr (containers: the container's log). Those records
outlive the host's process — a host that was killed keeps its file, a stopped container its log, and a
restarted one appends to them — unlike the in-memory history that `AgentEvents` streams replay, which a
restarted host has lost. So the timeline of a cluster is built from them:

* `persisted_logs(backend)` — the JSON records of every host the backend knows, in every state (alive,
  killed, left, stopped), through `Backend.log_records` (local: the data dirs' files; compose: the docker SDK's
  container logs, which stopped containers keep);
* `log_event` — the one parser of a timeline record (also used by haa.lab.chaos.timeline);
  `timeline_events(logs)` all of them, time ordered, agents named by display name (a removed agent is logged
  under its id prefix); `view_events(logs)` the membership changes (`hN removed`, `hN joined`), once per view;
* `Merger` — de-duplication and attribution over the time-ordered events of all hosts. Events every member
  logs for one committed change (created, removed, failed, and "crashed" when the table marks an agent
  crashed) are kept once; a table-level crash is attributed to the host where the agent last became active
  (`host`), and the host whose log reported it is kept as `reporter` — the host that ran an agent does not
  report its own removal from the group ("A1 crashed on h10 (reported by h1)").
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from haa.cluster.backend import Backend, ClusterError, natural_key

#: the timeline events of haa.hostd (agentnode, transfer, recovery), logged as agent_<event>
EVENTS = frozenset({"created", "spawning", "active", "freezing", "frozen", "thawing", "thawed", "crashed",
                    "recovering", "recovered", "removed", "backoff", "failed"})
#: events every member reports for the same committed table change (kept once)
TABLE_EVENTS = frozenset({"created", "removed", "failed"})
#: events that mean "the agent runs on the event's host from now on"
RUNS_ON = frozenset({"active", "thawed", "recovered"})
#: a repeat of a shared event (another member's report of the same change) within this many seconds is dropped
SHARED_S = 3.0


@dataclass
class TimelineEvent:
    """One line of the merged timeline."""

    time: float  # unix time at the reporting host
    agent: str  # agent id ("" for a host line: joined, removed, an operator's step)
    name: str
    event: str
    host: str  # where it happened (for a table-level crash: where the agent ran, once `Merger` attributed it)
    detail: str = ""
    type: str = ""
    text: str = ""  # the transcript line without the clock ("A1 (counter) freezing on h4 (to h3)")
    reporter: str = ""  # the host whose log (or stream) reported it, when that is not `host`

    def clock(self, t0: float, absolute: bool = False) -> str:
        if absolute:
            return time.strftime("%H:%M:%S", time.localtime(self.time))
        s = max(0, int(self.time - t0))
        return f"{s // 60:02d}:{s % 60:02d}"


def host_event(t: float, host: str, what: str) -> TimelineEvent:
    return TimelineEvent(t, "", host, what, host, text=f"{host} {what}")


# ---------------------------------------------------------------------------------------------- reading


def parse_lines(lines: Iterable[str]) -> list[dict[str, Any]]:
    """The JSON objects among raw log lines (a traceback or a start-up error line is skipped)."""
    out = []
    for line in lines:
        line = line.strip()
        if not line.startswith("{"):
            continue
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if isinstance(obj, dict):
            out.append(obj)
    return out


def persisted_logs(backend: Backend, names: Sequence[str] | None = None,
                   errors: dict[str, str] | None = None) -> dict[str, list[dict[str, Any]]]:
    """host name -> the JSON records of its persisted log in file order, for every host the backend knows
    (whatever its state) or the named ones. A host whose log cannot be read is left out (and, with `errors`,
    reported there with the reason)."""
    hosts = list(names) if names is not None else [h.name for h in backend.hosts()]
    out: dict[str, list[dict[str, Any]]] = {}
    for n in sorted(hosts, key=natural_key):
        try:
            out[n] = parse_lines(line for _, line in backend.log_records([n], follow=False))
        except (ClusterError, OSError) as e:
            if errors is not None:
                errors[n] = str(e)
        except Exception as e:  # the docker SDK's own errors (a container removed meanwhile, ...)
            if errors is not None:
                errors[n] = f"{type(e).__name__}: {e}"
    return out


# ---------------------------------------------------------------------------------------------- parsing


def log_event(host: str, r: dict[str, Any]) -> TimelineEvent | None:
    """The timeline event of one log record of `host` (an `agent_<event>` record with `agent` and `detail`
    fields, as haa.hostd.agentdriver logs it), else None. Other agent_* records (the supervisor's process
    events carry a pid) are not timeline entries."""
    ev = r.get("event")
    f = r.get("fields")
    if not isinstance(ev, str) or not ev.startswith("agent_") or not isinstance(f, dict):
        return None
    kind = ev[len("agent_"):]
    if kind not in EVENTS or "detail" not in f or "pid" in f or not isinstance(f.get("agent"), str):
        return None
    try:
        ts = float(r.get("ts", 0))
    except (TypeError, ValueError):
        return None
    return TimelineEvent(ts, f["agent"], str(f.get("name") or f["agent"][:8]), kind, host, str(f.get("detail") or ""))


def timeline_events(logs: dict[str, list[dict[str, Any]]]) -> list[TimelineEvent]:
    """Every timeline event of every host's log, time ordered (a stable sort: one host's events keep their
    order). A removed agent is logged under its id prefix (its table entry is gone): it gets its display name."""
    evs = [e for host, recs in logs.items() for r in recs if (e := log_event(host, r)) is not None]
    evs.sort(key=lambda e: e.time)
    names = {e.agent: e.name for e in evs if e.name and e.name != e.agent[:8]}
    for e in evs:
        if e.name == e.agent[:8]:
            e.name = names.get(e.agent, e.name)
    return evs


def view_events(logs: dict[str, list[dict[str, Any]]]) -> list[TimelineEvent]:
    """`hN removed` / `hN joined` for every view change the hosts logged, once per view (every member logs
    it), time ordered; `detail` is the view number and `reporter` the first host that logged it."""
    recs = sorted(((float(r.get("ts", 0)), host, r) for host, rs in logs.items() for r in rs
                   if r.get("event") == "view" and isinstance(r.get("fields"), dict)), key=lambda x: x[0])
    seen: set[tuple[Any, ...]] = set()
    out: list[TimelineEvent] = []
    for ts, host, r in recs:
        f = r["fields"]
        removed, added = list(f.get("removed") or ()), list(f.get("added") or ())
        if not removed and not added:
            continue
        key = (f.get("view"), tuple(removed), tuple(added))
        if key in seen:
            continue
        seen.add(key)
        for what, names in (("removed", removed), ("joined", added)):
            for n in names:
                e = host_event(ts, str(n), what)
                e.detail, e.reporter = f"view {f.get('view')}", host
                out.append(e)
    return out


# ---------------------------------------------------------------------------------------------- merging


class Merger:
    """De-duplication and attribution of the time-ordered timeline events of all hosts (module docstring).

    Stateful, so that a follower can feed it batch by batch. `take(e, batch)` returns False for an event that
    repeats one already kept; otherwise it fills `e.type` (from the agent's `created` event) and, for a
    table-level crash, `e.host` (where the agent last became active) and `e.reporter` (the reporting host)."""

    def __init__(self) -> None:
        self.types: dict[str, str] = {}  # agent id -> type
        self.runs_on: dict[str, str] = {}  # agent id -> the host it last became active on
        self.kept: dict[tuple[str, str], float] = {}  # (agent, event) -> time of the last kept shared event

    def take(self, e: TimelineEvent, batch: Sequence[TimelineEvent] = ()) -> bool:
        if not e.agent:
            return True  # a host line
        kind = e.event
        if kind == "created" and e.detail:
            self.types[e.agent] = e.detail
        e.type = self.types.get(e.agent, e.type)
        if kind in TABLE_EVENTS or kind == "crashed":
            last = self.kept.get((e.agent, kind))
            if last is not None and abs(e.time - last) < SHARED_S:
                return False  # another member's report of the same change (or the crash its cause explained)
            if kind == "crashed" and not e.detail and any(
                x.agent == e.agent and x.event == "crashed" and x.detail and abs(x.time - e.time) < SHARED_S
                for x in batch
            ):
                return False  # the host that ran it reported the cause: that line is kept instead
            self.kept[(e.agent, kind)] = e.time
        if kind == "crashed" and not e.detail:
            # the table marked it crashed (OAC(failed) committed, or its host was removed from the group):
            # every member says so, but it happened where the agent ran
            where = self.runs_on.get(e.agent, "")
            if where != e.host:
                e.reporter, e.host = e.host, where
        if kind in RUNS_ON:
            self.runs_on[e.agent] = e.host
        return True

    def merge(self, events: Iterable[TimelineEvent]) -> list[TimelineEvent]:
        """Sort and keep the events `take` keeps (one batch)."""
        evs = sorted(events, key=lambda e: e.time)
        return [e for e in evs if self.take(e, evs)]


def take_persisted(persisted: dict[tuple[str, str, str, str], list[float]], host: str, agent: str, event: str,
                   detail: str, t: float) -> bool:
    """Whether a persisted record (`persisted`: (host, agent, event, detail) -> times, from `timeline_events`)
    holds this streamed event: an AgentEvents stream replays the host's kept history, which its log already
    holds — the same host, agent, event and detail within a second. The matched record is used up."""
    times = persisted.get((host, agent, event, detail))
    if not times:
        return False
    best = min(times, key=lambda x: abs(x - t))
    if abs(best - t) > 1.0:
        return False
    times.remove(best)
    return True


def persisted_timeline(backend: Backend, views: bool = True,
                       errors: dict[str, str] | None = None) -> list[TimelineEvent]:
    """The merged timeline of every host's persisted log (with the view changes unless `views` is False):
    de-duplicated, attributed, time ordered. `errors` collects the hosts whose logs could not be read."""
    logs = persisted_logs(backend, errors=errors)
    evs = timeline_events(logs) + (view_events(logs) if views else [])
    return Merger().merge(evs)
