"""`haactl report DIR` and `haactl report A B`: an HTML report with PNG figures from a run's bundles.

A run directory holds the bundles of its hosts (`<host>.tar.gz`, haa.lab.stats.collect) and, when it is a
mission run folder (`haactl mission run -o DIR`, docs/team.md), `results.json` and `samples.json`; a chaos run
directory (`haactl chaos run`, docs/chaos.md) adds `faults.json` and `result.json`, a mission with a chaos
plan `chaos.json`. `build_report(DIR)` writes
`DIR/report.html` and its figures `DIR/figures/*.png` (haa.lab.stats.figures); `build_compare(A, B)` writes
`A/compare-<B>/report.html` with both runs side by side, each figure pair on the same scales, and a table
of the numbers of both with their difference. Everything is recomputed from the bundles (haa.lab.stats.summary);
a missing or broken input raises `BundleError` with one line.
"""

from __future__ import annotations

import html
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from haa.lab.stats import figures
from haa.lab.stats.run import RunData, load_run

REPORT_FILE = "report.html"
FIG_DIR = "figures"
#: timeline lines shown in the report (the summary and the bundles keep all)
MAX_TIMELINE_ROWS = 400


# ---------------------------------------------------------------------------------------------- figures

FigureFn = Callable[..., Path]
#: (file stem, caption, function, takes ylim)
FIGURES: list[tuple[str, str, FigureFn, bool]] = [
    ("allocation", "Allocation timeline per host (Fig. 7.1-2): one row per agent on each host that ran it",
     figures.allocation, False),
    ("hosts_agents", "Hosts and agents over time", figures.hosts_agents, True),
    ("cpu_hosts", "CPU per host (Fig. 7.1-8)", figures.cpu_hosts, True),
    ("cpu_types", "CPU per agent type (Fig. 7.1-9)", figures.cpu_types, True),
    ("ddb", "DDB size by kind (Fig. 7.1-7)", figures.ddb, True),
    ("faults", "Faults against recoveries", figures.faults, True),
]


def _ylim(runs: list[RunData], stem: str) -> tuple[float, float] | None:
    """A common y range for a figure drawn for several runs."""
    top = 0.0
    for r in runs:
        s = r.series
        if stem == "hosts_agents":
            top = max(top, *s.hosts_up, *s.members, *s.agents, 1)
        elif stem == "cpu_hosts":
            top = max(top, *(v for pts in s.host_cpu.values() for _, v in pts), 1.0)
        elif stem == "cpu_types":
            top = max(top, *(sum(x) for x in zip(*s.type_cpu.values(), strict=False)), 1.0)
        elif stem == "ddb":
            top = max(top, *(sum(x) / 2**20 for x in zip(*s.ddb_kind.values(), strict=False)), 0.01)
        elif stem == "faults":
            fs, rs, _ = figures.fault_recovery_times(r)
            top = max(top, len(fs), len(rs), 1)
        else:
            return None
    return (0.0, top * 1.08)


def draw(run: RunData, out: Path, prefix: str = "", xlim: tuple[float, float] | None = None,
         ylims: dict[str, tuple[float, float] | None] | None = None) -> list[tuple[str, str, Path]]:
    """Every figure of a run as PNGs in `out`; [(stem, caption, path)]."""
    done = []
    for stem, caption, fn, takes_y in FIGURES:
        kw: dict[str, Any] = {"xlim": xlim}
        if takes_y and ylims is not None:
            kw["ylim"] = ylims.get(stem)
        done.append((stem, caption, fn(run, out / f"{prefix}{stem}.png", **kw)))
    if run.mission is not None:
        done.append(("mission", "Mission: coverage, accuracy and position error over mission time",
                     figures.mission(run, out / f"{prefix}mission.png")))
    return done


# ---------------------------------------------------------------------------------------------- HTML

CSS = """body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:.5em 0 1.5em}
td,th{border:1px solid #ccc;padding:2px 8px;font-size:13px;text-align:right}th{background:#f0f0f0}
td.l,th.l{text-align:left}img{max-width:100%;border:1px solid #ddd}figure{margin:0 0 1.5em}
figcaption{font-size:13px;color:#555}.side{display:grid;grid-template-columns:1fr 1fr;gap:1em}
.bad{color:#b00}.ok{color:#070}"""


def esc(v: Any) -> str:
    return html.escape(str(v))


def table(head: list[str], rows: list[list[Any]], left: int = 1) -> str:
    h = "".join(f'<th class="{"l" if i < left else ""}">{esc(c)}</th>' for i, c in enumerate(head))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{esc("-" if c is None else c)}</td>'
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _lat(d: dict[str, Any]) -> list[Any]:
    if not d.get("n"):
        return [0, None, None, None, None]
    return [d["n"], d.get("mean_ms"), d.get("p50_ms"), d.get("p95_ms"), d.get("max_ms")]


