"""Stats bundles and reports on a real local cluster: 4 haa-hostd processes sampling every
0.5 s, two counter pairs; the host running A1 is killed and its agents are recovered elsewhere; bundles are
collected while the cluster runs (the dead host's from its data dir) and again after `cluster down`; a report
and a comparison are rendered and their PNGs are real images. Bad input gets one clear error line."""

from __future__ import annotations

import json
import re
import tarfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from haa.cluster.agents import wait_rows
from haa.cluster.backend import wait_until
from haa.cluster.local_backend import LocalBackend
from haa.lab.stats.bundle import BundleError, load_bundles, read_bundle
from haa.lab.stats.collect import collect_bundles
from haa.lab.stats.report import build_report
from haactl.main import app

PNG = b"\x89PNG\r\n\x1a\n"


def spawn(backend: LocalBackend, period: float = 0.1) -> str:
    cfg = json.dumps({"spawn_peer": True, "period": period}).encode()
    rep = backend.call(backend.pick_host(), lambda c: c.agent_spawn("counter", cfg, timeout=30.0), "AgentSpawn",
                       timeout=35.0)
    assert rep.ok, rep.reason
    return str(rep.id)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A cluster that ran counters, lost the host of A1 and recovered; bundles collected live and after down."""
    d = tmp_path_factory.mktemp("stats")
    backend = LocalBackend(d / "cluster")
    names = backend.up(4, 3, hostd_args=["--stats-period", "0.5"])
    info: dict = {"dir": d}
    try:
        backend.check_started()
        wait_until(lambda: backend.formation(names), 90, what="4 hosts to form a group")
        ids = [spawn(backend), spawn(backend)]
        rows = wait_rows(backend, lambda rs: rs if len(rs) == 4 and all(r.state == "active" for r in rs) else None,
                         60, "4 active counters")
        victim = next(r.host for r in rows if r.id == ids[0])
        on_victim = {r.id for r in rows if r.host == victim}
        info.update(victim=victim, on_victim=on_victim, ids=ids)
        wait_until(lambda: _sampled(d / "cluster" / victim, 4), 20, what="the victim's samples")
        backend.kill(victim)
        wait_rows(backend, lambda rs: len(rs) == 4 and all(r.state == "active" and r.host != victim for r in rs),
                  60, f"the agents of {victim} recovered elsewhere")
        info["live"] = collect_bundles(backend, d / "live")
    finally:
        backend.down(grace=3.0)
    info["after"] = collect_bundles(LocalBackend(d / "cluster"), d / "after")  # `cluster down` was done
    return info


def _sampled(data_dir: Path, n: int):
    from haa.cluster.backend import Formation

    p = data_dir / "stats.jsonl"
    k = p.read_text().count("\n") if p.exists() else 0
    return Formation(k > n, note=f"{k} samples")


def test_every_host_has_a_bundle_also_the_killed_one(run):
    res = run["live"]
    assert sorted(p.name for p in res.bundles) == ["h1.tar.gz", "h2.tar.gz", "h3.tar.gz", "h4.tar.gz"]
    assert res.errors == {}
    bundles = {b.host: b for b in load_bundles(run["dir"] / "live")}
    dead = bundles[run["victim"]]
    assert dead.manifest["state"] == "killed"
    for name in ("manifest.json", "log.jsonl", "stats.jsonl", "config.json", "views.jsonl", "events.jsonl",
                 "latency.json"):
        assert name in dead.files, name
    with tarfile.open(dead.path) as tar:
        assert all(m.name.startswith(f"{dead.host}/") for m in tar)


def test_bundle_contents_name_their_host(run):
    for b in load_bundles(run["dir"] / "live"):
        samples = b.samples
        assert len(samples) >= 3, b.host
        assert all(s["host"] == b.host for s in samples)
        # every sample belongs to a life of the host: none before its incarnation was made (the first sample,
        # taken at start, once was: a restarted container's bundle then showed three lives, one of them 0)
        assert all(s["inc"] > 0 for s in samples), [s["inc"] for s in samples]
        assert all(r["host"] == b.host for r in b.log)
        assert all(e["host"] == b.host for e in b.events)
        assert all(v["host"] == b.host for v in b.views) and b.views
        assert any("cpu" in s and "rss" in s and "ddb" in s for s in samples)
        cfg = b.json("config.json")
        assert cfg["settings"]["name"] == b.host and "token" not in json.dumps(cfg)


def test_the_killed_host_kept_its_events_and_samples(run):
    dead = read_bundle(run["dir"] / "live" / f"{run['victim']}.tar.gz")
    evs = dead.events
    ran = {e["agent"] for e in evs if e["event"] == "active"}
    assert run["on_victim"] <= ran, (run["on_victim"], evs)
    crashed = {e["agent"] for e in evs if e["event"] == "crashed"}
    assert run["on_victim"] <= crashed  # the group's crash record, on the host that ran them
    assert all(e.get("reporter") and e["reporter"] != dead.host for e in evs if e["event"] == "crashed")
    assert any(s.get("agents") for s in dead.samples)  # it sampled its agents while it ran
    pairs = [k for s in dead.samples for k in s.get("pairs", {})]
    assert any(k.startswith(run["ids"][0]) or k.endswith(run["ids"][0]) for k in pairs)


def test_summary_counts_and_latencies(run):
    s = json.loads((run["dir"] / "live" / "summary.json").read_text())
    assert set(s["hosts"]) == {"h1", "h2", "h3", "h4"}
    c = s["counts"]
    assert c["crashes"] >= len(run["on_victim"]) and c["recoveries"] >= len(run["on_victim"])
    assert c["host_removals"] >= 1 and c["spawns"] >= 4
    assert s["latency"]["spawn"]["n"] >= 4 and s["latency"]["recovery"]["n"] >= 1
    assert s["latency"]["oac_decide_deliver"]["n"] > 0
    assert s["pairs"] and s["pairs"][0]["msgs"] > 0
    cost = s["sampler_cost_pct_per_host"]
    assert cost is not None and cost < 1.0  # measured: ~0.1 % of a core per host at 0.5 s


def test_after_cluster_down_the_bundles_are_complete(run):
    after = {b.host: b for b in load_bundles(run["dir"] / "after")}
    live = {b.host: b for b in load_bundles(run["dir"] / "live")}
    for h, b in after.items():
        assert b.manifest["state"] in ("killed", "dead"), (h, b.manifest["state"])
        assert len(b.samples) >= len(live[h].samples)


def _images(html: str, base: Path) -> list[Path]:
    srcs = re.findall(r'<img src="([^"]+)"', html)
    assert srcs
    return [base / s for s in srcs]


def test_report_renders_with_real_figures(run):
    import matplotlib.image as mpimg

    path = build_report(run["dir"] / "live")
    html = path.read_text()
    imgs = _images(html, path.parent)
    stems = {p.stem for p in imgs}
    assert {"allocation", "hosts_agents", "cpu_hosts", "cpu_types", "ddb", "faults"} <= stems
    for p in imgs:
        assert p.read_bytes()[:8] == PNG, p
        assert mpimg.imread(p).shape[0] > 100  # decodes as an image
    assert run["victim"] in html and "crashed" in html


def test_compare_two_runs_side_by_side(run):
    r = CliRunner().invoke(app, ["report", str(run["dir"] / "live"), str(run["dir"] / "after"),
                                 "-o", str(run["dir"] / "cmp")])
    assert r.exit_code == 0, r.output
    html = (run["dir"] / "cmp" / "report.html").read_text()
    imgs = _images(html, run["dir"] / "cmp")
    assert any(p.name.startswith("a_") for p in imgs) and any(p.name.startswith("b_") for p in imgs)
    assert all(p.read_bytes()[:8] == PNG for p in imgs)
    assert "B - A" in html


def test_bad_input_gets_one_line(tmp_path):
    runner = CliRunner()
    r = runner.invoke(app, ["report", str(tmp_path / "nope")])
    assert r.exit_code == 1 and "no such directory" in r.output and r.output.count("\n") == 1
    r = runner.invoke(app, ["report", str(tmp_path)])
    assert r.exit_code == 1 and "no stats bundles" in r.output
    (tmp_path / "h1.tar.gz").write_bytes(b"not a tar at all")
    r = runner.invoke(app, ["report", str(tmp_path)])
    assert r.exit_code == 1 and "h1.tar.gz: not a stats bundle" in r.output and r.output.count("\n") == 1
    with pytest.raises(BundleError, match="no manifest"):
        p = tmp_path / "h2.tar.gz"
        with tarfile.open(p, "w:gz") as tar:
            tar.addfile(tarfile.TarInfo("h2/log.jsonl"))
        read_bundle(p)
    r = runner.invoke(app, ["stats", "collect", "-o", str(tmp_path / "o"), "--root", str(tmp_path / "none")])
    assert r.exit_code == 1 and "no hosts to collect from" in r.output


def _bomb(path: Path, members: dict[str, int]) -> Path:
    """A gzip'd tar of zero-filled members (name -> size): a few KB on disk however large they expand."""
    import io
    import os

    class Zeros(io.RawIOBase):
        def __init__(self, n: int) -> None:
            self.left = n

        def readable(self) -> bool:
            return True

        def readinto(self, b) -> int:  # type: ignore[override]
            n = min(len(b), self.left)
            b[:n] = bytes(n)
            self.left -= n
            return n

    with tarfile.open(path, "w:gz", compresslevel=1) as tar:
        for name, size in members.items():
            info = tarfile.TarInfo(name)
            info.size = size
            tar.addfile(info, io.BufferedReader(Zeros(size)))
    assert os.path.getsize(path) < 1 << 20
    return path


