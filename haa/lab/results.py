"""docs/results.md, generated from bench-results/*.json: every measured number on that page comes from a JSON file.

    python -m haa.lab.results            # write docs/results.md (`make results`)
    python -m haa.lab.results --check    # exit 1 if docs/results.md differs from what would be written

Each benchmark or experiment file has a section of its own, laid out in the thesis' shape where the thesis has
one (Tables 7.1-1, 7.1-2, 7.2-1, 7.2-3, 7.3-1; the statements of §7.2): our figures beside the thesis' values,
with run counts, seeds and spread where the file has them, the file it comes from and the command that
reproduces it. The thesis' values that the files do not carry are constants here, each with the line of the
specification text (seed/000_e446544e9113dd13.txt) it comes from. A file this module does not know gets a
generic section (its top-level scalar fields), so a new result never needs a hand edit.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import re
import statistics
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
RESULTS_DIR = ROOT / "bench-results"
PAGE = ROOT / "docs" / "results.md"

Json = dict[str, Any]
Lines = list[str]

# ----- the thesis' values that the JSON files do not carry (line numbers of the specification text) ------------

#: §7.2.1, L1603: "There is typically only a small delay, < 10 ms, between deciding and delivering"
THESIS_AP1 = "decide→deliver \"< 10 ms\" (L1603); messages per OAC plotted in Fig. 7.2-3 (L1605-1615)"
#: §7.2.2, L1629: joins "on the order of seconds", leaves "averaging close to 0.6 seconds", removal "in less
#: than 1.5 seconds after being suspected by the first member"
THESIS_AP2 = ("join: \"on the order of seconds\"; leave: \"close to 0.6 seconds\"; removal: \"less than 1.5 "
              "seconds after being suspected by the first member\" (L1629)")
#: §7.2.3, L1635: time grows with agents, not clearly with hosts; messages grow with both (figures only)
THESIS_AP3 = ("no strong correlation between time and the number of hosts, a clear increase with the number of "
              "agents; messages grow with hosts and agents (L1635; Fig. 7.2-5/7.2-6 give no table)")
#: §7.2.4, L1653: spawn 1-2 s, transfer 1.3-2.1 s (a third to a half of it freezing), recovery 0.7-2.9 s
THESIS_AP4 = {"spawn": "1-2 s", "freeze": "1/3-1/2 of transfer", "transfer": "1.3-2.1 s",
              "recovery": "0.7-2.9 s", "host_recovery": "0.7-2.9 s"}
#: Table 7.2-1 (L1670-1674): the AP-5.1 teams, their recorded length and uncorrected error [m]
THESIS_AP51 = {"Basic": ("4 Seekers", "2:56", 0.123), "Advanced A": ("4 Sweepers", "27:05", 0.804),
               "Advanced B": ("8 Sweepers", "15:22", 0.281)}
#: Table 7.2-3 (L1743-1747): N = 500, M observations between weight updates, operations saved
THESIS_AP52 = {"Basic": (2.93, "44 %"), "Advanced A": (3.97, "50 %"), "Advanced B": (4.89, "53 %")}
#: §7.2.5.3, L1758: JC-SLAM kept up with 24.0 readings/s (generation and processing) in the whole system
THESIS_SLAM = "the whole system processed 24.0 readings/s in AP-5.3 (L1758)"
#: §5.2, L968: 1000 particles, one prediction a second: ~12 KB/s, "less 42 MB after an hour"
THESIS_SLAM_MEMORY = "1000 particles at one prediction per second: \"42 MB after an hour\" (L968)"
#: §4.4, L535: the thesis' QoS (10 s, 1 week, 30 s) "cost roughly 12 messages/minute"
THESIS_UFD = "the thesis' QoS (T_D^U = 10 s, T_MR^L = 1 week, T_M^U = 30 s) \"cost roughly 12 messages/minute\" (L535)"

TABLE_REFS = {"af1": "Table 7.1-1 (L1390-1403)", "af2": "Table 7.1-2 (L1514-1527)", "r1": "Table 7.3-1 (L1794-1806)"}


# ----- formatting ---------------------------------------------------------------------------------------------


def num(x: Any, digits: int = 4) -> str:
    """A number as the tables show it: at most `digits` significant figures (trailing zeros dropped), thousands
    separated, `—` for none."""
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if not isinstance(x, float):
        return str(x)
    if math.isnan(x):
        return "—"
    if math.isinf(x):
        return "∞"
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 10 ** (digits - 1):
        return f"{x:,.0f}"
    decimals = max(0, digits - 1 - math.floor(math.log10(a)))
    text = f"{x:,.{decimals}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def ms(seconds: float | None) -> str:
    """Seconds as whole milliseconds."""
    return "—" if seconds is None else f"{seconds * 1e3:,.0f}"


def pct(share: float | None, decimals: int = 0) -> str:
    return "—" if share is None else f"{100 * share:.{decimals}f} %"


def table(headers: list[str], rows: Iterable[list[Any]]) -> Lines:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    for row in rows:
        out.append("| " + " | ".join(c if isinstance(c, str) else num(c) for c in row) + " |")
    return out


def machine_line(m: Json | None) -> str:
    """What the file says about the machine it was measured on."""
    if not m:
        return ""
    parts = []
    cpus = m.get("cpus", m.get("cpu_count"))
    if cpus is not None:
        parts.append(f"{cpus} CPUs")
    for key in ("load_avg", "load_avg_at_end", "load_1min", "load1"):
        if key in m:
            v = m[key]
            label = "load average at the end" if key == "load_avg_at_end" else "load average"
            parts.append(f"{label} " + (" / ".join(num(x, 3) for x in v) if isinstance(v, list) else num(v, 3)))
    if "python" in m:
        parts.append(f"Python {m['python']}")
    if "event_loop" in m:
        parts.append(f"event loop {m['event_loop']}")
    return "Machine: " + ", ".join(parts) + "." if parts else ""


def median(xs: list[float]) -> float | None:
    return statistics.median(xs) if xs else None


def mean_pstd(xs: list[float]) -> tuple[float | None, float | None]:
    xs = [x for x in xs if x == x]
    if not xs:
        return None, None
    return statistics.fmean(xs), statistics.pstdev(xs) if len(xs) > 1 else 0.0


def span(xs: Iterable[float]) -> str:
    v = [x for x in xs if x is not None]
    return f"{num(min(v), 3)}-{num(max(v), 3)}" if v else "—"


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


# ----- AP-1 and the commit path (§7.2.1) ----------------------------------------------------------------------


def render_ap1(d: Json, name: str) -> Lines:
    rows = []
    for r in d["rows"]:
        pd, dd = r["propose_to_decide_ms"], r["decide_to_deliver_ms"]
        rows.append([r["participants"], r["mode"], r["transactions"],
                     f"{num(pd['p50'], 3)} / {num(pd['p90'], 3)} / {num(pd['p99'], 3)}",
                     f"{num(dd['p50'], 3)} / {num(dd['p90'], 3)} / {num(dd['p99'], 3)}",
                     num(r["messages_per_tx"]), r["formula_n2_4n_minus_6"], num(r["throughput_tx_per_s"], 3),
                     "yes" if r.get("same_delivered_hash") else "no"])
    return [
        f"Real `haa-hostd` processes on loopback, {d.get('transactions_per_step')} transactions per row; *paced*: one "
        "transaction at a time with a pause between them; *back-to-back*: the next as soon as the previous is "
        "delivered; *all-proposing*: every participant proposes, one in flight each; *concurrent*: every "
        f"participant proposes, {d.get('concurrency')} in flight each. Messages are counted between hosts by "
        "the transport; the failure-free count is n² + 4n − 6 (docs/oac.md). *same order*: every participant "
        "delivered exactly the step's committed transactions in one order.",
        "", machine_line(d.get("machine")), "", f"Thesis: {THESIS_AP1}.", "",
        *table(["n", "load", "tx", "propose→decide p50 / p90 / p99 (ms)", "decide→deliver p50 / p90 / p99 (ms)",
                "msgs/tx", "n²+4n−6", "tx/s", "same order"], rows),
    ]


def render_hostd_oac(d: Json, name: str) -> Lines:
    rows = [[r["hosts"], r["transactions"], f"{num(r['propose_to_decide_p50_ms'], 3)} / "
             f"{num(r['propose_to_decide_p90_ms'], 3)} / {num(r['propose_to_decide_p99_ms'], 3)}",
             num(r["hop_p50_ms"], 3), num(r["control_rpc_p50_ms"], 3), num(r["idle_cpu_percent_per_host"]),
             "yes" if r.get("same_delivered_hash") else "no"] for r in d["results"]]
    return [f"Measured {d.get('when', '')}. Units: {d.get('units', 'ms')}.", "", machine_line(d.get("machine")), "",
            *table(["hosts", "tx", "propose→decide p50 / p90 / p99 (ms)", "one hop p50 (ms)", "control RPC p50 (ms)",
                    "idle CPU per host (%)", "same order"], rows)]


def render_transport(d: Json, name: str) -> Lines:
    rows = [[r["variant"], f"{num(r['one_way_p50_ms'], 3)} / {num(r['one_way_p99_ms'], 3)}",
             f"{num(r['burst_msgs_per_s_median'])} / {num(r['burst_msgs_per_s_min'])}",
             f"{num(r['burst_one_way_p50_ms'], 3)} / {num(r['burst_one_way_p99_ms'], 3)}"] for r in d["results"]]
    return [f"Two processes on loopback, measured {d.get('when', '')}: {d.get('latency_samples')} one-way latency "
            f"samples {num(d.get('latency_gap_s', 0) * 1e3)} ms apart, then {d.get('bursts')} bursts of "
            f"{d.get('burst_size')} messages. `transport` is HAA's own link (a batched gRPC stream with sequence "
            "numbers and acknowledgements).", "", machine_line(d.get("machine")), "",
            *table(["variant", "one-way p50 / p99 (ms)", "burst msgs/s median / min", "burst one-way p50 / p99 (ms)"],
                   rows)]


AB_MODES = ["paced", "back-to-back", "all-proposing", "concurrent"]


def render_hostlink_ab(d: Json, name: str) -> Lines:
    med = d["medians"]
    carriers = list(med)
    rows = []
    for mode in AB_MODES:
        for key, label in [("p50_ms", "propose→decide p50 (ms)"), ("p99_ms", "p99 (ms)"), ("tx_per_s", "tx/s"),
                           ("cpu_ms_per_tx", "cluster CPU per tx (ms)"), ("oac_msgs_per_tx", "OAC messages per tx"),
                           ("frames_per_tx", "frames per tx")]:
            if all(mode in med[c] and key in med[c][mode] for c in carriers):
                rows.append([mode, label, *(num(med[c][mode][key], 3) for c in carriers)])
    loads = {c: span(med[c].get("load_1min", [])) for c in carriers}
    runs = {c: sum(1 for r in d["runs"] if r["carrier"] == c) for c in carriers}
    lines = [f"AP-1 at n = {d['hosts']} (static group, {d['transactions']} transactions per load), runs alternating "
             "carrier by carrier; medians of " + ", ".join(f"{runs[c]} {c} runs (1-minute load {loads[c]})"
                                                         for c in carriers) + ".", "",
             *table(["load", "metric", *(f"{c} link" for c in carriers)], rows)]
    idle = d.get("idle_runs") or {}
    if idle:
        lines += ["", "Idle cluster (`bench idle`, 10 hosts), CPU of all hosts, % of one core, each run: " + "; ".join(
            f"{c} " + " / ".join(num(r["local"]["cpu_percent_total"], 3) for r in idle[c]) for c in idle) + "."]
    for key, label in [("ddb_sequencer_32w_writes_per_s", "DDB all-writing through the sequencer, 32 writers per "
                        "host, committed writes/s"), ("ddb_sequencer_32w_p50_ms", "The same, write p50 (ms)"),
                       ("ddb_sequencer_8w_writes_per_s", "With 8 writers per host, writes/s")]:
        v = d.get(key)
        if v:
            lines += ["", f"{label}, alternating pairs: " + "; ".join(
                f"{c} " + " / ".join(num(x, 4) for x in v[c]) for c in v) + "."]
    ap4 = d.get("ap4_p50_ms_two_runs") or {}
    if ap4:
        keys = list(next(iter(ap4.values())))
        lines += ["", "AP-4 at 10 hosts, median ms of each of two runs:", "",
                  *table(["step", *(f"{c} link" for c in ap4)],
                         [[k, *(" / ".join(num(x) for x in ap4[c].get(k, [])) for c in ap4)] for k in keys])]
    return lines


def render_commit_goals(d: Json, name: str) -> Lines:
    med, goals = d["medians"], d.get("goals", {})
    carriers = list(med)
    rows = []
    for k, v in med[carriers[0]].items():
        if k in ("runs", "loads") or isinstance(v, list):
            continue
        rows.append([f"`{k}`", *(num(med[c].get(k), 4) for c in carriers), goals.get(k, "")])
    loads = {c: span(med[c].get("loads", [])) for c in carriers}
    return [f"{d['hosts']} hosts; each run, for one carrier: AP-1 (static group; paced, back-to-back, all-proposing, "
            "concurrent with 2 in flight per host), the DDB all-writing load through the sequencer (8 and 32 "
            "writers per host), `bench idle`, `bench ap4`; runs alternate carriers. Medians of "
            + ", ".join(f"{med[c].get('runs')} {c} runs (1-minute load before each part {loads[c]})" for c in carriers)
            + ". Times in ms unless the key says otherwise; `ap4.*` in ms; the goal column is the target set for "
            "the commit path.", "",
            *table(["metric", *(f"{c} link" for c in carriers), "goal"], rows)]


def render_lazy_ab(d: Json, name: str) -> Lines:
    ap1 = d["ap1_n10_5_alternating_runs"]
    variants = list(ap1)
    labels = {"base": "before", "fixed20": "held a fixed 20 ms", "quiet": "after (released when quiet)"}
    rows = []
    for mode in AB_MODES:
        for key, label in [("p50", "propose→decide p50 (ms)"), ("tps", "tx/s"),
                           ("cpu_ms_tx", "cluster CPU per tx (ms)"), ("frames_tx", "frames per tx"),
                           ("oac_msgs_tx", "OAC messages per tx")]:
            if all(mode in ap1[v] and key in ap1[v][mode] for v in variants):
                rows.append([mode, label, *(f"{num(ap1[v][mode][key]['median'])} ("
                                            + ", ".join(num(x) for x in ap1[v][mode][key]["runs"]) + ")"
                                            for v in variants)])
    lines = ["Lazy messages: the messages nobody waits for (rebroadcasts of decisions, order rebroadcasts, round "
             "estimates after a positive ack) travel in the next frame on the same link or once the host is quiet "
             "(docs/oac.md, \"Lazy messages\"). Runs alternate the code before and after; medians, each run in "
             "brackets. AP-1 at n = 10, static hosts:", "",
             *table(["load", "metric", *(labels.get(v, v) for v in variants)], rows)]
    med = d.get("medians", {})
    if med:
        sides = list(med)
        keys = [k for k in med[sides[0]] if any(med[s].get(k) is not None for s in sides)]
        lines += ["", "Group-level figures (10 membership-mode hosts; `ap4_*` in seconds; `ddb_*`: the all-writing "
                  "load through the sequencer):", "",
                  *table(["metric", *(labels.get(s, s) for s in sides)],
                         [[f"`{k}`", *(num(med[s].get(k), 4) for s in sides)] for k in keys])]
    prof = d.get("profile_before", {})
    if prof:
        flat = {k: v for k, v in prof.items() if not isinstance(v, dict) and k != "how"}
        lines += ["", f"Profile of the code before ({prof.get('how', 'py-spy')}), % of samples: "
                  + "; ".join(f"{k.removesuffix('_pct')} {v}" for k, v in flat.items()) + "."]
        for k, v in prof.items():
            if isinstance(v, dict):
                lines += ["", f"`{k}`: " + "; ".join(f"{kk} {num(vv)}" for kk, vv in v.items()) + "."]
    return lines


def _seq_rows(rows: list[Json]) -> list[list[Any]]:
    return [[r["writers_per_host"], num(r["writes_per_s"]), num(r["p50_ms"], 3), num(r["oac_p50_ms"], 3),
             num(r["writes_per_oac"], 3), num(r.get("msgs_per_oac"), 4), num(r.get("cluster_cores_in_load"), 3),
             num(r.get("leader_cores_in_load"), 3), num(r.get("cluster_other_threads_cores"), 2)] for r in rows]


SEQ_HEAD = ["writers per host", "writes/s", "write p50 (ms)", "OAC p50 (ms)", "writes per OAC", "msgs per OAC",
            "cluster cores", "leader cores", "cores in non-main threads"]


def render_seq_profile(d: Json, name: str) -> Lines:
    ab = d["seq_inflight_ab"]
    runs = ab["runs"]
    lines = [f"Fresh groups of 10 membership-mode hosts, the all-writing DDB load through the sequencer, carrier "
             "(`HAA_HOST_LINK`) × batches in flight (`membership: seq_inflight`), variants alternating run by run; "
             f"measured {d.get('date', '')}.", "",
             f"Medians of {len(runs) // max(1, len(ab['medians']) // 2)} runs per variant (variant = "
             "carrier:in flight:writers per host):", "",
             *table(["variant", "writes/s", "write p50 (ms)", "OAC p50 (ms)", "writes per OAC", "msgs per OAC",
                     "cluster cores", "leader cores", "cores in non-main threads"],
                    [[k, num(v["writes_per_s"]), num(v["p50_ms"], 3), num(v["oac_p50_ms"], 3),
                      num(v["writes_per_oac"], 3), num(v["msgs_per_oac"], 4), num(v["cluster_cores_in_load"], 3),
                      num(v["leader_cores_in_load"], 3), num(v["cluster_other_threads_cores"], 2)]
                     for k, v in ab["medians"].items()])]
    per: dict[str, list[str]] = {}
    for r in runs:
        for row in r["rows"]:
            key = f"{r['carrier']}:{r['seq_inflight']}:w{row['writers_per_host']}"
            per.setdefault(key, []).append(num(row["writes_per_s"]))
    lines += ["", "Writes/s of each run: " + "; ".join(f"{k} {' / '.join(v)}" for k, v in per.items()) + "."]
    for key, label in [("profiled_pair_seq_ab", "Profiled pair (py-spy on the leader)"),
                       ("profiled_pair_seq_ab_2", "Second profiled pair")]:
        if d.get(key):
            lines += ["", f"{label}:", "", *table(["carrier", "in flight", "load before", *SEQ_HEAD],
                                                  [[r["carrier"], r["seq_inflight"], num(r["load_1min_before"], 3), *c]
                                                   for r in d[key] for c in _seq_rows(r["rows"])])]
    burn = d.get("contention_10_burners")
    if burn:
        lines += ["", f"With CPU burners beside the cluster ({burn.get('what', '')}):", "",
                  *table(["carrier", "in flight", "load before", *SEQ_HEAD],
                         [[r["carrier"], r["seq_inflight"], num(r["load_1min_before"], 3), *c]
                          for r in burn["runs"] for c in _seq_rows(r["rows"])])]
    proc = d.get("haactl_bench_ddb_procedure")
    if proc:
        lines += ["", f"The same through `{proc['command']}`:", "",
                  *table(["run", "carrier", "load before", "writers per host", "writes/s", "OACs/s", "write p50 (ms)",
                          "OAC p50 (ms)"],
                         [[r["run"], r["carrier"], num(r["load_1min_before"], 3), row["writers"],
                           num(row["writes_per_s"]), num(row["oacs_per_s"]), num(row["p50_ms"], 3),
                           num(row["oac_p50_ms"], 3)] for r in proc["runs"] for row in r["rows"]])]
    prof = d.get("leader_profile_py_spy_gil_seq_inflight2_w32_3runs_merged")
    if prof:
        lines += ["", "The sequencer leader's own time (py-spy `--gil`, 3 runs merged, 2 batches in flight, 32 "
                  "writers per host), top frames and by layer:", ""]
        for text in prof.values():
            total = next((i for i, ln in enumerate(text) if ln.startswith("-- total time")), len(text))
            group = next((i for i, ln in enumerate(text) if ln.startswith("-- own time by")), len(text))
            lines += ["```", *text[:min(total, 14)], *text[group:], "```", ""]
        lines.pop()
    return lines


def render_seq_inflight_ab(d: Json, name: str) -> Lines:
    med = d["medians"]
    keys = list(next(iter(med.values())))
    return [f"{d['runs'][0]['hosts']} hosts × {d['runs'][0]['writers_per_host']} writers each, the all-writing DDB "
            f"load through the sequencer; one or two sequencer batches in flight, alternating, {len(d['runs'])} runs "
            f"in all, measured {d.get('date', '')} at 1-minute load "
            + " / ".join(num(x, 3) for x in d.get("load_avg_1min_during", [])) + ". Medians:", "",
            *table(["metric", *(f"`{k}`" for k in med)], [[k, *(num(med[s][k], 4) for s in med)] for k in keys]), "",
            "Each run:", "",
            *table(["seq_inflight", "writes/s", "write p50 (ms)", "OAC p50 (ms)", "writes per OAC", "msgs per OAC",
                    "failed"],
                   [[r["seq_inflight"], num(r["writes_per_s"]), num(r["p50_ms"], 3), num(r["oac_p50_ms"], 3),
                     num(r["writes_per_oac"], 3), num(r["msgs_per_oac"], 4), r["failed"]] for r in d["runs"]])]


def render_ddb(d: Json, name: str) -> Lines:
    rows = [[r["hosts"], "yes" if r.get("sequencer") else "no", r["clients"], r["through"], r["batch"],
             num(r["ops_per_s"]), num(r["requests_per_s"]), num(r["p50_ms"], 3), num(r["p99_ms"], 3), r["failed"]]
            for r in d["rows"] if r.get("load") != "all writing"]
    allw = [r for r in d["rows"] if r.get("load") == "all writing"]
    lines = [f"Each client writes `put(key, blob)` requests and waits for each to be committed and applied on its "
             f"host; {num(d.get('seconds'))} s per row.", "", machine_line(d.get("machine")), "",
             *table(["hosts", "sequencer", "clients", "writing through", "ops per request", "ops/s", "requests/s",
                     "p50 (ms)", "p99 (ms)", "failed"], rows)]
    if allw:
        lines += ["", "Every host writing at once:", "", *table(
            ["hosts", "sequencer", "writers per host", "writes/s", "writes per OAC", "p50 (ms)", "p99 (ms)"],
            [[r["hosts"], "yes" if r["sequencer"] else "no", r["writers_per_host"], num(r["writes_per_s"]),
              num(r["writes_per_oac"], 3), num(r["p50_ms"], 3), num(r["p99_ms"], 3)] for r in allw])]
    return lines


# ----- membership, allocation, agents (§7.2.2-7.2.4) ----------------------------------------------------------


def render_ap2(d: Json, name: str) -> Lines:
    def both(s: Json) -> str:
        return f"{ms(s.get('median'))} / {ms(s.get('max'))}" if s else "—"

    rows = [[r["hosts"], both(r["join"]), both(r["join_all"]), both(r["leave"]), both(r["remove"]),
             both(r["crash_to_removal"]), f"{r['join'].get('n', 0)} / {r['leave'].get('n', 0)} / "
             f"{r['crash_to_removal'].get('n', 0)}"] for r in d["rows"]]
    return [f"A group of real processes grows from 1 to 10 hosts; at each size hosts join (after leaving, after "
            f"crashing, and at first), leave and are killed, {d.get('reps')} repetitions each. Delays from the hosts' "
            "logs, process start-up excluded; median / max in ms. *removal*: from the first member's suspicion to "
            "the new view; *crash to removal*: from the kill (includes the failure detector).", "",
            machine_line(d.get("machine")), "", f"Thesis: {THESIS_AP2}.", "",
            *table(["hosts", "join", "join, all members", "leave", "removal after 1st suspicion", "crash to removal",
                    "samples join / leave / crash"], rows)]


def _grid(rows: list[Json], key: str, stat: str, digits: int = 3, sd: bool = False) -> Lines:
    hosts = sorted({r["hosts"] for r in rows})
    agents = sorted({r["agents"] for r in rows})
    cell = {(r["hosts"], r["agents"]): r.get(key) for r in rows}
    out = []
    for h in hosts:
        vals: list[Any] = [h]
        for a in agents:
            v = cell.get((h, a))
            if v is None:
                vals.append("")
            elif isinstance(v, dict):
                vals.append((num(v[stat], digits) + (f" ± {num(v['sd'], 2)}" if sd else "")) if v.get("n") else "n/a")
            else:
                vals.append(num(v, digits))
        out.append(vals)
    return table(["hosts \\ agents", *(str(a) for a in agents)], out)


def render_ap3(d: Json, name: str) -> Lines:
    lines = [f"Mode `{d.get('mode')}`: loopback delays fitted to the transport, OAC latency from AP-1, the real "
             f"CPU time of every `Allocator` call; {d.get('reps')} sessions per cell, seed {d.get('seed')}. From "
             "OAC(start) to the committed OAC(finish), ms, mean ± sd:", "", *_grid(d["rows"], "allocated_ms", "mean",
                                                                                 sd=True),
             "", "Bid-update messages per session, mean:", "", *_grid(d["rows"], "bid_messages", "mean"), "",
             f"Thesis: {THESIS_AP3}."]
    real = d.get("real")
    if real:
        lines += ["", f"On real local hosts (`--real`, idle agents, {real.get('reps')} forced sessions per cell): "
                  "from the session's start to the finish applied on every host, ms, median:", "",
                  *_grid(real["rows"], "allocated_ms", "median"), "", "Bid-update messages per session, mean:", "",
                  *_grid(real["rows"], "bid_messages", "mean"), "",
                  "CPU of all haa-hostd processes per session, ms, median:", "",
                  *_grid(real["rows"], "hostd_cpu_ms", "median"), "", machine_line(real.get("machine"))]
    return lines


def render_alloc_quality(d: Json, name: str) -> Lines:
    rows = [[f"{regime} ({q['instances']})", q["rated"], num(q["mean_ratio"], 3), num(q["median_ratio"], 3),
             num(q["p10_ratio"], 3), num(q["min_ratio"], 3), pct(q["optimal_share"]), num(q["aggregate_ratio"], 3),
             num(q["mean_messages"], 3), num(q["mean_time_ms"], 3)] for regime, q in d["regimes"].items()]
    return [f"{d['instances']} random instances per regime (seeds from {d.get('first_seed')}): total reward "
            "(eq. 4.7-1) of the committed allocation over the exhaustive optimum.", "",
            *table(["regime (instances)", "rated", "mean ratio", "median", "p10", "min", "optimal", "Σ R / Σ R*",
                    "messages", "time (ms)"], rows)]


AP4_COLUMNS = [("spawn", "spawn"), ("freeze", "freeze"), ("transfer", "transfer"),
               ("transfer_unreachable", "unreachable in transfer"), ("transfer_idle", "transfer, no traffic"),
               ("recovery", "recovery after detection"), ("host_recovery", "host crash: recovery after removal"),
               ("host_removal", "host crash: kill → removed")]


def render_ap4(d: Json, name: str) -> Lines:
    rows: list[list[Any]] = [["thesis (L1653)", *(THESIS_AP4.get(k, "—") for k, _ in AP4_COLUMNS), ""]]
    for r in d["rows"]:
        cells: list[Any] = [r["hosts"]]
        for k, _ in AP4_COLUMNS:
            s = r["summary"].get(k) or {}
            cells.append(f"{ms(s.get('median'))} / {ms(s.get('p90'))}" if s.get("n") else "—")
        cells.append(str((r["summary"].get("transfer") or {}).get("n", "")))
        rows.append(cells)
    state = d["rows"][0].get("state_bytes") if d["rows"] else None
    return [f"Real local hosts, an agent with {num(state)} bytes of state, {d.get('reps')} repetitions per row; "
            "median / p90 in ms from the hosts' timeline events. *transfer*: move request to thawed on the new host, "
            "while a prober pings the agent; *unreachable*: the longest gap in the prober's replies; *recovery*: from "
            "the crash report to recovered after a SIGKILL of the agent; *host crash*: SIGKILL of a haa-hostd. A "
            "group of two cannot recover from a host crash with a transaction in flight.", "",
            machine_line(d.get("machine")), "",
            *table(["hosts", *(label for _, label in AP4_COLUMNS), "samples"], rows)]


def render_agents(d: Json, name: str) -> Lines:
    steps = [("spawn → Hello", "spawn_to_hello_s"), ("spawn → Ready", "spawn_to_ready_s"),
             ("freeze → Frozen", "freeze_to_frozen_s"), ("spawn + thaw → Ready", "spawn_thaw_to_ready_s"),
             ("kill -9 → Failed", "kill9_to_failed_s")]
    rows = []
    for r in d["rows"]:
        for label, key in steps:
            s = r.get(key) or {}
            if s.get("n"):
                rows.append([r["mode"], r["agents"], label, num(s["median"] * 1e3, 3), num(s["p90"] * 1e3, 3),
                             num(s["max"] * 1e3, 3), s["n"]])
    mem = [[r["mode"], num(r["forkserver_start_s"] * 1e3 if r.get("forkserver_start_s") else None, 3),
            num(r.get("rss_mib_mean"), 3), num(r.get("uss_mib_mean"), 3)] for r in d["rows"]]
    tput = [[t["count"], t["size"], num(t["msgs_per_s"]), num(t["mib_per_s"], 3)] for t in d.get("throughput", [])]
    return ["The agent runtime alone (supervisors wired in one process, no group): each step's delay in ms.", "",
            machine_line(d.get("machine")), "",
            *table(["mode", "agents", "step", "median", "p90", "max", "samples"], rows), "",
            *table(["mode", "fork server start (ms)", "RSS MiB per agent", "USS MiB per agent"], mem), "",
            "Agent → host → agent on one supervisor:", "",
            *table(["messages", "bytes each", "msgs/s", "MiB/s"], tput)]


# ----- JC-SLAM (§7.2.5) ---------------------------------------------------------------------------------------

AP51_ORDER = [("baseline", "unlimited")] + [(s, c) for c in ("nominal", "constrained")
                                            for s in ("discard", "jcslam", "fifo", "random", "nfp", "delay")]


def render_ap51(d: Json, name: str) -> Lines:
    rows = d["rows"]
    ps = d["particles"] if isinstance(d["particles"], list) else [d["particles"]]
    parts = sorted({r["n_particles"] for r in rows})
    ps = [p for p in ps if p in parts] + [p for p in parts if p not in ps]
    lines = ["Recordings of the three teams of Table 7.2-1 from `haa-sim`, replayed through every SLAM strategy at "
             "nominal and constrained processing capacity. Localization error [m], mean ± std over seeds (each "
             "seed's error is the mean over all weight requests of all avatars); processed share, out-of-order "
             "share and mean delay pooled over particle counts.", "", machine_line(d.get("machine"))]
    for key, info in d["scenarios"].items():
        mine = [r for r in rows if r.get("scenario_key", key) == key and r["scenario"] == info["name"]]
        seeds = sorted({r["seed"] for r in mine})
        unc, _ = mean_pstd([r["uncorrected_error_m"] for r in mine])
        th = THESIS_AP51.get(info["name"])
        thesis = (f"; thesis (Table 7.2-1, L1670-1674): {th[0]}, {th[1]} min, uncorrected {num(th[2], 3)} m"
                  if th else "")
        lines += ["", f"**{info['name']}** ({info['team']}, {info['arena']} arena, {num(info['duration_s'])} s "
                  f"recorded; {len(seeds)} seeds; uncorrected (dead-reckoning) error {num(unc, 3)} m{thesis}):", ""]
        out = []
        for strat, cond in AP51_ORDER:
            sel = [r for r in mine if r["strategy"] == strat and r["condition"] == cond]
            if not sel:
                continue
            cells: list[Any] = [strat, cond]
            for n in ps:
                m, s = mean_pstd([r["loc_error_m"] for r in sel if r["n_particles"] == n])
                cells.append(f"{num(m, 3)} ± {num(s, 2)}" if m is not None else "—")
            proc, _ = mean_pstd([r["processed_share"] for r in sel])
            ooo, _ = mean_pstd([r["ooo_share"] for r in sel])
            dly, _ = mean_pstd([r["mean_delay_s"] for r in sel])
            acc, _ = mean_pstd([r["map_accuracy"] for r in sel])
            cells += [pct(proc), pct(ooo, 1), num(dly, 3), num(acc, 3)]
            out.append(cells)
        lines += table(["strategy", "capacity", *(f"N = {n}" for n in ps), "processed", "out of order",
                        "delay (s)", "map accuracy"], out)
    return lines


def command_ap51(d: Json, name: str) -> str:
    notes = [n for n in d.get("notes", []) if "`haactl" in n]
    if notes:
        return "; ".join(re.findall(r"`([^`]+)`", " ".join(notes)))
    return "haactl bench ap5.1" + (" --quick" if d.get("quick") else "")


def render_ap52(d: Json, name: str) -> Lines:
    rows = []
    for r in d["rows"]:
        th = THESIS_AP52.get(r["scenario"])
        rows.append([r["scenario"], r["team"], f"{num(r['request_period_s'])} s", r["n_particles"], num(r["M"], 3),
                     ", ".join(num(x) for x in r["standard_cost"]), ", ".join(num(x) for x in r["jcslam_cost"]),
                     pct(r["savings_counted"]), f"{num(th[0])} → {th[1]}" if th else "—"])
    return ["Operations saved by delayed weight updates (strategy 1): M observations between weight updates, the "
            "standard cost (MN ×, MN +, MN /) against JC-SLAM's (MN ×, N +, N /), counted over the run; thesis "
            "Table 7.2-3 (L1743-1747).", "", machine_line(d.get("machine")), "",
            *table(["team", "avatars", "weight request period", "N", "M", "standard cost", "JC-SLAM cost", "saved",
                    "thesis M → saved"], rows)]


def render_slam(d: Json, name: str) -> Lines:
    rows = [[r["particles"], num(r["sonar_per_s"]), num(r["landmark_per_s"]), num(r["cooccupancy_per_s"]),
             num(r["all_readings_per_s"]), num(r["predictions_per_s"]), num(r["requests_per_s"]),
             num(r["memory_mb_per_hour_at_1hz"], 3), r.get("resamples")] for r in d["rows"]]
    return [f"The JC-SLAM library alone on one core (thread CPU time); workload: {d.get('source', '')}; readings "
            + ", ".join(f"{k} {v}" for k, v in d.get("readings", {}).items()) + ". Readings per CPU-second; history "
            "memory per avatar-hour at one prediction per second.", "", machine_line(d.get("machine")), "",
            f"Thesis: {THESIS_SLAM}; {THESIS_SLAM_MEMORY}.", "",
            *table(["particles", "sonar/s", "landmark/s", "co-occupancy/s", "all readings/s", "predictions/s",
                    "weight requests/s", "MB per avatar-hour", "resamples"], rows)]


# ----- the simulator, the failure detector, costs ------------------------------------------------------------


def render_sim(d: Json, name: str) -> Lines:
    step = [["physics, odometry, sonar and detections at 1 Hz" if s["sensors"] else "physics and odometry",
             s["avatars"], num(s["sim_seconds"]), num(s["cpu_s"], 3), f"{num(s['x_realtime_cpu'], 3)}×",
             f"{num(s['x_realtime_wall'], 3)}×"] for s in d["stepping"]]
    cam = [[c["arena"], c["camera"], c["size"], f"{num(c['render_cpu']['mean_ms'], 3)} / "
            f"{num(c['render_cpu']['p95_ms'], 3)}", num(c["png_cpu"]["mean_ms"], 3), num(c["aruco_cpu"]["mean_ms"], 3),
            f"{num(c['recall'], 3)} ({c['markers_found']}/{c['markers_expected']})"] for c in d["camera"]]
    s = d["sensors"]
    sens = [["sonar scan, all sonars", num(s["sonar_scan_cpu"]["mean_ms"], 3), num(s["sonar_scan_cpu"]["p95_ms"], 3)],
            ["one sonar", num(s["sonar_per_sonar_cpu_ms"], 3), ""],
            ["landmark detections of one camera", num(s["landmarks_cpu"]["mean_ms"], 3),
             num(s["landmarks_cpu"]["p95_ms"], 3)]]
    return ["CPU time on one core.", "", machine_line(d.get("machine")), "",
            *table(["stepping (large arena)", "avatars", "simulated s", "CPU s", "× real time (CPU)",
                    "× real time (wall)"], step), "",
            *table(["arena", "camera", "frame", "render mean / p95 (ms)", "PNG (ms)", "ArUco (ms)", "ArUco recall"],
                   cam), "",
            *table([f"reading ({s.get('arena', '')} arena, {s.get('avatars_in_world', '')} avatars)", "mean (ms)",
                    "p95 (ms)"], sens)]


def _t(x: float) -> str:
    if math.isinf(x):
        return "no mistake"
    if x >= 86400:
        return f"{num(x / 86400, 3)} d"
    if x >= 3600:
        return f"{num(x / 3600, 3)} h"
    return f"{num(x, 3)} s"


def render_ufd(d: Json, name: str) -> Lines:
    rates = [[r["qos"], num(r["p_loss"]), num(r["delay_std_ms"]), num(r["eta_s"], 4), num(r["alpha_s"], 4),
              num(r["heartbeats_per_minute"], 3)] for r in d["rates"]]
    meas = [[m["label"], m["delay"], _t(m["horizon"]), num(m["heartbeats_per_minute"], 3), m["mistakes"],
             f"{_t(m['mean_tmr'])} (≥ {_t(m['tmr_lower'])})", f"{num(m['mean_tm'] * 1e3, 3)} ms (≤ "
             f"{num(m['tm_upper'] * 1e3, 3)} ms)", num(m["query_accuracy"], 6),
             f"{num(m['max_detection'], 4)} / {num(m['detection_bound'], 4)} s", "yes" if m["meets_targets"] else "NO"]
            for m in d["measured"]]
    return ["The real Alg. 1 objects (adaptive re-configuration on) driven through simulated networks for hours to "
            f"weeks of virtual time ({num(d.get('seconds'), 3)} s of CPU for the whole run).", "",
            f"Thesis: {THESIS_UFD}.", "", "Configured heartbeat period η and timeout shift α for each QoS (T_D^U, "
            "T_MR^L, T_M^U), loss p_L and delay spread σ(D):", "",
            *table(["QoS", "p_L", "σ(D) (ms)", "η (s)", "α (s)", "heartbeats/min per pair"], rates), "",
            "Measured (crash trials and mistakes over the horizon):", "",
            *table(["case", "delay", "horizon", "heartbeats/min", "mistakes", "E(T_MR)", "E(T_M)", "P_A",
                    "max T_D / T_D^U + E(D)", "targets met"], meas)]


def render_idle(d: Json, name: str) -> Lines:
    rows = []
    for kind, r in d.items():
        if not isinstance(r, dict) or "cpu_percent_total" not in r:
            continue
        rows.append([kind, r["hosts"], num(r["seconds"], 3), num(r["cpu_percent_total"], 3),
                     num(r["cpu_percent_of_machine"], 3), f"{num(r['cpu_percent_host_min'], 3)} / "
                     f"{num(r['cpu_percent_host_max'], 3)}", num(r["rss_mib_mean"], 3),
                     num(r.get("heartbeats_per_s_per_pair"), 3), num(r.get("tx_frames_per_s_per_host"), 3),
                     num(r.get("formed_seconds"), 3), r.get("measured_at", "")])
    return ["An idle membership-mode cluster: CPU of all hosts as % of one core, memory per host.", "",
            *table(["cluster", "hosts", "seconds", "CPU total (% of one core)", "% of the machine",
                    "per host min / max", "RSS MiB per host", "heartbeats/s per pair", "frames/s per host",
                    "formed in (s)", "measured at"], rows)]


def render_memory(d: Json, name: str) -> Lines:
    hosts = [[n, num(h["rss_start_mib"], 4), num(h["rss_peak_mib"], 4), num(h["rss_end_of_traffic_mib"], 4),
              num(h["rss_after_settle_mib"], 4), num(h["loop_lag_max_ms"]), num(h["loop_stalls_over_250ms"])]
             for n, h in d["hosts"].items()]
    steps = [[n, s["count"], s["failed"], num(s["max_stall_ms"]), num(s["max_stall_cpu_ms"]), num(s["max_seconds"], 3),
              "; ".join(s.get("errors", []))] for n, s in d["steps"].items()]
    limits = ", ".join(f"{k} {num(v)} B" for k, v in d.get("limits", {}).items())
    return [f"{num(d['seconds'] / 60, 3)} minutes of the largest requests the limits accept ({d.get('requests')} "
            f"requests in {d.get('rounds')} rounds; limits: {limits}), then {num(d.get('settle'))} s to settle. "
            f"Largest event-loop stall {num(d.get('largest_stall_ms'))} ms, of it {num(d.get('largest_stall_cpu_ms'))} "
            "ms busy (CPU).", "", machine_line(d.get("machine")), "",
            *table(["host", "RSS start (MiB)", "peak", "end of traffic", "after settle", "max loop lag (ms)",
                    "stalls > 250 ms"], hosts), "",
            *table(["request", "count", "failed", "largest stall (ms)", "of it CPU (ms)", "slowest (s)", "errors"],
                   steps)]


def render_dashboard(d: Json, name: str) -> Lines:
    rows = []
    for obj in ("map", "estimate"):
        for key, label in [("commit_to_paint", "commit → painted"), ("write_to_paint", "write call → painted"),
                           ("commit", "write call → committed")]:
            s = d.get(obj, {}).get(key)
            if s:
                rows.append([obj, label, num(s["p50"], 3), num(s["p95"], 3), num(s["max"]), num(s["mean"], 3), s["n"]])
    return [f"{d.get('hosts')} hosts, {d.get('agents')} agents, a {d.get('grid')} occupancy grid; {d.get('rounds')} "
            f"changes of each kind written through {d.get('writer')}; the page in headless Chromium "
            f"({d.get('agents_on_page')} agents on the page, {len(d.get('page_errors', []))} page errors).", "",
            machine_line(d.get("machine")), "",
            *table(["object", "interval", "p50 (ms)", "p95 (ms)", "max (ms)", "mean (ms)", "samples"], rows)]


def render_restructure_ab(d: Json, name: str) -> Lines:
    rows = [[r["metric"], num(r["before_median"], 4), num(r["after_median"], 4), f"{num(r['change_percent'], 3)} %",
             f"{num(r['spread_percent_before'], 3)} / {num(r['spread_percent_after'], 3)} %",
             num(r["pair_ratio_median"], 3), "yes" if r["within_10_percent"] else "no"]
            for r in d["summary_primary_3_runs"]]
    n_all = {len(r["before_runs"]) for r in d.get("summary_all_runs", [])}
    return [f"Before = `{d['before_commit'][:7]}`, after = `{d['after_commit'][:7]}`, run alternately with the same "
            f"benchmark commands; {len(d.get('runs', []))} benchmark runs in all. Medians of the 3 primary "
            "alternating runs; spread is the file's `spread_percent` of each side; pair ratio is the median of after / "
            f"before over runs taken side by side (up to {max(n_all) if n_all else 0} runs per side in the file's "
            "`summary_all_runs`).",
            "", *table(["metric", "before", "after", "change", "spread before / after", "pair ratio", "within 10 %"],
                       rows)]


def command_restructure_ab(d: Json, name: str) -> str:
    seen: list[str] = []
    for r in d.get("runs", []):
        m = re.search(r"haactl\.main (bench [^(]+?)\s*(\(|$)", r.get("command", ""))
        if m and f"haactl {m.group(1)}" not in seen:
            seen.append(f"haactl {m.group(1)}")
    return "; ".join(seen) + " — alternately on the two trees"


# ----- unknown files -----------------------------------------------------------------------------------------


def render_generic(d: Any, name: str) -> Lines:
    if not isinstance(d, dict):
        return [f"A JSON {type(d).__name__} of {len(d) if hasattr(d, '__len__') else 1} items; no section layout "
                "is known for this file yet (add one to haa/lab/results.py)."]
    scalars = [[f"`{k}`", num(v)] for k, v in d.items() if not isinstance(v, dict | list)]
    nested = [f"`{k}` ({type(v).__name__} of {len(v)})" for k, v in d.items() if isinstance(v, dict | list)]
    lines = ["No section layout is known for this file yet (add one to haa/lab/results.py); its top-level "
             "fields:", ""]
    lines += table(["field", "value"], scalars) if scalars else ["(no scalar fields)"]
    if nested:
        lines += ["", "Also holds: " + ", ".join(nested) + "."]
    return lines


# ----- the page -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Known:
    part: str
    title: str
    render: Callable[[Json, str], Lines]
    command: str | Callable[[Json, str], str]


PARTS = [
    ("missions", "The robot team's missions (thesis §7.1, §7.3)"),
    ("commit", "Atomic commit, transport and the DDB (thesis §7.2.1)"),
    ("group", "Membership, allocation and agents (thesis §7.2.2-7.2.4)"),
    ("slam", "JC-SLAM (thesis §7.2.5)"),
    ("parts", "The failure detector, the simulator and running costs"),
    ("other", "Other results"),
]

KNOWN: dict[str, Known] = {
    "af1": Known("missions", "Exploration and mapping, AF-1 (Table 7.1-1)", render_mission, command_experiment),
    "af1-frontier": Known("missions", "Exploration and mapping with coordinated frontiers (AF-1 set-up)",
                          render_mission, command_experiment),
    "af1-cruise0.2": Known("missions", "Exploration and mapping at eight times the cruise speed (AF-1 set-up)",
                           render_mission, command_experiment),
    "af2": Known("missions", "Congregation, AF-2 (Table 7.1-2)", render_mission, command_experiment),
    "r1": Known("missions", "Agent failure, R-1 (Table 7.3-1)", render_r1, command_r1),
    "ap1": Known("commit", "Ordered atomic commit on real processes, AP-1", render_ap1, "haactl bench ap1"),
    "hostd_oac_latency": Known("commit", "One commit and one hop inside haa-hostd (2-3 hosts)", render_hostd_oac,
                               ".venv/bin/python -m haa.lab.bench.hostd_oac_latency"),
    "transport": Known("commit", "Host link: gRPC stream against unary calls", render_transport,
                       ".venv/bin/python -m haa.lab.bench.transport_stream_vs_unary"),
    "hostlink-ab": Known("commit", "Commit cost per host-link carrier: gRPC stream against plain TCP",
                         render_hostlink_ab, ".venv/bin/python -m haa.lab.bench.hostlink_ab --runs 3 --hosts 10 "
                         "-n 100 --out bench-results/hostlink-ab.json"),
    "issue14-final": Known("commit", "Commit-path goals per host-link carrier (10 hosts)", render_commit_goals,
                           "flock /tmp/haa-bench.lock env .venv/bin/python -m haa.lab.bench.carriers "
                           "--runs 3 --out bench-results/issue14-final.json"),
    "issue14-ab": Known("commit", "Lazy OAC messages, before and after (10 hosts)", render_lazy_ab,
                        "alternate the two trees with `haactl bench ap1 --hosts 10 --min-hosts 10 -n 200`, "
                        "`haactl bench idle --hosts 10`, `haactl bench ap4 --hosts 10 --reps 3`, "
                        "`haactl bench ddb --hosts 10 --all-writing`"),
    "issue14-seq-profile": Known("commit", "The sequencer leader profiled: carriers and batches in flight (10 hosts)",
                                 render_seq_profile, ".venv/bin/python -m haa.lab.bench.seq_ab --hosts 10 "
                                 "--writers 32 --writers 8 --variant grpc:2 --variant grpc:1 --variant tcp:2 "
                                 "--variant tcp:1 --runs 3 --out bench-results/issue14-seq-profile.json "
                                 "(`--profile DIR` for py-spy)"),
    "ddb-seq-inflight-ab": Known("commit", "Sequencer batches in flight, one against two (5 hosts)",
                                 render_seq_inflight_ab, "`haactl bench ddb --hosts 5 --all-writing --sequencer on` "
                                 "with `membership: seq_inflight: 1` or `2` in the hosts' hostd.yaml, alternating"),
    "ddb": Known("commit", "DDB writes: batching and clients", render_ddb, "haactl bench ddb"),
    "ap2": Known("group", "Join, leave and removal, AP-2", render_ap2, "haactl bench ap2"),
    "ap3": Known("group", "Time to allocation consensus, AP-3", render_ap3,
                 "haactl bench ap3; haactl bench ap3 --real"),
    "alloc_quality": Known("group", "Allocation quality against the exhaustive optimum", render_alloc_quality,
                           "haactl bench alloc-quality"),
    "ap4": Known("group", "Spawn, freeze, transfer and recovery delays, AP-4", render_ap4, "haactl bench ap4"),
    "agents": Known("group", "The agent runtime: spawn, freeze, kill and message throughput", render_agents,
                    "haactl bench agents"),
    "ap5.1": Known("slam", "SLAM strategies at nominal and constrained capacity, AP-5.1", render_ap51, command_ap51),
    "ap5.1-quick": Known("slam", "SLAM strategies on short recordings, AP-5.1 quick", render_ap51, command_ap51),
    "ap5.2": Known("slam", "Operations saved by delayed weight updates, AP-5.2 (Table 7.2-3)", render_ap52,
                   "haactl bench ap5.2"),
    "slam": Known("slam", "JC-SLAM library speed and history memory", render_slam, "haactl bench slam"),
    "ufd": Known("parts", "Failure detector QoS and heartbeat cost", render_ufd, "haactl bench ufd"),
    "sim": Known("parts", "Avatar simulator speed: stepping, camera frames, sonar", render_sim, "haactl bench sim"),
    "idle": Known("parts", "Idle cost of a 10-host cluster, processes and containers", render_idle,
                  "haactl bench idle --hosts 10 --duration 60; haactl bench idle --hosts 10 --duration 60 --compose"),
    "memory": Known("parts", "Memory and event-loop stalls under maximum-size requests", render_memory,
                    "haactl bench memory"),
    "dashboard": Known("parts", "Dashboard: commit to painted page", render_dashboard,
                       ".venv/bin/python -m haa.lab.bench.dashboard_latency"),
    "issue17-ab": Known("parts", "Before and after splitting the core and the runtime into machines (AP-1, AP-2, "
                        "AP-4, idle)", render_restructure_ab, command_restructure_ab),
}


def slug(title: str) -> str:
    """GitHub's anchor for a heading."""
    s = re.sub(r"[^\w\- ]", "", title.lower())
    return s.replace(" ", "-")


