"""The commit path's goals measured on one tree, per host-link carrier, run by run alternating.

Each run, for one carrier (`HAA_HOST_LINK`, which the hosts inherit), measures in this order:

* AP-1 at `--hosts` (static group, 50 warm-up transactions, then paced, back-to-back, all-proposing and
  concurrent with 2 in flight per host; `haa.lab.bench.hostlink_ab`'s `one_run`, cluster CPU and frames per
  transaction included);
* the DDB all-writing load through the sequencer with the tree's default `seq_inflight` (a fresh membership
  group; `haa.lab.bench.seq_ab`'s `one_run`: writes/s, write p50, OAC p50, writes per OAC, cluster CPU per
  write);
* `bench idle` (`haa.lab.experiments.idle.measure_local`: CPU of an idle membership-mode cluster, % of one core);
* `bench ap4` at `--hosts` (`haa.lab.experiments.ap4.run_ap4`: transfer idle / under ping, host recovery, crash
  detection).

Runs alternate grpc, tcp, grpc, ... so that a neighbour's load falls on both alike; the 1-minute load is
recorded before each part. Every run is written to `--out` as soon as it ends (a killed sweep keeps what it
measured); the summary prints the medians per carrier beside the issue's goals.

    flock /tmp/haa-bench.lock env .venv/bin/python -m haa.lab.bench.carriers --runs 3 \\
        --out bench-results/issue14-final.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import time
from pathlib import Path
from typing import Any

from haa.core.membership.membership import NodeConfig
from haa.lab.experiments.ap4 import run_ap4
from haa.lab.experiments.idle import measure_local

CARRIERS = ("grpc", "tcp")


def _bench(name: str) -> Any:
    """A sibling benchmark (haa.lab.bench.<name>)."""
    return importlib.import_module(f"haa.lab.bench.{name}")


def _ap4_summary(row: dict[str, Any]) -> dict[str, float | None]:
    s = row.get("summary", {})
    keys = ("transfer_idle", "transfer", "host_removal", "host_recovery", "recovery", "crash_detect", "spawn")
    return {k: (s[k]["median"] if isinstance(s.get(k), dict) and s[k].get("n") else None) for k in keys}


def _retry(out: dict[str, Any], part: str, fn: Any, tries: int = 3) -> Any:
    """`fn()`, again with a fresh group if it could not be formed or broke (a host that failed to start: its
    port taken between `free_port` and its bind); the failures are kept in the run's `retries`."""
    for i in range(tries):
        try:
            return fn()
        except (AssertionError, RuntimeError, OSError) as e:
            out.setdefault("retries", []).append(f"{part}: {type(e).__name__}: {str(e)[:300]}")
            print(f"  {part} failed ({type(e).__name__}), try {i + 2} of {tries}", flush=True)
            if i == tries - 1:
                raise
    raise AssertionError("unreachable")


def one_run(carrier: str, hosts: int, transactions: int, writers: list[int], seconds: float, reps: int,
            idle_s: float) -> dict[str, Any]:
    os.environ["HAA_HOST_LINK"] = carrier
    out: dict[str, Any] = {"carrier": carrier, "seq_inflight": NodeConfig().seq_inflight,
                           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "load": {}}
    out["load"]["ap1"] = os.getloadavg()[0]
    out["ap1"] = _retry(out, "ap1", lambda: _bench("hostlink_ab").one_run(carrier, hosts, transactions)["rows"])
    out["load"]["ddb"] = os.getloadavg()[0]
    ddb = _retry(out, "ddb", lambda: _bench("seq_ab").one_run(carrier, NodeConfig().seq_inflight, hosts, writers,
                                                             seconds, None, "final"))
    out["ddb"] = [{k: r[k] for k in ("writers_per_host", "writes_per_s", "p50_ms", "p99_ms", "oac_p50_ms",
                                     "writes_per_oac", "failed", "cluster_cores_in_load")}
                  | {"cpu_ms_per_write": 1e3 * r["cluster_cpu_s"] / max(1, r["requests"])} for r in ddb["rows"]]
    out["load"]["idle"] = os.getloadavg()[0]
    idle = _retry(out, "idle", lambda: measure_local(hosts, idle_s, 10.0, log=lambda s: None))
    out["idle"] = {k: idle[k] for k in ("cpu_percent_total", "tx_frames_per_s_per_host", "rss_mib_mean")}
    out["load"]["ap4"] = os.getloadavg()[0]
    rows = run_ap4([hosts], reps=reps, log=lambda s: None)
    out["ap4"] = _ap4_summary(rows[0]) | ({"error": rows[0]["error"]} if "error" in rows[0] else {})
    return out