MISSION_KEYS = ("completed", "reason", "duration_s", "coverage", "accuracy", "explored", "position_error_m",
                "rotation_error_rad", "landmark_error_m", "hosts_avg", "agents_avg", "cpu_percent", "transfers",
                "recoveries", "agent_failures", "ddb_mb")


def numbers(run: RunData) -> list[tuple[str, Any]]:
    """The run's headline numbers (for the comparison table)."""
    s = run.summary
    out: list[tuple[str, Any]] = [("duration [s]", s["duration_s"]), ("hosts", len(s["hosts"]))]
    out += [(k.replace("_", " "), v) for k, v in s["counts"].items()]
    for k, v in s["latency"].items():
        out.append((f"{k.replace('_', ' ')} mean [ms]", v.get("mean_ms") if v.get("n") else None))
    cpu = [h["cpu_host_pct"] for h in s["hosts"].values() if h.get("cpu_host_pct") is not None]
    out.append(("haa-hostd CPU per host, mean [%]", round(sum(cpu) / len(cpu), 2) if cpu else None))
    out.append(("sampler CPU per host [%]", s.get("sampler_cost_pct_per_host")))
    out += [(f"CPU {t} [%]", v) for t, v in s["cpu_by_type_pct"].items()]
    d = s.get("ddb") or {}
    out.append(("DDB bytes at the end", d.get("bytes")))
    if run.mission is not None:
        res = run.mission.get("results") or {}
        out += [(f"mission {k}", res.get(k)) for k in MISSION_KEYS if k in res]
    if run.chaos is not None:
        out.append(("chaos checks passed", run.chaos.get("passed")))
    return out


def sections(run: RunData, figs: list[tuple[str, str, Path]], base: Path) -> str:
    s = run.summary
    parts = [f"<p>{esc(s.get('cluster', ''))}: {len(s['hosts'])} hosts, {s['duration_s']:.0f} s of records, "
             f"sampled every {esc(s['sampler_period_s'])} s ({s['samples']} samples); the sampler cost "
             f"{esc(s.get('sampler_cost_pct_per_host'))} % of a core per host.</p>"]
    if run.mission is not None:
        res = run.mission.get("results") or {}
        parts.append("<h2>Mission</h2>" + table(["result", "value"],
                                                [[k, res.get(k)] for k in MISSION_KEYS if k in res]))
    if run.chaos is not None:
        rows = [[k, "passed" if c.get("passed") else "FAILED", c.get("detail", "")]
                for k, c in (run.chaos.get("checks") or {}).items()]
        parts.append("<h2>Chaos checks</h2>" + table(["check", "result", "detail"], rows, left=3))
    for stem, caption, path in figs:
        rel = path.relative_to(base).as_posix()
        parts.append(f'<figure id="{stem}"><img src="{esc(rel)}" alt="{esc(caption)}">'
                     f"<figcaption>{esc(caption)}</figcaption></figure>")
    parts.append("<h2>Hosts</h2>" + table(
        ["host", "state", "incarnations", "samples", "events", "host CPU %", "agents CPU %", "RSS max MB",
         "sampler CPU %", "ms per sample", "errors"],
        [[h, v.get("state"), v.get("incarnations"), v.get("samples"), v.get("events"), v.get("cpu_host_pct"),
          v.get("cpu_agents_pct"), v.get("rss_max_mb"), v.get("sampler_cost_pct"), v.get("sampler_ms_per_sample"),
          "; ".join(v.get("errors") or [])] for h, v in s["hosts"].items()], left=2))
    parts.append("<h2>Counts</h2>" + table(["what", "count"], [[k.replace("_", " "), v]
                                                              for k, v in s["counts"].items()]))
    parts.append("<h2>Latencies</h2>" + table(["phase", "n", "mean ms", "p50 ms", "p95 ms", "max ms"],
                                              [[k.replace("_", " "), *_lat(v)] for k, v in s["latency"].items()]))
    parts.append("<h2>Messages between agents</h2>" + table(
        ["from", "to", "messages", "bytes"], [[p["src"], p["dst"], p["msgs"], p["bytes"]] for p in s["pairs"][:20]],
        left=2))
    d = s.get("ddb") or {}
    if d:
        parts.append("<h2>DDB at the end</h2>" + table(
            ["prefix / kind", "bytes"],
            [[f"kind: {k}", v] for k, v in (d.get("by_kind") or {}).items()]
            + [[p, v] for p, v in sorted((d.get("by_prefix") or {}).items(), key=lambda kv: -kv[1])]))
    rows = []
    for r in s["timeline"][:MAX_TIMELINE_ROWS]:
        if r.get("event") == "view":
            what = "; ".join([*(f"{h} joined" for h in r.get("added") or []),
                              *(f"{h} removed" for h in r.get("removed") or [])])
            rows.append([f"{r['t']:.1f}", r.get("host"), f"view {r.get('view')}: {what}"])
        else:
            who = f"{r.get('name')} ({r.get('type')})" if r.get("type") else r.get("name")
            rep = f" (reported by {r['reporter']})" if r.get("reporter") else ""
            det = f": {r['detail']}" if r.get("detail") else ""
            rows.append([f"{r['t']:.1f}", r.get("host"), f"{who} {r.get('event')}{det}{rep}"])
    more = len(s["timeline"]) - len(rows)
    parts.append(f"<h2>Timeline</h2><p>every agent event on the host where it happened, and the view changes"
                 f"{f'; {more} more lines in summary.json and the bundles' if more > 0 else ''}</p>"
                 + table(["t [s]", "host", "event"], rows, left=3))
    return "\n".join(parts)