def load(results: Path) -> dict[str, Any]:
    return {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}


def section(name: str, data: Any) -> tuple[str, str, Lines]:
    """(part, title, body lines) of one file's section."""
    k = KNOWN.get(name)
    if k is None:
        return "other", f"`{name}.json`", [f"Source: `bench-results/{name}.json`.", "", *render_generic(data, name)]
    try:
        body = k.render(data, name)
        cmd = k.command if isinstance(k.command, str) else k.command(data, name)
    except (KeyError, TypeError, IndexError, ValueError, AttributeError, ZeroDivisionError) as exc:
        raise RuntimeError(f"bench-results/{name}.json does not have the shape haa/lab/results.py expects: "
                           f"{type(exc).__name__}: {exc}") from exc
    cmd_text = cmd if "`" in cmd else f"`{cmd}`"
    head = f"Source: `bench-results/{name}.json`. Reproduce: {cmd_text}."
    body = [ln for i, ln in enumerate(body) if ln or (i and body[i - 1])]  # no double blank lines
    return k.part, k.title, [head, "", *body]


def generate(results: Path = RESULTS_DIR) -> str:
    files = load(results)
    sections = {name: section(name, data) for name, data in files.items()}
    order = [n for n in KNOWN if n in sections] + sorted(n for n in sections if n not in KNOWN)
    out = [
        "# Results",
        "",
        "<!-- Generated by `python -m haa.lab.results` (`make results`) from bench-results/*.json. Do not edit: "
        "`make test` fails when this page and the JSON files disagree. -->",
        "",
        "Every measured number on this page is read from the JSON file its section names (`bench-results/`), "
        "written by the command the section gives. The thesis' values stand beside ours where the thesis has "
        "them, with the line of the thesis text they come from (L*n*). Timings were taken on the shared machine "
        "each section describes, beside other jobs: single runs scatter, and the A/B sections alternate their "
        "variants run by run for that reason. What the numbers led to, and when, is in CHANGELOG.md.",
        "",
    ]
    for part, heading in PARTS:
        names = [n for n in order if sections[n][0] == part]
        if not names:
            continue
        out.append(f"* {heading}")
        out += [f"  * [{sections[n][1]}](#{slug(sections[n][1])})" for n in names]
    for part, heading in PARTS:
        names = [n for n in order if sections[n][0] == part]
        if not names:
            continue
        out += ["", f"## {heading}"]
        for n in names:
            _part, title, body = sections[n]
            out += ["", f"### {title}", "", *body]
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m haa.lab.results", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the page differs from what would be written")
    ap.add_argument("--results", type=Path, default=RESULTS_DIR, help="the JSON files (default bench-results/)")
    ap.add_argument("--out", type=Path, default=PAGE, help="the page (default docs/results.md)")
    args = ap.parse_args(argv)
    text = generate(args.results)
    if args.check:
        old = args.out.read_text() if args.out.exists() else ""
        if old == text:
            print(f"{args.out} is up to date with {args.results}/*.json")
            return 0
        diff = list(difflib.unified_diff(old.splitlines(), text.splitlines(), str(args.out), "generated", lineterm=""))
        print(f"{args.out} differs from what {args.results}/*.json give ({len(diff)} diff lines); run `make results` "
              "(python -m haa.lab.results) and commit the page. First lines of the diff:", file=sys.stderr)
        print("\n".join(diff[:40]), file=sys.stderr)
        return 1
    args.out.write_text(text)
    print(f"wrote {args.out} ({len(text.splitlines())} lines, {len(load(args.results))} result files)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
