"""Smoke run of the agent runtime benchmark (haa.lab.experiments.agents): it measures, it does not judge."""

from __future__ import annotations

from haa.lab.experiments.agents import measure_spawn
from haactl.benchtables import agents


def test_measure_spawn_smoke():
    r = measure_spawn(3, transfers=1, kills=1)
    assert r["spawn_to_ready_s"]["n"] == 3
    assert r["freeze_to_frozen_s"]["n"] == 1 and r["kill9_to_failed_s"]["n"] == 1
    assert 0 < r["spawn_to_hello_s"]["median"] <= r["spawn_to_ready_s"]["median"]
    assert r["uss_mib_mean"] is None or r["uss_mib_mean"] < r["rss_mib_mean"]
    table = agents([r])
    assert "| fork server | 3 | spawn -> Ready |" in table
    assert "| mode | fork server start ms | RSS MiB/agent | USS MiB/agent (private) |" in table
    print("\n" + table)


def test_haactl_bench_agents_prints_the_tables():
    from typer.testing import CliRunner

    from haactl.main import app

    res = CliRunner().invoke(app, ["bench", "agents", "-n", "2", "--cold-n", "0", "--messages", "200", "--no-json"])
    assert res.exit_code == 0, res.output
    assert "| fork server | 2 | spawn -> Ready |" in res.output
    assert "| one supervisor | 200 | 100 |" in res.output and "| one supervisor | 200 | 10000 |" in res.output
