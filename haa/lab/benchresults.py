"""Where benchmarks put their figures: one JSON file per benchmark under `bench-results/` (relative to the
working directory, the repository root when run through `make` or `haactl bench`).

Library code (e.g. `haa.lab.experiments`) and the CLI (`haactl bench ...`) both write through `write_json`, so the
library never imports `haactl` (the import contract in `.importlinter`, docs/architecture.md). Each result file
describes the machine it was measured on with `machine(...)`: the facts a benchmark names, under the keys its
JSON has always used (they differ between benchmarks, and the JSON keys are a public interface).
"""

from __future__ import annotations

import json
import math
import os
import platform
from collections.abc import Callable
from pathlib import Path
from typing import Any

RESULTS = Path("bench-results")


def write_json(name: str, data: Any) -> Path:
    """Write `data` to `bench-results/<name>.json` (indented; infinity and non-JSON values become null/strings)
    and return the path."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2, default=lambda o: None if o == math.inf else str(o)) + "\n")
    return path


#: the facts `machine()` can report, by their key in the result files
MACHINE_FACTS: dict[str, Callable[[], Any]] = {
    "cpus": os.cpu_count,
    "python": platform.python_version,
    "platform": platform.platform,
    "load_avg": os.getloadavg,  # (1, 5, 15 min)
    "load_avg_at_end": os.getloadavg,  # the same, named for benchmarks that read it after the run
    "load_1min": lambda: os.getloadavg()[0],
    "event_loop": lambda: os.environ.get("HAA_EVENT_LOOP", "uvloop"),
}


def machine(*facts: str) -> dict[str, Any]:
    """The machine a benchmark ran on: `{fact: value}` for each of `facts` (keys of `MACHINE_FACTS`, in that
    order), read now; `machine()` without arguments: the CPU count and the load average."""
    unknown = [f for f in facts if f not in MACHINE_FACTS]
    if unknown:
        raise ValueError(f"unknown machine facts {unknown}; known: {', '.join(MACHINE_FACTS)}")
    return {f: MACHINE_FACTS[f]() for f in facts or ("cpus", "load_avg")}
