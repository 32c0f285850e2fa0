"""`haactl agent events` from what the hosts persisted: the merged timeline must be true first.

Regression guard: an agent active on h10, `host kill h10`, `host restart h10`, then `agent events` printed "A1 (counter)
crashed on h1" with no line of A1 thawing on h10 — the restarted host's in-memory history had lost it, and the
crash every member reports was put on the wrong host. The timeline is read from every host's log (its data
dir; a container's log), and a crash the table recorded is shown where the agent ran, "reported by" the member
that logged it.

* unit: the parser and the merge on synthetic logs of that scenario; the compose backend with a fake docker
  SDK (a killed container that was not restarted, one that was restarted: the container log keeps both lives);
* a real local cluster of 3 hosts (≈25 s): an agent moved to a host (a thaw there), that host killed (the agent
  recovered elsewhere) and restarted; `agent events --json` shows the thaw on the killed host, the crash on that
  host reported by another, the recovery and the view changes; `-f` shows the same history once (the streams'
  replay of it is dropped); the host killed again and not restarted, and the cluster stopped: the same lines,
  from the logs alone.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from helpers import Cli, haactl, wait_value

from haa.cluster.events import Merger, TimelineEvent, log_event, timeline_events, view_events

REPO = Path(__file__).resolve().parents[1]
A1 = "7f3c9a10-0000-4000-8000-000000000001"


def rec(ts: float, host: str, event: str, **fields: Any) -> dict[str, Any]:
    return {"ts": ts, "host": host, "inc": 1, "level": "info", "event": event, "fields": fields}


def scenario() -> dict[str, list[dict[str, Any]]]:
    """The reported scenario as the three hosts' logs: A1 spawned on h1, moved to h10, h10 killed (its log just
    stops), the table's crash logged by both survivors, A1 recovered on h2, h10 restarted."""
    def ev(ts: float, host: str, kind: str, detail: str = "", name: str = "A1") -> dict[str, Any]:
        return rec(ts, host, "agent_" + kind, agent=A1, name=name, detail=detail)

    return {
        "h1": [ev(1.0, "h1", "created", "counter"), ev(1.1, "h1", "spawning"), ev(1.2, "h1", "active", "fresh state"),
               ev(5.0, "h1", "freezing", "to h10"), ev(5.2, "h1", "frozen"),
               rec(9.0, "h1", "view", view=4, removed=["h10"], added=[]),
               ev(9.01, "h1", "crashed"),
               rec(12.0, "h1", "view", view=5, removed=[], added=["h10"]),
               ev(20.0, "h1", "removed", name=A1[:8])],
        "h2": [ev(1.0, "h2", "created", "counter"), rec(9.0, "h2", "view", view=4, removed=["h10"], added=[]),
               ev(9.02, "h2", "crashed"), ev(9.1, "h2", "recovering"), ev(9.3, "h2", "recovered", "from backup"),
               ev(20.0, "h2", "removed", name=A1[:8])],
        "h10": [ev(1.0, "h10", "created", "counter"), ev(5.1, "h10", "thawing"),
                ev(5.3, "h10", "thawed", "3 queued messages"),
                rec(5.4, "h10", "agent_active", agent=A1, pid=4242),  # a supervisor record, not a timeline entry
                "not json: a traceback line"],  # type: ignore[list-item]
    }


def test_parser_and_merge_put_the_crash_where_the_agent_ran() -> None:
    logs = scenario()
    logs["h10"] = [r for r in logs["h10"] if isinstance(r, dict)]
    assert log_event("h10", logs["h10"][3]) is None  # the supervisor's record (pid) is not a timeline entry
    evs = timeline_events(logs)
    assert [e.time for e in evs] == sorted(e.time for e in evs)
    assert {e.name for e in evs} == {"A1"}  # the removal, logged under the id prefix, gets the display name
    kept = Merger().merge(evs + view_events(logs))
    got = [(e.time, e.event, e.host, e.reporter) for e in kept if e.agent]
    assert got == [
        (1.0, "created", "h1", ""), (1.1, "spawning", "h1", ""), (1.2, "active", "h1", ""),
        (5.0, "freezing", "h1", ""), (5.1, "thawing", "h10", ""), (5.2, "frozen", "h1", ""),
        (5.3, "thawed", "h10", ""),
        (9.01, "crashed", "h10", "h1"),  # once, where it ran, and who said so
        (9.1, "recovering", "h2", ""), (9.3, "recovered", "h2", ""),
        (20.0, "removed", "h1", ""),
    ]
    assert all(e.type == "counter" for e in kept if e.agent)
    views = [(e.text, e.detail, e.reporter) for e in kept if not e.agent]
    assert views == [("h10 removed", "view 4", "h1"), ("h10 joined", "view 5", "h1")]


