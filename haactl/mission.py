"""`haactl mission run|start|status|logs|stop` and `haactl experiment af1|af2|af3|r1`.

Thin: arguments are parsed here, the work is haa.mission (runner, metrics, transcript, experiment), and the
results are printed with rich. docs/missions.md, "Running a mission".

* `mission run FILE [--speed X] [--json OUT] [-o DIR]`: its own local cluster and haa-sim, a progress bar,
  the results table (Table 7.1-1's shape), where the PNGs and the transcript are; exit 0 iff the mission
  completed. A bad mission file: one error line, exit 2, nothing started.
* `mission start FILE` against the running local cluster (`--root`), starting haa-sim unless one runs (and
  refusing one with another arena or seed); `status`, `logs [-f]`, `stop`. With `--compose` the same on the
  compose cluster, its `sim` service as haa-sim (haa.mission.compose).
* `experiment af1|af2|af3 [--runs N] [--speed X] [--resume]`: N runs on seeds seed..seed+N-1, the table
  beside the thesis' values, bench-results/<name>.json (written after every run; `--resume` goes on from it).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from haa.mission.schema import MissionError, load_mission
from haactl.cliopts import LOCAL, ClusterOpts, cluster_options, err, out
from haactl.tables import table

mission_app = typer.Typer(help="Run robot-team missions: run one end to end, or start/status/logs/stop one on a "
                          "running cluster.", no_args_is_help=True)

FileArg = Annotated[Path, typer.Argument(metavar="FILE", help="mission file (YAML, docs/missions.md)")]
SpeedOpt = Annotated[float | None, typer.Option("--speed", min=0.01, max=1000.0,
                                                help="simulated seconds per wall second (default: the file's)")]


def _load(path: Path) -> Any:
    try:
        return load_mission(path)
    except MissionError as e:
        err.print(f"[bold red]error:[/bold red] {escape(str(e))}")
        raise typer.Exit(2) from None


def _fail(message: str, code: int = 1) -> None:
    err.print(f"[bold red]error:[/bold red] {escape(message)}")
    raise typer.Exit(code)


def _compose_backend() -> Any:
    """The compose cluster (HAA_COMPOSE_FILE, HAA_COMPOSE_PROJECT) for `--compose` (haa.mission.compose)."""
    from haa.cluster.backend import ClusterError
    from haa.cluster.compose_backend import ComposeBackend

    try:
        return ComposeBackend()
    except ClusterError as e:
        _fail(str(e))


def _state_dir(compose: bool, root: Path | None) -> Path:
    """Where the mission's state lives: <root>/mission, or the compose cluster's (haa.mission.compose)."""
    from haa.cluster.local_backend import default_root
    from haa.mission.attached import mission_dir

    if compose:
        from haa.mission.compose import state_dir

        if root is not None:
            _fail("--root is for local clusters; not with --compose")
        return state_dir(_compose_backend())
    return mission_dir(root or default_root())


def results_table(results: dict[str, Any], title: str) -> Table:
    from haa.mission.metrics import results_rows

    t = table(["Title", "Value"], title=title, right=["Value"])
    for name, value in results_rows(results):
        t.add_row(escape(name), value)
    return t


def print_results(results: dict[str, Any]) -> None:
    ok = results.get("completed")
    style = "bold green" if ok else "bold red"
    out.print(results_table(results, f"mission {results.get('mission')} (seed {results.get('seed')}, "
                                     f"speed {results.get('speed')})"))
    out.print(f"[{style}]{'completed' if ok else 'not completed'}[/]: {escape(str(results.get('reason')))} "
              f"after {float(results.get('duration_s') or 0):.1f} s simulated "
              f"({float(results.get('wall_s') or 0):.1f} s wall)")
    for e in results.get("errors") or []:
        out.print(f"[yellow]note:[/] {escape(str(e))}")
    files = results.get("files") or {}
    for key, label in (("map_png", "map (estimated | ideal)"), ("timeline_png", "allocation timeline"),
                       ("transcript", "transcript"), ("results", "results JSON")):
        if files.get(key):
            out.print(f"{label}: {files[key]}")


@mission_app.command("run")
def mission_run(
    file: FileArg,
    speed: SpeedOpt = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the results JSON here")] = None,
    out_dir: Annotated[Path | None, typer.Option("--out", "-o", help="folder for the PNGs, transcript, results "
                                                 "and the cluster's logs (default mission-runs/NAME-TIME)")] = None,
    transcript: Annotated[bool, typer.Option("--transcript", help="print the transcript at the end")] = False,
    record: Annotated[Path | None, typer.Option("--record", help="record every agent's inputs and outputs into "
                                                "this folder (AgentPlayback: haactl record ls, haactl replay; "
                                                "docs/playback.md)")] = None,
) -> None:
    """Run a mission end to end on its own local cluster and haa-sim; exit 0 iff it completed."""
    from haa.mission.plan import MissionRunError
    from haa.mission.runner import ProgressInfo, run_mission

    mission = _load(file)
    spec = mission.spec
    out_dir = out_dir or Path("mission-runs") / f"{spec.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    progress = Progress(
        TextColumn("{task.description}"), BarColumn(bar_width=30), TextColumn("{task.fields[clock]}"),
        TextColumn("[dim]{task.fields[note]}"), TimeElapsedColumn(), console=err, transient=False,
    )
    limit = spec.complete.time_limit_s
    task = progress.add_task(f"mission {spec.name}", total=limit, clock="", note="starting")

    def show(p: ProgressInfo) -> None:
        explored = f"explored {100 * p.explored:.1f}/{100 * p.target:.0f} %" if p.explored is not None else ""
        progress.update(task, completed=min(p.t, limit), clock=f"{p.t:.0f}/{limit:.0f} s",
                        note=f"{p.state} {explored} {p.hosts} hosts {p.agents} agents")

    try:
        with progress:
            results = run_mission(mission, speed, out_dir, json_out, show, log=lambda s: progress.console.print(
                f"[dim]{escape(s)}[/]"), record=record)
    except MissionRunError as e:
        _fail(str(e))
    except KeyboardInterrupt:
        err.print("interrupted: everything the mission started is down")
        raise typer.Exit(130) from None
    if transcript:
        out.print((Path(results["files"]["transcript"])).read_text(), end="")
    print_results(results)
    raise typer.Exit(0 if results.get("completed") else 1)


@mission_app.command("start")
@cluster_options(without=("swarm", "compose_file"))
def mission_start(
    file: FileArg,
    speed: SpeedOpt = None,
    local: Annotated[bool, typer.Option("--local", help="the local cluster (the default)")] = False,
    where: ClusterOpts = LOCAL,
    sim: Annotated[str | None, typer.Option("--sim", help="a running haa-sim HOST:PORT to use")] = None,
    sim_token_file: Annotated[Path | None, typer.Option("--sim-token-file", help="its token file")] = None,
) -> None:
    """Start a mission on the running cluster (haa-sim is started unless one runs); it goes on in the
    background: `haactl mission status|logs|stop`."""
    from haa.cluster.local_backend import default_root
    from haa.mission.attached import start_attached
    from haa.mission.plan import MissionRunError

    if local and where.compose:
        _fail("--local and --compose exclude each other")
    mission = _load(file)
    try:
        if where.compose:
            from haa.cluster.backend import ClusterError
            from haa.mission import compose as mission_compose

            if where.root is not None or sim is not None:
                _fail("--root and --sim are for local clusters (the compose cluster's haa-sim is its `sim` service)")
            try:
                st = mission_compose.start(_compose_backend(), mission, speed)
            except ClusterError as e:
                _fail(str(e))
        else:
            st = start_attached(where.root or default_root(), mission, speed, sim, str(sim_token_file or ""))
    except MissionRunError as e:
        _fail(str(e))
    out.print(f"mission {mission.spec.name} started (conductor pid {st.get('pid')}, haa-sim {st.get('sim', '?')}): "
              "haactl mission status | logs -f | stop")


@mission_app.command("status")
@cluster_options(without=("swarm", "compose_file"))
def mission_status(
    where: ClusterOpts = LOCAL,
    json_out: Annotated[bool, typer.Option("--json", help="JSON output")] = False,
) -> None:
    """Explored share, coverage, accuracy, each avatar's supervisor and target, agents per host."""
    from haa.mission.attached import STATE_FILE, conductor_alive, read_json

    st = read_json(_state_dir(where.compose, where.root) / STATE_FILE)
    if not st:
        _fail("no mission on this cluster (haactl mission start FILE)")
    assert st is not None
    if json_out:
        print(json.dumps(st))
        return
    alive = conductor_alive(st)
    state = st.get("state", "?") + ("" if alive or st.get("state") in ("finished", "failed") else " (conductor gone)")
    out.print(f"mission [bold]{st.get('mission')}[/]: {escape(state)}")
    if st.get("error"):
        out.print(f"[red]{escape(str(st['error']))}[/]")
    if "t" in st:
        def pct(v: Any) -> str:
            return f"{100 * v:.1f} %" if isinstance(v, int | float) else "—"

        out.print(f"t = {st['t']:.0f} s of {st.get('limit', 0):.0f} s simulated; explored {pct(st.get('explored'))} "
                  f"(target {pct(st.get('target_explored'))}); coverage {pct(st.get('coverage'))}, accuracy "
                  f"{pct(st.get('accuracy'))}")
        t = table(["avatar", "type", "in arena", "agent", "supervisor", "task", "target"], title="avatars")
        for a in st.get("avatars", []):
            t.add_row(*(escape(str(a.get(k, ""))) for k in ("avatar", "type", "in_arena", "agent", "supervisor",
                                                             "task", "target")))
        out.print(t)
        for h in st.get("hosts", []):
            agents = st.get("agents_per_host", {}).get(h, [])
            out.print(f"{h}: {len(agents)} agents {' '.join(agents)}")
    if st.get("results"):
        print_results(st["results"])


