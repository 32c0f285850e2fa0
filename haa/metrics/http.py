"""`/metrics` over HTTP for one daemon: prometheus_client's own exposition server, reading on the daemon's loop.

    GET /metrics    the registry in the Prometheus text format (OpenMetrics when the scraper asks for it; gzip
                    when it accepts it) — prometheus_client's WSGI app and server, a thread per request

The daemon's collectors read structures its asyncio loop changes; a scrape runs on a server thread. So the
collectors are wrapped in `OnLoop`: at a scrape, their `collect()` runs *on the loop* (scheduled with
`call_soon_threadsafe`, between two of its callbacks: no half-applied update is ever seen, no lock is needed)
and the server thread only encodes the result. A loop that does not answer within `timeout` seconds (a hung
host) fails the scrape with HTTP 500, which Prometheus records as `up == 0`. The loop's share of a scrape —
its CPU time — is kept in `OnLoop.last_s` and exported as `haa_metrics_scrape_seconds` (docs/metrics.md has
the measurement). The server costs about 1 MiB of memory (prometheus_client; wsgiref is in the standard library).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import os
import time
from collections.abc import Iterable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import start_http_server

#: a scrape waits at most this long for the daemon's loop (then HTTP 500)
LOOP_TIMEOUT = 5.0


def metrics_bind_host(listen: str) -> str:
    """The address `/metrics` binds to: the host part of the daemon's `--listen` (`0.0.0.0:7000` -> `0.0.0.0`,
    `[::1]:7000` -> `::1`)."""
    host = listen.rpartition(":")[0]
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


class OnLoop:
    """A collector that runs other collectors' `collect()` on an asyncio loop and returns their metrics to the
    calling (server) thread; counts scrapes and keeps the loop's CPU time of the last one."""

    def __init__(self, loop: asyncio.AbstractEventLoop, collectors: Iterable[Any],
                 timeout: float = LOOP_TIMEOUT) -> None:
        self.loop = loop
        self.collectors = list(collectors)
        self.timeout = timeout
        self.last_s = 0.0
        self.scrapes = 0

    def _gather(self, fut: concurrent.futures.Future[list[Metric]]) -> None:
        t0 = time.thread_time()
        try:
            fut.set_result([m for c in self.collectors for m in c.collect()])
        except BaseException as e:  # the scrape fails (HTTP 500) with it; the loop goes on
            fut.set_exception(e)
        finally:
            self.last_s = time.thread_time() - t0

    def collect(self) -> Iterator[Metric]:
        fut: concurrent.futures.Future[list[Metric]] = concurrent.futures.Future()
        self.loop.call_soon_threadsafe(self._gather, fut)
        metrics = fut.result(self.timeout)
        self.scrapes += 1
        yield from metrics
        yield GaugeMetricFamily("haa_metrics_scrape_seconds",
                                "CPU seconds this scrape took on the daemon's event loop", value=self.last_s)
        yield CounterMetricFamily("haa_metrics_scrapes", "scrapes of this daemon's /metrics", value=self.scrapes)


class MetricsServer:
    """Serves `registry` on http://host:port/metrics from a server thread (`start`, `stop`)."""

    def __init__(self, registry: CollectorRegistry, host: str, port: int) -> None:
        self.registry = registry
        self.host = host
        self.port = port
        self._server: Any = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        if host in ("0.0.0.0", "[::]", ""):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/metrics"

    def start(self) -> None:
        """Bind and serve; OSError (its `strerror` the plain reason) if the port cannot be bound. Port 0 takes any
        free port (`port` is then the one bound)."""
        try:
            self._server, _thread = start_http_server(self.port, addr=self.host, registry=self.registry)
        except OSError as e:
            raise OSError(e.errno, os.strerror(e.errno) if e.errno else str(e)) from None
        self.port = int(self._server.server_port)

    def stop(self) -> None:
        """Stop serving (waits for the server thread's poll, at most half a second)."""
        s, self._server = self._server, None
        if s is not None:
            s.shutdown()
            s.server_close()
