"""Shared test fixtures. The helper modules of tests/ (imported by name, this directory is on sys.path):

* `helpers`: waiting and running — `until(cond)` polls a condition on the event loop, `wait_sync(cond)` off
  it (both return the true value; `NotYet(why)` is a false answer that says why; `ignore=` names exceptions
  that mean "not yet"), `wait_value(get, pred)` returns `get()` once `pred` holds for it, `run(coro)` runs a
  coroutine with a timeout; `haactl` in-process — `haactl(args)`, `Cli` (a cluster's `haactl`, with `out`,
  `json`, `fails`, `status`, `hosts`, `agents`, `events`), `local_cluster(root, *up)` (a local cluster taken
  down at the end, no process left behind). Tests wait for conditions; they sleep only where they measure
  time or let time pass on purpose (a quiet period, a pace, a hang), and say so.
* `hashseed`: runs simulated schedules under several PYTHONHASHSEEDs (a seed must reproduce anywhere).
* `hostilecluster`: a real three-host cluster for the hostile-peer and hostile-client tests.
* `limitagents`: agent types for the resource-limit tests.
* `collectables_sweep`: the collectable detector against the simulator's truth on seeded frames (also prints
  the table of docs/control.md: `python tests/collectables_sweep.py`).

The fixtures below hand out the `helpers` to tests that prefer fixtures to imports, and a local cluster per
test.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import helpers
import pytest


@pytest.fixture
def until() -> Callable[..., Any]:
    """`helpers.until`: `await until(lambda: cond, what="...")`."""
    return helpers.until


@pytest.fixture
def wait_sync() -> Callable[..., Any]:
    """`helpers.wait_sync`: `wait_sync(lambda: cond, what="...")` outside an event loop."""
    return helpers.wait_sync


@pytest.fixture
def local_cluster(tmp_path: Path) -> Iterator[helpers.Cli]:
    """A `helpers.Cli` for a local cluster under tmp_path/cluster, not started (`local_cluster("cluster",
    "up", "--hosts", "3")`); after the test it is taken down and no host process of it is left."""
    with helpers.local_cluster(tmp_path / "cluster") as cli:
        yield cli
