"""`haactl chaos run PLAN --compose`: a 30 s plan against a 5-container compose cluster — a
host container killed and restarted, one paused and unpaused, one cut off the network (`docker network
disconnect`) and connected again, two agent hangs — under the ddb-writes workload, with every check green
from the hosts' persisted logs (the killed container's read through the docker SDK) and every fault and
effect on one timeline.

The cluster is a compose project of its own (`haachaos<pid>`: the first 5 host services of
compose/compose.yaml, free published ports, a free 10.77.x.0/24 subnet; helpers of test_agents_chaos), so
it never touches the project `haa`. Marker `docker`: skipped without an engine or the image (failed with
HAA_REQUIRE_DOCKER=1). ≈ 80-110 s.
"""

from __future__ import annotations

import json
import os
import random

import pytest
from chaoslib import docker_problem
from test_agents_chaos import derive_compose, free_prefix
from typer.testing import CliRunner

from haa.cluster.compose_backend import ComposeBackend
from haactl.main import app

pytestmark = pytest.mark.docker

PLAN = """
name: compose-ci
seed: 5
duration_s: 30
hosts: 5
workload: ddb-writes
agents: 3
period_s: 0.2
settle_s: 45
faults:
  - {at_s: 2, action: kill, target: host h4}
  - {at_s: 5, action: hang, target: agent A1, hang_s: 5}      # longer than the hang timeout: its host kills it
  - {at_s: 8, action: pause, target: host h5, for_s: 4}       # docker pause, then unpause
  - {at_s: 13, action: restart, target: host h4}
  - {at_s: 20, action: partition, target: [h5], for_s: 5}     # docker network disconnect, then connect
  - {at_s: 23, action: hang, target: random-agent, hang_s: 2} # shorter: it fails by itself
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    d = tmp_path_factory.mktemp("chaos-compose")
    f = derive_compose(d / "compose", 5, free_prefix(random.Random(os.getpid())))
    project = f"haachaos{os.getpid()}"
    (d / "plan.yaml").write_text(PLAN)
    try:
        r = CliRunner().invoke(app, ["chaos", "run", str(d / "plan.yaml"), "--compose", "--compose-file", str(f),
                                     "--out", str(d / "run"), "--json", str(d / "result.json")],
                               env={"HAA_COMPOSE_PROJECT": project})
    finally:
        b = ComposeBackend(f, project=project)
        if b.containers():  # the run removes its project; a crash of the test must not leave it behind
            b.down(grace=1)
    result = json.loads((d / "result.json").read_text()) if (d / "result.json").exists() else None
    return r, result, d / "run"


def test_the_plan_runs_on_the_compose_cluster_with_every_check_green(run) -> None:
    r, result, out = run
    assert result is not None, f"{r.output}\n{r.exception!r}"
    assert r.exit_code == 0, r.output + json.dumps(result.get("checks"), indent=1)
    assert result["passed"] is True and result["error"] == ""
    assert set(result["checks"]) == {"acked_writes_once", "replicas_agree", "single_instance",
                                     "crashed_agents_recovered"}
    done = {(f["action"], f["target"]) for f in result["faults"] if f["ok"]}
    assert {("kill", "h4"), ("pause", "h5"), ("resume", "h5"), ("restart", "h4"), ("partition", "h5"),
            ("heal", "h5")} <= done, result["faults"]
    hangs = [f for f in result["faults"] if f["action"] == "hang"]
    assert len(hangs) == 2 and any(f["ok"] for f in hangs), hangs
    assert "acknowledged writes" in result["checks"]["acked_writes_once"]["detail"]
    # every host's persisted log was read out of its container, the killed one's too
    assert sorted(p.stem for p in (out / "hosts").glob("*.jsonl")) == ["h1", "h2", "h3", "h4", "h5"]


def test_faults_and_their_effects_on_one_timeline(run) -> None:
    _, result, _ = run
    assert result is not None
    tl = result["timeline"]
    assert [e["ts"] for e in tl] == sorted(e["ts"] for e in tl)
    texts = [e["text"] for e in tl]
    faults = [e for e in tl if e["kind"] == "fault"]
    assert any(t.startswith("partition h5") for t in texts) and any(t.startswith("heal h5") for t in texts)
    effects = [e for e in tl if e["kind"] == "effect"]
    assert all(e["host"] for e in effects)
    # h4 (killed), h5 (paused, then partitioned) are removed by the group; A1's hang ends in a recovery
    removed = [t for t in texts if "removed" in t and t.startswith("view")]
    assert any("h4" in t for t in removed) and any("h5" in t for t in removed), texts
    assert any(t.startswith("A1") and "recovered" in t for t in texts), texts
    kill_t = next(e["t"] for e in faults if e["text"].startswith("kill h4"))
    assert any("h4" in t and e["t"] > kill_t for e, t in zip(tl, texts, strict=True) if t.startswith("view")), texts
