"""The Foxglove bridge (issue 19 §4): a running cluster's mirror stream, live, in Foxglove or Lichtblick.

`haactl foxglove` serves the Foxglove WebSocket protocol (subprotocol `foxglove.websocket.v1`, through the
`foxglove-sdk` package) on a local port; open it in Foxglove ("Open connection" -> Foxglove WebSocket ->
ws://127.0.0.1:8765) or Lichtblick. What it publishes comes from the same sources as the dashboard
(haa.lab.dashboard.sources: one host's mirror stream into a `DdbMirror` replica, haa-sim's ground truth, the hosts'
agent timelines) and is decoded by the dashboard's own code (haa.lab.dashboard.model) — see `haa.lab.foxglove.bridge`
for the topics and docs/metrics.md for the how-to.
"""

from __future__ import annotations

from haa.lab.foxglove.bridge import FoxgloveBridge, run

__all__ = ["FoxgloveBridge", "run"]
