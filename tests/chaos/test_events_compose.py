"""`haactl agent events --compose` after a host container was killed and restarted (a regression
guard: on the compose cluster the timeline said "A1 (counter) crashed on h1" and had no line of A1 thawing on h10).

A compose project of its own (`haaevents<pid>`: the first 4 host services of compose/compose.yaml, free
published ports, a free 10.77.x.0/24 subnet; helpers of test_agents_chaos) runs one counter agent; it is moved
to h4 (a thaw there), h4's container is killed (`haactl host kill h4 --compose --wait`; the agent is recovered
on a survivor) and started again (`host restart`). `agent events --compose --json` must show the thaw on h4 —
read from the container's log through the docker SDK, which keeps the log of the life before the restart —,
the crash on h4 reported by a survivor, the recovery elsewhere, and h4 removed and joined again; then h4 is
killed again and left stopped: the same from the stopped container's log. Marker `docker`: skipped without an
engine or the image (failed with HAA_REQUIRE_DOCKER=1). ≈40-60 s.
"""

from __future__ import annotations

import json
import os
import random
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from chaoslib import docker_problem
from helpers import Cli, wait_value
from test_agents_chaos import up_on_free_subnet

from haa.cluster.backend import wait_until

pytestmark = pytest.mark.docker
N = 4
VICTIM = "h4"  # not a core host: the group keeps its three core members


class Compose(Cli):
    """`haactl ... --compose` for one compose file and project."""

    def __init__(self, file: Path, project: str) -> None:
        super().__init__(extra=("--compose", "--compose-file", str(file)), env={"HAA_COMPOSE_PROJECT": project})

    def wait_a1(self, pred: Any, timeout: float, what: str) -> dict[str, Any]:
        """A1's row of `agent list` once `pred` holds for it (a command failing meanwhile is "not yet")."""
        return wait_value(lambda: self.agents().get("A1"), lambda a: a and pred(a), timeout, what, interval=0.3,
                          ignore=(AssertionError,))


@pytest.fixture(scope="module")
def compose(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Compose]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    project = f"haaevents{os.getpid()}"
    rng = random.Random(os.getpid())
    backend, names, _ = up_on_free_subnet(lambda: tmp_path_factory.mktemp("events"), N, project, rng)
    f = backend.file
    try:
        wait_until(lambda: backend.formation(names), 120, what=f"{N} hosts in one group")
        yield Compose(f, project)
    finally:
        backend.down(grace=1)


def check_story(evs: list[dict[str, Any]]) -> None:
    texts = [e["text"] for e in evs]
    a1 = [e for e in evs if e["name"] == "A1"]
    thaw = [e for e in a1 if e["event"] == "thawed" and e["host"] == VICTIM]
    assert thaw, f"no thaw of A1 on {VICTIM}:\n" + "\n".join(texts)
    crash = [e for e in a1 if e["event"] == "crashed" and e["time"] > thaw[0]["time"]]
    assert len(crash) == 1, "\n".join(texts)
    c = crash[0]
    assert c["host"] == VICTIM and c["reporter"] not in ("", VICTIM), c
    assert c["text"] == f"A1 (counter) crashed on {VICTIM} (reported by {c['reporter']})"
    assert any(e["event"] == "recovered" and e["host"] != VICTIM and e["time"] > c["time"] for e in a1), texts
    assert any(e["text"] == f"{VICTIM} removed" for e in evs), texts
    assert any(e["text"] == f"{VICTIM} joined" and e["time"] > c["time"] for e in evs), texts
    assert [e["time"] for e in evs] == sorted(e["time"] for e in evs)
    assert all(e["host"] for e in evs)


def test_killed_and_restarted_container_keeps_its_events(compose: Compose) -> None:
    t0 = time.monotonic()
    compose("agent", "spawn", "counter", "--config", json.dumps({"period": 0.2, "backup_every": 5}))
    compose.wait_a1(lambda a: a["state"] == "active", 60, "A1 active")
    compose("agent", "move", "A1", VICTIM)
    compose("host", "kill", VICTIM, "--wait", "--timeout", "60")
    compose.wait_a1(lambda a: a["state"] == "active" and a["host"] != VICTIM, 60, "A1 recovered elsewhere")
    compose("host", "restart", VICTIM, "--timeout", "90")  # the same container: a new incarnation
    evs = [json.loads(ln) for ln in compose.out("agent", "events", "--json").splitlines()]
    print("\n".join(f"{e['clock']} {e['text']}" for e in evs))
    check_story(evs)
    compose("host", "kill", VICTIM, "--wait", "--timeout", "60")  # stopped for good: its container's log remains
    check_story([json.loads(ln) for ln in compose.out("agent", "events", "--json").splitlines()])
    print(f"compose scenario: {time.monotonic() - t0:.1f} s")


def test_stats_bundles_of_the_compose_cluster(compose: Compose, tmp_path: Path) -> None:
    """`haactl stats collect --compose` after the scenario above (docs/stats.md): one bundle per
    container, read through the docker SDK — the killed, stopped VICTIM's too — with its samples, its log and
    the events that happened on it (A1 thawed there, its crash reported by a survivor). Runs on the cluster of
    the test above (it leaves VICTIM stopped); ≈5 s."""
    from haa.lab.stats.bundle import load_bundles

    compose("stats", "collect", "-o", str(tmp_path / "b"), "-q")
    bundles = {b.host: b for b in load_bundles(tmp_path / "b")}
    assert sorted(bundles) == [f"h{i + 1}" for i in range(N)]
    dead = bundles[VICTIM]
    assert dead.manifest["state"] == "killed" and dead.manifest["errors"] == [], dead.manifest
    assert dead.manifest["source"].startswith("container "), dead.manifest["source"]
    assert dead.samples and all(s["host"] == VICTIM for s in dead.samples)
    assert len({s["inc"] for s in dead.samples}) == 2  # before and after its restart
    assert all(r["host"] == VICTIM for r in dead.log)
    names = {(e["name"], e["event"]) for e in dead.events}
    assert ("A1", "thawed") in names and ("A1", "crashed") in names, dead.events
    assert all(e["host"] == VICTIM for e in dead.events)
    for b in bundles.values():
        assert b.samples and b.views and b.json("config.json")["settings"]["name"] == b.host
