"""Smoke run of the agent runtime benchmark (haa.agents.bench): it measures, it does not judge."""

from __future__ import annotations

from haa.agents.bench import markdown_table, measure_spawn


def test_measure_spawn_smoke():
    r = measure_spawn(3, transfers=1, kills=1)
    assert r["spawn_to_ready_s"]["n"] == 3
    assert r["freeze_to_frozen_s"]["n"] == 1 and r["kill9_to_failed_s"]["n"] == 1
    assert 0 < r["spawn_to_hello_s"]["median"] <= r["spawn_to_ready_s"]["median"]
    assert r["uss_mib_mean"] is None or r["uss_mib_mean"] < r["rss_mib_mean"]
    table = markdown_table([r])
    assert "| fork server | 3 | spawn -> Ready |" in table
    print("\n" + table)
