"""TimerWheel: the core's timers (`SetTimer`/`CancelTimer` effects) as asyncio `call_at` handles, one per key.

The sans-I/O machines arm timers by key (`("hb", peer)`, `("excl", peer, inc)`, `("m", what)`, ...) at a
deadline on their clock, `time.monotonic()`. The wheel keeps one loop handle per key: setting a key again
replaces its handle, cancelling drops it. The loop's clock may differ from `time.monotonic()` (uvloop, a
custom loop): the offset between the two is measured once at `start` and added to every deadline. When a
handle fires, the key is forgotten first and then `fire(key, at)` runs with the deadline `at` the core asked
for, so the runtime can report the timer no earlier than that (a loop may run a handle a hair early).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Hashable


class TimerWheel:
    """See the module docstring."""

    def __init__(self, fire: Callable[[Hashable, float], None]) -> None:
        self._fire = fire
        self._loop: asyncio.AbstractEventLoop | None = None
        self._offset = 0.0
        self._handles: dict[Hashable, asyncio.TimerHandle] = {}

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind to the running loop and measure its clock's offset from `time.monotonic()`."""
        self._loop = loop
        self._offset = loop.time() - time.monotonic()

    def set(self, key: Hashable, at: float) -> None:
        """Arm (or re-arm) `key` for monotonic time `at`."""
        old = self._handles.get(key)
        if old is not None:
            old.cancel()
        loop = self._loop
        assert loop is not None, "TimerWheel.start was not called"
        self._handles[key] = loop.call_at(at + self._offset, self._expired, key, at)

    def cancel(self, key: Hashable) -> None:
        h = self._handles.pop(key, None)
        if h is not None:
            h.cancel()

    def clear(self) -> None:
        """Cancel every timer (shutdown, or a new incarnation whose core arms its own)."""
        for h in self._handles.values():
            h.cancel()
        self._handles.clear()

    def __len__(self) -> int:
        return len(self._handles)

    def _expired(self, key: Hashable, at: float) -> None:
        self._handles.pop(key, None)
        self._fire(key, at)
