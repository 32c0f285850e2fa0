"""Run many seeded schedules on every core and report property violations.

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

from haa.dsim import schedule as sched
from haa.dsim.checks import CheckResult, Violation, check_oac, check_ufd

ALGORITHMS = ("ufd", "oac")


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


def trace_excerpt(algorithm: str, seed: int, hosts: int, result: SeedResult, lines: int = 40) -> list[str]:
    """Re-run a seed with tracing and pick the lines about the violating transactions or hosts."""
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
        if r.violations:
            violations += len(r.violations)
            bad_seeds.append(r.seed)
            for text in r.violations:
                report(f"VIOLATION seed={r.seed} {text}")
            if shown < excerpts and r.trace_hash:
                shown += 1
                for line in trace_excerpt(algorithm, r.seed, hosts, r):
                    report(line)
            report(f"  reproduce: haactl verify {algorithm} --seed {r.seed} --schedules 1 --hosts {hosts} --trace")
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
    )


def resume_seed(checkpoint: Path, algorithm: str, hosts: int) -> int | None:
    data = _load_checkpoint(checkpoint)
    if data.get("algorithm") == algorithm and data.get("hosts") == hosts:
        return int(data["next_seed"])
    return None
