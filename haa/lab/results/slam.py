"""JC-SLAM (thesis §7.2.5): AP-5.1, AP-5.2 and the SLAM library's speed."""

from __future__ import annotations

import re
from typing import Any

from haa.lab.results.common import (
    THESIS_AP51,
    THESIS_AP52,
    THESIS_SLAM,
    THESIS_SLAM_MEMORY,
    Json,
    Lines,
    machine_line,
    mean_pstd,
    num,
    pct,
    table,
)

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


