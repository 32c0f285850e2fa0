"""Experiment AP-3 (thesis §7.2.3): time to allocation consensus and messages sent, 2..10 hosts x 5..60
agents, and the allocation-quality study (`haactl bench ap3`, `haactl bench alloc-quality`).

AP-3 runs one allocation session of the real `haa.core.allocation.allocation.Allocator`s in the deterministic simulator
(`haa.lab.dsim.allocsim.AllocSim`) with:

* bid updates delayed by a model of our loopback gRPC transport: a log-normal fitted to the one-way latency
  `bench transport` measured (bench-results/transport.json, variant "transport": p50 0.39 ms, p99 0.99 ms);
* OAC(start) and OAC(finish) decided after the propose-to-decide latency `bench ap1` measured for that
  many participants on real haa-hostd processes (bench-results/ap1.json, paced p50, x log-normal jitter);
* the real CPU time of every Allocator call added to its host's virtual clock: a host is busy while it builds
  a bundle or resolves conflicts, messages wait, and inboxes batch up as on a real host (one core per host, as
  in a cluster of containers). `clock="thread"` (the default) measures it with time.thread_time, the CPU time
  of the call itself; `clock="perf"` with time.perf_counter, which also counts the time other processes of a
  loaded machine (this one is shared) took the core away.

Each session is a rebalance: most agents already run somewhere (transfer penalties apply), some are new,
costs fill 40-80% of the group's capacity, a few agents need hardware only some hosts have, and agents have
sparse affinities. Reported: time from the leader's OAC(start) proposal to its consensus and to the committed
OAC(finish) at the leader, bid-update messages (one per destination), the OAC messages of start and finish
(n^2 + 4n - 6 each, the count `bench ap1` measured), bundle builds, CPU seconds.

The quality study compares the committed allocation's total reward (eq. 4.7-1 summed over hosts, each host's
agents in their best order) with the exhaustive optimum on random instances of up to 8 agents and 4 hosts
(`haa.lab.dsim.allocquality.run_quality`).
"""

from __future__ import annotations

import json
import math
import random
import statistics
import time
from pathlib import Path
from typing import Any

from haa.core.allocation.specs import AgentSpec, HostSpec
from haa.lab.dsim.allocquality import REGIMES, run_quality
from haa.lab.dsim.allocschedule import AllocScenario
from haa.lab.dsim.allocsim import AllocSim
from haa.lab.dsim.network import DelayModel

HOSTS = (2, 3, 4, 5, 6, 7, 8, 9, 10)
AGENTS = (5, 10, 20, 30, 45, 60)
RESULTS = Path("bench-results")

#: fallbacks when bench-results/ has no measurements: loopback one-way latency (s) and OAC decide (ms, p50)
LOOPBACK_P50, LOOPBACK_P99 = 0.000387, 0.000987
OAC_P50_MS = {2: 1.93, 3: 2.85, 4: 3.82, 5: 4.46, 6: 5.68, 7: 6.19, 8: 7.41, 9: 7.54, 10: 8.98}


def loopback_model(results: Path = RESULTS) -> DelayModel:
    """Log-normal one-way delay: base 0.2 ms + a log-normal with the measured p50 and p99."""
    p50, p99 = LOOPBACK_P50, LOOPBACK_P99
    try:
        data = json.loads((results / "transport.json").read_text())
        row = next(r for r in data["results"] if r["variant"] == "transport")
        p50, p99 = row["one_way_p50_ms"] / 1e3, row["one_way_p99_ms"] / 1e3
    except (OSError, ValueError, KeyError, StopIteration):
        pass
    base = min(0.0002, p50 / 2)
    median = p50 - base
    sigma = max(0.05, math.log((p99 - base) / median) / 2.326)
    return DelayModel("lognormal", base, median, sigma)


def oac_table(results: Path = RESULTS) -> dict[int, float]:
    """Propose-to-decide p50 (ms) per participant count, paced, from bench ap1."""
    table = dict(OAC_P50_MS)
    try:
        data = json.loads((results / "ap1.json").read_text())
        for r in data["rows"]:
            if r.get("mode") == "paced":
                table[int(r["participants"])] = float(r["propose_to_decide_ms"]["p50"])
    except (OSError, ValueError, KeyError):
        pass
    return table


def oac_messages(n: int) -> int:
    """Messages of one OAC with n participants (bench ap1 measured n^2 + 4n - 6)."""
    return n * n + 4 * n - 6 if n > 1 else 0


def ap3_scenario(seed: int, hosts: int, agents: int) -> AllocScenario:
    rng = random.Random(f"ap3-{seed}-{hosts}-{agents}")
    names = [f"h{i + 1}" for i in range(hosts)]
    ids = [f"a{i + 1}" for i in range(agents)]
    costs = [rng.uniform(0.02, 0.3) for _ in ids]
    load = rng.uniform(0.4, 0.8)
    per_host = sum(costs) / load / hosts
    specs = {
        n: HostSpec(
            n,
            round(max(max(costs) * 1.1, per_host * rng.uniform(0.7, 1.3)), 3),
            frozenset(["camera"]) if rng.random() < 0.3 else frozenset(),
        )
        for n in names
    }
    if not any(h.hardware for h in specs.values()):
        specs["h1"] = HostSpec("h1", specs["h1"].capacity, frozenset(["camera"]))
    out = []
    for i, a in enumerate(ids):
        partners = rng.sample(ids, k=min(len(ids), rng.choice([0, 0, 1, 2])))
        aff = {p: round(rng.uniform(0.01, 0.1), 3) for p in partners if p != a}
        out.append(
            AgentSpec(
                a,
                round(costs[i], 3),
                frozenset(["camera"]) if rng.random() < 0.05 else frozenset(),
                aff,
                round(rng.uniform(0.0, 0.5), 3),
                rng.choice(names) if rng.random() < 0.8 else None,
            )
        )
    return AllocScenario(
        seed=seed,
        names=names,
        hosts=specs,
        agents=tuple(out),
        delay=loopback_model(),
        deliver=DelayModel("lognormal", 0.0001, 0.0002, 0.5),
        proc=0.0,
        final_pause=True,
    )