@mission_app.command("logs")
@cluster_options(without=("swarm", "compose_file"))
def mission_logs(
    follow: Annotated[bool, typer.Option("--follow", "-f", help="keep printing new lines until it finishes")] = False,
    where: ClusterOpts = LOCAL,
) -> None:
    """The mission transcript (Fig. 7.1-3 style): mission, agent, host and avatar events in simulated mm:ss."""
    from haa.mission.attached import STATE_FILE, conductor_alive, live_transcript, read_json

    md = _state_dir(where.compose, where.root)
    if read_json(md / STATE_FILE) is None:
        _fail("no mission on this cluster (haactl mission start FILE)")
    shown: set[tuple[str, str]] = set()
    try:
        while True:
            for ln in live_transcript(None, md):
                key = (str(ln.get("clock")), str(ln.get("text")))
                if key not in shown:
                    shown.add(key)
                    out.print(f"[dim]{ln.get('clock')}[/] {escape(str(ln.get('text')))}")
            if not follow or not conductor_alive(read_json(md / STATE_FILE)):
                if follow:  # the conductor wrote the final transcript as it ended
                    for ln in live_transcript(None, md):
                        key = (str(ln.get("clock")), str(ln.get("text")))
                        if key not in shown:
                            shown.add(key)
                            out.print(f"[dim]{ln.get('clock')}[/] {escape(str(ln.get('text')))}")
                return
            time.sleep(1.0)
    except KeyboardInterrupt:
        return