def test_a_bundle_that_expands_beyond_its_bounds_is_refused_in_one_line(tmp_path, monkeypatch):
    """The probe's D6: a 1 MB bundle whose stats.jsonl expanded to 900 MB took `haactl report` past 4.8 GB and
    ended in a 65-line MemoryError traceback. The tar headers' sizes are checked before a member is read, and
    the decompressed stream as it goes."""
    import haa.lab.stats.bundle as bundle_mod

    d = tmp_path / "b"
    d.mkdir()
    _bomb(d / "h1.tar.gz", {"h1/manifest.json": 10, "h1/stats.jsonl": 70 << 20})
    r = CliRunner().invoke(app, ["report", str(d)])
    assert r.exit_code == 1 and r.output.count("\n") == 1, r.output
    assert "h1/stats.jsonl expands to 70 MiB, more than 64 MiB (MAX_MEMBER)" in r.output
    monkeypatch.setattr(bundle_mod, "MAX_BUNDLE_BYTES", 3 << 20)
    p = _bomb(tmp_path / "h2.tar.gz", {f"h2/agents/A{i}.log": 1 << 20 for i in range(4)})
    with pytest.raises(BundleError, match=r"h2\.tar\.gz: expands to more than 3 MiB \(MAX_BUNDLE_BYTES\)"):
        read_bundle(p)
    monkeypatch.setattr(bundle_mod, "MAX_MEMBERS", 10)
    p = _bomb(tmp_path / "h3.tar.gz", {f"h3/agents/A{i}.log": 1 for i in range(11)})
    with pytest.raises(BundleError, match=r"more than 10 members \(MAX_MEMBERS\)"):
        read_bundle(p)


