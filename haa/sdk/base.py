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
  `watch_log(key, callback(index, item))`, `unwatch(id)`; `haa.core.ddb.ops.decode_log(ddb_get bytes)` reads a
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

`AgentContext` (haa.sdk.context) is the machinery behind it: the mailbox and its worker, conversations, the
calls answered by the host, timers, the AgentPlayback tap. Its names (and the exceptions an agent sees:
`RemoteError`, `HostError`, `AgentFatal`) are re-exported here.
"""

from __future__ import annotations

import asyncio
import functools
import json
import random
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any, ClassVar

import pydantic

from haa.core.ddb import objects as ddbmod
from haa.core.ddb.ops import log_append

# AgentContext and what it raises live in haa.sdk.context; imported from here as before
from haa.sdk.context import CHAOS_HANG as CHAOS_HANG
from haa.sdk.context import CHAOS_HANG_MAX as CHAOS_HANG_MAX
from haa.sdk.context import AgentContext as AgentContext
from haa.sdk.context import AgentFatal as AgentFatal
from haa.sdk.context import HostError as HostError
from haa.sdk.context import LogCallback as LogCallback
from haa.sdk.context import RemoteError as RemoteError
from haa.sdk.context import Timer as Timer
from haa.sdk.context import TimerCallback as TimerCallback
from haa.sdk.context import WatchCallback as WatchCallback
from haa.sdk.context import agent_random as agent_random

# Clock, WALL_CLOCK and ScaledClock live with the schedulers; imported from here as before
from haa.sdk.sched import WALL_CLOCK as WALL_CLOCK
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
#: longest spawn key (`spawn_child(key=)`; haa.core.ddb.agenttable.MAX_SPAWN_KEY)
MAX_SPAWN_KEY = 256


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
        """Write several DDB ops (`haa.core.ddb.ops.put`, `delete`, `append`, `cas`, `add`, `log_append`,
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
            op = log_append(key, items)
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
