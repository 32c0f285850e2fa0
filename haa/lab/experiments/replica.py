"""The SLAM replica's costs (docs/slam.md "The SLAM state in the DDB"; thesis §5.2.3, §6.2: the team's map
state shared through the DDB): a recorded run of the robot simulator (haa.slam.explorer) is turned into the
DDB event log (haa.slam.events) and applied item by item to a `haa.slam.replica.SlamReplica`, as the
SupervisorSLAM agent applies it in a mission.

`run_replica_bench(scenario, duration, n_particles, seed, floor)` returns one dict: the mean apply cost per
event kind (µs of thread CPU time, decoding included), the mean encoded size per kind, a checkpoint and a
restore every 10 s of simulated time (their sizes, blobs and times), the published map's size and encoding
time, the replica's memory and its skip counters. `haactl bench replica` prints it as JSON and writes
bench-results/replica.json.
"""

from __future__ import annotations

import time
from typing import Any

from haa.slam.events import Observe, Predict, SlamEvent, encode
from haa.slam.explorer import record
from haa.slam.explorer import scenario as get_scenario
from haa.slam.recording import recording_events
from haa.slam.replay import config_for
from haa.slam.replica import SlamReplica
from haa.slam.sensors import FloorReading, LandmarkReading


def run_replica_bench(
    scenario: str = "basic", duration: float = 0.0, n_particles: int = 100, seed: int = 0, floor: bool = False
) -> dict[str, Any]:
    """Replay a recorded run (haa.slam.explorer) through the log into a replica and measure: apply cost per
    event kind (mean µs, thread CPU time, decoding included), the checkpoint's blobs, size and time every 10 s
    of the run (and the restore's time), the published map's size, memory. Floor readings are not recorded;
    with `floor` a 1.2 m × 1.6 m floor polygon is added at each camera image to measure their cost."""
    sc = get_scenario(scenario)
    rec = record(scenario, duration or sc.mission_s, seed)
    evs: list[SlamEvent] = []
    for ev in recording_events(rec):
        evs.append(ev)
        if floor and isinstance(ev, Observe) and isinstance(ev.reading, LandmarkReading):
            poly = ((0.3, -0.5), (1.5, -0.8), (1.5, 0.8), (0.3, 0.5))
            evs.append(Observe(FloorReading(ev.reading.avatar, ev.reading.t, poly), "floorfinder"))
    items = [encode(e) for e in evs]
    rep = SlamReplica(rec.grid, config_for(rec, n_particles), seed)
    cost: dict[str, list[float]] = {}
    size: dict[str, list[int]] = {}
    ckpts: list[dict[str, Any]] = []
    next_ckpt = 10.0
    t_now = 0.0
    for i, (ev, data) in enumerate(zip(evs, items, strict=True)):
        key = ev.KIND
        if isinstance(ev, Observe):
            key = f"observe.{ev.reading.kind}"
        t0 = time.thread_time()
        res = rep.apply(i, data)
        dt = time.thread_time() - t0
        if res.kind == "request" and res.resampled:
            key = "request.resampled"
        cost.setdefault(key, []).append(dt)
        size.setdefault(key, []).append(len(data))
        if isinstance(ev, Predict):
            t_now = max(t_now, ev.prediction.t)
        if t_now >= next_ckpt:
            next_ckpt += 10.0
            t0 = time.perf_counter()
            blobs = rep.checkpoint()
            t_ck = time.perf_counter() - t0
            t0 = time.perf_counter()
            SlamReplica.restore(blobs)
            t_rs = time.perf_counter() - t0
            ckpts.append(
                {
                    "t": t_now,
                    "bytes": sum(len(b) for b in blobs.values()),
                    "blobs": {k: len(v) for k, v in blobs.items()},
                    "checkpoint_ms": 1000 * t_ck,
                    "restore_ms": 1000 * t_rs,
                    "memory_bytes": rep.memory_bytes(),
                }
            )
    t0 = time.perf_counter()
    m = rep.encode_map()
    t_map = time.perf_counter() - t0
    biggest = max(ckpts, key=lambda c: c["bytes"])
    return {
        "scenario": sc.name,
        "duration_s": rec.duration,
        "n_particles": n_particles,
        "items": len(items),
        "log_bytes": sum(len(d) for d in items),
        "apply_us": {k: round(1e6 * sum(v) / len(v), 1) for k, v in sorted(cost.items())},
        "event_bytes": {k: round(sum(v) / len(v), 1) for k, v in sorted(size.items())},
        "count": {k: len(v) for k, v in sorted(cost.items())},
        "checkpoint_bytes_mean": round(sum(c["bytes"] for c in ckpts) / len(ckpts)),
        "checkpoint_biggest": biggest,
        "checkpoint_ms_mean": round(sum(c["checkpoint_ms"] for c in ckpts) / len(ckpts), 2),
        "restore_ms_mean": round(sum(c["restore_ms"] for c in ckpts) / len(ckpts), 2),
        "map_bytes": len(m),
        "map_encode_ms": round(1000 * t_map, 3),
        "memory_bytes_final": rep.memory_bytes(),
        "counts": rep.counts,
    }
