"""AgentBase, the class every agent derives from, and AgentContext, the machinery behind it (thesis §6.1.1).

An agent is a subclass of `AgentBase` registered under a type name (`haa.sdk.registry`). Its host runs it
in an OS process of its own (`haa.sdk.runner`, started by the fork server); the agent talks only to its
host, over one channel (`haa.sdk.channel`). What an agent gets:

* identity: `self.id` (a UUID string, the same on every host and across transfers and recoveries),
  `self.name` (display name by parentage: "A6.2.1" is a child of "A6.2"), `self.parent` (id or None),
  `self.config` (bytes; `self.config_json()` parses JSON), `self.epoch` (the fencing epoch of this instance),
  `self.host` (the host running this instance);
* messages: `send(to, payload)` — routed by the hosts, the sender never knows where the receiver lives;
  `await request(to, payload, timeout=...)` — a conversation: the receiver's `on_request` answers it;
* timers: `call_later(delay, fn)`, `every(period, fn)` (cancelled when the agent freezes);
* DDB: `await ddb_get(key)`, `await ddb_scan(prefix) -> {key: bytes}`, `await ddb_put(key, value, type_name)`,
  `await ddb_put_json(key, obj)`;
  `await ddb_write(ops, atomic=False) -> [reason or "" per op]` (ops built with `haa.core.ddb`: put, delete,
  append, cas, add, log_append, log_trim), `await ddb_log_append(key, items)`; `watch(prefix, callback)`,
  `watch_log(key, callback(index, item))`, `unwatch(id)`; `haa.core.ddb.decode_log(ddb_get bytes)` reads a
  log as (first, items);
* `backup()` (Alg. 7 ll. 1-3), `await spawn_child(type_name, config, key=...)` (idempotent: a retried spawn
  gets the child its first request created, docs/agents.md "Idempotent spawn"), `stop()`,
  `log(event, **fields)`.

Hooks an agent implements (all optional): `on_start()` (a new agent), `on_message(src, payload)`,
`on_request(src, payload) -> bytes`, `pack_state() -> bytes` / `unpack_state(data)` (transfer, Alg. 5 l. 18
and Alg. 6 l. 20), `pack_backup() -> bytes` (defaults to `pack_state()`), `recover(backup)` (Alg. 8 l. 11;
defaults to `unpack_state(backup)` when there is a backup), `on_resume(how)` (after a thaw or a recovery: the
place to re-arm timers and watches) and `on_stop()`. State is bytes the agent packs itself: no pickle.

Execution model. Everything the agent's code does runs on one scheduler (`haa.sdk.sched`: the process's
asyncio loop and wall clock by default; the simulator's virtual time in `haa.lab.dsim.vagent`, issue 17), and the
*handlers* run one at a time, in arrival order, from one mailbox: messages and requests (in delivery order —
the host's transfer algorithm relies on it), timer callbacks, watch notifications, and the
start/thaw/recover/freeze steps. A handler may await (a request, a DDB read): the mailbox waits for it — the
next handler starts only when the current one returns. Replies to the agent's own requests and answers from
its host do not go through the mailbox (they resolve the awaiting call directly), so awaiting them inside a
handler cannot deadlock on the agent itself. The loop must not be blocked: the agent heartbeats its host from
the same loop, and an agent that does not heartbeat for the host's hang timeout is killed as hung.

Freeze (Alg. 5 ll. 17-20): timers stop at once (a queued tick is dropped), every message delivered before
the freeze is handled, then `pack_state()`, the state goes to the host, and the process exits. Every message
the agent sent before packing reaches the host before its state. Thaw (Alg. 6 ll. 19-22): `unpack_state()`,
then the queued messages in order, then `on_resume("thaw")`, then Ready. Recover (Alg. 8 ll. 10-12):
`recover(backup or None)`, then any queued messages, then `on_resume("recover")`, then Ready.

Errors. An exception in `on_message`, a timer or a watch callback is logged (event `handler_error`) and
the agent goes on, unless the class sets `CRASH_ON_ERROR = True`; an exception in `on_request` becomes an
error reply (the requester's `request()` raises `RemoteError`). An exception in `on_start`, `unpack_state`,
`recover`, `on_resume` or `pack_state` is fatal: the agent reports it and exits with code 1 (an agent
failure for the host).

`AgentContext` is the host-facing side: the runner feeds it the host's frames (`feed`) and runs its mailbox
worker (`run`); it emits the agent's frames through a callable, so it can be driven in-process by tests.

AgentPlayback (thesis §6.1.4, docs/playback.md): an optional `tap` (haa.lab.playback) sees every input where the
agent consumes it — the mailbox item the worker takes (`_take_item`), the host's answer a call awaited
(`_await_answer`), the reply a request awaited (`_await_reply`), each `now()` and random number (the clock and
random source are wrapped by the tap) — and every frame the agent emits. The recorder writes them to MCAP; the
offline replay (haa.lab.playback.replay) overrides the same three methods to feed the recorded inputs back.
"""

from __future__ import annotations

import asyncio
import functools
import hashlib
import inspect
import json
import random
import sys
import time
import traceback
import uuid
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, ClassVar

import pydantic

from haa.core import ddb as ddbmod
from haa.pb import agent_pb2 as pb
from haa.sdk.channel import message_too_large

# Clock, WALL_CLOCK and ScaledClock live with the schedulers; imported from here as before
from haa.sdk.sched import WALL_CLOCK as WALL_CLOCK
from haa.sdk.sched import AgentScheduler, AsyncioScheduler
from haa.sdk.sched import Clock as Clock
from haa.sdk.sched import ScaledClock as ScaledClock

#: recovery strategies an agent type declares (docs/agents.md, "Recovery strategies")
RECOVERY_STRATEGIES = frozenset({"backup", "restart", "none"})

#: defaults of `AgentBase.MEMORY_LIMIT_MB` and `AgentBase.CPU_LIMIT` (docs/limits.md)
DEFAULT_MEMORY_LIMIT_MB = 512
DEFAULT_CPU_LIMIT = 0.9