def test_chaos_timeline_uses_the_same_parser_and_attribution(tmp_path: Path) -> None:
    from haa.lab.chaos.timeline import build

    (tmp_path / "hosts").mkdir()
    for host, recs in scenario().items():
        (tmp_path / "hosts" / f"{host}.jsonl").write_text(
            "".join((json.dumps(r) if isinstance(r, dict) else r) + "\n" for r in recs))
    (tmp_path / "faults.json").write_text(json.dumps({"t0": 4.0, "t_end": 30.0, "faults": [
        {"ts": 8.9, "action": "kill", "target": "host h10", "ok": True, "detail": "SIGKILL"}]}))
    got = [(round(e.t, 2), e.host, e.text) for e in build(tmp_path)]
    assert got == [
        (1.0, "h1", "A1 freezing on h1 (to h10)"), (1.1, "h10", "A1 thawing on h10"), (1.2, "h1", "A1 frozen on h1"),
        (1.3, "h10", "A1 thawed on h10 (3 queued messages)"),
        (4.9, "", "kill host h10: SIGKILL"),
        (5.0, "h1", "view 4: h10 removed"),
        (5.01, "h10", "A1 crashed on h10 (reported by h1)"),
        (5.1, "h2", "A1 recovering on h2"), (5.3, "h2", "A1 recovered on h2 (from backup)"),
        (8.0, "h1", "view 5: h10 joined"),
        (16.0, "h1", "A1 removed (reported by h1)"),
    ]


def test_merger_keeps_a_cause_over_the_table_crash_and_unknown_hosts_honest() -> None:
    m = Merger()
    evs = [TimelineEvent(1.0, "x", "A2", "crashed", "h1", ""),  # the table's, logged a moment before the cause
           TimelineEvent(1.01, "x", "A2", "crashed", "h3", "killed by signal 9"),
           TimelineEvent(9.0, "y", "A3", "crashed", "h2", "")]  # never seen running: nowhere to put it
    kept = m.merge(evs)
    assert [(e.detail, e.host, e.reporter) for e in kept] == [("killed by signal 9", "h3", ""), ("", "", "h2")]


# ---------------------------------------------------------------------------------------------- compose, fake SDK


class FakeContainer:
    def __init__(self, service: str, status: str, exit_code: int, lines: list[Any], port: int) -> None:
        self.labels = {"com.docker.compose.project": "haa", "com.docker.compose.service": service}
        self.status = status
        self.short_id = f"c0ffee{port}"
        self.attrs = {"State": {"Status": status, "ExitCode": exit_code},
                      "HostConfig": {"PortBindings": {"7000/tcp": [{"HostIp": "127.0.0.1", "HostPort": str(port)}]}}}
        self.data = "".join((json.dumps(x) if isinstance(x, dict) else x) + "\n" for x in lines).encode()

    def logs(self, stdout: bool = True, stderr: bool = True, **kw: Any) -> bytes:
        assert not kw.get("stream"), "the persisted timeline reads the whole log, it does not stream"
        return self.data


class FakeDocker:
    def __init__(self, containers: list[FakeContainer]) -> None:
        self._list = containers
        self.containers = self
        self.listed: list[dict[str, Any]] = []

    def list(self, all: bool = False, filters: dict[str, Any] | None = None) -> list[FakeContainer]:
        self.listed.append({"all": all, "filters": filters})
        return [c for c in self._list if all or c.status == "running"]


def test_compose_reads_the_container_logs_of_stopped_and_restarted_hosts(monkeypatch: pytest.MonkeyPatch) -> None:
    logs = scenario()
    fake = FakeDocker([
        FakeContainer("h1", "running", 0, logs["h1"], 17001),
        FakeContainer("h2", "running", 0, logs["h2"], 17002),
        FakeContainer("h10", "exited", 137, logs["h10"], 17010),  # killed, not restarted
    ])
    monkeypatch.setattr("haa.cluster.compose_backend.docker_client", lambda: fake)
    monkeypatch.delenv("HAA_COMPOSE_PROJECT", raising=False)
    args = ["agent", "events", "--compose", "--compose-file", str(REPO / "compose" / "compose.yaml")]
    r = haactl([*args, "--json"])
    assert r.exit_code == 0, r.output
    assert fake.listed and all(x["all"] for x in fake.listed)  # stopped containers too
    js = [json.loads(ln) for ln in r.stdout.splitlines()]
    lines = [e["text"] for e in js]
    assert "A1 (counter) thawed by h10 (3 queued messages)" in lines
    crash = [e for e in js if e["event"] == "crashed"]
    assert [(e["host"], e["reporter"], e["text"]) for e in crash] == [
        ("h10", "h1", "A1 (counter) crashed on h10 (reported by h1)")]
    assert lines.index("h10 removed") < lines.index("A1 (counter) crashed on h10 (reported by h1)") \
        < lines.index("A1 (counter) recovered by h2 (from backup)") < lines.index("h10 joined")
    assert js[0]["clock"] == "00:00" and [e["time"] for e in js] == sorted(e["time"] for e in js)
    # restarted: the same container, its log holds both lives (here: the same lines and a new start)
    fake._list[2] = FakeContainer("h10", "running", 0, [*logs["h10"], rec(13.0, "h10", "view", view=5,
                                                                          removed=[], added=["h10"])], 17010)
    r = haactl(args)
    assert r.exit_code == 0, r.output
    text = " ".join(r.stdout.split())
    assert "A1 (counter) thawing on h10" in text and "A1 (counter) crashed on h10 (reported by h1)" in text
    assert text.count("h10 joined") == 1  # view 5, logged by h1 and by h10 itself: once


