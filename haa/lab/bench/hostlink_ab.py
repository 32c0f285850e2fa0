"""A/B of the host-link carriers (issue 14; docs/transport.md, "The TCP host link"): AP-1 at n hosts on the gRPC
host link and on the TCP one, run by run alternating, with the cluster's CPU and frames per transaction.

Each run starts a fresh static group of `--hosts` `haa-hostd` processes (`haa.cluster.hostprocs.LocalCluster`; the
carrier comes from `HAA_HOST_LINK`, which the hosts inherit), warms up with 50 back-to-back transactions, then
runs `haa.lab.experiments.ap1.run_step` for each load (paced, back-to-back, all-proposing, concurrent with 2 in
flight per host) and adds, per row: the CPU time (user + system) of every haa-hostd process over the row, per committed
transaction, and the frames every host wrote (`tx_frames`) per transaction. Runs alternate grpc, tcp, grpc, ...
so that a neighbour's load falls on both alike; the 1-minute load average is recorded before each run.

    .venv/bin/python -m haa.lab.bench.hostlink_ab --runs 3 --hosts 10 -n 100 --out bench-results/hostlink-ab.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.hostprocs import LocalCluster
from haa.lab.experiments.ap1 import MODES, run_step


def _cpu(cluster: LocalCluster) -> float:
    total = 0.0
    for h in cluster.hosts.values():
        assert h.proc is not None
        t = psutil.Process(h.proc.pid).cpu_times()
        total += t.user + t.system
    return total


def _frames(cluster: LocalCluster) -> int:
    return sum(int(h.status().counters.values["tx_frames"]) for h in cluster.hosts.values())


def one_run(carrier: str, hosts: int, transactions: int) -> dict[str, Any]:
    os.environ["HAA_HOST_LINK"] = carrier
    names = [f"h{i + 1}" for i in range(hosts)]
    out: dict[str, Any] = {"carrier": carrier, "load_1min": os.getloadavg()[0], "rows": {}}
    with tempfile.TemporaryDirectory(prefix="haa-linkab-") as root, LocalCluster(names, Path(root)) as cluster:
        cluster.start()
        cluster.wait_trusted(timeout=60)
        run_step(cluster, names, 50, "back-to-back", concurrency=1)
        for mode in MODES:
            c0, f0 = _cpu(cluster), _frames(cluster)
            row = run_step(cluster, names, transactions, mode, 2)
            c1, f1 = _cpu(cluster), _frames(cluster)
            done = max(1, row["transactions"] - row["aborted"])
            out["rows"][mode] = {
                "p50_ms": row["propose_to_decide_ms"]["p50"],
                "p99_ms": row["propose_to_decide_ms"]["p99"],
                "tx_per_s": row["throughput_tx_per_s"],
                "oac_msgs_per_tx": row["messages_per_tx"],
                "cpu_ms_per_tx": (c1 - c0) * 1e3 / done,
                "frames_per_tx": (f1 - f0) / done,
                "same_delivered_hash": row["same_delivered_hash"],
            }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--hosts", type=int, default=10)
    p.add_argument("-n", "--transactions", type=int, default=100)
    p.add_argument("--out", default="bench-results/hostlink-ab.json")
    a = p.parse_args()
    runs = []
    for i in range(a.runs):
        for carrier in ("grpc", "tcp"):
            t0 = time.monotonic()
            r = one_run(carrier, a.hosts, a.transactions)
            runs.append(r)
            print(f"run {i + 1} {carrier}: load {r['load_1min']:.1f}, {time.monotonic() - t0:.0f} s", flush=True)
            for mode, row in r["rows"].items():
                print(f"  {mode:13s} p50 {row['p50_ms']:7.2f} ms  {row['tx_per_s']:5.0f} tx/s  "
                      f"cpu {row['cpu_ms_per_tx']:6.2f} ms/tx  frames {row['frames_per_tx']:6.1f}/tx", flush=True)
    medians: dict[str, Any] = {}
    for carrier in ("grpc", "tcp"):
        mine = [r for r in runs if r["carrier"] == carrier]
        medians[carrier] = {
            mode: {k: statistics.median(r["rows"][mode][k] for r in mine)
                   for k in ("p50_ms", "p99_ms", "tx_per_s", "oac_msgs_per_tx", "cpu_ms_per_tx", "frames_per_tx")}
            for mode in MODES
        }
        medians[carrier]["load_1min"] = [r["load_1min"] for r in mine]
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"hosts": a.hosts, "transactions": a.transactions, "runs": runs,
                                       "medians": medians}, indent=1))
    print(json.dumps(medians, indent=1))


if __name__ == "__main__":
    main()
