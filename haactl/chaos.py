"""`haactl chaos run PLAN` and `haactl chaos check DIR`: chaos experiments (docs/chaos.md).

Argument parsing and printing only; the work is in haa.lab.chaos (plan, inject, collect, checks, timeline, run).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from haa.lab.chaos.checks import Check, run_checks
from haa.lab.chaos.inject import Injected
from haa.lab.chaos.plan import PlanError, load_plan, parse_plan
from haa.lab.chaos.run import ChaosCluster, LocalChaosCluster, run_on
from haa.lab.chaos.timeline import Entry, build, clock
from haactl.cliopts import cli_errors, err, out
from haactl.tables import table

chaos_app = typer.Typer(help="Chaos experiments: faults on a schedule, then Jepsen-style checks (docs/chaos.md).",
                        no_args_is_help=True)


def _plan_error(e: PlanError) -> None:
    err.print(f"[bold red]error:[/bold red] {escape(str(e))}")
    raise typer.Exit(2)


def fault_line(f: Injected) -> str:
    mark = "" if f.ok else " [yellow](not done)[/yellow]"
    return f"{clock(f.t)}  [bold]{f.action}[/bold] {escape(f.target)}: {escape(f.detail)}{mark}"


def timeline_table(entries: list[Entry]) -> Table:
    t = table(["t", "host", "event"], title="timeline (faults and their effects, from every host's log)", right=["t"])
    for e in entries:
        text = f"[bold]{escape(e.text)}[/bold]" if e.kind == "fault" else escape(e.text)
        t.add_row(clock(e.t), e.host or "chaos", text)
    return t


def checks_table(checks: dict[str, Check]) -> Table:
    t = table(["check", "result", "detail"], title="checks (from the hosts' persisted logs and their replicas)")
    for name, c in checks.items():
        t.add_row(name, "[green]passed[/green]" if c.passed else "[bold red]FAILED[/bold red]", escape(c.detail))
    return t


def _run_dir(path: Path) -> Path:
    """An empty directory, or a previous run's (replaced); anything else is refused."""
    if path.exists():
        if not path.is_dir():
            raise PlanError(f"--out {path}: not a directory")
        if any(path.iterdir()) and not (path / "plan.json").exists():
            raise PlanError(f"--out {path}: not empty and not a chaos run directory; choose another")
        shutil.rmtree(path)
    return path


@chaos_app.command("run")
@cli_errors
def chaos_run(
    plan_file: Annotated[Path, typer.Argument(metavar="PLAN", help="the chaos plan (YAML)")],
    local: Annotated[bool, typer.Option("--local", help="on a local cluster of its own (the default)")] = True,
    compose: Annotated[bool, typer.Option("--compose", help="on the docker compose cluster (brought up for the run "
                                          "and removed after it)")] = False,
    compose_file: Annotated[Path | None, typer.Option("--compose-file", help="compose file (default "
                                                      "$HAA_COMPOSE_FILE, else compose/compose.yaml)")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result (faults, checks, timeline) "
                                                  "as JSON to this file ('-': stdout)")] = None,
    out_dir: Annotated[Path | None, typer.Option("--out", "-o", help="run directory (default .haa/lab/chaos/<plan "
                                                 "name>); given, the hosts' stats bundles are collected into it "
                                                 "at the end (haactl report DIR)", show_default=False)] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="only the checks table")] = False,
) -> None:
    """Run a chaos plan: start a cluster, a workload and the faults, then check the hosts' histories.
    Exit code 0 only when every check passed (2: the plan is invalid; nothing was started)."""
    try:
        plan = load_plan(plan_file)
        if compose_file is not None and not compose:
            raise PlanError("--compose-file needs --compose")
        run = _run_dir(out_dir or Path(".haa") / "chaos" / plan.name)
    except PlanError as e:
        _plan_error(e)
        return
    to_stdout = json_out is not None and str(json_out) == "-"
    show = not quiet and not to_stdout
    say = (lambda s: err.print(f"[dim]{escape(s)}[/dim]")) if show else (lambda _s: None)
    on_fault = (lambda f: out.print(fault_line(f))) if show else None
    cluster: ChaosCluster
    try:
        if compose:
            from haa.lab.chaos.compose import ComposeChaosCluster

            cluster = ComposeChaosCluster(compose_file, bundles_to=run.absolute() if out_dir is not None else None)
        else:
            cluster = LocalChaosCluster(run.absolute() / "cluster")
        res = run_on(cluster, plan, run, progress=say, on_fault=on_fault)
    except PlanError as e:
        _plan_error(e)
        return
    if to_stdout:
        print(json.dumps(res.to_json(), indent=1))
    else:
        if show:
            out.print(timeline_table(res.timeline))
        if res.checks:
            out.print(checks_table(res.checks))
        if json_out is not None:
            json_out.write_text(json.dumps(res.to_json(), indent=1) + "\n")
    if out_dir is not None and not compose:
        _bundles(res.out, show)
    elif out_dir is not None and show:
        err.print(escape(getattr(cluster, "bundle_note", "") or "stats bundles not collected"))
    if res.error:
        err.print(f"[bold red]error:[/bold red] {escape(res.error)}")
    verdict = "[green]every check passed[/green]" if res.passed else "[bold red]FAILED[/bold red]"
    err.print(f"chaos run {escape(plan.name)}: {verdict} (run directory {escape(str(res.out))})")
    raise typer.Exit(0 if res.passed else 1)


def _bundles(run: Path, show: bool) -> None:
    """The hosts' stats bundles into the run directory (its cluster is down; the data dirs remain)."""
    from haa.cluster.local_backend import LocalBackend
    from haa.lab.stats.collect import collect_quietly

    res = collect_quietly(LocalBackend(run / "cluster", last=True), run)
    if isinstance(res, str):
        err.print(f"[yellow]warning:[/yellow] stats bundles not collected: {escape(res)}")
    elif show:
        err.print(f"stats bundles of {len(res.bundles)} hosts in {escape(str(run))} (haactl report {escape(str(run))})")


@chaos_app.command("check")
@cli_errors
def chaos_check(
    run_dir: Annotated[Path, typer.Argument(metavar="DIR", help="a chaos run directory")],
    json_out: Annotated[bool, typer.Option("--json", help="print the checks as JSON")] = False,
    timeline: Annotated[bool, typer.Option("--timeline", help="print the timeline too")] = False,
) -> None:
    """Check a finished run again from its directory (host logs and replicas); exit code 0 only when every
    check passed."""
    try:
        plan = parse_plan(json.loads((run_dir / "plan.json").read_text()), f"{run_dir}/plan.json")
    except (OSError, ValueError) as e:
        _plan_error(PlanError(f"{run_dir}: not a chaos run directory ({e})"))
        return
    except PlanError as e:
        _plan_error(e)
        return
    checks = run_checks(run_dir, plan.workload)
    ok = all(c.passed for c in checks.values())
    if json_out:
        print(json.dumps({"passed": ok, "checks": {k: c.to_json() for k, c in checks.items()}}, indent=1))
    else:
        if timeline:
            out.print(timeline_table(build(run_dir)))
        out.print(checks_table(checks))
    raise typer.Exit(0 if ok else 1)
