"""`haactl bench ...`: benchmarks that print markdown tables and write JSON under bench-results/.

Benchmarks measure; they never fail on a timing. `ufd` measures the failure detector's QoS in simulation
(haa.dsim.ufdqos); `ap1` is the thesis' experiment AP-1 on real haa-hostd processes (haactl.ap1).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import typer

from haa.benchresults import RESULTS, write_json
from haa.dsim.network import DelayModel
from haa.dsim.ufdqos import QosMeasurement, measure
from haa.hostd.qos import CLUSTER_QOS, THESIS_QOS, QosTargets, configure, heartbeats_per_minute

bench_app = typer.Typer(help="Benchmarks: print a table, write bench-results/<name>.json.", no_args_is_help=True)

MEASURABLE_QOS = QosTargets(td_upper=0.5, tmr_lower=60.0, tm_upper=0.5)


def _fmt_time(x: float) -> str:
    if math.isinf(x):
        return "no mistake"
    if x >= 86400:
        return f"{x / 86400:.1f} d"
    if x >= 3600:
        return f"{x / 3600:.1f} h"
    return f"{x:.1f} s"


def ufd_rates_table() -> list[dict[str, Any]]:
    """Heartbeat rate of the configuration procedure for the thesis' QoS and our cluster default."""
    rows = []
    for qname, qos in (("thesis (10 s, 1 week, 30 s)", THESIS_QOS), ("cluster (1 s, 1 day, 1 s)", CLUSTER_QOS)):
        for p_loss in (0.0, 1e-4, 1e-3, 1e-2):
            for std in (0.001, 0.01, 0.05):
                # the observer's add-one loss estimate over its window of 1000 heartbeats never reads 0
                p_est = max(p_loss, 1 / 1002)
                params = configure(qos, p_est, std**2)
                rows.append(
                    {
                        "qos": qname,
                        "p_loss": p_loss,
                        "delay_std_ms": std * 1e3,
                        "eta_s": params.eta,
                        "alpha_s": params.alpha,
                        "heartbeats_per_minute": heartbeats_per_minute(params),
                    }
                )
    return rows


