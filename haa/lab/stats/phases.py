"""Latencies of the agent layer's phases, from what the hosts logged (no extra bookkeeping in the hosts).

Per host (`host_phases`, its own log: every phase below starts and ends on the same host):
  spawn      agent_spawning -> agent_active of the same agent
  freeze     agent_freezing -> agent_frozen (the transfer's first half, on the source host)
  thaw       agent_thawing -> agent_thawed (its second half, on the destination)
  recover    agent_recovering -> agent_recovered
  allocation allocation_session -> allocation_accepted (the leader logs the session's start: Alg. 4)

Cluster-wide (`cluster_phases`, the merged timeline of every host, haa.cluster.events):
  transfer   freezing (source) -> thawed (destination) of the same agent
  recovery   crashed -> recovered or active again of the same agent (the crash as reported: after detection)

Values are milliseconds. `summary(values)` gives n, mean, percentiles and the histogram over the sampler's
bounds (haa.hostd.sampler.HIST_BOUNDS_MS), so that a host's OAC histograms and these read alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

from haa.cluster.events import TimelineEvent
from haa.hostd.sampler import HIST_BOUNDS_MS, histogram

#: (start event, end event) of each per-host phase, keyed by agent id (allocation: by nothing)
HOST_PHASES = {
    "spawn": ("agent_spawning", "agent_active"),
    "freeze": ("agent_freezing", "agent_frozen"),
    "thaw": ("agent_thawing", "agent_thawed"),
    "recover": ("agent_recovering", "agent_recovered"),
}


def host_phases(records: Iterable[dict[str, Any]]) -> dict[str, list[float]]:
    """Phase name -> durations (ms) of one host's log records (in file order)."""
    out: dict[str, list[float]] = {k: [] for k in (*HOST_PHASES, "allocation")}
    ends = {end: name for name, (_, end) in HOST_PHASES.items()}
    starts = {start: name for name, (start, _) in HOST_PHASES.items()}
    open_: dict[tuple[str, str], float] = {}
    session: float | None = None
    for r in records:
        ev = r.get("event")
        try:
            ts = float(r.get("ts", 0))
        except (TypeError, ValueError):
            continue
        if ev == "allocation_session":
            session = ts
            continue
        if ev == "allocation_accepted":
            if session is not None:
                out["allocation"].append((ts - session) * 1000.0)
                session = None
            continue
        f = r.get("fields")
        if not isinstance(f, dict) or "pid" in f or not isinstance(f.get("agent"), str):
            continue
        if ev in starts:
            open_[(starts[ev], f["agent"])] = ts
        elif ev in ends:
            t0 = open_.pop((ends[ev], f["agent"]), None)
            if t0 is not None:
                out[ends[ev]].append((ts - t0) * 1000.0)
    return out


def cluster_phases(events: Sequence[TimelineEvent]) -> dict[str, list[float]]:
    """transfer and recovery durations (ms) over the merged, time-ordered timeline of every host."""
    out: dict[str, list[float]] = {"transfer": [], "recovery": []}
    freezing: dict[str, float] = {}
    crashed: dict[str, float] = {}
    for e in events:
        if not e.agent:
            continue
        if e.event == "freezing":
            freezing.setdefault(e.agent, e.time)
        elif e.event == "thawed":
            t0 = freezing.pop(e.agent, None)
            if t0 is not None:
                out["transfer"].append((e.time - t0) * 1000.0)
        elif e.event == "crashed":
            crashed.setdefault(e.agent, e.time)
            freezing.pop(e.agent, None)
        elif e.event in ("recovered", "active"):
            t0 = crashed.pop(e.agent, None)
            if t0 is not None:
                out["recovery"].append((e.time - t0) * 1000.0)
        elif e.event in ("removed", "failed"):
            crashed.pop(e.agent, None)
            freezing.pop(e.agent, None)
    return out


def percentile(sorted_values: Sequence[float], q: float) -> float:
    if not sorted_values:
        return math.nan
    k = (len(sorted_values) - 1) * q
    lo, hi = math.floor(k), math.ceil(k)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (k - lo)


def summary(values_ms: Sequence[float], hist: Sequence[int] | None = None) -> dict[str, Any]:
    """n, mean, p50, p95, max (ms, rounded) and the histogram; from raw values, or from a histogram alone
    (then the mean and percentiles are estimated from the buckets' upper bounds)."""
    vs = sorted(values_ms)
    if vs:
        h = histogram(v / 1000.0 for v in vs)
        return {"n": len(vs), "mean_ms": round(sum(vs) / len(vs), 3), "p50_ms": round(percentile(vs, 0.5), 3),
                "p95_ms": round(percentile(vs, 0.95), 3), "max_ms": round(vs[-1], 3), "hist": h}
    h = list(hist or [0] * (len(HIST_BOUNDS_MS) + 1))
    n = sum(h)
    if not n:
        return {"n": 0, "hist": h}
    bounds = [*HIST_BOUNDS_MS, HIST_BOUNDS_MS[-1] * 2]
    mean = sum(c * b for c, b in zip(h, bounds, strict=True)) / n

    def q(p: float) -> float:
        acc = 0
        for c, b in zip(h, bounds, strict=True):
            acc += c
            if acc >= p * n:
                return float(b)
        return float(bounds[-1])

    return {"n": n, "mean_ms": round(mean, 3), "p50_ms": q(0.5), "p95_ms": q(0.95), "hist": h, "from": "buckets"}


def add_hist(a: list[int] | None, b: Sequence[int]) -> list[int]:
    if a is None:
        return list(b)
    return [x + y for x, y in zip(a, b, strict=False)]
