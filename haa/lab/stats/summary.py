"""The cluster summary of a set of bundles (`summary.json`), and the binned time series the report draws.

`summarize(bundles)` — per host: state, incarnations, samples, time range, mean CPU of the host process and
of its agents, peak RSS, the sampler's own measured cost; for the cluster: agent counts (spawns, transfers,
crashes, recoveries, failures), view changes, host joins and removals, latency summaries of every phase
(haa.lab.stats.phases: spawn, freeze, thaw, recover, allocation per host; transfer and recovery across hosts;
OAC propose->decide and decide->deliver from the samples), messages and bytes per agent pair, CPU per agent
type, the DDB's last size by prefix and by kind, and the merged timeline.

`series(bundles)` — the samples of every host on one clock (seconds since the first record of any host),
in bins of the sampler's period: per host CPU (host process + its agents) and agent count; cluster-wide
hosts sampling, members, agents, CPU per agent type and DDB bytes per kind (Fig. 7.1-7's categories).
"""

from __future__ import annotations

import itertools
import statistics
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from haa.cluster.events import TimelineEvent
from haa.lab.stats import phases
from haa.lab.stats.bundle import FORMAT, Bundle

#: DDB kinds of the thesis' Fig. 7.1-7, by key prefix (haa.hostd.sampler.ddb_prefix); the rest is "other",
#: and the agent table's backups are "agents"
DDB_KINDS = {
    "particle filters": ("slam/log", "slam/ckpt", "slam/est", "slam/estimates", "slam/anchor", "slam/landmarks"),
    "map (POG)": ("slam/map",),
    "sensor readings": ("slam/raw", "slam/done"),
    "agents": ("assign", "targets", "bids", "stats", "avatars"),
}
KIND_ORDER = ("particle filters", "map (POG)", "sensor readings", "agents", "other")
#: a host's last sample counts in a bin of the series for this many sampler periods (then it has stopped)
STALE_PERIODS = 2.5
#: a removal within this many seconds after the host asked to leave is its graceful leave
LEAVE_S = 60.0
#: timeline events kept in the summary at most (the bundles keep all)
MAX_TIMELINE = 5000


def ddb_kind(prefix: str) -> str:
    for kind, prefixes in DDB_KINDS.items():
        if prefix in prefixes or prefix.split("/", 1)[0] in prefixes:
            return kind
    return "other"


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def sampler_period(bundles: Sequence[Bundle]) -> float:
    for b in bundles:
        for r in b.records("stats.jsonl"):
            if r.get("kind") == "config" and _num(r.get("period")):
                return float(r["period"])
    gaps = []
    for b in bundles:
        ts = [float(s["ts"]) for s in b.samples if _num(s.get("ts"))]
        gaps += [y - x for x, y in itertools.pairwise(ts) if y > x]
    return statistics.median(gaps) if gaps else 1.0


def events_of(bundles: Sequence[Bundle]) -> list[TimelineEvent]:
    """The merged agent events of every bundle (each in the bundle of the host where it happened)."""
    out = []
    for b in bundles:
        for r in b.events:
            ts = _num(r.get("ts"))
            if ts is None:
                continue
            out.append(TimelineEvent(ts, str(r.get("agent", "")), str(r.get("name", "")), str(r.get("event", "")),
                                     str(r.get("host") or b.host), str(r.get("detail", "")), str(r.get("type", "")),
                                     reporter=str(r.get("reporter", ""))))
    out.sort(key=lambda e: e.time)
    return out


def view_changes(bundles: Sequence[Bundle]) -> list[dict[str, Any]]:
    """Every view change once (the first host that logged it), time ordered."""
    seen: set[tuple[Any, ...]] = set()
    out = []
    for v in sorted((v for b in bundles for v in b.views), key=lambda v: _num(v.get("ts")) or 0.0):
        key = (v.get("view"), tuple(v.get("members") or ()))
        if key in seen:
            continue
        seen.add(key)
        out.append(v)
    return out


