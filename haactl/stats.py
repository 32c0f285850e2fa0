"""`haactl stats collect -o DIR` and `haactl report DIR [B]` (docs/stats.md).

Argument parsing and printing only; the work is in haa.lab.stats (collect, summary, report).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from haa.cluster.backend import ClusterError
from haa.lab.stats.bundle import BundleError
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    cli_errors,
    cluster_options,
    err,
    out,
)
from haactl.tables import table

stats_app = typer.Typer(help="Per-host statistics bundles (docs/stats.md).", no_args_is_help=True)


def _ms(d: dict[str, Any] | None) -> str:
    if not d or not d.get("n"):
        return "-"
    return f"{d['n']} × mean {d.get('mean_ms', 0):.1f} ms, p95 {d.get('p95_ms', 0):.1f} ms"


def summary_tables(s: dict[str, Any]) -> list[Table]:
    numbers = ["inc.", "samples", "events", "host CPU %", "agents CPU %", "RSS MB", "sampler CPU %"]
    hosts = table(["host", "state", *numbers, "errors"], right=numbers,
                  title=f"hosts ({s.get('duration_s', 0):.0f} s, sampled every {s.get('sampler_period_s')} s)")
    for name, h in s.get("hosts", {}).items():
        hosts.add_row(name, str(h.get("state")), str(h.get("incarnations")), str(h.get("samples")),
                      str(h.get("events")), str(h.get("cpu_host_pct", "-")), str(h.get("cpu_agents_pct", "-")),
                      str(h.get("rss_max_mb", "-")), str(h.get("sampler_cost_pct", "-")),
                      escape("; ".join(h.get("errors") or [])))
    counts = table(["what", "count"], title="the cluster", right=["count"])
    for k, v in s.get("counts", {}).items():
        counts.add_row(k.replace("_", " "), str(v))
    lat = table(["phase", "latency"], title="latencies (ms)")
    for k, v in s.get("latency", {}).items():
        lat.add_row(k.replace("_", " "), _ms(v))
    return [hosts, counts, lat]


@stats_app.command("collect")
@cli_errors
@cluster_options(without=("swarm",))
def collect(
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="write DIR/<host>.tar.gz and DIR/summary.json")],
    local: Annotated[bool, typer.Option("--local", help="the local cluster (the default)")] = False,
    where: ClusterOpts = LOCAL,
    hosts: Annotated[list[str] | None, typer.Option("--host", "-H", help="only this host (repeatable)")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="only the paths written")] = False,
) -> None:
    """One bundle per host (log, stats time series, config, view history, agent events, latencies) and a
    cluster summary; works while the cluster runs, for hosts that crashed, and after `cluster down`."""
    from haa.lab.stats.collect import collect_bundles

    if local and where.compose:
        raise ClusterError("--local and --compose exclude each other")
    backend = where.backend(last=True)
    say = None if quiet else (lambda s: err.print(f"[dim]{escape(s)}[/dim]"))
    res = collect_bundles(backend, out_dir, names=hosts or None, progress=say)
    if not quiet:
        for t in summary_tables(res.summary):
            out.print(t)
    for p in res.bundles:
        out.print(escape(str(p)))
    out.print(escape(str(out_dir / "summary.json")))
    for h, e in res.errors.items():
        err.print(f"[yellow]warning:[/yellow] {escape(h)}: {escape(e)}")


@cli_errors
def report(
    run: Annotated[Path, typer.Argument(metavar="DIR", help="a folder of bundles (stats collect, mission run "
                                        "-o, chaos run)")],
    other: Annotated[Path | None, typer.Argument(metavar="[B]", help="a second run: compare DIR and B side "
                                                 "by side", show_default=False)] = None,
    out_dir: Annotated[Path | None, typer.Option("--out", "-o", help="where report.html and its figures go "
                                                 "(default DIR, or DIR/compare-<B> with B)",
                                                 show_default=False)] = None,
) -> None:
    """Render DIR/report.html with PNG figures from a run's bundles (and its mission results, if any);
    with a second run B, both side by side."""
    from haa.lab.stats.report import build_compare, build_report

    try:
        path = build_report(run, out_dir) if other is None else build_compare(run, other, out_dir)
    except BundleError as e:
        err.print(f"[bold red]error:[/bold red] {escape(str(e))}")
        raise typer.Exit(1) from None
    out.print(escape(str(path)))
