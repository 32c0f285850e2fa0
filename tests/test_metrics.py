"""Prometheus `/metrics` of haa-hostd and haa-sim (haa.metrics, docs/metrics.md), scraped over HTTP from real
processes: a local cluster of 2 hosts started by `haactl cluster up` (their URLs from `cluster status --json`),
and an haa-sim in step mode. Values are checked against what the cluster and the simulator say themselves:
DDB writes against the OAC histograms and the DDB size, agents by state against `haactl agent list`, a killed
host against the survivor's suspicions, simulated time and avatars against the SimControl calls made."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import Cli, local_cluster, wait_sync
from prometheus_client.parser import text_string_to_metric_families

from haa.cluster.procs import free_port, hostd_command
from haa.hostd.daemon import load_settings
from haa.sim.service import SimClient


def scrape(url: str) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    """{sample name: {sorted labels: value}} of one /metrics page (parsed by prometheus_client's parser)."""
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.status == 200
        assert r.headers["Content-Type"].startswith("text/plain")
        text = r.read().decode()
    out: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def one(m: dict[str, Any], name: str, **labels: str) -> float:
    return m[name][tuple(sorted(labels.items()))]


def by_label(m: dict[str, Any], name: str, label: str) -> dict[str, float]:
    return {dict(k)[label]: v for k, v in m.get(name, {}).items() if v}


@pytest.fixture(scope="module")
def cli(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cli]:
    with local_cluster(tmp_path_factory.mktemp("metrics"), "--local", "--hosts", "2", "--timeout", "60") as c:
        yield c


def urls(cli: Cli) -> dict[str, str]:
    st = cli.json("cluster", "status", "--sample", "0")
    return {h["name"]: h["metrics_url"] for h in st["hosts"]}


def test_every_host_serves_metrics_and_status_gives_their_urls(cli: Cli) -> None:
    u = urls(cli)
    assert set(u) == {"h1", "h2"} and len(set(u.values())) == 2
    for name, url in u.items():
        assert url.startswith("http://127.0.0.1:") and url.endswith("/metrics"), url
        m = scrape(url)
        assert one(m, "haa_member") == 1 and one(m, "haa_members") == 2
        assert one(m, "haa_leader") == (1 if name == "h1" else 0)
        assert one(m, "haa_suspicions") == 0
        assert one(m, "process_cpu_seconds_total") > 0 and one(m, "process_resident_memory_bytes") > 10e6
        other = "h2" if name == "h1" else "h1"
        assert one(m, "haa_link_connected", peer=other) == 1
        assert one(m, "haa_messages_sent_total", kind="heartbeat") > 0
    m = scrape(u["h1"])
    assert one(m, "haa_metrics_scrapes_total") >= 1 and 0 < one(m, "haa_metrics_scrape_seconds") < 0.5


def test_ddb_writes_show_in_the_oac_histograms_and_the_ddb_size(cli: Cli) -> None:
    u = urls(cli)
    before = {h: scrape(url) for h, url in u.items()}
    n = 6
    for i in range(n):
        cli("ddb", "put", f"metrics/k{i}", json.dumps({"i": i, "pad": "x" * 100}), "--host", "h1")

    def grown() -> dict[str, Any] | None:
        now = {h: scrape(url) for h, url in u.items()}
        ok = all(one(now[h], "haa_oac_decide_to_deliver_seconds_count")
                 >= one(before[h], "haa_oac_decide_to_deliver_seconds_count") + n
                 and one(now[h], "haa_ddb_objects") == one(before[h], "haa_ddb_objects") + n for h in u)
        return now if ok else None

    after = wait_sync(grown, 20, f"{n} more deliveries and objects on every host", interval=0.1)
    for h in u:
        m, b = after[h], before[h]
        # a histogram is consistent: +Inf bucket == count, buckets never decrease
        buckets = [v for k, v in sorted(m["haa_oac_decide_to_deliver_seconds_bucket"].items(),
                                        key=lambda kv: float(dict(kv[0])["le"]))]
        assert buckets == sorted(buckets) and buckets[-1] == one(m, "haa_oac_decide_to_deliver_seconds_count")
        assert one(m, "haa_oac_delivered_total") >= one(b, "haa_oac_delivered_total") + n
        assert one(m, "haa_ddb_bytes_by_prefix", prefix="metrics") >= n * 100
        assert one(m, "haa_ddb_seq") >= one(b, "haa_ddb_seq") + n
    # the proposals were made (by the sequencer: docs/oac.md) and decided: their latencies are in a histogram
    p2d = sum(one(after[h], "haa_oac_propose_to_decide_seconds_count")
              - one(before[h], "haa_oac_propose_to_decide_seconds_count") for h in u)
    assert p2d >= 1
    assert sum(one(after[h], "haa_oac_propose_to_decide_seconds_sum") for h in u) > 0


def test_agents_by_state_match_agent_list(cli: Cli) -> None:
    for _ in range(2):
        cli("agent", "spawn", "counter")
    cli("agent", "spawn", "counter", "--config", '{"spawn_peer": true}')  # A3 and its child A3.1 ping each other
    u = urls(cli)

    def agree() -> bool:
        rows = cli.json("agent", "list")["agents"]
        if len(rows) < 4 or any(r["state"] != "active" for r in rows):
            return False
        for h, url in u.items():
            m = scrape(url)
            listed = Counter(r["phases"][h] for r in rows if r["phases"].get(h))
            if by_label(m, "haa_agents", "state") != dict(listed):
                return False
            if by_label(m, "haa_agent_table", "status") != dict(Counter(r["status"] for r in rows)):
                return False
        return True

    wait_sync(agree, 30, "every agent active, and haa_agents and haa_agent_table to match `agent list`", interval=0.1)

    def four_processes() -> dict[str, Any] | None:
        """4 processes (an allocation session may still be moving one), each measured by its supervisor once."""
        ms = {h: scrape(url) for h, url in u.items()}
        n = sum(sum(by_label(ms[h], "haa_agent_processes", "state").values()) for h in u)
        rss = [v for h in u for v in ms[h].get("haa_agent_rss_bytes", {}).values()]
        return ms if n == 4 and len(rss) == 4 and min(rss) > 1e6 else None

    m = wait_sync(four_processes, 30, "4 agent processes, their memory measured", interval=0.1)
    assert sum(one(m[h], "haa_agents_spawned_total") for h in u) >= 4
    assert all(one(m[h], "haa_allocation_sessions_total") >= 1 for h in u)
    assert sum(by_label(m[h], "haa_agent_events_total", "event").get("active", 0) for h in u) >= 4

    # messages and bytes by peer agent: A3 -> A3.1, wherever A3 runs, and no more than `agent list` counts later
    def pinged() -> tuple[float, float] | None:
        for url in u.values():
            mm = scrape(url)
            n = mm.get("haa_agent_messages_sent_total", {}).get((("agent", "A3"), ("peer", "A3.1")), 0)
            b = mm.get("haa_agent_bytes_sent_total", {}).get((("agent", "A3"), ("peer", "A3.1")), 0)
            if n >= 3:
                return n, b
        return None

    n, b = wait_sync(pinged, 30, "A3's pings to A3.1 in haa_agent_messages_sent_total", interval=0.1)
    assert b >= n * 8  # every ping carries at least its header
    listed = {r["name"]: r for r in cli.json("agent", "list")["agents"]}
    assert listed["A3"]["msgs_out"] >= n


def test_transfers_and_recoveries_are_counted(cli: Cli) -> None:
    u = urls(cli)

    def events() -> dict[str, float]:
        out: Counter[str] = Counter()
        for url in u.values():
            out.update(by_label(scrape(url), "haa_agent_events_total", "event"))
        return dict(out)

    before = events()
    rows = {r["name"]: r for r in cli.json("agent", "list")["agents"]}
    dest = "h2" if rows["A1"]["host"] == "h1" else "h1"
    cli("agent", "move", "A1", dest)  # a transfer: frozen here, thawed there (Alg. 6)
    cli("agent", "kill", "A2")  # an agent failure, recovered from its backup (Alg. 8)
    after = wait_sync(lambda: (lambda e: e if e.get("thawed", 0) > before.get("thawed", 0)
                               and e.get("recovered", 0) > before.get("recovered", 0) else None)(events()),
                      20, "a thawed and a recovered event", interval=0.1)
    assert after.get("crashed", 0) > before.get("crashed", 0)
    assert after.get("freezing", 0) > before.get("freezing", 0)


def test_a_killed_host_is_suspected_by_the_survivor(cli: Cli) -> None:
    u = urls(cli)
    cli("host", "kill", "h2")
    # the survivor's failure detector suspects h2 (2 core hosts: no quorum to remove it, it stays suspected)
    m = wait_sync(lambda: (lambda m: m if one(m, "haa_suspected", peer="h2") == 1 else None)(scrape(u["h1"])),
                  20, "h1 to suspect h2", interval=0.1)
    assert one(m, "haa_suspicions") == 1 and one(m, "haa_link_connected", peer="h2") == 0
    with pytest.raises(OSError):
        scrape(u["h2"])


def test_bad_metrics_port_is_one_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tok = tmp_path / "token"
    tok.write_text("t" * 32)
    base = ["--name", "h1", "--listen", "127.0.0.1:0", "--core", "h1=127.0.0.1:1", "--token-file", str(tok)]
    with pytest.raises(SystemExit) as e:
        load_settings([*base, "--metrics-port", "70000"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("haa-hostd: error: --metrics-port:"), err
    with socket.socket() as s:  # a taken port: exit 1 and one line, before the host joins anything
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = subprocess.run([*hostd_command(), *base, "--data-dir", str(tmp_path / "d"), "--metrics-port", str(port)],
                           capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines == [f"haa-hostd: error: --metrics-port: cannot listen on 127.0.0.1:{port}: Address already in use"]


def test_sim_metrics(tmp_path: Path) -> None:
    tok = tmp_path / "token"
    tok.write_text("s" * 32)
    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "haa.sim.service", "--listen", "127.0.0.1:0", "--step", "--seed", "2",
                          "--token-file", str(tok), "--metrics-port", str(port)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert p.stderr is not None
        first = json.loads(p.stderr.readline())
        assert first["event"] == "listening" and first["metrics"] == f"http://127.0.0.1:{port}/metrics", first
        url = first["metrics"]
        m0 = scrape(url)
        assert one(m0, "haa_sim_time_seconds") == 0 and not m0.get("haa_sim_avatars")
        with SimClient(first["address"], token="s" * 32, timeout=10, caller="A9") as c:
            a = c.register("seeker").avatar.avatar_id
            c.register("sweeper")
            c.step(1.5)
            c.crash(a)
            c.poses()  # a ground-truth call, counted by caller
            odo = c.odometry(c.register("seeker").avatar.avatar_id, period=0.1)
            next(iter(c.events(replay=True)), None)
            m = scrape(url)
            assert one(m, "haa_sim_subscribers", stream="odometry") == 1
            odo.cancel()
        with SimClient(first["address"], token="wrong", timeout=10) as bad, contextlib.suppress(Exception):
            bad.info()
        m = scrape(url)
        assert one(m, "haa_sim_time_seconds") == pytest.approx(1.5)
        assert one(m, "haa_sim_avatars", status="crashed", type="seeker") == 1
        assert one(m, "haa_sim_avatars", status="active", type="sweeper") == 1
        assert one(m, "haa_sim_avatars", status="active", type="seeker") == 1
        assert one(m, "haa_sim_truth_calls_total", caller="A9", method="Poses") == 1
        assert one(m, "haa_sim_rejected_total", reason="unauthenticated") == 1
        assert one(m, "haa_sim_speed_target_ratio") == 0  # step mode
        assert one(m, "process_cpu_seconds_total") > 0
    finally:
        p.terminate()
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def test_compose_backend_reports_the_published_metrics_port() -> None:
    from types import SimpleNamespace

    from haa.cluster.compose_backend import METRICS_PORT, ComposeBackend

    def container(bindings: dict[str, Any]) -> Any:
        return SimpleNamespace(attrs={"HostConfig": {"PortBindings": bindings}})

    c = container({"7000/tcp": [{"HostIp": "127.0.0.1", "HostPort": "17003"}],
                   METRICS_PORT: [{"HostIp": "127.0.0.1", "HostPort": "19003"}]})
    assert ComposeBackend._metrics_url(c) == "http://127.0.0.1:19003/metrics"
    assert ComposeBackend._metrics_url(container({METRICS_PORT: [{"HostIp": "0.0.0.0", "HostPort": "19100"}]})) \
        == "http://127.0.0.1:19100/metrics"
    assert ComposeBackend._metrics_url(container({"7000/tcp": [{"HostPort": "17001"}]})) == ""
    # compose/compose.yaml publishes 9400 of every service on 19000 + N (hosts) and 19100 (sim)
    import yaml

    spec = yaml.safe_load((Path(__file__).parents[1] / "compose" / "compose.yaml").read_text())
    assert spec["x-hostd"]["environment"]["HAA_METRICS_PORT"] == "9400"
    for name, svc in spec["services"].items():
        want = 19100 if name == "sim" else 19000 + int(name[1:])
        assert f"127.0.0.1:{want}:9400" in svc["ports"], (name, svc["ports"])


def test_collectors_run_on_the_daemons_loop_and_a_hung_loop_fails_the_scrape() -> None:
    """`OnLoop` runs the collectors on the event loop's thread (they read what only that thread changes); a loop
    that does not come round within the timeout fails the scrape instead of hanging it."""
    import asyncio
    import concurrent.futures
    import threading

    from prometheus_client.core import GaugeMetricFamily

    from haa.metrics.http import OnLoop

    loop = asyncio.new_event_loop()
    t = threading.Thread(target=loop.run_forever, daemon=True)
    t.start()
    seen: list[int] = []

    class Probe:
        def collect(self) -> Iterator[Any]:
            seen.append(threading.get_ident())
            yield GaugeMetricFamily("probe", "a probe", value=1)

    try:
        c = OnLoop(loop, [Probe()], timeout=2.0)
        names = [m.name for m in c.collect()]
        assert names == ["probe", "haa_metrics_scrape_seconds", "haa_metrics_scrapes"] and seen == [t.ident]
        loop.call_soon_threadsafe(time.sleep, 1.0)  # the loop is busy for a second
        with pytest.raises(concurrent.futures.TimeoutError):
            list(OnLoop(loop, [Probe()], timeout=0.2).collect())
    finally:
        loop.call_soon_threadsafe(loop.stop)
        t.join(5)
        loop.close()


def test_a_missions_haa_sim_serves_metrics(tmp_path: Path) -> None:
    """The haa-sim a mission starts (haactl mission run|start) serves /metrics too, and says where."""
    from haa.mission import load_mission
    from haa.mission.runner import SimHandle, start_sim

    m = load_mission(Path(__file__).resolve().parent / "missions" / "ci.yaml")
    h = start_sim(m, 1.0, tmp_path)
    try:
        assert h.metrics_url.startswith("http://127.0.0.1:") and h.metrics_url.endswith("/metrics"), h
        got = scrape(h.metrics_url)
        assert "haa_sim_time_seconds" in got
        assert SimHandle.from_json(json.loads(json.dumps(h.to_json()))).metrics_url == h.metrics_url
    finally:
        h.stop()
