"""Demo agent types: `counter`, `spawner`, `busy` and `probe` (for `make demo`, chaos tests and unit tests).

counter — a pair of agents exchanging numbered messages, to check the transfer and recovery algorithms
from the agents' point of view. Each pings its peer every `period` seconds with (gen, seq) and checks
every stream it receives, per sender: the next expected number and the numbers still missing. It counts

    received             messages taken (in order, or late filling a gap)
    lost                 numbers skipped (a gap) and never filled      -> a routing bug unless recovery
    out_of_order         a number that filled an earlier gap           -> a routing bug
    duplicate            a number seen before                          -> a routing bug
    lost_after_recovery  a gap right after this agent or the sender was recovered from an older backup
                         (Alg. 8 is lossy by design: AR-Recovery promises the latest backup, no more)
    resent_after_recovery numbers a recovered sender used again (its backup was older than its last send)
    stale                messages of an older life of a sender that arrived after its newer life

`gen` is the sender's life: its epoch when it started, raised at every recovery (max(gen + 1, epoch)), so a
receiver can tell a recovered sender's restart from duplicates. The counters, expected numbers and gaps are
in pack_state, so a transfer (freeze/thaw) keeps them exactly; `backup()` runs every `backup_every`
messages. Counters are readable through the request b"stats" (JSON) and are written to DDB key
`demo/<agent name>` (type json) every `stats_period` seconds. Requests b"pause" / b"resume" stop and restart
the pinging (tests compare counts at rest), b"backup" makes a backup now.

    config (JSON): {"peer": "<agent id>"} or {"spawn_peer": true}   (the child gets {"peer": <parent id>})
                   "period": 0.05, "payload": 0 (extra bytes per message), "backup_every": 100,
                   "stats_period": 1.0, "ddb": true (write the stats to the DDB),
                   "paused": false (start without pinging, until the request b"resume": tests start both
                   agents of a pair paused, so that no first ping goes to a peer that does not exist yet)

spawner — spawns `count` children of `type` with `config` through spawn_child (parent/child naming:
A3 -> A3.1, A3.2, ...); request b"children" -> JSON list of child ids.

busy — burns `cpu` (fraction of one core) in slices of `slice` seconds (to exercise the allocation's cost
measurement); request b"hang" blocks its event loop forever (to exercise hang detection); request
{"cpu": x} changes the share; b"stats" -> JSON.

probe — a scriptable agent for tests and operators: every request is a JSON command {"op": ...} (echo,
send (also "count" times, "size" bytes), request, sleep, ddb_get, ddb_put, ddb_write, ddb_log, watch,
watch_log, unwatch, spawn_child (optional "key"), set, backup, state, timer, log, stop, raise, exit, hang, garbage,
oversize, bigmsg); see `ProbeAgent.on_request`. It
counts the plain messages it receives and keeps them (state "messages") unless its config says
{"record": false}.

Each type declares its config as a pydantic model (`CONFIG`: CounterConfig, SpawnerConfig, BusyConfig,
ProbeConfig), so a spawn with a config the type cannot start with is refused with the reason before it is
committed (docs/agents.md, "Configs"); the agent reads the validated values from `self.cfg`.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import os
import struct
import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from haa.core.ddb import ops as ddbmod
from haa.pb import agent_pb2 as apb
from haa.sdk.base import AgentBase, AgentContext, RemoteError
from haa.sdk.channel import MAX_AGENT_MESSAGE
from haa.sdk.registry import register

#: counter message: magic, sender life (gen), sequence number (from 1), then `payload` padding bytes
PING = struct.Struct(">4sQQ")
PING_MAGIC = b"HAAc"
#: gaps remembered per stream (older ones are given up as lost)
MAX_MISSING = 1000


#: config models: unknown keys and values of the wrong JSON type are refused (strict: "1" is not a number)
_STRICT = ConfigDict(extra="forbid", strict=True)


class CounterConfig(BaseModel):
    """Config of `counter` (module docstring)."""

    model_config = _STRICT
    period: float = Field(0.05, ge=0.001, le=3600)
    payload: int = Field(0, ge=0, le=8 * 1024 * 1024)
    backup_every: int = Field(100, ge=0, le=10**12)
    stats_period: float = Field(1.0, ge=0.01, le=3600)
    ddb: bool = True
    spawn_peer: bool = False
    peer: str | None = Field(None, min_length=1, max_length=256)
    paused: bool = False


class SpawnerConfig(BaseModel):
    """Config of `spawner`: `count` children of `type` with `config`."""

    model_config = _STRICT
    type: str = Field("probe", min_length=1, max_length=64)
    count: int = Field(1, ge=0, le=1000)
    config: dict[str, Any] | list[Any] | str = Field(default_factory=dict)


class BusyConfig(BaseModel):
    """Config of `busy`: the share of one core it burns, in slices of `slice` seconds."""

    model_config = _STRICT
    cpu: float = Field(0.3, ge=0.0, le=1.0)
    slice: float = Field(0.05, ge=0.005, le=1.0)


class ProbeConfig(BaseModel):
    """Config of `probe`: a JSON object; "value" (its initial value), "record" (false: do not keep the
    messages received). Other keys are allowed: tests give it whatever they like."""

    model_config = ConfigDict(extra="allow")
    value: Any = None
    record: Any = True


def _number(cfg: dict[str, Any], key: str, default: float, lo: float, hi: float) -> float:
    v = cfg.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
        raise ValueError(f"config.{key}: must be a number in [{lo}, {hi}], got {v!r}")
    return float(v)


class _Stream:
    """What a receiver knows of one sender's numbered messages."""

    __slots__ = ("adopt", "duplicate", "expected", "gen", "lost", "lost_after_recovery", "missing", "out_of_order",
                 "received", "resent_after_recovery", "stale")

    def __init__(self, gen: int, expected: int = 1, adopt: bool = False) -> None:
        self.gen = gen
        self.expected = expected
        self.missing: list[int] = []
        self.adopt = adopt
        self.received = self.lost = self.out_of_order = self.duplicate = 0
        self.lost_after_recovery = self.resent_after_recovery = self.stale = 0

    def to_json(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__slots__}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> _Stream:
        s = cls(int(d["gen"]))
        for k in cls.__slots__:
            if k in d:
                setattr(s, k, list(d[k]) if k == "missing" else d[k])
        return s

    def take(self, gen: int, seq: int) -> None:
        if gen < self.gen:
            self.stale += 1
            return
        if gen > self.gen or self.adopt:
            # the sender (gen > self.gen) or this receiver (adopt) was recovered: start the stream again here
            if seq > self.expected:
                self.lost_after_recovery += seq - self.expected
            elif seq < self.expected and gen > self.gen:
                self.resent_after_recovery += self.expected - seq
            self.gen, self.expected, self.missing, self.adopt = gen, seq + 1, [], False
            self.received += 1
            return
        if seq == self.expected:
            self.expected += 1
            self.received += 1
        elif seq > self.expected:
            self.lost += seq - self.expected
            self.missing.extend(range(self.expected, seq))
            del self.missing[:-MAX_MISSING]
            self.expected = seq + 1
            self.received += 1
        elif seq in self.missing:
            self.missing.remove(seq)
            self.lost -= 1
            self.out_of_order += 1
            self.received += 1
        else:
            self.duplicate += 1


