"""haa-sim: the avatar simulator as a gRPC service (proto/haa/pb/sim.proto), and a small blocking client.

```
haa-sim --arena small|large|FILE --listen HOST:PORT --seed S [--speed X | --step] [--schedule FILE]
        [--token-file FILE] [--tick 0.05] [--drift thesis|table|systematic] [--metrics-port P]
```

* Clock. Real time by default; `--speed X` runs X simulated seconds per wall second (as fast as it can when
  X is more than the machine manages; `Info.achieved_speed` says what it gets); `--step` freezes the clock
  so that only `SimControl.Step(dt)` advances it — deterministic for a given seed and call sequence, for
  tests. Time advances in ticks of `--tick` simulated seconds (physics sub-steps inside, haa.sim.world).
* Everything runs on one asyncio loop: the world is only touched between ticks, so no locks. Readings are
  produced inside the tick (synchronously, hence deterministically) and queued to the stream handlers:
  odometry at each subscriber's period, sonar every 1.0 s of each sweeper's life (whether anyone listens or
  not, so readings do not depend on subscribers), action progress at the requested period.
* AvatarSim is what avatar agents use (hardware stand-in): Register (create, or attach to an avatar that
  joined by schedule), Release (retire), Act (an AvatarBase action; the stream ends with its outcome),
  Cancel, SetVelocity, Odometry and Sonar streams, Capture (a rendered frame: raw RGB, PNG or JPEG), Detect (the
  camera's landmark and collectable detections), Events (joined / retired / crashed / picked / dropped /
  deposited). A retired or crashed avatar's streams end with UNAVAILABLE, like hardware that stopped
  answering; calls about it get UNAVAILABLE too.
* GroundTruth serves what metrics need: Info (arena YAML, time, mode), Poses (true and odometry), the ideal
  OccupancyGrid with the explorable mask (eq. 7.1-1/7.1-2), Landmarks, Collectables.
* SimControl: Step (step mode only), Join / Retire / Crash on demand (the schedule's actions).

With `--token-file`, every call must carry the token in metadata `x-haa-token` (else UNAUTHENTICATED, checked
before the request is decoded: haa.rpcguard); a request that does not parse is INVALID_ARGUMENT, and no call
ends in UNKNOWN. Requests up to gRPC's default 4 MiB are accepted (larger: RESOURCE_EXHAUSTED), replies up
to 32 MiB (a raw 640x480 capture is 0.9 MiB).
Logs are JSON lines on stderr; the first is {"event": "listening", "address": ..., "port": ..., "metrics": URL}.
With `--metrics-port P` (or HAA_METRICS_PORT) it serves Prometheus metrics on http://<listen host>:P/metrics
(haa.sim.metrics, docs/metrics.md: simulated time, avatars by status, streams, refused calls, CPU).

This module is the server process (arguments, building the world, serving, `main`); the parts are
haa.sim.simcore (world, clock, subscriptions), haa.sim.servicer (the three services), haa.sim.convert (messages
from the world) and haa.sim.client (`SimClient`), whose names are re-exported here.
"""


from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

from grpc import aio

from haa import files
from haa.sim.arena import ArenaError, load_arena
from haa.sim.avatars import DRIFT_MODELS
from haa.sim.client import SimClient, truth_from_server
from haa.sim.convert import (
    MD_CALLER,
    MD_TOKEN,
    avatar_info,
    camera_info,
    decode_frame,
    encode_frame,
    event_msg,
    pose_msg,
)
from haa.sim.schedule import ScheduleError, load_schedule
from haa.sim.servicer import SimService, authed
from haa.sim.simcore import DEFAULT_PERIOD, DEFAULT_TICK, QUEUE_MAX, SimCore, log
from haa.sim.world import World

__all__ = [
    "DEFAULT_PERIOD",
    "DEFAULT_TICK",
    "MD_CALLER",
    "MD_TOKEN",
    "QUEUE_MAX",
    "Settings",
    "SimClient",
    "SimCore",
    "SimService",
    "authed",
    "avatar_info",
    "build",
    "camera_info",
    "decode_frame",
    "encode_frame",
    "event_msg",
    "log",
    "main",
    "parse_args",
    "pose_msg",
    "serve",
    "truth_from_server",
]


