"""The simulator, the failure detector and running costs (idle, memory, the dashboard, restructurings)."""

from __future__ import annotations

import math
import re

from haa.lab.results.common import (
    THESIS_UFD,
    Json,
    Lines,
    machine_line,
    num,
    table,
)

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


def render_soak(d: Json, name: str) -> Lines:
    hosts = [[n, num(g["rss_second_fifth_mib"], 4), num(g["rss_last_fifth_mib"], 4), num(g["rss_peak_mib"], 4)]
             for n, g in d["rss"].items()]
    kills = sum(1 for _t, _h, k in d["kills"] if k == "kill")
    largest = d["largest_stalls"][0]["ms"] if d["largest_stalls"] else 0
    return [f"{num(d['minutes'], 3)} minutes of a mission-like load on {len(d['hosts'])} hosts (docs/limits.md, "
            f"\"A soak\"): {d['writes']} DDB writes, {d['writes_failed']} not committed, "
            f"p50 {num(d['write_p50_ms'], 3)} ms, p99 {num(d['write_p99_ms'], 4)} ms; {d['spawned']} agents spawned, "
            f"{d['removed']} removed; "
            f"{d['messages']} messages ({d['message_failures']} failed); {kills} kills, {len(d['removals'])} removals, "
            f"{d['expulsions_without_fault']} without a fault; stalls over 500 ms: {d['stalls_over_500ms']} (largest "
            f"{num(largest)} ms).", "", machine_line(d.get("machine")), "",
            *table(["host", "RSS, 2nd fifth (MiB)", "RSS, last fifth", "peak"], hosts)]


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