@bench_app.command("ufd")
def bench_ufd(
    quick: bool = typer.Option(False, "--quick", help="short horizons (a smoke run, not a measurement)"),
    seed: int = typer.Option(1, "--seed"),
) -> None:
    """Failure detector (Alg. 1): heartbeat cost for the thesis' QoS and ours, and measured QoS."""
    t0 = time.perf_counter()
    rates = ufd_rates_table()
    print("## Heartbeat rate chosen by the configuration procedure (per monitored pair)\n")
    print("| QoS (T_D^U, T_MR^L, T_M^U) | p_L | σ(D) | η | α | heartbeats/min |")
    print("|---|---|---|---|---|---|")
    for r in rates:
        print(
            f"| {r['qos']} | {r['p_loss']:g} | {r['delay_std_ms']:g} ms | {r['eta_s']:.3f} s | "
            f"{r['alpha_s']:.3f} s | {r['heartbeats_per_minute']:.1f} |"
        )
    scale = 0.1 if quick else 1.0
    cases: list[tuple[str, QosTargets, DelayModel, float, float]] = [
        ("measurable: exp 20 ms, 1% loss", MEASURABLE_QOS, DelayModel("exp", 0.001, 0.02), 0.01, 20000),
        ("measurable: lognormal σ=0.8", MEASURABLE_QOS, DelayModel("lognormal", 0.001, 0.01, 0.8), 0.01, 20000),
        ("measurable: Pareto α=2.5 (heavy tail)", MEASURABLE_QOS, DelayModel("pareto", 0.001, 0.02, 2.5), 0.01, 20000),
        ("measurable: exp 50 ms, 5% loss", MEASURABLE_QOS, DelayModel("exp", 0.001, 0.05), 0.05, 20000),
        ("cluster: LAN exp 1 ms, 0.1% loss", CLUSTER_QOS, DelayModel("exp", 0.0002, 0.001), 0.001, 10 * 86400),
        ("thesis: LAN exp 1 ms, 0.1% loss", THESIS_QOS, DelayModel("exp", 0.0002, 0.001), 0.001, 8 * 7 * 86400),
        ("thesis: WLAN lognormal 20 ms, 1% loss", THESIS_QOS, DelayModel("lognormal", 0.002, 0.015, 0.7), 0.01,
         8 * 7 * 86400),
    ]
    measured: list[QosMeasurement] = []
    for label, qos, delay, p_loss, horizon in cases:
        measured.append(measure(label, qos, delay, p_loss, horizon * scale, seed=seed, crash_trials=100))
    print("\n## Measured QoS in simulation (real Alg. 1 objects, adaptive re-configuration on)\n")
    print(
        "| case | horizon | η (final) | hb/min | mistakes | E(T_MR) ≥ T_MR^L? | E(T_M) ≤ T_M^U? | P_A | "
        "max T_D / (T_D^U + E(D)) | targets met |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for m in measured:
        print(
            f"| {m.label} | {_fmt_time(m.horizon)} | {m.eta:.3f} s | {m.heartbeats_per_minute:.1f} | {m.mistakes} | "
            f"{_fmt_time(m.mean_tmr)} vs {_fmt_time(m.tmr_lower)} | {m.mean_tm * 1e3:.0f} ms vs "
            f"{m.tm_upper * 1e3:.0f} ms | {m.query_accuracy:.6f} | {m.max_detection:.3f} / {m.detection_bound:.3f} s | "
            f"{'yes' if m.meets_targets else 'NO'} |"
        )
    path = write_json(
        "ufd",
        {
            "rates": rates,
            "measured": [m.row() for m in measured],
            "seconds": time.perf_counter() - t0,
            "quick": quick,
        },
    )
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap1")
def bench_ap1(
    hosts: int = typer.Option(10, "--hosts", min=2, max=16, help="largest participant count"),
    transactions: int = typer.Option(300, "--transactions", "-n", min=10, help="transactions per step"),
    concurrency: int = typer.Option(2, "--concurrency", min=1, help="in-flight proposals per proposer"),
    min_hosts: int = typer.Option(2, "--min-hosts", min=2, max=16, help="smallest participant count"),
    mode: list[str] = typer.Option([], "--mode", help="only these loads (repeat): paced, back-to-back, "
                                   "all-proposing, concurrent"),
    tls: bool = typer.Option(False, "--tls", help="the hosts talk over mutual TLS (docs/deploy.md)"),
) -> None:
    """Experiment AP-1 (thesis §7.2.1): OAC latency and messages vs. participants, real haa-hostd processes."""
    from haactl.ap1 import MODES, machine, markdown_table, run_ap1

    bad = [m for m in mode if m not in MODES]
    if bad:
        raise typer.BadParameter(f"unknown load {bad[0]!r}: one of {', '.join(MODES)}", param_hint="--mode")
    t0 = time.perf_counter()
    rows = run_ap1(max_hosts=hosts, transactions=transactions, concurrency=concurrency,
                   min_hosts=min(min_hosts, hosts), modes=tuple(mode) or MODES, tls=tls)
    print()
    print(markdown_table(rows))
    # a partial run (some sizes or loads only, or over TLS) does not overwrite the full table
    partial = min_hosts > 2 or bool(mode) or tls
    path = write_json(
        "ap1-partial" if partial else "ap1",
        {"machine": machine(), "transactions_per_step": transactions, "concurrency": concurrency, "tls": tls,
         "rows": rows},
    )
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("idle")
def bench_idle(
    hosts: int = typer.Option(10, "--hosts", min=1, max=32, help="hosts in the idle cluster"),
    duration: float = typer.Option(60.0, "--duration", min=1, help="measurement window, s"),
    settle: float = typer.Option(10.0, "--settle", min=0, help="wait after the group formed, s"),
    compose: bool = typer.Option(False, "--compose", help="measure the docker compose cluster instead"),
) -> None:
    """Idle cost: CPU and memory of an idle membership-mode cluster -> bench-results/idle.json."""
    from haactl.ap1 import machine
    from haactl.idle import measure_compose, measure_local

    kind = "compose" if compose else "local"
    r = (measure_compose if compose else measure_local)(hosts, duration, settle)
    print("\n| cluster | hosts | CPU total (% of one core) | per host min / max | % of the machine | RSS MiB/host |")
    print("|---|---|---|---|---|---|")
    print(
        f"| {kind} | {r['hosts']} | {r['cpu_percent_total']:.1f} | {r['cpu_percent_host_min']:.2f} / "
        f"{r['cpu_percent_host_max']:.2f} | {r['cpu_percent_of_machine']:.1f} | {r['rss_mib_mean']:.0f} |"
    )
    if "tx_msgs_per_s_per_host" in r:
        print(
            f"\nper host: {r['tx_msgs_per_s_per_host']:.1f} messages/s sent "
            f"({r['tx_frames_per_s_per_host']:.1f} frames, {r['acks_per_s_per_host']:.1f} acks); "
            f"heartbeats {r['heartbeats_per_s_per_pair']:.2f}/s per pair"
        )
    if "tree_cpu_percent_total" in r:
        print(
            f"\nwith each host's fork server ({r['tree_processes_per_host']:.0f} processes per host): "
            f"{r['tree_cpu_percent_total']:.1f} % of one core in all, {r['tree_pss_mib_mean']:.0f} MiB PSS per host"
        )
    if compose:
        print(f"\nengine processes: {r['engine_cpu_percent_total']:.1f} % of one core {r['engine_cpu_percent']}")
    path = RESULTS / "idle.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data[kind] = {**r, "machine": machine(), "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    path = write_json("idle", data)
    print(f"\nwrote {path}")


@bench_app.command("ap2")
def bench_ap2(
    hosts: int = typer.Option(10, "--hosts", min=2, max=16, help="largest group size"),
    reps: int = typer.Option(3, "--reps", min=1, help="leaves and crashes per group size"),
    root: Path | None = typer.Option(None, "--root", help="data dirs and logs (default: a temporary dir)"),
) -> None:
    """Experiment AP-2 (thesis §7.2.2): join, leave and removal delays vs. group size, real haa-hostd."""
    import tempfile

    from haactl.ap2 import machine, markdown_table, run_ap2

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="haa-ap2-") as tmp:
        rows = run_ap2(root or Path(tmp), max_hosts=hosts, reps=reps)
    print()
    print(markdown_table(rows))
    path = write_json("ap2", {"machine": machine(), "reps": reps, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ddb")
def bench_ddb(
    hosts: int = typer.Option(5, "--hosts", min=1, max=16, help="group size"),
    seconds: float = typer.Option(5.0, "--seconds", min=0.5, help="duration of each step"),
    writers: list[int] = typer.Option([1, 8, 32], "--writers", min=1, max=1000,
                                      help="all-writing loads: concurrent writers inside every host (repeat)"),
    all_writing: bool = typer.Option(False, "--all-writing", help="only the all-writing loads (no client loads)"),
    sequencer: str = typer.Option("both", "--sequencer", help="on, off or both (a comparison)"),
) -> None:
    """DDB writes through OAC: client loads (does batching pay?) and every host writing at once, with and
    without the sequencer."""
    from haactl.ap2 import machine
    from haactl.ddbbench import all_writing_table, markdown_table, run_ddb_bench

    modes = {"on": (True,), "off": (False,), "both": (True, False)}
    if sequencer not in modes:
        raise typer.BadParameter("on, off or both", param_hint="--sequencer")
    t0 = time.perf_counter()
    rows = run_ddb_bench(hosts=hosts, seconds=seconds, writers=tuple(writers), sequencer=modes[sequencer],
                         client_loads=not all_writing)
    print()
    if not all_writing:
        print(markdown_table(rows))
        print()
    print(all_writing_table(rows))
    partial = all_writing or sequencer != "both"
    path = write_json("ddb-partial" if partial else "ddb",
                      {"machine": machine(), "seconds": seconds, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("sim")
def bench_sim(
    quick: bool = typer.Option(False, "--quick", help="short runs (a smoke run, not a measurement)"),
) -> None:
    """The simulator (haa.sim): stepping 10 avatars vs real time, camera frames, sonar readings."""
    from haactl.ap1 import machine
    from haactl.simbench import markdown, run_sim_bench

    t0 = time.perf_counter()
    r = run_sim_bench(quick=quick)
    print(markdown(r))
    path = write_json("sim", {"machine": machine(), **r})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap3")
def bench_ap3(
    reps: int = typer.Option(5, "--reps", min=1, help="sessions per (hosts, agents) cell"),
    max_hosts: int = typer.Option(10, "--max-hosts", min=2, max=10, help="largest group size"),
    max_agents: int = typer.Option(60, "--max-agents", min=5, max=60, help="largest agent count"),
    seed: int = typer.Option(1, "--seed"),
    real: bool = typer.Option(False, "--real", help="real haa-hostd processes, 2,4..10 hosts (haactl.ap3real)"),
    clock: str = typer.Option("thread", "--clock", help="simulated: CPU time per Allocator call, thread or perf"),
) -> None:
    """Experiment AP-3 (thesis §7.2.3): allocation time and messages, 2..10 hosts x 5..60 agents (simulated:
    loopback gRPC delay model, bench ap1's OAC latency, real CPU time of the Allocator calls)."""
    from haactl.ap1 import machine
    from haactl.ap3 import AGENTS, HOSTS, markdown_tables, run_ap3
    from haactl.ap3real import existing, merge_json

    t0 = time.perf_counter()
    if real:
        from haactl.ap3real import HOSTS as REAL_HOSTS
        from haactl.ap3real import markdown_tables as real_tables
        from haactl.ap3real import run_ap3_real

        rows = run_ap3_real(tuple(h for h in REAL_HOSTS if h <= max_hosts),
                            tuple(a for a in AGENTS if a <= max_agents), reps=reps, seed=seed)
        print(real_tables(rows))
        path = write_json("ap3", merge_json(RESULTS / "ap3.json", {"machine": machine(), "reps": reps, "seed": seed,
                                                                    "mode": "real", "rows": rows}))
        print(f"\nwrote {path} (key \"real\") in {time.perf_counter() - t0:.0f} s")
        return
    hosts = tuple(h for h in HOSTS if h <= max_hosts)
    agents = tuple(a for a in AGENTS if a <= max_agents)
    rows = run_ap3(hosts, agents, reps=reps, seed=seed, clock=clock)
    print(markdown_tables(rows))
    old = existing(RESULTS / "ap3.json").get("real")  # keep the real-hosts results of --real
    data = {"machine": machine(), "reps": reps, "seed": seed, "mode": "simulated", "clock": clock, "rows": rows}
    path = write_json("ap3", {**data, "real": old} if old else data)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("alloc-quality")
def bench_alloc_quality(
    instances: int = typer.Option(500, "--instances", "-n", min=10, help="random instances per family"),
    seed: int = typer.Option(0, "--seed"),
) -> None:
    """Allocation quality: total reward (eq. 4.7-1) of the committed allocation vs the exhaustive optimum on
    random instances of up to 8 agents and 4 hosts."""
    from haactl.ap3 import quality_table, run_quality_study

    t0 = time.perf_counter()
    study = run_quality_study(instances, seed)
    print(quality_table(study))
    path = write_json("alloc_quality", study)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("slam")
def bench_slam(
    duration: float = typer.Option(60.0, "--duration", min=5, help="seconds of the 8-sweeper recording replayed"),
) -> None:
    """JC-SLAM library speed: readings per CPU-second at 100..1000 particles, history memory (haactl.slambench)."""
    from haactl.slambench import bench_slam_table, machine, run_bench_slam

    t0 = time.perf_counter()
    data = run_bench_slam(duration=duration)
    print()
    print(bench_slam_table(data))
    path = write_json("slam", {"machine": machine(), **data})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap5.2")
def bench_ap52(
    particles: int = typer.Option(500, "--particles", min=1),
    quick: bool = typer.Option(False, "--quick", help="short recordings"),
) -> None:
    """Experiment AP-5.2 (thesis §7.2.5.2): operations saved by delayed weight updates."""
    from haactl.slambench import ap52_table, machine, run_ap52

    t0 = time.perf_counter()
    rows = run_ap52(particles, quick=quick)
    print()
    print(ap52_table(rows))
    path = write_json("ap5.2", {"machine": machine(), "quick": quick, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap5.1")
def bench_ap51(
    quick: bool = typer.Option(False, "--quick", help="short recordings, 100 and 500 particles, 2 seeds"),
    seeds: int = typer.Option(0, "--seeds", min=0, help="seeds per variant (0: 2 quick, 10 full)"),
    particles: str = typer.Option("", "--particles", help="comma-separated particle counts (default by mode)"),
    scenario: list[str] = typer.Option([], "--scenario", help="basic | advanced_a | advanced_b (repeatable)"),
    jobs: int = typer.Option(1, "--jobs", min=1, help="worker processes"),
    strategy: list[str] = typer.Option([], "--strategy", help="only these strategies (repeatable; default all)"),
    merge: bool = typer.Option(False, "--merge", help="keep the other scenarios of the existing JSON"),
) -> None:
    """Experiment AP-5.1 (thesis §7.2.5.1): SLAM strategies at nominal and constrained capacity (haactl.slambench)."""
    from haactl.slambench import STRATEGY_ORDER, ap51_tables, machine, merge_ap51, run_ap51

    t0 = time.perf_counter()
    ps = tuple(int(p) for p in particles.split(",") if p.strip()) or None
    keys = tuple(scenario) or ("basic", "advanced_a", "advanced_b")
    bad = [s for s in strategy if s not in STRATEGY_ORDER]
    if bad:
        known = ", ".join(STRATEGY_ORDER)
        raise typer.BadParameter(f"unknown {', '.join(bad)} (known: {known})", param_hint="--strategy")
    data = run_ap51(quick=quick, particles=ps, seeds=seeds or None, scenarios=keys, jobs=jobs,
                    strategies=tuple(strategy))
    name = "ap5.1-quick" if quick else "ap5.1"
    data["notes"] = [f"{k}: `haactl bench ap5.1 --scenario {k} --particles {','.join(map(str, data['particles']))} "
                     f"--seeds {data['seeds']}" + "".join(f" --strategy {s}" for s in strategy) + "`"
                     for k in keys]
    old = RESULTS / f"{name}.json"
    if merge and old.exists():
        data = merge_ap51(json.loads(old.read_text()), data)
    print()
    print(ap51_tables(data))
    path = write_json(name, {"machine": machine(), **data})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap4")
def bench_ap4(
    hosts: str = typer.Option("2,4,6,8,10", "--hosts", help="comma-separated group sizes (2..16)"),
    reps: int = typer.Option(10, "--reps", min=1, help="samples of each action per group size"),
    quick: bool = typer.Option(False, "--quick", help="groups of 2 and 3, 3 samples each (a smoke run)"),
    state_kb: float = typer.Option(111.0, "--state-kb", min=0, help="agent state, kB (thesis average: 111)"),
    root: Path | None = typer.Option(None, "--root", help="data dirs and logs (default: a temporary dir)"),
) -> None:
    """Experiment AP-4 (thesis §7.2.4): spawn, freeze, transfer and recovery delays vs. hosts (haactl.ap4)."""
    from haactl.ap4 import compact_table, machine, markdown_table, parse_hosts, run_ap4

    t0 = time.perf_counter()
    try:
        sizes = (2, 3) if quick else parse_hosts(hosts)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    reps = 3 if quick else reps
    rows = run_ap4(sizes, reps=reps, root=root, state_bytes=int(state_kb * 1000))
    print()
    print(markdown_table(rows))
    print()
    print(compact_table(rows))
    path = write_json("ap4-quick" if quick else "ap4", {"machine": machine(), "reps": reps, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("memory")
def bench_memory(
    seconds: float = typer.Option(600.0, "--seconds", min=1.0, help="duration of the maximum-size traffic"),
    settle: float = typer.Option(20.0, "--settle", min=0.0, help="seconds to keep sampling after the traffic"),
    interval: float = typer.Option(1.0, "--interval", min=0.1, help="RSS sampling interval, s"),
    root: Path | None = typer.Option(None, "--root", help="data dirs and logs (default: a temporary dir)"),
    out: str = typer.Option("memory", "--out", help="result name: bench-results/<out>.json"),
) -> None:
    """RSS per host and event-loop stalls of a 4-host group under maximum-size requests (haactl.membench)."""
    from haactl.ap4 import machine
    from haactl.membench import markdown, run_memory_bench

    t0 = time.perf_counter()
    res = run_memory_bench(seconds=seconds, interval=interval, settle=settle, root=root)
    print()
    print(markdown(res))
    print(f"\nlargest stall {res['largest_stall_ms']} ms; view changed: {res['view_changed']}")
    path = write_json(out, {"machine": machine(), **res})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")
