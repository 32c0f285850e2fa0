"""`haactl cluster up|status|down` and `haactl host add|leave|kill|pause|resume|restart` (issue 3 §5).

Each command is written once against `haa.cluster.backend.Backend`; `--compose` selects the docker compose
cluster instead of the local one (docs/cluster.md), `--swarm` the Docker Swarm stack (docs/swarm.md).
"""

from __future__ import annotations

import json
import shlex
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from haa.cluster.backend import ALIVE, Backend, ClusterError, Formation, StartError, wait_until
from haa.cluster.status import gather_status
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    cli_errors,
    cluster_options,
    err,
    out,
)
from haactl.tables import table

cluster_app = typer.Typer(help="Bring a cluster of haa-hostd hosts up, inspect it, take it down.", no_args_is_help=True)
host_app = typer.Typer(help="Add, retire, kill, pause, resume or restart one host.", no_args_is_help=True)

TimeoutOpt = Annotated[float, typer.Option("--timeout", min=1, help="seconds to wait")]


def progress_bar() -> Progress:
    return Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        BarColumn(bar_width=30),
        TextColumn("{task.completed}/{task.total}"),
        TextColumn("[dim]{task.fields[note]}"),
        TimeElapsedColumn(),
        console=err,
        transient=False,
    )


def wait_with_progress(
    backend: Backend, check: Any, total: int, description: str, timeout: float, what: str, before: Any = None
) -> tuple[Formation, float]:
    """`wait_until` with a rich progress bar of `Formation.joined` out of `total`."""
    with progress_bar() as progress:
        task = progress.add_task(description, total=total, note="")

        def step() -> Formation:
            if before is not None:
                before()
            return check()

        def show(f: Formation) -> None:
            progress.update(task, completed=min(f.joined, total), note=f.note)

        return wait_until(step, timeout, show, what=what)


# ---------------------------------------------------------------------------------------------- cluster


@cluster_app.command("up")
@cli_errors
@cluster_options()
def cluster_up(
    local: Annotated[bool, typer.Option("--local", help="real haa-hostd processes on loopback (the default)")] = False,
    where: ClusterOpts = LOCAL,
    hosts: Annotated[int, typer.Option("--hosts", "-n", min=1, max=64, help="number of hosts h1..hN")] = 3,
    core: Annotated[
        int | None, typer.Option("--core", min=1, help="core hosts: the first K (default 3, or N if N < 3)")
    ] = None,
    config: Annotated[
        Path | None, typer.Option("--config", help="YAML config file given to every haa-hostd (local)")
    ] = None,
    hostd_args: Annotated[str, typer.Option("--hostd-args", help="extra haa-hostd arguments (local)")] = "",
    capacity: Annotated[
        float | None,
        typer.Option(
            "--capacity",
            min=0.001,
            max=1000.0,
            help="capacity K_h of every host, in cores (default: this machine's cores / N, unless --hostd-args, "
            "--config or HAA_CAPACITY set one; compose: the docker host's cores / N)",
        ),
    ] = None,
    tls: Annotated[
        bool,
        typer.Option("--tls", help="mutual TLS: a new cluster CA, a certificate per host and one for haactl "
                     "(docs/deploy.md); default: the cluster token only"),
    ] = False,
    timeout: TimeoutOpt = 90.0,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until the group has formed")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="print the formed group as JSON")] = False,
) -> None:
    """Start hosts h1..hN and wait until they have formed one group with all N members."""
    if local and (where.compose or where.swarm):
        raise ClusterError(f"--local and --{'compose' if where.compose else 'swarm'} exclude each other")
    if core is not None and core > hosts:
        raise ClusterError(f"--core {core} is more than --hosts {hosts}")
    backend = where.backend()
    t0 = time.monotonic()
    if where.swarm:
        from haa.cluster.swarm_backend import SwarmBackend

        assert isinstance(backend, SwarmBackend)
        if config is not None or hostd_args:
            raise ClusterError("--config and --hostd-args are for local clusters (edit compose/stack.yaml)")
        with err.status(f"docker stack deploy of {hosts} hosts ..."):
            names = backend.up(hosts, core, log=err.print, capacity=capacity, tls=tls)
        before = None
    elif where.compose:
        from haa.cluster.compose_backend import ComposeBackend

        assert isinstance(backend, ComposeBackend)
        if config is not None or hostd_args:
            raise ClusterError("--config and --hostd-args are for local clusters (edit compose/compose.yaml)")
        with err.status(f"docker compose up of {hosts} hosts ..."):
            names = backend.up(hosts, core, log=err.print, capacity=capacity, tls=tls)
        before = None
    else:
        from haa.cluster.local_backend import LocalBackend

        assert isinstance(backend, LocalBackend)
        k = core if core is not None else min(3, hosts)
        names = backend.up(hosts, k, shlex.split(hostd_args), config, capacity, tls=tls)
        before = backend.check_started
    started = time.monotonic() - t0
    err.print(f"started {len(names)} hosts ({backend.describe()}{', mutual TLS' if tls else ''}) in {started:.1f} s")
    if not wait:
        return
    try:
        f, took = wait_with_progress(
            backend,
            lambda: backend.formation(names),
            len(names),
            "forming the group",
            timeout,
            f"the group to form with {len(names)} members",
            before,
        )
    except StartError:
        backend.down(grace=1.0)  # nothing stays up after a bad start
        raise
    total = time.monotonic() - t0
    if json_out:
        out.print_json(
            json.dumps(
                {
                    "backend": backend.kind,
                    "members": f.members,
                    "leader": f.leader,
                    "view": f.view,
                    "formed_seconds": round(total, 3),
                    "start_seconds": round(started, 3),
                }
            )
        )
    else:
        out.print(
            f"[green]group formed[/green]: {len(f.members)} members, leader {f.leader}, view {f.view}, "
            f"{total:.2f} s after start ({took:.2f} s after the last host started)"
        )


