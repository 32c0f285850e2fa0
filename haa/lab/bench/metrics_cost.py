"""What Prometheus metrics cost an idle local cluster (issue 19 §4; docs/metrics.md, "Cost").

    .venv/bin/python -m haa.lab.bench.metrics_cost [--hosts 10] [--window 20] [--period 1]

Brings up an idle cluster of N membership-mode hosts (haa.cluster.local_backend, every host with its /metrics)
and measures, over `window` seconds each, the CPU of every haa-hostd process (psutil: user + system):

1. metrics served, nobody scraping;
2. every host scraped every `period` seconds (Prometheus' default is 15 s: this is 15x that);
3. the same cluster brought up again without metrics (no --metrics-port).

It also times single scrapes (wall time of the HTTP GET; the CPU its collectors took on the host's event loop,
`haa_metrics_scrape_seconds`; the host's whole CPU per scrape over 100 in a row, less its idle use) and prints
one JSON object. A benchmark: it measures and never fails on a number.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.backend import wait_until
from haa.cluster.local_backend import LocalBackend


def cpu_of(pids: list[int]) -> float:
    t = 0.0
    for pid in pids:
        try:
            c = psutil.Process(pid).cpu_times()
            t += c.user + c.system
        except psutil.NoSuchProcess:
            pass
    return t


def window(pids: list[int], seconds: float) -> float:
    """% of one core used by the processes together over `seconds`."""
    a, t0 = cpu_of(pids), time.monotonic()
    time.sleep(seconds)
    return 100.0 * (cpu_of(pids) - a) / (time.monotonic() - t0)


def get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.read()


def cluster(root: Path, hosts: int, metrics: bool) -> LocalBackend:
    b = LocalBackend(root)
    if not metrics:  # as before issue 19: no --metrics-port
        spawn = b._spawn

        def no_metrics(name: str) -> None:
            b._rec(name).pop("metrics_port", None)
            spawn(name)

        b._spawn = no_metrics  # type: ignore[method-assign]
    names = b.up(hosts, min(3, hosts))
    wait_until(lambda: b.formation(names), 120, what="the group to form")
    return b


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hosts", type=int, default=10)
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--settle", type=float, default=10.0)
    ap.add_argument("--period", type=float, default=1.0)
    a = ap.parse_args()
    out: dict[str, Any] = {"hosts": a.hosts, "window_s": a.window, "scrape_period_s": a.period,
                           "cpus": psutil.cpu_count()}
    with tempfile.TemporaryDirectory() as tmp:
        b = cluster(Path(tmp) / "with", a.hosts, True)
        try:
            time.sleep(a.settle)
            hosts = b.hosts()
            pids = [h.pid for h in hosts if h.pid]
            urls = [h.metrics_url for h in hosts]
            out["busy_machine_pct"] = psutil.cpu_percent(1.0)
            out["served_not_scraped_pct_core"] = round(window(pids, a.window), 2)
            stop = threading.Event()

            def scraper() -> None:
                while not stop.is_set():
                    t0 = time.monotonic()
                    for u in urls:
                        get(u)
                    stop.wait(max(0.0, a.period - (time.monotonic() - t0)))

            th = threading.Thread(target=scraper, daemon=True)
            th.start()
            out["scraped_pct_core"] = round(window(pids, a.window), 2)
            stop.set()
            th.join()
            walls, cpus, sizes = [], [], []
            for _ in range(5):
                for u in urls:
                    t0 = time.perf_counter()
                    body = get(u)
                    walls.append(time.perf_counter() - t0)
                    sizes.append(len(body))
                    for line in body.decode().splitlines():
                        if line.startswith("haa_metrics_scrape_seconds "):
                            cpus.append(float(line.split()[1]))
            # the whole cost of a scrape to one host (its loop's share + the server thread's encoding): its CPU over
            # 100 back-to-back scrapes, less what it uses idle over the same time
            idle_per_s = out["served_not_scraped_pct_core"] / 100.0 / len(pids)
            t0, c0 = time.monotonic(), cpu_of(pids[:1])
            for _ in range(100):
                get(urls[0])
            spent = cpu_of(pids[:1]) - c0 - idle_per_s * (time.monotonic() - t0)
            out["scrape_host_cpu_ms"] = round(1000 * max(0.0, spent) / 100, 3)
            out["scrape_wall_ms_median"] = round(1000 * statistics.median(walls), 2)
            out["scrape_wall_ms_p90"] = round(1000 * statistics.quantiles(walls, n=10)[-1], 2)
            out["scrape_render_cpu_ms_median"] = round(1000 * statistics.median(cpus), 3)
            out["scrape_bytes_median"] = int(statistics.median(sizes))
        finally:
            b.down(grace=2.0, purge=True)
        b = cluster(Path(tmp) / "without", a.hosts, False)
        try:
            time.sleep(a.settle)
            pids = [h.pid for h in b.hosts() if h.pid]
            out["without_metrics_pct_core"] = round(window(pids, a.window), 2)
        finally:
            b.down(grace=2.0, purge=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