def page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(title)}</title><style>{CSS}</style>"
            f"</head><body><h1>{esc(title)}</h1><p>generated {time.strftime('%Y-%m-%d %H:%M:%S')} by haactl "
            f"report</p>\n{body}\n</body></html>\n")


def build_report(run_dir: Path, out_dir: Path | None = None) -> Path:
    """`DIR/report.html` (or `out_dir/report.html`) with its figures; the path of the HTML file."""
    run = load_run(run_dir)
    out = Path(out_dir) if out_dir is not None else Path(run_dir)
    figs = draw(run, out / FIG_DIR)
    path = out / REPORT_FILE
    path.write_text(page(f"HAA run {run.name}", sections(run, figs, out)))
    return path


def build_compare(a_dir: Path, b_dir: Path, out_dir: Path | None = None) -> Path:
    """Both runs side by side: `out_dir` (default `A/compare-<B name>`)/report.html; its path."""
    a, b = load_run(a_dir), load_run(b_dir)
    out = Path(out_dir) if out_dir is not None else Path(a_dir) / f"compare-{Path(b_dir).absolute().name}"
    span = max(a.t1 - a.t0, b.t1 - b.t0, 1.0)
    xlim = (0.0, span * 1.02)
    ylims = {stem: _ylim([a, b], stem) for stem, _, _, takes in FIGURES if takes}
    fa = draw(a, out / FIG_DIR, "a_", xlim, ylims)
    fb = draw(b, out / FIG_DIR, "b_", xlim, ylims)
    na, nb = dict(numbers(a)), dict(numbers(b))
    rows = []
    for k in dict.fromkeys([*na, *nb]):
        va, vb = na.get(k), nb.get(k)
        diff = None
        if isinstance(va, int | float) and isinstance(vb, int | float) and not isinstance(va, bool):
            diff = round(vb - va, 4)
            if va:
                diff = f"{diff:+g} ({100 * (vb - va) / abs(va):+.0f} %)"
        rows.append([k, va, vb, diff])
    parts = [f"<p>A = {esc(a_dir)}, B = {esc(b_dir)}; the same time axis (s since each run's first record) "
             f"and the same scales for both.</p>",
             "<h2>Numbers</h2>" + table(["", f"A: {a.name}", f"B: {b.name}", "B - A"], rows)]
    by_b = {stem: (cap, p) for stem, cap, p in fb}
    for stem, cap, pa in fa:
        pb = by_b.get(stem, (cap, None))[1]
        cells = [f'<div><img src="{esc(pa.relative_to(out).as_posix())}" alt="A {esc(cap)}"></div>']
        cells.append(f'<div><img src="{esc(pb.relative_to(out).as_posix())}" alt="B {esc(cap)}"></div>'
                     if pb is not None else "<div>(none in B)</div>")
        parts.append(f'<figure id="{stem}"><div class="side">{"".join(cells)}</div>'
                     f"<figcaption>{esc(cap)} — left A, right B</figcaption></figure>")
    for stem, cap, pb in fb:
        if stem not in {s for s, _, _ in fa}:
            parts.append(f'<figure id="{stem}"><div class="side"><div>(none in A)</div><div><img '
                         f'src="{esc(pb.relative_to(out).as_posix())}" alt="B {esc(cap)}"></div></div>'
                         f"<figcaption>{esc(cap)} — left A, right B</figcaption></figure>")
    path = out / REPORT_FILE
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(page(f"HAA runs {a.name} vs {b.name}", "\n".join(parts)))
    return path