CLOCKS = {"thread": time.thread_time, "perf": time.perf_counter}


def run_session(seed: int, hosts: int, agents: int, oac_ms: dict[int, float], clock: str = "thread") -> dict[str, Any]:
    """One AP-3 session; times in seconds of virtual time (network model + measured CPU)."""
    sc = ap3_scenario(seed, hosts, agents)

    def oac_delay(rng: random.Random, n: int) -> float:
        p50 = oac_ms.get(n) or oac_ms[min(oac_ms, key=lambda k: abs(k - n))] * n / max(1, min(oac_ms))
        return p50 / 1e3 * rng.lognormvariate(0.0, 0.25) if n > 1 else 0.0002

    sim = AllocSim(sc, cpu=True, oac_delay=oac_delay, clock=CLOCKS[clock])
    wall = time.perf_counter()
    sim.run(until=60.0)
    wall = time.perf_counter() - wall
    leader = sim.nodes[sc.names[0]]
    t0 = sim.ses_started.get(1, math.nan)
    done = next((t for _i, ses, t, _a in leader.accepted if ses == 1), math.nan)
    return {
        "hosts": hosts,
        "agents": agents,
        "seed": seed,
        "consensus_s": sim.ses_consensus.get(1, math.nan) - t0,
        "allocated_s": done - t0,
        "bid_messages": sim.msgs_by_ses.get(1, 0),
        "oac_messages": 2 * oac_messages(hosts),
        "builds": sum(n.alloc.stats["builds"] for n in sim.nodes.values()),
        "cpu_s": sim.cpu_time,
        "wall_s": wall,
        "unallocatable": len(sc.agents) - len(leader.accepted[0][3]) if leader.accepted else None,
    }


def _agg(xs: list[float]) -> dict[str, float]:
    xs = [x for x in xs if not math.isnan(x)]
    if not xs:
        return {"mean": math.nan, "sd": math.nan, "n": 0}
    return {"mean": statistics.mean(xs), "sd": statistics.stdev(xs) if len(xs) > 1 else 0.0, "n": len(xs)}


def run_ap3(
    hosts: tuple[int, ...] = HOSTS,
    agents: tuple[int, ...] = AGENTS,
    reps: int = 5,
    seed: int = 1,
    clock: str = "thread",
) -> list[dict[str, Any]]:
    if clock not in CLOCKS:
        raise ValueError(f"clock: must be one of {sorted(CLOCKS)}, got {clock!r}")
    oac_ms = oac_table()
    rows = []
    for h in hosts:
        for a in agents:
            runs = [run_session(seed + r, h, a, oac_ms, clock) for r in range(reps)]
            rows.append(
                {
                    "hosts": h,
                    "agents": a,
                    "reps": reps,
                    "consensus_ms": _agg([r["consensus_s"] * 1e3 for r in runs]),
                    "allocated_ms": _agg([r["allocated_s"] * 1e3 for r in runs]),
                    "bid_messages": _agg([float(r["bid_messages"]) for r in runs]),
                    "oac_messages": runs[0]["oac_messages"],
                    "builds": _agg([float(r["builds"]) for r in runs]),
                    "cpu_ms": _agg([r["cpu_s"] * 1e3 for r in runs]),
                    "failed": sum(1 for r in runs if math.isnan(r["allocated_s"])),
                }
            )
    return rows


# --------------------------------------------------------------------------------------------- quality


def run_quality_study(instances: int = 500, seed: int = 0) -> dict[str, Any]:
    """Both instance families of `haa.lab.dsim.allocquality.quality_instance`; the ratio is reported for the
    instances whose optimum is positive (a negative optimum means every allocation overloads a host)."""
    out: dict[str, Any] = {"instances": instances, "first_seed": seed, "regimes": {}}
    for regime in REGIMES:
        res = [run_quality(s, regime) for s in range(seed, seed + instances)]
        ok = [r for r in res if r.optimum > 0 and not math.isinf(r.reward)]
        ratios = [r.ratio for r in ok]
        out["regimes"][regime] = {
            "instances": len(res),
            "rated": len(ok),
            "no_allocation": sum(1 for r in res if math.isinf(r.reward)),
            "mean_ratio": statistics.mean(ratios),
            "median_ratio": statistics.median(ratios),
            "min_ratio": min(ratios),
            "p10_ratio": sorted(ratios)[len(ratios) // 10],
            "optimal_share": sum(1 for x in ratios if x >= 1 - 1e-9) / len(ratios),
            "aggregate_ratio": sum(r.reward for r in ok) / sum(r.optimum for r in ok),
            "mean_messages": statistics.mean(r.messages for r in res),
            "mean_time_ms": statistics.mean(r.seconds * 1e3 for r in res if not math.isinf(r.seconds)),
            "worst": [(r.seed, round(r.ratio, 3)) for r in sorted(ok, key=lambda r: r.ratio)[:5]],
        }
    return out
