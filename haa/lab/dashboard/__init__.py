"""The monitoring dashboard (issue 19 §1; thesis §6.1.4, Table 6.1-1 "Graphical User Interface"): a web page,
served by `haactl dashboard`, that shows a running cluster live in four views —

1. the map: the team's occupancy grid with estimated poses and paths, particle clouds, landmark estimates,
   targets, and (for display only, from haa-sim's ground truth) the true poses, landmarks and obstacles;
2. the agent distribution: a timeline per host of every agent it ran, coloured by state (spawning, active,
   freezing, thawing, crashed, recovering), the real-time version of the thesis' allocation figures;
3. the agent hierarchy: the parentage tree with each agent's type, host, state, CPU and message rates;
4. the DDB browser: every object by parentage (an avatar's objects under the avatar), with a summary of the
   selected one.

How it is put together (docs/dashboard.md):

* `haa.lab.dashboard.sources` — threads that read the cluster into one `Hub`: the DDB from one host's mirror
  stream (thesis AgentMirror), the agents by polling every host's AgentList each second, the timeline from
  the hosts' persisted records and their AgentEvents streams, the ground truth from haa-sim;
* `haa.lab.dashboard.model` — the dashboard's own DDB replica and the JSON views the page draws (no I/O);
* `haa.lab.dashboard.server` — the aiohttp server: the page, its static files, and a WebSocket per page over which
  every change is pushed;
* `haa.lab.dashboard.static` — the page itself: plain HTML, CSS and JavaScript with no build step and nothing
  loaded from anywhere but this server;
* `haa.lab.dashboard.browser` — a small headless-Chromium driver (DevTools protocol) used by the tests and the
  latency measurement.

`run(backend, port)` runs all of it until Ctrl-C; `haactl dashboard` only parses arguments and calls it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from haa.cluster.backend import Backend
from haa.lab.dashboard.server import serve
from haa.lab.dashboard.sources import Hub, SimTarget, start_sources


def run(backend: Backend, port: int = 8765, bind: str = "127.0.0.1", host: str | None = None,
        sim: SimTarget | None = None, truth: bool = True, on_ready: Callable[[str], None] | None = None) -> None:
    """Serve the dashboard of `backend`'s cluster on `bind:port` until interrupted (KeyboardInterrupt).
    `host`: follow this host's mirror stream (default: the first alive member); `sim`: the haa-sim to show the
    ground truth of (default: the local cluster's mission, else `mission/params`); `truth=False`: none."""
    hub = Hub(backend.describe())
    srcs = start_sources(hub, backend, host=host, sim=sim, truth=truth)
    try:
        asyncio.run(serve(hub, bind, port, on_ready=on_ready))
    finally:
        for s in srcs:
            s.stop()
        for s in srcs:
            s.join(2.0)
