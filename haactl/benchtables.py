"""How `haactl bench` shows each experiment's results: the markdown tables printed after a run (and pasted
into the docs and the README), laid out from the row dicts that the experiments of haa.lab.experiments return
(the same dicts `bench-results/<name>.json` holds). Every table is built with haactl.tables (one helper);
this module only chooses the columns and formats the numbers.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from haactl.tables import Cell, markdown, table

if TYPE_CHECKING:  # the experiments are imported by the table that needs them: `haactl --help` stays quick
    from haa.lab.dsim.ufdqos import QosMeasurement


def _md(headers: list[str], rows: list[list[Cell]], title: str | None = None) -> str:
    return markdown(table(headers, rows, title=title))


# ----- ufd (Alg. 1) -------------------------------------------------------------------------------------------


def fmt_time(x: float) -> str:
    if math.isinf(x):
        return "no mistake"
    if x >= 86400:
        return f"{x / 86400:.1f} d"
    if x >= 3600:
        return f"{x / 3600:.1f} h"
    return f"{x:.1f} s"


def ufd_rates(rates: list[dict[str, Any]]) -> str:
    return _md(
        ["QoS (T_D^U, T_MR^L, T_M^U)", "p_L", "σ(D)", "η", "α", "heartbeats/min"],
        [[r["qos"], f"{r['p_loss']:g}", f"{r['delay_std_ms']:g} ms", f"{r['eta_s']:.3f} s", f"{r['alpha_s']:.3f} s",
          f"{r['heartbeats_per_minute']:.1f}"] for r in rates],
    )


def ufd_measured(measured: list[QosMeasurement]) -> str:
    return _md(
        ["case", "horizon", "η (final)", "hb/min", "mistakes", "E(T_MR) ≥ T_MR^L?", "E(T_M) ≤ T_M^U?", "P_A",
         "max T_D / (T_D^U + E(D))", "targets met"],
        [[m.label, fmt_time(m.horizon), f"{m.eta:.3f} s", f"{m.heartbeats_per_minute:.1f}", m.mistakes,
          f"{fmt_time(m.mean_tmr)} vs {fmt_time(m.tmr_lower)}",
          f"{m.mean_tm * 1e3:.0f} ms vs {m.tm_upper * 1e3:.0f} ms", f"{m.query_accuracy:.6f}",
          f"{m.max_detection:.3f} / {m.detection_bound:.3f} s", "yes" if m.meets_targets else "NO"]
         for m in measured],
    )


# ----- AP-1 (§7.2.1) ------------------------------------------------------------------------------------------


def ap1(rows: list[dict[str, Any]]) -> str:
    out: list[list[Cell]] = []
    for r in rows:
        pd, dd = r["propose_to_decide_ms"], r["decide_to_deliver_ms"]
        out.append([r["participants"], r["mode"], r["transactions"],
                    f"{pd['p50']:.2f} / {pd['p90']:.2f} / {pd['p99']:.2f}",
                    f"{dd['p50']:.3f} / {dd['p90']:.3f} / {dd['p99']:.3f}", f"{r['messages_per_tx']:.1f}",
                    r["formula_n2_4n_minus_6"], f"{r['throughput_tx_per_s']:.0f}"])
    return _md(["n", "load", "tx", "propose→decide p50 / p90 / p99 (ms)", "decide→deliver p50 / p90 / p99 (ms)",
                "msgs/tx", "n²+4n−6", "tx/s"], out)


# ----- idle cost ----------------------------------------------------------------------------------------------


def idle(kind: str, r: dict[str, Any]) -> str:
    return _md(
        ["cluster", "hosts", "CPU total (% of one core)", "per host min / max", "% of the machine", "RSS MiB/host"],
        [[kind, r["hosts"], f"{r['cpu_percent_total']:.1f}",
          f"{r['cpu_percent_host_min']:.2f} / {r['cpu_percent_host_max']:.2f}", f"{r['cpu_percent_of_machine']:.1f}",
          f"{r['rss_mib_mean']:.0f}"]],
    )


# ----- AP-2 (§7.2.2) ------------------------------------------------------------------------------------------


def ap2(rows: list[dict[str, Any]]) -> str:
    def ms(d: dict[str, float], key: str = "median") -> str:
        return f"{d[key] * 1e3:.0f}" if d else "-"

    def both(d: dict[str, float]) -> str:
        return f"{ms(d)} / {ms(d, 'max')}"

    return _md(
        ["hosts", "join (ms, median / max)", "join, all members", "leave", "removal after 1st suspicion",
         "crash to removal"],
        [[r["hosts"], both(r["join"]), both(r["join_all"]), both(r["leave"]), both(r["remove"]),
          both(r["crash_to_removal"])] for r in rows],
    )


# ----- DDB writes ---------------------------------------------------------------------------------------------


def ddb_clients(rows: list[dict[str, Any]]) -> str:
    return _md(
        ["hosts", "sequencer", "clients", "writing through", "ops per request", "ops/s", "requests/s", "latency p50",
         "p99"],
        [[r["hosts"], "yes" if r["sequencer"] else "no", r["clients"], r["through"], r["batch"],
          f"{r['ops_per_s']:.0f}", f"{r['requests_per_s']:.0f}", f"{r['p50_ms']:.1f} ms", f"{r['p99_ms']:.1f} ms"]
         for r in rows if r.get("load") != "all writing"],
    )


def ddb_all_writing(rows: list[dict[str, Any]]) -> str:
    return _md(
        ["hosts", "sequencer", "writers per host", "writes/s", "OACs/s", "writes per OAC", "latency p50", "p99",
         "failed", "OAC p50 / p99", "msgs per OAC (n²+4n−6)"],
        [[r["hosts"], "yes" if r["sequencer"] else "no", r["writers_per_host"], f"{r['writes_per_s']:.0f}",
          f"{r['oacs_per_s']:.0f}", f"{r['writes_per_oac']:.1f}", f"{r['p50_ms']:.1f} ms", f"{r['p99_ms']:.1f} ms",
          r["failed"], f"{r.get('oac_p50_ms', 0.0):.1f} / {r.get('oac_p99_ms', 0.0):.1f} ms",
          f"{r.get('msgs_per_oac', 0.0):.0f} ({r.get('formula_n2_4n_minus_6', '')})"]
         for r in rows if r.get("load") == "all writing"],
    )


# ----- the robot simulator ------------------------------------------------------------------------------------


def sim(r: dict[str, Any]) -> str:
    stepping = _md(
        ["workload", "simulated", "CPU", "x real time (CPU)", "x real time (wall)", "target"],
        [["physics + odometry + sonar 1 Hz + detections 1 Hz" if s["sensors"] else "headless: physics + odometry",
          f"{s['sim_seconds']:.0f} s", f"{s['cpu_s']:.2f} s", f"{s['x_realtime_cpu']:.0f}x",
          f"{s['x_realtime_wall']:.0f}x", ">= 50x"] for s in r["stepping"]],
        "Stepping (large arena, 10 avatars, 0.05 s ticks)",
    )
    camera = _md(
        ["arena", "camera", "size", "render mean / p95", "render wall p50", "PNG", "ArUco detect", "recall", "target"],
        [[c["arena"], c["camera"], c["size"], f"{c['render_cpu']['mean_ms']:.2f} / {c['render_cpu']['p95_ms']:.2f}",
          f"{c['render_wall']['p50_ms']:.2f}", f"{c['png_cpu']['mean_ms']:.2f}", f"{c['aruco_cpu']['mean_ms']:.2f}",
          f"{c['recall']:.3f} ({c['markers_found']}/{c['markers_expected']})", "render <= 10 ms"]
         for c in r["camera"]],
        "Camera frame (render), PNG encoding and OpenCV ArUco detection, CPU ms per frame",
    )
    s = r["sensors"]
    sensors = _md(
        ["reading", "mean", "p95", "target"],
        [["sonar scan (5 sonars x 9 rays)", f"{s['sonar_scan_cpu']['mean_ms']:.3f}",
          f"{s['sonar_scan_cpu']['p95_ms']:.3f}", "<= 1 ms"],
         ["one sonar (scan / 5)", f"{s['sonar_per_sonar_cpu_ms']:.3f}", "", "<= 1 ms"],
         ["landmark detections of one camera", f"{s['landmarks_cpu']['mean_ms']:.3f}",
          f"{s['landmarks_cpu']['p95_ms']:.3f}", ""]],
        "Sensors (large arena, a sweeper among 10 avatars), CPU ms",
    )
    return "\n\n".join([stepping, camera, sensors])


# ----- AP-3 (§7.2.3) ------------------------------------------------------------------------------------------


def _grid(rows: list[dict[str, Any]], key: str, stat: str, fmt: str, title: str) -> str:
    """A hosts x agents table of `key`: a number, or a summary dict shown as its `stat` (with "± sd" when the
    stat is the mean; "n/a" without samples)."""
    hosts = sorted({r["hosts"] for r in rows})
    agents = sorted({r["agents"] for r in rows})
    cell = {(r["hosts"], r["agents"]): r[key] for r in rows if key in r}
    out: list[list[Cell]] = []
    for h in hosts:
        vals: list[Cell] = [h]
        for a in agents:
            v = cell.get((h, a))
            if v is None:
                vals.append("")
            elif isinstance(v, dict):
                vals.append(f"{v[stat]:{fmt}}" + (f" ± {v['sd']:{fmt}}" if stat == "mean" else "") if v["n"] else "n/a")
            else:
                vals.append(f"{v:{fmt}}")
        out.append(vals)
    return _md(["hosts \\ agents", *(str(a) for a in agents)], out, title)


def ap3(rows: list[dict[str, Any]]) -> str:
    return "\n\n".join([
        _grid(rows, "allocated_ms", "mean", ".1f", "Time from OAC(start) proposal to committed OAC(finish), ms"),
        _grid(rows, "consensus_ms", "mean", ".1f", "Time from OAC(start) proposal to the leader's consensus, ms"),
        _grid(rows, "bid_messages", "mean", ".0f", "Bid-update messages per session"),
        _grid(rows, "oac_messages", "mean", "d", "OAC messages per session (start + finish)"),
        _grid(rows, "cpu_ms", "mean", ".1f", "CPU time of all Allocator calls per session, ms (sum over hosts)"),
    ])


def ap3_real(rows: list[dict[str, Any]]) -> str:
    return "\n\n".join([
        _grid(rows, "consensus_ms", "median", ".1f",
              "Real hosts: OAC(start) proposal to the leader's consensus, ms (median)"),
        _grid(rows, "allocated_ms", "median", ".1f",
              "Real hosts: OAC(start) proposal to OAC(finish) applied on every host, ms (median)"),
        _grid(rows, "allocated_ms", "max", ".1f", "Real hosts: the same, ms (max)"),
        _grid(rows, "bid_messages", "mean", ".0f", "Real hosts: bid-update messages per session (mean ± sd)"),
        _grid(rows, "oac_messages_session", "", "d", "OAC messages of the session's two OACs, 2 (n²+4n−6)"),
        _grid(rows, "oac_messages_window", "mean", ".0f",
              "Real hosts: all OAC messages during the session and the transfers it started (mean ± sd)"),
        _grid(rows, "transfers", "mean", ".1f", "Real hosts: transfers the session started (mean ± sd)"),
        _grid(rows, "hostd_cpu_ms", "median", ".0f",
              "Real hosts: CPU of all haa-hostd processes from Alloc(run) to the last commit, ms (median)"),
    ])


def alloc_quality(study: dict[str, Any]) -> str:
    return _md(
        ["instances", "rated", "mean ratio", "median", "p10", "min", "optimal", "sum R / sum R*", "msgs", "time ms"],
        [[f"{regime} ({q['instances']})", q["rated"], f"{q['mean_ratio']:.3f}", f"{q['median_ratio']:.3f}",
          f"{q['p10_ratio']:.3f}", f"{q['min_ratio']:.3f}", f"{q['optimal_share'] * 100:.0f}%",
          f"{q['aggregate_ratio']:.3f}", f"{q['mean_messages']:.0f}", f"{q['mean_time_ms']:.1f}"]
         for regime, q in study["regimes"].items()],
    )


# ----- AP-4 (§7.2.4) ------------------------------------------------------------------------------------------


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e3:.0f}"


def ap4(rows: list[dict[str, Any]]) -> str:
    from haa.lab.experiments.ap4 import METRICS

    out: list[list[Cell]] = []
    for key, (_kind, _field, label, thesis, target) in METRICS.items():
        for r in rows:
            s = r["summary"].get(key)
            if not s:
                continue
            miss = f" ({s['missing']} missing)" if s.get("missing") else ""
            out.append([label, r["hosts"], _ms(s.get("median")), _ms(s.get("p90")), _ms(s.get("max")),
                        f"{s['n']}{miss}", thesis, target])
    return _md(["action", "hosts", "median (ms)", "p90 (ms)", "max (ms)", "samples", "thesis (mean)", "target"], out)


def ap4_compact(rows: list[dict[str, Any]]) -> str:
    """One row per group size: median / p90 of the four headline delays (for the README)."""
    cols = [("spawn", "spawn"), ("freeze", "freeze"), ("transfer", "transfer"),
            ("transfer_unreachable", "unreachable in transfer"), ("recovery", "recovery after detection"),
            ("host_recovery", "host crash: recovery after removal")]
    out: list[list[Cell]] = [
        ["thesis (mean)", "1-2 s", "~1/3-1/2 of transfer", "1.3-2.1 s", "-", "0.7-2.9 s", "0.7-2.9 s"],
        ["target", "<= 500 ms", "-", "<= 150 ms", "-", "<= 300 ms", "<= 300 ms"],
    ]
    for r in rows:
        cells: list[Cell] = [r["hosts"]]
        for k, _label in cols:
            s = r["summary"].get(k) or {}
            cells.append(f"{_ms(s.get('median'))} / {_ms(s.get('p90'))} ms" if s.get("n") else "-")
        out.append(cells)
    return _md(["hosts", *(label for _k, label in cols)], out)


# ----- agents (the agent runtime on this machine) -------------------------------------------------------------

_AGENT_STEPS = [("spawn -> Hello", "spawn_to_hello_s"), ("spawn -> Ready", "spawn_to_ready_s"),
                ("freeze -> Frozen", "freeze_to_frozen_s"), ("spawn + thaw -> Ready", "spawn_thaw_to_ready_s"),
                ("kill -9 -> Failed", "kill9_to_failed_s")]


def agents(rows: list[dict[str, Any]]) -> str:
    """The rows of haa.lab.experiments.agents.measure_spawn: each step's delays, then start time and memory."""

    def ms(s: dict[str, float], k: str) -> str:
        return f"{s[k] * 1e3:.1f}" if s.get("n") else "-"

    steps: list[list[Cell]] = []
    for r in rows:
        for label, key in _AGENT_STEPS:
            s = r[key]
            if s.get("n"):
                steps.append([r["mode"], r["agents"], label, ms(s, "median"), ms(s, "p90"), ms(s, "max")])
    mem: list[list[Cell]] = []
    for r in rows:
        rss = f"{r['rss_mib_mean']:.1f}" if r["rss_mib_mean"] else "-"
        uss = f"{r['uss_mib_mean']:.1f}" if r["uss_mib_mean"] else "-"
        mem.append([r["mode"], f"{r['forkserver_start_s'] * 1e3:.0f}", rss, uss])
    return (_md(["mode", "agents", "step", "median ms", "p90 ms", "max ms"], steps) + "\n\n"
            + _md(["mode", "fork server start ms", "RSS MiB/agent", "USS MiB/agent (private)"], mem))


