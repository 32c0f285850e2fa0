"""The Foxglove bridge (haa.lab.foxglove, `haactl foxglove`).

A WebSocket client speaking the Foxglove WebSocket protocol (aiohttp; the SDK names the subprotocol
`foxglove.sdk.v1`, the same protocol as `foxglove.websocket.v1`, which it refuses by name) connects to the
bridge, reads the advertised channels, subscribes, and decodes the binary message frames with the protobuf
schemas the server advertised (google.protobuf builds the classes from the FileDescriptorSet: nothing of the
SDK is used to read them):

* from a recorded mirror feed (a DDB snapshot and batches as a host streams them, fed to the dashboard's `Hub`):
  the map arrives as a foxglove.Grid with the grid's geometry and cells, the estimated and true poses as
  PosesInFrame / PoseInFrame, landmarks as a SceneUpdate, the transcript as Logs, particles as a PointCloud;
  a later write reaches a subscribed client; a client subscribing late still gets the map (latched);
* end to end: `haactl foxglove --port 0` against a 1-host local cluster, whose DDB gets a map and an estimate
  through the control API: the Grid and the pose arrive from the host's real mirror stream.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from helpers import Cli

from haa.core.ddb import ops as ddbops
from haa.core.ddb.ddb import Ddb
from haa.lab.dashboard.sources import Hub
from haa.lab.foxglove import FoxgloveBridge
from haa.pb import control_pb2 as cpb
from haa.pb import ddb_pb2

REPO = Path(__file__).resolve().parents[1]
#: the Foxglove WebSocket protocol's subprotocol names: foxglove-sdk 0.30 serves the protocol (spec: the
#: ws-protocol repository's docs/spec.md) as "foxglove.sdk.v1" and refuses the older name "foxglove.websocket.v1"
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


def encoded_map(rows: int = 40, cols: int = 30, res: float = 0.1) -> bytes:
    from haa.slam.grid import GridSpec
    from haa.slam.replica import encode_map

    p = np.full((rows, cols), 0.5)
    p[:5, :] = 0.05  # the lowest rows seen free
    p[rows // 2, :] = 0.95  # a wall across the middle
    return encode_map(GridSpec(cols * res, rows * res, res), p)


class Feed:
    """A DDB and the mirror events a host would stream of it."""

    def __init__(self) -> None:
        self.db = Ddb()

    def snapshot(self) -> cpb.MirrorEvent:
        return cpb.MirrorEvent(snapshot=ddb_pb2.DdbSnapshot.FromString(self.db.snapshot()))

    def write(self, *ops: Any) -> cpb.MirrorEvent:
        payload = ddbops.encode_batch(ops)
        self.db.apply(payload)
        return cpb.MirrorEvent(batch=cpb.MirrorBatch(ddb_seq=self.db.seq, payload=payload))


def checkpoint_blobs(points: np.ndarray) -> dict[str, bytes]:
    """A SLAM checkpoint of one filter (`filter-0`, avatar s1) as the DDB blobs `slam/ckpt/*` hold it."""
    from haa.slam.replica import _pack  # the checkpoint's own blob writer (SlamReplica.checkpoint uses it)

    data = _pack({"name": "s1"}, [("current", points)])
    meta = {"next_index": 7, "parts": {"filter-0": [1, len(data), 0]}}
    return {"meta": json.dumps(meta).encode(), "filter-0": data}


class FoxgloveClient:
    """A minimal foxglove.websocket.v1 client: advertised channels, subscriptions, decoded messages."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.subs: dict[int, str] = {}  # subscription id -> topic
        self.classes: dict[str, Any] = {}
        self.server_info: dict[str, Any] = {}

    async def read(self, timeout: float = 20.0) -> tuple[str, Any] | None:
        """One message: ("json", op) for a text frame, (topic, decoded message) for a message data frame."""
        msg = await self.ws.receive(timeout=timeout)
        if msg.type == aiohttp.WSMsgType.TEXT:
            op = json.loads(msg.data)
            if op.get("op") == "serverInfo":
                self.server_info = op
            elif op.get("op") == "advertise":
                for c in op["channels"]:
                    self.channels[c["topic"]] = c
            return "json", op
        assert msg.type == aiohttp.WSMsgType.BINARY, msg
        data = msg.data
        assert data[0] == 0x01, data[:1]  # Message Data
        sub_id, log_time = struct.unpack_from("<IQ", data, 1)
        assert log_time > 1.6e18  # nanoseconds of the wall clock
        topic = self.subs[sub_id]
        return topic, self.decode(topic, data[13:])

    def decode(self, topic: str, payload: bytes) -> Any:
        c = self.channels[topic]
        if c["encoding"] == "json":
            return json.loads(payload)
        assert c["encoding"] == "protobuf" and c["schemaEncoding"] == "protobuf"
        cls = self.classes.get(c["schemaName"])
        if cls is None:
            fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(c["schema"]))
            pool = descriptor_pool.DescriptorPool()
            for f in fds.file:
                pool.Add(f)
            cls = self.classes[c["schemaName"]] = message_factory.GetMessageClass(
                pool.FindMessageTypeByName(c["schemaName"]))
        return cls.FromString(payload)

    async def wait_topics(self, *topics: str) -> None:
        while not all(t in self.channels for t in topics):
            await self.read()

    async def subscribe(self, *topics: str) -> None:
        subs = []
        for t in topics:
            sid = len(self.subs) + 1
            self.subs[sid] = t
            subs.append({"id": sid, "channelId": self.channels[t]["id"]})
        await self.ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def collect(self, want: Any, timeout: float = 30.0) -> dict[str, list[Any]]:
        """Messages by topic until `want(got)` is true."""
        got: dict[str, list[Any]] = {}
        async with asyncio.timeout(timeout):
            while not want(got):
                r = await self.read(timeout)
                if r is not None and r[0] != "json":
                    got.setdefault(r[0], []).append(r[1])
        return got