def removals(bundles: Sequence[Bundle], views: Sequence[dict[str, Any]]) -> list[tuple[float, str, bool]]:
    """(ts, host, left) for every host removed from a view: `left` when the host had asked to leave within
    LEAVE_S before (a graceful leave, not a fault)."""
    leaves = {b.host: [float(t) for t in b.manifest.get("leaves") or []] for b in bundles}
    out = []
    for v in views:
        ts = float(v.get("ts") or 0.0)
        for h in v.get("removed") or ():
            left = any(ts - LEAVE_S <= t <= ts + 1.0 for t in leaves.get(h, []))
            out.append((ts, str(h), left))
    return out


def time_range(bundles: Sequence[Bundle]) -> tuple[float, float]:
    lo = [float(b.manifest["first_ts"]) for b in bundles if _num(b.manifest.get("first_ts"))]
    hi = [float(b.manifest["last_ts"]) for b in bundles if _num(b.manifest.get("last_ts"))]
    return (min(lo) if lo else 0.0, max(hi) if hi else 0.0)


def agent_names(bundles: Sequence[Bundle]) -> dict[str, dict[str, str]]:
    """agent id -> {name, type}, from the samples and the events."""
    out: dict[str, dict[str, str]] = {}
    for b in bundles:
        for s in b.samples:
            for aid, a in (s.get("agents") or {}).items():
                if isinstance(a, dict):
                    out.setdefault(aid, {"name": str(a.get("name", aid[:8])), "type": str(a.get("type", ""))})
        for e in b.events:
            aid = str(e.get("agent", ""))
            if aid:
                d = out.setdefault(aid, {"name": str(e.get("name") or aid[:8]), "type": ""})
                if not d["type"] and e.get("type"):
                    d["type"] = str(e["type"])
    return out


def _host_summary(b: Bundle) -> dict[str, Any]:
    samples = b.samples
    cpu = [s["cpu"] for s in samples if _num(s.get("cpu")) is not None]
    agents_cpu = [sum(float(a.get("cpu") or 0) for a in (s.get("agents") or {}).values()) for s in samples]
    rss = [s["rss"] for s in samples if _num(s.get("rss")) is not None]
    # the sampler's cost: its cumulative CPU seconds over the span of each incarnation's samples
    by_inc: dict[Any, list[dict[str, Any]]] = defaultdict(list)
    for s in samples:
        by_inc[s.get("inc")].append(s)
    cost = span = 0.0
    for ss in by_inc.values():
        if len(ss) >= 2:
            cost += float(ss[-1].get("cost_s") or 0) - float(ss[0].get("cost_s") or 0)
            span += float(ss[-1]["ts"]) - float(ss[0]["ts"])
    m = b.manifest
    return {
        "state": m.get("state"), "core": m.get("core"), "incarnations": len(m.get("incarnations") or []),
        "samples": len(samples), "log_records": (m.get("counts") or {}).get("log_records"),
        "events": (m.get("counts") or {}).get("events"), "views": (m.get("counts") or {}).get("views"),
        "first_ts": m.get("first_ts"), "last_ts": m.get("last_ts"),
        "cpu_host_pct": round(100 * statistics.fmean(cpu), 2) if cpu else None,
        "cpu_agents_pct": round(100 * statistics.fmean(agents_cpu), 2) if agents_cpu else None,
        "rss_max_mb": round(max(rss) / 2**20, 1) if rss else None,
        "sampler_cost_pct": round(100 * cost / span, 4) if span > 0 else None,
        "sampler_ms_per_sample": round(1000 * cost / max(1, len(samples) - len(by_inc)), 3) if span > 0 else None,
        "errors": m.get("errors") or [],
    }


