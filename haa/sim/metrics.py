"""The Prometheus metrics of one haa-sim, read from its `SimCore` and `SimService` at scrape time.

`sim_registry(core, service, loop)` returns a fresh `CollectorRegistry` holding a `SimCollector` (run on the
simulator's event loop by `haa.metrics.http.OnLoop`) and prometheus_client's `ProcessCollector` (the simulator's
CPU and memory). Metrics (docs/metrics.md):

* `haa_sim_time_seconds` — simulated time; `haa_sim_speed_ratio` — simulated seconds per wall second achieved
  lately (SimInfo.achieved_speed), `haa_sim_speed_target_ratio` — the `--speed` asked for;
* `haa_sim_avatars{status,type}` — avatars by status (active, retired, crashed) and type; `haa_sim_bumps_total
  {avatar}` — contacts each avatar began; `haa_sim_collectables{state}`;
* `haa_sim_subscribers{stream}` — open odometry, sonar, action and event streams;
* `haa_sim_dropped_total` — readings dropped because a subscriber's queue was full;
* `haa_sim_rejected_total{reason}` — calls refused (unauthenticated, malformed) and handler errors;
* `haa_sim_truth_calls_total{caller,method}` — ground-truth and Detect calls by caller (the team's agents must
  make none: issue 15).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, ProcessCollector
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from haa.metrics.http import OnLoop

if TYPE_CHECKING:
    import asyncio


class SimCollector:
    """See the module docstring. `core` is haa-sim's `haa.sim.simcore.SimCore`, `service` its
    `haa.sim.servicer.SimService` (typed Any, as haa.sim.service, which imports this module, passes them)."""

    def __init__(self, core: Any, service: Any) -> None:
        self.core = core
        self.service = service

    def collect(self) -> Iterator[Metric]:
        core, svc = self.core, self.service
        w = core.world
        yield GaugeMetricFamily("haa_sim_time_seconds", "simulated time", value=w.time)
        yield GaugeMetricFamily("haa_sim_speed_ratio", "simulated seconds per wall second, achieved lately",
                                value=core.achieved_speed())
        yield GaugeMetricFamily("haa_sim_speed_target_ratio", "simulated seconds per wall second asked for "
                                "(--speed; 0 in step mode)", value=core.speed if core.mode == "realtime" else 0.0)
        by: Counter[tuple[str, str]] = Counter((av.status, av.kind) for av in w.avatars.values())
        g = GaugeMetricFamily("haa_sim_avatars", "avatars by status and type", labels=["status", "type"])
        for (status, kind), n in sorted(by.items()):
            g.add_metric([status, kind], n)
        yield g
        bumps = CounterMetricFamily("haa_sim_bumps", "contacts the avatar began (walls, obstacles, avatars)",
                                    labels=["avatar"])
        for aid, av in sorted(w.avatars.items()):
            bumps.add_metric([aid], av.bumps)
        yield bumps
        states: Counter[str] = Counter(c.state for c in w.collectables.values())
        g = GaugeMetricFamily("haa_sim_collectables", "collectables by where they are", labels=["state"])
        for s, n in sorted(states.items()):
            g.add_metric([s], n)
        yield g
        subs = GaugeMetricFamily("haa_sim_subscribers", "open streams by kind", labels=["stream"])
        subs.add_metric(["odometry"], len(core.odo_subs))
        subs.add_metric(["sonar"], len(core.sonar_subs))
        subs.add_metric(["action"], len(core.watches))
        subs.add_metric(["events"], len(core.event_subs))
        yield subs
        yield CounterMetricFamily("haa_sim_dropped", "readings dropped: a subscriber's queue was full",
                                  value=core.dropped)
        rej = CounterMetricFamily("haa_sim_rejected", "calls refused or failed", labels=["reason"])
        rej.add_metric(["unauthenticated"], svc.rejected)
        rej.add_metric(["malformed"], svc.malformed)
        rej.add_metric(["error"], svc.errors)
        yield rej
        tc = CounterMetricFamily("haa_sim_truth_calls", "ground-truth and Detect calls by caller and method",
                                 labels=["caller", "method"])
        for key, n in sorted(svc.truth_calls.items()):
            caller, _, method = key.rpartition("/")
            tc.add_metric([caller, method], n)
        yield tc


def sim_registry(core: Any, service: Any, loop: asyncio.AbstractEventLoop) -> CollectorRegistry:
    """A fresh registry with the simulator's collector (run on `loop`, the simulator's) and the process collector."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(OnLoop(loop, [SimCollector(core, service)]))
    ProcessCollector(registry=reg)
    return reg
