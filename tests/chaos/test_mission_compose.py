"""`haactl mission start|status|logs|stop --compose`: a short exploration by the real robot team
on a 3-host compose cluster, its agents in the host containers, haa-sim the compose `sim` service (started by
`mission start` with the mission's arena, seed and speed, reached by the agents as sim:7100), to completion;
then `stop` takes the sim container down again.

The cluster is a compose project of its own (`haamission<pid>`: the first 3 host services and the `sim`
service of compose/compose.yaml, free published ports, a free 10.77.x.0/24 subnet; helpers of
test_agents_chaos). Marker `docker`: skipped without an engine or the image (failed with
HAA_REQUIRE_DOCKER=1). ≈ 60-90 s.
"""

from __future__ import annotations

import os
import random
import re
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from chaoslib import docker_problem
from helpers import Cli, NotYet, wait_sync
from test_agents_chaos import SOURCE, up_on_free_subnet

from haa.cluster.backend import wait_until
from haa.cluster.compose_backend import ComposeBackend
from haa.cluster.hostprocs import free_port

pytestmark = pytest.mark.docker
N = 3

MISSION = """\
name: compose-quick
scenario: explore
arena: small
seed: 7
slam: jc-slam
particles: 30
speed: 4
complete: {explored: 0.3, time_limit_s: 300}
hosts: {start: 3}
avatars:
  - {name: s1, type: seeker, pose: [0.5, 0.5, 1.5708]}
  - {name: s2, type: seeker, pose: [2.9, 0.5, 1.5708]}
"""


def with_sim(f: Path, prefix: str) -> None:
    """Add compose/compose.yaml's `sim` service to the derived file `f` (its address in `prefix`, a free
    published port)."""
    spec = yaml.safe_load(f.read_text())
    sim = dict(yaml.safe_load(SOURCE.read_text())["services"]["sim"])
    sim["ports"] = [f"127.0.0.1:{free_port()}:7100"]
    sim["labels"] = {"io.haa.test": "mission-compose"}
    spec["services"]["sim"] = sim
    f.write_text(re.sub(r"\$\{HAA_SUBNET_PREFIX:-[0-9.]+\}", prefix, yaml.safe_dump(spec, sort_keys=False)))


def sim_containers(backend: ComposeBackend) -> list:
    mine = backend.docker.containers.list(all=True, filters={"label": f"com.docker.compose.project={backend.project}"})
    return [c for c in mine if c.labels.get("com.docker.compose.service") == "sim"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ComposeBackend, Path]]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    project = f"haamission{os.getpid()}"
    rng = random.Random(os.getpid() + 1)
    backend, names, _ = up_on_free_subnet(lambda: tmp_path_factory.mktemp("mission-compose"), N, project, rng,
                                          prepare=with_sim)
    f = backend.file
    try:
        wait_until(lambda: backend.formation(names), 120, what=f"{N} hosts in one group")
        yield backend, f
    finally:
        backend.down(grace=1)


def test_a_mission_runs_to_completion_on_the_compose_cluster(cluster, tmp_path, monkeypatch) -> None:
    backend, f = cluster
    monkeypatch.chdir(tmp_path)  # the mission state: .haa/compose-<project>/mission under the current directory
    (tmp_path / "m.yaml").write_text(MISSION)
    cli = Cli(extra=("--compose",), env={"HAA_COMPOSE_FILE": str(f), "HAA_COMPOSE_PROJECT": backend.project})
    try:
        t0 = time.monotonic()
        started = cli.out("mission", "start", str(tmp_path / "m.yaml"))
        assert "mission compose-quick started" in started
        sim = sim_containers(backend)
        assert sim and sim[0].status == "running"
        saw_running = False

        def ended() -> dict | NotYet:
            nonlocal saw_running
            st = cli.json("mission", "status")
            saw_running = saw_running or (st.get("state") == "running" and bool(st.get("agents_per_host")))
            return st if st.get("state") in ("finished", "failed") else NotYet(f"state {st.get('state')}")

        st = wait_sync(ended, 150, "the mission to end", interval=1.0)
        print(f"mission on compose: {st.get('state')} after {time.monotonic() - t0:.1f} s wall")
        assert st.get("state") == "finished", st
        res = st["results"]
        assert res["completed"] is True, res.get("reason")
        assert saw_running
        # the agents ran in the containers (the hosts of the compose cluster), and the status says where
        assert set(st["hosts"]) == {"h1", "h2", "h3"}
        assert sum(len(v) for v in st["agents_per_host"].values()) >= 4, st["agents_per_host"]
        logs = cli.out("mission", "logs")
        assert "mission" in logs.lower() and "s1" in logs
        text = cli.out("mission", "status")
        assert "compose-quick" in text
    finally:
        stopped = cli("mission", "stop", ok=False).stdout
    assert "haa-sim stopped" in stopped, stopped
    assert not sim_containers(backend)
