"""How long a committed DDB change takes to show on the dashboard page (issue 19 §1: "within 1 s, with 50 agents
and a 200x200 grid").

    .venv/bin/python -m haa.lab.bench.dashboard_latency [--hosts 3] [--agents 50] [--cells 200] [--rounds 30]

A local cluster of `--hosts` haa-hostd processes runs `--agents` counter agents (pairs that message each other
once a second, so that the hierarchy shows message rates); a `--cells` x `--cells` occupancy grid is published at
`slam/map` and two avatar estimates at `slam/est/*`. `haactl dashboard --port 0` serves the cluster (following
the mirror of the first member) and headless Chromium shows the page. Then, `--rounds` times each: a new map
(other cells) is written through the *last* host (so the change crosses the group before the followed host's
mirror sends it), and separately a moved estimate; for each we take the wall time before the write call, when
the write returned committed, and when the page had drawn that version of the object and the browser had painted
the frame (`window.HAA.drawn`, Date.now() after the next animation frame; one clock: everything runs on this
machine). Results: bench-results/dashboard.json (p50/p95/max of write->painted and commit->painted, ms).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from haa.cluster.agents import wait_rows
from haa.cluster.backend import wait_until
from haa.cluster.local_backend import LocalBackend
from haa.core.ddb import ops as ddbops
from haa.lab.dashboard.browser import Chromium
from haa.slam.grid import GridSpec
from haa.slam.replica import encode_map

REPO = Path(__file__).resolve().parents[3]

HAACTL = [sys.executable, "-c", "from haactl.main import app; app()"]

WAIT_JS = """new Promise((res) => { const t0 = Date.now(); const chk = () => {
  const d = window.HAA.drawn.%s; if (d && d.%s >= %d) res(d.painted);
  else if (Date.now() - t0 > 10000) res(null); else setTimeout(chk, 2); }; chk(); })"""


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, round(q * (len(xs) - 1)))]


def stats(xs: list[float]) -> dict[str, float]:
    return {"p50": round(statistics.median(xs), 1), "p95": round(pct(xs, 0.95), 1), "max": round(max(xs), 1),
            "mean": round(statistics.fmean(xs), 1), "n": len(xs)}


async def measure(url: str, backend: LocalBackend, writer: str, cells: int, rounds: int, tmp: Path) -> dict:
    rng = np.random.default_rng(1)
    spec = GridSpec(cells * 0.1, cells * 0.1, 0.1)
    out: dict = {"map": {"write_to_paint": [], "commit_to_paint": [], "commit": []},
                 "estimate": {"write_to_paint": [], "commit_to_paint": [], "commit": []}}
    c = backend.client(writer, timeout=10.0)
    async with Chromium(tmp, width=1600, height=1000) as b:
        await b.navigate(url)
        await b.wait_for("window.HAA && window.HAA.connected", 20)
        await b.wait_for("window.HAA.drawn.map && window.HAA.drawn.map.version", 30)
        await b.wait_for("S.agents.length > 0", 30)
        for i in range(rounds):
            for what in ("map", "estimate"):
                if what == "map":
                    p = rng.uniform(0.0, 1.0, size=spec.shape)
                    ops = [ddbops.put("slam/map", "blob", encode_map(spec, p))]
                else:
                    ops = [ddbops.put("slam/est/s1", "json", {"t": i, "x": 1.0 + 0.05 * i, "y": 2.0, "theta": 0.3,
                                                              "std": [0.05, 0.05, 0.02]})]
                t_write = time.time()
                reply = await asyncio.to_thread(c.ddb_write, ops)
                t_commit = time.time()
                assert reply.committed, reply.reason
                version = reply.results[0].version
                js = WAIT_JS % (("map", "version", version) if what == "map" else ("overlay", "seq", version))
                painted = await b.evaluate(js)
                if painted is None:
                    raise SystemExit(f"round {i}: the page never drew {what} version {version}")
                r = out[what]
                r["write_to_paint"].append(painted - 1000 * t_write)
                r["commit_to_paint"].append(painted - 1000 * t_commit)
                r["commit"].append(1000 * (t_commit - t_write))
                await asyncio.sleep(0.25)
        out["agents_on_page"] = await b.evaluate("S.agents.length")
        out["page_errors"] = list(b.console)
        await b.screenshot(tmp / "dashboard-bench.png")
    c.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hosts", type=int, default=3)
    ap.add_argument("--agents", type=int, default=50)
    ap.add_argument("--cells", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--out", type=Path, default=REPO / "bench-results" / "dashboard.json")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="haa-dash-bench-"))
    backend = LocalBackend(tmp / "cluster")
    names = backend.up(args.hosts, min(3, args.hosts))
    dash = None
    try:
        backend.check_started()
        wait_until(lambda: backend.formation(names), 90, what="the group")
        cfg = json.dumps({"spawn_peer": True, "period": 1.0}).encode()
        t0 = time.monotonic()
        for _ in range(args.agents // 2):
            rep = backend.call(names[0], lambda c: c.agent_spawn("counter", cfg, timeout=60.0), "AgentSpawn", 65.0)
            assert rep.ok, rep.reason
        wait_rows(backend, lambda rs: len(rs) == args.agents and all(r.state == "active" for r in rs), 300,
                  f"{args.agents} active agents")
        print(f"{args.agents} agents active in {time.monotonic() - t0:.0f} s", flush=True)
        spec = GridSpec(args.cells * 0.1, args.cells * 0.1, 0.1)
        backend.call(names[0], lambda c: c.ddb_write([
            ddbops.put("slam/map", "blob", encode_map(spec, np.full(spec.shape, 0.5))),
            ddbops.put("slam/est/s1", "json", {"x": 1.0, "y": 2.0, "theta": 0.0}),
            ddbops.put("slam/est/s2", "json", {"x": 3.0, "y": 2.0, "theta": 1.0})]), "DdbWrite", 30.0)
        dash = subprocess.Popen([*HAACTL, "dashboard", "--port", "0", "--no-truth", "--root", str(tmp / "cluster")],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
        assert dash.stdout is not None
        line = dash.stdout.readline()
        m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
        assert m, line
        res = asyncio.run(measure(m.group(1), backend, names[-1], args.cells, args.rounds, tmp))
    finally:
        if dash is not None:
            dash.terminate()
            dash.wait(10)
        backend.down(grace=3.0)
    result = {
        "what": "committed DDB change -> painted on the dashboard page (ms)",
        "hosts": args.hosts, "agents": args.agents, "grid": f"{args.cells}x{args.cells}", "rounds": args.rounds,
        "writer": names[-1], "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version(),
                                          "load1": round(__import__("os").getloadavg()[0], 2)},
        "map": {k: stats(v) for k, v in res["map"].items()},
        "estimate": {k: stats(v) for k, v in res["estimate"].items()},
        "agents_on_page": res["agents_on_page"], "page_errors": res["page_errors"],
        "screenshot": str(tmp / "dashboard-bench.png"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
