"""Run many seeded schedules on every core and report property violations.

Algorithms: `ufd` and `oac` run `haa.lab.dsim.schedule` scenarios on bare host cores (checked by
`haa.lab.dsim.checks`); `membership` and `ddb` run `haa.lab.dsim.group` scenarios on `MembershipNode`s (Alg. 3 and
the replicated DDB; `ddb` with a heavier write workload) and report `haa.lab.dsim.group.VERIFIER_PROPS`;
`allocation` runs `haa.lab.dsim.allocation` schedules (Alg. 4 on N Allocators, `haa.lab.dsim.alloccheck.PROPS`);
`transfer` and `recovery` run `haa.lab.dsim.agents` schedules (the whole agent layer on `AgentNode`s over a host
group: allocation, Alg. 5-8, routing; `haa.lab.dsim.agents.AGENT_PROPS`); `join` runs `haa.lab.dsim.joins` schedules
(the agent layer on a quiet group that hosts join: no agent transferred twice per join, plus the agent props).

`run_seed` draws one scenario, runs it, checks it, and returns a small picklable result. `sweep` fans
seeds out to a process pool (one worker per core), reports progress and schedules per minute, and for each
violating seed re-runs it with tracing on to print a readable trace excerpt: every failure is reproducible
from its seed alone (`haactl verify <alg> --seed S --schedules 1 --trace`).

A checkpoint file (JSON) records the contiguous prefix of completed seeds so that an interrupted sweep can
be resumed (`--resume`).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from haa.lab.dsim import group
from haa.lab.dsim import schedule as sched
from haa.lab.dsim.checks import CheckResult, Violation, check_oac, check_ufd

GROUP_ALGORITHMS = ("membership", "ddb")
#: the agent layer (haa.lab.dsim.agents): transfers under pauses and false suspicions; recoveries under crashes
AGENT_ALGORITHMS = ("transfer", "recovery")
#: `executive`: a real control-system agent (ExecutiveMission) on virtual time under the recovery mix of faults
#: (haa.lab.dsim.vagent: the agent layer's properties and the executive's EX-*)
ALGORITHMS = ("ufd", "oac", *GROUP_ALGORITHMS, "allocation", *AGENT_ALGORITHMS, "join", "executive")
#: per-seed figures of the group verifiers that the summary adds up
GROUP_TOTALS = ("faults_injected", "faults_dropped", "writes_acked", "views")


@dataclass
class SeedResult:
    seed: int
    violations: list[str]
    liveness_checked: bool
    trace_hash: str
    events: int
    messages: int
    stats: dict[str, float] = field(default_factory=dict)
    txids: list[str] = field(default_factory=list)
    hosts: list[str] = field(default_factory=list)
    description: str = ""


def check(algorithm: str, sc: sched.Scenario, cl: sched.SimCluster, quiescent: bool) -> CheckResult:
    if algorithm == "ufd":
        r = check_ufd(sc, cl)
        o = check_oac(sc, cl, quiescent)  # the UFD schedules carry a light OAC workload too
        return CheckResult(r.violations + o.violations, o.liveness_checked, {**o.stats, **r.stats})
    return check_oac(sc, cl, quiescent)


def run_seed(
    algorithm: str,
    seed: int,
    hosts: int,
    mutate: Callable[[], object] | None = None,
) -> SeedResult:
    """Run one seed. `mutate` (tests only) is called first in the worker, e.g. to break the algorithm."""
    if mutate is not None:
        mutate()
    if algorithm == "allocation":
        from haa.lab.dsim import allocation as alloc_sim

        return SeedResult(**alloc_sim.seed_result(seed, hosts))
    if algorithm in AGENT_ALGORITHMS:
        from haa.lab.dsim import agents as agent_sim

        return SeedResult(**agent_sim.seed_result(seed, hosts, algorithm))
    if algorithm == "join":
        from haa.lab.dsim import joins as join_sim

        return SeedResult(**join_sim.seed_result(seed, hosts))
    if algorithm == "executive":
        from haa.lab.dsim import vagent

        return SeedResult(**vagent.seed_result(seed, hosts))
    if algorithm in GROUP_ALGORITHMS:
        return run_group_seed(algorithm, seed, hosts)
    sc = sched.draw(seed, hosts, algorithm)
    cl, stats = sched.run(sc)
    res = check(algorithm, sc, cl, stats["quiescent"])
    vs: list[Violation] = res.violations
    return SeedResult(
        seed=seed,
        violations=[str(x) for x in vs],
        liveness_checked=res.liveness_checked,
        trace_hash=cl.trace_hash(),
        events=cl.events,
        messages=int(stats["messages"]),
        stats=res.stats,
        txids=[str(t) for x in vs for t in x.txids],
        hosts=[hh for x in vs for hh in x.hosts],
        description=sc.describe(),
    )


def run_group_seed(algorithm: str, seed: int, hosts: int) -> SeedResult:
    sc = group.draw_group(seed, hosts, algorithm)
    sim = group.GroupSim(sc)
    sim.run()
    vs = group.check_group(sim, group.VERIFIER_PROPS[algorithm])
    gh = sim.gh
    cl = sim.cl
    injected = sum(1 for f in sc.faults if f.kind != "restart") + len(sc.leaves) - len(gh.dropped)
    return SeedResult(
        seed=seed,
        violations=[str(x) for x in vs],
        liveness_checked=sim.quiescent,
        trace_hash=cl.trace_hash(),
        events=cl.events,
        messages=sum(cl.msg_counts.values()),
        stats={
            "faults_injected": float(injected),
            "faults_dropped": float(len(gh.dropped)),
            "writes_acked": float(len(gh.acked)),
            "views": float(max((len(v) for v in gh.views.values()), default=0)),
        },
        hosts=[hh for x in vs for hh in x.hosts],
        description=" | ".join(sc.describe()[:3]),
    )


_GROUP_TRACE_NOISE = ("Heartbeat(", "SetPeriod(", "StateSnapshot(", "StateForward(")


def full_trace(algorithm: str, seed: int, hosts: int) -> list[str]:
    """The scenario and the whole event trace of one seed (`haactl verify ... --trace`)."""
    if algorithm == "allocation":
        from haa.lab.dsim import allocation as alloc_sim

        return alloc_sim.full_trace(seed, hosts)
    if algorithm in AGENT_ALGORITHMS:
        from haa.lab.dsim import agents as agent_sim

        return agent_sim.full_trace(seed, hosts, algorithm)
    if algorithm == "join":
        from haa.lab.dsim import joins as join_sim

        return join_sim.full_trace(seed, hosts)
    if algorithm == "executive":
        from haa.lab.dsim import vagent

        return vagent.full_trace(seed, hosts)
    if algorithm in GROUP_ALGORITHMS:
        sc = group.draw_group(seed, hosts, algorithm)
        sim = group.GroupSim(sc, trace=True)
        sim.run()
        out = [f"# {ln}" for ln in sc.describe()]
        out += [ln for ln in sim.cl.trace or [] if not any(k in ln for k in _GROUP_TRACE_NOISE)]
        out.append(f"# trace hash {sim.cl.trace_hash()}")
        return out
    sc2 = sched.draw(seed, hosts, algorithm)
    cl, _stats = sched.run(sc2, trace=True)
    out = [f"# {sc2.describe()}"]
    out += [f"# fault {f.describe()}" for f in sc2.faults]
    out += list(cl.trace or [])
    out.append(f"# trace hash {cl.trace_hash()}")
    return out


def _group_excerpt(algorithm: str, seed: int, hosts: int, result: SeedResult, lines: int) -> list[str]:
    sc = group.draw_group(seed, hosts, algorithm)
    sim = group.GroupSim(sc, trace=True)
    sim.run()
    keys = tuple(f"{hh}#" for hh in set(result.hosts))
    # membership events (views, logs, faults) of the hosts concerned; messages are left to --trace
    picked = [
        ln
        for ln in sim.cl.trace or []
        if " -> " not in ln and " <- " not in ln and (not keys or any(k in ln for k in keys))
    ]
    out = [f"  scenario: {ln}" for ln in sc.describe()[:12]]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    out += [f"  {ln}" for ln in picked]
    return out


def trace_excerpt(algorithm: str, seed: int, hosts: int, result: SeedResult, lines: int = 40) -> list[str]:
    """Re-run a seed with tracing and pick the lines about the violating transactions or hosts."""
    if algorithm == "allocation":
        from haa.lab.dsim import allocation as alloc_sim

        return alloc_sim.trace_excerpt(seed, hosts, result.hosts, lines)
    if algorithm in AGENT_ALGORITHMS:
        from haa.lab.dsim import agents as agent_sim

        return agent_sim.trace_excerpt(seed, hosts, algorithm, result.hosts, lines)
    if algorithm == "join":
        from haa.lab.dsim import joins as join_sim

        return join_sim.trace_excerpt(seed, hosts, result.hosts, lines)
    if algorithm == "executive":
        from haa.lab.dsim import vagent

        return vagent.trace_excerpt(seed, hosts, result.hosts, lines)
    if algorithm in GROUP_ALGORITHMS:
        return _group_excerpt(algorithm, seed, hosts, result, lines)
    sc = sched.draw(seed, hosts, algorithm)
    cl, _stats = sched.run(sc, trace=True)
    trace = cl.trace or []
    keys = set(result.txids)
    keys.update(f"{hh}#" for hh in result.hosts)
    if keys:
        picked = [ln for ln in trace if any(k in ln for k in keys)]
    else:
        picked = trace
    faults = [f.describe() for f in sc.faults]
    out = [f"  scenario: {sc.describe()}"]
    out += [f"  fault: {f}" for f in faults[:12]]
    if len(picked) > lines:
        half = lines // 2
        out += [f"  {ln}" for ln in picked[:half]]
        out.append(f"  ... {len(picked) - lines} more lines ...")
        out += [f"  {ln}" for ln in picked[-half:]]
    else:
        out += [f"  {ln}" for ln in picked]
    return out


def _worker(args: tuple[str, int, int]) -> SeedResult:
    algorithm, seed, hosts = args
    try:
        return run_seed(algorithm, seed, hosts)
    except Exception as exc:  # a crash of the algorithm is a violation too, with its seed
        import traceback

        tb = traceback.format_exc(limit=6).strip().splitlines()[-4:]
        return SeedResult(seed, [f"Exception: {exc!r} | {' | '.join(tb)}"], False, "", 0, 0)


@dataclass
class SweepSummary:
    algorithm: str
    schedules: int
    violations: int
    violating_seeds: list[int]
    liveness_checked: int
    seconds: float
    events: int
    messages: int
    totals: dict[str, float] = field(default_factory=dict)

    @property
    def per_minute(self) -> float:
        return self.schedules / self.seconds * 60.0 if self.seconds > 0 else 0.0


def _load_checkpoint(path: Path) -> dict[str, int]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def sweep(
    algorithm: str,
    schedules: int,
    seed: int,
    hosts: int,
    workers: int | None = None,
    report: Callable[[str], None] = print,
    progress: Callable[[int, int], None] | None = None,
    checkpoint: Path | None = None,
    excerpts: int = 5,
    mutate: str | None = None,
) -> SweepSummary:
    """Run seeds [seed, seed + schedules) and report violations (see the module docstring)."""
    if algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algorithm!r}; choose from {ALGORITHMS}")
    workers = workers or os.cpu_count() or 1
    seeds = list(range(seed, seed + schedules))
    t0 = time.perf_counter()
    done: set[int] = set()
    contiguous = seed
    violations = 0
    bad_seeds: list[int] = []
    live = 0
    events = 0
    messages = 0
    shown = 0
    totals: dict[str, float] = dict.fromkeys(GROUP_TOTALS, 0.0) if algorithm in GROUP_ALGORITHMS else {}
    if algorithm in AGENT_ALGORITHMS:
        totals = dict.fromkeys(("transfers", "recoveries", "processed", "faults_dropped"), 0.0)
    if algorithm == "executive":
        totals = dict.fromkeys(("transfers", "recoveries", "duplicate_children", "faults_dropped"), 0.0)
    if algorithm == "join":
        totals = dict.fromkeys(("joins", "transfers_after_joins", "transfers_to_joiners", "agents_moved_twice"), 0.0)
    again = f" --mutate {mutate}" if mutate else ""

    def results() -> Iterator[SeedResult]:
        args = [(algorithm, s, hosts) for s in seeds]
        if workers == 1 or schedules < 8:
            for a in args:
                yield _worker(a)
            return
        ctx = mp.get_context("fork")
        with ctx.Pool(workers) as pool:
            chunk = max(1, min(50, schedules // (workers * 8) or 1))
            yield from pool.imap_unordered(_worker, args, chunksize=chunk)

    for r in results():
        done.add(r.seed)
        while contiguous in done:
            done.discard(contiguous)
            contiguous += 1
        events += r.events
        messages += r.messages
        live += int(r.liveness_checked)
        for k in totals:
            totals[k] += r.stats.get(k, 0.0)
        if r.violations:
            violations += len(r.violations)
            bad_seeds.append(r.seed)
            for text in r.violations:
                report(f"VIOLATION seed={r.seed} {text}")
            if shown < excerpts and r.trace_hash:
                shown += 1
                for line in trace_excerpt(algorithm, r.seed, hosts, r):
                    report(line)
            report(
                f"  reproduce: haactl verify {algorithm} --seed {r.seed} --schedules 1 --hosts {hosts}{again} --trace"
            )
        if progress is not None:
            progress(len(seeds) - (len(seeds) - (contiguous - seed) - len(done)), len(seeds))
        if checkpoint is not None and (contiguous - seed) % 500 == 0:
            checkpoint.write_text(json.dumps({"algorithm": algorithm, "hosts": hosts, "next_seed": contiguous}))
    if checkpoint is not None:
        checkpoint.write_text(json.dumps({"algorithm": algorithm, "hosts": hosts, "next_seed": contiguous}))
    return SweepSummary(
        algorithm=algorithm,
        schedules=schedules,
        violations=violations,
        violating_seeds=sorted(bad_seeds),
        liveness_checked=live,
        seconds=time.perf_counter() - t0,
        events=events,
        messages=messages,
        totals=totals,
    )


def resume_seed(checkpoint: Path, algorithm: str, hosts: int) -> int | None:
    data = _load_checkpoint(checkpoint)
    if data.get("algorithm") == algorithm and data.get("hosts") == hosts:
        return int(data["next_seed"])
    return None