def agents_throughput(tput: list[dict[str, Any]]) -> str:
    """haa.lab.experiments.agents.measure_throughput's figures: agent -> host -> agent on one supervisor."""
    return _md(["agent -> host -> agent", "messages", "bytes each", "msgs/s", "MiB/s"],
               [["one supervisor", t["count"], t["size"], f"{t['msgs_per_s']:.0f}", f"{t['mib_per_s']:.1f}"]
                for t in tput])


# ----- memory -------------------------------------------------------------------------------------------------


def memory(res: dict[str, Any]) -> str:
    hosts = _md(
        ["host", "RSS start", "peak", "end of traffic", "after settle", "max loop lag"],
        [[n, f"{h['rss_start_mib']} MiB", f"{h['rss_peak_mib']} MiB", f"{h['rss_end_of_traffic_mib']} MiB",
          f"{h['rss_after_settle_mib']} MiB", f"{h['loop_lag_max_ms']} ms"] for n, h in res["hosts"].items()],
    )
    steps = _md(
        ["step", "count", "failed", "largest stall", "of it busy (CPU)", "slowest"],
        [[name, s["count"], s["failed"], f"{s['max_stall_ms']} ms", f"{s['max_stall_cpu_ms']} ms",
          f"{s['max_seconds']} s"] for name, s in res["steps"].items()],
    )
    return f"{hosts}\n\n{steps}"


