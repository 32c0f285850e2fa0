"""Experiment AP-1 (thesis §7.2.1): ordered atomic commit latency and message count vs. participants.

Starts real `haa-hostd` processes on loopback (one per participant, up to 10), and for each participant
count n = 2..10 runs four loads on participants h1..hn:

* paced: h1 proposes one transaction at a time and waits `gap` seconds after each, so that the n^2
  rebroadcasts of one transaction are over before the next starts: the latency of the protocol itself;
* back-to-back: h1 proposes the next transaction as soon as the previous one is delivered: the machine is
  busy with the previous rebroadcasts (on 2 cores this measures CPU saturation, not the protocol);
* all-proposing: all n participants propose at once, one transaction in flight each (a mission's DDB
  writes from every host);
* concurrent: all n participants propose at once, `--concurrency` transactions in flight each: order
  conflicts, the l. 37 gate, and the decide -> deliver wait the thesis measured under live load.

Measured: propose -> decide on the proposer's clock (from each Propose reply), decide -> deliver on every
participant's clock (Latencies RPC), and OAC messages sent between hosts per transaction (the sum over all
hosts of the `tx_msgs.oac_*` transport counters, divided by the transactions). At the end of each step every
participant's deliveries of that step are read back and hashed (`step_deliveries`): `same_delivered_hash` says
that every participant delivered exactly the step's committed transactions, in one order.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import math
import statistics
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from haa.cluster.hostprocs import LocalCluster


def percentile(xs: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (q in [0, 100]); NaN for no samples."""
    if not xs:
        return math.nan
    s = sorted(xs)
    k = (len(s) - 1) * q / 100.0
    lo = math.floor(k)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)


def summarize_ms(xs: Sequence[float]) -> dict[str, float]:
    return {
        "p50": percentile(xs, 50) * 1e3,
        "p90": percentile(xs, 90) * 1e3,
        "p99": percentile(xs, 99) * 1e3,
        "mean": (statistics.fmean(xs) * 1e3) if xs else math.nan,
        "n": float(len(xs)),
    }


def oac_messages_sent(cluster: LocalCluster, names: Sequence[str]) -> int:
    total = 0
    for n in names:
        for k, v in cluster[n].status().counters.values.items():
            if k.startswith("tx_msgs.oac_"):
                total += v
    return total


