"""`haactl dashboard`: serve the monitoring dashboard (haa.lab.dashboard, docs/dashboard.md) of the local cluster
(default, or `--local`) or, with `--compose`, of the docker compose cluster. Only parses arguments and prints."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from haa.cluster.backend import ClusterError
from haactl.cliopts import (
    LOCAL,
    ClusterOpts,
    HostOpt,
    cli_errors,
    cluster_options,
    out,
    stop_on_signals,
)


@cli_errors
@cluster_options(without=("swarm",))
def dashboard(
    port: Annotated[int, typer.Option("--port", "-p", min=0, max=65535, help="HTTP port (0: any free port)")] = 8765,
    bind: Annotated[str, typer.Option("--bind", help="address to listen on (loopback by default)")] = "127.0.0.1",
    local: Annotated[bool, typer.Option("--local", help="the local cluster (the default)")] = False,
    where: ClusterOpts = LOCAL,
    host: HostOpt = None,
    sim: Annotated[str | None, typer.Option("--sim", help="haa-sim HOST:PORT for the ground truth (default: the "
                                                          "local cluster's mission, else mission/params)")] = None,
    sim_token_file: Annotated[Path | None, typer.Option("--sim-token-file", help="haa-sim's token file")] = None,
    no_truth: Annotated[bool, typer.Option("--no-truth", help="show no ground truth at all")] = False,
) -> None:
    """Serve the monitoring dashboard: the map, the agent distribution timeline, the agent hierarchy and the DDB
    browser of a running cluster, updated live in the browser."""
    from haa import files
    from haa.lab import dashboard
    from haa.lab.dashboard.sources import SimTarget

    if local and where.compose:
        raise ClusterError("--local and --compose exclude each other")
    backend = where.backend()
    backend.require_hosts()
    target = None
    if sim:
        target = SimTarget(sim, files.read_token(sim_token_file) if sim_token_file else None)

    def ready(url: str) -> None:
        out.print(f"dashboard of the {backend.describe()} on [bold]{url}[/] (Ctrl-C to stop)", soft_wrap=True)

    stop_on_signals()
    try:
        dashboard.run(backend, port=port, bind=bind, host=host, sim=target, truth=not no_truth, on_ready=ready)
    except OSError as e:
        raise ClusterError(f"cannot serve on {bind}:{port}: {e.strerror or e}") from None
