"""The robot team's missions (thesis §7.1, §7.3): AF-1, AF-2 and R-1 beside Tables 7.1-1, 7.1-2 and 7.3-1."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from haa.lab.results.common import (
    TABLE_REFS,
    Json,
    Lines,
    num,
    pct,
    table,
)

# ----- mission experiments (thesis §7.1, §7.3) ----------------------------------------------------------------


def _provenance(d: Json) -> str:
    p = d.get("provenance") or {}
    bits = []
    if p.get("commit"):
        bits.append(f"commit `{p['commit'][:7]}`" + (" with uncommitted changes" if p.get("dirty") else ""))
    if p.get("mission_file"):
        bits.append(f"mission file `{Path(p['mission_file']).name}`")
    return "; ".join(bits)


def _mission_summary(rows: list[Json], thesis_label: str) -> Lines:
    out: list[list[Any]] = []
    for r in rows:
        if not r.get("n"):
            continue
        t = r.get("thesis") or [None] * 4
        out.append([r["title"], num(r.get("representative")), num(r["mean"]), num(r["rms"]), num(r["std"]),
                    r["n"], *(num(x) for x in t)])
    return table(["measure", "rep. run", "mean", "RMS", "STD", "runs", f"{thesis_label} rep.", "thesis mean",
                  "thesis RMS", "thesis STD"], out)


def _mission_runs(results: list[Json]) -> Lines:
    out = []
    for r in results:
        out.append([r.get("seed"), "yes" if r.get("completed") else f"no: {r.get('reason', '')}",
                    num(r["duration_s"] / 60 if r.get("duration_s") is not None else None),
                    pct(r.get("coverage"), 1), pct(r.get("accuracy"), 1), num(r.get("position_error_m"), 3),
                    num(r.get("uncorrected_error_m"), 3), r.get("bumps"), r.get("transfers"), r.get("recoveries"),
                    num(r["wall_s"] / 60 if r.get("wall_s") is not None else None, 3)])
    return table(["seed", "completed", "duration [min]", "coverage", "accuracy", "position err [m]",
                  "dead reckoning [m]", "bumps", "transfers", "recoveries", "wall [min]"], out)


def render_mission(d: Json, name: str) -> Lines:
    exp = d.get("experiment", "")
    ref = TABLE_REFS.get(exp, "")
    head = (f"{d['runs']} runs, {d['completed']} completed; seeds {', '.join(str(s) for s in d.get('seeds', []))}; "
            f"`--speed {num(d.get('speed'))}` (simulated seconds per wall second); SupervisorExplore strategy "
            f"`{d.get('exploration', '')}`; representative run: seed {d.get('representative_seed')} (the run "
            f"closest to the means); {num(d['wall_s'] / 60, 3)} min of wall time in all.")
    prov = _provenance(d)
    lines = [head + (f" Measured at {prov}." if prov else ""), ""]
    lines.append(f"Beside the thesis' {ref}: durations are simulated time; \"Average # Hosts\" counts the "
                 "simulation computer as the thesis does; CPU is the whole machine here, one PC of ten in the "
                 "thesis. Map coverage and accuracy are relative to a map built with no localization error. STD is the "
                 "population standard deviation over the runs that have the value (`runs`).")
    lines += ["", *_mission_summary(d["rows"], "thesis"), "", "Each run:", "", *_mission_runs(d.get("results", []))]
    return lines


def command_experiment(d: Json, name: str) -> str:
    exp = d.get("experiment", name)
    cmd = f"haactl experiment {exp} --runs {d.get('runs_planned', d.get('runs'))} --speed {num(d.get('speed'))}"
    if d.get("exploration") and d["exploration"] != "em":
        cmd += f" --exploration {d['exploration']}"
    mission_file = Path((d.get("provenance") or {}).get("mission_file", "")).name
    if mission_file and mission_file != f"{exp}.yaml":
        cmd += f" --mission {mission_file}"
    if name != exp:
        cmd += f" --json bench-results/{name}.json"
    return cmd


R1_LEVELS = ["none", "moderate", "high", "extreme"]


def render_r1(d: Json, name: str) -> Lines:
    levels = [lv for lv in R1_LEVELS if lv in d["levels"]]
    th = d.get("thesis", {})
    ttable = th.get("table", {})
    runs = {lv: d["levels"][lv]["runs"] for lv in levels}
    done = {lv: d["levels"][lv]["completed"] for lv in levels}
    windows = d.get("windows_s", {})

    def window(lv: str) -> str:
        w = windows.get(lv)
        return "no failure" if not w else f"agent life {num(w[0] / 60, 2)}-{num(w[1] / 60, 2)} min"

    lines = [
        "Every agent hangs (its event loop blocked " + num(d.get("hang_s")) + " s simulated) at a uniform time in "
        "its life window and again after each recovery: " + "; ".join(f"{lv}: {window(lv)}" for lv in levels)
        + ". Runs per level: " + ", ".join(f"{lv} {done[lv]}/{runs[lv]}" for lv in levels)
        + f"; seeds {', '.join(str(s) for s in d.get('seeds', []))}; `--speed {num(d.get('speed'))}`; "
        + f"{num(d['wall_s'] / 60, 3)} min of wall time in all."
        + (f" Measured at {_provenance(d)}." if _provenance(d) else ""),
        "",
        f"Means beside the thesis' {TABLE_REFS['r1']}:",
        "",
    ]
    by_level = {lv: {r["title"]: r for r in d["levels"][lv]["rows"]} for lv in levels}
    titles = [r["title"] for r in d["levels"][levels[0]]["rows"]]
    rows: list[list[Any]] = []
    for t in titles:
        cells = [by_level[lv].get(t) for lv in levels]
        if not any(c and c.get("n") for c in cells):
            continue
        thesis = ttable.get(t, {}).get("mean") or [None] * len(levels)
        rows.append([t, *(num(c["mean"]) if c and c.get("n") else "—" for c in cells), *(num(x) for x in thesis)])
    lines += table(["measure", *levels, *(f"thesis {lv}" for lv in levels)], rows)
    lines += ["", "Standard deviations (over the runs of each level) beside the thesis':", ""]
    rows = []
    for t in titles:
        cells = [by_level[lv].get(t) for lv in levels]
        if not any(c and c.get("n") for c in cells) or t not in ttable:
            continue
        rows.append([t, *(num(c["std"]) if c and c.get("n") else "—" for c in cells),
                     *(num(x) for x in ttable[t].get("std", []))])
    lines += table(["measure", *levels, *(f"thesis {lv}" for lv in levels)], rows)
    inc, tinc = d.get("increase", {}), th.get("increase", {})
    lines += ["", "Mission duration against no failure (eq. 7.3-1):", ""]
    lines += table(["", *(lv for lv in levels if lv != "none"), "k [min]"],
                   [["ours", *(pct(inc.get(lv), 1) for lv in levels if lv != "none"), num(d.get("k_min"), 3)],
                    ["thesis", *(pct(tinc.get(lv), 0) for lv in levels if lv != "none"), num(th.get("k_min"))]])
    fails = d.get("failures", {})
    if fails:
        lines += ["", "Agent failures per run: " + "; ".join(
            f"{lv} {num(fails[lv]['mean'], 3)} ± {num(fails[lv]['std'], 3)}" for lv in levels if lv in fails) + "."]
    return lines


def command_r1(d: Json, name: str) -> str:
    runs = d["levels"][next(iter(d["levels"]))]["runs"]
    return f"haactl experiment r1 --runs {runs} --speed {num(d.get('speed'))}"