def summarize(bundles: Sequence[Bundle], cluster: str = "") -> dict[str, Any]:
    t0, t1 = time_range(bundles)
    hosts = {b.host: _host_summary(b) for b in bundles}
    evs = events_of(bundles)
    names = agent_names(bundles)
    kinds = Counter(e.event for e in evs if e.agent)
    views = view_changes(bundles)
    joined = sum(len(v.get("added") or []) for v in views)
    rem = removals(bundles, views)
    removed = sum(1 for _, _, left in rem if not left)
    # latencies: per-host phases pooled, cross-host phases from the merged events, OAC from the histograms
    lat: dict[str, Any] = {}
    pooled: dict[str, list[float]] = defaultdict(list)
    oac: dict[str, list[int] | None] = {"oac_propose_decide": None, "oac_decide_deliver": None}
    for b in bundles:
        lb = b.latency
        for k in ("spawn", "freeze", "thaw", "recover", "allocation"):
            pooled[k] += [float(x) for x in (lb.get(k) or {}).get("values_ms") or []]
        for k in oac:
            h = (lb.get(k) or {}).get("hist")
            if isinstance(h, list) and sum(h):
                oac[k] = phases.add_hist(oac[k], h)
    for k, v in pooled.items():
        lat[k] = phases.summary(v)
    for k, v in phases.cluster_phases(evs).items():
        lat[k] = phases.summary(v)
    for k, h in oac.items():
        lat[k] = phases.summary([], h)
    # messages per agent pair, CPU per agent type, the DDB at the end
    pairs: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0])
    type_cpu: dict[str, float] = defaultdict(float)
    n_samples = 0
    last_ddb: tuple[float, dict[str, Any]] | None = None
    for b in bundles:
        for s in b.samples:
            n_samples += 1
            for k, (n, nb) in (s.get("pairs") or {}).items():
                src, _, dst = k.partition(">")
                p = pairs[(src, dst)]
                p[0] += int(n)
                p[1] += int(nb)
            for a in (s.get("agents") or {}).values():
                type_cpu[str(a.get("type", "?"))] += float(a.get("cpu") or 0)
            d = s.get("ddb")
            if isinstance(d, dict) and (last_ddb is None or float(s["ts"]) > last_ddb[0]):
                last_ddb = (float(s["ts"]), {**d, "table": s.get("table") or {}})
    period = sampler_period(bundles)
    dur = max(t1 - t0, period)
    top = sorted(pairs.items(), key=lambda kv: -kv[1][1])[:50]

    def nm(aid: str) -> str:
        return names.get(aid, {}).get("name") or aid[:8]

    ddb: dict[str, Any] = {}
    if last_ddb is not None:
        d = last_ddb[1]
        by_kind: Counter[str] = Counter()
        for p, nb in (d.get("by_prefix") or {}).items():
            by_kind[ddb_kind(p)] += int(nb)
        by_kind["agents"] += int((d.get("table") or {}).get("backup_bytes") or 0)
        ddb = {"objects": d.get("objects"), "bytes": d.get("bytes"), "by_prefix": d.get("by_prefix"),
               "by_kind": dict(by_kind), "agent_backups_bytes": (d.get("table") or {}).get("backup_bytes")}
    timeline: list[dict[str, Any]] = [{"ts": round(e.time, 3), "t": round(e.time - t0, 3), "host": e.host or e.reporter,
                 "agent": e.agent, "name": e.name, "type": e.type, "event": e.event, "detail": e.detail,
                 **({"reporter": e.reporter} if e.reporter else {})} for e in evs]
    timeline += [{"ts": v.get("ts"), "t": round(float(v.get("ts") or t0) - t0, 3), "host": v.get("host"),
                  "event": "view", "view": v.get("view"), "added": v.get("added"), "removed": v.get("removed")}
                 for v in views if v.get("added") or v.get("removed")]
    timeline.sort(key=lambda r: float(r.get("ts") or 0))
    costs = [h["sampler_cost_pct"] for h in hosts.values() if h["sampler_cost_pct"] is not None]
    return {
        "format": FORMAT, "cluster": cluster, "t0": t0, "t1": t1, "duration_s": round(t1 - t0, 3),
        "sampler_period_s": period, "samples": n_samples,
        "sampler_cost_pct_per_host": round(statistics.fmean(costs), 4) if costs else None,
        "hosts": hosts,
        "counts": {
            "agents": len(names), "spawns": kinds["spawning"], "transfers": kinds["thawed"],
            "crashes": kinds["crashed"], "recoveries": kinds["recovered"], "failed": kinds["failed"],
            "removed": kinds["removed"], "view_changes": len(views), "host_joins": joined,
            "host_removals": removed, "host_leaves": len(rem) - removed,
        },
        "latency": lat,
        "pairs": [{"src": nm(s), "dst": nm(d), "src_id": s, "dst_id": d, "msgs": n, "bytes": nb}
                  for (s, d), (n, nb) in top],
        "cpu_by_type_pct": {t: round(100 * v * period / dur, 2) for t, v in sorted(type_cpu.items())},
        "ddb": ddb,
        "agents": names,
        "timeline": timeline[:MAX_TIMELINE],
    }


