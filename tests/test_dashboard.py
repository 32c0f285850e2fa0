"""The monitoring dashboard (docs/dashboard.md).

* The dashboard's DDB replica follows a mirror stream (snapshot, batches) and builds the page's views.
* The server pushes a new page everything, then only what changed; the page's object summaries.
* In a real browser (headless Chromium over the DevTools protocol): a 2-host local cluster runs a short mission
  with the real team (tests/missions/dashboard.yaml); `haactl dashboard --port 0` serves it; the page's map canvas
  has drawn pixels, its agent count matches `haactl agent list`, the timeline, hierarchy and DDB browser show
  what the cluster runs, and a screenshot is kept under the test's tmp dir (its path is printed).

Without Chromium the browser test is skipped with the reason (`make setup` installs it:
scripts/browser-setup.sh); with HAA_REQUIRE_BROWSER=1 (CI) it fails instead.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from haa.core.ddb import ops as ddbops
from haa.core.ddb.ddb import Ddb
from haa.lab.dashboard.browser import Chromium, find_chromium
from haa.lab.dashboard.model import DdbMirror, avatar_of, batch_keys, map_view
from haa.lab.dashboard.server import DashboardServer
from haa.lab.dashboard.sources import Hub
from haa.pb import control_pb2 as cpb
from haa.pb import ddb_pb2

REPO = Path(__file__).resolve().parents[1]
HAACTL = [sys.executable, "-c", "from haactl.main import app; app()"]


def encoded_map(rows: int = 200, cols: int = 200, res: float = 0.1) -> bytes:
    from haa.slam.grid import GridSpec
    from haa.slam.replica import encode_map

    p = np.full((rows, cols), 0.5)
    p[:10, :] = 0.05  # the lowest rows seen free
    p[rows // 2, :] = 0.95  # a wall across the middle
    return encode_map(GridSpec(cols * res, rows * res, res), p)


class Feed:
    """A DDB and the mirror events a host would stream of it."""

    def __init__(self) -> None:
        self.db = Ddb()

    def snapshot(self) -> cpb.MirrorEvent:
        return cpb.MirrorEvent(snapshot=ddb_pb2.DdbSnapshot.FromString(self.db.snapshot()))

    def write(self, *ops) -> cpb.MirrorEvent:
        payload = ddbops.encode_batch(ops)
        self.db.apply(payload)
        return cpb.MirrorEvent(batch=cpb.MirrorBatch(ddb_seq=self.db.seq, payload=payload))


# ---------------------------------------------------------------------------------------------- the replica


def test_mirror_replica_follows_a_snapshot_then_batches():
    f = Feed()
    f.write(ddbops.put("avatars/s1", "json", {"type": "seeker", "status": "active"}))
    m = DdbMirror()
    assert m.apply(f.snapshot()) is None  # everything changed
    assert m.seq == 1 and m.json("avatars/s1")["type"] == "seeker"
    ev = f.write(ddbops.put("slam/est/s1", "json", {"x": 1.0, "y": 2.0, "theta": 0.5, "std": [0.1, 0.1, 0.05]}),
                 ddbops.put("slam/map", "blob", encoded_map()))
    assert m.apply(ev) == {"slam/est/s1", "slam/map"}
    m.apply(f.write(ddbops.put("slam/est/s1", "json", {"x": 1.5, "y": 2.0, "theta": 0.5})))
    assert m.ddb.content_hash() == f.db.content_hash()  # the same replica as the host's
    assert list(m.paths["s1"]) == [(1.0, 2.0), (1.5, 2.0)]
    ov = m.overlay_view()
    assert ov["estimates"]["s1"]["x"] == 1.5 and ov["seq"] == 3
    mv = m.map_view()
    assert (mv["w"], mv["h"], mv["res"]) == (200, 200, 0.1)
    import base64

    cells = np.frombuffer(base64.b64decode(mv["cells"]), dtype=np.uint8).reshape(200, 200)
    assert cells[0, 0] == round(0.05 * 254) and cells[100, 5] == round(0.95 * 254) and cells[150, 5] == 127
    # a batch out of step is refused (the follower resubscribes for a fresh snapshot)
    f.write(ddbops.put("x", "json", 1))
    with pytest.raises(Exception, match="after"):
        m.apply(f.write(ddbops.put("y", "json", 2)))


def test_views_and_summaries():
    assert batch_keys(ddbops.encode_batch([ddbops.put("a/b", "json", 1), ddbops.delete("c")])) == {"a/b", "c"}
    assert batch_keys(b"\xff\x00junk") == set()
    assert map_view(b"not a map") is None
    avatars = {"s1", "s2"}
    assert avatar_of("slam/raw/s1/00000017", avatars) == "s1" and avatar_of("avatars/s2", avatars) == "s2"
    assert avatar_of("bids/s2/0f3a", avatars) == "s2" and avatar_of("mission/status", avatars) == ""
    f = Feed()
    m = DdbMirror()
    m.apply(f.snapshot())
    m.apply(f.write(ddbops.put("slam/map", "blob", encoded_map(40, 30)),
                    ddbops.put("mission/status", "json", {"state": "running", "t": 12.5, "explored": 0.25}),
                    ddbops.log_append("mission/events", [json.dumps({"t": 1.0, "text": "Mission started"}).encode()]),
                    ddbops.add("stats/readings_generated", 7)))
    assert "occupancy grid 30 x 40 cells of 0.1 m" in m.object_summary("slam/map")["text"]
    assert '"explored": 0.25' in m.object_summary("mission/status")["text"]
    assert m.object_summary("stats/readings_generated")["text"] == "7"
    log = m.object_summary("mission/events")
    assert "items 0..0" in log["text"] and "Mission started" in log["items"][0]
    assert m.object_summary("nope") == {"key": "nope", "missing": True}
    assert m.overlay_view()["transcript"] == [{"t": 1.0, "text": "Mission started"}]
    assert [e[0] for e in m.ddb_entries()] == ["mission/events", "mission/status", "slam/map",
                                               "stats/readings_generated"]


# ---------------------------------------------------------------------------------------------- the server


def test_server_sends_everything_then_changes():
    async def go():
        f = Feed()
        hub = Hub("test cluster")
        hub.mirror_event(f.snapshot())
        hub.set_agents([{"id": "a1", "name": "A1", "type": "counter", "state": "active", "host": "h1", "cpu": 0.01,
                         "parent": ""}], ["counter"])
        hub.add_timeline([{"t": time.time(), "agent": "a1", "name": "A1", "event": "active", "host": "h1"}])
        srv = DashboardServer(hub, "127.0.0.1", 0)
        url = await srv.start()
        try:
            async with aiohttp.ClientSession() as s:
                async with s.get(url) as r:
                    page = await r.text()
                    assert r.status == 200 and "/static/app.js" in page and "agent-count" in page
                for name in ("app.js", "app.css"):
                    async with s.get(url + "static/" + name) as r:
                        assert r.status == 200 and len(await r.read()) > 1000
                # the page loads nothing from anywhere else
                assert not re.search(r"(src|href)=\"(https?:)?//", page)
                async with s.ws_connect(url + "ws") as ws:
                    first = {}
                    while "timeline" not in first:
                        m = json.loads((await ws.receive(timeout=5)).data)
                        first[m["type"]] = m
                    assert first["hello"]["cluster"] == "test cluster"
                    assert [a["name"] for a in first["agents"]["agents"]] == ["A1"]
                    assert first["timeline"]["events"][0]["i"] == 1
                    hub.mirror_event(f.write(ddbops.put("slam/map", "blob", encoded_map()),
                                             ddbops.put("targets/s1", "json", {"x": 1, "y": 2})))
                    got = {}
                    while not {"map", "overlay", "ddb"} <= set(got):
                        m = json.loads((await ws.receive(timeout=5)).data)
                        got[m["type"]] = m
                    assert got["map"]["w"] == 200 and got["overlay"]["targets"]["s1"] == {"x": 1, "y": 2}
                    assert sorted(e[0] for e in got["ddb"]["set"]) == ["slam/map", "targets/s1"]
                    await ws.send_str(json.dumps({"op": "object", "key": "targets/s1"}))
                    while True:
                        m = json.loads((await ws.receive(timeout=5)).data)
                        if m["type"] == "object":
                            break
                    o = m["object"]
                    assert o["key"] == "targets/s1" and o["type"] == "json" and '"x": 1' in o["text"]
                async with s.get(url + "api/state") as r:
                    st = await r.json()
                    assert st["agents"] == 1 and st["ddb_seq"] == 1 and st["map_version"] == 1
        finally:
            await srv.stop()

    asyncio.run(go())


# ---------------------------------------------------------------------------------------------- in a browser


def haactl(*args: str, env: dict | None = None, timeout: float = 120.0) -> str:
    r = subprocess.run([*HAACTL, *args], capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)
    assert r.returncode == 0, f"haactl {' '.join(args)}: {r.stdout}\n{r.stderr}"
    return r.stdout


def browser_or_skip() -> str:
    path = find_chromium()
    if path:
        return path
    why = "no Chromium on PATH: install Debian's chromium (scripts/browser-setup.sh, run by `make setup`)"
    if os.environ.get("HAA_REQUIRE_BROWSER") == "1":
        pytest.fail(why + " — HAA_REQUIRE_BROWSER=1")
    pytest.skip(why)


def canvas_pixels(png: Path, rect: dict) -> tuple[int, int]:
    """(pixels inside `rect` that differ from the canvas background, pixels in `rect`) of a screenshot."""
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
    x0, y0 = int(rect["x"]) + 2, int(rect["y"]) + 2
    x1, y1 = int(rect["x"] + rect["width"]) - 2, int(rect["y"] + rect["height"]) - 2
    crop = img[y0:y1, x0:x1]
    bg = np.array([0xFA, 0xFA, 0xFA])
    differ = np.any(np.abs(crop - bg) > 8, axis=2)
    return int(differ.sum()), int(differ.size)


@pytest.mark.slow
def test_dashboard_in_a_browser_against_a_running_mission(tmp_path):
    browser_or_skip()
    env = {**os.environ, "HAA_CLUSTER_DIR": str(tmp_path / "cluster")}
    env.pop("HAA_COMPOSE", None)
    dash = None
    t0 = time.monotonic()
    try:
        haactl("cluster", "up", "--hosts", "2", env=env)
        haactl("mission", "start", str(REPO / "tests" / "missions" / "dashboard.yaml"), env=env)
        dash = subprocess.Popen([*HAACTL, "dashboard", "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env, cwd=REPO)
        assert dash.stdout is not None
        line = dash.stdout.readline()
        m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
        assert m, line
        url = m.group(1)
        shot = tmp_path / "dashboard.png"

        async def look() -> dict:
            async with Chromium(tmp_path, width=1600, height=1000) as b:
                await b.navigate(url)
                await b.wait_for("window.HAA && window.HAA.connected", 20)
                # the team publishes a map, estimates and targets within a few simulated seconds
                await b.wait_for("window.HAA.drawn.map && window.HAA.drawn.map.version", 90)
                await b.wait_for("(() => { const o = S.overlay || {}; return Object.keys(o.estimates || {}).length"
                                 " >= 2 && Object.keys(o.targets || {}).length >= 1 })()", 60)
                await b.wait_for("S.timeline.length > 0 && S.agents.length >= 8", 60)
                # the agent count on the page is what `haactl agent list` says (the team may still be spawning:
                # compare until both agree)
                deadline = time.monotonic() + 30
                while True:
                    listed = json.loads(haactl("agent", "list", "--json", env=env))["agents"]
                    shown = int(await b.evaluate("document.getElementById('agent-count').textContent"))
                    if shown == len(listed) or time.monotonic() > deadline:
                        break
                    await asyncio.sleep(1.0)
                # open the DDB's slam node and select an agent, as an operator would
                await b.evaluate("document.querySelector('[data-dtw=\"/slam\"]').click()")
                await b.evaluate("document.querySelector('#tree [data-agent]').click()")
                await b.wait_for("document.getElementById('detail').textContent.includes('type')", 10)
                await asyncio.sleep(0.3)  # the page paints the selection before the screenshot is taken
                await b.screenshot(shot)
                return {
                    "listed": len(listed), "shown": shown,
                    "rect": await b.evaluate("(() => { const r = document.getElementById('map')"
                                             ".getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width,"
                                             " height: r.height} })()"),
                    "types": sorted({a["type"] for a in listed}),
                    "tree": await b.evaluate("document.getElementById('tree').textContent"),
                    "ddb": await b.evaluate("document.getElementById('ddb').textContent"),
                    "detail": await b.evaluate("document.getElementById('detail').textContent"),
                    "hosts_in_timeline": await b.evaluate("[...timelineRows().hosts.keys()]"),
                    "timeline_agents": await b.evaluate(
                        "[...timelineRows().hosts.values()].reduce((n, h) => n + h.agents.size, 0)"),
                    "errors": list(b.console),
                }

        got = asyncio.run(look())
        print(f"\ndashboard screenshot: {shot} ({time.monotonic() - t0:.0f} s)")
        assert got["errors"] == []
        assert got["shown"] == got["listed"] >= 8, got
        on, total = canvas_pixels(shot, got["rect"])
        assert on > 0.05 * total, (on, total)  # the map is drawn (a blank canvas would be its background only)
        for t in ("executive_mission", "supervisor_slam", "avatar_simulation", "path_planner"):
            assert t in got["types"] and t in got["tree"], t
        assert "avatar s1" in got["ddb"] and "map" in got["ddb"] and "mission" in got["ddb"]
        assert "type" in got["detail"] and "cpu" in got["detail"]
        assert set(got["hosts_in_timeline"]) >= {"h1", "h2"} and got["timeline_agents"] >= 8
    finally:
        if dash is not None:
            dash.terminate()
            try:
                dash.wait(10)
            except subprocess.TimeoutExpired:
                dash.kill()
        subprocess.run([*HAACTL, "mission", "stop"], env=env, cwd=REPO, capture_output=True, timeout=120)
        subprocess.run([*HAACTL, "cluster", "down"], env=env, cwd=REPO, capture_output=True, timeout=120)