def _med(xs: list[float | None]) -> float | None:
    ys = [x for x in xs if x is not None]
    return statistics.median(ys) if ys else None


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians per carrier of every figure the issue names a goal for."""
    med: dict[str, Any] = {}
    for c in CARRIERS:
        mine = [r for r in runs if r["carrier"] == c]
        if not mine:
            continue
        m: dict[str, Any] = {"runs": len(mine), "loads": [round(v, 1) for r in mine for v in r["load"].values()]}
        for mode in mine[0]["ap1"]:
            for k in ("p50_ms", "tx_per_s", "oac_msgs_per_tx", "cpu_ms_per_tx"):
                m[f"ap1.{mode}.{k}"] = _med([r["ap1"][mode][k] for r in mine])
            m[f"ap1.{mode}.same_delivered_hash"] = all(r["ap1"][mode]["same_delivered_hash"] for r in mine)
        for w in sorted({row["writers_per_host"] for r in mine for row in r["ddb"]}):
            for k in ("writes_per_s", "p50_ms", "oac_p50_ms", "writes_per_oac", "cpu_ms_per_write", "failed"):
                m[f"ddb.w{w}.{k}"] = _med([row[k] for r in mine for row in r["ddb"] if row["writers_per_host"] == w])
        m["idle.cpu_percent"] = _med([r["idle"]["cpu_percent_total"] for r in mine])
        for k in mine[0]["ap4"]:
            if k != "error":
                m[f"ap4.{k}_ms"] = _med([1e3 * r["ap4"][k] if r["ap4"].get(k) is not None else None for r in mine])
        m["ap4.errors"] = [r["ap4"]["error"] for r in mine if "error" in r["ap4"]]
        med[c] = m
    return med


GOALS = {
    "ap1.paced.p50_ms": "<= 6",
    "ap1.all-proposing.p50_ms": "<= 2 x paced",
    "ap1.concurrent.p50_ms": "<= 2 x paced",
    "ap1.all-proposing.oac_msgs_per_tx": "<= 268",
    "ap1.concurrent.oac_msgs_per_tx": "<= 268",
    "ddb.w32.writes_per_s": ">= 5000",
    "ddb.w32.p50_ms": "<= 20",
    "idle.cpu_percent": "<= 15",
    "ap4.transfer_idle_ms": "<= 150",
    "ap4.transfer_ms": "<= 250",
    "ap4.host_recovery_ms": "<= 300",
    "ap4.host_removal_ms": "no slower (host kill -> removed)",
    "ap4.crash_detect_ms": "no slower (agent kill -> detected)",
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--hosts", type=int, default=10)
    p.add_argument("-n", "--transactions", type=int, default=100)
    p.add_argument("--writers", type=int, action="append", help="all-writing writers per host (repeat; 8, 32)")
    p.add_argument("--seconds", type=float, default=5.0, help="each all-writing load")
    p.add_argument("--reps", type=int, default=3, help="AP-4 samples of each action")
    p.add_argument("--idle", type=float, default=30.0, help="idle measurement window, s")
    p.add_argument("--out", type=Path, default=Path("bench-results/issue14-final.json"))
    a = p.parse_args()
    runs: list[dict[str, Any]] = []
    for i in range(a.runs):
        for carrier in CARRIERS:
            t0 = time.monotonic()
            runs.append(one_run(carrier, a.hosts, a.transactions, a.writers or [8, 32], a.seconds, a.reps, a.idle))
            print(f"run {i + 1} {carrier}: {time.monotonic() - t0:.0f} s, loads {runs[-1]['load']}", flush=True)
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.write_text(json.dumps({"hosts": a.hosts, "runs": runs, "medians": summary(runs), "goals": GOALS},
                                        indent=1))
    med = summary(runs)
    keys = sorted({k for m in med.values() for k in m if k not in ("runs", "loads")})
    print(f"\n{'figure':42s} " + " ".join(f"{c:>12s}" for c in med) + "  goal")
    for k in keys:
        cells = [med[c].get(k) for c in med]
        print(f"{k:42s} " + " ".join(f"{v:12.2f}" if isinstance(v, float) else f"{v!s:>12s}" for v in cells)
              + f"  {GOALS.get(k, '')}")


if __name__ == "__main__":
    main()