#: default timeout of `request()`, seconds
REQUEST_TIMEOUT = 5.0
#: default timeout of the calls answered by the host (DDB, spawn_child), seconds
HOST_TIMEOUT = 30.0
#: longest spawn key (`spawn_child(key=)`; haa.core.agenttable.MAX_SPAWN_KEY)
MAX_SPAWN_KEY = 256

#: fault injection (haactl chaos, docs/chaos.md): an *operator* request (sender "@<host>") whose payload is this
#: prefix followed by a number of seconds makes any agent answer b"hanging", then block its own event loop for
#: that long (no heartbeat, no handler: a stuck computation), then fail with "chaos hang" (exit code 1)
CHAOS_HANG = b"\x00haa-chaos-hang "
#: longest chaos hang, seconds
CHAOS_HANG_MAX = 3600.0

TimerCallback = Callable[[], Any]
WatchCallback = Callable[[str, str, bytes | None], Any]
LogCallback = Callable[[int, bytes], Any]


class RemoteError(Exception):
    """A request failed at the other end: the responder raised, or a host answered for it (no such agent)."""


class HostError(Exception):
    """The host refused a DDB operation or a spawn_child request; the message is the host's reason."""


class AgentFatal(Exception):
    """Raised inside the runtime when the agent cannot go on; the agent reports it and exits with code 1."""


def new_agent_id() -> str:
    """A fresh agent id (a random UUID, thesis §6.1.1)."""
    return str(uuid.uuid4())


def root_name(n: int) -> str:
    """Display name of the n-th agent requested by a host or the operator: "A6"."""
    if n < 0:
        raise ValueError(f"n: must be >= 0, got {n}")
    return f"A{n}"


def child_name(parent_name: str, n: int) -> str:
    """Display name of the n-th child (1-based) of `parent_name`: child_name("A6.2", 1) == "A6.2.1"."""
    if n < 1:
        raise ValueError(f"n: children are numbered from 1, got {n}")
    if not parent_name:
        raise ValueError("parent_name: must not be empty")
    return f"{parent_name}.{n}"


def agent_random(seed: int | str, name: str, epoch: int) -> random.Random:
    """The seeded random source of one agent instance: the mission seed, the agent's name (stable across
    runs, unlike its UUID) and its epoch (a recovered instance draws new numbers)."""
    return random.Random(f"{seed}/{name}/{epoch}")


class Timer:
    """A handle of `call_later` / `every`; `cancel()` it to stop it. Callbacks run in the agent's mailbox."""

    def __init__(self, ctx: AgentContext, fn: TimerCallback, delay: float, period: float | None) -> None:
        self._ctx = ctx
        self.fn = fn
        self.period = period
        self.cancelled = False
        self.fired = 0
        self._queued = False
        ctx._timer_ids += 1
        #: 1-based number of this timer among those the instance armed (AgentPlayback names timers by it)
        self.id = ctx._timer_ids
        self._handle: Any = None
        sched = ctx.sched
        # delays are in the agent's clock; the scheduler's timers run on its own time base (the loop's wall
        # time, or the simulator's virtual time: haa.sdk.sched)
        self._wall_period = None if period is None else ctx.clock.wall_delay(period)
        self._due = sched.time() + ctx.clock.wall_delay(delay)
        self._handle = sched.call_at(self._due, self._fire)

    def cancel(self) -> None:
        self.cancelled = True
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._ctx._timers.discard(self)

    @property
    def active(self) -> bool:
        return not self.cancelled

    def _fire(self) -> None:
        self._handle = None
        if self.cancelled:
            return
        if self.period is not None:
            sched = self._ctx.sched
            # fixed rate; ticks missed while the loop was busy are skipped, not bunched
            assert self._wall_period is not None
            self._due += self._wall_period
            now = sched.time()
            if self._due <= now:
                self._due = now + self._wall_period
            self._handle = sched.call_at(self._due, self._fire)
        if not self._queued:  # a periodic timer whose last tick still waits in the mailbox is not queued twice
            self._queued = True
            self._ctx._put(("timer", self))


