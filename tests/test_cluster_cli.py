"""`haactl cluster|host|ddb|logs` on a local cluster of 4 real haa-hostd processes (membership mode).

The tests share one cluster and run in order: up, status, DDB put/get/ls/watch, kill (removed from the
view) and restart (rejoins with an equal replica), pause/resume, add, graceful leave, logs, operator
errors, down. Commands run in-process through typer's CliRunner (`watch` in a subprocess, since it
streams while other commands write).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
from helpers import Cli, local_cluster, wait_sync, wait_value

from haa.cluster.local_backend import _proc_state, _reap

HAACTL = Path(sys.executable).parent / "haactl"


def wait_status(cli: Cli, pred: Any, timeout: float, what: str) -> dict[str, Any]:
    """`cluster status` once `pred` holds for it."""
    return wait_value(cli.status, pred, timeout, what, show=lambda st: json.dumps(st, indent=1))


def converged(st: dict[str, Any], members: set[str]) -> bool:
    rows = [h for h in st["hosts"] if h["state"] == "alive"]
    return (
        set(st["members"]) == members
        and all(h.get("member") and h["members"] == st["members"] for h in rows)
        and len({h["ddb_hash"] for h in rows}) == 1
    )


def test_a_host_that_looks_gone_while_its_threads_exit_is_reaped() -> None:
    """A zombie thread-group leader whose other threads still run looks gone (`_proc_state`) but cannot be
    reaped yet; a single reap attempt leaves a zombie of ours (CI: "host process ... still there after
    cluster down"). `_reap` waits for it."""
    code = ("import ctypes, os, threading, time\n"
            "threading.Thread(target=lambda: (time.sleep(0.5), os._exit(0))).start()\n"
            "ctypes.CDLL(None).pthread_exit(None)\n")  # the main thread ends first, as a leader can
    p = subprocess.Popen([sys.executable, "-c", code])
    wait_sync(lambda: psutil.Process(p.pid).status() == psutil.STATUS_ZOMBIE, 10, "the leader to be a zombie",
              interval=0.01)
    assert _proc_state(p.pid, None) is None  # looks gone ...
    os.kill(p.pid, 0)  # ... but is still there: its one reap attempt came too early
    assert _reap(p.pid, 10)
    with pytest.raises(ProcessLookupError):
        os.kill(p.pid, 0)
    p.returncode = 0  # reaped by us: keep Popen from waiting for it


@pytest.fixture(scope="module")
def cli(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cli]:
    with local_cluster(tmp_path_factory.mktemp("cluster")) as c:  # started by the first test
        yield c


def test_up_forms_the_group(cli: Cli) -> None:
    r = cli("cluster", "up", "--local", "--hosts", "4", "--timeout", "60")
    assert "group formed: 4 members, leader h1" in r.output
    st = cli.json("cluster", "status")
    assert set(st["members"]) == {"h1", "h2", "h3", "h4"}
    assert st["leader"] == st["members"][0] == "h1"
    assert st["view"] >= 1 and st["agreed"] and st["ddb_hashes_equal"]
    rows = {h["name"]: h for h in st["hosts"]}
    assert [rows[n]["core"] for n in ("h1", "h2", "h3", "h4")] == [True, True, True, False]
    for name, h in rows.items():
        assert h["state"] == "alive" and h["member"] and h["view"] == st["view"]
        assert h["rank"] == st["members"].index(name)
        assert h["suspicions"] == [] and h["rss_bytes"] > 0 and 0 <= h["cpu_percent"] <= 100 * os.cpu_count()
    assert sum(h["cpu_percent"] for h in rows.values()) > 0  # measured over the 1 s sample: heartbeats cost CPU
    table = cli("cluster", "status", "--sample", "0").output
    assert "4 members, leader h1" in table and "members (rank order): " + " ".join(st["members"]) in table


def test_ddb_put_get_ls(cli: Cli) -> None:
    assert "version" in cli("ddb", "put", "cfg/a", '{"x": [1, 2]}').output
    cli("ddb", "put", "cfg/b", "hello world", "--type", "blob", "--host", "h3")
    cli("ddb", "put", "cfg/n", "41", "--type", "counter", "--host", "h4")
    cli("ddb", "put", "cfg/l", '["p", "q"]', "--type", "list")
    got = cli.json("ddb", "get", "cfg/a", "cfg/b", "cfg/n", "cfg/l", "--host", "h2")
    values = {o["key"]: (o["type"], o["value"]) for o in got["objects"]}
    assert values == {
        "cfg/a": ("json", {"x": [1, 2]}),
        "cfg/b": ("blob", "hello world"),
        "cfg/n": ("counter", 41),
        "cfg/l": ("list", ["p", "q"]),
    }
    ls = cli.json("ddb", "ls", "cfg/", "--host", "h4")
    assert [o["key"] for o in ls["objects"]] == ["cfg/a", "cfg/b", "cfg/l", "cfg/n"]
    assert "value" not in ls["objects"][0]
    assert "cfg/b" in cli("ddb", "ls", "-v").output
    # operator mistakes: one clear line, exit code 1
    r = cli("ddb", "put", "cfg/x", "not json", ok=False)
    assert r.exit_code == 1 and "not JSON" in r.output and "--type blob" in r.output
    r = cli("ddb", "get", "cfg/a", "cfg/missing", ok=False)
    assert r.exit_code == 1 and "not found on" in r.output and "cfg/missing" in r.output
    wait_status(cli, lambda st: converged(st, {"h1", "h2", "h3", "h4"}), 10, "equal replicas")


def test_watch_streams_snapshot_then_writes(cli: Cli) -> None:
    proc = subprocess.Popen(
        [str(HAACTL), "ddb", "watch", "w/", "--json", "--count", "3", "--host", "h2", "--root", str(cli.root)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first = json.loads(proc.stdout.readline())
        assert first["event"] == "snapshot" and first["objects"] == 0
        cli("ddb", "put", "w/1", "1", "--host", "h1")
        cli("ddb", "put", "other", "0")  # not under the prefix
        cli("ddb", "put", "w/2", "2", "--type", "counter", "--host", "h4")
        out, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    events = [json.loads(line) for line in out.splitlines()]
    assert [(e["event"], e["op"], e["key"], e["value"]) for e in events] == [
        ("write", "put", "w/1", 1),
        ("write", "put", "w/2", 2),
    ], err
    assert proc.returncode == 0


def test_kill_removes_the_host_and_restart_rejoins_with_an_equal_replica(cli: Cli) -> None:
    r = cli("host", "kill", "h2", "--wait", "--timeout", "20")
    assert "h2 removed from every view" in r.output
    rows = cli.hosts()
    assert rows["h2"]["state"] == "killed"
    st = cli.status()
    assert "h2" not in st["members"] and all("h2" not in h["members"] for h in st["hosts"] if h.get("member"))
    for i in range(5):  # written while h2 is down: it must get them from its sponsor
        cli("ddb", "put", f"late/{i}", str(i))
    r = cli("host", "restart", "h2", "--timeout", "30")
    assert "h2 is a member in every view" in r.output
    st = wait_status(cli, lambda st: converged(st, {"h1", "h2", "h3", "h4"}), 20, "h2 back with an equal replica")
    rows = {h["name"]: h for h in st["hosts"]}
    assert rows["h2"]["ddb_size"] == rows["h1"]["ddb_size"] >= 10
    got = cli.json("ddb", "get", "late/4", "--host", "h2")
    assert got["objects"][0]["value"] == 4
    r = cli("host", "restart", "h2", ok=False)
    assert r.exit_code == 1 and "h2 is alive" in r.output


def test_pause_and_resume(cli: Cli) -> None:
    r = cli("host", "pause", "h4", "--wait", "--timeout", "20")
    assert "h4 removed from every view" in r.output
    assert cli.hosts()["h4"]["state"] == "paused"
    r = cli("ddb", "get", "cfg/a", "--host", "h4", ok=False)
    assert r.exit_code == 1 and "h4 is paused" in r.output and "haactl host resume h4" in r.output
    cli("ddb", "put", "while-paused", "true")
    cli("host", "resume", "h4", "--wait", "--timeout", "30")
    wait_status(cli, lambda st: converged(st, {"h1", "h2", "h3", "h4"}), 20, "h4 back")


def test_add_a_host(cli: Cli) -> None:
    r = cli("host", "add", "--timeout", "30")
    assert "started h5" in r.output and "h5 is a member in every view" in r.output
    st = wait_status(cli, lambda st: converged(st, {"h1", "h2", "h3", "h4", "h5"}), 20, "h5 in")
    assert not {h["name"]: h for h in st["hosts"]}["h5"]["core"]
    r = cli("host", "add", "h5", ok=False)
    assert r.exit_code == 1 and "already exists" in r.output


def test_leave(cli: Cli) -> None:
    r = cli("host", "leave", "h5", "--timeout", "20")
    assert "h5 left (Leave RPC)" in r.output
    assert cli.hosts()["h5"]["state"] == "left"
    st = wait_status(cli, lambda st: converged(st, {"h1", "h2", "h3", "h4"}), 10, "h5 out")
    assert "h5" not in st["members"]
    r = cli("ddb", "ls", "--host", "h5", ok=False)
    assert r.exit_code == 1 and "host h5 has left" in r.output
    r = cli("host", "leave", "h3", "--signal", "--timeout", "20")  # SIGTERM = graceful leave too
    assert "h3 left (SIGTERM)" in r.output
    wait_status(cli, lambda st: converged(st, {"h1", "h2", "h4"}), 10, "h3 out")


def test_logs(cli: Cli) -> None:
    r = cli("logs", "--json", "--tail", "50")
    lines = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(lines) == 50
    ts = [x["ts"] for x in lines]
    assert ts == sorted(ts)  # merged by time
    assert {x["host"] for x in lines} <= {"h1", "h2", "h3", "h4", "h5"}
    views = [json.loads(line) for line in cli("logs", "--json", "-H", "h1", "-e", "view").stdout.splitlines()]
    assert views and all(v["host"] == "h1" and v["event"] == "view" for v in views)
    text = cli("logs", "--host", "h5", "--tail", "3").output
    assert "h5" in text and "shutdown" in text


def test_operator_errors(cli: Cli, tmp_path: Path) -> None:
    for args in (["host", "kill", "h9"], ["ddb", "get", "x", "--host", "h9"], ["logs", "--host", "h9"]):
        r = cli(*args, ok=False)
        assert r.exit_code == 1 and "unknown host 'h9'" in r.output, r.output
    r = cli("host", "kill", "h3", ok=False)  # it left
    assert r.exit_code == 1 and "host h3 has left" in r.output
    token = cli.root / "token"
    good = token.read_text()
    token.write_text("not-the-token\n")
    try:
        r = cli("cluster", "status", ok=False)
        assert r.exit_code == 1 and "rejected the cluster token" in r.output
    finally:
        token.write_text(good)
    other = Cli(tmp_path / "none")
    r = other("cluster", "status", ok=False)
    assert r.exit_code == 1 and "no cluster running" in r.output
    bad = tmp_path / "bad.yaml"
    bad.write_text("qos_td: [1,\n  x: 2\n")
    r = other("cluster", "up", "--hosts", "2", "--config", str(bad), ok=False)
    assert r.exit_code == 1 and "broken YAML" in r.output and "line 3" in r.output
    assert not (other.root / "cluster.json").exists()
    bad.write_text("qos_td: -1\n")  # valid YAML, invalid setting: the daemon names it, nothing stays up
    r = other("cluster", "up", "--hosts", "2", "--config", str(bad), ok=False)
    assert r.exit_code == 1 and "exited at start with code 2" in r.output and "qos-td" in r.output.replace("_", "-")
    assert "no cluster running" in other("cluster", "status", ok=False).output


def test_down(cli: Cli) -> None:
    pids = [h["pid"] for h in cli.status()["hosts"] if h["state"] == "alive"]
    r = cli("cluster", "down")
    assert "stopped 3 hosts" in r.output
    assert "SIGKILL" not in r.output, r.output  # every host left gracefully
    for pid in pids:  # gone (and reaped: `cluster up` ran in this process, so they were our children)
        wait_sync(lambda pid=pid: not psutil.pid_exists(pid), 3, f"host process {pid} to go after cluster down",
                  interval=0.05)
    r = cli("cluster", "status", ok=False)
    assert "no cluster running" in r.output
    # the logs outlive the cluster; "shutdown" is not always among the last lines: a stopping host still
    # logs its links going down and the exclusions its peers send it, one line per peer each
    assert "shutdown" in cli("logs", "--host", "h1", "--tail", "30").output
    cli("cluster", "down", "--purge")
    assert not (cli.root / "h1").exists() and not (cli.root / "token").exists()
