"""Jepsen-style checks of a chaos run, from what the hosts persisted and hold (docs/chaos.md, "Checks").

Input is a run directory (haa.lab.chaos.collect): each host's JSON-lines log (copied from its data dir, also for
hosts that were killed) and each live host's own replica of the workload's keys. Nothing the chaos tool
believed while it ran is used. Each check returns `Check(passed, detail)`:

* `acked_writes_once` (ddb-writes): every write a writer logged as acknowledged (`chaos_ack` in its host's
  log) is in the writer's DDB log exactly once on every live replica, and no item is there twice;
* `replicas_agree`: every live host is a member of one view with the same member list and the same DDB hash;
* `single_instance` (fencing): no output of an older instance of an agent is accepted once a newer one's is —
  ddb-writes: in each writer's log (commit order) the epochs never go down; counters: no receiver counted a
  `stale` message (an older life of a sender after its newer one);
* `counter_streams` (counters): no message lost outside a recovery, none out of order, none twice; for a
  pair whose counters never crashed, none lost or resent at all (per-sender order across transfers);
* `crashed_agents_recovered`: every agent that a host reported crashed was afterwards recovered, thawed or
  started again somewhere, or is reported `failed` with its reason, or was removed.
"""

from __future__ import annotations

import contextlib
import json
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from haa.lab.chaos.collect import host_logs, replicas
from haa.lab.chaos.workload import ACK_EVENT, LOG_PREFIX

#: timeline events (haa.hostd.agentdriver.on_timeline logs them as agent_<event>) after which a crashed agent
#: counts as back
BACK_EVENTS = frozenset({"agent_recovered", "agent_active", "agent_thawed"})
#: most problems listed in one detail
SHOW = 5


@dataclass
class Check:
    passed: bool
    detail: str

    def to_json(self) -> dict[str, Any]:
        return {"passed": self.passed, "detail": self.detail}


def _listing(problems: list[str]) -> str:
    more = f" (+{len(problems) - SHOW} more)" if len(problems) > SHOW else ""
    return "; ".join(problems[:SHOW]) + more