class AgentBase:
    """Base class of every agent. See the module docstring; subclass, set `TYPE`, and `@register` it."""

    #: registry name of the type (required, unique): letters, digits, "_", "-", "."
    TYPE: ClassVar[str] = ""
    #: declared processing cost estimate: fraction of one core it is expected to use (allocation input until
    #: the host has measured it)
    COST: ClassVar[float] = 0.01
    #: hardware a host must have to run it (e.g. frozenset({"camera"}))
    HARDWARE: ClassVar[frozenset[str]] = frozenset()
    #: 0..1: how much the allocation should avoid moving it (0 = free to move, 1 = never move while alive)
    TRANSFER_PENALTY: ClassVar[float] = 0.0
    #: at most this many agents of this type on one host (0 = no limit): the allocation never places more, and
    #: those beyond the type's places in the group are unallocatable (issue 15: SupervisorSLAM's "at most one
    #: sensor agent of each type per host", thesis App. III; docs/allocation.md, "per-host limits")
    MAX_PER_HOST: ClassVar[int] = 0
    #: "backup": recover from the latest backup; "restart": start it afresh (on_start, same id and config);
    #: "none": do not recover it (docs/agents.md)
    RECOVERY: ClassVar[str] = "backup"
    #: if True an exception in on_message / a timer / a watch callback kills the agent (an agent failure)
    CRASH_ON_ERROR: ClassVar[bool] = False
    #: the pydantic model of the agent's config (JSON; an empty config reads as {}), or None for a type that
    #: parses its config itself. With a model, the host refuses a spawn whose config does not validate before
    #: anything is committed (`check_config`, asked of the fork server), and `self.cfg` is the validated model
    CONFIG: ClassVar[type[pydantic.BaseModel] | None] = None
    #: resident memory (RSS, MiB) the agent's process may use; over it, its host kills it (docs/agents.md,
    #: "Resource limits"). The address space is capped too, at a margin above it (`haa.hostd.agentmonitor`)
    MEMORY_LIMIT_MB: ClassVar[int] = DEFAULT_MEMORY_LIMIT_MB
    #: CPU the agent may use, as a fraction of one core, sustained over `haa.hostd.agentmonitor.CPU_LIMIT_WINDOW`
    #: (10 s); over it, its host kills it. Per type: a sensor agent may need a whole core (1.0) or more
    CPU_LIMIT: ClassVar[float] = DEFAULT_CPU_LIMIT

    def __init__(self, ctx: AgentContext) -> None:
        self._ctx = ctx
        #: the validated config (an instance of CONFIG) when the type declares a model, else None
        self.cfg: Any = None
        if self.CONFIG is not None:
            why = self.check_config(ctx.config)
            if why:
                raise ValueError(f"config of agent {ctx.name} ({self.TYPE}): {why}")
            self.cfg = self.CONFIG.model_validate_json(ctx.config.strip() or b"{}")

    @classmethod
    def check_config(cls, data: bytes) -> str:
        """'' when `data` is a valid config of this type, else the reason in one line: the first error of
        the model, as `config.<field path>: <message>` (the host shows it to whoever asked for the spawn)."""
        if cls.CONFIG is None:
            return ""
        return config_error(cls.CONFIG, data)

    # ------------------------------------------------------------------ identity

    @property
    def id(self) -> str:
        return self._ctx.agent_id

    @property
    def name(self) -> str:
        return self._ctx.name

    @property
    def parent(self) -> str | None:
        return self._ctx.parent

    @property
    def config(self) -> bytes:
        return self._ctx.config

    @property
    def epoch(self) -> int:
        return self._ctx.epoch

    @property
    def host(self) -> str:
        return self._ctx.host

    def config_json(self, default: Any = None) -> Any:
        """The config parsed as JSON (`default`, or {} if None, when the config is empty)."""
        if not self.config.strip():
            return {} if default is None else default
        try:
            return json.loads(self.config)
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"config of agent {self.name} ({self.TYPE}) is not valid JSON: {e}") from None

    def log(self, event: str, *, level: str = "info", **fields: Any) -> None:
        """A structured line in the host's log: {"event": event, "fields": {agent, name, **fields}}."""
        self._ctx.log(event, level, fields)

    # ------------------------------------------------------------------ hooks

    async def on_start(self) -> None:
        """A new agent (not a thawed or recovered one) begins."""

    async def on_message(self, src: str, payload: bytes) -> None:
        """A plain message from agent `src` ("" = the host or the operator)."""

    async def on_request(self, src: str, payload: bytes) -> bytes:
        """A request from `src`; return the response (raise to send an error reply)."""
        raise NotImplementedError(f"agent type {self.TYPE!r} does not answer requests")

    def pack_state(self) -> bytes:
        """The agent's whole state as bytes (Alg. 5 l. 18, writeState). Stateless agents keep the default."""
        return b""

    def unpack_state(self, data: bytes) -> None:
        """Restore what `pack_state()` returned (Alg. 6 l. 20, readState)."""

    def pack_backup(self) -> bytes:
        """The critical part of the state for `backup()` (Alg. 7 l. 2, backupState); default: pack_state()."""
        return self.pack_state()

    def recover(self, backup: bytes | None) -> None:
        """Restore from the latest backup (Alg. 8 l. 11), None if none was ever made; default: unpack_state."""
        if backup is not None:
            self.unpack_state(backup)

    async def on_resume(self, how: str) -> None:
        """After a thaw (`how` = "thaw") or a recovery ("recover"): re-arm timers and watches here."""

    def on_stop(self) -> None:
        """The agent ends itself (`stop()`) or its host asked it to."""

    # ------------------------------------------------------------------ calls

    def send(self, to: str, payload: bytes) -> None:
        """Send a message to agent `to` through the hosts (FIFO per sender-receiver pair); ValueError if the
        payload exceeds `haa.sdk.channel.MAX_AGENT_MESSAGE` (4 MiB)."""
        self._ctx.send(to, payload)

    async def request(self, to: str, payload: bytes, timeout: float = REQUEST_TIMEOUT) -> bytes:
        """Send a request and wait for its response; TimeoutError, RemoteError. Late replies are dropped."""
        return await self._ctx.request(to, payload, timeout)

    def now(self) -> float:
        """The agent's time in seconds: the wall clock, or the simulated clock a mission set."""
        return self._ctx.clock.now()

    def perf_counter(self) -> float:
        """A monotonic wall clock, seconds, for measuring how long something took (`time.perf_counter()`),
        taken through the agent so that AgentPlayback records it: an agent that reads time.perf_counter(),
        time.time() or the random module itself cannot be replayed (docs/playback.md)."""
        read = getattr(self._ctx, "perf_counter", None)  # a test's stand-in context may not have it
        return read() if read is not None else time.perf_counter()

    async def run_in_thread(self, executor: Any, fn: Callable[..., Any], *args: Any) -> Any:
        """`fn(*args)` on `executor` (a concurrent.futures executor; None = the loop's default), awaited without
        blocking the loop, taken through the agent so that AgentPlayback records when its result came back
        among the other inputs (a replay hands it over at the same point; docs/playback.md)."""
        call = functools.partial(fn, *args)
        run = getattr(self._ctx, "run_in_thread", None)  # a test's stand-in context may not have it
        if run is None:
            return await asyncio.get_running_loop().run_in_executor(executor, call)
        return await run(executor, call)

    @property
    def random(self) -> random.Random:
        """The agent's random source (seeded by the mission when it sets the clock)."""
        return self._ctx.random

    def call_later(self, delay: float, fn: TimerCallback) -> Timer:
        """Run `fn()` (sync or async) once after `delay` seconds of the agent's clock, in the mailbox."""
        return self._ctx.timer(fn, delay, None)

    def every(self, period: float, fn: TimerCallback, *, first: float | None = None) -> Timer:
        """Run `fn()` every `period` seconds of the agent's clock (first after `first`, default `period`)."""
        if period <= 0:
            raise ValueError(f"period: must be > 0, got {period}")
        return self._ctx.timer(fn, period if first is None else first, period)

    async def ddb_get(self, key: str, timeout: float = HOST_TIMEOUT) -> bytes | None:
        """Read `key` from the host's DDB replica: its value's wire bytes, or None if it does not exist."""
        return await self._ctx.ddb_get(key, timeout)

    async def ddb_scan(self, prefix: str, limit: int = 0, timeout: float = HOST_TIMEOUT) -> dict[str, bytes]:
        """The objects under `prefix` in the host's replica (a local read), key → value wire bytes, in key
        order: at most `limit` keys (0: the host's bound, 10,000) and 8 MiB of values; `self._ctx.scan_truncated`
        tells whether the last scan was cut."""
        return await self._ctx.ddb_scan(prefix, limit, timeout)

    async def ddb_put(self, key: str, value: bytes, type_name: str = "blob", timeout: float = HOST_TIMEOUT) -> None:
        """Write `key` (through OAC, so this waits for the commit); HostError if the host refuses it."""
        await self._ctx.ddb_put(key, value, type_name, timeout)

    async def ddb_put_json(self, key: str, value: Any, timeout: float = HOST_TIMEOUT) -> None:
        """`ddb_put` of a JSON object (DDB type "json")."""
        await self._ctx.ddb_put(key, json.dumps(value, separators=(",", ":")).encode(), "json", timeout)

    async def ddb_write(self, ops: Iterable[Any], atomic: bool = False, timeout: float = HOST_TIMEOUT) -> list[str]:
        """Write several DDB ops (`haa.core.ddb.put`, `delete`, `append`, `cas`, `add`, `log_append`,
        `log_trim`) in one batch, committed through the group (this waits for the commit). Returns one entry
        per op, in order: "" if it succeeded, else its reason. With `atomic`, one failing op fails them all
        ("atomic batch aborted: op i failed: ...") and nothing is written. HostError if the host refused the
        batch before proposing it (an invalid key, an unknown type, a value, item or batch too large: nothing
        is written) or it was not committed."""
        return await self._ctx.ddb_write(ops, atomic, timeout)

    async def ddb_log_append(self, key: str, items: Iterable[bytes], timeout: float = HOST_TIMEOUT) -> None:
        """Append `items` to the DDB log `key` (created if absent); HostError if it failed (e.g. the log is
        full: trim it with `ddb_write([log_trim(key, upto)])`, docs/ddb.md "Logs")."""
        try:
            op = ddbmod.log_append(key, items)
        except ddbmod.DdbError as e:
            raise ValueError(f"ddb_log_append {key!r}: {e}") from None
        (why,) = await self._ctx.ddb_write([op], False, timeout)
        if why:
            raise HostError(f"ddb_log_append {key!r}: {why}")

    def watch(self, prefix: str, callback: WatchCallback) -> int:
        """Call `callback(event, key, value)` for DDB events under `prefix`, in the mailbox; returns the id."""
        return self._ctx.watch(prefix, callback)

    def watch_log(self, key: str, callback: LogCallback) -> int:
        """Call `callback(index, item)` for every item appended to the DDB log `key` from now on, in index
        order, in the mailbox (trims are not reported); returns the id for `unwatch`. To read what the log
        held before: watch first, then `decode_log(await ddb_get(key))`, and skip in the callback the
        indexes already read."""
        return self._ctx.watch_log(key, callback)

    def unwatch(self, watch_id: int) -> None:
        self._ctx.unwatch(watch_id)

    def backup(self) -> None:
        """Alg. 7 ll. 1-3: send `pack_backup()` to the host, which stores it in the DDB."""
        self._ctx.backup(self.pack_backup())

    async def spawn_child(self, type_name: str, config: bytes | str | dict | list = b"",
                          timeout: float = HOST_TIMEOUT, *, key: str | None = None) -> str:
        """Ask the hosts for a new agent whose parent is this one; returns its id once it is allocated.

        Idempotent (docs/agents.md, "Idempotent spawn"): if this agent already has a live child created with
        the same `key`, that child's id is returned and nothing is created — so a spawn that a transferred or
        recovered instance asks for again, after its first request had committed, does not make a second
        child. `key=None` (the default) derives the key from the type, the config and how many spawns of that
        type and config this instance asked for before ("<type>/<config digest>/<n>"): the code path a
        recovered instance re-runs asks for the same keys. An agent that spawns identical children over its
        life (not only at start) passes a key of its own, or `key=""`: always a new child."""
        if key is not None:
            if not isinstance(key, str):
                raise TypeError(f"key: expected str or None, not {type(key).__name__}")
            if len(key) > MAX_SPAWN_KEY:
                raise ValueError(f"key: at most {MAX_SPAWN_KEY} characters, got {len(key)}")
            return await self._ctx.spawn_child(type_name, _config_bytes(config), timeout, key=key)
        return await self._ctx.spawn_child(type_name, _config_bytes(config), timeout)

    def stop(self) -> None:
        """End this agent once the current handler returns: on_stop(), the host is told, the process exits."""
        self._ctx.request_stop()


