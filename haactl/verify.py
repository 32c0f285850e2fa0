"""`haactl verify ufd|oac|membership|ddb|allocation|transfer|recovery|join`: run seeded fault schedules in the
deterministic simulator and check the thesis' properties (`haa.lab.dsim.checks` for UFD and OAC, `haa.lab.dsim.group`
for host membership and the replicated DDB, `haa.lab.dsim.allocation` for Alg. 4, `haa.lab.dsim.agents` for the whole
agent layer: transfer Alg. 5-6, backup and recovery Alg. 7-8; `haa.lab.dsim.joins` for the allocation after hosts
join).

Output contract: one `VIOLATION seed=S <property>: <detail>` line per violation, a trace excerpt and a
`reproduce:` command for the first few violating seeds, a summary, and as the very last line exactly
`verify <algorithm>: <N> schedules, <V> violations`. Exit status 1 when V > 0.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from haa.lab.dsim import mutations, sweep

console = Console(stderr=True)


def verify(
    algorithm: str = typer.Argument(..., help=", ".join(sweep.ALGORITHMS)),
    schedules: int = typer.Option(2000, "--schedules", "-n", min=1, help="number of seeded schedules"),
    seed: int = typer.Option(0, "--seed", "-s", min=0, help="first seed; schedules use seed .. seed+N-1"),
    hosts: int = typer.Option(7, "--hosts", min=2, max=64, help="hosts per schedule"),
    workers: int = typer.Option(0, "--workers", "-j", min=0, help="worker processes (0 = every core)"),
    trace: bool = typer.Option(False, "--trace", help="print the full event trace of each schedule"),
    checkpoint: Path | None = typer.Option(None, "--checkpoint", help="record progress in this JSON file"),
    resume: bool = typer.Option(False, "--resume", help="continue from --checkpoint's next seed"),
    mutate: str | None = typer.Option(
        None, "--mutate", help=f"break the algorithm on purpose: {', '.join(sorted(mutations.MUTATIONS))}"
    ),
    excerpts: int = typer.Option(5, "--excerpts", min=0, help="trace excerpts to print"),
) -> None:
    """Verify an algorithm over N random fault schedules (crashes, pauses, restarts, delay spikes, false
    suspicions; for membership and ddb also joins and leaves); every violation prints the seed that
    reproduces it."""
    if algorithm not in sweep.ALGORITHMS:
        console.print(f"[red]error:[/red] unknown algorithm {algorithm!r}; choose from {', '.join(sweep.ALGORITHMS)}")
        raise typer.Exit(2)
    if resume:
        if checkpoint is None:
            console.print("[red]error:[/red] --resume needs --checkpoint FILE")
            raise typer.Exit(2)
        nxt = sweep.resume_seed(checkpoint, algorithm, hosts)
        if nxt is not None:
            schedules = max(0, seed + schedules - nxt)
            seed = nxt
            console.print(f"resuming at seed {seed}, {schedules} schedules left")
    if mutate:
        try:
            mutations.apply(mutate)
        except ValueError as exc:
            console.print(f"[red]error:[/red] {exc}")
            raise typer.Exit(2) from None
        console.print(f"[yellow]running with the deliberately broken variant {mutate!r}[/yellow]")
    if trace:
        for s in range(seed, seed + schedules):
            for line in sweep.full_trace(algorithm, s, hosts):
                print(line)
    nworkers = workers or os.cpu_count() or 1
    with Progress(
        TextColumn(f"verify {algorithm}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=not console.is_terminal,
    ) as progress:
        task = progress.add_task("schedules", total=schedules)
        summary = sweep.sweep(
            algorithm,
            schedules,
            seed,
            hosts,
            workers=nworkers,
            report=lambda line: print(line, flush=True),
            progress=lambda done, total: progress.update(task, completed=done),
            checkpoint=checkpoint,
            excerpts=excerpts,
            mutate=mutate,
        )
    print(
        f"seeds {seed}..{seed + schedules - 1}: {summary.per_minute:.0f} schedules/minute on {nworkers} "
        f"worker(s), {summary.events} events, liveness checked in {summary.liveness_checked}/{schedules}"
    )
    if summary.totals:
        print("totals: " + ", ".join(f"{k.replace('_', ' ')} {v:.0f}" for k, v in summary.totals.items()))
    if summary.violating_seeds:
        print(f"violating seeds: {' '.join(str(s) for s in summary.violating_seeds[:50])}")
    print(f"verify {algorithm}: {summary.schedules} schedules, {summary.violations} violations", flush=True)
    if summary.violations:
        raise typer.Exit(1)