# ----- SLAM (§7.2.5) ------------------------------------------------------------------------------------------


def slam(data: dict[str, Any]) -> str:
    head = (f"Workload: {data['source']}; readings {data['readings']}. Rates are readings per CPU-second of one core "
            "(thread CPU time); 'all' includes predictions and weight requests.\n")
    return head + "\n" + _md(
        ["particles", "sonar scans/s", "camera images/s", "co-occupancy/s", "all readings/s", "predictions/s",
         "weight requests/s", "history MB per avatar-hour (at ~Hz)", "MB/hour at 1 prediction/s"],
        [[r["particles"], f"{r['sonar_per_s']:,.0f}", f"{r['landmark_per_s']:,.0f}", f"{r['cooccupancy_per_s']:,.0f}",
          f"{r['all_readings_per_s']:,.0f}", f"{r['predictions_per_s']:,.0f}", f"{r['requests_per_s']:,.0f}",
          f"{r['memory_mb_per_avatar_hour']:.0f} ({r['prediction_rate_hz']:.1f} Hz)",
          f"{r['memory_mb_per_hour_at_1hz']:.1f}"] for r in data["rows"]],
    )


AP52_THESIS = {"Basic": "2.93 → 44%", "Advanced A": "3.97 → 50%", "Advanced B": "4.89 → 53%"}


