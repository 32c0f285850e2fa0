"""Agent types for the agent-layer benchmarks (`haactl bench ap4`, `haactl bench ap3 --real`): `ballast` and
`pinger`.

ballast — an agent whose state is a fixed blob of `state_bytes` pseudo-random (incompressible) bytes, 111 kB
by default: the thesis' average agent state in experiment AP-4 (§7.2.4). Its whole state (a small JSON header
with its counters + the blob) goes through `pack_state` on every freeze and through `backup()` once when it
starts (Alg. 7), so a transfer moves 111 kB through the agent table (Alg. 5-6) and a recovery restores
111 kB from the latest backup (Alg. 8). `unpack_state`/`recover` check the blob's length and CRC-32 (a
corrupted state is a fatal error, so the host sees it as an agent failure). It answers the request b"ping"
with b"pong" (the pinger's probe), b"stats" with its counters as JSON, and b"backup" by making a backup.

With {"report_ready": true} it writes `bench/ready/<agent id>` (DDB type json) each time it starts, thaws or
recovers: {"how": start|thaw|recover, "t": unix time, "epoch", "host", "bytes"}. `t` is taken in the agent
process when `on_start` / `on_resume` runs — after the state was unpacked, right before the agent tells its
host it is ready — so the benchmark can see when the agent itself was back, next to the host's timeline
events. The write is not awaited (a slow commit must not hold the mailbox).

    config (JSON): "state_bytes": 111000, "seed": 0, "backup": true (back up once when it starts),
                   "report_ready": false

pinger — sends the request b"ping" to `target` every `period` seconds (5 ms by default; up to
`max_outstanding` requests in flight, each its own task, so a request that waits for a frozen target does
not hold up the next ones) and keeps (time sent, time answered, ok) of the last `keep` requests. The
benchmark asks it, by an operator message {"op": "report", "key": K, "t0": T0, "t1": T1} (unix times),
to write `bench/<K>` (json) with what it saw of the replies that arrived in [t0, t1]: the longest gap
between two consecutive replies (the time the target was unreachable, give or take one period), the longest
round trip of a request sent in the window, and the counts. Other operator messages: {"op": "pause"},
{"op": "resume"}, {"op": "target", "id": ...}. It declares TRANSFER_PENALTY 1.0 (the allocation keeps it
where it is) and is restarted afresh if it fails.

    config (JSON): "target": "<agent id>" (or none: idle until told), "period": 0.005, "timeout": 5.0,
                   "max_outstanding": 2000, "keep": 50000, "paused": false

A request to an agent that crashes is lost (Alg. 8 recovers from the latest backup; what was queued in the
dead process is gone) and times out after `timeout`; `max_outstanding` is large enough that the pinger keeps
sending through a recovery, so the first reply after the gap comes from the first request the recovered
agent received.

Both types live in the `haa.agents` package, so the fork server preloads them like every other agent module
(`haa.sdk.registry.load_builtin`).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import random
import struct
import time
import zlib
from collections import deque
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from haa.sdk.base import AgentBase, AgentContext, RemoteError
from haa.sdk.registry import register

#: the thesis' average agent state (§7.2.4: "the average agent state size was 111 kB")
THESIS_STATE_BYTES = 111_000
#: ballast state: magic, header length, then the JSON header and the blob
STATE_HEAD = struct.Struct(">4sI")
STATE_MAGIC = b"HAAb"
#: largest ballast blob (the agent table takes 64 MiB; a DDB value 4 MiB)
MAX_STATE_BYTES = 32 * 1024 * 1024


class BallastConfig(BaseModel):
    """Config of `ballast` (module docstring); a spawn with anything else is refused before it commits."""

    model_config = ConfigDict(extra="forbid", strict=True)
    state_bytes: int = Field(THESIS_STATE_BYTES, ge=0, le=MAX_STATE_BYTES)
    seed: int = Field(0, ge=0, le=2**63)
    backup: bool = True
    report_ready: bool = False


class PingerConfig(BaseModel):
    """Config of `pinger` (module docstring)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    target: str | None = Field(None, min_length=1, max_length=256)
    period: float = Field(0.005, ge=0.001, le=60)
    timeout: float = Field(5.0, ge=0.01, le=3600)
    max_outstanding: int = Field(2000, ge=1, le=100_000)
    keep: int = Field(50_000, ge=10, le=10**7)
    paused: bool = False


