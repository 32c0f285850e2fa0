"""Shared test fixtures. The helper modules of tests/ (imported by name, this directory is on sys.path):

* `waits`: `until(cond)` polls a condition on the event loop, `wait_sync(cond)` off it, `run(coro)` runs a
  coroutine with a timeout. Tests wait for conditions; they sleep only where they measure time.
* `hashseed`: runs simulated schedules under several PYTHONHASHSEEDs (a seed must reproduce anywhere).
* `hostilecluster`: a real three-host cluster for the hostile-peer and hostile-client tests.
* `limitagents`: agent types for the resource-limit tests.

The fixtures below hand out the `waits` helpers to tests that prefer fixtures to imports.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import waits


@pytest.fixture
def until() -> Callable[..., Any]:
    """`waits.until`: `await until(lambda: cond, what="...")`."""
    return waits.until


@pytest.fixture
def wait_sync() -> Callable[..., Any]:
    """`waits.wait_sync`: `wait_sync(lambda: cond, what="...")` outside an event loop."""
    return waits.wait_sync