@cluster_app.command("down")
@cli_errors
@cluster_options()
def cluster_down(
    where: ClusterOpts = LOCAL,
    grace: Annotated[float, typer.Option("--grace", min=0, help="seconds for a graceful leave before SIGKILL")] = 5.0,
    purge: Annotated[bool, typer.Option("--purge", help="also delete the local cluster's logs and data")] = False,
) -> None:
    """Stop every host (SIGTERM = graceful leave, SIGKILL after --grace) and forget the cluster."""
    backend = where.backend(last=purge)
    if where.swarm:
        from haa.cluster.swarm_backend import SwarmBackend

        assert isinstance(backend, SwarmBackend)
        with err.status("docker stack rm ..."):
            done = backend.down(grace)
        out.print(f"{backend.describe()}: down ({done})")
        return
    if where.compose:
        from haa.cluster.compose_backend import ComposeBackend

        assert isinstance(backend, ComposeBackend)
        with err.status("docker compose down ..."):
            backend.down(grace)
        out.print(f"{backend.describe()}: down")
        return
    from haa.cluster.local_backend import LocalBackend

    assert isinstance(backend, LocalBackend)
    backend.require_hosts()
    ended = backend.down(grace, purge)
    killed = [n for n, how in ended.items() if how == "SIGKILL"]
    msg = f"{backend.describe()}: stopped {len(ended)} hosts"
    if killed:
        msg += f" ({', '.join(killed)} needed SIGKILL after {grace:g} s)"
    out.print(msg + ("; data purged" if purge else f"; logs kept in {backend.root}"))


STATE_STYLE = {"alive": "green", "paused": "yellow", "killed": "red", "left": "blue", "dead": "red"}


def status_table(st: dict[str, Any]) -> Table:
    t = table(
        ["host", "state", "address", "member", "rank", "view", "suspects", "ddb", "ddb hash", "cpu %", "rss MiB"],
        title=f"{st['cluster']}: {len(st['members'])} members, leader {st['leader'] or '-'}, view {st['view']}",
        right=["rank", "view", "ddb", "cpu %", "rss MiB"],
    )
    for r in st["hosts"]:
        state = f"[{STATE_STYLE.get(r['state'], 'white')}]{r['state']}[/]"
        if r.get("detail"):
            state += f" [dim]({r['detail']})[/]"
        name = r["name"] + (" [dim]core[/]" if r["core"] else "")
        if "member" not in r:
            t.add_row(name, state, r["address"], "", "", "", "", "", f"[red]{r['error']}[/]" if r["error"] else "")
            continue
        member = "[green]yes[/]" if r["member"] else "[yellow]no[/]"
        if r["name"] == st["leader"] and r["member"]:
            member += " [bold](leader)[/]"
        t.add_row(
            name,
            state,
            r["address"],
            member,
            str(r["rank"]) if r["rank"] >= 0 else "-",
            str(r["view"]),
            ",".join(r["suspicions"]) or "-",
            f"{r['ddb_size']} / #{r['ddb_seq']}",
            r["ddb_hash"][:12],
            f"{r['cpu_percent']:.1f}",
            f"{r['rss_bytes'] / 2**20:.0f}",
        )
    return t


@cluster_app.command("status")
@cli_errors
@cluster_options()
def cluster_status(
    where: ClusterOpts = LOCAL,
    json_out: Annotated[bool, typer.Option("--json", help="one JSON object (members, leader, view, hosts)")] = False,
    sample: Annotated[float, typer.Option("--sample", min=0, help="seconds over which CPU use is measured")] = 1.0,
) -> None:
    """Members in rank order, leader, view, and per host its state, view, rank, suspicions, DDB, CPU, RSS."""
    backend = where.backend()
    st = gather_status(backend, sample)
    if json_out:
        print(json.dumps(st, indent=2))
        return
    out.print(status_table(st))
    if st["members"]:
        out.print(f"members (rank order): {' '.join(st['members'])}")
    notes = []
    if st["members"] and not st["agreed"]:
        notes.append("[yellow]members disagree on the view (a change in progress?)[/]")
    if st["members"] and not st["ddb_hashes_equal"]:
        notes.append("[yellow]DDB hashes differ between members (writes in flight?)[/]")
    for n in notes:
        out.print(n)


# ---------------------------------------------------------------------------------------------- host

