"""The clock and scheduler an agent runs on (issue 17, item 4): wall time in a process, virtual time in the simulator.

Everything in an agent's runtime (`haa.sdk.context.AgentContext`) that depends on time or waits goes
through one `AgentScheduler`:

* `time()` and `call_at(when, fn)` — the base of the agent's timers (`call_later`, `every`) and a handle to
  `cancel()` them;
* `create_future()` and `wait_for(fut, timeout)` — what a request to another agent or a call to the host
  (a DDB read or write, `spawn_child`) awaits, with its timeout;
* `queue()` — the agent's mailbox; `sleep(0)` — the worker's yield between two handlers;
* `run_in_executor(executor, fn)` — `run_in_thread` (the sensor agents' image processing);
* `clock_for(clock)` — the clock `now()` reads, given the clock a mission asked for (`Clock`, `ScaledClock`,
  `haa.agents.team.MissionClock`).

Two implementations:

* `AsyncioScheduler`, the default: the process's asyncio loop, exactly what the agent runtime did before
  the scheduler was injected — timers on `loop.call_at` (an agent's delays converted with the clock's
  `wall_delay`, so a mission at `--speed 4` runs its timers 4 times faster), asyncio futures, `asyncio.Queue`,
  `asyncio.wait_for`, the loop's thread pool; `clock_for` keeps the clock it is given.
* `VirtualScheduler`: no event loop and no wall clock. Time is a simulator's (`now` callable) and every
  wake-up is an event the simulator schedules (`post(when, fn)`): a timer is an event at its virtual
  deadline, a resolved future resumes its awaiting coroutine in an event at the current time (as asyncio's
  `call_soon` would), a timeout is an event at `now + timeout` (seconds of virtual time). Coroutines are
  driven by `VirtualTask` (the agent's mailbox worker, and whatever it spawns with `spawn`); they may await
  only this scheduler's futures — an agent that awaits asyncio itself (a raw `asyncio.sleep`, a gRPC
  call) cannot run on virtual time and fails with `RuntimeError` naming what it awaited. `clock_for`
  returns the virtual clock whatever a mission asks for: in the simulator the simulated time *is* the
  mission time. Work handed to `run_in_executor` runs at once, inline (no thread: the simulation stays
  deterministic, and virtual time does not advance while it runs). `haa.lab.dsim.vagent` runs real agents on it.

Same seed, same inputs, same order of events: a `VirtualScheduler` adds no source of nondeterminism, so a
real agent in the simulator keeps the simulator's guarantee that a seed reproduces a run.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable, Coroutine, Generator
from typing import Any, Protocol


class Clock:
    """The time an agent sees (issue 15: at `--speed X` an agent's `now()`, timers and random numbers follow
    the simulator's clock). `now()` is the agent's time in seconds; `wall_delay(d)` is how many seconds of the
    scheduler's timer base `d` of the agent's seconds last (timers are armed with it). The default is the
    wall clock; a mission sets a `ScaledClock` or `haa.agents.team.MissionClock` with `AgentContext.set_clock`,
    and a `VirtualScheduler` replaces either by its `VirtualClock`."""

    def now(self) -> float:
        return time.time()

    def wall_delay(self, delay: float) -> float:
        return delay


#: the default clock of every agent
WALL_CLOCK = Clock()


class ScaledClock(Clock):
    """Simulated time running `speed` times faster than the wall clock: `start` simulated seconds at the
    wall-clock instant `wall_start` (time.monotonic(); default: now)."""

    def __init__(self, speed: float, start: float = 0.0, wall_start: float | None = None) -> None:
        if not (speed > 0 and speed < float("inf")):
            raise ValueError(f"speed: must be a positive finite number, got {speed}")
        self.speed = float(speed)
        self.start = float(start)
        self.wall_start = time.monotonic() if wall_start is None else float(wall_start)

    def now(self) -> float:
        return self.start + (time.monotonic() - self.wall_start) * self.speed

    def wall_delay(self, delay: float) -> float:
        return delay / self.speed


class Handle(Protocol):
    def cancel(self) -> None: ...


class AgentScheduler(Protocol):
    """What an agent's runtime waits on (module docstring)."""

    def time(self) -> float: ...

    def call_at(self, when: float, fn: Callable[[], None]) -> Handle: ...

    def create_future(self) -> Any: ...

    async def wait_for(self, fut: Any, timeout: float) -> Any: ...

    def queue(self) -> Any: ...

    async def sleep(self, delay: float) -> None: ...

    async def run_in_executor(self, executor: Any, fn: Callable[[], Any]) -> Any: ...

    def clock_for(self, clock: Clock) -> Clock: ...


# ---------------------------------------------------------------------------------------------- asyncio


class AsyncioScheduler:
    """The running asyncio loop and the wall clock (the agent processes; module docstring)."""

    def time(self) -> float:
        return asyncio.get_running_loop().time()

    def call_at(self, when: float, fn: Callable[[], None]) -> asyncio.TimerHandle:
        return asyncio.get_running_loop().call_at(when, fn)

    def create_future(self) -> asyncio.Future[Any]:
        return asyncio.get_running_loop().create_future()

    async def wait_for(self, fut: Any, timeout: float) -> Any:
        return await asyncio.wait_for(fut, timeout)

    def queue(self) -> asyncio.Queue[Any]:
        return asyncio.Queue()

    async def sleep(self, delay: float) -> None:
        await asyncio.sleep(delay)

    async def run_in_executor(self, executor: Any, fn: Callable[[], Any]) -> Any:
        return await asyncio.get_running_loop().run_in_executor(executor, fn)

    def clock_for(self, clock: Clock) -> Clock:
        return clock


# ---------------------------------------------------------------------------------------------- virtual time


class VirtualFuture:
    """A result that is not there yet, on virtual time (the subset of `asyncio.Future` the agent runtime uses).
    Awaiting it suspends the awaiting `VirtualTask` until `set_result`/`set_exception`/`cancel`."""

    __slots__ = ("_callbacks", "_done", "_exc", "_result")

    def __init__(self) -> None:
        self._done = False
        self._result: Any = None
        self._exc: BaseException | None = None
        self._callbacks: list[Callable[[VirtualFuture], None]] = []

    def done(self) -> bool:
        return self._done

    def cancelled(self) -> bool:
        return self._done and isinstance(self._exc, asyncio.CancelledError)

    def result(self) -> Any:
        if not self._done:
            raise asyncio.InvalidStateError("result is not set")
        if self._exc is not None:
            raise self._exc
        return self._result

    def exception(self) -> BaseException | None:
        return self._exc

    def set_result(self, value: Any) -> None:
        self._finish(value, None)

    def set_exception(self, exc: BaseException) -> None:
        self._finish(None, exc)

    def cancel(self) -> bool:
        if self._done:
            return False
        self._finish(None, asyncio.CancelledError())
        return True

    def add_done_callback(self, fn: Callable[[VirtualFuture], None]) -> None:
        if self._done:
            fn(self)
        else:
            self._callbacks.append(fn)

    def _finish(self, value: Any, exc: BaseException | None) -> None:
        if self._done:
            raise asyncio.InvalidStateError("the future is done already")
        self._done, self._result, self._exc = True, value, exc
        callbacks, self._callbacks = self._callbacks, []
        for fn in callbacks:
            fn(self)

    def __await__(self) -> Generator[VirtualFuture, None, Any]:
        if not self._done:
            yield self  # the VirtualTask driving the awaiting coroutine resumes it once this is done
        return self.result()


class VirtualQueue:
    """An unbounded FIFO whose `get()` waits on virtual time (the mailbox)."""

    def __init__(self, sched: VirtualScheduler) -> None:
        self._sched = sched
        self._items: deque[Any] = deque()
        self._getters: deque[VirtualFuture] = deque()

    def put_nowait(self, item: Any) -> None:
        while self._getters:
            g = self._getters.popleft()
            if not g.done():
                g.set_result(item)
                return
        self._items.append(item)

    async def get(self) -> Any:
        if self._items:
            return self._items.popleft()
        g = self._sched.create_future()
        self._getters.append(g)
        return await g

    def empty(self) -> bool:
        return not self._items

    def qsize(self) -> int:
        return len(self._items)


class VirtualClock(Clock):
    """The simulator's time as the agent's clock: `now()` reads it, a delay lasts as long as it says."""

    def __init__(self, now: Callable[[], float]) -> None:
        self._now = now

    def now(self) -> float:
        return self._now()

    def wall_delay(self, delay: float) -> float:
        return max(0.0, delay)


class _VirtualHandle:
    __slots__ = ("cancelled", "fn")

    def __init__(self, fn: Callable[[], None]) -> None:
        self.fn = fn
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True

    def run(self) -> None:
        if not self.cancelled:
            self.cancelled = True
            self.fn()


class VirtualTask:
    """Drives one coroutine on a `VirtualScheduler`: runs it until it awaits a `VirtualFuture` that is not
    done, and resumes it (in an event at the current virtual time) once that future is. `result` is a future
    of the coroutine's return value or exception."""

    def __init__(self, sched: VirtualScheduler, coro: Coroutine[Any, Any, Any]) -> None:
        self._sched = sched
        self._coro = coro
        self.result = VirtualFuture()
        sched._tasks.add(self)
        sched.post(sched.time(), self._step)

    def _step(self) -> None:
        if self.result.done() or self._sched.closed:
            return
        try:
            awaited = self._coro.send(None)
        except StopIteration as stop:
            self._sched._tasks.discard(self)
            self.result.set_result(stop.value)
            return
        except BaseException as e:  # the coroutine raised: its result carries it
            self._sched._tasks.discard(self)
            self.result.set_exception(e)
            return
        if not isinstance(awaited, VirtualFuture):
            self._coro.close()
            self._sched._tasks.discard(self)
            what = type(awaited).__name__
            self.result.set_exception(RuntimeError(
                f"awaited {what} outside the agent's scheduler: an agent on virtual time may await only "
                "its own calls (requests, DDB, timers), not asyncio or I/O directly (haa.sdk.sched)"))
            return
        awaited.add_done_callback(lambda _f: self._sched.post(self._sched.time(), self._step))

    def close(self) -> None:
        """Abandon the coroutine (its instance was killed): nothing of it runs any more."""
        if not self.result.done():
            self._coro.close()
            self.result.cancel()
        self._sched._tasks.discard(self)


class VirtualScheduler:
    """The agent runtime on a simulator's virtual time (module docstring). `now()` is the simulator's current
    time as this agent's host sees it; `post(when, fn)` asks the simulator to call `fn()` at virtual time
    `when` (never before the current time), in order of (time, posting order)."""

    def __init__(self, now: Callable[[], float], post: Callable[[float, Callable[[], None]], None]) -> None:
        self._now = now
        self._post = post
        self.clock = VirtualClock(now)
        self.closed = False
        self._tasks: set[VirtualTask] = set()

    def time(self) -> float:
        return self._now()

    def post(self, when: float, fn: Callable[[], None]) -> None:
        def run() -> None:
            if not self.closed:
                fn()
        self._post(max(when, self._now()), run)

    def call_at(self, when: float, fn: Callable[[], None]) -> _VirtualHandle:
        h = _VirtualHandle(fn)
        self.post(when, h.run)
        return h

    def create_future(self) -> VirtualFuture:
        return VirtualFuture()

    async def wait_for(self, fut: Any, timeout: float) -> Any:
        if not fut.done():
            waiter = VirtualFuture()

            def wake(_f: Any = None) -> None:
                if not waiter.done():
                    waiter.set_result(None)

            fut.add_done_callback(wake)
            timer = self.call_at(self._now() + max(0.0, timeout), wake)
            await waiter
            timer.cancel()
            if not fut.done():
                fut.cancel()
                raise TimeoutError
        return fut.result()

    def queue(self) -> VirtualQueue:
        return VirtualQueue(self)

    async def sleep(self, delay: float) -> None:
        fut = VirtualFuture()
        self.call_at(self._now() + max(0.0, delay), lambda: fut.set_result(None))
        await fut

    async def run_in_executor(self, executor: Any, fn: Callable[[], Any]) -> Any:
        return fn()

    def clock_for(self, clock: Clock) -> Clock:
        return self.clock

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> VirtualTask:
        """Run `coro` as a task on this scheduler (it starts in an event at the current time)."""
        return VirtualTask(self, coro)

    def close(self) -> None:
        """The instance is gone (killed, its host crashed): no task, timer or wake-up of it runs again."""
        self.closed = True
        for t in list(self._tasks):
            t.close()
