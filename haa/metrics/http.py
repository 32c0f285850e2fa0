"""`/metrics` over HTTP on the daemon's own asyncio loop (aiohttp), for one `CollectorRegistry`.

    GET /metrics    the registry in the Prometheus text format (OpenMetrics when the scraper asks for it)
    GET /           one line saying where the metrics are

The handler runs on the daemon's event loop: the collectors read the runtime's structures from the thread that
changes them, between two of its callbacks, so a scrape never sees a half-applied update and needs no lock.
The price is that a scrape delays the loop by its own duration (a few milliseconds: docs/metrics.md has the
measurement); each scrape's CPU time is kept in `last_scrape_s` and exported as `haa_metrics_scrape_seconds`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

from aiohttp import web
from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import choose_encoder

#: the scrape of an haa daemon: a GaugeMetricFamily reads `MetricsServer.last_scrape_s` (see `ScrapeCollector`)
SCRAPE_METRIC = "haa_metrics_scrape_seconds"


def metrics_bind_host(listen: str) -> str:
    """The address `/metrics` binds to: the host part of the daemon's `--listen` (`0.0.0.0:7000` -> `0.0.0.0`,
    `[::1]:7000` -> `::1`)."""
    host = listen.rpartition(":")[0]
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


class MetricsServer:
    """Serves `registry` on http://host:port/metrics from the running event loop (`start`, `stop`)."""

    def __init__(self, registry: CollectorRegistry, host: str, port: int) -> None:
        self.registry = registry
        self.host = host
        self.port = port
        self.scrapes = 0
        self.last_scrape_s = 0.0  # CPU seconds (thread time) of the last scrape's rendering
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        if host in ("0.0.0.0", "[::]", ""):
            host = "127.0.0.1"
        return f"http://{host}:{self.port}/metrics"

    async def start(self) -> None:
        """Bind and serve; raises OSError if the port cannot be bound. Port 0 takes any free port (`port` is
        then the one bound)."""
        app = web.Application()
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/", self._index)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, self.host, self.port)
        try:
            await site.start()
        except OSError as e:
            await runner.cleanup()
            if e.errno:  # aiohttp words it "error while attempting to bind on address ...": the plain reason
                raise OSError(e.errno, os.strerror(e.errno)) from None
            raise
        self._runner = runner
        server = site._server
        if self.port == 0 and server is not None and getattr(server, "sockets", None):
            self.port = int(server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def render(self, accept: str = "") -> tuple[bytes, str]:
        """The registry as (body, content type) for a scraper's Accept header."""
        t0 = time.thread_time()
        encoder, content_type = choose_encoder(accept)
        body = encoder(self.registry)
        self.last_scrape_s = time.thread_time() - t0
        self.scrapes += 1
        return body, content_type

    async def _metrics(self, request: web.Request) -> web.Response:
        body, content_type = self.render(request.headers.get("Accept", ""))
        resp = web.Response(body=body)
        resp.headers["Content-Type"] = content_type
        return resp

    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(text="haa metrics: GET /metrics (Prometheus text format)\n")


class ScrapeCollector:
    """`haa_metrics_scrape_seconds` (CPU time the previous scrape took to render) and
    `haa_metrics_scrapes_total` of one `MetricsServer`."""

    def __init__(self, server: MetricsServer | None = None) -> None:
        self.server = server

    def collect(self) -> Iterator[Metric]:
        s = self.server
        if s is None:
            return
        yield GaugeMetricFamily(SCRAPE_METRIC, "CPU seconds the previous scrape of this daemon took to render",
                                value=s.last_scrape_s)
        yield CounterMetricFamily("haa_metrics_scrapes", "scrapes of this daemon's /metrics", value=s.scrapes)