@register
class BallastAgent(AgentBase):
    """An agent with `state_bytes` of state that answers pings (module docstring)."""

    TYPE = "ballast"
    COST = 0.01
    RECOVERY = "backup"
    CONFIG = BallastConfig

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        cfg: BallastConfig = self.cfg
        self.state_bytes = cfg.state_bytes
        self.seed = cfg.seed
        self.backup_at_start = cfg.backup
        self.report_ready = cfg.report_ready
        self.blob = random.Random(self.seed).randbytes(self.state_bytes)
        self.pings = 0
        self.thaws = 0
        self.recoveries = 0
        self.backups = 0
        self._tasks: set[asyncio.Task[None]] = set()

    # -- lifecycle

    async def on_start(self) -> None:
        if self.backup_at_start:
            self._backup()
        self._ready("start")

    async def on_resume(self, how: str) -> None:
        self._ready(how)

    def _backup(self) -> None:
        self.backups += 1
        self.backup()

    def _ready(self, how: str) -> None:
        if not self.report_ready:
            return
        stamp = {"how": how, "t": time.time(), "epoch": self.epoch, "host": self.host, "bytes": len(self.blob)}
        task = asyncio.get_running_loop().create_task(self._put_ready(stamp))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _put_ready(self, stamp: dict[str, Any]) -> None:
        try:
            await self.ddb_put_json(f"bench/ready/{self.id}", stamp, timeout=10.0)
        except Exception as e:  # the benchmark sees the stamp missing; the agent goes on
            self.log("ballast_ready_error", level="warning", error=f"{type(e).__name__}: {e}")

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"ping":
            self.pings += 1
            return b"pong"
        if payload == b"stats":
            return json.dumps(self.stats()).encode()
        if payload == b"backup":
            self._backup()
            return b"ok"
        raise ValueError(f"unknown ballast request {payload[:40]!r}")

    def stats(self) -> dict[str, Any]:
        return {"name": self.name, "epoch": self.epoch, "host": self.host, "bytes": len(self.blob),
                "pings": self.pings, "thaws": self.thaws, "recoveries": self.recoveries, "backups": self.backups}

    # -- state

    def pack_state(self) -> bytes:
        head = json.dumps({"v": 1, "seed": self.seed, "n": len(self.blob), "crc": zlib.crc32(self.blob),
                           "pings": self.pings, "thaws": self.thaws, "recoveries": self.recoveries,
                           "backups": self.backups}, separators=(",", ":")).encode()
        return STATE_HEAD.pack(STATE_MAGIC, len(head)) + head + self.blob

    def unpack_state(self, data: bytes) -> None:
        self._load(data)
        self.thaws += 1

    def recover(self, backup: bytes | None) -> None:
        if backup is not None:
            self._load(backup)
        self.recoveries += 1

    def _load(self, data: bytes) -> None:
        if len(data) < STATE_HEAD.size:
            raise ValueError(f"ballast state: {len(data)} bytes is shorter than its header")
        magic, n = STATE_HEAD.unpack_from(data)
        if magic != STATE_MAGIC:
            raise ValueError(f"ballast state: bad magic {magic!r}")
        head = json.loads(data[STATE_HEAD.size:STATE_HEAD.size + n])
        if head.get("v") != 1:
            raise ValueError(f"ballast state: unknown version {head.get('v')!r}")
        blob = data[STATE_HEAD.size + n:]
        if len(blob) != head["n"] or zlib.crc32(blob) != head["crc"]:
            raise ValueError(f"ballast state: blob of {len(blob)} bytes does not match its header (corrupted)")
        self.blob = blob
        self.seed = int(head["seed"])
        self.pings, self.thaws = int(head["pings"]), int(head["thaws"])
        self.recoveries, self.backups = int(head["recoveries"]), int(head["backups"])


@register
class PingerAgent(AgentBase):
    """Requests b"ping" from a target every `period`; reports reply gaps on demand (module docstring)."""

    TYPE = "pinger"
    COST = 0.05
    TRANSFER_PENALTY = 1.0
    RECOVERY = "restart"
    CONFIG = PingerConfig

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        cfg: PingerConfig = self.cfg
        self.target: str | None = cfg.target
        self.period = cfg.period
        self.timeout = cfg.timeout
        self.max_outstanding = cfg.max_outstanding
        self.paused = cfg.paused
        #: (sent, answered or 0, ok) per request, oldest first
        self.records: deque[tuple[float, float, bool]] = deque(maxlen=cfg.keep)
        self.outstanding = 0
        self.sent = self.answered = self.failed = 0
        self._tasks: set[asyncio.Task[None]] = set()

    async def on_start(self) -> None:
        self.every(self.period, self._tick)

    async def on_resume(self, how: str) -> None:
        self.every(self.period, self._tick)

    def _tick(self) -> None:
        if self.paused or not self.target or self.outstanding >= self.max_outstanding:
            return
        self.outstanding += 1
        self.sent += 1
        task = asyncio.get_running_loop().create_task(self._one(self.target))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _one(self, target: str) -> None:
        t = time.time()
        ok = False
        try:
            ok = await self.request(target, b"ping", timeout=self.timeout) == b"pong"
        except (TimeoutError, RemoteError, RuntimeError):
            ok = False
        finally:
            self.outstanding -= 1
        self.answered += ok
        self.failed += not ok
        self.records.append((t, time.time(), ok))

    async def on_message(self, src: str, payload: bytes) -> None:
        cmd = json.loads(payload)
        if not isinstance(cmd, dict):
            raise ValueError("pinger command: must be a JSON object")
        op = cmd.get("op")
        if op == "pause":
            self.paused = True
        elif op == "resume":
            self.paused = False
        elif op == "target":
            self.target = str(cmd["id"])
        elif op == "report":
            report = self.report(float(cmd["t0"]), float(cmd["t1"]))
            await self.ddb_put_json(f"bench/{cmd['key']}", report, timeout=10.0)
        else:
            raise ValueError(f"unknown pinger op {op!r}")

    def report(self, t0: float, t1: float) -> dict[str, Any]:
        """What the pinger saw of the replies that arrived in [t0, t1] (module docstring)."""
        done = sorted(a for _s, a, ok in self.records if ok and a <= t1)
        before = [a for a in done if a < t0]
        inside = [a for a in done if a >= t0]
        points = ([before[-1]] if before else []) + inside
        gaps = [b - a for a, b in itertools.pairwise(points)]
        sent_in = [(s, a, ok) for s, a, ok in self.records if t0 <= s <= t1]
        rtts = [a - s for s, a, ok in sent_in if ok]
        return {
            "t0": t0, "t1": t1, "period": self.period, "target": self.target,
            "replies": len(inside), "sent": len(sent_in), "failed": sum(1 for _s, _a, ok in sent_in if not ok),
            "max_gap": max(gaps) if gaps else None,
            "gap_start": points[gaps.index(max(gaps))] if gaps else None,
            "gap_end": points[gaps.index(max(gaps)) + 1] if gaps else None,
            "max_rtt": max(rtts) if rtts else None,
            "totals": {"sent": self.sent, "answered": self.answered, "failed": self.failed},
        }