@register
class CounterAgent(AgentBase):
    """Numbered ping-pong with loss/order/duplicate accounting (module docstring)."""

    TYPE = "counter"
    COST = 0.02
    RECOVERY = "backup"
    CONFIG = CounterConfig

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        cfg: CounterConfig = self.cfg
        self.period = cfg.period
        self.payload = cfg.payload
        self.backup_every = cfg.backup_every
        self.stats_period = cfg.stats_period
        self.use_ddb = cfg.ddb
        self.spawn_peer = cfg.spawn_peer
        self.peer: str | None = cfg.peer
        self.gen = self.epoch
        self.next_seq = 1
        self.sent = 0
        self.paused = cfg.paused
        self.streams: dict[str, _Stream] = {}
        self.adopt_new = False
        self.since_backup = 0
        self.backups = 0
        self.recoveries = 0
        self.thaws = 0
        self.ddb_errors = 0

    # -- lifecycle

    async def on_start(self) -> None:
        if self.peer is None and self.spawn_peer:
            child_cfg = {"peer": self.id, "period": self.period, "payload": self.payload,
                         "backup_every": self.backup_every, "stats_period": self.stats_period, "ddb": self.use_ddb}
            self.peer = await self.spawn_child("counter", child_cfg)
        self._arm()

    async def on_resume(self, how: str) -> None:
        if how == "thaw":
            self.thaws += 1
        self._arm()

    def _arm(self) -> None:
        self.every(self.period, self._ping)
        self.every(self.stats_period, self._publish)

    def _ping(self) -> None:
        if self.paused or not self.peer:
            return
        self.send(self.peer, PING.pack(PING_MAGIC, self.gen, self.next_seq) + bytes(self.payload))
        self.next_seq += 1
        self.sent += 1
        self._count_for_backup()

    def _count_for_backup(self) -> None:
        self.since_backup += 1
        if self.backup_every and self.since_backup >= self.backup_every:
            self.since_backup = 0
            self.backups += 1
            self.backup()

    async def on_message(self, src: str, payload: bytes) -> None:
        if len(payload) < PING.size or payload[:4] != PING_MAGIC:
            self.log("counter_unknown_message", src=src, size=len(payload))
            return
        _, gen, seq = PING.unpack_from(payload)
        st = self.streams.get(src)
        if st is None:
            st = self.streams[src] = _Stream(gen, 1, adopt=self.adopt_new)
        st.take(gen, seq)
        self._count_for_backup()

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"stats":
            return json.dumps(self.stats()).encode()
        if payload == b"pause":
            self.paused = True
            return json.dumps(self.stats()).encode()
        if payload == b"resume":
            self.paused = False
            return b"ok"
        if payload == b"backup":
            self.backups += 1
            self.backup()
            return b"ok"
        raise ValueError(f"unknown counter request {payload[:40]!r}")

    def stats(self) -> dict[str, Any]:
        keys = ("received", "lost", "out_of_order", "duplicate", "lost_after_recovery", "resent_after_recovery",
                "stale")
        total = {k: sum(getattr(s, k) for s in self.streams.values()) for k in keys}
        return {
            "name": self.name, "id": self.id, "peer": self.peer, "gen": self.gen, "epoch": self.epoch,
            "sent": self.sent, "next_seq": self.next_seq, **total, "backups": self.backups,
            "recoveries": self.recoveries, "thaws": self.thaws, "paused": self.paused,
            "streams": {src: {k: getattr(s, k) for k in (*keys, "gen", "expected")} for src, s in self.streams.items()},
        }

    async def _publish(self) -> None:
        if not self.use_ddb:
            return
        snapshot = self.stats()
        snapshot["time"] = time.time()
        # not awaited in the mailbox: a slow commit must not hold up the pings
        task = asyncio.create_task(self._put_stats(snapshot))
        task.add_done_callback(lambda t: t.cancelled() or t.exception())

    async def _put_stats(self, snapshot: dict[str, Any]) -> None:
        try:
            await self.ddb_put_json(f"demo/{self.name}", snapshot, timeout=10.0)
        except Exception as e:
            self.ddb_errors += 1
            if self.ddb_errors <= 3:
                self.log("counter_ddb_error", level="warning", error=f"{type(e).__name__}: {e}")

    # -- state

    def pack_state(self) -> bytes:
        return json.dumps({
            "v": 1, "peer": self.peer, "gen": self.gen, "next_seq": self.next_seq, "sent": self.sent,
            "paused": self.paused, "adopt_new": self.adopt_new, "since_backup": self.since_backup,
            "backups": self.backups, "recoveries": self.recoveries, "thaws": self.thaws,
            "streams": {k: s.to_json() for k, s in self.streams.items()},
        }, separators=(",", ":")).encode()

    def unpack_state(self, data: bytes) -> None:
        d = json.loads(data)
        if d.get("v") != 1:
            raise ValueError(f"counter state: unknown version {d.get('v')!r}")
        self.peer = d["peer"]
        self.gen = int(d["gen"])
        self.next_seq = int(d["next_seq"])
        self.sent = int(d["sent"])
        self.paused = bool(d["paused"])
        self.adopt_new = bool(d["adopt_new"])
        self.since_backup = int(d["since_backup"])
        self.backups = int(d["backups"])
        self.recoveries = int(d["recoveries"])
        self.thaws = int(d["thaws"])
        self.streams = {k: _Stream.from_json(v) for k, v in d["streams"].items()}

    def recover(self, backup: bytes | None) -> None:
        if backup is not None:
            self.unpack_state(backup)
        # a new life: receivers restart our stream; we restart theirs at their next message
        self.gen = max(self.gen + 1, self.epoch)
        self.recoveries += 1
        self.adopt_new = True
        for st in self.streams.values():
            st.adopt = True


