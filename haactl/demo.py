"""`haactl demo` (`make demo`): counter agents live on a local cluster while hosts join, retire and crash.

The scenario and its checks are haa.lab.experiments.demo (its docstring says what happens and what is checked);
this command prints its timeline as it happens in the style of the thesis' transcript (Fig. 7.1-3, lines
formatted by haactl.agentcli.event_line), then the counters of every agent as a table and the verdict

    messages lost: N, order violations: N, duplicate agents: N

and exits 0 only if all three are 0 (1 otherwise, 130 on Ctrl-C).
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from haa.cluster.backend import ClusterError
from haa.cluster.events import TimelineEvent
from haa.lab.experiments.demo import COUNTS, HEADERS, Demo, DemoResult
from haactl.agentcli import event_line
from haactl.tables import table

console = Console(highlight=False, width=None if sys.stdout.isatty() else 120)


def print_result(d: Demo, r: DemoResult) -> None:
    """The counters at the end, what did not arrive, the duplicates found, and the verdict line."""
    t = table(["agent", "host", *HEADERS], title="counter agents at the end", right=HEADERS)
    for name in sorted(r.counters):
        s = r.counters[name]
        t.add_row(name, r.hosts.get(name, "?"), *(str(s.get(k, 0)) for k in COUNTS))
    total = r.total()
    t.add_row("[bold]total[/]", "", *(f"[bold]{total[k]}[/]" for k in COUNTS))
    console.print(t)
    if len(r.counters) != r.expected:
        console.print(f"[red]{len(r.counters)} counters published their counters, expected {r.expected}[/]")
    for line in r.behind:
        console.print(f"[red]not arrived by the end: {line}[/]")
    evs = r.checks.events
    moves = sum(1 for e in evs if e.event == "thawed")
    recov = sum(1 for e in evs if e.event == "recovered")
    console.print(f"{moves} transfers (freeze/thaw), {recov} recoveries, {r.checks.samples} samples of every "
                  f"host's agent list, {len(evs)} timeline lines")
    for when, name, a, b in r.overlaps:
        console.print(f"[red]{d.clock(when)} {name} active on {a} and {b} at once (timeline)[/]")
    console.print(f"lost to recovery (by design): {total['lost_after_recovery']} "
                  f"(resent after recovery: {total['resent_after_recovery']}, stale: {total['stale']})")
    style = "bold green" if r.ok else "bold red"
    console.print(f"[{style}]messages lost: {r.lost}, order violations: {r.order_violations}, "
                  f"duplicate agents: {r.duplicates}[/]")


def demo(
    quick: bool = typer.Option(False, "--quick", help="a shorter scenario (about 30 s instead of 50 s)"),
    pairs: int = typer.Option(3, "--pairs", min=1, max=10, help="counter pairs"),
    seed: int = typer.Option(1, "--seed", help="seed of the demo's choices (which agent is killed)"),
    data_dir: Path | None = typer.Option(None, "--data-dir", help="keep the hosts' logs here (default: a temp dir)"),
) -> None:
    """Counter agents live on a local cluster while hosts join, retire and crash; prints the allocation
    timeline and checks that no message was lost or reordered and no agent ran twice."""
    with contextlib.ExitStack() as stack:
        root = data_dir or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="haa-demo-")))

        def show(e: TimelineEvent) -> None:  # called once the demo runs: `d` is bound, its clock started
            console.print(event_line(e, d.t0))

        d = Demo(root.absolute(), quick, seed, pairs, show=show,
                 alert=lambda text: console.print(f"[bold red]{escape(text)}[/]"))
        code = 1
        try:
            console.print(f"[bold]HAA demo[/]: counter agents on a local cluster of haa-hostd processes "
                          f"(data in {d.root})")
            result = d.run()
            print_result(d, result)
            code = 0 if result.ok else 1
        except ClusterError as e:
            console.print(f"[bold red]demo failed:[/] {e}")
        except KeyboardInterrupt:
            console.print("interrupted")
            code = 130
        finally:
            with contextlib.suppress(Exception):
                d.backend.down(grace=1.0)
        raise typer.Exit(code)
