"""DDB write throughput and latency through OAC (thesis §4.7; `haactl bench ddb`), real processes.

A group of `hosts` membership-mode `haa-hostd` processes on loopback (h1-h3 core).

* Client loads (`DdbWrite` RPCs from this process): for each batch size (ops per request) and number of
  concurrent clients, every client writes batches of `put(key, blob, 64 bytes)` through its own host (client
  i uses host i mod hosts) for `seconds`, each waiting for its previous write's reply.
* All writing (issue 14, a mission's load: every host writes at once): every host runs `writers` concurrent
  writers inside itself (`DdbLoad`), each awaiting single-put writes, all starting at the same instant. A
  Python client issuing thousands of RPCs a second would measure itself, and a mission's agents write
  through their host, not through the control API. Reported: committed writes/s across the group, global
  transactions (OACs) per second, write latency p50 / p99.

Every load runs with the sequencer (docs/oac.md, "The sequencer": writes forwarded to the leader and batched)
and, for the comparison, without it (every host proposes its own group-committed batches: Alg. 3 as printed).
At the end every replica's content hash must be equal (the run fails otherwise). `run_ddb_bench` returns one
row dict per load (`load`: "clients" or "all writing"), the rows of bench-results/ddb.json.
"""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from haa.cluster.hostprocs import MemberHost, member_group, wait_for
from haa.core.ddb import ops as ddb
from haa.lab.experiments.ap2 import CORE