@register
class SpawnerAgent(AgentBase):
    """Spawns `count` children of `type` (module docstring)."""

    TYPE = "spawner"
    RECOVERY = "backup"
    CONFIG = SpawnerConfig

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        cfg: SpawnerConfig = self.cfg
        self.child_type = cfg.type
        self.count = cfg.count
        self.child_config = cfg.config
        self.children: list[str] = []

    async def on_start(self) -> None:
        for _ in range(self.count):
            self.children.append(await self.spawn_child(self.child_type, self.child_config))
        self.log("spawner_done", children=self.children)
        self.backup()

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"children":
            return json.dumps(self.children).encode()
        raise ValueError(f"unknown spawner request {payload[:40]!r}")

    def pack_state(self) -> bytes:
        return json.dumps({"children": self.children}).encode()

    def unpack_state(self, data: bytes) -> None:
        self.children = list(json.loads(data)["children"])


@register
class BusyAgent(AgentBase):
    """Burns a share of one core; hangs on request (module docstring)."""

    TYPE = "busy"
    COST = 0.3
    RECOVERY = "restart"
    CONFIG = BusyConfig
    #: it burns up to a whole core on purpose (plus its own overhead)
    CPU_LIMIT = 1.5

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        cfg: BusyConfig = self.cfg
        self.share = cfg.cpu
        self.slice = cfg.slice
        self.burned = 0.0

    async def on_start(self) -> None:
        self.every(self.slice, self._burn)

    async def on_resume(self, how: str) -> None:
        self.every(self.slice, self._burn)

    def _burn(self) -> None:
        end = time.perf_counter() + self.share * self.slice
        x = 0
        while time.perf_counter() < end:
            x += 1
        self.burned += self.share * self.slice

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"hang":
            while True:  # block the event loop: no more heartbeats
                time.sleep(3600)
        if payload == b"stats":
            return json.dumps({"cpu": self.share, "burned": self.burned}).encode()
        cmd = json.loads(payload)
        self.share = _number(cmd, "cpu", self.share, 0.0, 1.0)
        return b"ok"

    def pack_state(self) -> bytes:
        return json.dumps({"cpu": self.share, "burned": self.burned}).encode()

    def unpack_state(self, data: bytes) -> None:
        d = json.loads(data)
        self.share, self.burned = float(d["cpu"]), float(d["burned"])


