"""Smoke runs of the membership benchmarks (AP-2, DDB batching) on tiny groups: they must keep working and
produce every figure; the numbers themselves are the benchmarks' business (bench-results/)."""

from __future__ import annotations

from pathlib import Path

from haa.lab.experiments.ap2 import run_ap2
from haa.lab.experiments.ddb import run_ddb_bench
from haactl import benchtables


def test_ap2_measures_join_leave_and_removal(tmp_path: Path) -> None:
    rows = run_ap2(tmp_path, max_hosts=3, reps=1, log=lambda _s: None)
    assert [r["hosts"] for r in rows] == [2, 3]
    for r in rows:
        assert r["join"]["n"] == 3 and r["leave"]["n"] == 1 and r["remove"]["n"] == 1
        assert 0 < r["join"]["median"] < 10 and 0 < r["leave"]["median"] < 5
        # removal needs a failure detection first: at least a good part of T_D^U (1 s) after the kill
        assert 0.3 < r["crash_to_removal"]["median"] < 10
        assert 0 <= r["remove"]["median"] <= r["crash_to_removal"]["median"]
    assert "| 3 |" in benchtables.ap2(rows)


def test_ddb_bench_writes_and_replicas_agree(tmp_path: Path) -> None:
    rows = run_ddb_bench(
        hosts=2, batch_sizes=(1, 20), clients=(1,), crowd=3, seconds=0.5, root=tmp_path, log=lambda _s: None,
        writers=(4,), sequencer=(True, False),
    )
    clients = [(r["sequencer"], r["clients"], r["batch"], r["through"]) for r in rows if r["load"] == "clients"]
    assert clients == [
        (seq, c, b, t)
        for seq in (True, False)
        for c, b, t in [(1, 1, "every host"), (1, 20, "every host"), (3, 1, "one host")]
    ]
    every = [r for r in rows if r["load"] == "all writing"]
    assert [(r["sequencer"], r["writers_per_host"]) for r in every] == [(True, 4), (False, 4)]
    assert all(r["requests"] > 0 and r["failed"] == 0 for r in rows)
    assert all(r["ops_per_s"] > 0 for r in rows if r["load"] == "clients")
    assert all(r["writes_per_s"] > 0 and r["oacs_per_s"] > 0 and r["p50_ms"] > 0 for r in every)
    # the OACs themselves (the sequencer's batches, or each host's own): latency at their proposers, and OAC
    # messages per OAC — at least the failure-free n^2 + 4n - 6 = 6 for two hosts
    assert all(r["oacs_measured"] > 0 and r["oac_p50_ms"] > 0 and r["msgs_per_oac"] >= 5 for r in every)
    assert "ops per request" in benchtables.ddb_clients(rows)
    every_table = benchtables.ddb_all_writing(rows)
    assert "| 2 | yes | 4 |" in every_table and "| 2 | no | 4 |" in every_table
