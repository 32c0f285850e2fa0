"""Benchmark: end-to-end message hop cost inside a real haa-hostd cluster on loopback.

Starts N real `haa-hostd` processes (full mesh, T_D^U = 0.5 s), waits until they all trust each other, then
proposes transactions one at a time at h1 through the control API (`wait=True`) with every host as a
participant. A failure-free OAC transaction decides at its proposer after four message delays (transaction
-> estimate -> proposal -> ack, docs/oac.md), so `propose->decide / 4` is the cost of one hop *including*
everything a hop costs in the daemon: encode, queue, batch, gRPC stream write, loopback, gRPC read, decode,
the core's step, and the effect loop. The idle CPU of each daemon (heartbeats only) is measured too.

Prints a table and writes `bench-results/hostd_oac_latency.json`. Never fails on a timing.
Run: `.venv/bin/python -m haa.lab.bench.hostd_oac_latency [--hosts 2,3] [--tx 300]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

from haa.hostd.control import ControlClient

ROOT = Path(__file__).resolve().parents[3]
TOKEN = "bench-token"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def run_cluster(n: int, n_tx: int, tmp: Path) -> dict[str, object]:
    names = [f"h{i + 1}" for i in range(n)]
    ports = {h: _free_port() for h in names}
    token = tmp / "token"
    token.write_text(TOKEN + "\n")
    exe = Path(sys.executable).parent / "haa-hostd"
    cmd0 = [str(exe)] if exe.exists() else [sys.executable, "-m", "haa.hostd.daemon"]
    procs = []
    for h in names:
        peers = ",".join(f"{p}=127.0.0.1:{ports[p]}" for p in names if p != h)
        args = ["--name", h, "--listen", f"127.0.0.1:{ports[h]}", "--token-file", str(token)]
        args += ["--data-dir", str(tmp / f"{n}-{h}"), "--qos-td", "0.5"]
        if peers:
            args += ["--peers", peers]
        procs.append(subprocess.Popen([*cmd0, *args], stderr=subprocess.DEVNULL))
    clients = [ControlClient(f"127.0.0.1:{ports[h]}", TOKEN) for h in names]
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                sts = [c.status() for c in clients]
                incs = {s.name: s.incarnation for s in sts}
                if all(not p.suspected and p.incarnation == incs[p.name] for s in sts for p in s.peers):
                    break
            except Exception:  # not up yet
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("cluster did not come up")
            time.sleep(0.1)
        for i in range(20):  # warm-up
            clients[0].propose(b"warm-up %d" % i, participants=names)
        # idle CPU: heartbeats only
        ps = [psutil.Process(p.pid) for p in procs]
        for p in ps:
            p.cpu_percent(None)
        time.sleep(3.0)
        idle_cpu = [p.cpu_percent(None) for p in ps]
        p2d, rpc = [], []
        for i in range(n_tx):
            t0 = time.monotonic()
            r = clients[0].propose(b"tx %06d" % i, participants=names)
            rpc.append(time.monotonic() - t0)
            assert r.committed
            p2d.append(r.propose_to_decide)
            time.sleep(0.003)
        hashes = {c.status().delivered_hash for c in clients}
        ms = 1e3
        return {
            "hosts": n,
            "transactions": n_tx,
            "propose_to_decide_p50_ms": _pct(p2d, 0.5) * ms,
            "propose_to_decide_p90_ms": _pct(p2d, 0.9) * ms,
            "propose_to_decide_p99_ms": _pct(p2d, 0.99) * ms,
            "hop_p50_ms": _pct(p2d, 0.5) * ms / 4,
            "control_rpc_p50_ms": _pct(rpc, 0.5) * ms,
            "idle_cpu_percent_per_host": statistics.mean(idle_cpu),
            "same_delivered_hash": len(hashes) == 1,
        }
    finally:
        for c in clients:
            c.close()
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hosts", default="2,3")
    ap.add_argument("--tx", type=int, default=300)
    ap.add_argument("--out", default=str(ROOT / "bench-results" / "hostd_oac_latency.json"))
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="haa-bench-"))
    try:
        results = [run_cluster(int(n), args.tx, tmp) for n in args.hosts.split(",")]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    heads = ["p2d p50", "p2d p90", "p2d p99", "hop p50", "rpc p50", "idle cpu"]
    print(f"{'hosts':>5}  " + "  ".join(f"{h:>8}" for h in heads))
    for r in results:
        print(
            f"{r['hosts']:>5}  {r['propose_to_decide_p50_ms']:8.2f}  {r['propose_to_decide_p90_ms']:8.2f}  "
            f"{r['propose_to_decide_p99_ms']:8.2f}  {r['hop_p50_ms']:8.3f}  {r['control_rpc_p50_ms']:8.2f}  "
            f"{r['idle_cpu_percent_per_host']:7.1f}%"
        )
    out = {
        "benchmark": "hostd_oac_latency",
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "units": "milliseconds; propose_to_decide on the proposer's clock; hop = propose_to_decide / 4",
        "results": results,
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