def config_error(model: type[pydantic.BaseModel], data: bytes) -> str:
    """'' when `data` (JSON; empty = {}) validates into `model`, else its first error in one line."""
    try:
        model.model_validate_json(data.strip() or b"{}")
    except pydantic.ValidationError as e:
        errs = e.errors(include_url=False)
        if not errs:
            return "config: invalid"
        first = errs[0]
        loc = ".".join(str(x) for x in first.get("loc", ()))
        where = f"config.{loc}" if loc else "config"
        msg = " ".join(str(first.get("msg", "invalid")).split())
        got = ""
        if first.get("type") not in ("missing", "json_invalid") and loc:
            got = f" (got {_short(first.get('input'))})"
        more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
        return f"{where}: {msg}{got}{more}"[:400]
    except (ValueError, RecursionError) as e:  # pragma: no cover - pydantic reports JSON errors as above
        return f"config: {type(e).__name__}: {' '.join(str(e).split())}"[:400]
    return ""


def _short(v: Any) -> str:
    text = " ".join(repr(v).split())
    return text if len(text) <= 60 else text[:57] + "..."


def _config_bytes(config: bytes | str | dict | list) -> bytes:
    if isinstance(config, bytes | bytearray):
        return bytes(config)
    if isinstance(config, str):
        return config.encode()
    if isinstance(config, dict | list):
        return json.dumps(config, separators=(",", ":")).encode()
    raise TypeError(f"config: expected bytes, str, dict or list, not {type(config).__name__}")


