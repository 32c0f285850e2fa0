"""haa-sim as a real server process on a free loopback port: the avatar API, streams, ground truth, step mode
determinism, schedules, errors and tokens."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
from helpers import haactl, wait_sync
from test_metrics import one, scrape

from haa.cluster.procs import free_port
from haa.pb import sim_pb2 as pb
from haa.sim.groundtruth import surface_grid
from haa.sim.service import DEFAULT_TICK, SimClient, decode_frame
from haa.sim.world import World


class SimProcess:
    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "haa.sim.service", "--listen", "127.0.0.1:0", *args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        self._ready = threading.Event()
        self.port = 0
        threading.Thread(target=self._read, daemon=True).start()
        if not self._ready.wait(30) or not self.port:
            self.stop()
            raise AssertionError(f"haa-sim did not start: {self.lines}")
        self.address = f"127.0.0.1:{self.port}"

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip())
            if not self.port:
                try:
                    ev = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if ev.get("event") == "listening":
                    self.port = int(ev["port"])
                    self._ready.set()
        self._ready.set()

    def client(self, token: str | None = None) -> SimClient:
        c = SimClient(self.address, token=token, timeout=10.0)
        return c

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            return self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(10)


@pytest.fixture(scope="module")
def sim() -> Iterator[SimProcess]:
    s = SimProcess("--arena", "small", "--seed", "3", "--step")
    try:
        yield s
    finally:
        assert s.stop() == 0, s.lines[-5:]
        assert any('"event": "stopped"' in line for line in s.lines)
        assert not any("Traceback" in line for line in s.lines), s.lines


def test_avatar_api_end_to_end(sim: SimProcess) -> None:
    with sim.client() as c:
        info = c.wait_ready()
        assert info.arena == "small" and info.mode == "step" and info.seed == 3
        assert "panel-a" in info.arena_yaml
        events = c.events(replay=True)
        r = c.register("sweeper")
        aid = r.avatar.avatar_id
        assert not r.attached and r.avatar.type == "sweeper" and r.avatar.max_speed == 1.0
        assert r.avatar.camera.name == "enhanced" and len(r.avatar.camera.K) == 9
        assert r.avatar.sonars == 5 and r.avatar.sonar_period == 1.0 and r.avatar.sonar_range == 2.0
        ev = next(events)
        assert (ev.kind, ev.avatar_id, ev.type) == ("joined", aid, "sweeper")
        t0 = info.time
        odo = c.odometry(aid, period=0.5)
        first = next(odo)
        assert first.time == pytest.approx(t0)
        sonar = c.sonar(aid)
        updates = c.act(pb.ActionRequest(avatar_id=aid, move_by=pb.MoveBy(distance=1.0), progress_period=0.5))
        accepted = next(updates)
        assert accepted.status == pb.ACTION_STATUS_RUNNING and accepted.kind == "move_by"
        assert c.step(3.0) == pytest.approx(t0 + 3.0)
        rest = list(updates)
        assert rest[-1].status == pb.ACTION_STATUS_SUCCEEDED and rest[-1].progress == 1.0
        progress = [u.progress for u in rest]
        assert progress == sorted(progress) and len(rest) >= 3
        assert rest[-1].odometry.y == pytest.approx(first.pose.y + 1.0, abs=0.02)
        times = [round(next(odo).time - t0, 6) for _ in range(6)]
        assert times == [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
        scans = [next(sonar) for _ in range(3)]
        assert [round(s.time - t0, 6) for s in scans] == [1.0, 2.0, 3.0]
        assert all(len(s.readings) == 5 for s in scans)
        # capture: PNG and raw decode to the same frame; detections are landmarks in view
        f = c.capture(aid, pb.IMAGE_ENCODING_PNG)
        img = decode_frame(f)
        assert img.shape == (480, 640, 3) and f.data[:4] == b"\x89PNG"
        raw = decode_frame(c.capture(aid))
        assert len(c.capture(aid).data) == 640 * 480 * 3
        assert np.abs(raw.astype(int) - img).max() <= 12  # the same view, another draw of pixel noise
        assert len(f.floor_homography) == 9 and f.odometry.y == pytest.approx(rest[-1].odometry.y, abs=1e-6)
        det = c.detect(aid)
        lm = {m.id: (m.position.x, m.position.y) for m in c.landmarks().landmarks}
        assert len(lm) == 35
        pose = next(a for a in c.poses().avatars if a.avatar_id == aid).pose
        for o in det.landmarks:
            lx, ly = lm[o.landmark_id]
            assert o.range == pytest.approx(math.hypot(lx - pose.x, ly - pose.y), rel=0.4)
        # capture as an action
        cap = list(c.act(pb.ActionRequest(avatar_id=aid, capture=pb.CaptureAction())))
        assert cap[-1].status == pb.ACTION_STATUS_SUCCEEDED and cap[-1].frame.width == 640
        rel = c.release(aid)
        assert rel.status == "retired"
        assert next(events).kind == "retired"
        with pytest.raises(grpc.RpcError) as e:
            next(odo)
            next(odo)
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE and "retired" in e.value.details()
        odo.cancel()
        sonar.cancel()
        events.cancel()


def test_ground_truth(sim: SimProcess) -> None:
    w = World.from_arena("small")
    with sim.client() as c:
        occ, ex, r = c.grid(0.05)
        assert np.array_equal(occ, w.ideal_grid(0.05).grid)
        assert r.origin.x == 0 and r.resolution == 0.05 and occ.shape == (144, 68)
        assert ex.sum() > 0.9 * (occ == 0).sum() and r.explorable_area == pytest.approx(24.2, abs=0.1)
        occ10, _, r10 = c.grid(0.1)  # the metrics' ideal map: every cell a solid touches (the panels at 0.1 m)
        surf = np.frombuffer(r10.surface, dtype=np.uint8).reshape(occ10.shape)
        assert np.array_equal(surf, surface_grid(w.arena, 0.1).grid) and surf.sum() > occ10.sum()
        lms = c.landmarks()
        assert lms.dictionary == "DICT_4X4_250" and sum(m.congregation for m in lms.landmarks) == 1
        with pytest.raises(grpc.RpcError) as e:
            c.grid(0.0)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "resolution" in e.value.details()


def test_ground_truth_calls_are_counted_per_caller(sim: SimProcess) -> None:
    """haa-sim counts ground-truth and Detect calls per caller (x-haa-caller), so a mission test can
    assert that the agents made none; the avatar API itself is not counted."""
    with SimClient(sim.address, caller="A7") as c, SimClient(sim.address, caller="runner") as r:
        before = dict(r.info().truth_calls)
        c.poses()
        c.poses()
        c.landmarks()
        aid = c.register("seeker").avatar.avatar_id
        c.odometry(aid, timeout=0.01).cancel()
        c.detect(aid)
        after = dict(r.info().truth_calls)
        c.release(aid)
    delta = {k: after.get(k, 0) - before.get(k, 0) for k in after if after.get(k, 0) != before.get(k, 0)}
    assert delta == {"A7/Poses": 2, "A7/Landmarks": 1, "A7/Detect": 1, "runner/Info": 1}, delta


def test_step_mode_is_deterministic_and_equals_the_library() -> None:
    """The server in step mode gives exactly what the library World gives when stepped in the same ticks."""
    s2 = SimProcess("--arena", "small", "--seed", "9", "--step")
    try:
        with s2.client() as c:
            c.wait_ready()
            aid = c.register("seeker", pose=(1.7, 1.0, math.pi / 2)).avatar.avatar_id
            odo = c.odometry(aid, period=0.25)
            next(odo)
            c.set_velocity(aid, 1.0, 0.4)
            t = c.step(1.0)
            got = [next(odo) for _ in range(4)]
            det = c.detect(aid)
            truth = next(a for a in c.poses().avatars if a.avatar_id == aid)
            odo.cancel()
    finally:
        assert s2.stop() == 0
    w = World.from_arena("small", seed=9)
    a = w.add_avatar("seeker", (1.7, 1.0, math.pi / 2))
    w.set_velocity(a, 1.0, 0.4)
    want = []
    for k in range(1, round(1.0 / DEFAULT_TICK) + 1):
        w.step(DEFAULT_TICK)
        if k % 5 == 0:
            want.append(w.odometry(a))
    assert [(o.pose.x, o.pose.y, o.pose.theta) for o in got] == want
    assert (truth.pose.x, truth.pose.y, truth.pose.theta) == w.true_pose(a)
    assert [(o.landmark_id, o.range, o.bearing) for o in det.landmarks] == [
        (o.landmark_id, o.range, o.bearing) for o in w.landmark_observations(a)
    ]
    assert t == pytest.approx(w.time) == pytest.approx(1.0)  # the server's clock: the same ticks, only when stepped


def test_schedule_join_crash_retire_and_attach(tmp_path: Path) -> None:
    mission = tmp_path / "mission.yaml"
    mission.write_text(
        "schedule:\n"
        "  - {at: 0, join: {type: seeker, id: s1}}\n"
        "  - {at: 0, join: {type: sweeper, id: s2}}\n"
        "  - {at: 1.5, crash: s2}\n"
        "  - {at: 2.0, retire: s1}\n"
        "  - {at: 2.5, join: {type: carrier, id: s3, start: 6}}\n"
    )
    metrics = f"http://127.0.0.1:{(port := free_port())}/metrics"
    s = SimProcess("--arena", "small", "--seed", "1", "--step", "--schedule", str(mission), "--metrics-port", str(port))
    try:
        with s.client() as c:
            c.wait_ready()
            r = c.register(avatar_id="s2")  # an avatar agent attaches to the scheduled sweeper
            assert r.attached and r.avatar.type == "sweeper"
            with pytest.raises(grpc.RpcError) as e:
                c.register("seeker", avatar_id="s2")
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            events = c.events(replay=True)
            assert {next(events).avatar_id for _ in range(2)} == {"s1", "s2"}
            sonar = c.sonar("s2")
            got: list[float] = []
            ended: list[grpc.RpcError] = []

            def read_sonar() -> None:
                try:
                    for reading in sonar:
                        got.append(reading.time)
                except grpc.RpcError as err:
                    ended.append(err)

            reader = threading.Thread(target=read_sonar, daemon=True)
            reader.start()
            # the stream is served once its first message is asked for: the clock moves only once the server has
            # subscribed it (under load the call can reach the server after a step)
            wait_sync(lambda: one(scrape(metrics), "haa_sim_subscribers", stream="sonar") == 1, 20,
                      "the sonar stream subscribed at the server", interval=0.05)
            c.step(3.0)
            seen = [(e.kind, e.avatar_id, round(e.time, 3)) for e in (next(events) for _ in range(3))]
            assert seen == [("crashed", "s2", 1.5), ("retired", "s1", 2.0), ("joined", "s3", 2.5)]
            reader.join(10)
            assert got == [pytest.approx(1.0)]
            assert ended and ended[0].code() == grpc.StatusCode.UNAVAILABLE and "crashed" in ended[0].details()
            with pytest.raises(grpc.RpcError) as e:
                c.capture("s2")
            assert e.value.code() == grpc.StatusCode.UNAVAILABLE
            st = {a.avatar_id: a for a in c.poses().avatars}
            assert (st["s1"].status, st["s2"].status, st["s3"].status) == ("retired", "crashed", "active")
            assert st["s2"].left == pytest.approx(1.5)
            # on demand
            info = c.join("enhanced_seeker", "e1")
            assert info.status == "active"
            assert c.crash("e1").status == "crashed"
            assert next(events).kind == "joined" and next(events).kind == "crashed"
            events.cancel()
    finally:
        assert s.stop() == 0


def test_errors_are_clear(sim: SimProcess, tmp_path: Path) -> None:
    with sim.client() as c:
        for call, code, text in (
            (lambda: c.register("tank"), grpc.StatusCode.INVALID_ARGUMENT, "avatar type 'tank'"),
            (lambda: c.register(""), grpc.StatusCode.INVALID_ARGUMENT, "type: required"),
            (lambda: c.capture("nobody"), grpc.StatusCode.NOT_FOUND, "no avatar 'nobody'"),
            (lambda: c.step(-1), grpc.StatusCode.INVALID_ARGUMENT, "dt"),
            (
                lambda: list(c.act(pb.ActionRequest(avatar_id=c.register("seeker").avatar.avatar_id))),
                grpc.StatusCode.INVALID_ARGUMENT,
                "action: none given",
            ),
        ):
            with pytest.raises(grpc.RpcError) as e:
                call()
            assert e.value.code() == code and text in e.value.details(), e.value.details()
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nsize: [1, 1]\nstart_poses: []\n")
    for args, text in (
        (["--arena", str(bad)], "start_poses: List should have at least 1 item"),
        (["--arena", "nowhere"], "arena nowhere: no such file"),
        (["--speed", "0"], "--speed: 0.0 must be a positive number"),
        (["--listen", "nohost"], "--listen: 'nohost' is not HOST:PORT"),
    ):
        r = subprocess.run([sys.executable, "-m", "haa.sim.service", *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r.stderr
        assert text in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_realtime_clock_speed_and_token(tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text("s3cret\n")
    s = SimProcess("--arena", "small", "--speed", "20", "--token-file", str(token))
    try:
        with s.client() as bad:
            with pytest.raises(grpc.RpcError) as e:
                bad.info()
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        with s.client(token="s3cret") as c:
            t0, w0 = c.info().time, time.monotonic()
            time.sleep(1.0)  # the wall time over which the clock's rate is measured
            t1, w1 = c.info().time, time.monotonic()
            rate = (t1 - t0) / (w1 - w0)
            assert 5.0 < rate < 22.0, rate  # 20x requested; a loaded machine may fall behind, never ahead
            with pytest.raises(grpc.RpcError) as e:
                c.step(1.0)
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    finally:
        assert s.stop() == 0


def test_forage_actions_over_grpc(tmp_path: Path) -> None:
    s = SimProcess("--arena", "large", "--seed", "2", "--step")
    try:
        with s.client() as c:
            c.wait_ready()
            col = {x.id: x for x in c.collectables().collectables}
            cx, cy = col["c1"].position.x, col["c1"].position.y
            aid = c.join("carrier", "k1", pose=(cx - 0.3, cy, 0.0)).avatar_id
            done = list(c.act(pb.ActionRequest(avatar_id=aid, pick_up=pb.PickUp())))
            assert done[-1].status == pb.ACTION_STATUS_SUCCEEDED and done[-1].collectable_id == "c1"
            st = {x.id: x for x in c.collectables().collectables}
            assert st["c1"].state == "carried" and st["c1"].carrier == "k1"
            again = list(c.act(pb.ActionRequest(avatar_id=aid, pick_up=pb.PickUp())))
            assert again[-1].status == pb.ACTION_STATUS_FAILED and again[-1].reason == "capacity_full"
            dropped = list(c.act(pb.ActionRequest(avatar_id=aid, drop=pb.Drop())))
            assert dropped[-1].status == pb.ACTION_STATUS_SUCCEEDED and dropped[-1].region_id == ""
            assert len(c.collectables().regions) == 3
            out = tmp_path / "state.png"
            r = haactl(["sim", "show", "--server", s.address, "-o", str(out)])
            assert r.exit_code == 0, r.output
            assert out.stat().st_size > 10_000
    finally:
        assert s.stop() == 0
