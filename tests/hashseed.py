"""Test helper: run simulated schedules in fresh interpreters under several PYTHONHASHSEEDs.

A seed must reproduce its schedule in any process; iterating a set of strings (whose order follows the string
hash seed) in a simulated algorithm breaks that silently. `trace_hashes` returns the distinct outputs: one
means every hash seed gave the same trace hashes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterable

CODE = (
    "import json, sys\n"
    "from haa.lab.dsim.sweep import run_seed\n"
    "print(' '.join(run_seed(a, s, h).trace_hash for a, s, h in json.loads(sys.argv[1])))"
)


def trace_hashes(runs: Iterable[tuple[str, int, int]], hash_seeds: Iterable[str]) -> set[str]:
    """The space-separated trace hashes of `runs` (algorithm, seed, hosts), one output per distinct result."""
    arg = json.dumps(list(runs))
    outs = set()
    for hs in hash_seeds:
        env = {**os.environ, "PYTHONHASHSEED": hs}
        r = subprocess.run([sys.executable, "-c", CODE, arg], env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        outs.add(r.stdout)
    return outs
