"""Trace hashes of the verifiers' schedules, to show that a change which only moves code decides the same way.

    python -m haa.lab.dsim.tracehashes --seeds 200 -o before.json        # on the old tree
    python -m haa.lab.dsim.tracehashes --seeds 200 --compare before.json  # on the new tree: exit 1 on a difference

Every verifier (haa.lab.dsim.sweep.ALGORITHMS) runs seeds 0..N-1 at its usual group size (7 hosts; 5 for transfer
and recovery, whose schedules are heavier) and the trace hash of each schedule is kept: one message, timer or
fault decided differently anywhere changes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from haa.lab.dsim import sweep

#: hosts per schedule of each verifier (the CI sweeps' sizes)
HOSTS = {"transfer": 5, "recovery": 5}


def _one(args: tuple[str, int, int]) -> tuple[str, int, str]:
    algorithm, seed, hosts = args
    return algorithm, seed, sweep.run_seed(algorithm, seed, hosts).trace_hash


def hashes(seeds: int, algorithms: list[str], workers: int | None = None) -> dict[str, list[str]]:
    """algorithm -> the trace hash of seeds 0..seeds-1."""
    jobs = [(a, s, HOSTS.get(a, 7)) for a in algorithms for s in range(seeds)]
    out: dict[str, list[str]] = {a: [""] * seeds for a in algorithms}
    with ProcessPoolExecutor(workers) as ex:
        for a, s, h in ex.map(_one, jobs, chunksize=4):
            out[a][s] = h
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200, help="seeds 0..N-1 of each verifier (200)")
    ap.add_argument("--only", default="", help="comma-separated verifiers (default: all)")
    ap.add_argument("--workers", type=int, default=None, help="processes (default: every core)")
    ap.add_argument("-o", "--out", type=Path, help="write the hashes to this JSON file")
    ap.add_argument("--compare", type=Path, help="compare with this JSON file; exit 1 on any difference")
    a = ap.parse_args(argv)
    algorithms = [x for x in a.only.split(",") if x] or list(sweep.ALGORITHMS)
    got = hashes(a.seeds, algorithms, a.workers)
    if a.out:
        a.out.write_text(json.dumps(got, indent=0) + "\n")
    if a.compare is None:
        print(f"{sum(map(len, got.values()))} trace hashes of {', '.join(algorithms)}")
        return 0
    want = json.loads(a.compare.read_text())
    bad = 0
    for alg, hs in got.items():
        old = want.get(alg, [])
        diff = [s for s, h in enumerate(hs) if s < len(old) and old[s] != h]
        same = sum(1 for s, h in enumerate(hs) if s < len(old) and old[s] == h)
        bad += len(diff)
        print(f"{alg:11s} {same} identical, {len(diff)} different" + (f" (seeds {diff[:10]})" if diff else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
