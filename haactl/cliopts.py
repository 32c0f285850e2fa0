"""What the commands of haactl share: the options that say which cluster a command works on, declared once —
`ClusterOpts` and the decorator `cluster_options` give a command --compose, --swarm, --root and --compose-file
(the annotations `ComposeOpt`, `SwarmOpt`, `RootOpt`, `ComposeFileOpt`) as one value, `where.backend()` the
haa.cluster backend they name (`open_backend`); every command of `cluster`, `host`, `agent`, `alloc`, `ddb`,
`logs`, `stats`, `mission`, `dashboard` and `foxglove` takes them so. Also `HostOpt`, `JsonOpt`, the benchmarks'
`BenchRootOpt`, the consoles `out`/`err`, and `cli_errors` (a ClusterError as one red line, exit code 1).
Tables are drawn with haactl.tables."""

from __future__ import annotations

import functools
import inspect
import sys
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated, Any, TypeVar, cast

import typer
from rich.console import Console
from rich.markup import escape

from haa.cluster.backend import Backend, ClusterError

F = TypeVar("F", bound=Callable[..., Any])


def stop_on_signals() -> None:
    """For a command that serves until stopped (dashboard, foxglove): SIGINT and SIGTERM end it as Ctrl-C does
    (KeyboardInterrupt: a clean shutdown, exit code 130). A process started in the background by a shell
    inherits SIGINT *ignored*, and Python then installs no handler of its own: `kill -INT` did nothing.
    SIGUSR1 prints every thread's stack to stderr (faulthandler): where a server that does not stop is stuck."""
    import faulthandler
    import signal

    faulthandler.register(signal.SIGUSR1, all_threads=True)

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, interrupt)

# Not a terminal (a pipe, a file, a test runner): wide lines rather than tables squeezed into 80 columns.
out = Console(highlight=False, width=None if sys.stdout.isatty() else 200)
err = Console(stderr=True, highlight=False, width=None if sys.stderr.isatty() else 200)

ComposeOpt = Annotated[
    bool,
    typer.Option(
        "--compose",
        envvar="HAA_COMPOSE",
        help="the docker compose cluster (compose/compose.yaml) instead of the local one (env HAA_COMPOSE=1)",
    ),
]
SwarmOpt = Annotated[
    bool,
    typer.Option(
        "--swarm",
        envvar="HAA_SWARM",
        help="the Docker Swarm stack (compose/stack.yaml, stack $HAA_SWARM_STACK or haa; docs/swarm.md) instead of "
        "the local cluster (env HAA_SWARM=1)",
    ),
]
RootOpt = Annotated[
    Path | None,
    typer.Option(
        "--root",
        help="local cluster directory (default $HAA_CLUSTER_DIR, else .haa/cluster under the current directory)",
        show_default=False,
    ),
]
ComposeFileOpt = Annotated[
    Path | None,
    typer.Option(
        "--compose-file",
        help="compose file (default $HAA_COMPOSE_FILE, else compose/compose.yaml); with --swarm the stack file "
        "(default $HAA_STACK_FILE, else compose/stack.yaml)",
        show_default=False,
    ),
]
HostOpt = Annotated[
    str | None, typer.Option("--host", "-H", help="talk to this host (default: the first alive member)")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="JSON output")]
BenchRootOpt = Annotated[
    Path | None, typer.Option("--root", help="data dirs and logs (default: a temporary dir)")
]


def open_backend(
    compose: bool, root: Path | None = None, compose_file: Path | None = None, last: bool = False, swarm: bool = False
) -> Backend:
    """The cluster a command works on; `last`: a local cluster that `cluster down` stopped will do (logs)."""
    if swarm:
        if compose:
            raise ClusterError("--swarm and --compose exclude each other")
        if root is not None:
            raise ClusterError("--root is for local clusters; not with --swarm")
        from haa.cluster.swarm_backend import SwarmBackend

        return SwarmBackend(compose_file)
    if compose:
        if root is not None:
            raise ClusterError("--root is for local clusters; not with --compose")
        from haa.cluster.compose_backend import ComposeBackend

        return ComposeBackend(compose_file)
    if compose_file is not None:
        raise ClusterError("--compose-file needs --compose (or --swarm)")
    from haa.cluster.local_backend import LocalBackend

    return LocalBackend(root, last=last)


@dataclass(frozen=True)
class ClusterOpts:
    """Which cluster a command works on: its cluster-selection options, as `cluster_options` passes them."""

    compose: bool = False
    swarm: bool = False
    root: Path | None = None
    compose_file: Path | None = None

    def backend(self, last: bool = False) -> Backend:
        """The cluster they name (`open_backend`; `last`: a stopped local cluster will do)."""
        return open_backend(self.compose, self.root, self.compose_file, last=last, swarm=self.swarm)


#: the placeholder default of a command's ClusterOpts parameter (the local cluster at its default root)
LOCAL = ClusterOpts()

#: ClusterOpts' fields as command options, in the order --help shows them
_CLUSTER_OPTIONS = {"compose": ComposeOpt, "swarm": SwarmOpt, "root": RootOpt, "compose_file": ComposeFileOpt}


def cluster_options(*, without: tuple[str, ...] = ()) -> Callable[[F], F]:
    """Give a command the cluster-selection options: its one parameter annotated `ClusterOpts` (default `LOCAL`)
    becomes --compose, --swarm, --root and --compose-file in its place (`without`: fields left out, e.g.
    ("swarm",) for a command that runs on local and compose clusters only), and the command is called with
    their values as that one ClusterOpts. Put it below `@cli_errors`, next to the function."""

    def deco(fn: F) -> F:
        sig = inspect.signature(fn, eval_str=True)
        params = list(sig.parameters.values())
        (where,) = (p for p in params if p.annotation is ClusterOpts)
        names = [f.name for f in fields(ClusterOpts) if f.name not in without]
        options = [inspect.Parameter(n, inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=_CLUSTER_OPTIONS[n],
                                     default=getattr(LOCAL, n)) for n in names]
        k = params.index(where)
        params[k:k + 1] = options

        @functools.wraps(fn)
        def command(*args: Any, **kwargs: Any) -> Any:
            kwargs[where.name] = ClusterOpts(**{n: kwargs.pop(n) for n in names if n in kwargs})
            return fn(*args, **kwargs)

        cast(Any, command).__signature__ = sig.replace(parameters=params)  # what typer reads (inspect.signature)
        command.__annotations__ = {p.name: p.annotation for p in params} | {"return": sig.return_annotation}
        return cast(F, command)

    return deco


def fail(message: str) -> None:
    err.print(f"[bold red]error:[/bold red] {escape(message)}")
    raise typer.Exit(1)


def cli_errors(fn: F) -> F:
    """Turn `ClusterError` into one red line on stderr and exit code 1; Ctrl-C into exit code 130."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ClusterError as e:
            fail(str(e))
        except KeyboardInterrupt:
            err.print("interrupted")
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]
