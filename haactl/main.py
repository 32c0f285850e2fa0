"""haactl: the operator command line of HAA (typer + rich).

Subcommands live in their own modules: `verify` (deterministic simulation of the algorithms), `bench`
(the thesis' experiments and our own measurements) and `demo` (the main job on a local cluster).
"""

from __future__ import annotations

import typer

from haactl.bench import bench_app
from haactl.demo import demo
from haactl.verify import verify

app = typer.Typer(
    name="haactl",
    help="Operate HAA clusters: verify the algorithms, run benchmarks and demos.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Operate HAA clusters: verify the algorithms, run benchmarks and demos."""


app.command("verify")(verify)
app.add_typer(bench_app, name="bench")
app.command("demo")(demo)

if __name__ == "__main__":
    app()