NamesArg = Annotated[list[str], typer.Argument(help="host names (h1, h2, ...)")]
WaitOpt = Annotated[
    bool, typer.Option("--wait/--no-wait", help="wait until the group has removed the host(s) from every view")
]


def _check_names(backend: Backend, names: list[str]) -> None:
    for n in names:
        backend.host(n)


def _wait_removed(backend: Backend, names: list[str], timeout: float) -> None:
    f, took = wait_with_progress(
        backend,
        lambda: backend.removed_everywhere(names),
        max(1, len([h for h in backend.hosts() if h.state == ALIVE])),
        f"removing {', '.join(names)}",
        timeout,
        f"{', '.join(names)} to leave every view",
    )
    out.print(f"{', '.join(names)} removed from every view in {took:.2f} s: view {f.view}, leader {f.leader}")


def _wait_joined(backend: Backend, name: str, timeout: float) -> None:
    f, took = wait_with_progress(
        backend,
        lambda: backend.rejoined(name),
        max(1, len([h for h in backend.hosts() if h.state == ALIVE])),
        f"{name} joining",
        timeout,
        f"{name} to join the group",
        getattr(backend, "check_started", None),
    )
    out.print(f"{name} is a member in every view after {took:.2f} s: view {f.view}, leader {f.leader}")


@host_app.command("add")
@cli_errors
@cluster_options()
def host_add(
    name: Annotated[str | None, typer.Argument(help="new host name (default: the next free hN)")] = None,
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until it is a member")] = True,
    timeout: TimeoutOpt = 60.0,
) -> None:
    """Start a new non-core host; it finds the group through the core list and joins."""
    backend = where.backend()
    backend.require_hosts()
    name = name or backend.next_name()
    h = backend.add(name)
    out.print(f"started {name} at {h.address}")
    if wait:
        _wait_joined(backend, name, timeout)


@host_app.command("restart")
@cli_errors
@cluster_options()
def host_restart(
    name: Annotated[str, typer.Argument(help="a killed or departed host")],
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until it is a member again")] = True,
    timeout: TimeoutOpt = 60.0,
) -> None:
    """Start a killed (or departed) host again: a new incarnation that re-applies to the group."""
    backend = where.backend()
    h = backend.restart(name)
    out.print(f"restarted {name} at {h.address}")
    if wait:
        _wait_joined(backend, name, timeout)


@host_app.command("leave")
@cli_errors
@cluster_options()
def host_leave(
    name: Annotated[str, typer.Argument(help="host to retire")],
    where: ClusterOpts = LOCAL,
    use_signal: Annotated[bool, typer.Option("--signal", help="send SIGTERM instead of calling Leave")] = False,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """Retire a host gracefully (Alg. 3 voluntary leave): the Leave RPC, or SIGTERM with --signal."""
    backend = where.backend()
    t0 = time.monotonic()
    if use_signal:
        backend.host(name)
        backend.terminate(name, timeout)
        if backend.host(name).up:
            raise ClusterError(f"host {name} is still running {timeout:.0f} s after SIGTERM")
        backend.mark_left(name)
        how = "SIGTERM"
    else:
        how = backend.leave(name, timeout)
    out.print(f"{name} left ({how}) in {time.monotonic() - t0:.2f} s")
    if any(h.state == ALIVE for h in backend.hosts()):
        _wait_removed(backend, [name], timeout)


def _break_hosts(
    backend: Backend, names: list[str], action: Callable[[str], None], done: str, wait: bool, timeout: float
) -> None:
    """`host kill` / `host pause`: `action` on each host, then optionally wait until the group removed them."""
    _check_names(backend, names)
    for n in names:
        action(n)
        out.print(f"{done} {n}")
    if wait:
        _wait_removed(backend, names, timeout)


@host_app.command("kill")
@cli_errors
@cluster_options()
def host_kill(
    names: NamesArg,
    where: ClusterOpts = LOCAL,
    wait: WaitOpt = False,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """SIGKILL host(s): a crash (connections refused from then on)."""
    backend = where.backend()
    _break_hosts(backend, names, backend.kill, "killed", wait, timeout)


@host_app.command("pause")
@cli_errors
@cluster_options()
def host_pause(
    names: NamesArg,
    where: ClusterOpts = LOCAL,
    wait: WaitOpt = False,
    timeout: TimeoutOpt = 30.0,
) -> None:
    """SIGSTOP / freeze host(s): a hung host whose TCP connections stay open."""
    backend = where.backend()
    _break_hosts(backend, names, backend.pause, "paused", wait, timeout)


@host_app.command("resume")
@cli_errors
@cluster_options()
def host_resume(
    names: NamesArg,
    where: ClusterOpts = LOCAL,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="wait until each is a member again")] = False,
    timeout: TimeoutOpt = 60.0,
) -> None:
    """SIGCONT / unfreeze host(s). A host the group removed meanwhile comes back as a new incarnation."""
    backend = where.backend()
    _check_names(backend, names)
    for n in names:
        backend.resume(n)
        out.print(f"resumed {n}")
    if wait:
        for n in names:
            _wait_joined(backend, n, timeout)
