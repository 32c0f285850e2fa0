"""The dashboard's web server (aiohttp): the page, its static files, and one WebSocket per open page.

    GET /               the page (haa/lab/dashboard/static/index.html; app.js and app.css beside it)
    GET /static/...     the page's files — everything the page loads comes from here, nothing from elsewhere
    GET /ws             WebSocket: the server pushes JSON messages (below); the page may ask
                        {"op": "object", "key": K} and gets {"type": "object", "object": {...}}
                        (the DDB browser's summary of one object)
    GET /api/state      a JSON summary (agents, hosts, DDB seq, map version, sources): for scripts and tests
    GET /api/object?key=K   the summary of one DDB object

Messages (each a JSON object with "type"): "hello" (cluster, agent types, server time), "hosts" (every host
and its state, the group, each source's state), "agents" (every agent: type, host, state, CPU, message rates,
parent), "map" (the occupancy grid, base64 uint8 cells), "overlay" (estimates, paths, landmarks, targets,
particles, mission status, transcript), "truth" (true poses), "arena" (true obstacles and landmarks), "ddb"
(the DDB browser's entries: "full" or "set"/"del"), "timeline" (agent events, each with an increasing "i").

A new page gets everything at once; after that, one loop sends every page what changed (`Hub.take`), at most
every `tick` seconds (50 ms) and at once when a source wakes it — so a commit reaches the page within one
mirror hop, one tick and the page's own drawing (docs/dashboard.md has the measured latency).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from haa.lab.dashboard.sources import Changes, Hub

log = logging.getLogger("haa.lab.dashboard")

STATIC = Path(__file__).with_name("static")
#: the broadcast loop's minimum period, seconds (changes within it are sent together)
TICK = 0.05
#: a page that cannot take a message within this many seconds is dropped
SEND_TIMEOUT = 5.0


def _dump(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=str)


class DashboardServer:
    """Serves the page and pushes `Hub` changes to every open page. Runs on the caller's asyncio loop."""

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 0, tick: float = TICK) -> None:
        self.hub = hub
        self.host = host
        self.port = port
        self.tick = tick
        self.clients: set[web.WebSocketResponse] = set()
        self.runner: web.AppRunner | None = None
        self.url = ""
        self.sent = 0
        self._wake: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> str:
        loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        wake = self._wake

        def waker() -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile (shutting down)
                loop.call_soon_threadsafe(wake.set)

        self.hub.set_waker(waker)
        self.hub.take()  # what changed before: a page gets everything when it connects anyway
        app = web.Application()
        app.router.add_get("/", self.index)
        app.router.add_get("/ws", self.websocket)
        app.router.add_get("/api/state", self.api_state)
        app.router.add_get("/api/object", self.api_object)
        app.router.add_static("/static/", STATIC, append_version=False)
        app.on_response_prepare.append(self._no_cache)
        self.runner = web.AppRunner(app, access_log=None)
        await self.runner.setup()
        site = web.TCPSite(self.runner, self.host, self.port)
        await site.start()
        server = site._server
        sockets = getattr(server, "sockets", None) or []
        port = sockets[0].getsockname()[1] if sockets else self.port
        shown = f"[{self.host}]" if ":" in self.host else self.host
        self.url = f"http://{shown}:{port}/"
        self._task = asyncio.create_task(self._broadcast())
        return self.url

    async def stop(self) -> None:
        self.hub.set_waker(lambda: None)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for ws in list(self.clients):
            with contextlib.suppress(Exception):
                await ws.close()
        if self.runner is not None:
            await self.runner.cleanup()

    @staticmethod
    async def _no_cache(request: web.Request, response: web.StreamResponse) -> None:
        response.headers["Cache-Control"] = "no-store"

    # ------------------------------------------------------------------ HTTP
    async def index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def api_state(self, request: web.Request) -> web.Response:
        hub = self.hub
        with hub.lock:
            mv = hub.mirror.get("slam/map")
            state = {"cluster": hub.cluster, "agents": len(hub.agents), "hosts": hub.hosts, "group": hub.group,
                     "ddb_seq": hub.mirror.seq, "ddb_objects": hub.mirror.ddb.size if hub.mirror.ddb else 0,
                     "map_version": mv.version if mv is not None else None, "mirror_host": hub.mirror_host,
                     "sources": dict(hub.sources), "timeline_events": len(hub.timeline), "pages": len(self.clients),
                     "messages_sent": self.sent}
        return web.json_response(state)

    async def api_object(self, request: web.Request) -> web.Response:
        key = request.query.get("key", "")
        with self.hub.lock:
            return web.json_response(self.hub.mirror.object_summary(key))

    # ------------------------------------------------------------------ WebSocket
    async def websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=1 << 20)
        await ws.prepare(request)
        for text in self.full():
            await ws.send_str(text)
        self.clients.add(ws)
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                try:
                    req = json.loads(msg.data)
                except ValueError:
                    continue
                if isinstance(req, dict) and req.get("op") == "object":
                    with self.hub.lock:
                        summary = self.hub.mirror.object_summary(str(req.get("key", "")))
                    await ws.send_str(_dump({"type": "object", "object": summary}))
        finally:
            self.clients.discard(ws)
        return ws

    # ------------------------------------------------------------------ messages
    def full(self) -> list[str]:
        """Everything, for a page that just connected."""
        hub = self.hub
        with hub.lock:
            m = hub.mirror
            msgs: list[dict[str, Any]] = [
                {"type": "hello", "cluster": hub.cluster, "agent_types": hub.agent_types, "now": time.time()},
                self._hosts_msg(),
                {"type": "agents", "agents": hub.agents, "now": time.time()},
                {"type": "ddb", "full": True, "seq": m.seq, "entries": m.ddb_entries()},
                {"type": "overlay", **m.overlay_view()},
                {"type": "timeline", "full": True, "t0": hub.t0, "events": hub.timeline},
            ]
            mv = m.map_view()
            if mv is not None:
                msgs.append({"type": "map", **mv})
            if hub.truth:
                msgs.append({"type": "truth", **hub.truth})
            if hub.arena:
                msgs.append({"type": "arena", **hub.arena})
        return [_dump(x) for x in msgs]

    def _hosts_msg(self) -> dict[str, Any]:
        hub = self.hub
        return {"type": "hosts", "hosts": hub.hosts, "group": hub.group, "view": hub.mirror.view,
                "sources": hub.sources, "mirror_host": hub.mirror_host}

    def delta(self, c: Changes) -> list[str]:
        """What changed, for the pages already open."""
        hub = self.hub
        msgs: list[dict[str, Any]] = []
        with hub.lock:
            m = hub.mirror
            if c.map:
                mv = m.map_view()
                if mv is not None:
                    msgs.append({"type": "map", **mv})
            if c.overlay:
                msgs.append({"type": "overlay", **m.overlay_view()})
            if c.ddb_all:
                msgs.append({"type": "ddb", "full": True, "seq": m.seq, "entries": m.ddb_entries()})
            elif c.ddb_keys:
                set_, del_ = [], []
                for k in sorted(c.ddb_keys):
                    e = m.entry(k)
                    if e is None:
                        del_.append(k)
                    else:
                        set_.append(e)
                msgs.append({"type": "ddb", "seq": m.seq, "set": set_, "del": del_})
            if c.agents:
                msgs.append({"type": "agents", "agents": hub.agents, "now": time.time()})
            if c.hosts:
                msgs.append(self._hosts_msg())
            if c.truth:
                msgs.append({"type": "truth", **hub.truth})
            if c.arena:
                msgs.append({"type": "arena", **hub.arena})
            if c.timeline:
                msgs.append({"type": "timeline", "t0": hub.t0, "events": c.timeline})
        return [_dump(x) for x in msgs]

    async def _broadcast(self) -> None:
        assert self._wake is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            c = self.hub.take()
            if c and self.clients:
                texts = await asyncio.to_thread(self.delta, c)  # map and overlay building stays off the loop
                await asyncio.gather(*(self._send(ws, texts) for ws in list(self.clients)))
            await asyncio.sleep(self.tick)

    async def _send(self, ws: web.WebSocketResponse, texts: list[str]) -> None:
        try:
            for t in texts:
                await asyncio.wait_for(ws.send_str(t), SEND_TIMEOUT)
                self.sent += 1
        except (TimeoutError, ConnectionError, RuntimeError):
            self.clients.discard(ws)
            with contextlib.suppress(Exception):
                await ws.close()


async def serve(hub: Hub, host: str, port: int, on_ready: Any = None, stop: asyncio.Event | None = None) -> None:
    """Run the server until `stop` is set (or the task is cancelled); `on_ready(url)` once it listens."""
    srv = DashboardServer(hub, host, port)
    url = await srv.start()
    if on_ready is not None:
        on_ready(url)
    try:
        if stop is None:
            await asyncio.Event().wait()
        else:
            await stop.wait()
    finally:
        await srv.stop()
