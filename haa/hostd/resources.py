"""Event-loop stall watchdog and heap tuning of one haa-hostd process (issue 13, defects 2 and 6).

**Why a stall matters.** Heartbeats are sent and received on the host's one event loop. A callback that
keeps the loop busy for longer than the failure detector's margin (about T_D^U − η: 1 s − ~0.3 s with the
cluster QoS, docs/ufd.md) makes the peers suspect this host, and once every member suspects it the group
removes it (a 50 MB spawn config once did exactly that: a 1.7 s stall). `LoopWatch` measures every stall:
a task sleeps `tick` seconds and records how late it woke up. It keeps, in the host's counters (so
`haactl status` and the Status RPC show them):

    loop_lag_max_ms        the largest lateness seen since the process started
    loop_stalls_over_100ms / _250ms / _500ms   how many wake-ups were that late

and logs `loop_stall` for every wake-up later than `report` seconds (50 ms: info; from `warn`, 250 ms:
warning), with `ms` (the lateness) and `cpu_ms` (CPU time the loop's thread used from the previous wake-up to
this one): on a machine whose cores are shared, a late wake-up with little CPU is the scheduler's doing (the
process was not running), one with as much CPU as lateness is work of ours that kept the loop busy. A stall is seen to
within `tick` (a stall that began just before a wake-up is due shows as its full length; one that began
just after, as its length minus `tick`).

**Why memory stayed grown.** Big requests (a 16 MiB DDB batch, an 8 MiB agent state) are copied a few
times on their way through a host; the copies are freed, but glibc keeps them: it raises its mmap
threshold after the first big free (so later big buffers come from the heap, which only shrinks from the
top), and gRPC's threads each get an arena of their own. `tune_malloc` fixes the mmap threshold (buffers of
`MMAP_THRESHOLD` bytes and more are always mmapped, so freeing one returns it to the system at once) and
caps the number of arenas; `LoopWatch` also calls `malloc_trim(0)` after the process moved a lot of bytes
(`TRIM_AFTER_BYTES`) or its RSS grew by `TRIM_AFTER_GROWTH` since the last trim, at most every
`trim_interval` seconds. All of it is a no-op where glibc is not the allocator.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import logging
import time
from collections import Counter
from collections.abc import Callable

import psutil

from haa.hostd.logs import LOGGER_NAME, log_event

log = logging.getLogger(LOGGER_NAME + ".resources")

#: mallopt parameters (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: buffers of at least this size are mmapped (and unmapped when freed); glibc's default starts at 128 KiB
#: but moves up to 32 MiB after the first big free, which is what kept freed request buffers in the heap
MMAP_THRESHOLD = 256 * 1024
#: top-of-heap free space above this is returned to the system at once
TRIM_THRESHOLD = 1 << 20
#: malloc arenas (glibc default: 8 per core); gRPC's threads would otherwise each keep one
ARENA_MAX = 2
#: `malloc_trim` once this many bytes went through the transport since the last trim ...
TRIM_AFTER_BYTES = 32 << 20
#: ... or the RSS grew this much since the last trim
TRIM_AFTER_GROWTH = 32 << 20

_libc: ctypes.CDLL | None = None
_tuned = False


def _glibc() -> ctypes.CDLL | None:
    global _libc
    if _libc is None:
        name = ctypes.util.find_library("c")
        if not name:
            return None
        try:
            lib = ctypes.CDLL(name)
            lib.mallopt  # noqa: B018 - glibc only (musl has no mallopt/malloc_trim)
            lib.malloc_trim  # noqa: B018
        except (OSError, AttributeError):
            return None
        _libc = lib
    return _libc


def tune_malloc() -> bool:
    """Fix glibc's mmap and trim thresholds and cap its arenas (see the module docstring). True if done."""
    global _tuned
    lib = _glibc()
    if lib is None:
        return False
    if not _tuned:
        lib.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        lib.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
        lib.mallopt(_M_ARENA_MAX, ARENA_MAX)
        _tuned = True
    return True


def malloc_trim() -> bool:
    """Return free heap memory to the system (glibc `malloc_trim(0)`). True if glibc released something."""
    lib = _glibc()
    return bool(lib.malloc_trim(0)) if lib is not None else False


class LoopWatch:
    """Measures event-loop stalls and trims the heap after heavy traffic (see the module docstring).

    Args:
        counters: where the loop_* counters go (the host's).
        moved_bytes: returns the bytes the host moved so far (e.g. the transport's rx + tx byte counters);
            the trim decision compares it with its value at the last trim.
    """

    def __init__(
        self,
        counters: Counter[str],
        moved_bytes: Callable[[], int] = lambda: 0,
        *,
        tick: float = 0.05,
        report: float = 0.05,
        warn: float = 0.25,
        trim_interval: float = 2.0,
    ) -> None:
        self.counters = counters
        self.moved_bytes = moved_bytes
        self.tick = tick
        self.report = report
        self.warn = warn
        self.trim_interval = trim_interval
        self.task: asyncio.Task[None] | None = None
        self._proc = psutil.Process()

    def start(self) -> None:
        self.task = asyncio.get_running_loop().create_task(self._run(), name="loopwatch")

    def stop(self) -> None:
        if self.task is not None:
            self.task.cancel()
            self.task = None

    def record(self, lag: float, cpu: float = 0.0) -> None:
        """One wake-up `lag` seconds late, `cpu` seconds of the loop thread's CPU time since the last one."""
        c = self.counters
        ms = int(lag * 1000)
        if ms > c["loop_lag_max_ms"]:
            c["loop_lag_max_ms"] = ms
        if lag >= 0.1:
            c["loop_stalls_over_100ms"] += 1
            if lag >= 0.25:
                c["loop_stalls_over_250ms"] += 1
                if lag >= 0.5:
                    c["loop_stalls_over_500ms"] += 1
        if lag >= self.report:
            level = logging.WARNING if lag >= self.warn else logging.INFO
            log_event(log, level, "loop_stall", ms=ms, cpu_ms=int(cpu * 1000))

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        tick = self.tick
        last_trim = loop.time()
        trimmed_at_bytes = self.moved_bytes()
        trimmed_at_rss = self._rss()
        while True:
            t0 = loop.time()
            c0 = time.thread_time()
            await asyncio.sleep(tick)
            now = loop.time()
            self.record(max(0.0, now - t0 - tick), time.thread_time() - c0)
            if now - last_trim < self.trim_interval:
                continue
            last_trim = now
            moved = self.moved_bytes()
            rss = self._rss()
            if moved - trimmed_at_bytes >= TRIM_AFTER_BYTES or rss - trimmed_at_rss >= TRIM_AFTER_GROWTH:
                malloc_trim()
                self.counters["malloc_trims"] += 1
                trimmed_at_bytes = moved
                trimmed_at_rss = self._rss()
                last_trim = loop.time()

    def _rss(self) -> int:
        with contextlib.suppress(psutil.Error):
            return int(self._proc.memory_info().rss)
        return 0
