"""`haactl demo` (make demo): end to end on real processes (the --quick scenario), and its duplicate-agent check.

The end-to-end test runs the demo as a subprocess and reads its transcript: every kind of step happened
(join, move, graceful leave, agent kill, host crash) and the final line says nothing was lost, reordered or
run twice. The unit tests feed the timeline replay synthetic events, so that the duplicate check is shown
to find an agent active on two hosts at once (and not to flag a correct transfer or recovery).
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from haa.cluster.events import TimelineEvent
from haa.cluster.feed import EventFeed, operator_event
from haa.lab.experiments.demo import Demo
from haa.pb import control_pb2 as cpb
from haactl.agentcli import event_line

BIN = Path(sys.executable).parent / "haactl"


def test_demo_quick_loses_nothing(tmp_path: Path) -> None:
    r = subprocess.run(
        [str(BIN), "demo", "--quick", "--data-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    out = r.stdout
    assert r.returncode == 0, out + r.stderr
    assert "messages lost: 0, order violations: 0, duplicate agents: 0" in out
    lines = out.splitlines()
    timeline = [ln for ln in lines if re.match(r"^\d\d:\d\d ", ln)]
    # the transcript: hosts joining and removed, transfers, the killed agent and the crashed host's agents
    for pattern in (
        r"\d\d:\d\d h1 joined",
        r"\d\d:\d\d h4 joined",
        r"\d\d:\d\d A\d+ \(counter\) requested by the operator",
        r"\d\d:\d\d A\d+\.1 \(counter\) requested by A\d+",
        r"\d\d:\d\d A[\d.]+ \(counter\) spawned by h\d",
        r"\d\d:\d\d A[\d.]+ \(counter\) freezing on h\d",
        r"\d\d:\d\d A[\d.]+ \(counter\) thawed by h\d",
        r"\d\d:\d\d A[\d.]+ \(counter\) crashed on h\d: killed by signal 9",
        r"\d\d:\d\d A[\d.]+ \(counter\) recovered by h\d \(from backup\)",
        r"\d\d:\d\d h\d removed",
    ):
        assert any(re.match(pattern, ln) for ln in timeline), f"no line like {pattern!r} in\n{out}"
    retired = re.search(r"▶ (h\d) retires: SIGTERM", out)
    crashed = re.search(r"▶ (h\d) crashes: SIGKILL", out)
    assert retired and crashed and retired.group(1) != crashed.group(1), out
    for host in (retired.group(1), crashed.group(1)):
        assert re.search(rf"\d\d:\d\d {host} removed", out), out
    # the agents of the crashed host: shown crashed there, as a survivor reported it, and recovered by a survivor
    assert any(re.match(rf"\d\d:\d\d A[\d.]+ \(counter\) crashed on {crashed.group(1)} \(reported by h\d\)$", ln)
               for ln in timeline), out
    assert re.search(r"lost to recovery \(by design\): \d+", out)
    assert (tmp_path / "h4" / "h4.jsonl").exists()


def ev(t: float, name: str, event: str, host: str, detail: str = "") -> TimelineEvent:
    return TimelineEvent(t, "id-" + name, name, event, host, detail)


def replay(events: list[TimelineEvent], gone: dict[str, float] | None = None) -> list[tuple[float, str, str, str]]:
    d = Demo.__new__(Demo)  # only the timeline replay: no cluster
    d.checks = type("C", (), {"events": events})()  # type: ignore[assignment]
    d.host_gone = gone or {}
    return d.overlaps()


def test_overlap_check_accepts_transfers_and_recoveries() -> None:
    events = [
        ev(1.0, "A1", "active", "h1"),
        ev(2.0, "A1", "freezing", "h1", "to h2"),
        ev(2.1, "A1", "frozen", "h1"),
        ev(2.2, "A1", "thawed", "h2"),
        ev(3.0, "A1", "crashed", "h2", "killed by signal 9"),
        ev(3.1, "A1", "crashed", "h1"),
        ev(3.2, "A1", "recovered", "h3", "from backup"),
        ev(4.0, "A2", "active", "h3"),
        ev(5.5, "A2", "crashed", "h1"),  # h3 crashed at 5.0: the survivors mark A2 crashed
        ev(5.6, "A2", "recovered", "h1", "from backup"),
    ]
    assert replay(events, {"h3": 5.0}) == []


def test_overlap_check_finds_an_agent_active_twice() -> None:
    events = [
        ev(1.0, "A1", "active", "h1"),
        ev(2.0, "A1", "thawed", "h2"),  # h1 never froze it
        ev(3.0, "A2", "active", "h3"),
        ev(4.0, "A2", "recovered", "h1"),  # no crash, h3 still up
    ]
    dups = replay(events)
    assert [(d[1], d[2], d[3]) for d in dups] == [("A1", "h1", "h2"), ("A2", "h3", "h1")]


def test_operator_lines_are_ordered_with_late_host_events() -> None:
    """An operator line said now is printed after a host event stamped earlier that reaches us later (the
    demo printed "▶ quiet for 8 s" before events a second older), and before events stamped after it."""
    feed = EventFeed(backend=None, delay=0.6)  # type: ignore[arg-type]  # no hosts: events are fed by hand
    feed.last_connect = time.monotonic() + 60  # poll() must not look for hosts
    now = time.time()
    feed.add(operator_event(now - 1.0, "h4 retires: SIGTERM"))
    assert [e.text for e in feed.poll(0.0)] == ["h4 retires: SIGTERM"]  # nothing else is known yet
    feed.add(operator_event(now - 0.9, "quiet for 8 s"))
    for t, what in ((now - 0.95, "freezing"), (now - 0.8, "thawed"), (now + 5.0, "frozen")):
        feed.q.put(("h4", cpb.AgentEvent(time=t, agent="id-A1", name="A1", event=what, host="h4")))
    shown = feed.poll(0.0)
    assert [e.event for e in shown] == ["freezing", "operator", "thawed"]  # "frozen" is not 0.6 s old yet
    assert [e.event for e in feed.poll(0.0, flush=True)] == ["frozen"]
    line = event_line(shown[1], now - 61.0)
    assert line.startswith("[dim]01:00[/]") and "▶ quiet for 8 s" in line
    assert event_line(operator_event(now, "h4 exited 0.4 s after SIGTERM", "note"), now) == (
        "      [dim]h4 exited 0.4 s after SIGTERM[/]")
