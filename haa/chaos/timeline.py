"""One time line of a chaos run: the injected faults and their effects as the hosts logged them.

Sources: `faults.json` (what the injector did, when) and every host's persisted JSON-lines log
(`hosts/<name>.jsonl`), so the events of a host that was killed are there and every line names the host where
it happened. Effects kept: suspicions (a host starts or stops suspecting a peer), view changes (removals and
joins, once per view), a host finding itself removed, agents hung, crashed, recovering, recovered, freezing,
thawed (transfers), failed, removed. Events that every member logs for one committed change (an agent's
crash from the table, its removal) are shown once.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from haa.chaos.collect import host_logs

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
#: events every member logs for one committed change: shown once per (agent, event) within this many seconds
DEDUP_S = 3.0


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
    if ev in AGENT_WORDS and "detail" in f and "pid" not in f:
        detail = f" ({f['detail']})" if f.get("detail") else ""
        return f"{f.get('name')} {AGENT_WORDS[ev]} on {host}{detail}"
    return None


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
    seen_views: set[tuple[Any, ...]] = set()
    last_shared: dict[tuple[str, str, str], float] = {}
    records = sorted(((float(r.get("ts", 0)), host, r) for host, recs in host_logs(run).items() for r in recs),
                     key=lambda x: x[0])
    # a removed agent is logged under its id prefix (its table entry is gone): show its display name
    names = {f["agent"]: f["name"] for _, _, r in records
             if isinstance(f := r.get("fields"), dict) and isinstance(f.get("agent"), str) and f.get("name")
             and f["name"] != f["agent"][:8]}
    for ts, host, r in records:
        fl = r.get("fields")
        if isinstance(fl, dict) and isinstance(fl.get("agent"), str) and fl.get("name", "") in ("", fl["agent"][:8]):
            r = {**r, "fields": {**fl, "name": names.get(fl["agent"], fl["agent"][:8])}}
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
        if text is None:
            continue
        if ev in ("agent_crashed", "agent_removed"):
            k = (str(f.get("agent")), str(ev), "")
            seen, last_shared[k] = last_shared.get(k, -1e18), ts
            if not f.get("detail"):
                if ts - seen < DEDUP_S:
                    continue
                text = f"{f.get('name')} {AGENT_WORDS[str(ev)]} (reported by {host})"
        out.append(Entry(ts, ts - t0, host, "effect", text))
    out.sort(key=lambda e: e.ts)
    return out


def clock(t: float) -> str:
    sign = "-" if t < 0 else ""
    t = abs(t)
    return f"{sign}{int(t // 60):02d}:{t % 60:04.1f}"