def test_compose_unreadable_log_is_a_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    logs = scenario()
    broken = FakeContainer("h2", "exited", 137, [], 17002)

    def gone(**kw: Any) -> bytes:
        raise RuntimeError("404 Client Error: No such container")

    broken.logs = gone  # type: ignore[method-assign]
    fake = FakeDocker([FakeContainer("h1", "running", 0, logs["h1"], 17001), broken])
    monkeypatch.setattr("haa.cluster.compose_backend.docker_client", lambda: fake)
    r = haactl(["agent", "events", "--compose", "--compose-file", str(REPO / "compose" / "compose.yaml")])
    assert r.exit_code == 0, r.output
    assert "the log of h2 could not be read" in " ".join(r.output.split())
    assert "A1 (counter) spawned by h1" in " ".join(r.stdout.split())


# ---------------------------------------------------------------------------------------------- a real cluster


def wait_agent(cli: Cli, pred: Any, timeout: float, what: str) -> dict[str, Any]:
    """A1's row of `agent list` once `pred` holds for it (a command failing meanwhile is "not yet")."""
    return wait_value(lambda: cli.agents().get("A1"), lambda a: a and pred(a), timeout, what, interval=0.2,
                      ignore=(AssertionError,))


def check_story(evs: list[dict[str, Any]], victim: str, restarted: bool) -> None:
    """The thaw on the killed host, its crash there reported by a survivor, the recovery elsewhere."""
    a1 = [e for e in evs if e["name"] == "A1"]
    thaw = [e for e in a1 if e["event"] == "thawed" and e["host"] == victim]
    assert thaw, f"no thaw of A1 on {victim}:\n" + "\n".join(e["text"] for e in evs)
    crash = [e for e in a1 if e["event"] == "crashed" and e["time"] > thaw[0]["time"]]
    assert len(crash) == 1, "\n".join(e["text"] for e in evs)
    c = crash[0]
    assert c["host"] == victim and c["reporter"] not in ("", victim), c
    assert c["text"] == f"A1 (counter) crashed on {victim} (reported by {c['reporter']})"
    back = [e for e in a1 if e["event"] == "recovered" and e["time"] > c["time"]]
    assert back and back[0]["host"] != victim
    assert back[0]["text"].startswith(f"A1 (counter) recovered by {back[0]['host']}")
    texts = [e["text"] for e in evs]
    removed = [e for e in evs if e["text"] == f"{victim} removed"]
    assert removed and removed[0]["time"] <= c["time"] + 1.0, texts
    if restarted:
        assert any(e["text"] == f"{victim} joined" and e["time"] > c["time"] for e in evs), texts
    assert [e["time"] for e in evs] == sorted(e["time"] for e in evs)
    assert all(e["host"] for e in evs), [e for e in evs if not e["host"]]  # every line names a host


def test_killed_and_restarted_host_keeps_its_events(local_cluster: Cli) -> None:
    cli = local_cluster
    t0 = time.monotonic()
    cli("cluster", "up", "--hosts", "3")
    cli("agent", "spawn", "counter", "--config", json.dumps({"period": 0.2, "backup_every": 5}))
    a = wait_agent(cli, lambda a: a["state"] == "active", 30, "A1 active")
    victim = "h3" if a["host"] != "h3" else "h2"
    cli("agent", "move", "A1", victim)  # thawed on the victim
    assert cli.agents()["A1"]["host"] == victim
    cli("host", "kill", victim, "--wait")
    wait_agent(cli, lambda a: a["state"] == "active" and a["host"] != victim, 30, "A1 recovered elsewhere")
    cli("host", "restart", victim)  # a new incarnation: its in-memory timeline starts empty
    evs = cli.events()
    check_story(evs, victim, restarted=True)
    # -f: the same history first (the live streams replay what the logs hold: not shown twice), then follows
    follow = [json.loads(ln)
              for ln in cli.out("agent", "events", "-f", "--count", str(len(evs)), "--json").splitlines()]
    def lines(es: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
        return [(e["text"], e["host"], e["reporter"]) for e in es]

    assert lines(follow) == lines(evs)
    # killed again and left down: its data dir still has both lives
    cli("host", "kill", victim, "--wait")
    check_story(cli.events(), victim, restarted=True)
    # the whole cluster stopped: the logs remain (cluster.last.json), so does the timeline
    cli("cluster", "down", "--grace", "1")
    check_story(cli.events(), victim, restarted=True)
    print(f"cluster scenario: {time.monotonic() - t0:.1f} s")
