"""`haactl foxglove`: bridge the local cluster (default, or `--local`) or, with `--compose`, the docker compose
cluster to Foxglove / Lichtblick over the Foxglove WebSocket protocol (haa.lab.foxglove, docs/metrics.md). Only
parses arguments and prints."""

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
def foxglove(
    port: Annotated[int, typer.Option("--port", "-p", min=0, max=65535,
                                      help="WebSocket port (0: any free port)")] = 8765,
    bind: Annotated[str, typer.Option("--bind", help="address to listen on (loopback by default)")] = "127.0.0.1",
    local: Annotated[bool, typer.Option("--local", help="the local cluster (the default)")] = False,
    where: ClusterOpts = LOCAL,
    host: HostOpt = None,
    sim: Annotated[str | None, typer.Option(
        "--sim", help="haa-sim HOST:PORT for the true poses and landmarks (default: the local cluster's mission, else "
        "mission/params)")] = None,
    sim_token_file: Annotated[Path | None, typer.Option("--sim-token-file", help="haa-sim's token file")] = None,
    no_truth: Annotated[bool, typer.Option("--no-truth", help="publish no ground truth at all")] = False,
) -> None:
    """Serve a running cluster to Foxglove: the map as a Grid, estimated and true poses, particles as point clouds,
    landmarks, paths and targets, the mission transcript and the agent timeline as logs, live."""
    from haa import files
    from haa.lab import foxglove as bridge
    from haa.lab.dashboard.sources import SimTarget

    if local and where.compose:
        raise ClusterError("--local and --compose exclude each other")
    backend = where.backend()
    backend.require_hosts()
    target = None
    if sim:
        target = SimTarget(sim, files.read_token(sim_token_file) if sim_token_file else None)

    def ready(url: str) -> None:
        out.print(f"Foxglove bridge of the {backend.describe()} on [bold]{url}[/] (in Foxglove: Open connection -> "
                  "Foxglove WebSocket; Ctrl-C to stop)", soft_wrap=True)

    stop_on_signals()
    try:
        bridge.run(backend, port=port, bind=bind, host=host, sim=target, truth=not no_truth, on_ready=ready)
    except OSError as e:
        raise ClusterError(f"cannot serve on {bind}:{port}: {e.strerror or e}") from None
