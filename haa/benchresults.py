"""Where benchmarks put their figures: one JSON file per benchmark under `bench-results/` (relative to the
working directory, the repository root when run through `make` or `haactl bench`).

Library code (e.g. `haa.agents.bench`) and the CLI (`haactl bench ...`) both write through `write_json`, so the
library never imports `haactl` (the import contract in `.importlinter`, docs/architecture.md).
"""

from __future__ import annotations

import json
import math
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