def ap52(rows: list[dict[str, Any]]) -> str:
    out: list[list[Cell]] = []
    for r in rows:
        s, j = r["standard_cost"], r["jcslam_cost"]
        out.append([r["scenario"], r["team"], f"{r['request_period_s']:g} s", r["n_particles"], f"{r['M']:.2f}",
                    f"{s[0]:.0f}, {s[1]:.0f}, {s[2]:.0f}", f"{j[0]:.0f}, {j[1]:.0f}, {j[2]:.0f}",
                    f"{100 * r['savings_formula']:.0f}%", f"{100 * r['savings_counted']:.0f}%",
                    AP52_THESIS.get(r["scenario"], "")])
    return _md(["experiment", "team", "weight request period", "N", "M (observations per weight update)",
                "standard cost (MN ×, MN +, MN /)", "JC-SLAM cost (MN ×, N +, N /)", "savings (formula)",
                "savings (counted over the run)", "thesis (M → savings)"], out)


def ap51(data: dict[str, Any]) -> str:
    from haa.lab.experiments.slam import mean_sd, variants

    rows = data["rows"]
    parts = []
    ps = data["particles"]
    for key, info in data["scenarios"].items():
        mine = [r for r in rows if r["scenario_key"] == key]
        unc, _ = mean_sd(mine, "uncorrected_error_m")
        parts.append(
            f"### {info['name']} ({info['team']}, {info['arena']} arena, {info['duration_s']:g} s recorded; "
            f"uncorrected error {unc:.3f} m)\n"
        )
        parts.append(
            "Localization error [m], mean ± std over seeds (each seed's error is the mean over all weight "
            "requests of all avatars):\n"
        )
        errors: list[list[Cell]] = []
        for strat, cond in variants():
            sel = [r for r in mine if r["strategy"] == strat and r["condition"] == cond]
            cells: list[Cell] = [strat, cond]
            for n in ps:
                m, s = mean_sd([r for r in sel if r["n_particles"] == n], "loc_error_m")
                cells.append(f"{m:.3f} ± {s:.3f}")
            proc, _ = mean_sd(sel, "processed_share")
            ooo, _ = mean_sd(sel, "ooo_share")
            dly, _ = mean_sd(sel, "mean_delay_s")
            errors.append([*cells, f"{100 * proc:.0f}%", f"{100 * ooo:.1f}%", f"{dly:.2f} s"])
        parts.append(_md(["strategy", "condition", *(f"N={n}" for n in ps), "processed", "OOO", "delay"], errors))
        parts.append("")
        parts.append("Resampling vs processing (all particle counts and seeds pooled):\n")
        pooled: list[list[Cell]] = []
        for strat, cond in variants():
            sel = [r for r in mine if r["strategy"] == strat and r["condition"] == cond]
            pr, _ = mean_sd(sel, "processing_rate_per_s")
            rr, _ = mean_sd(sel, "resample_rate_per_min")
            le, _ = mean_sd(sel, "landmark_error")
            ma, _ = mean_sd(sel, "map_accuracy")
            pooled.append([strat, cond, f"{pr:.1f}", f"{rr:.1f}", f"{le:.3f}", f"{ma:.3f}"])
        parts.append(_md(["strategy", "condition", "readings processed/s", "resamples/min", "landmark error [m]",
                          "map accuracy"], pooled))
        parts.append("")
    return "\n".join(parts)


def soak(res: dict[str, Any]) -> str:
    """`haactl bench soak`: per host RSS early / late / peak, then the write latency, stalls and view changes."""
    rows = [[n, g["rss_second_fifth_mib"], g["rss_last_fifth_mib"], g["rss_peak_mib"]] for n, g in res["rss"].items()]
    out = [_md(["host", "RSS 2nd fifth (MiB)", "RSS last fifth (MiB)", "peak (MiB)"], rows)]
    out.append(f"writes {res['writes']} ({res['writes_failed']} failed), p50 {res['write_p50_ms']} ms, "
               f"p99 {res['write_p99_ms']} ms; spawned {res['spawned']}, removed {res['removed']}; "
               f"messages {res['messages']} ({res['message_failures']} failed)")
    largest = res["largest_stalls"][0]["ms"] if res["largest_stalls"] else 0
    out.append(f"kills {sum(k == 'kill' for _t, _h, k in res['kills'])}, removals {len(res['removals'])}, "
               f"expulsions without a fault {res['expulsions_without_fault']}; stalls over 500 ms "
               f"{res['stalls_over_500ms']}, largest {largest} ms")
    return "\n".join(out)