@mission_app.command("stop")
@cluster_options(without=("swarm", "compose_file"))
def mission_stop(
    where: ClusterOpts = LOCAL,
) -> None:
    """Stop the mission: its agents are removed, the haa-sim `start` started is stopped (a finished mission has
    stopped it already); prints its results."""
    from haa.cluster.local_backend import default_root
    from haa.mission.attached import stop_attached

    if where.compose:
        from haa.cluster.backend import ClusterError
        from haa.mission import compose as mission_compose

        if where.root is not None:
            _fail("--root is for local clusters; not with --compose")
        try:
            res = mission_compose.stop(_compose_backend())
        except ClusterError as e:
            _fail(str(e))
            return
    else:
        res = stop_attached(where.root or default_root())
    if not res["was_running"] and not res["sim"] and not res["removed"]:
        out.print("no mission running" + (" (the last one's results follow)" if res["results"] else ""))
    if res["removed"]:
        out.print(f"removed {len(res['removed'])} agents: {' '.join(res['removed'])}")
    if res["sim"]:
        out.print(f"haa-sim {res['sim']}")
    if res["results"]:
        print_results(res["results"])


def experiment(
    name: Annotated[str, typer.Argument(metavar="NAME", help="af1 | af2 | af3 | r1")],
    runs: Annotated[int, typer.Option("--runs", "-n", min=1, max=100, help="runs (seeds seed..seed+N-1)")] = 10,
    speed: SpeedOpt = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="default bench-results/NAME.json")] = None,
    out_dir: Annotated[Path | None, typer.Option("--out", "-o", help="per-run folders (default mission-runs/NAME)")]
    = None,
    mission_file: Annotated[Path | None, typer.Option("--mission", help="default missions/NAME.yaml")] = None,
    exploration: Annotated[str | None, typer.Option(
        "--exploration", help="em | frontier: SupervisorExplore's strategy (default: the file's); compare them on "
        "the same seeds")] = None,
    levels: Annotated[str | None, typer.Option(
        "--levels", help="r1 only: failure levels to run, comma-separated (none,moderate,high,extreme: all)")] = None,
    resume: Annotated[bool, typer.Option(
        "--resume", help="af1/af2/af3: go on from the runs its JSON already holds (same mission file, speed, first "
        "seed, exploration); a run cut off mid-mission is made again")] = False,
) -> None:
    """Experiments AF-1 / AF-2 / AF-3 (thesis §7.1.1-7.1.3): N missions, representative run, mean, RMS, STD
    beside the thesis' Table 7.1-1 / 7.1-2 / 7.1-3. R-1 (§7.3.1): N missions per failure level, Table 7.3-1
    and eq. 7.3-1's k."""
    from haa.lab.experiments.af import EXPERIMENTS, mission_for, run_experiment, table_rows
    from haa.mission.plan import MissionRunError

    if name == "r1":
        _experiment_r1(runs, speed, json_out, out_dir, mission_file, levels)
        return
    if name not in EXPERIMENTS:
        _fail(f"unknown experiment {name!r} (known: {', '.join(EXPERIMENTS)}, r1)", 2)
    try:
        mission = mission_for(name, mission_file)
    except MissionError as e:
        _fail(str(e), 2)

    def on_run(k: int, r: dict[str, Any]) -> None:
        reason = escape(str(r.get("reason")))
        state = "[green]completed[/]" if r.get("completed") else f"[red]not completed[/] ({reason})"
        out.print(f"run {k + 1}/{runs} (seed {r.get('seed')}): {state}, {float(r.get('duration_s') or 0):.1f} s "
                  f"simulated, {float(r.get('wall_s') or 0):.1f} s wall")

    try:
        doc = run_experiment(name, runs, speed, out_dir, json_out, mission, on_run=on_run,
                             log=lambda s: err.print(f"[dim]{escape(s)}[/]"), exploration=exploration, resume=resume)
    except (MissionRunError, ValueError) as e:
        _fail(str(e))
    except KeyboardInterrupt:
        err.print("interrupted")
        raise typer.Exit(130) from None
    cols = ["Title", "Rep. run", "Mean", "RMS", "STD", "thesis rep.", "thesis mean", "thesis RMS", "thesis STD"]
    t = table(cols, title=f"{name.upper()}: {doc['runs']} runs, {doc['completed']} completed "
                          f"(representative: seed {doc['representative_seed']})", right=cols[1:])
    for row in table_rows(doc):
        t.add_row(escape(row[0]), *row[1:])
    out.print(t)
    out.print(f"results: {doc['json']}")
    raise typer.Exit(0 if doc["completed"] == doc["runs"] else 1)