def live_replicas(reps: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {h: r for h, r in reps.items() if r.get("status", {}).get("member")}


def writer_items(rep: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """writer name -> its log's items (decoded) in commit order, from one replica record."""
    out: dict[str, list[dict[str, Any]]] = {}
    for key, obj in rep.get("objects", {}).items():
        if key.startswith(LOG_PREFIX) and obj.get("type") == "log":
            items = []
            for raw in obj["value"]["items"]:
                try:
                    items.append(json.loads(raw))
                except ValueError:
                    items.append({"bad": raw})
            out[key[len(LOG_PREFIX):]] = items
    return out


def acks(logs: dict[str, list[dict[str, Any]]]) -> set[tuple[str, int, int]]:
    """(writer, epoch, n) of every acknowledged write, from every host's log."""
    out = set()
    for recs in logs.values():
        for r in recs:
            if r.get("event") == ACK_EVENT:
                f = r.get("fields", {})
                try:
                    out.add((str(f["w"]), int(f["e"]), int(f["n"])))
                except (KeyError, TypeError, ValueError):
                    continue
    return out


def check_acked_writes(logs: dict[str, list[dict[str, Any]]], reps: dict[str, dict[str, Any]]) -> Check:
    acked = acks(logs)
    live = live_replicas(reps)
    if not live:
        return Check(False, "no live replica to check")
    if not acked:
        return Check(False, "no acknowledged write in any host's log: the workload did not write")
    problems = []
    for host, rep in sorted(live.items()):
        counts: Counter[tuple[str, int, int]] = Counter()
        for w, items in writer_items(rep).items():
            for it in items:
                try:
                    counts[(w, int(it["e"]), int(it["n"]))] += 1
                except (KeyError, TypeError, ValueError):
                    problems.append(f"{host}: malformed item in chaos/log/{w}: {it}")
        missing = sorted(a for a in acked if counts[a] == 0)
        twice = sorted((k, c) for k, c in counts.items() if c > 1)
        for w, e, n in missing:
            problems.append(f"{host}: acknowledged write {w} epoch {e} #{n} missing")
        for (w, e, n), c in twice:
            problems.append(f"{host}: {w} epoch {e} #{n} present {c} times")
    writers = len({a[0] for a in acked})
    if problems:
        return Check(False, f"{len(problems)} problems: {_listing(problems)}")
    return Check(True, f"{len(acked)} acknowledged writes of {writers} writers, each exactly once on "
                       f"{len(live)} live replicas ({', '.join(sorted(live))})")


def check_replicas_agree(reps: dict[str, dict[str, Any]]) -> Check:
    if not reps:
        return Check(False, "no replica was read (no live host)")
    problems = [f"{h} is not a member" for h, r in sorted(reps.items()) if not r["status"].get("member")]
    views = defaultdict(list)
    for h, r in sorted(reps.items()):
        s = r["status"]
        views[(s.get("view"), tuple(sorted(s.get("members", []))), s.get("ddb_hash"))].append(h)
    if len(views) > 1:
        problems.append("; ".join(
            f"{', '.join(hs)}: view {k[0]}, members {','.join(k[1])}, DDB {str(k[2])[:12]}"
            for k, hs in sorted(views.items(), key=lambda kv: kv[1])
        ))
    if problems:
        return Check(False, _listing(problems))
    (view, members, digest), hs = next(iter(views.items()))
    return Check(True, f"{len(hs)} live replicas in view {view} ({', '.join(members)}), DDB hash {str(digest)[:12]}")


def check_fencing_writes(reps: dict[str, dict[str, Any]]) -> Check:
    live = live_replicas(reps)
    problems = []
    epochs: dict[str, set[int]] = defaultdict(set)
    for host, rep in sorted(live.items()):
        for w, items in sorted(writer_items(rep).items()):
            top = -1
            for i, it in enumerate(items):
                e = it.get("e")
                if not isinstance(e, int):
                    continue
                epochs[w].add(e)
                if e < top:
                    problems.append(f"{host}: {w}'s log item {i} is from epoch {e}, committed after epoch {top}'s")
                top = max(top, e)
    if not live:
        return Check(False, "no live replica to check")
    if not epochs:
        return Check(False, "no writer log in any live replica")
    if problems:
        return Check(False, f"outputs of an older instance accepted after a newer one's: {_listing(problems)}")
    multi = sum(1 for es in epochs.values() if len(es) > 1)
    return Check(True, f"{len(epochs)} writers, {multi} of them with several instances (epochs "
                       f"{', '.join(f'{w}: {min(es)}-{max(es)}' for w, es in sorted(epochs.items()))}): "
                       "in commit order no older epoch after a newer one")


def counter_stats(reps: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """demo/<name> of the first live replica (replicas agree, or replicas_agree fails)."""
    live = live_replicas(reps)
    if not live:
        return {}
    rep = live[sorted(live)[0]]
    return {k[len("demo/"):]: o["value"] for k, o in rep.get("objects", {}).items()
            if k.startswith("demo/") and isinstance(o.get("value"), dict)}


def check_fencing_counters(reps: dict[str, dict[str, Any]]) -> Check:
    stats = counter_stats(reps)
    if not stats:
        return Check(False, "no counter statistics (demo/) in the live replicas")
    stale = {n: s.get("stale", 0) for n, s in stats.items() if s.get("stale", 0)}
    if stale:
        return Check(False, "messages of an older instance accepted after its newer one's: "
                            + _listing([f"{n} counted {c} stale" for n, c in sorted(stale.items())]))
    return Check(True, f"{len(stats)} counters: no message of an older instance after a newer one's")


def check_counter_streams(reps: dict[str, dict[str, Any]],
                          logs: dict[str, list[dict[str, Any]]] | None = None) -> Check:
    """No message lost outside a recovery, none out of order, none twice; and for a pair whose two counters
    never crashed (no `agent_crashed` of either in any host's log) not even that: every message of the peer
    arrived once and in its sender's order across every transfer (AT-Consistency, thesis §4.5)."""
    stats = counter_stats(reps)
    if not stats:
        return Check(False, "no counter statistics (demo/) in the live replicas")
    crashed = {e["agent"] for e in agent_events(logs or {}) if e["event"] == "agent_crashed"}
    problems = []
    intact = 0
    thaws = 0
    for n, s in sorted(stats.items()):
        for k in ("lost", "out_of_order", "duplicate"):
            if s.get(k, 0):
                problems.append(f"{n}: {k} {s[k]}")
        if logs is not None and s.get("id") and s.get("peer") and not {s["id"], s["peer"]} & crashed:
            intact += 1
            thaws += int(s.get("thaws", 0))
            for k in ("lost_after_recovery", "resent_after_recovery"):
                if s.get(k, 0):
                    problems.append(f"{n}: {k} {s[k]} though neither it nor its peer crashed")
    if problems:
        return Check(False, _listing(problems))
    got = sum(int(s.get("received", 0)) for s in stats.values())
    rec = sum(int(s.get("lost_after_recovery", 0)) for s in stats.values())
    kept = (f"; {intact} counters whose pair never crashed: every message once and in order, across {thaws} "
            "transfers" if logs is not None else "")
    return Check(True, f"{len(stats)} counters received {got} messages: none lost outside a recovery, out of "
                       f"order or twice ({rec} lost to recoveries from older backups, Alg. 8){kept}")


def agent_events(logs: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Every allocation-timeline record of every host (agent_<event> with a `detail` field), time ordered."""
    out = []
    for host, recs in logs.items():
        for r in recs:
            ev = str(r.get("event", ""))
            f = r.get("fields", {})
            if ev.startswith("agent_") and isinstance(f, dict) and "detail" in f and "pid" not in f and "agent" in f:
                out.append({"ts": float(r.get("ts", 0)), "host": host, "event": ev, "agent": f["agent"],
                            "name": f.get("name", ""), "detail": f.get("detail", "")})
    return sorted(out, key=lambda e: e["ts"])


def check_crashed_recovered(logs: dict[str, list[dict[str, Any]]], t_end: float | None = None) -> Check:
    """`t_end`: when the run ended (the replicas were read); what hosts log after it — agents crashing while
    `cluster down` stops their hosts — is not part of the run."""
    evs = agent_events(logs)
    if t_end:
        evs = [e for e in evs if e["ts"] <= t_end]
    crashes: dict[str, list[float]] = defaultdict(list)
    names: dict[str, str] = {}
    for e in evs:
        names[e["agent"]] = e["name"] or names.get(e["agent"], "")
        if e["event"] == "agent_crashed":
            crashes[e["agent"]].append(e["ts"])
    problems, delays, failed = [], [], []
    for agent, ts_list in crashes.items():
        name = names.get(agent) or agent[:8]
        later = [e for e in evs if e["agent"] == agent and e["ts"] >= max(ts_list)]
        back = [e for e in later if e["event"] in BACK_EVENTS]
        gave_up = [e for e in later if e["event"] == "agent_failed"]
        removed = [e for e in later if e["event"] == "agent_removed"]
        if back:
            delays.append(back[0]["ts"] - max(ts_list))
        elif gave_up:
            why = gave_up[-1]["detail"]
            if why:
                failed.append(f"{name}: {why}")
            else:
                problems.append(f"{name} reported failed without a reason")
        elif not removed:
            problems.append(f"{name} crashed (last at {max(ts_list):.1f}) and was never recovered or reported failed")
    if problems:
        return Check(False, _listing(problems))
    if not crashes:
        return Check(True, "no agent crashed")
    slow = f", slowest {max(delays):.1f} s after its last crash report" if delays else ""
    tail = f"; failed with reason: {_listing(failed)}" if failed else ""
    return Check(True, f"{len(crashes)} crashed agents: {len(delays)} recovered{slow}{tail}")


def run_checks(run: Path, workload: str | None) -> dict[str, Check]:
    """Every check that applies to the run's workload (module docstring), by name."""
    logs = host_logs(run)
    reps = replicas(run)
    out: dict[str, Check] = {}
    if workload == "ddb-writes":
        out["acked_writes_once"] = check_acked_writes(logs, reps)
    out["replicas_agree"] = check_replicas_agree(reps)
    if workload == "ddb-writes":
        out["single_instance"] = check_fencing_writes(reps)
    elif workload == "counters":
        out["single_instance"] = check_fencing_counters(reps)
        out["counter_streams"] = check_counter_streams(reps, logs)
    t_end = None
    with contextlib.suppress(OSError, ValueError, TypeError, AttributeError):
        t_end = float(json.loads((run / "faults.json").read_text()).get("t_end") or 0) or None
    out["crashed_agents_recovered"] = check_crashed_recovered(logs, t_end)
    return out
