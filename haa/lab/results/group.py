"""Membership, allocation and agents (thesis §7.2.2-7.2.4): AP-2, AP-3, AP-4 and the agent runtime."""

from __future__ import annotations

from typing import Any

from haa.lab.results.common import (
    THESIS_AP2,
    THESIS_AP3,
    THESIS_AP4,
    Json,
    Lines,
    machine_line,
    ms,
    num,
    pct,
    table,
)

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


