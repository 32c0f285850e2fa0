"""Atomic commit, the host link and the DDB (thesis §7.2.1): AP-1 and the commit path's benchmarks."""

from __future__ import annotations

from typing import Any

from haa.lab.results.common import (
    THESIS_AP1,
    Json,
    Lines,
    machine_line,
    mean_std,
    num,
    span,
    table,
)

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




def render_write_path_ab(d: Json, name: str) -> Lines:
    trees = d["trees"]
    lines = [f"{d['hosts']} membership-mode hosts, every host writing at once (`DdbLoad`: writers inside each host, "
             f"single-put writes, {num(d['seconds'])} s per row), through the sequencer; the trees alternating run by "
             f"run, measured {d['date']} on {d['cores']} cores. Mean ± STD over the runs:", "",
             *(f"* `{k}`: {v}" for k, v in trees.items()), ""]
    rows = []
    for w in sorted({r["writers_per_host"] for r in d["ddb_runs"]}):
        for t in trees:
            rs = [r for r in d["ddb_runs"] if r["tree"] == t and r["writers_per_host"] == w]
            if rs:
                rows.append([w, f"`{t}`", len(rs), mean_std([r["writes_per_s"] for r in rs], 0),
                             mean_std([r["p50_ms"] for r in rs], 1), mean_std([r["writes_per_oac"] for r in rs], 1),
                             mean_std([r["cpu_per_write_ms"] for r in rs], 3)])
    lines += table(["writers per host", "tree", "runs", "writes/s", "write p50 (ms)", "writes per OAC",
                    "cluster CPU per write (ms)"], rows)
    ap1 = d.get("ap1_runs", [])
    if ap1:
        lines += ["", f"`haactl bench ap1` on the same trees (static mode: OAC among the hosts, not the DDB path; "
                  f"{len({r['run'] for r in ap1})} runs of each, alternating), propose→decide p50 (ms), mean ± STD:",
                  ""]
        keys = sorted({(r["n"], r["load"]) for r in ap1}, key=lambda k: (k[0], k[1]))
        ts = [t for t in trees if any(r["tree"] == t for r in ap1)]
        lines += table(["n", "load", *(f"`{t}`" for t in ts)],
                       [[n, load, *(mean_std([r["p50_ms"] for r in ap1 if r["tree"] == t and r["n"] == n
                                             and r["load"] == load], 2) for t in ts)] for n, load in keys])
    return lines