def _pct(xs: list[float], q: float) -> float:
    if not xs:
        return 0.0
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def run_ddb_bench(
    hosts: int = 5,
    batch_sizes: tuple[int, ...] = (1, 10, 100),
    clients: tuple[int, ...] = (1, 4),
    crowd: int = 16,
    seconds: float = 5.0,
    root: Path | None = None,
    log: Any = print,
    writers: tuple[int, ...] = (1, 8, 32),
    sequencer: tuple[bool, ...] = (True, False),
    client_loads: bool = True,
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for seq in sequencer:
        log(f"--- {'with' if seq else 'without'} the sequencer")
        rows += _run_group(hosts, batch_sizes if client_loads else (), clients, crowd, seconds, root, log,
                           writers, seq)
    return rows


def _run_group(
    hosts: int,
    batch_sizes: tuple[int, ...],
    clients: tuple[int, ...],
    crowd: int,
    seconds: float,
    root: Path | None,
    log: Any,
    writers: tuple[int, ...],
    sequencer: bool,
) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="haa-ddb-") as tmp:
        base = (root / ("seq" if sequencer else "noseq")) if root else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        group = member_group(base, hosts, f"membership:\n  sequencer: {'true' if sequencer else 'false'}\n", CORE,
                             "ddb-bench")
        names = [h.name for h in group]
        rows: list[dict[str, Any]] = []
        try:
            for h in group:
                h.start()
            wait_for(
                lambda: all(sorted(h.client.status().members) == sorted(names) for h in group),
                60,
                f"a group of {hosts}",
            )
            value = bytes(64)
            # (clients, ops per request, spread over the hosts?) — the last: many clients of one host (agents
            # writing through their host)
            cases = [(c, b, True) for c in clients for b in batch_sizes] + ([(crowd, 1, False)] if batch_sizes else [])
            for run_id, (n_clients, size, spread) in enumerate(cases):
                lat: list[list[float]] = [[] for _ in range(n_clients)]
                failed = [0] * n_clients
                stop = time.monotonic() + seconds

                def client(
                    i: int,
                    spread: bool = spread,
                    run: int = run_id,
                    size: int = size,
                    stop: float = stop,
                    lat: list[list[float]] = lat,
                    failed: list[int] = failed,
                ) -> None:
                    c = group[i % hosts if spread else 0].client
                    k = 0
                    while time.monotonic() < stop:
                        ops = [ddb.put(f"b{run}/c{i}/{k + j}", "blob", value) for j in range(size)]
                        k += size
                        t0 = time.perf_counter()
                        r = c.ddb_write(ops, timeout=30)
                        if r.committed:
                            lat[i].append(time.perf_counter() - t0)
                        else:
                            failed[i] += 1

                t0 = time.perf_counter()
                threads = [threading.Thread(target=client, args=(i,)) for i in range(n_clients)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                wall = time.perf_counter() - t0
                all_lat = [x for xs in lat for x in xs]
                row = {
                    "hosts": hosts,
                    "sequencer": sequencer,
                    "load": "clients",
                    "clients": n_clients,
                    "batch": size,
                    "through": "every host" if spread else "one host",
                    "requests": len(all_lat),
                    "failed": sum(failed),
                    "ops_per_s": len(all_lat) * size / wall,
                    "requests_per_s": len(all_lat) / wall,
                    "p50_ms": _pct(all_lat, 0.5) * 1e3,
                    "p99_ms": _pct(all_lat, 0.99) * 1e3,
                    "mean_ms": statistics.fmean(all_lat) * 1e3 if all_lat else 0.0,
                }
                rows.append(row)
                log(
                    f"clients={n_clients} ({row['through']}) batch={size}: {row['ops_per_s']:.0f} ops/s, "
                    f"{row['requests_per_s']:.0f} tx/s, p50 {row['p50_ms']:.1f} ms, p99 {row['p99_ms']:.1f} ms"
                )
            for w in writers:
                rows.append(_all_writing(group, w, seconds, sequencer, log))
            wait_for(lambda: len({h.client.status().ddb_hash for h in group}) == 1, 30, "equal replicas at the end")
        finally:
            for h in group:
                h.kill()
                h.client.close()
        return rows


def _all_writing(group: list[MemberHost], writers: int, seconds: float, sequencer: bool, log: Any) -> dict[str, Any]:
    """Every host writes at once from inside itself (`DdbLoad`), `writers` concurrent writers each."""
    for h in group:
        h.client.latencies(reset=True)
    msgs0 = _oac_messages(group)
    start_at = time.time() + 1.0
    replies: dict[str, Any] = {}
    errors: list[str] = []

    def one(h: MemberHost) -> None:
        try:
            replies[h.name] = h.client.ddb_load(writers, seconds, 64, f"all/{writers}/{h.name}", start_at)
        except Exception as e:  # reported below: a host that could not run the load fails the row
            errors.append(f"{h.name}: {e}")

    threads = [threading.Thread(target=one, args=(h,)) for h in group]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise RuntimeError("DdbLoad failed: " + "; ".join(errors))
    lat = [x for r in replies.values() for x in r.latencies]
    elapsed = max(r.elapsed for r in replies.values())
    committed = sum(r.committed for r in replies.values())
    oacs = statistics.median(r.global_applied for r in replies.values())
    # the OACs themselves: propose -> decide at their proposers (with the sequencer: the leader's batches), and
    # OAC messages between hosts per OAC (each host's share of the load's OACs also counts writes that were
    # still in flight at the end: a few percent)
    p2d = [x for h in group for x in h.client.latencies(reset=True).propose_to_decide]
    msgs = _oac_messages(group) - msgs0
    row = {
        "hosts": len(group),
        "sequencer": sequencer,
        "load": "all writing",
        "writers_per_host": writers,
        "requests": committed,
        "failed": sum(r.failed for r in replies.values()),
        "writes_per_s": committed / elapsed,
        "oacs_per_s": oacs / elapsed,
        "writes_per_oac": committed / oacs if oacs else 0.0,
        "p50_ms": _pct(lat, 0.5) * 1e3,
        "p99_ms": _pct(lat, 0.99) * 1e3,
        "mean_ms": statistics.fmean(lat) * 1e3 if lat else 0.0,
        "oac_p50_ms": _pct(p2d, 0.5) * 1e3,
        "oac_p99_ms": _pct(p2d, 0.99) * 1e3,
        "oacs_measured": len(p2d),
        "msgs_per_oac": msgs / len(p2d) if p2d else 0.0,
        "formula_n2_4n_minus_6": len(group) ** 2 + 4 * len(group) - 6,
    }
    log(
        f"all writing, {writers} writers per host: {row['writes_per_s']:.0f} writes/s, {row['oacs_per_s']:.0f} "
        f"OACs/s ({row['writes_per_oac']:.1f} writes each), p50 {row['p50_ms']:.1f} ms, p99 {row['p99_ms']:.1f} ms; "
        f"OAC p50 {row['oac_p50_ms']:.1f} ms, {row['msgs_per_oac']:.0f} msgs/OAC"
    )
    return row


def _oac_messages(group: list[MemberHost]) -> int:
    return sum(v for h in group for k, v in h.client.status().counters.values.items() if k.startswith("tx_msgs.oac_"))
