"""One time line of a chaos run: the injected faults and their effects as the hosts logged them.

Sources: `faults.json` (what the injector did, when) and every host's persisted JSON-lines log
(`hosts/<name>.jsonl`), so the events of a host that was killed are there and every line names the host where
it happened. Effects kept: suspicions (a host starts or stops suspecting a peer), view changes (removals and
joins, once per view), a host finding itself removed, agents hung, crashed, recovering, recovered, freezing,
thawed (transfers), failed, removed. The agent events are read and merged by haa.cluster.events (the same
parser and merge as `haactl agent events`): events that every member logs for one committed change (an
agent's crash from the table, its removal, its failure) are shown once, and a crash the table recorded is
shown on the host that ran the agent, with the host that reported it ("A1 crashed on h4 (reported by h1)").
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from haa.cluster.events import Merger, TimelineEvent, timeline_events
from haa.lab.chaos.collect import host_logs

#: agent timeline events shown, and how
AGENT_WORDS = {
    "agent_crashed": "crashed",
    "agent_recovering": "recovering",
    "agent_recovered": "recovered",
    "agent_freezing": "freezing",
    "agent_frozen": "frozen",
    "agent_thawing": "thawing",
    "agent_thawed": "thawed",
    "agent_active": "started",
    "agent_failed": "failed",
    "agent_backoff": "start failure",
    "agent_removed": "removed",
}


@dataclass
class Entry:
    ts: float
    t: float  # seconds since the chaos started
    host: str  # where it happened ("" for the injector's own lines)
    kind: str  # "fault" | "effect"
    text: str

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _effects(host: str, r: dict[str, Any]) -> str | None:
    ev = r.get("event")
    f = r.get("fields") or {}
    if not isinstance(f, dict):
        return None
    if ev == "suspicion":
        return f"{host} {'suspects' if f.get('suspected') else 'trusts again'} {f.get('peer')}"
    if ev == "removed":
        return f"{host} finds itself removed from the group (view {f.get('view')}): it re-applies"
    if ev == "reincarnate":
        return f"{host} starts a new incarnation"
    if ev == "agent_hung":
        return f"{f.get('name')} hung on {host} (no heartbeat for {f.get('silent')} s): killed"
    return None


def _agent_text(e: TimelineEvent) -> str:
    """An agent event (kept and attributed by `Merger`) as a timeline line."""
    word = AGENT_WORDS["agent_" + e.event]
    if e.event == "crashed" and not e.detail:
        where = f" on {e.host}" if e.host else ""
        return f"{e.name} {word}{where}" + (f" (reported by {e.reporter})" if e.reporter else "")
    if e.event == "removed":  # a change of the group's table, not of one host: say which host logged it first
        return f"{e.name} removed (reported by {e.host})"
    detail = f" ({e.detail})" if e.detail else ""
    return f"{e.name} {word} on {e.host}{detail}"


def build(run: Path) -> list[Entry]:
    """The merged time line of a run directory, time ordered."""
    faults = json.loads((run / "faults.json").read_text()) if (run / "faults.json").exists() else {}
    t0 = float(faults.get("t0", 0.0))
    t_end = float(faults.get("t_end", 0.0)) or float("inf")  # the replicas were read: the run is over
    out: list[Entry] = []
    for f in faults.get("faults", []):
        state = "" if f.get("ok") else " [not done]"
        detail = f": {f['detail']}" if f.get("detail") else ""
        out.append(Entry(f["ts"], f["ts"] - t0, "", "fault", f"{f['action']} {f['target']}{detail}{state}"))
    logs = host_logs(run)
    in_run = [e for e in timeline_events(logs) if e.event in {k[len("agent_"):] for k in AGENT_WORDS}]
    for e in Merger().merge(in_run):  # attributed from the whole history (an agent may have moved before t0)
        if t0 - 1.0 <= e.time <= t_end:
            out.append(Entry(e.time, e.time - t0, e.host or e.reporter, "effect", _agent_text(e)))
    seen_views: set[tuple[Any, ...]] = set()
    records = sorted(((float(r.get("ts", 0)), host, r) for host, recs in logs.items() for r in recs),
                     key=lambda x: x[0])
    for ts, host, r in records:
        if ts < t0 - 1.0 or ts > t_end:
            continue  # before the chaos (cluster start, workload start) or after it (the cluster stopping)
        ev = r.get("event")
        f = r.get("fields") or {}
        if ev == "view" and isinstance(f, dict) and (f.get("removed") or f.get("added")):
            key = (f.get("view"), tuple(f.get("removed") or ()), tuple(f.get("added") or ()))
            if key in seen_views:
                continue
            seen_views.add(key)
            parts = [f"{', '.join(f['removed'])} removed"] if f.get("removed") else []
            parts += [f"{', '.join(f['added'])} joined"] if f.get("added") else []
            out.append(Entry(ts, ts - t0, host, "effect", f"view {f.get('view')}: {'; '.join(parts)}"))
            continue
        text = _effects(host, r)
        if text is not None:
            out.append(Entry(ts, ts - t0, host, "effect", text))
    out.sort(key=lambda e: e.ts)
    return out


def clock(t: float) -> str:
    sign = "-" if t < 0 else ""
    t = abs(t)
    return f"{sign}{int(t // 60):02d}:{t % 60:04.1f}"
