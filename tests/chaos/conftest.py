"""Container chaos tests: a 10-container compose cluster (compose/compose.yaml, project haa).

Needs a reachable docker engine and the image haa-hostd:latest (`make docker-setup image`); without them the
tests are skipped with the reason — or fail, when HAA_REQUIRE_DOCKER=1 (as in .ci/run, so that CI cannot
pass by skipping them). The cluster is brought up with `haactl cluster up --compose --hosts 10` and taken
down at the end; a compose cluster already running under project `haa` is taken down first. Every random
choice comes from one seed (HAA_CHAOS_SEED, else the time), printed at the start. The containers' logs of
each run are saved as JSON lines in .haa/lab/chaos/ (the five newest runs).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from chaoslib import Chaos, docker_problem

from haa.cluster.compose_backend import ComposeBackend

HAACTL = Path(sys.executable).parent / "haactl"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def chaos() -> Iterator[Chaos]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    seed = int(os.environ.get("HAA_CHAOS_SEED") or time.time_ns() % 1_000_000)
    print(f"\nchaos seed {seed} (HAA_CHAOS_SEED={seed} reproduces the choices)")
    backend = ComposeBackend(REPO / "compose" / "compose.yaml")
    if backend.containers():
        backend.down(grace=1)
    t0 = time.monotonic()
    r = subprocess.run(
        [str(HAACTL), "cluster", "up", "--compose", "--hosts", "10", "--json", "--timeout", "120"],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "HAA_COMPOSE_FILE": str(backend.file)},
    )
    if r.returncode != 0:
        backend.down(grace=1)
        pytest.fail(f"haactl cluster up --compose failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")
    formed = json.loads(r.stdout)
    print(f"compose cluster of 10 formed in {time.monotonic() - t0:.1f} s: {formed}")
    backend = ComposeBackend(REPO / "compose" / "compose.yaml")  # the token may have been made by `up`
    try:
        yield Chaos(backend, seed)
    finally:
        # Kept under .haa/lab/chaos/ (gitignored; the 5 newest runs), where pytest's tmp cleanup cannot reach them.
        keep = REPO / ".haa" / "chaos"
        keep.mkdir(parents=True, exist_ok=True)
        logs = keep / f"{time.strftime('%Y%m%d-%H%M%S')}-seed{seed}.jsonl"
        with open(logs, "w") as f:
            subprocess.run(
                [str(HAACTL), "logs", "--compose", "--json"],
                stdout=f,
                stderr=subprocess.DEVNULL,
                timeout=120,
                env={**os.environ, "HAA_COMPOSE_FILE": str(backend.file)},
            )
        for old in sorted(keep.glob("*.jsonl"))[:-5]:
            old.unlink()
        print(f"\ncontainer logs: {logs} (chaos seed {seed})")
        backend.down(grace=2)
