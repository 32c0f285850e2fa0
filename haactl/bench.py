"""`haactl bench ...`: run an experiment of haa.lab.experiments, print its tables, write bench-results/<name>.json.

Benchmarks measure; they never fail on a timing. Each command parses its options, calls the experiment's
library function (haa.lab.experiments.<module>: the thesis' experiments AP-1..AP-5 and our own measurements),
prints the results as markdown tables (haactl.benchtables, through the one table helper haactl.tables) and
writes the JSON with the machine description (haa.lab.benchresults). The JSON keys are a public interface: the
docs, the README and later comparisons read them.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import typer

from haa.lab.benchresults import RESULTS, machine, write_json
from haactl import benchtables
from haactl.cliopts import BenchRootOpt

bench_app = typer.Typer(help="Benchmarks: print a table, write bench-results/<name>.json.", no_args_is_help=True)


@bench_app.command("ufd")
def bench_ufd(
    quick: bool = typer.Option(False, "--quick", help="short horizons (a smoke run, not a measurement)"),
    seed: int = typer.Option(1, "--seed"),
) -> None:
    """Failure detector (Alg. 1): heartbeat cost for the thesis' QoS and ours, and measured QoS."""
    from haa.lab.experiments.ufd import heartbeat_rates, measured_qos

    t0 = time.perf_counter()
    rates = heartbeat_rates()
    print("## Heartbeat rate chosen by the configuration procedure (per monitored pair)\n")
    print(benchtables.ufd_rates(rates))
    measured = measured_qos(quick, seed)
    print("\n## Measured QoS in simulation (real Alg. 1 objects, adaptive re-configuration on)\n")
    print(benchtables.ufd_measured(measured))
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
    from haa.lab.experiments.ap1 import MODES, run_ap1

    bad = [m for m in mode if m not in MODES]
    if bad:
        raise typer.BadParameter(f"unknown load {bad[0]!r}: one of {', '.join(MODES)}", param_hint="--mode")
    t0 = time.perf_counter()
    rows = run_ap1(max_hosts=hosts, transactions=transactions, concurrency=concurrency,
                   min_hosts=min(min_hosts, hosts), modes=tuple(mode) or MODES, tls=tls)
    print()
    print(benchtables.ap1(rows))
    # a partial run (some sizes or loads only, or over TLS) does not overwrite the full table
    partial = min_hosts > 2 or bool(mode) or tls
    path = write_json(
        "ap1-partial" if partial else "ap1",
        {"machine": machine("cpus", "load_avg"), "transactions_per_step": transactions, "concurrency": concurrency,
         "tls": tls, "rows": rows},
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
    from haa.lab.experiments.idle import measure_compose, measure_local

    kind = "compose" if compose else "local"
    r = (measure_compose if compose else measure_local)(hosts, duration, settle)
    print()
    print(benchtables.idle(kind, r))
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
    data[kind] = {**r, "machine": machine("cpus", "load_avg"), "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    path = write_json("idle", data)
    print(f"\nwrote {path}")


@bench_app.command("ap2")
def bench_ap2(
    hosts: int = typer.Option(10, "--hosts", min=2, max=16, help="largest group size"),
    reps: int = typer.Option(3, "--reps", min=1, help="leaves and crashes per group size"),
    root: BenchRootOpt = None,
) -> None:
    """Experiment AP-2 (thesis §7.2.2): join, leave and removal delays vs. group size, real haa-hostd."""
    import tempfile

    from haa.lab.experiments.ap2 import run_ap2

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="haa-ap2-") as tmp:
        rows = run_ap2(root or Path(tmp), max_hosts=hosts, reps=reps)
    print()
    print(benchtables.ap2(rows))
    path = write_json("ap2", {"machine": machine("cpus", "python", "platform"), "reps": reps, "rows": rows})
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
    from haa.lab.experiments.ddb import run_ddb_bench

    modes = {"on": (True,), "off": (False,), "both": (True, False)}
    if sequencer not in modes:
        raise typer.BadParameter("on, off or both", param_hint="--sequencer")
    t0 = time.perf_counter()
    rows = run_ddb_bench(hosts=hosts, seconds=seconds, writers=tuple(writers), sequencer=modes[sequencer],
                         client_loads=not all_writing)
    print()
    if not all_writing:
        print(benchtables.ddb_clients(rows))
        print()
    print(benchtables.ddb_all_writing(rows))
    partial = all_writing or sequencer != "both"
    path = write_json("ddb-partial" if partial else "ddb",
                      {"machine": machine("cpus", "python", "platform"), "seconds": seconds, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("sim")
def bench_sim(
    quick: bool = typer.Option(False, "--quick", help="short runs (a smoke run, not a measurement)"),
) -> None:
    """The simulator (haa.sim): stepping 10 avatars vs real time, camera frames, sonar readings."""
    from haa.lab.experiments.sim import run_sim_bench

    t0 = time.perf_counter()
    r = run_sim_bench(quick=quick)
    print(benchtables.sim(r))
    path = write_json("sim", {"machine": machine(), **r})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap3")
def bench_ap3(
    reps: int = typer.Option(5, "--reps", min=1, help="sessions per (hosts, agents) cell"),
    max_hosts: int = typer.Option(10, "--max-hosts", min=2, max=10, help="largest group size"),
    max_agents: int = typer.Option(60, "--max-agents", min=5, max=60, help="largest agent count"),
    seed: int = typer.Option(1, "--seed"),
    real: bool = typer.Option(False, "--real", help="real haa-hostd processes, 2,4..10 hosts"),
    clock: str = typer.Option("thread", "--clock", help="simulated: CPU time per Allocator call, thread or perf"),
) -> None:
    """Experiment AP-3 (thesis §7.2.3): allocation time and messages, 2..10 hosts x 5..60 agents (simulated:
    loopback gRPC delay model, bench ap1's OAC latency, real CPU time of the Allocator calls)."""
    from haa.lab.experiments.ap3 import AGENTS, HOSTS, run_ap3
    from haa.lab.experiments.ap3real import existing, merge_json

    t0 = time.perf_counter()
    if real:
        from haa.lab.experiments.ap3real import HOSTS as REAL_HOSTS
        from haa.lab.experiments.ap3real import run_ap3_real

        rows = run_ap3_real(tuple(h for h in REAL_HOSTS if h <= max_hosts),
                            tuple(a for a in AGENTS if a <= max_agents), reps=reps, seed=seed)
        print(benchtables.ap3_real(rows))
        path = write_json("ap3", merge_json(RESULTS / "ap3.json", {"machine": machine(), "reps": reps, "seed": seed,
                                                                    "mode": "real", "rows": rows}))
        print(f"\nwrote {path} (key \"real\") in {time.perf_counter() - t0:.0f} s")
        return
    hosts = tuple(h for h in HOSTS if h <= max_hosts)
    agents = tuple(a for a in AGENTS if a <= max_agents)
    rows = run_ap3(hosts, agents, reps=reps, seed=seed, clock=clock)
    print(benchtables.ap3(rows))
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
    from haa.lab.experiments.ap3 import run_quality_study

    t0 = time.perf_counter()
    study = run_quality_study(instances, seed)
    print(benchtables.alloc_quality(study))
    path = write_json("alloc_quality", study)
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("slam")
def bench_slam(
    duration: float = typer.Option(60.0, "--duration", min=5, help="seconds of the 8-sweeper recording replayed"),
) -> None:
    """JC-SLAM library speed: readings per CPU-second at 100..1000 particles, history memory
    (haa.lab.experiments.slam)."""
    from haa.lab.experiments.slam import run_bench_slam

    t0 = time.perf_counter()
    data = run_bench_slam(duration=duration)
    print()
    print(benchtables.slam(data))
    path = write_json("slam", {"machine": machine(), **data})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap5.2")
def bench_ap52(
    particles: int = typer.Option(500, "--particles", min=1),
    quick: bool = typer.Option(False, "--quick", help="short recordings"),
) -> None:
    """Experiment AP-5.2 (thesis §7.2.5.2): operations saved by delayed weight updates."""
    from haa.lab.experiments.slam import run_ap52

    t0 = time.perf_counter()
    rows = run_ap52(particles, quick=quick)
    print()
    print(benchtables.ap52(rows))
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
    """Experiment AP-5.1 (thesis §7.2.5.1): SLAM strategies at nominal and constrained capacity
    (haa.lab.experiments.slam)."""
    from haa.lab.experiments.slam import STRATEGY_ORDER, merge_ap51, run_ap51

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
    print(benchtables.ap51(data))
    path = write_json(name, {"machine": machine(), **data})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("ap4")
def bench_ap4(
    hosts: str = typer.Option("2,4,6,8,10", "--hosts", help="comma-separated group sizes (2..16)"),
    reps: int = typer.Option(10, "--reps", min=1, help="samples of each action per group size"),
    quick: bool = typer.Option(False, "--quick", help="groups of 2 and 3, 3 samples each (a smoke run)"),
    state_kb: float = typer.Option(111.0, "--state-kb", min=0, help="agent state, kB (thesis average: 111)"),
    root: BenchRootOpt = None,
) -> None:
    """Experiment AP-4 (thesis §7.2.4): spawn, freeze, transfer and recovery delays vs. hosts
    (haa.lab.experiments.ap4)."""
    from haa.lab.experiments.ap4 import parse_hosts, run_ap4

    t0 = time.perf_counter()
    try:
        sizes = (2, 3) if quick else parse_hosts(hosts)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    reps = 3 if quick else reps
    rows = run_ap4(sizes, reps=reps, root=root, state_bytes=int(state_kb * 1000))
    print()
    print(benchtables.ap4(rows))
    print()
    print(benchtables.ap4_compact(rows))
    path = write_json("ap4-quick" if quick else "ap4",
                      {"machine": machine("cpus", "load_avg_at_end"), "reps": reps, "rows": rows})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("agents")
def bench_agents(
    n: int = typer.Option(50, "-n", min=1, help="agents spawned through the fork server"),
    cold_n: int = typer.Option(10, "--cold-n", min=0, help="agents spawned by exec (0 = skip)"),
    messages: int = typer.Option(20000, "--messages", min=1, help="messages for the throughput figure"),
    no_json: bool = typer.Option(False, "--no-json", help="do not write bench-results/agents.json"),
) -> None:
    """The agent runtime on this machine: spawn latency (fork server, exec), transfer and failure steps, memory
    per agent, agent -> host -> agent throughput (haa.lab.experiments.agents)."""
    from haa.lab.experiments.agents import run_agents_bench

    t0 = time.perf_counter()
    res = run_agents_bench(n, cold_n, messages)
    print(benchtables.agents(res["rows"]))
    print()
    print(benchtables.agents_throughput(res["throughput"]))
    if not no_json:
        path = write_json("agents", res)
        print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("memory")
def bench_memory(
    seconds: float = typer.Option(600.0, "--seconds", min=1.0, help="duration of the maximum-size traffic"),
    settle: float = typer.Option(20.0, "--settle", min=0.0, help="seconds to keep sampling after the traffic"),
    interval: float = typer.Option(1.0, "--interval", min=0.1, help="RSS sampling interval, s"),
    root: BenchRootOpt = None,
    out: str = typer.Option("memory", "--out", help="result name: bench-results/<out>.json"),
) -> None:
    """RSS per host and event-loop stalls of a 4-host group under maximum-size requests (haa.lab.experiments.memory)."""
    from haa.lab.experiments.memory import run_memory_bench

    t0 = time.perf_counter()
    res = run_memory_bench(seconds=seconds, interval=interval, settle=settle, root=root)
    print()
    print(benchtables.memory(res))
    print(f"\nlargest stall {res['largest_stall_ms']} ms; view changed: {res['view_changed']}")
    path = write_json(out, {"machine": machine("cpus", "load_avg_at_end"), **res})
    print(f"\nwrote {path} in {time.perf_counter() - t0:.0f} s")


@bench_app.command("soak")
def bench_soak(
    minutes: float = typer.Option(30.0, "--minutes", min=0.5, help="duration of the load"),
    kill_every: float = typer.Option(180.0, "--kill-every", min=10.0, help="s between kill -9 of h4 / h5"),
    burst: int = typer.Option(20, "--burst", min=0, help="counter agents spawned per burst (removed a burst later)"),
    write_rate: float = typer.Option(40.0, "--write-rate", min=1.0, help="DDB writes per second, in all"),
    root: BenchRootOpt = None,
    out: str = typer.Option("soak", "--out", help="result name: bench-results/<out>.json"),
) -> None:
    """A 5-host group under a mission-like load for MINUTES: DDB writes, spawn bursts, agent messages, a host
    killed and restarted every few minutes; RSS, loop stalls and commit latency over time
    (haa.lab.experiments.soak; figure docs/img/soak.png)."""
    from pathlib import Path

    from haa.lab.experiments.soak import plot_soak, run_soak

    t0 = time.perf_counter()
    res = run_soak(minutes, write_rate=write_rate, burst=burst, kill_every=kill_every, root=root)
    print()
    print(benchtables.soak(res))
    path = write_json(out, {"machine": machine("cpus", "load_avg_at_end"), **res})
    plot_soak(res, Path("docs/img") / f"{out}.png")
    print(f"\nwrote {path} and docs/img/{out}.png in {time.perf_counter() - t0:.0f} s")


@bench_app.command("replica")
def bench_replica(
    scenario: str = typer.Option("basic", "--scenario", help="basic | advanced_a | advanced_b"),
    duration: float = typer.Option(0.0, "--duration", min=0, help="s recorded (0: the thesis' mission time)"),
    particles: int = typer.Option(100, "--particles", min=1),
    seed: int = typer.Option(0, "--seed"),
    floor: bool = typer.Option(False, "--floor", help="add a floor region per camera image"),
) -> None:
    """The SLAM replica: apply cost per event kind, checkpoints, the published map (haa.lab.experiments.replica).

    A recorded run (haa.slam.explorer) applied to a replica through the DDB log (docs/slam.md "The SLAM state in
    the DDB"), a checkpoint and a restore every 10 s of the run. Prints the figures as JSON on stdout and writes
    bench-results/replica.json."""
    from haa.lab.experiments.replica import run_replica_bench

    t0 = time.perf_counter()
    res = run_replica_bench(scenario, duration, particles, seed, floor)
    print(json.dumps(res, indent=1))
    path = write_json("replica", {"machine": machine("cpus", "load_avg"), **res})
    print(f"wrote {path} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
