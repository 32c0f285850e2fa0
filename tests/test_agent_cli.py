"""`haactl agent ...` and `haactl alloc ...` on a local cluster of 3 real haa-hostd processes.

The tests share one cluster and run in order: spawn a counter pair, list and tree, move, kill (recovered),
alloc pause/resume/run, the merged timeline, operator errors, a crashed host (its agents recovered
elsewhere; a move to it refused), remove. Commands run in-process through typer's CliRunner. The first
tests check the merging of AgentList replies without a cluster.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from helpers import Cli, local_cluster, wait_value

from haa.cluster.agents import AgentRow, merge_agents
from haa.cluster.events import TimelineEvent
from haa.cluster.feed import EventFeed
from haa.pb import control_pb2 as cpb

COUNTER = json.dumps({"spawn_peer": True, "period": 0.05, "backup_every": 20})


# ---------------------------------------------------------------------------------------------- no cluster


def info(agent_id: str, name: str, status: str, owner: str, phase: str = "", **kw: Any) -> cpb.AgentInfo:
    return cpb.AgentInfo(id=agent_id, name=name, type="counter", status=status, owner=owner,
                         alloc=kw.pop("alloc", owner), epoch=kw.pop("epoch", 1), local_phase=phase, **kw)


def test_merge_prefers_the_local_phase_of_the_host_running_the_agent() -> None:
    replies = {
        "h1": cpb.AgentListReply(host="h1", agents=[
            info("a1", "A1", "active", "h2"),
            info("b2", "A1.1", "new", "", parent="a1"),
            info("c3", "A2", "freezing", "h1", "freezing", epoch=3),
        ]),
        "h2": cpb.AgentListReply(host="h2", agents=[
            info("a1", "A1", "active", "h2", "active", local_cpu=0.25, pid=42),
            info("b2", "A1.1", "new", "", "recovering", parent="a1"),
            info("c3", "A2", "freezing", "h1", epoch=3),
        ]),
        "h3": cpb.AgentListReply(host="h3", agents=[
            info("a1", "A1", "active", "h2"),
            info("b2", "A1.1", "new", "", parent="a1"),
            info("c3", "A2", "frozen", "", "claiming", epoch=4, alloc="h3"),
        ]),
    }
    rows = {r.name: r for r in merge_agents(replies)}
    assert (rows["A1"].state, rows["A1"].host, rows["A1"].cpu, rows["A1"].pid) == ("active", "h2", 0.25, 42)
    # the first start of a new agent goes through recoverAgent: shown as spawning on the host preparing it
    assert (rows["A1.1"].state, rows["A1.1"].host, rows["A1.1"].parent) == ("spawning", "h2", "A1")
    # h3's replica is one commit ahead (frozen, epoch 4) and h3 is claiming it: thawing on h3
    assert (rows["A2"].state, rows["A2"].host, rows["A2"].epoch) == ("thawing", "h3", 4)
    assert [r.name for r in merge_agents(replies)] == ["A1", "A1.1", "A2"]
    # OAC(recovered) of the first start committed (active, life 1), the process not started yet: spawning;
    # the same phase after a crash (life 2) is a recovery
    for life, want in ((1, "spawning"), (2, "recovering")):
        rows = {r.name: r for r in merge_agents({"h2": cpb.AgentListReply(host="h2", agents=[
            info("b2", "A1.1", "active", "h2", "recovering", life=life)])})}
        assert rows["A1.1"].state == want, (life, rows["A1.1"])


def test_timeline_shows_each_table_event_once() -> None:
    feed = EventFeed(None)  # type: ignore[arg-type]  # describe() needs no cluster
    evs = [
        TimelineEvent(1.0, "x", "A1", "created", "h1", "counter"),
        TimelineEvent(1.0, "x", "A1", "created", "h2", "counter"),
        TimelineEvent(1.1, "x", "A1", "active", "h2", "fresh state"),
        TimelineEvent(5.0, "x", "A1", "crashed", "h2", "killed by signal 9"),
        TimelineEvent(5.01, "x", "A1", "crashed", "h1", ""),
        TimelineEvent(5.01, "x", "A1", "crashed", "h2", ""),
        TimelineEvent(5.1, "x", "A1", "recovered", "h3", "from backup"),
        TimelineEvent(9.0, "x", "A1", "crashed", "h1", ""),  # h3 crashed: only the survivors report it
    ]
    shown = [e.text for e in evs if feed.describe(e, evs)]
    assert shown == [
        "A1 (counter) requested by the operator",
        "A1 (counter) spawned by h2",
        "A1 (counter) crashed on h2: killed by signal 9",
        "A1 (counter) recovered by h3 (from backup)",
        "A1 (counter) crashed on h3 (reported by h1)",  # where it ran, and who said so
    ]
    assert (evs[-1].host, evs[-1].reporter) == ("h3", "h1")


def test_no_cluster_is_a_clear_error(tmp_path: Path) -> None:
    r = Cli(tmp_path)("agent", "list", ok=False)
    assert r.exit_code == 1
    assert "no cluster running" in r.output and "haactl cluster up" in r.output


class MovedAgentCluster:
    """A cluster where agent A1 was listed on h1 but has moved by the time of the kill: h1 answers AgentKill
    with the typed owner of the agent table (`owner`), the host that runs it now kills it."""

    def __init__(self, owner: str, reason: str) -> None:
        self.asked: list[str] = []
        self.replies = {
            "h1": cpb.AgentOpReply(ok=False, id="a1", name="A1", owner=owner, reason=reason),
            "h2": cpb.AgentOpReply(ok=True, id="a1", name="A1"),
        }

    def hosts(self) -> list[Any]:
        return [SimpleNamespace(name=n) for n in ("h1", "h2", "h3")]

    def call(self, name: str, fn: Any, what: str, timeout: float | None = None) -> Any:
        self.asked.append(name)
        return fn(SimpleNamespace(agent_kill=lambda ref: self.replies[name]))


@pytest.mark.parametrize(("owner", "reason", "asked", "said"), [
    # it moved: asked once more, on the owner the reply names (its reason's words are for people only)
    ("h2", "not running here; its owner is h2", ["h1", "h2"], "killed A1 on h2"),
    ("h2", "not running here (moved to h2)", ["h1", "h2"], "killed A1 on h2"),
    # no owner: nobody to ask
    ("", "not running here; its owner is nobody", ["h1"],
     "error: kill A1 on h1: not running here; its owner is nobody"),
])
def test_kill_asks_the_owner_the_host_names(monkeypatch: pytest.MonkeyPatch, owner: str, reason: str,
                                            asked: list[str], said: str) -> None:
    import haactl.agentcli as ac

    cluster = MovedAgentCluster(owner, reason)
    row = AgentRow(name="A1", id="a1", type="counter", state="active", host="h1", cpu=0.0, parent="",
                   parent_id="", epoch=1, backup=True, status="active", owner="h1", alloc="h1",
                   phases={"h1": "active"})
    monkeypatch.setattr(ac.ClusterOpts, "backend", lambda self, last=False: cluster)
    monkeypatch.setattr(ac, "load_rows", lambda backend: ({}, [row]))
    r = Cli()("agent", "kill", "A1", "--no-wait", ok=False)
    assert r.exit_code == (0 if owner else 1), r.output
    assert said in " ".join(r.output.split()) and cluster.asked == asked


# ---------------------------------------------------------------------------------------------- a cluster


def wait_agents(cli: Cli, pred: Any, timeout: float, what: str) -> dict[str, dict[str, Any]]:
    return wait_value(cli.agents, pred, timeout, what, interval=0.2, show=lambda a: json.dumps(a, indent=1))


@pytest.fixture(scope="module")
def cli(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cli]:
    with local_cluster(tmp_path_factory.mktemp("agents"), "--hosts", "3") as c:
        yield c


def test_spawn_list_tree(cli: Cli) -> None:
    r = json.loads(cli("agent", "spawn", "counter", "--config", COUNTER, "--json").stdout)
    assert r["ok"] and r["name"] == "A1" and r["host"]
    a = wait_agents(cli, lambda a: a.get("A1.1", {}).get("state") == "active", 30, "A1.1 active")
    assert set(a) == {"A1", "A1.1"}
    assert a["A1"]["id"] == r["id"] and a["A1.1"]["parent"] == "A1" and a["A1.1"]["parent_id"] == r["id"]
    for x in a.values():
        assert x["type"] == "counter" and x["host"] in ("h1", "h2", "h3") and x["pid"] > 0 and x["epoch"] >= 1
    table = cli("agent", "list").stdout
    assert "A1.1" in table and "counter" in table and r["id"][:8] in table
    tree = cli("agent", "tree").stdout
    lines = tree.splitlines()
    i = next(i for i, ln in enumerate(lines) if "A1 (counter)" in ln)
    assert "A1.1 (counter) active on h" in lines[i + 1] and lines[i + 1].index("A1.1") > lines[i].index("A1")


def test_move(cli: Cli) -> None:
    a = cli.agents()
    to = next(h for h in ("h1", "h2", "h3") if h != a["A1"]["host"])
    out = cli("agent", "move", "A1", to).stdout
    assert f"A1 moved to {to}" in out
    a = cli.agents()
    assert a["A1"]["host"] == to and a["A1"]["state"] == "active"


def test_request(cli: Cli) -> None:
    stats = json.loads(cli("agent", "request", "A1", "stats").stdout)
    assert stats["name"] == "A1" and stats["sent"] > 0
    assert "unknown counter request" in cli.fails("agent", "request", "A1", "nonsense")


def test_kill_is_recovered(cli: Cli) -> None:
    before = cli.agents()["A1.1"]
    out = cli("agent", "kill", "A1.1").stdout
    assert f"killed A1.1 on {before['host']} (SIGKILL of pid {before['pid']})" in out
    assert "A1.1 recovered on h" in out
    after = cli.agents()["A1.1"]
    assert after["epoch"] > before["epoch"] and after["pid"] != before["pid"] and after["state"] == "active"


def test_alloc_pause_resume_run(cli: Cli) -> None:
    cli("alloc", "pause")
    st = json.loads(cli("alloc", "status", "--json").stdout)
    assert st["paused"] is True and {a["name"] for a in st["agents"]} == {"A1", "A1.1"}
    assert sum(d["agents"] for d in st["load"].values()) == 2
    assert "paused" in cli("alloc", "status").stdout
    cli("alloc", "resume")
    st2 = json.loads(cli("alloc", "status", "--json").stdout)
    assert st2["paused"] is False
    out = cli("alloc", "run").stdout
    m = [int(w) for w in out.split() if w.isdigit()]
    assert "allocation session" in out and "finished" in out and m and m[0] > st2["session"]


def test_events_merged_timeline(cli: Cli) -> None:
    out = cli("agent", "events").stdout
    text = " ".join(out.split())
    for s in ("A1 (counter) requested by the operator", "A1.1 (counter) requested by A1", "A1 (counter) spawned by h",
              "A1 (counter) freezing on h", "A1 (counter) thawed by h", "A1.1 (counter) crashed on h",
              ": killed by signal 9", "A1.1 (counter) recovered by h"):
        assert s in text, out
    assert text.count("A1 (counter) requested by the operator") == 1  # every member reports it; shown once
    js = [json.loads(ln) for ln in cli("agent", "events", "--json").stdout.splitlines()]
    times = [e["time"] for e in js]
    assert times == sorted(times) and len({e["host"] for e in js if e["event"] in ("active", "thawed")}) >= 2
    assert js[0]["clock"] == "00:00"
    follow = cli("agent", "events", "-f", "--count", "3", "--json").stdout.splitlines()
    assert len(follow) == 3


def test_operator_errors(cli: Cli) -> None:
    msg = cli.fails("agent", "spawn", "nope")
    assert "unknown agent type 'nope' (registered: " in msg and "counter, " in msg and "probe, " in msg
    assert "unknown agent 'A99' (agents: A1, A1.1)" in cli.fails("agent", "kill", "A99")
    assert "unknown agent 'A99'" in cli.fails("agent", "move", "A99", "h1")
    assert "unknown agent 'A99'" in cli.fails("agent", "remove", "A99")
    assert "unknown host 'h9'" in cli.fails("agent", "move", "A1", "h9")
    assert "--config is not JSON" in cli.fails("agent", "spawn", "counter", "--config", "{bad")
    assert "--recovery must be one of backup, none, restart" in cli.fails("agent", "spawn", "probe", "--recovery", "x")
    assert "unknown parent 'A77'" in cli.fails("agent", "spawn", "probe", "--parent", "A77")


def test_crashed_host(cli: Cli) -> None:
    a = cli.agents()
    victim = a["A1"]["host"]
    cli("host", "kill", victim, "--wait", "--timeout", "30")
    a = wait_agents(cli, lambda a: all(x["state"] == "active" and x["host"] != victim for x in a.values()), 30,
                    f"the agents of {victim} recovered elsewhere")
    assert a["A1"]["epoch"] >= 2
    assert f"{victim} is not a member of the group" in cli.fails("agent", "move", "A1", victim)
    cli("agent", "remove", "A1.1")
    wait_agents(cli, lambda a: set(a) == {"A1"}, 15, "A1.1 removed")
