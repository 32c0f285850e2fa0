"""Experiment AP-3 (thesis §7.2.3) on real processes: `haactl bench ap3 --real`.

The simulated `bench ap3` (haa.lab.experiments.ap3) runs the real Allocator objects in the deterministic simulator
with a delay model; this module measures the same two quantities — time to allocation consensus and messages sent
— on real `haa-hostd` processes on loopback (h1-h3 core, `--rebalance-period 0`), for n = 2..10 hosts and
5..60 agents:

* the agents are idle `ballast` agents without state (haa.lab.experiments.benchagents; this machine has 2 cores, so
  60 CPU-burning agents would measure the machine, not the algorithm) with declared costs drawn from a
  seeded RNG: cost U(0.5, 1.5) x 0.6 n / 60 of a host's capacity 1.0 (60 agents fill ~60% of the group),
  transfer penalty U(0, 0.5). Idle agents measure ~0 CPU, below the threshold (0.02) at which a host
  commits measured costs, so the allocation works on the declared costs throughout;
* per group size, agents are added level by level (5, 10, 20, 30, 45, 60: each spawn changes the agent list
  and starts a session; the benchmark waits until every agent is active and no session has started for
  1.2 s), then at each level `reps` sessions are forced with `Alloc(run)` on the leader, each after the
  group has been quiet (no session started for 1.2 s, every agent active);
* times come from the hosts' JSON-lines logs (one machine, one clock): the leader's `alloc.propose_start`
  (OAC(start) proposed) -> the leader's `alloc.consensus` (l. 86-88: every bid agrees; OAC(finish) is
  proposed) = **consensus**; -> the last host's `allocation_accepted` (OAC(finish) committed and applied
  everywhere) = **allocated**;
* messages: bid updates = the sum over hosts of the Status counter `tx_msgs.agent_host` across the session
  (bid updates, plus the freeze/claim acknowledgements of the transfers the new allocation starts: 2 (n-1)
  per transfer, subtracted; the idle agents send nothing); OAC messages = the sum of `tx_msgs.oac_*`
  across the same window, which also holds the transfers' OACs (freeze, release, claim) and anything else
  committed meanwhile, next to the count for the session's two OACs alone, 2 (n^2 + 4n - 6), the formula
  `bench ap1` measured. The agent layer's own counter of bid messages (`AgentNode.counters["sent_alloc"]`)
  is not exposed in Status, hence the subtraction;
* CPU: the user + system time of all haa-hostd processes from the `Alloc(run)` request until every host has
  applied the finish (polled through AgentList every 20 ms: the benchmark reads the logs only once the
  session is over, so that parsing them does not compete with the hosts for the CPU). All hosts share this
  machine's cores, so with n hosts on 2 cores the session's time is bounded below by that CPU time / 2.

Results go into bench-results/ap3.json under the key "real", next to the simulated results.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import random
import statistics
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import grpc
import psutil

from haa.cluster.hostprocs import wait_for
from haa.lab.experiments.ap4 import BenchCluster
from haa.pb import control_pb2 as cpb

HOSTS = (2, 4, 6, 8, 10)
AGENTS = (5, 10, 20, 30, 45, 60)
#: a session that has not committed everywhere within this long is counted as failed
SESSION_TIMEOUT = 60.0


def _active_is(c: BenchCluster, a: int) -> bool:
    return sum(1 for x in c.agents().values() if x.status == "active") == a


def oac_messages(n: int) -> int:
    """Messages of one failure-free OAC with n participants (bench ap1: n^2 + 4n - 6)."""
    return n * n + 4 * n - 6 if n > 1 else 0


def _counters(c: BenchCluster) -> tuple[int, int]:
    """(agent_host messages, OAC messages) sent so far, summed over the hosts."""
    ah = oac = 0
    for h in c.hosts.values():
        for k, v in h.status().counters.values.items():
            if k == "tx_msgs.agent_host":
                ah += v
            elif k.startswith("tx_msgs.oac_"):
                oac += v
    return ah, oac


def spawn_idle(c: BenchCluster, rng: random.Random, n_hosts: int, via: str) -> str:
    """One idle agent with a seeded declared cost and transfer penalty (module docstring). A host that is not a
    member right now (removed after a false suspicion under load, rejoining) refuses: wait for the group and
    ask h1 instead."""
    cost = rng.uniform(0.5, 1.5) * 0.6 * n_hosts / max(AGENTS)
    req = cpb.AgentSpawnRequest(
        type="ballast", config=json.dumps({"state_bytes": 0, "backup": False}).encode(),
        cost=round(cost, 4), transfer_penalty=round(rng.uniform(0.0, 0.5), 3),
    )
    reason = ""
    for _attempt in range(5):
        client = c.hosts[via].client
        try:
            r = client._stub.AgentSpawn(req, metadata=client._md, timeout=15.0)
        except grpc.RpcError as e:
            reason = f"{e.code().name}: {e.details()}"
        else:
            if r.ok:
                return str(r.id)
            reason = r.reason
        c.wait_group(timeout=120.0)
        via = "h1"
    raise RuntimeError(f"spawn failed 5 times: {reason}")


def _log_events(c: BenchCluster, since: float, names: set[str]) -> list[tuple[str, dict[str, Any]]]:
    return [(x, e) for x, h in c.hosts.items() for e in h.events(since, names)]


def _hostd_cpu(c: BenchCluster) -> float:
    """CPU seconds (user + system) used so far by the haa-hostd processes (not their agents)."""
    total = 0.0
    for h in c.hosts.values():
        if h.proc is not None:
            with contextlib.suppress(psutil.Error):
                t = psutil.Process(h.proc.pid).cpu_times()
                total += t.user + t.system
    return total


def session_sample(c: BenchCluster, n: int) -> dict[str, Any]:
    """Force one session on the leader and measure it (module docstring). Progress is polled through
    AgentList (cheap); the logs are read once, after the session."""
    c.wait_quiet()
    st = c.h1.status()
    leader, view0 = st.leader or "h1", st.view
    s0 = c.hosts[leader].client.agent_list().session
    ah0, oac0 = _counters(c)
    cpu0 = _hostd_cpu(c)
    t0 = time.time()
    c.hosts[leader].client.alloc("run")
    deadline = time.monotonic() + SESSION_TIMEOUT
    ses = 0
    done = False
    while time.monotonic() < deadline and not done:
        if not ses:
            cur = c.hosts[leader].client.agent_list().session
            ses = cur if cur > s0 else 0
        if ses:
            done = all(h.client.agent_list().finished_session >= ses for h in c.hosts.values())
        if not done:
            time.sleep(0.02)
    cpu = _hostd_cpu(c) - cpu0
    settled = True
    try:
        c.wait_quiet(timeout=30.0, settle=0.1)
    except AssertionError:
        settled = False
    ah1, oac1 = _counters(c)
    evs = _log_events(c, t0, {"alloc.propose_start", "alloc.consensus", "allocation_accepted", "agent_freezing"})
    t_start = next((float(e["ts"]) for x, e in evs
                    if x == leader and e["event"] == "alloc.propose_start" and e["fields"]["ses"] == ses), math.nan)
    cons = [(float(e["ts"]), e["fields"]) for x, e in evs
            if x == leader and e["event"] == "alloc.consensus" and e["fields"]["ses"] == ses]
    accepted = {x: float(e["ts"]) for x, e in evs
                if e["event"] == "allocation_accepted" and e["fields"].get("session") == ses}
    ok = bool(ses) and len(accepted) == n
    transfers = sum(1 for _x, e in evs if e["event"] == "agent_freezing")
    acks = 2 * (n - 1) * transfers
    return {
        "hosts": n,
        "session": ses,
        "ok": ok,
        "settled": settled,
        "view_changed": c.h1.status().view != view0,
        "request_s": (max(accepted.values()) - t0) if ok else math.nan,
        "consensus_s": (cons[0][0] - t_start) if cons else math.nan,
        "allocated_s": (max(accepted.values()) - t_start) if ok else math.nan,
        "hostd_cpu_s": cpu if done else math.nan,
        "leader_bid_messages": cons[0][1].get("messages") if cons else None,
        "builds_at_leader": cons[0][1].get("builds") if cons else None,
        "bid_messages": ah1 - ah0 - acks,
        "oac_messages_window": oac1 - oac0,
        "oac_messages_session": 2 * oac_messages(n),
        "transfers": transfers,
    }


def _agg(xs: Iterable[float]) -> dict[str, float]:
    v = [x for x in xs if not math.isnan(x)]
    if not v:
        return {"mean": math.nan, "sd": math.nan, "median": math.nan, "max": math.nan, "n": 0}
    return {"mean": statistics.fmean(v), "sd": statistics.stdev(v) if len(v) > 1 else 0.0,
            "median": statistics.median(v), "max": max(v), "n": len(v)}


def run_group(n: int, agents: Iterable[int], reps: int, root: Path, seed: int = 1,
              log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    rng = random.Random(f"ap3real-{seed}-{n}")
    rows = []
    with BenchCluster(root, n) as c:
        took = c.form()
        log(f"n={n}: group formed in {took:.1f} s")
        c.wait_quiet()
        have = 0
        for a in sorted(agents):
            try:
                while have < a:
                    spawn_idle(c, rng, n, c.names[have % n])
                    have += 1
                wait_for(functools.partial(_active_is, c, a), 120,
                         f"{a} active agents")
                c.wait_quiet(timeout=120.0)
            except (grpc.RpcError, AssertionError, RuntimeError) as e:
                log(f"n={n} agents={a}: could not set the level up, stopping this group size: {e}")
                rows.append({"hosts": n, "agents": a, "reps": reps, "error": str(e)[:500]})
                break
            runs = []
            for _ in range(reps):
                try:
                    runs.append(session_sample(c, n))
                except (grpc.RpcError, AssertionError) as e:
                    log(f"n={n} agents={a}: a session sample failed: {e}")
                    runs.append({"ok": False})
            row: dict[str, Any] = {
                "hosts": n, "agents": a, "reps": reps, "load_avg_1min": os.getloadavg()[0],
                "view_changes": sum(1 for r in runs if r.get("view_changed")),
                "consensus_ms": _agg(r.get("consensus_s", math.nan) * 1e3 for r in runs),
                "allocated_ms": _agg(r.get("allocated_s", math.nan) * 1e3 for r in runs),
                "request_ms": _agg(r.get("request_s", math.nan) * 1e3 for r in runs),
                "bid_messages": _agg(float(r["bid_messages"]) for r in runs if "bid_messages" in r),
                "oac_messages_window": _agg(float(r["oac_messages_window"]) for r in runs
                                            if "oac_messages_window" in r),
                "oac_messages_session": 2 * oac_messages(n),
                "transfers": _agg(float(r["transfers"]) for r in runs if "transfers" in r),
                "hostd_cpu_ms": _agg(r.get("hostd_cpu_s", math.nan) * 1e3 for r in runs),
                "failed": sum(1 for r in runs if not r.get("ok")),
                "samples": runs,
            }
            rows.append(row)
            log(f"n={n} agents={a}: consensus {row['consensus_ms']['median']:.1f} ms, allocated "
                f"{row['allocated_ms']['median']:.1f} ms, bid messages {row['bid_messages']['median']:.0f}, "
                f"transfers {row['transfers']['mean']:.1f}")
    return rows


def run_ap3_real(hosts: Iterable[int] = HOSTS, agents: Iterable[int] = AGENTS, reps: int = 5, seed: int = 1,
                 root: Path | None = None, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="haa-ap3-") as tmp:
        base = root or Path(tmp)
        for n in hosts:
            rows += run_group(n, agents, reps, base / f"n{n}", seed, log)
    return rows


def existing(path: Path) -> dict[str, Any]:
    """The JSON object in `path`, or {} if there is none (or it does not parse)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def merge_json(path: Path, real: dict[str, Any]) -> dict[str, Any]:
    """bench-results/ap3.json with `real` under the key "real"; the simulated results are kept as they are."""
    return {**existing(path), "real": real}