def test_a_fifo_or_a_directory_as_a_bundle_is_refused_unopened(tmp_path):
    import os
    import time

    os.mkfifo(tmp_path / "h1.tar.gz")  # nobody writes to it
    t0 = time.monotonic()
    with pytest.raises(BundleError, match=r"h1\.tar\.gz: is a FIFO"):
        load_bundles(tmp_path)
    assert time.monotonic() - t0 < 1.0
    (tmp_path / "h1.tar.gz").unlink()
    (tmp_path / "h1.tar.gz").mkdir()
    with pytest.raises(BundleError, match=r"h1\.tar\.gz: is a directory"):
        load_bundles(tmp_path)


def test_truncated_bundle_is_refused(run, tmp_path):
    src = run["dir"] / "live" / "h1.tar.gz"
    data = src.read_bytes()
    (tmp_path / "h1.tar.gz").write_bytes(data[: len(data) // 2])
    with pytest.raises(BundleError, match=r"h1\.tar\.gz: (damaged stats bundle|not a stats bundle)"):
        load_bundles(tmp_path)


# ------------------------------------------------------------------ compose: data dirs through the docker SDK


class FakeContainer:
    """What `get_archive` of the docker SDK returns: a tar stream of the directory (named by its last part)."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files
        self.asked: list[str] = []

    def get_archive(self, path: str):
        import io

        self.asked.append(path)
        buf = io.BytesIO()
        base = path.rstrip("/").rsplit("/", 1)[-1]
        with tarfile.open(fileobj=buf, mode="w") as tar:
            for name, data in self.files.items():
                info = tarfile.TarInfo(f"{base}/{name}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
        data = buf.getvalue()
        return iter([data[:1000], data[1000:]]), {"name": base}


class FakeCompose:
    kind = "compose"

    def __init__(self, containers: dict[str, FakeContainer]) -> None:
        self.containers = containers
        self.services = {n: {"command": ["--name", n, "--data-dir", f"/srv/haa/{n}"]} for n in containers}

    def describe(self) -> str:
        return "compose cluster (fake)"

    def hosts(self):
        from haa.cluster.backend import HostInfo

        return [HostInfo(n, "127.0.0.1:1", "killed" if n == "h2" else "alive", container=n) for n in self.containers]

    def container(self, name: str) -> FakeContainer:
        return self.containers[name]

    def log_records(self, names, follow):
        return iter([])


def _line(**kw) -> bytes:
    return (json.dumps(kw) + "\n").encode()


def test_compose_data_dirs_are_read_through_the_docker_sdk(tmp_path):
    t = 1_700_000_000.0
    h1_log = _line(ts=t, host="h1", inc=1, level="info", event="view",
                   fields={"view": 2, "members": ["h1.1", "h2.2"], "removed": [], "added": ["h2"]})
    h2_log = (_line(ts=t + 1, host="h2", inc=2, level="info", event="agent_spawning",
                    fields={"agent": "a" * 36, "name": "A1", "detail": ""})
              + _line(ts=t + 1.2, host="h2", inc=2, level="info", event="agent_active",
                      fields={"agent": "a" * 36, "name": "A1", "detail": "fresh state"}))
    h1_log += _line(ts=t + 5, host="h1", inc=1, level="info", event="agent_crashed",
                    fields={"agent": "a" * 36, "name": "A1", "detail": ""})
    sample = {"ts": t + 1, "host": "h2", "inc": 2, "seq": 1, "cpu": 0.01, "rss": 1, "agents": {}, "cost_s": 0.001}
    half = b'{"ts": 1700000002, "host": "h2", "se'  # killed while writing
    fake = FakeCompose({
        "h1": FakeContainer({"h1.jsonl": h1_log, "stats.jsonl": _line(**{**sample, "host": "h1"})}),
        "h2": FakeContainer({"h2.jsonl": h2_log, "stats.jsonl": _line(**sample) + half,
                             "agents/" + "a" * 36 + ".log": b"agent says hi\n", "stderr.1.txt": b"boom\n"}),
    })
    res = collect_bundles(fake, tmp_path / "b")
    assert res.errors == {}
    assert fake.containers["h2"].asked == ["/srv/haa/h2"]
    h2 = read_bundle(tmp_path / "b" / "h2.tar.gz")
    assert h2.manifest["state"] == "killed" and h2.manifest["source"].startswith("container h2:/srv/haa/h2")
    assert len(h2.samples) == 1  # the half-written last line is left out
    crash = [e for e in h2.events if e["event"] == "crashed"]
    assert crash and crash[0]["host"] == "h2" and crash[0]["reporter"] == "h1"  # where it ran, who saw it
    assert h2.files["stderr.txt"] == b"boom\n" and h2.files["agents/" + "a" * 36 + ".log"] == b"agent says hi\n"
    assert h2.latency["spawn"]["n"] == 1 and abs(h2.latency["spawn"]["values_ms"][0] - 200) < 1