@register
class ProbeAgent(AgentBase):
    """A scriptable agent: requests are JSON commands (module docstring). Records what it receives."""

    TYPE = "probe"
    RECOVERY = "backup"
    CONFIG = ProbeConfig
    MAX_RECORDED = 10_000

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        self.value = ""
        self.messages: list[list[str]] = []  # [src, payload as text]
        self.events: list[list[Any]] = []  # watch events, timers, lifecycle
        self.received = 0
        cfg: ProbeConfig = self.cfg
        if "value" in cfg.model_fields_set:
            self.value = str(cfg.value)
        self.record = cfg.record is not False  # keep the messages received

    def _log_item(self, key: str, index: int, item: bytes) -> None:
        self._record(self.events, ["log", key, index, item.decode("utf-8", "replace")])

    def _record(self, lst: list[Any], item: Any) -> None:
        lst.append(item)
        del lst[: -self.MAX_RECORDED]

    async def on_start(self) -> None:
        self._record(self.events, ["start"])

    async def on_resume(self, how: str) -> None:
        self._record(self.events, ["resume", how])

    def recover(self, backup: bytes | None) -> None:
        super().recover(backup)
        self._record(self.events, ["recover", backup is not None])

    async def on_message(self, src: str, payload: bytes) -> None:
        self.received += 1
        if self.record:
            self._record(self.messages, [src, payload.decode("utf-8", "replace")])

    def pack_state(self) -> bytes:
        return json.dumps({"value": self.value, "messages": self.messages, "events": self.events}).encode()

    def unpack_state(self, data: bytes) -> None:
        d = json.loads(data)
        self.value, self.messages, self.events = d["value"], d["messages"], d["events"]

    def on_stop(self) -> None:
        self.log("probe_stopping", value=self.value)

    async def on_request(self, src: str, payload: bytes) -> bytes:
        cmd = json.loads(payload)
        op = cmd.get("op")
        out: Any = "ok"
        if op == "echo":
            out = cmd.get("data", "")
        elif op == "send":  # "size": send that many bytes instead of "data"; "count": that many times
            data = b"x" * int(cmd["size"]) if "size" in cmd else str(cmd.get("data", "")).encode()
            for i in range(int(cmd.get("count", 1))):
                self.send(cmd["to"], data)
                if i % 256 == 255:
                    await asyncio.sleep(0)  # let the heartbeat and the channel breathe
        elif op == "request":
            try:
                data = str(cmd.get("data", "")).encode()
                r = await self.request(cmd["to"], data, timeout=float(cmd.get("timeout", 5)))
                out = {"ok": r.decode("utf-8", "replace")}
            except (TimeoutError, RemoteError) as e:
                out = {"error": f"{type(e).__name__}: {e}"}
        elif op == "sleep":
            await asyncio.sleep(float(cmd.get("seconds", 0.1)))
        elif op == "ddb_get":
            v = await self.ddb_get(cmd["key"], timeout=float(cmd.get("timeout", 5)))
            out = None if v is None else v.decode("utf-8", "replace")
        elif op == "ddb_put":
            await self.ddb_put(cmd["key"], str(cmd.get("value", "")).encode(), cmd.get("type", "blob"))
        elif op == "ddb_scan":  # {key: text} of the objects under "prefix" (at most "limit")
            got = await self.ddb_scan(cmd.get("prefix", ""), int(cmd.get("limit", 0)))
            out = {"objects": {k: v.decode("utf-8", "replace") for k, v in got.items()},
                   "truncated": self._ctx.scan_truncated}
        elif op == "ddb_write":  # "ops": [["put", key, type, value] | ["log_append", key, [text, ...]] | ...]
            ops = [_probe_op(o) for o in cmd["ops"]]
            out = await self.ddb_write(ops, atomic=bool(cmd.get("atomic", False)))
        elif op == "ddb_log":  # a log read back: {"first": n, "items": [text, ...]}, or None if absent
            v = await self.ddb_get(cmd["key"], timeout=float(cmd.get("timeout", 5)))
            if v is not None:
                first, items = ddbmod.decode_log(v)
                out = {"first": first, "items": [i.decode("utf-8", "replace") for i in items]}
            else:
                out = None
        elif op == "watch_log":
            out = self.watch_log(cmd["key"], functools.partial(self._log_item, cmd["key"]))
        elif op == "watch":
            prefix = cmd["prefix"]
            out = self.watch(prefix, lambda ev, key, val: self._record(
                self.events, ["watch", ev, key, None if val is None else val.decode("utf-8", "replace")]))
        elif op == "unwatch":
            self.unwatch(int(cmd["id"]))
        elif op == "spawn_child":
            out = await self.spawn_child(cmd["type"], cmd.get("config", b""), key=cmd.get("key"))
        elif op == "set":
            self.value = str(cmd["value"])
        elif op == "backup":
            self.backup()
        elif op == "state":
            out = {"value": self.value, "messages": self.messages, "events": self.events, "name": self.name,
                   "id": self.id, "parent": self.parent, "epoch": self.epoch, "host": self.host, "pid": os.getpid(),
                   "late_replies": self._ctx.late_replies, "handler_errors": self._ctx.handler_errors,
                   "received": self.received}
        elif op == "timer":
            self.call_later(float(cmd.get("delay", 0.01)), lambda: self._record(self.events, ["timer", cmd.get("tag")]))
        elif op == "log":
            self.log("probe_log", **cmd.get("fields", {}))
        elif op == "stop":
            self.stop()
        elif op == "raise":
            raise ValueError(cmd.get("message", "probe was asked to raise"))
        elif op == "exit":
            os._exit(int(cmd.get("code", 3)))
        elif op == "hang":
            while True:
                time.sleep(3600)
        elif op in ("garbage", "oversize", "bigmsg"):
            raw = self._ctx.send_raw
            if raw is None:
                raise RuntimeError("no raw channel access")
            if op == "garbage":  # a frame whose body is not an AgentToHost
                body = bytes(cmd.get("body", "\x00\xff\xfe garbage").encode("latin-1"))
                raw(struct.pack(">I", len(body)) + body)
            elif op == "bigmsg":  # a well-formed frame whose message is over MAX_AGENT_MESSAGE (send() refuses it)
                msg = apb.AgentMsg(src=self.id, dst=self.id, payload=bytes(MAX_AGENT_MESSAGE + 1))
                body = apb.AgentToHost(sent=msg).SerializeToString()
                raw(struct.pack(">I", len(body)) + body)
            else:  # a header announcing 2 GiB
                raw(struct.pack(">I", 0x7FFFFFFF))
            with contextlib.suppress(Exception):
                await asyncio.sleep(3600)  # the host drops us
        else:
            raise ValueError(f"unknown probe op {op!r}")
        return json.dumps(out).encode()


def _probe_op(o: list[Any]) -> Any:
    """A probe's JSON op -> a DdbOp: ["put", key, type, value] (value: JSON for json, text for blob, an int for
    counter), ["delete", key], ["append", key, text], ["add", key, n], ["log_append", key, [text, ...]],
    ["log_trim", key, upto]."""
    kind, key, *args = o
    if kind == "put":
        type_name, value = args
        if type_name == "blob":
            value = str(value).encode()
        return ddbmod.put(key, type_name, value)
    if kind == "delete":
        return ddbmod.delete(key)
    if kind == "append":
        return ddbmod.append(key, str(args[0]).encode())
    if kind == "add":
        return ddbmod.add(key, int(args[0]))
    if kind == "log_append":
        return ddbmod.log_append(key, [str(i).encode() for i in args[0]])
    if kind == "log_trim":
        return ddbmod.log_trim(key, int(args[0]))
    raise ValueError(f"unknown ddb op {kind!r}")
