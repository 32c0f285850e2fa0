"""haactl: the operator command line of HAA (typer + rich).

Subcommands live in their own modules: `verify` (deterministic simulation of the algorithms), `bench`
(the thesis' experiments and our own measurements), `demo` (the main job on a local cluster), and the
operator commands `cluster`, `host`, `ddb` and `logs` (haactl.cluster, haactl.ddbcli, haactl.logview; local
processes or, with --compose, the docker compose cluster: docs/cluster.md), and the robot team's `mission` and
`experiment` (haactl.mission: docs/missions.md), `chaos` (haactl.chaos: docs/chaos.md), and `stats collect` and `report`
(haactl.stats: docs/stats.md), and `dashboard` (haactl.dashboard: docs/dashboard.md) and `foxglove` (haactl.foxglove:
docs/metrics.md).
"""

from __future__ import annotations

import typer

from haactl.agentcli import agent_app, alloc_app
from haactl.bench import bench_app
from haactl.chaos import chaos_app
from haactl.cluster import cluster_app, host_app
from haactl.dashboard import dashboard
from haactl.ddbcli import ddb_app
from haactl.demo import demo
from haactl.foxglove import foxglove
from haactl.logview import logs
from haactl.mission import experiment, mission_app
from haactl.record import record_app
from haactl.replay import replay
from haactl.sim import sim_app
from haactl.stats import report, stats_app
from haactl.verify import verify

app = typer.Typer(
    name="haactl",
    help="Operate HAA clusters: bring them up, inspect and break them, verify the algorithms, run benchmarks.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Operate HAA clusters: bring them up, inspect and break them, verify the algorithms, run benchmarks."""


app.command("verify")(verify)
app.add_typer(bench_app, name="bench")
app.command("demo")(demo)
app.add_typer(cluster_app, name="cluster")
app.add_typer(host_app, name="host")
app.add_typer(ddb_app, name="ddb")
app.command("logs")(logs)
app.add_typer(sim_app, name="sim")
app.add_typer(agent_app, name="agent")
app.add_typer(alloc_app, name="alloc")
app.add_typer(mission_app, name="mission")
app.command("experiment")(experiment)
app.add_typer(chaos_app, name="chaos")
app.add_typer(stats_app, name="stats")
app.command("report")(report)
app.command("dashboard")(dashboard)
app.command("foxglove")(foxglove)
app.add_typer(record_app, name="record")
app.command("replay")(replay)

if __name__ == "__main__":
    app()
