"""One run directory, read: `load_run(DIR)` gives the `RunData` that the report (haa.lab.stats.report) and its
figures (haa.lab.stats.figures) draw from — the bundles of its hosts (haa.lab.stats.collect), and what a mission or a
chaos run adds (`results.json`, `samples.json`, `faults.json`, `chaos.json`, `result.json`). The summary, the
time series, the timeline and the view changes are computed from the bundles on first use (haa.lab.stats.summary);
a missing or broken input raises `BundleError` with one line.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from haa.cluster.backend import natural_key
from haa.cluster.events import TimelineEvent
from haa.lab.stats.bundle import Bundle, BundleError, load_bundles
from haa.lab.stats.summary import Series, events_of, series, summarize, time_range, view_changes


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise BundleError(f"{path}: not readable JSON ({e})") from None


@dataclass
class RunData:
    """One run directory, read (module docstring)."""

    dir: Path
    bundles: list[Bundle]
    faults: list[dict[str, Any]] = field(default_factory=list)
    chaos: dict[str, Any] | None = None  # result.json of a chaos run
    mission: dict[str, Any] | None = None  # {"results": ..., "samples": ...}

    @property
    def name(self) -> str:
        return self.dir.name

    @cached_property
    def by_host(self) -> dict[str, Bundle]:
        return {b.host: b for b in self.bundles}

    @cached_property
    def _range(self) -> tuple[float, float]:
        return time_range(self.bundles)

    @property
    def t0(self) -> float:
        return self._range[0]

    @property
    def t1(self) -> float:
        return self._range[1]

    @cached_property
    def summary(self) -> dict[str, Any]:
        return summarize(self.bundles, cluster=str(self.bundles[0].manifest.get("cluster", "")))

    @cached_property
    def series(self) -> Series:
        return series(self.bundles, self.t0)

    @cached_property
    def events(self) -> list[TimelineEvent]:
        return events_of(self.bundles)

    @cached_property
    def views(self) -> list[dict[str, Any]]:
        return view_changes(self.bundles)

    @staticmethod
    def host_key(name: str) -> tuple[str, int, str]:
        return natural_key(name)


def load_run(d: Path) -> RunData:
    d = Path(d)
    run = RunData(d, load_bundles(d))
    for name in ("faults.json", "chaos.json"):  # a chaos run's, a mission's with a chaos plan
        if (d / name).exists():
            f = _load_json(d / name)
            run.faults = [x for x in (f.get("faults") or []) if isinstance(x, dict) and "ts" in x]
            break
    if (d / "result.json").exists():
        run.chaos = _load_json(d / "result.json")
    if (d / "results.json").exists():
        run.mission = {"results": _load_json(d / "results.json"),
                       "samples": _load_json(d / "samples.json") if (d / "samples.json").exists() else {}}
    return run
