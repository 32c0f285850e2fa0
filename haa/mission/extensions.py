"""What a mission uses from the lab without importing it (docs/architecture.md, "Three products").

The robot team sits below the lab in the import graph, yet a mission file may name a chaos plan (`chaos: FILE`,
docs/chaos.md "Inside a mission": experiments R-1 and R-2 are missions with failures), and `mission run -o DIR`
writes the hosts' stats bundles beside its results (docs/stats.md). The lab offers both as entry points of group
`haa.mission` (pyproject.toml), found by name when a mission needs them:

* `chaos` — a module with `load(path) -> plan` (ValueError with one line if the plan cannot run),
  `problems(plan, hosts) -> list[str]` (what the plan asks that the mission cannot do) and
  `injector(plan, backend, **options)` (an object with `run(stop, t0)` and `injected`);
* `bundles` — `collect(backend, out_dir)`, which never raises.

A team installed without the lab refuses a mission with a `chaos:` key with one line and writes no bundles.
"""

from __future__ import annotations

import importlib.metadata
from typing import Any

GROUP = "haa.mission"


class ExtensionMissing(LookupError):
    """No installed distribution offers the extension."""


def extension(name: str) -> Any:
    """The object the entry point `name` of group `haa.mission` names, loaded now; ExtensionMissing if none."""
    for ep in importlib.metadata.entry_points(group=GROUP, name=name):
        return ep.load()
    raise ExtensionMissing(f"no installed package offers the mission extension {name!r} (entry point group "
                           f"{GROUP}; HAA's lab offers it: install haa with its lab)")
