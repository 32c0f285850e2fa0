"""`haactl sim show`: top-down pictures of arenas and of a running simulation's true state (docs/sim.md).

* `haactl sim show small -o small.png`: an arena ("small", "large" or a YAML file), validated first (a bad
  file gets its one-line error and exit code 2).
* `haactl sim show --server 127.0.0.1:7100 -o now.png`: the true state of a running haa-sim (arena, avatars,
  collectables) read through its ground-truth API.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

sim_app = typer.Typer(
    help="The avatar simulator: pictures of arenas and of a running simulation.", no_args_is_help=True
)


@sim_app.callback()
def _sim() -> None:
    """The avatar simulator: pictures of arenas and of a running simulation."""


@sim_app.command("show")
def show(
    arena: Annotated[str | None, typer.Argument(help='"small", "large" or an arena YAML file')] = None,
    output: Annotated[Path, typer.Option("--output", "-o", help="PNG file to write")] = Path("arena.png"),
    server: Annotated[
        str | None, typer.Option("--server", help="HOST:PORT of a running haa-sim: draw its true state")
    ] = None,
    token_file: Annotated[
        Path | None, typer.Option("--token-file", help="token of that haa-sim (if it was started with one)")
    ] = None,
    scale: Annotated[float | None, typer.Option("--scale", help="pixels per metre (default: fit ~900 px)")] = None,
    labels: Annotated[bool, typer.Option("--labels/--no-labels", help="draw ids")] = True,
) -> None:
    """Render a top-down picture of an arena (or of a running simulation's true state) to a PNG."""
    from haa import files
    from haa.sim.arena import ArenaError, load_arena
    from haa.sim.render import render_topdown, save_png

    if (arena is None) == (server is None):
        typer.echo("error: give an ARENA or --server HOST:PORT (one of them)", err=True)
        raise typer.Exit(2)
    try:
        if server is not None:
            import grpc

            from haa.sim.service import SimClient, truth_from_server

            token = files.read_token(token_file) if token_file else None
            try:
                with SimClient(server, token=token, timeout=10.0) as c:
                    a, truth = truth_from_server(c)
            except grpc.RpcError as e:
                typer.echo(f"error: haa-sim at {server}: {e.code().name}: {e.details()}", err=True)
                raise typer.Exit(1) from None
            img = render_topdown(a, truth, scale=scale, labels=labels)
        else:
            assert arena is not None
            a = load_arena(arena)
            img = render_topdown(a, scale=scale, labels=labels)
        path = save_png(img, output)
    except (ArenaError, files.FileError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    except OSError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"wrote {path} ({img.shape[1]} x {img.shape[0]} px)")
