"""What `haactl chaos run --compose` refuses before anything starts (no docker needed): a mutation (local only),
`hostd_args` (the compose file gives the command lines), more hosts than the compose file has; and what the
local cluster refuses that compose does (a partition)."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from haa.lab.chaos.compose import ComposeChaosCluster
from haa.lab.chaos.plan import parse_plan
from haa.lab.chaos.run import LocalChaosCluster
from haactl.main import app

REPO = Path(__file__).resolve().parents[1]
COMPOSE = REPO / "compose" / "compose.yaml"


def plan(**kw):
    return parse_plan({"name": "p", "duration_s": 10, "workload": "ddb-writes", **kw})


def test_compose_refuses_what_only_a_local_cluster_does() -> None:
    c = ComposeChaosCluster(COMPOSE, project="haaplantest")
    assert c.problems(plan()) == []
    assert c.problems(plan(faults=[{"at_s": 1, "action": "partition", "target": ["h4"], "for_s": 2}])) == []
    assert c.problems(plan(mutation="late-commit")) == [
        "mutation: local cluster only (the mutated hosts are started from this checkout)"]
    assert c.problems(plan(hostd_args=["--agent-start-grace", "1"]))[0].startswith("hostd_args: not available")


def test_the_local_cluster_refuses_a_partition(tmp_path: Path) -> None:
    p = plan(faults=[{"at_s": 1, "action": "partition", "target": ["h4"], "for_s": 2}])
    assert "partition is not available on the local cluster" in LocalChaosCluster(tmp_path).problems(p)[0]


def test_the_cli_says_compose_file_needs_compose(tmp_path: Path) -> None:
    (tmp_path / "p.yaml").write_text("name: p\nduration_s: 5\n")
    r = CliRunner().invoke(app, ["chaos", "run", str(tmp_path / "p.yaml"), "--compose-file", str(COMPOSE)])
    assert r.exit_code == 2 and "--compose-file needs --compose" in r.output