async def connect(session: aiohttp.ClientSession, url: str) -> FoxgloveClient:
    ws = await session.ws_connect(url, protocols=SUBPROTOCOLS)
    assert ws.protocol == SUBPROTOCOLS[0]
    return FoxgloveClient(ws)


@contextlib.contextmanager
def running(bridge: FoxgloveBridge) -> Iterator[str]:
    url = bridge.start()
    stop = threading.Event()
    t = threading.Thread(target=bridge.run_forever, args=(stop,), daemon=True)
    t.start()
    try:
        yield url
    finally:
        stop.set()
        t.join(5)
        bridge.stop()


def test_bridge_publishes_a_recorded_mirror_feed() -> None:
    f = Feed()
    hub = Hub("recorded feed")
    hub.mirror_event(f.snapshot())
    particles = np.array([[1.0 + 0.01 * i, 2.0, 0.1] for i in range(50)])
    hub.mirror_event(f.write(
        ddbops.put("slam/map", "blob", encoded_map()),
        ddbops.put("slam/est/s1", "json", {"t": 3.0, "x": 1.0, "y": 2.0, "theta": 0.5, "std": [0.1, 0.1, 0.05]}),
        ddbops.put("slam/est/s2", "json", {"t": 3.0, "x": 2.5, "y": 0.5, "theta": -1.0, "std": [0.1, 0.1, 0.05]}),
        ddbops.put("slam/landmarks", "json", {"3": [1.2, 3.4, 0.05]}),
        ddbops.put("targets/s1", "json", {"x": 2.0, "y": 3.0, "task": "explore"}),
        ddbops.put("mission/status", "json", {"state": "running", "t": 3.0, "explored": 0.25}),
        *[ddbops.put(f"slam/ckpt/{k}", "blob", v) for k, v in checkpoint_blobs(particles).items()],
        ddbops.log_append("mission/events", [json.dumps({"t": 1.0, "text": "Mission started"}).encode(),
                                             json.dumps({"t": 2.0, "agent": "A1", "type": "executive_mission",
                                                         "text": "assigned s1"}).encode()]),
    ))
    hub.set_truth({"t": 3.0, "avatars": {"s1": {"x": 1.05, "y": 2.02, "theta": 0.52, "status": "active"}}})
    bridge = FoxgloveBridge(hub, port=0)

    async def go() -> None:
        async with aiohttp.ClientSession() as s:
            c = await connect(s, url)
            await c.wait_topics("/map", "/avatars/estimated", "/avatars/true", "/avatars/s1/estimated",
                                "/avatars/s1/particles", "/landmarks", "/transcript", "/mission/status", "/paths")
            assert c.server_info["name"].startswith("HAA")
            assert c.channels["/map"]["schemaName"] == "foxglove.Grid"
            assert c.channels["/avatars/s1/particles"]["schemaName"] == "foxglove.PointCloud"
            topics = ["/map", "/avatars/estimated", "/avatars/true", "/avatars/s1/estimated", "/avatars/s1/particles",
                      "/landmarks", "/transcript", "/mission/status", "/paths"]
            await c.subscribe(*topics)
            got = await c.collect(lambda g: all(t in g for t in topics) and len(g["/transcript"]) >= 2)
            grid = got["/map"][-1]
            assert (grid.column_count, grid.row_stride, grid.cell_stride) == (30, 30, 1)
            assert grid.cell_size.x == pytest.approx(0.1) and grid.frame_id == "map"
            assert [(fl.name, fl.offset) for fl in grid.fields] == [("occupancy", 0)]
            cells = np.frombuffer(grid.data, dtype=np.uint8).reshape(40, 30)
            assert cells[0, 0] == round(0.05 * 254) and cells[20, 3] == round(0.95 * 254) and cells[30, 3] == 127
            est = got["/avatars/estimated"][-1]
            assert [(p.position.x, p.position.y) for p in est.poses] == [(1.0, 2.0), (2.5, 0.5)]
            one = got["/avatars/s1/estimated"][-1].pose
            assert one.orientation.z == pytest.approx(np.sin(0.25)) and one.orientation.w == pytest.approx(np.cos(0.25))
            assert got["/avatars/true"][-1].poses[0].position.x == pytest.approx(1.05)
            cloud = got["/avatars/s1/particles"][-1]
            pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
            assert cloud.point_stride == 12 and len(pts) == 50 and pts[0, 0] == pytest.approx(1.0)
            lm = got["/landmarks"][-1].entities[0]
            assert lm.spheres[0].pose.position.x == pytest.approx(1.2) and lm.texts[0].text == "L3"
            assert any(e.id == "target/s1" for e in got["/paths"][-1].entities)
            lines = [m.message for m in got["/transcript"]]
            assert lines[:2] == ["00:01 Mission started", "00:02 A1 (ExecutiveMission) assigned s1"]
            assert got["/mission/status"][-1]["explored"] == 0.25
            # a write on the mirror reaches the subscribed client
            hub.mirror_event(f.write(ddbops.put("slam/est/s1", "json", {"x": 1.5, "y": 2.0, "theta": 0.0})))
            got = await c.collect(lambda g: any(p.poses[0].position.x == 1.5 for p in g.get("/avatars/estimated", [])))
            # a second client subscribing later still gets the map at once (latched)
            c2 = await connect(s, url)
            await c2.wait_topics("/map")
            await c2.subscribe("/map", "/transcript")
            got2 = await c2.collect(lambda g: "/map" in g, timeout=10)
            assert got2["/map"][0].column_count == 30
            await c.ws.close()
            await c2.ws.close()

    with running(bridge) as url:
        asyncio.run(go())
    assert bridge.published["/map"] >= 2 and bridge.published["/transcript"] == 2


