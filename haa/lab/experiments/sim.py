"""The robot simulator's speed (issue 5 §5; `haactl bench sim` -> bench-results/sim.json).

* stepping: 10 avatars (2 sweepers, 4 enhanced seekers, 4 carriers, as in R-2) in the large arena driving
  seeded random velocity commands, stepped in the server's 0.05 s ticks; simulated seconds per second of
  CPU and of wall time ("x real time"); headless (physics + odometry) and with the sensors a mission reads
  (sonar 1 Hz on the sweepers, landmark detections 1 Hz on every avatar);
* camera: one frame rendered (basic 320 x 240, enhanced 640 x 480) from random free poses in both arenas,
  plus the PNG encoding the service adds, and OpenCV's ArUco detection on the frame;
* sonar: one reading of all 5 sonars of a sweeper (9 rays per cone), and per sonar;
* landmark detections: `World.landmark_observations` of one avatar.

Everything runs on one thread (OpenCV limited to one thread). Times are reported as CPU time of this
thread (what the work costs on one core, whatever else the machine runs) and as wall time. `run_sim_bench`
returns the dict of bench-results/sim.json ("stepping", "camera", "sensors", "quick").
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

TEAM = ["sweeper", "sweeper"] + ["enhanced_seeker"] * 4 + ["carrier"] * 4


def _timed(fn: Callable[[], Any]) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), time.thread_time()
    fn()
    return time.perf_counter() - w0, time.thread_time() - c0


def _stats(xs: list[float]) -> dict[str, float]:
    a = np.asarray(xs) * 1e3
    return {
        "mean_ms": float(a.mean()),
        "p50_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(a.max()),
        "n": len(xs),
    }


def bench_stepping(seconds: float, sensors: bool, seed: int = 1) -> dict[str, Any]:
    from haa.sim.world import World

    w = World.from_arena("large", seed=seed)
    ids = [w.add_avatar(k) for k in TEAM]
    rng = np.random.default_rng(seed)
    tick = 0.05
    steps = round(seconds / tick)

    def run() -> None:
        for k in range(steps):
            if k % 40 == 0:  # new commands every 2 s
                for a in ids:
                    w.set_velocity(a, float(rng.uniform(-0.3, 2.0)), float(rng.uniform(-1.5, 1.5)))
            w.step(tick)
            if sensors and k % 20 == 0:  # 1 Hz
                for a in ids:
                    if w.avatars[a].spec.sonars:
                        w.sonar(a)
                    w.landmark_observations(a)

    wall, cpu = _timed(run)
    return {
        "avatars": len(ids),
        "sim_seconds": steps * tick,
        "sensors": sensors,
        "wall_s": wall,
        "cpu_s": cpu,
        "x_realtime_cpu": steps * tick / cpu,
        "x_realtime_wall": steps * tick / wall,
        "physics_substeps_per_s": steps * math.ceil(tick / w.physics_dt) / cpu,
    }


def _random_poses(w: Any, n: int, radius: float, seed: int) -> list[tuple[float, float, float]]:
    rng = np.random.default_rng(seed)
    out: list[tuple[float, float, float]] = []
    while len(out) < n:
        x = float(rng.uniform(0.3, w.arena.width - 0.3))
        y = float(rng.uniform(0.3, w.arena.height - 0.3))
        if w._pose_free(x, y, radius + 0.05):
            out.append((x, y, float(rng.uniform(-math.pi, math.pi))))
    return out


def bench_camera(arena: str, kind: str, frames: int, seed: int = 2) -> dict[str, Any]:
    import cv2

    from haa.sim.world import World

    w = World.from_arena(arena, seed=seed)
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, w.arena.marker_dictionary)),
        cv2.aruco.DetectorParameters(),
    )
    aid = w.add_avatar(kind)
    w.capture(aid)  # builds the renderer
    poses = _random_poses(w, frames, w.avatars[aid].spec.radius, seed)
    render_w: list[float] = []
    render_c: list[float] = []
    png_c: list[float] = []
    det_c: list[float] = []
    expected = found = 0
    for p in poses:
        w.retire(aid)
        aid = w.add_avatar(kind, p)
        frame = None

        def cap(a: str = aid) -> None:
            nonlocal frame
            frame = w.capture(a)

        wall, cpu = _timed(cap)
        render_w.append(wall)
        render_c.append(cpu)
        assert frame is not None
        bgr = cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)
        png_c.append(_timed(functools.partial(cv2.imencode, ".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1]))[1])
        gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
        ids = None

        def det(g: np.ndarray = gray) -> None:
            nonlocal ids
            _, ids, _ = detector.detectMarkers(g)

        det_c.append(_timed(det)[1])
        got = set() if ids is None else {int(i) for i in np.asarray(ids).ravel()}
        strict = {lid for mi, lid, _ in w.visible_markers(aid, math.radians(60)) if _in_view(w, aid, mi)}
        expected += len(strict)
        found += len(strict & got)
    spec = w.avatars[aid].camera
    return {
        "arena": arena,
        "camera": spec.name,
        "size": f"{spec.width}x{spec.height}",
        "render_cpu": _stats(render_c),
        "render_wall": _stats(render_w),
        "png_cpu": _stats(png_c),
        "aruco_cpu": _stats(det_c),
        "markers_expected": expected,
        "markers_found": found,
        "recall": found / expected if expected else None,
    }


def _in_view(w: Any, aid: str, mi: int) -> bool:
    from haa.sim.geometry import wrap_angle

    m = w.arena.markers[mi]
    e = w.arena.edges
    x, y, th = w.true_pose(aid)
    u = (e.b[m.edge] - e.a[m.edge]) / e.length[m.edge]
    fov = w.avatars[aid].camera.fov
    for s in (m.s0, m.s0 + m.plate):
        px, py = e.a[m.edge] + u * s
        if abs(wrap_angle(math.atan2(py - y, px - x) - th)) > fov / 2 * 0.97:
            return False
    return True


def bench_sensors(readings: int, seed: int = 3) -> dict[str, Any]:
    from haa.sim.world import World

    w = World.from_arena("large", seed=seed)
    others = [w.add_avatar(k) for k in TEAM[1:]]
    del others
    aid = w.add_avatar("sweeper", (9.0, 7.25, 0.3))
    poses = _random_poses(w, readings, 0.25, seed)
    sonar_w, sonar_c, lm_c = [], [], []
    for p in poses:
        av = w.avatars[aid]
        av.body.position = p[0], p[1]
        av.body.angle = p[2]
        wall, cpu = _timed(lambda: w.sonar(aid))
        sonar_w.append(wall)
        sonar_c.append(cpu)
        lm_c.append(_timed(lambda: w.landmark_observations(aid))[1])
    return {
        "sonar_scan_cpu": _stats(sonar_c),
        "sonar_scan_wall": _stats(sonar_w),
        "sonar_per_sonar_cpu_ms": float(np.mean(sonar_c)) * 1e3 / 5,
        "landmarks_cpu": _stats(lm_c),
        "arena": "large",
        "avatars_in_world": len(w.avatars),
    }


def run_sim_bench(quick: bool = False) -> dict[str, Any]:
    import cv2

    cv2.setNumThreads(1)
    seconds = 30.0 if quick else 300.0
    frames = 40 if quick else 300
    out: dict[str, Any] = {
        "stepping": [bench_stepping(seconds, sensors=False), bench_stepping(seconds, sensors=True)],
        "camera": [
            bench_camera("small", "seeker", frames),
            bench_camera("small", "sweeper", frames),
            bench_camera("large", "enhanced_seeker", frames),
        ],
        "sensors": bench_sensors(400 if quick else 3000),
        "quick": quick,
    }
    return out
