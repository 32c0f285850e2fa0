"""`haactl chaos run` on a real 5-host local cluster (one ~30 s plan: a host kill, a pause, a restart and two
agent hangs under the ddb-writes workload): every check green, the faults and their effects on one timeline,
the JSON as documented. Then each check is shown to fail: a copy of the run directory with its persisted
history mutated (an acknowledged write lost, a write applied twice, a replica's hash changed, an older
instance's write accepted after a newer one's, a crashed agent's recovery missing) makes exactly that check
fail, and `haactl chaos check` exits 1 on it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from haa.lab.chaos.checks import agent_events, run_checks
from haa.lab.chaos.collect import host_logs, replicas
from haactl.main import app

PLAN = """
name: ci
seed: 11
duration_s: 30
hosts: 5
workload: ddb-writes
agents: 3
period_s: 0.2
settle_s: 40
faults:
  - {at_s: 4, action: kill, target: host h4}
  - {at_s: 8, action: hang, target: agent A1, hang_s: 5}     # longer than the hang timeout: its host kills it
  - {at_s: 12, action: pause, target: host h5, for_s: 4}
  - {at_s: 20, action: restart, target: host h4}
  - {at_s: 23, action: hang, target: random-agent, hang_s: 2}  # shorter: it fails by itself
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("chaos")
    (d / "plan.yaml").write_text(PLAN)
    r = CliRunner().invoke(app, ["chaos", "run", str(d / "plan.yaml"), "--out", str(d / "run"),
                                 "--json", str(d / "result.json")])
    result = json.loads((d / "result.json").read_text()) if (d / "result.json").exists() else None
    return r, result, d / "run"


def test_the_plan_runs_with_every_check_green(run):
    r, result, _ = run
    assert result is not None, r.output
    assert r.exit_code == 0, r.output + json.dumps(result.get("checks"), indent=1)
    assert result["passed"] is True and result["error"] == ""
    assert set(result["checks"]) == {"acked_writes_once", "replicas_agree", "single_instance",
                                     "crashed_agents_recovered"}
    assert all(c["passed"] for c in result["checks"].values())
    done = {(f["action"], f["target"]) for f in result["faults"] if f["ok"]}
    assert {("kill", "h4"), ("pause", "h5"), ("resume", "h5"), ("restart", "h4")} <= done
    hangs = [f for f in result["faults"] if f["action"] == "hang"]
    assert len(hangs) == 2 and any(f["ok"] for f in hangs), hangs
    for f in result["faults"]:
        assert {"t", "ts", "action", "target", "ok", "detail"} <= set(f)
    assert "acknowledged writes of 3 writers" in result["checks"]["acked_writes_once"]["detail"]


def test_faults_and_effects_on_one_timeline(run):
    _, result, _ = run
    assert result is not None
    lines = [(e["host"], e["text"]) for e in result["timeline"]]
    texts = [t for _, t in lines]
    assert any(t.startswith("kill h4") for t in texts)
    assert any("h4 removed" in t for t in texts)  # a view change
    assert any("suspects h5" in t for t in texts)
    assert any("h4 joined" in t for t in texts)  # the restart
    assert any(" hung on " in t or "chaos hang" in t for t in texts)
    assert any(" recovered on " in t for t in texts)
    ts = [e["ts"] for e in result["timeline"]]
    assert ts == sorted(ts)
    assert all(e["host"] for e in result["timeline"] if e["kind"] == "effect")  # every effect names its host
    assert max(e["ts"] for e in result["timeline"]) <= result["t_end"]  # the cluster stopping is not in it


# ------------------------------------------------------------------ each check can fail

def mutated(run_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run_dir, dst, ignore=shutil.ignore_patterns("cluster"))
    return dst


def rewrite_replicas(run_dir: Path, fn) -> None:
    for p in sorted((run_dir / "replicas").glob("*.json")):
        rec = json.loads(p.read_text())
        fn(p.stem, rec)
        p.write_text(json.dumps(rec))


def writer_log(rec: dict, writer: str) -> list[str]:
    return rec["objects"][f"chaos/log/{writer}"]["value"]["items"]


def failing(run_dir: Path) -> set[str]:
    return {k for k, c in run_checks(run_dir, "ddb-writes").items() if not c.passed}


def an_acked_item(run_dir: Path) -> tuple[str, str]:
    for recs in host_logs(run_dir).values():
        for r in recs:
            if r.get("event") == "chaos_ack":
                f = r["fields"]
                return f["w"], json.dumps({"w": f["w"], "e": f["e"], "n": f["n"]}, separators=(",", ":"))
    raise AssertionError("no ack in the logs")


@pytest.fixture
def copy(run, tmp_path):
    _, result, run_dir = run
    if result is None or not result["passed"]:
        pytest.skip("the chaos run itself failed (see test_the_plan_runs_with_every_check_green)")
    assert failing(run_dir) == set()
    return mutated(run_dir, tmp_path)


def test_a_lost_acknowledged_write_fails_acked_writes_once(copy):
    w, item = an_acked_item(copy)
    rewrite_replicas(copy, lambda _h, rec: writer_log(rec, w).remove(item))
    assert failing(copy) == {"acked_writes_once"}
    assert "missing" in run_checks(copy, "ddb-writes")["acked_writes_once"].detail
    r = CliRunner().invoke(app, ["chaos", "check", str(copy)])
    assert r.exit_code == 1 and "FAILED" in r.output


def test_a_write_applied_twice_fails_acked_writes_once(copy):
    w, item = an_acked_item(copy)

    def twice(_h, rec):  # applied again right after itself (a retried batch applied twice)
        items = writer_log(rec, w)
        items.insert(items.index(item) + 1, item)

    rewrite_replicas(copy, twice)
    assert failing(copy) == {"acked_writes_once"}
    assert "present 2 times" in run_checks(copy, "ddb-writes")["acked_writes_once"].detail


def test_a_diverging_replica_fails_replicas_agree(copy):
    first = sorted(replicas(copy))[0]

    def change(h, rec):
        if h == first:
            rec["status"]["ddb_hash"] = "0" * 64

    rewrite_replicas(copy, change)
    assert failing(copy) == {"replicas_agree"}


def test_a_stale_instance_write_accepted_fails_single_instance(copy):
    reps = replicas(copy)
    logs = next(iter(reps.values()))["objects"]
    w = next(k.split("/")[-1] for k, o in logs.items() if k.startswith("chaos/log/"))
    stale = json.dumps({"w": w, "e": 0, "n": 10**6}, separators=(",", ":"))  # epoch 0: older than any instance
    rewrite_replicas(copy, lambda _h, rec: writer_log(rec, w).append(stale))
    assert failing(copy) == {"single_instance"}
    assert "older instance accepted" in run_checks(copy, "ddb-writes")["single_instance"].detail


def test_a_crashed_agent_never_recovered_fails_crashed_agents_recovered(copy):
    evs = agent_events(host_logs(copy))
    crashed = next(e["agent"] for e in evs if e["event"] == "agent_crashed")
    for p in (copy / "hosts").glob("*.jsonl"):
        keep = []
        for line in p.read_text().splitlines():
            try:
                r = json.loads(line)
            except ValueError:
                keep.append(line)
                continue
            f = r.get("fields", {})
            if f.get("agent") == crashed and r.get("event") in ("agent_recovered", "agent_active", "agent_thawed"):
                continue
            keep.append(line)
        p.write_text("\n".join(keep) + "\n")
    assert failing(copy) == {"crashed_agents_recovered"}
    assert "never recovered" in run_checks(copy, "ddb-writes")["crashed_agents_recovered"].detail
