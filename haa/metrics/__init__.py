"""Prometheus metrics of haa-hostd and haa-sim (issue 19 §4; docs/metrics.md).

Each daemon started with `--metrics-port P` serves `GET /metrics` (the Prometheus text format, through the
`prometheus_client` library) on its own HTTP port, bound to the host part of its `--listen` address. Nothing is
counted for the metrics: at each scrape, custom collectors read what the daemon already keeps — the runtime's
counters and latency samples, the membership state, the replicated agent table, the agent supervisor's
measurements, the DDB replica, haa-sim's world — the same sources the statistics sampler (haa.hostd.sampler)
writes to `stats.jsonl`. The sans-I/O core modules (haa.core.ufd.ufd, oac, core, membership, ddb, allocation,
transfer, recovery, agentnode) do not know about any of it.

The collectors live next to what they read; this package holds what they share and imports no other HAA
package (it sits below haa.hostd and haa.sim):

* `haa.hostd.metrics` — `HostCollector`: the metrics of one haa-hostd (`host_registry(rt, loop)`);
* `haa.sim.metrics` — `SimCollector`: the metrics of one haa-sim (`sim_registry(core, service, loop)`);
* `haa.metrics.http` — `MetricsServer`: `/metrics` served by prometheus_client's own HTTP server from a thread,
  and `OnLoop`, which runs the collectors on the daemon's event loop at each scrape, so that they read the
  daemon's structures from the thread that changes them (no locks, no torn reads);
* `haa.metrics.latency` — cumulative histograms folded from the daemons' bounded buffers of latency samples.

Each daemon has its own `CollectorRegistry` (a test may run several hosts in one process); the registry also
holds prometheus_client's `ProcessCollector` (CPU seconds, resident memory, open files of the process).
"""

from __future__ import annotations

from haa.metrics.http import MetricsServer, metrics_bind_host

__all__ = ["MetricsServer", "metrics_bind_host"]