def _quiesce(cluster: LocalCluster, names: Sequence[str], timeout: float = 10.0) -> None:
    """Wait until no host has an open transaction (every rebroadcast of the last step has arrived)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sts = [cluster[n].status() for n in names]
        if all(s.active_transactions == 0 and s.decided_transactions == 0 for s in sts):
            return
        time.sleep(0.02)


def step_deliveries(cluster: LocalCluster, name: str, start: int, count: int) -> tuple[int, str]:
    """(how many, hash) of the `count` transactions `name` delivered from its delivered index `start` on: the
    hash covers each one's id and payload in delivery order, so two hosts that delivered the same transactions
    in the same order during a step have the same hash whatever they delivered before it (a host's cumulative
    `delivered_hash` also covers the steps it was no participant of)."""
    h = hashlib.sha256()
    n = 0
    if count:
        it = cluster[name].client.deliveries(start, timeout=30)
        try:
            for d in it:
                h.update(f"{d.id.host}.{d.id.incarnation}.{d.id.seq}|{len(d.payload)}|".encode())
                h.update(d.payload)
                n += 1
                if n == count:
                    break
        finally:
            it.cancel()
    return n, h.hexdigest()


def run_step(
    cluster: LocalCluster, names: list[str], transactions: int, mode: str, concurrency: int, gap: float = 0.02
) -> dict[str, Any]:
    for n in names:
        cluster[n].client.latencies(reset=True)
    _quiesce(cluster, names)
    start = {n: cluster[n].status().delivered for n in names}
    msgs0 = oac_messages_sent(cluster, list(cluster.hosts))
    p2d: list[float] = []
    aborted = 0
    lock = threading.Lock()

    def one(proposer: str, i: int) -> None:
        nonlocal aborted
        reply = cluster[proposer].client.propose(f"ap1-{proposer}-{i}".encode(), names, wait=True)
        with lock:
            if reply.committed:
                p2d.append(reply.propose_to_decide)
            else:
                aborted += 1

    t0 = time.perf_counter()
    if mode in ("paced", "back-to-back"):
        for i in range(transactions):
            one(names[0], i)
            if mode == "paced":
                time.sleep(gap)
    else:
        per = max(1, transactions // len(names))
        jobs: list[Callable[[], None]] = []
        for proposer in names:
            for i in range(per):
                jobs.append(functools.partial(one, proposer, i))
        in_flight = 1 if mode == "all-proposing" else concurrency  # per participant
        with ThreadPoolExecutor(max_workers=in_flight * len(names)) as pool:
            for f in [pool.submit(j) for j in jobs]:
                f.result()
    elapsed = time.perf_counter() - t0
    done = len(p2d) + aborted
    _quiesce(cluster, names)
    msgs = oac_messages_sent(cluster, list(cluster.hosts)) - msgs0
    d2d: list[float] = []
    for n in names:
        d2d.extend(cluster[n].client.latencies(reset=True).decide_to_deliver)
    # every participant delivered exactly the step's committed transactions, in one and the same order
    committed = len(p2d)
    seen = {n: step_deliveries(cluster, n, start[n], cluster[n].status().delivered - start[n]) for n in names}
    same = len({h for _, h in seen.values()}) == 1 and all(k == committed for k, _ in seen.values())
    return {
        "participants": len(names),
        "mode": mode,
        "transactions": done,
        "aborted": aborted,
        "throughput_tx_per_s": done / elapsed if elapsed > 0 else 0.0,
        "propose_to_decide_ms": summarize_ms(p2d),
        "decide_to_deliver_ms": summarize_ms(d2d),
        "messages_per_tx": msgs / done if done else math.nan,
        "formula_n2_4n_minus_6": len(names) ** 2 + 4 * len(names) - 6,
        "same_delivered_hash": same,
        "delivered_per_participant": sorted({k for k, _ in seen.values()}),
    }


#: the loads of one step, in the order they run
MODES = ("paced", "back-to-back", "all-proposing", "concurrent")


def run_ap1(
    max_hosts: int = 10,
    transactions: int = 300,
    concurrency: int = 2,
    root: Path | None = None,
    log: Callable[[str], None] = print,
    min_hosts: int = 2,
    modes: Sequence[str] = MODES,
    tls: bool = False,
) -> list[dict[str, Any]]:
    names = [f"h{i + 1}" for i in range(max_hosts)]
    with contextlib.ExitStack() as stack:
        if root is None:
            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="haa-ap1-")))
        cluster = stack.enter_context(LocalCluster(names, root, tls=tls))
        log(f"starting {max_hosts} haa-hostd processes under {root}{' (mutual TLS)' if tls else ''} ...")
        cluster.start()
        cluster.wait_trusted(timeout=60)
        log("cluster formed; warming up")
        run_step(cluster, names, 50, "back-to-back", concurrency=1)
        rows = []
        for n in range(max(2, min_hosts), max_hosts + 1):
            parts = names[:n]
            for mode in modes:
                row = run_step(cluster, parts, transactions, mode, concurrency)
                rows.append(row)
                pd, dd = row["propose_to_decide_ms"], row["decide_to_deliver_ms"]
                log(
                    f"n={n:2d} {row['mode']:12s} p50 {pd['p50']:.2f} ms p99 {pd['p99']:.2f} ms "
                    f"d->d p50 {dd['p50']:.3f} ms msgs/tx {row['messages_per_tx']:.1f}"
                )
        return rows