# ---------------------------------------------------------------------------------------------- end to end


@pytest.fixture()
def cluster(local_cluster: Cli) -> Path:
    local_cluster("cluster", "up", "--hosts", "1", "--timeout", "60")
    return local_cluster.root


def test_haactl_foxglove_bridges_a_running_cluster(cluster: Path) -> None:
    from haa.cluster.local_backend import LocalBackend

    backend = LocalBackend(cluster)
    backend.call("h1", lambda c: c.ddb_write([ddbops.put("slam/map", "blob", encoded_map()),
                                              ddbops.put("slam/est/s1", "json", {"x": 0.5, "y": 0.7, "theta": 0.0})]),
                 "ddb write")
    env = {**os.environ, "HAA_CLUSTER_DIR": str(cluster)}
    p = subprocess.Popen([sys.executable, "-c", "from haactl.main import app; app()", "foxglove", "--port", "0",
                          "--no-truth"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                         cwd=REPO)
    try:
        assert p.stdout is not None
        line = p.stdout.readline()
        m = re.search(r"(ws://127\.0\.0\.1:\d+)", line)
        assert m, line

        async def go() -> dict[str, list[Any]]:
            async with aiohttp.ClientSession() as s:
                c = await connect(s, m.group(1))
                await c.wait_topics("/map", "/avatars/estimated")
                await c.subscribe("/map", "/avatars/estimated")
                return await c.collect(lambda g: "/map" in g and "/avatars/estimated" in g)

        got = asyncio.run(go())
        assert got["/map"][-1].column_count == 30
        assert got["/avatars/estimated"][-1].poses[0].position.y == pytest.approx(0.7)
    finally:
        p.send_signal(signal.SIGINT)
        try:
            out = p.communicate(timeout=60)[0]  # a clean exit, not a fast one: CI machines are loaded
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGUSR1)  # every thread's stack into the output below (haactl's faulthandler)
            time.sleep(2)  # time for the dump to be written; this is the failure path
            p.kill()
            out = p.communicate()[0]
    assert p.returncode == 130 and "Traceback" not in out, out


def test_a_taken_port_is_one_clear_error() -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(OSError) as e:
            FoxgloveBridge(Hub(), port=port).start()
    assert str(e.value).startswith("Failed to bind port") and "\n" not in str(e.value), str(e.value)
