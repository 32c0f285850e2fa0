"""`haactl bench ddb`: does batching DDB operations into one OAC transaction pay? Real processes.

A group of `hosts` membership-mode `haa-hostd` processes on loopback (h1-h3 core). For each batch size
(ops per `DdbWrite`, i.e. per OAC transaction) and number of concurrent clients, every client writes
batches of `put(key, blob, 64 bytes)` through its own host (client i uses host i mod hosts) for
`seconds`, each waiting for its previous write's reply. Reported: committed ops/s and batches/s, and the
write latency (request -> committed and applied on the client's host) p50 / p99. At the end every
replica's content hash must be equal (the run fails otherwise).
"""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from haa.hostd import ddb
from haactl.ap2 import CORE
from haactl.local import MemberHost, free_port, wait_for


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
) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="haa-ddb-") as tmp:
        base = root or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        token = "ddb-bench-" + str(time.time_ns())
        (base / "token").write_text(token + "\n")
        names = [f"h{i}" for i in range(1, hosts + 1)]
        ports = {n: free_port() for n in names}
        core = {n: f"127.0.0.1:{ports[n]}" for n in names[:CORE]}
        group = [MemberHost(n, ports[n], core, base, token, ["--no-agents"]) for n in names]
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
            # (clients, ops per request, spread over the hosts?) — the last: many clients of one host, the
            # case group commit is for (agents writing through their host)
            cases = [(c, b, True) for c in clients for b in batch_sizes] + [(crowd, 1, False)]
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
            wait_for(lambda: len({h.client.status().ddb_hash for h in group}) == 1, 30, "equal replicas at the end")
        finally:
            for h in group:
                h.kill()
                h.client.close()
        return rows


def markdown_table(rows: list[dict[str, Any]]) -> str:
    out = [
        "| hosts | clients | writing through | ops per request | ops/s | requests/s | latency p50 | p99 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['hosts']} | {r['clients']} | {r['through']} | {r['batch']} | {r['ops_per_s']:.0f} | "
            f"{r['requests_per_s']:.0f} | "
            f"{r['p50_ms']:.1f} ms | {r['p99_ms']:.1f} ms |"
        )
    return "\n".join(out)
