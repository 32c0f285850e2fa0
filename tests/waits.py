"""Waiting in tests: poll a condition, never sleep a guessed time.

A fixed sleep used as synchronization ("the message has surely arrived after 0.1 s") passes on an idle
laptop and fails on a loaded CI machine; a poll waits exactly as long as needed, up to a generous timeout,
and says what it was waiting for when that runs out. A sleep stays right where the test measures time
itself (a quiet period in which nothing may happen, a delay the code under test must keep).

Imported by the tests (`from waits import until, run`); tests/conftest.py offers the same as fixtures.
(Not in conftest.py itself: tests/chaos has its own conftest.py, and pytest imports each under the name
`conftest`, so `from conftest import ...` would find whichever was loaded last.)
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

T = TypeVar("T")

#: long enough for a loaded 2-core CI machine; a passing test never waits for it
DEFAULT_TIMEOUT = 10.0


async def until(cond: Callable[[], bool | Awaitable[bool]], timeout: float = DEFAULT_TIMEOUT,
                what: str = "condition", interval: float = 0.005) -> None:
    """Return as soon as `cond()` is true (it may be a coroutine function); fail after `timeout` seconds
    with `what` in the message. Polls every `interval` seconds on the running event loop."""
    deadline = time.monotonic() + timeout
    while True:
        ok = cond()
        if inspect.isawaitable(ok):
            ok = await ok
        if ok:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        await asyncio.sleep(interval)


def wait_sync(cond: Callable[[], bool], timeout: float = DEFAULT_TIMEOUT, what: str = "condition",
              interval: float = 0.02) -> None:
    """`until` for code outside an event loop (processes, threads)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def run(coro: Coroutine[Any, Any, T], timeout: float = 30.0) -> T:
    """Run `coro` on a fresh event loop, failing it after `timeout` seconds (a hung test fails, not hangs)."""
    return asyncio.run(asyncio.wait_for(coro, timeout))