async def _maybe_await(value: Any) -> Any:
    if inspect.isawaitable(value):
        return await value
    return value


class AgentContext:
    """The runtime of one agent instance: mailbox, conversations, host calls, timers (see module docstring).

    `emit(frame)` sends an `AgentToHost` frame to the host; it may raise `ValueError` (frame too large) which
    reaches the agent's call. `feed(frame)` takes each `HostToAgent` frame after Init, in order; `run()` is
    the mailbox worker and returns the process exit code.
    """

    def __init__(
        self,
        init: pb.HostToAgent.Init,
        cls: type[AgentBase],
        emit: Callable[[pb.AgentToHost], None],
        *,
        drain: Callable[[], Awaitable[None]] | None = None,
        send_raw: Callable[[bytes], None] | None = None,
        tap: Any = None,
        scheduler: AgentScheduler | None = None,
    ) -> None:
        #: what the runtime waits on: timers, futures, the mailbox, the clock (haa.sdk.sched); the default
        #: is the process's asyncio loop and wall clock, the simulator injects a VirtualScheduler
        self.sched: AgentScheduler = scheduler if scheduler is not None else AsyncioScheduler()
        #: AgentPlayback (module docstring): a recorder or a replay feed (haa.lab.playback), or None
        self.tap = tap
        if tap is not None:
            emit = tap.wrap_emit(emit)
        self._timer_ids = 0
        self._thread_calls = 0
        self.agent_id = init.agent_id
        self.name = init.name
        self.type_name = init.type_name
        self.config = bytes(init.config)
        self.epoch = int(init.epoch)
        self.parent: str | None = init.parent or None
        self.host = init.host
        self._emit = emit
        self._drain = drain
        #: writes bytes to the channel unframed: fault injection only (the probe demo agent)
        self.send_raw = send_raw
        self._mailbox = self.sched.queue()
        self._timers: set[Timer] = set()
        self._convs: dict[int, Any] = {}  # conv -> future of the reply (the scheduler's futures)
        self._calls: dict[int, Any] = {}  # req id -> future of the host's answer
        self._watches: dict[int, WatchCallback] = {}
        self._log_watches: dict[int, tuple[str, LogCallback]] = {}  # watch id -> (log key, callback)
        # conversation ids are unique across the instances of one agent: the epoch in the high 32 bits
        self._next_conv = ((self.epoch & 0xFFFFFFFF) << 32) + 1
        self._next_call = 1
        self._next_watch = 1
        #: default spawn keys: "<type>/<config digest>" -> spawns of it this instance asked for
        self._spawn_counts: dict[str, int] = {}
        self.state = "shell"  # shell -> running -> freezing | stopping -> done
        self.exit_code: int | None = None
        self.handled = 0
        self.late_replies = 0
        self.handler_errors = 0
        self._stop_requested = False
        #: the agent's clock (default the wall clock) and seeded random source; a mission sets both
        self.clock: Clock = self._wrap_clock(self.sched.clock_for(WALL_CLOCK))
        self.scan_truncated = False
        self.random: random.Random = self._wrap_random(agent_random(self.agent_id, self.name, self.epoch))
        self.agent: AgentBase = cls(self)

    def set_clock(self, clock: Clock, seed: int | str | None = None) -> None:
        """Use `clock` from now on (timers armed later follow it) and, with `seed`, a random source seeded by
        the mission seed, the agent's name and epoch (reproducible across runs). On a virtual scheduler the
        clock stays the simulator's (haa.sdk.sched: the simulated time is the mission time)."""
        self.clock = self._wrap_clock(self.sched.clock_for(clock))
        if seed is not None:
            self.random = self._wrap_random(agent_random(seed, self.name, self.epoch))

    async def run_in_thread(self, executor: Any, call: Callable[[], Any]) -> Any:
        self._thread_calls += 1
        n = self._thread_calls
        try:
            return await self.sched.run_in_executor(executor, call)
        finally:
            if self.tap is not None:
                self.tap.thread_done(n)

    def perf_counter(self) -> float:
        v = time.perf_counter()
        if self.tap is not None:
            self.tap.perf_counter(v)
        return v

    def _wrap_clock(self, clock: Clock) -> Clock:
        return clock if self.tap is None else self.tap.wrap_clock(clock)

    def _wrap_random(self, rnd: random.Random) -> random.Random:
        return rnd if self.tap is None else self.tap.wrap_random(rnd)

    # ------------------------------------------------------------------ host -> agent

    def feed(self, msg: pb.HostToAgent) -> None:
        """Take one frame from the host (synchronously, in channel order)."""
        kind = msg.WhichOneof("msg")
        if kind == "deliver":
            env = msg.deliver
            if env.reply:
                fut = self._convs.get(env.conv)
                if fut is None or fut.done():
                    self.late_replies += 1  # its request timed out, or it was made by a previous instance
                else:
                    fut.set_result(env)
            else:
                self._put(("msg", env))
        elif kind == "answer":
            fut_a = self._calls.get(msg.answer.req_id)
            if fut_a is not None and not fut_a.done():
                fut_a.set_result(msg.answer)
        elif kind == "watch_event":
            w = msg.watch_event
            if w.watch_id in self._log_watches:
                log_key = self._log_watches[w.watch_id][0]
                if w.event == "append" and w.key == log_key and w.has_value:
                    self._put(("log_item", (w.watch_id, w.index, bytes(w.value))))
            elif w.watch_id in self._watches:
                self._put(("watch", (w.watch_id, w.event, w.key, bytes(w.value) if w.has_value else None)))
        elif kind == "start":
            self._put(("begin", ("start", None)))
        elif kind == "thaw":
            self._put(("begin", ("thaw", bytes(msg.thaw.state))))
        elif kind == "recover":
            r = msg.recover
            self._put(("begin", ("recover", bytes(r.backup) if r.has_backup else None)))
        elif kind == "resume":
            self._put(("resume", msg.resume.how))
        elif kind == "freeze":
            # Alg. 5 l. 17: stop the timers now; what was delivered before the freeze is still handled
            self.state = "freezing"
            self._cancel_timers()
            if self.tap is not None:
                self.tap.freeze_fed()  # an input of its own: it changes how the queued items are handled
            self._put(("freeze", None))
        elif kind == "stop":
            self._put(("stop", None))
        else:
            raise AgentFatal(f"unexpected frame from the host: {kind}")

    def _put(self, item: tuple[str, Any]) -> None:
        self._mailbox.put_nowait(item)

    @property
    def queued(self) -> int:
        return self._mailbox.qsize()

    # ------------------------------------------------------------------ the mailbox worker

    async def run(self) -> int:
        """Handle mailbox items one at a time until the agent freezes, stops or fails; the exit code."""
        while self.exit_code is None:
            kind, data = await self._take_item()
            try:
                await self._handle(kind, data)
            except AgentFatal as e:
                self._fatal(str(e))
                break
            self.handled += 1
            if self._stop_requested and self.exit_code is None and self.state == "running":
                self._do_stop()
            if self._drain is not None and self.exit_code is None:
                await self._drain()  # backpressure: wait while the host is not reading
            # Queue.get() and a handler that never awaits do not yield: without this a long backlog (a thaw
            # with many queued messages) would starve the heartbeat and the reader, and look like a hang
            await self.sched.sleep(0)
        self._cancel_timers()
        for fut in [*self._convs.values(), *self._calls.values()]:
            fut.cancel()
        return self.exit_code if self.exit_code is not None else 0

    async def _take_item(self) -> tuple[str, Any]:
        """The next mailbox item (the worker consumes it now: the tap records it)."""
        item = await self._mailbox.get()
        if self.tap is not None:
            self.tap.item(*item)
        return item

    async def _await_answer(self, fut: Any, req_id: int, timeout: float) -> pb.HostToAgent.Answer:
        """The host's answer to call `req_id` (TimeoutError after `timeout`); the tap records either."""
        try:
            ans = await self.sched.wait_for(fut, timeout)
        except TimeoutError:
            if self.tap is not None:
                self.tap.answer(req_id, None)
            raise
        if self.tap is not None:
            self.tap.answer(req_id, ans)
        return ans

    async def _await_reply(self, fut: Any, conv: int, timeout: float) -> pb.AgentMsg:
        """The reply to request `conv` (TimeoutError after `timeout`); the tap records either."""
        try:
            env = await self.sched.wait_for(fut, timeout)
        except TimeoutError:
            if self.tap is not None:
                self.tap.reply(conv, None)
            raise
        if self.tap is not None:
            self.tap.reply(conv, env)
        return env

    async def _handle(self, kind: str, data: Any) -> None:
        a = self.agent
        if kind == "msg":
            await self._handle_message(data)
        elif kind == "timer":
            timer: Timer = data
            timer._queued = False
            if timer.cancelled:  # cancelled (or the agent is freezing) after the tick was queued
                return
            timer.fired += 1
            if timer.period is None:
                self._timers.discard(timer)
            await self._guarded("timer", timer.fn)
        elif kind == "watch":
            wid, event, key, value = data
            cb = self._watches.get(wid)
            if cb is not None:
                await self._guarded("watch", lambda: cb(event, key, value))
        elif kind == "log_item":
            wid, index, item = data
            entry = self._log_watches.get(wid)
            if entry is not None:
                log_cb = entry[1]
                await self._guarded("watch_log", lambda: log_cb(index, item))
        elif kind == "begin":
            how, blob = data
            if how == "start":
                await self._fatal_on_error("on_start", a.on_start)
            elif how == "thaw":
                await self._fatal_on_error("unpack_state", lambda: a.unpack_state(blob))
            else:
                await self._fatal_on_error("recover", lambda: a.recover(blob))
            self.state = "running"
        elif kind == "resume":
            if data != "start":
                await self._fatal_on_error("on_resume", lambda: a.on_resume(data))
            self._emit(pb.AgentToHost(ready=pb.AgentToHost.Ready(how=data)))
        elif kind == "freeze":
            self._cancel_timers()
            state = await self._fatal_on_error("pack_state", a.pack_state)
            if not isinstance(state, bytes | bytearray):
                raise AgentFatal(f"pack_state returned {type(state).__name__}, not bytes")
            try:
                self._emit(pb.AgentToHost(frozen=pb.AgentToHost.Frozen(state=bytes(state))))
            except ValueError as e:
                raise AgentFatal(f"cannot send the packed state: {e}") from None
            self.state = "done"
            self.exit_code = 0
        elif kind == "stop":
            if self.state in ("running", "shell"):
                self._do_stop()
        else:  # pragma: no cover - internal
            raise AgentFatal(f"unknown mailbox item {kind}")

    async def _handle_message(self, env: pb.AgentMsg) -> None:
        a = self.agent
        if env.conv and not env.reply and env.src.startswith("@") and env.payload.startswith(CHAOS_HANG):
            await self._chaos_hang(env)
            return
        if env.conv and not env.reply:
            try:
                result = await a.on_request(env.src, bytes(env.payload))
                if not isinstance(result, bytes | bytearray):
                    raise TypeError(f"on_request returned {type(result).__name__}, not bytes")
                reply = pb.AgentMsg(src=self.agent_id, dst=env.src, payload=bytes(result), conv=env.conv, reply=True)
            except Exception as e:
                self.handler_errors += 1
                reply = pb.AgentMsg(src=self.agent_id, dst=env.src, conv=env.conv, reply=True,
                                    error=f"{type(e).__name__}: {e}")
            try:
                self._emit(pb.AgentToHost(sent=reply))
            except ValueError as e:  # the response is too large: tell the requester that instead
                reply = pb.AgentMsg(src=self.agent_id, dst=env.src, conv=env.conv, reply=True, error=str(e))
                self._emit(pb.AgentToHost(sent=reply))
            return
        await self._guarded("on_message", lambda: a.on_message(env.src, bytes(env.payload)))

    async def _chaos_hang(self, env: pb.AgentMsg) -> None:
        """CHAOS_HANG from the operator: answer, then block this loop for the given seconds, then fail."""
        try:
            seconds = float(env.payload[len(CHAOS_HANG):].decode())
            if not 0 < seconds <= CHAOS_HANG_MAX:
                raise ValueError(seconds)
        except ValueError:
            why = f"chaos hang: seconds must be in (0, {CHAOS_HANG_MAX:g}]"
            self._emit(pb.AgentToHost(sent=pb.AgentMsg(src=self.agent_id, dst=env.src, conv=env.conv, reply=True,
                                                       error=why)))
            return
        self._emit(pb.AgentToHost(sent=pb.AgentMsg(src=self.agent_id, dst=env.src, conv=env.conv, reply=True,
                                                   payload=b"hanging")))
        if self._drain is not None:
            await self._drain()
        await self.sched.sleep(0)
        time.sleep(seconds)  # deliberately synchronous: the loop (heartbeat included) stops, as in a stuck handler
        raise AgentFatal(f"chaos hang: blocked its event loop for {seconds:g} s")

    async def _guarded(self, what: str, fn: Callable[[], Any]) -> None:
        try:
            await _maybe_await(fn())
        except Exception as e:
            self.handler_errors += 1
            tb = traceback.format_exc(limit=8)
            self.log("handler_error", "error", {"in": what, "error": f"{type(e).__name__}: {e}", "traceback": tb})
            if self.agent.CRASH_ON_ERROR:
                raise AgentFatal(f"{what} raised {type(e).__name__}: {e}") from None

    async def _fatal_on_error(self, what: str, fn: Callable[[], Any]) -> Any:
        try:
            return await _maybe_await(fn())
        except AgentFatal:
            raise
        except Exception as e:
            traceback.print_exc(file=sys.stderr)
            raise AgentFatal(f"{what} raised {type(e).__name__}: {e}") from None

    def _fatal(self, message: str) -> None:
        self._cancel_timers()
        self.state = "done"
        self.exit_code = 1
        try:
            self._emit(pb.AgentToHost(error=pb.AgentToHost.Error(message=message[:4000])))
        except Exception:
            print(f"agent {self.name}: {message}", file=sys.stderr)

    def _do_stop(self) -> None:
        self.state = "stopping"
        self._cancel_timers()
        try:
            self.agent.on_stop()
        except Exception as e:
            self.log("handler_error", "error", {"in": "on_stop", "error": f"{type(e).__name__}: {e}"})
        self._emit(pb.AgentToHost(stopped=pb.AgentToHost.Stopped()))
        self.state = "done"
        self.exit_code = 0

    def _cancel_timers(self) -> None:
        for t in list(self._timers):
            t.cancel()

    # ------------------------------------------------------------------ agent -> host

    def send(self, to: str, payload: bytes, *, conv: int = 0) -> None:
        if not isinstance(to, str):
            raise TypeError(f"to: expected an agent id (str), not {type(to).__name__}")
        if not isinstance(payload, bytes | bytearray):
            raise TypeError(f"payload: expected bytes, not {type(payload).__name__}")
        if self.state == "done":
            raise RuntimeError(f"agent {self.name} has ended; it cannot send")
        if too_large := message_too_large(len(payload)):  # every hop's frame must fit it (haa.sdk.channel)
            raise ValueError(f"send to {to}: {too_large}")
        self._emit(pb.AgentToHost(sent=pb.AgentMsg(src=self.agent_id, dst=to, payload=bytes(payload), conv=conv)))

    async def request(self, to: str, payload: bytes, timeout: float) -> bytes:
        conv = self._next_conv
        self._next_conv += 1
        fut = self.sched.create_future()
        self._convs[conv] = fut
        try:
            self.send(to, payload, conv=conv)
            try:
                env = await self._await_reply(fut, conv, timeout)
            except TimeoutError:
                raise TimeoutError(f"request to {to} timed out after {timeout:g} s") from None
        finally:
            self._convs.pop(conv, None)
        if env.error:
            raise RemoteError(env.error)
        return bytes(env.payload)

    async def _call(self, frame: pb.AgentToHost, req_id: int, timeout: float, what: str) -> pb.HostToAgent.Answer:
        fut = self.sched.create_future()
        self._calls[req_id] = fut
        try:
            self._emit(frame)
            try:
                ans = await self._await_answer(fut, req_id, timeout)
            except TimeoutError:
                raise TimeoutError(f"{what}: the host did not answer within {timeout:g} s") from None
        finally:
            self._calls.pop(req_id, None)
        if not ans.ok:
            raise HostError(f"{what}: {ans.error or 'refused by the host'}")
        return ans

    def _new_call(self) -> int:
        n = self._next_call
        self._next_call += 1
        return n

    async def ddb_get(self, key: str, timeout: float) -> bytes | None:
        _check_key(key)
        rid = self._new_call()
        ans = await self._call(
            pb.AgentToHost(ddb_get=pb.AgentToHost.DdbGet(req_id=rid, key=key)), rid, timeout, f"ddb_get {key!r}"
        )
        return None if ans.missing else bytes(ans.value)

    async def ddb_scan(self, prefix: str, limit: int, timeout: float) -> dict[str, bytes]:
        if len(prefix) > 512 or "\0" in prefix:
            raise ValueError("prefix: at most 512 characters, no NUL")
        if not 0 <= limit < 2**32:
            raise ValueError(f"limit: must be in 0..2**32-1, got {limit}")
        rid = self._new_call()
        ans = await self._call(pb.AgentToHost(ddb_scan=pb.AgentToHost.DdbScan(req_id=rid, prefix=prefix, limit=limit)),
                               rid, timeout, f"ddb_scan {prefix!r}")
        self.scan_truncated = bool(ans.truncated)
        return dict(zip(ans.keys, (bytes(v) for v in ans.values), strict=True))

    async def ddb_put(self, key: str, value: bytes, type_name: str, timeout: float) -> None:
        _check_key(key)
        if not isinstance(value, bytes | bytearray):
            raise TypeError(f"value: expected bytes, not {type(value).__name__}")
        rid = self._new_call()
        frame = pb.AgentToHost(ddb_put=pb.AgentToHost.DdbPut(req_id=rid, key=key, value=bytes(value),
                                                             type_name=type_name))
        await self._call(frame, rid, timeout, f"ddb_put {key!r}")

    async def ddb_write(self, ops: Iterable[Any], atomic: bool, timeout: float) -> list[str]:
        batch = list(ops)
        if not batch:
            raise ValueError("ddb_write: no ops")
        rid = self._new_call()
        try:
            body = pb.AgentToHost.DdbWrite(req_id=rid, ops=batch, atomic=bool(atomic))
        except TypeError:
            raise TypeError("ddb_write: ops must be DdbOp messages (haa.core.ddb.put, log_append, ...)") from None
        ans = await self._call(pb.AgentToHost(ddb_write=body), rid, timeout, f"ddb_write of {len(batch)} op(s)")
        errors = list(ans.op_errors)
        if len(errors) != len(batch):  # pragma: no cover - a host bug
            raise HostError(f"ddb_write: the host answered {len(errors)} results for {len(batch)} ops")
        return errors

    async def spawn_child(self, type_name: str, config: bytes, timeout: float, key: str | None = None) -> str:
        if not type_name:
            raise ValueError("type_name: must not be empty")
        if key is None:  # the default key (AgentBase.spawn_child): type, config digest, n-th such request
            base = f"{type_name}/{hashlib.sha256(config).hexdigest()[:16]}"
            n = self._spawn_counts[base] = self._spawn_counts.get(base, 0) + 1
            key = f"{base}/{n}"
        rid = self._new_call()
        frame = pb.AgentToHost(spawn_child=pb.AgentToHost.SpawnChild(req_id=rid, type_name=type_name, config=config,
                                                                     key=key))
        ans = await self._call(frame, rid, timeout, f"spawn_child {type_name!r}")
        return bytes(ans.value).decode()

    def watch(self, prefix: str, callback: WatchCallback) -> int:
        if not isinstance(prefix, str):
            raise TypeError(f"prefix: expected str, not {type(prefix).__name__}")
        if not callable(callback):
            raise TypeError("callback: must be callable")
        wid = self._next_watch
        self._next_watch += 1
        self._watches[wid] = callback
        self._emit(pb.AgentToHost(ddb_watch=pb.AgentToHost.DdbWatch(watch_id=wid, prefix=prefix)))
        return wid

    def watch_log(self, key: str, callback: LogCallback) -> int:
        _check_key(key)
        if not callable(callback):
            raise TypeError("callback: must be callable")
        wid = self._next_watch
        self._next_watch += 1
        self._log_watches[wid] = (key, callback)
        # the host watches by prefix: events of other keys under it are dropped in `feed`
        self._emit(pb.AgentToHost(ddb_watch=pb.AgentToHost.DdbWatch(watch_id=wid, prefix=key)))
        return wid

    def unwatch(self, watch_id: int) -> None:
        if self._log_watches.pop(watch_id, None) is not None or self._watches.pop(watch_id, None) is not None:
            self._emit(pb.AgentToHost(ddb_unwatch=pb.AgentToHost.DdbUnwatch(watch_id=watch_id)))

    def backup(self, data: bytes) -> None:
        if not isinstance(data, bytes | bytearray):
            raise TypeError(f"pack_backup returned {type(data).__name__}, not bytes")
        self._emit(pb.AgentToHost(backup=pb.AgentToHost.Backup(data=bytes(data))))

    def timer(self, fn: TimerCallback, delay: float, period: float | None) -> Timer:
        if delay < 0:
            raise ValueError(f"delay: must be >= 0, got {delay}")
        t = Timer(self, fn, delay, period)
        if self.state in ("freezing", "stopping", "done"):
            t.cancel()  # timers stop at a freeze; one armed while the agent drains its mailbox never fires
        else:
            self._timers.add(t)
        return t

    def request_stop(self) -> None:
        self._stop_requested = True
        if self.state == "running" and self._mailbox.empty():
            self._put(("stop", None))  # wake the worker if it is idle (stop() called from outside a handler)

    def log(self, event: str, level: str, fields: dict[str, Any]) -> None:
        try:
            text = json.dumps(fields, default=str, separators=(",", ":"))
        except (TypeError, ValueError) as e:
            text = json.dumps({"unserializable_fields": str(e)})
        try:
            self._emit(pb.AgentToHost(log=pb.AgentToHost.Log(level=level, event=event, fields_json=text)))
        except Exception:
            print(f"agent {self.name} log {event}: {text}", file=sys.stderr)


def _check_key(key: str) -> None:
    if not isinstance(key, str) or not key:
        raise ValueError(f"key: must be a non-empty string, got {key!r}")