@dataclass
class Settings:
    arena: str
    listen: str
    seed: int
    speed: float
    step: bool
    tick: float
    schedule: Path | None
    token_file: Path | None
    drift: str = "thesis"
    metrics_port: int = 0


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(prog="haa-sim", description="HAA avatar simulator service (docs/sim.md).")
    p.add_argument("--arena", default="small", help='"small", "large" or an arena YAML file (default small)')
    p.add_argument("--listen", default="127.0.0.1:7100", help="HOST:PORT to serve on (port 0: any free port)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random thing (default 0)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--step", action="store_true", help="step mode: time advances only by SimControl.Step")
    p.add_argument("--tick", type=float, default=DEFAULT_TICK, help=f"simulated seconds per tick ({DEFAULT_TICK})")
    p.add_argument("--schedule", type=Path, help="mission file whose `schedule` makes avatars join/retire/crash")
    p.add_argument("--token-file", type=Path, help="require this token in metadata x-haa-token")
    p.add_argument(
        "--drift",
        choices=DRIFT_MODELS,
        default="thesis",
        help="odometry drift model: thesis (random walk, default), table (the same with Table 6.2-3's seeker"
        " drift as printed, 10x the default's) or systematic (table + scale and heading bias)",
    )
    p.add_argument("--metrics-port", default=os.environ.get("HAA_METRICS_PORT") or "0",
                   help="serve Prometheus metrics on http://<listen host>:PORT/metrics (haa.metrics; env "
                   "HAA_METRICS_PORT; 0 = off, the default)")
    a = p.parse_args(argv)

    def fail(msg: str) -> None:
        p.exit(2, f"haa-sim: error: {msg}\n")

    if not str(a.metrics_port).isdigit() or int(a.metrics_port) > 65535:
        fail(f"--metrics-port: {a.metrics_port!r} is not a port number (0..65535)")

    if not (a.speed > 0 and math.isfinite(a.speed)):
        fail(f"--speed: {a.speed} must be a positive number")
    if not (0.001 <= a.tick <= 1.0):
        fail(f"--tick: {a.tick} s is outside 0.001..1")
    if a.seed < 0:
        fail(f"--seed: {a.seed} must be >= 0")
    host, sep, port = a.listen.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        fail(f"--listen: {a.listen!r} is not HOST:PORT")
    return Settings(a.arena, a.listen, a.seed, a.speed, a.step, a.tick, a.schedule, a.token_file, a.drift,
                    int(a.metrics_port))


def build(s: Settings) -> tuple[SimCore, str | None]:
    """World and core from settings; raises ArenaError / ScheduleError / OSError with one-line messages."""
    arena = load_arena(s.arena)
    schedule = None
    if s.schedule is not None:
        schedule = list(arena.spec.schedule) + load_schedule(s.schedule, len(arena.start_poses))
    world = World(arena, seed=s.seed, schedule=schedule, drift=s.drift)
    token = None
    if s.token_file is not None:
        try:
            token = files.read_token(s.token_file)
        except files.FileError as e:
            raise OSError(f"--token-file: {e}") from None
    core = SimCore(world, arena.name, "step" if s.step else "realtime", s.speed, s.tick)
    return core, token


async def serve(core: SimCore, listen: str, token: str | None, stop: asyncio.Event | None = None,
                metrics_port: int = 0) -> None:
    server = aio.server(options=[("grpc.max_send_message_length", 32 << 20)])
    svc = SimService(core, token)
    svc.add_to_server(server)
    port = server.add_insecure_port(listen)
    if port == 0:
        raise RuntimeError(f"cannot bind {listen}")
    metrics = None
    if metrics_port:  # Prometheus /metrics on the same loop (haa.sim.metrics, docs/metrics.md)
        from haa.metrics.http import MetricsServer, metrics_bind_host
        from haa.sim.metrics import sim_registry

        metrics = MetricsServer(sim_registry(core, svc, asyncio.get_running_loop()), metrics_bind_host(listen),
                                metrics_port)
        try:
            metrics.start()
        except OSError as e:
            raise RuntimeError(f"--metrics-port: cannot listen on {metrics.host}:{metrics_port}: "
                               f"{e.strerror or e}") from None
    await server.start()
    host = listen.rpartition(":")[0]
    log(
        "listening",
        address=f"{host}:{port}",
        port=port,
        arena=core.arena_name,
        mode=core.mode,
        speed=core.speed,
        seed=core.world.seed,
        tick=core.tick,
        metrics=metrics.url if metrics is not None else "",
    )
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    clock = asyncio.create_task(core.run_clock()) if core.mode == "realtime" else None
    try:
        await stop.wait()
    finally:
        if clock is not None:
            clock.cancel()
        core.close_streams()
        await asyncio.sleep(0.1)
        await server.stop(grace=1.0)
        if metrics is not None:
            await asyncio.to_thread(metrics.stop)
        log("stopped", time=round(core.world.time, 3), dropped=core.dropped, rejected=svc.rejected,
            malformed=svc.malformed, errors=svc.errors)


def main(argv: list[str] | None = None) -> None:
    s = parse_args(argv)
    try:
        core, token = build(s)
    except (ArenaError, ScheduleError) as e:
        print(f"haa-sim: error: {e}", file=sys.stderr)
        sys.exit(2)
    except OSError as e:
        print(f"haa-sim: error: {e.strerror or e}", file=sys.stderr)
        sys.exit(2)
    try:
        asyncio.run(serve(core, s.listen, token, metrics_port=s.metrics_port))
    except RuntimeError as e:
        print(f"haa-sim: error: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
