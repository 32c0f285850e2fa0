"""A/B of the DDB all-writing load through the sequencer (issue 14, seventh session): host-link carrier x
`membership: seq_inflight`, run by run alternating, optionally with a py-spy profile of the sequencer leader.

Each run starts a fresh group of `--hosts` membership-mode `haa-hostd` processes (`haa.lab.experiments.ddb`'s
`MemberHost`s; the carrier comes from `HAA_HOST_LINK`, which the hosts inherit; `sequencer` and `seq_inflight`
go into the hosts' hostd.yaml), then runs `haa.lab.experiments.ddb._all_writing` for each `--writers` and adds, per
row, the CPU time (user + system) of the leader and of the whole cluster over the row. The variants given with
`--variant CARRIER:INFLIGHT` (repeat) alternate run by run (A B A B ...); the 1-minute load average is recorded
before and after each run. `--profile DIR` records the leader with py-spy (`--native`-less, `--idle` off) during
the first `--writers` row of every run, as a raw collapsed-stack file per run.

    .venv/bin/python -m haa.lab.bench.seq_ab --hosts 10 --writers 32 --variant grpc:2 --variant tcp:2 \\
        --runs 3 --out bench-results/issue14-seq-profile.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.hostprocs import MemberHost, member_group, wait_for
from haa.lab.experiments import ddb as ddbx
from haa.lab.experiments.ap2 import CORE


def _cpu(h: MemberHost) -> float:
    assert h.proc is not None
    t = psutil.Process(h.proc.pid).cpu_times()
    return float(t.user + t.system)


def _threads(h: MemberHost) -> tuple[float, float]:
    """(CPU s of the main thread, CPU s of every other thread) of a host, from /proc/PID/task/*/stat."""
    assert h.proc is not None
    tick = os.sysconf("SC_CLK_TCK")
    main = other = 0.0
    for task in Path(f"/proc/{h.proc.pid}/task").iterdir():
        try:
            f = task.joinpath("stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        t = (int(f[11]) + int(f[12])) / tick
        if int(task.name) == h.proc.pid:
            main += t
        else:
            other += t
    return main, other


def one_run(carrier: str, inflight: int, hosts: int, writers: list[int], seconds: float,
            profile: Path | None, tag: str, native: bool = False) -> dict[str, Any]:
    os.environ["HAA_HOST_LINK"] = carrier
    out: dict[str, Any] = {"carrier": carrier, "seq_inflight": inflight, "load_1min_before": os.getloadavg()[0],
                           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "rows": []}
    with tempfile.TemporaryDirectory(prefix="haa-seqab-") as tmp:
        base = Path(tmp)
        group = member_group(base, hosts, f"membership:\n  sequencer: true\n  seq_inflight: {inflight}\n", CORE,
                             "seq-ab")
        names = [h.name for h in group]
        try:
            for h in group:
                h.start()
            wait_for(lambda: all(sorted(h.client.status().members) == sorted(names) for h in group), 90,
                     f"a group of {hosts}")
            leader_name = group[0].client.status().leader
            leader = next(h for h in group if h.name == leader_name)
            assert leader.proc is not None
            environ = Path(f"/proc/{leader.proc.pid}/environ").read_bytes().split(b"\0")
            cmdline = Path(f"/proc/{leader.proc.pid}/cmdline").read_bytes().split(b"\0")
            out["leader"] = leader_name
            out["leader_pythonpath"] = next((e.decode() for e in environ if e.startswith(b"PYTHONPATH=")), "")
            out["leader_host_link_env"] = next((e.decode() for e in environ if e.startswith(b"HAA_HOST_LINK=")), "")
            out["leader_cmd0"] = cmdline[0].decode()
            for i, w in enumerate(writers):
                spy: list[subprocess.Popen[bytes]] = []
                if profile is not None and i == 0:
                    profile.mkdir(parents=True, exist_ok=True)
                    cmd = [str(Path(sys.executable).parent / "py-spy"), "record", "--pid", str(leader.proc.pid),
                           "--format", "raw", "--rate", "200", "--duration", str(int(seconds) - 1), "--nonblocking",
                           *(["--native"] if native else []), *(["--gil"] if os.environ.get("SEQ_AB_GIL") else []),
                           "-o", str(profile / f"{tag}-{carrier}-{inflight}-w{w}.txt")]
                    # the load starts 1 s after the call (DdbLoad's start_at) and lasts `seconds`: sample inside it
                    timer = threading.Timer(1.5, lambda cmd=cmd, spy=spy: spy.append(subprocess.Popen(
                        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)))
                    timer.start()
                c_l0, c_all0 = _cpu(leader), sum(_cpu(h) for h in group)
                # the leader's and the cluster's CPU inside the load window only (it starts 1 s after the call)
                window: list[tuple[float, float, float, float, float]] = []

                def sample(group: list[MemberHost] = group, leader: MemberHost = leader,
                           window: list[tuple[float, float, float, float, float]] = window) -> None:
                    th = [_threads(h) for h in group]
                    window.append((time.monotonic(), _cpu(leader), sum(_cpu(h) for h in group),
                                   sum(m for m, _ in th), sum(o for _, o in th)))

                timers = [threading.Timer(1.2, sample), threading.Timer(1.0 + seconds - 0.2, sample)]
                for tm in timers:
                    tm.start()
                t0 = time.monotonic()
                row = ddbx._all_writing(group, w, seconds, True, lambda *a: None)
                wall = time.monotonic() - t0
                c_l1, c_all1 = _cpu(leader), sum(_cpu(h) for h in group)
                for p in spy:
                    p.wait(60)
                for tm in timers:
                    tm.join()
                (w0, l0, a0, m0, o0), (w1, l1, a1, m1, o1) = window
                row["cluster_main_thread_cores"] = (m1 - m0) / (w1 - w0)
                row["cluster_other_threads_cores"] = (o1 - o0) / (w1 - w0)
                row["leader_cores_in_load"] = (l1 - l0) / (w1 - w0)
                row["cluster_cores_in_load"] = (a1 - a0) / (w1 - w0)
                lc = leader.client.status().counters.values
                row.update({
                    "leader_cpu_s": c_l1 - c_l0, "cluster_cpu_s": c_all1 - c_all0, "wall_s": wall,
                    "leader_cpu_share": (c_l1 - c_l0) / wall,
                    "leader_tx_frames": int(lc.get("tx_frames", 0)), "leader_rx_frames": int(lc.get("rx_frames", 0)),
                })
                out["rows"].append(row)
                print(f"  {carrier}:{inflight} w={w}: {row['writes_per_s']:.0f} writes/s p50 {row['p50_ms']:.1f} ms "
                      f"oac p50 {row['oac_p50_ms']:.1f} ms, {row['writes_per_oac']:.1f} w/OAC, leader cpu "
                      f"{row['leader_cores_in_load']:.2f}, cluster {row['cluster_cores_in_load']:.2f} cores "
                      f"(main threads {row['cluster_main_thread_cores']:.2f}, "
                      f"others {row['cluster_other_threads_cores']:.2f}), cpu/write "
                      f"{1e3 * row['cluster_cpu_s'] / max(1, row['requests']):.3f} ms, failed {row['failed']}",
                      flush=True)
        finally:
            for h in group:
                h.kill()
                h.client.close()
    out["load_1min_after"] = os.getloadavg()[0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hosts", type=int, default=10)
    ap.add_argument("--writers", type=int, action="append")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--variant", action="append", required=True, help="CARRIER:SEQ_INFLIGHT, e.g. tcp:2")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--profile", type=Path)
    ap.add_argument("--tag", default="run")
    ap.add_argument("--native", action="store_true", help="py-spy --native (C frames too)")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    writers = a.writers or [32]
    variants = [(v.split(":")[0], int(v.split(":")[1])) for v in a.variant]
    runs: list[dict[str, Any]] = []
    if a.out.exists():
        runs = json.loads(a.out.read_text()).get("runs", [])
    for r in range(a.runs):
        for carrier, inflight in variants:
            print(f"run {r + 1} {carrier}:{inflight} load {os.getloadavg()[0]:.2f}", flush=True)
            res = one_run(carrier, inflight, a.hosts, writers, a.seconds, a.profile, f"{a.tag}{r + 1}", a.native)
            res["tag"] = a.tag
            res["hosts"] = a.hosts
            runs.append(res)
            a.out.write_text(json.dumps({"runs": runs}, indent=1))
    new = [x for x in runs if x["tag"] == a.tag]
    for carrier, inflight in variants:
        for w in writers:
            rows = [row for x in new if (x["carrier"], x["seq_inflight"]) == (carrier, inflight)
                    for row in x["rows"] if row["writers_per_host"] == w]
            loads = [round(x["load_1min_before"], 1) for x in new
                     if (x["carrier"], x["seq_inflight"]) == (carrier, inflight)]
            if rows:
                print(f"{carrier}:{inflight} w={w}: median writes/s "
                      f"{statistics.median(r['writes_per_s'] for r in rows):.0f}, p50 "
                      f"{statistics.median(r['p50_ms'] for r in rows):.1f} ms, loads {loads}")


if __name__ == "__main__":
    main()