# ---------------------------------------------------------------------------------------------- series


@dataclass
class Series:
    """Every host's samples on one clock (`t0`), binned by `period` (module docstring)."""

    t0: float
    period: float
    t: list[float] = field(default_factory=list)  # bin times (s since t0)
    host_cpu: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # % of a core, host + agents
    host_agents: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    hosts_up: list[int] = field(default_factory=list)  # hosts sampling in each bin
    members: list[int] = field(default_factory=list)  # the largest view any host had in each bin
    agents: list[int] = field(default_factory=list)  # agent processes running on all hosts
    type_cpu: dict[str, list[float]] = field(default_factory=dict)  # % of a core, summed over hosts
    ddb_kind: dict[str, list[float]] = field(default_factory=dict)  # bytes

    def to_json(self) -> dict[str, Any]:
        return self.__dict__


def series(bundles: Sequence[Bundle], t0: float | None = None) -> Series:
    start = time_range(bundles)[0] if t0 is None else t0
    period = sampler_period(bundles)
    s = Series(start, period)
    host_samples: dict[str, list[tuple[float, dict[str, Any]]]] = {}
    for b in bundles:
        cpu, cnt, rows = [], [], []
        for r in b.samples:
            ts = _num(r.get("ts"))
            if ts is None:
                continue
            t = ts - start
            agents = [a for a in (r.get("agents") or {}).values() if isinstance(a, dict)]
            if _num(r.get("cpu")) is not None:
                cpu.append((t, 100 * (float(r["cpu"]) + sum(float(a.get("cpu") or 0) for a in agents))))
            cnt.append((t, len(agents)))
            rows.append((t, r))
        rows.sort(key=lambda x: x[0])
        s.host_cpu[b.host] = cpu
        s.host_agents[b.host] = cnt
        host_samples[b.host] = rows
    ends = [rows[-1][0] for rows in host_samples.values() if rows]
    if not ends:
        return s
    n = int(max(ends) // period) + 1
    types = sorted({str(a.get("type", "?")) for rows in host_samples.values() for _, r in rows
                    for a in (r.get("agents") or {}).values() if isinstance(a, dict)})
    s.type_cpu = {t: [] for t in types}
    s.ddb_kind = {k: [] for k in KIND_ORDER}
    idx = dict.fromkeys(host_samples, 0)
    last_ddb: dict[str, float] = {}
    for i in range(n):
        end = (i + 1) * period
        current = []  # each host's latest sample in this bin, if it is recent (a host that stopped drops out)
        for h, rows in host_samples.items():
            j = idx[h]
            while j < len(rows) and rows[j][0] < end:
                j += 1
            idx[h] = j
            if j and rows[j - 1][0] > end - STALE_PERIODS * period:
                current.append(rows[j - 1][1])
        s.t.append(end - period / 2)
        s.hosts_up.append(len(current))
        s.members.append(max((int(r.get("members") or 0) for r in current), default=0))
        s.agents.append(sum(len(r.get("agents") or {}) for r in current))
        tc: dict[str, float] = {}
        for r in current:
            for a in (r.get("agents") or {}).values():
                if isinstance(a, dict):
                    k = str(a.get("type", "?"))
                    tc[k] = tc.get(k, 0) + 100 * float(a.get("cpu") or 0)
        for t in types:
            s.type_cpu[t].append(tc.get(t, 0))
        with_ddb = [r for r in current if isinstance(r.get("ddb"), dict)]
        if with_ddb:  # every replica holds the same: the most advanced one
            r = max(with_ddb, key=lambda r: int(r["ddb"].get("seq") or 0))
            kc: Counter[str] = Counter()
            for p, nb in (r["ddb"].get("by_prefix") or {}).items():
                kc[ddb_kind(p)] += int(nb)
            kc["agents"] += int((r.get("table") or {}).get("backup_bytes") or 0)
            last_ddb = {k: float(kc[k]) for k in KIND_ORDER}
        for k in KIND_ORDER:
            s.ddb_kind[k].append(last_ddb.get(k, 0.0))
    return s
