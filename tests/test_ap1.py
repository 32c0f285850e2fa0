"""`haactl bench ap1` checks what it quotes: every participant of a step delivered the step's committed
transactions, the same ones in the same order (a regression guard: a cumulative hash chain per host also
covers the steps a host took no part in, so comparing those was false for every n >= 3)."""

from __future__ import annotations

from pathlib import Path

from haa.cluster.hostprocs import LocalCluster
from haa.lab.experiments.ap1 import run_step, step_deliveries


def test_step_hash_compares_the_steps_deliveries_of_every_participant(tmp_path: Path) -> None:
    names = ["h1", "h2", "h3"]
    with LocalCluster(names, tmp_path) as cluster:
        cluster.start()
        cluster.wait_trusted(timeout=60)
        first = run_step(cluster, names[:2], 6, "back-to-back", concurrency=1)  # h3 takes no part
        assert first["same_delivered_hash"] and first["delivered_per_participant"] == [6]
        row = run_step(cluster, names, 9, "concurrent", concurrency=1)
        assert row["same_delivered_hash"], row
        assert row["delivered_per_participant"] == [row["transactions"] - row["aborted"]]
        # the check can fail: the same host's deliveries from another start, or fewer of them, differ
        total = cluster["h1"].status().delivered
        a = step_deliveries(cluster, "h1", total - 9, 9)
        assert a[0] == 9
        assert step_deliveries(cluster, "h1", total - 10, 9) != a
        assert step_deliveries(cluster, "h2", total - 9, 8)[1] != a[1]