def _experiment_r1(runs: int, speed: float | None, json_out: Path | None, out_dir: Path | None,
                   mission_file: Path | None, levels: str | None) -> None:
    from haa.lab.experiments import r1
    from haa.mission.plan import MissionRunError

    try:
        mission = load_mission(mission_file) if mission_file else None
    except MissionError as e:
        _fail(str(e), 2)

    def on_run(level: str, k: int, r: dict[str, Any]) -> None:
        reason = escape(str(r.get("reason")))
        state = "[green]completed[/]" if r.get("completed") else f"[red]not completed[/] ({reason})"
        out.print(f"{level} run {k + 1}/{runs} (seed {r.get('seed')}): {state}, "
                  f"{float(r.get('duration_s') or 0):.1f} s simulated, {r.get('agent_failures')} agent failures, "
                  f"{float(r.get('wall_s') or 0):.1f} s wall")

    try:
        doc = r1.run_r1(runs, speed, out_dir, json_out, mission,
                        levels=[x.strip() for x in levels.split(",") if x.strip()] if levels else None,
                        on_run=on_run, log=lambda s: err.print(f"[dim]{escape(s)}[/]"))
    except (MissionRunError, ValueError) as e:
        _fail(str(e))
    except KeyboardInterrupt:
        err.print("interrupted")
        raise typer.Exit(130) from None
    names = [n.capitalize() for n, _ in r1.LEVELS]
    for which in ("mean", "std"):
        numbers = [*names, *(f"thesis {n}" for n in names)]
        t = table(["Title", *numbers], title=f"R-1 ({which.upper()}): {doc['runs_done']} runs, beside the thesis' "
                  "Table 7.3-1", right=numbers)
        for row in r1.table(doc, which):
            t.add_row(escape(row[0]), *row[1:])
        out.print(t)
    inc = doc["increase"]
    th = doc["thesis"]["increase"]
    parts = [f"{n} {inc[n] * 100:+.0f} % (thesis {th[n] * 100:+.0f} %)" for n in ("moderate", "high", "extreme")
             if inc.get(n) is not None]
    if parts:
        out.print("duration against no failure: " + ", ".join(parts))
    if doc["k_min"] is not None:
        out.print(f"eq. 7.3-1 fitted k = {doc['k_min']:.3f} min (thesis {r1.THESIS_K_MIN} min)")
    out.print(f"results: {doc['json']}")
    completed = sum(1 for rs in doc["results"].values() for r in rs if r.get("completed"))
    raise typer.Exit(0 if completed == doc["runs_done"] else 1)
