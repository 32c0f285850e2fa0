"""AgentContext: the runtime of one agent instance behind `AgentBase` (haa.sdk.base, whose docstring says what an
agent gets and how its handlers run) — the mailbox and its worker, conversations, the calls answered by the host
(DDB, spawn_child), timers, watches, the agent's clock and random source, and the frames to and from the host.

`AgentContext` is the host-facing side: the runner feeds it the host's frames (`feed`) and runs its mailbox
worker (`run`); it emits the agent's frames through a callable, so it can be driven in-process by tests.

AgentPlayback (thesis §6.1.4, docs/playback.md): an optional `tap` (haa.lab.playback) sees every input where the
agent consumes it — the mailbox item the worker takes (`_take_item`), the host's answer a call awaited
(`_await_answer`), the reply a request awaited (`_await_reply`), each `now()` and random number (the clock and
random source are wrapped by the tap) — and every frame the agent emits. The recorder writes them to MCAP; the
offline replay (haa.lab.playback.replay) overrides the same three methods to feed the recorded inputs back.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import random
import sys
import time
import traceback
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, ClassVar, Protocol

from haa.pb import agent_pb2 as pb
from haa.sdk.channel import message_too_large
from haa.sdk.sched import WALL_CLOCK, AgentScheduler, AsyncioScheduler, Clock

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


class AgentHooks(Protocol):
    """What the runtime calls of its agent: `haa.sdk.base.AgentBase` (which imports this module) and its hooks."""

    CRASH_ON_ERROR: ClassVar[bool]

    async def on_start(self) -> None: ...

    async def on_message(self, src: str, payload: bytes) -> None: ...

    async def on_request(self, src: str, payload: bytes) -> bytes: ...

    def pack_state(self) -> bytes: ...

    def unpack_state(self, data: bytes) -> None: ...

    def recover(self, backup: bytes | None) -> None: ...

    async def on_resume(self, how: str) -> None: ...

    def on_stop(self) -> None: ...


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
        cls: Callable[[AgentContext], AgentHooks],
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
        #: the agent (an `AgentBase` subclass instance, made by `cls(self)`)
        self.agent: AgentHooks = cls(self)

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
            raise TypeError("ddb_write: ops must be DdbOp messages (haa.core.ddb.ops.put, log_append, ...)") from None
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
