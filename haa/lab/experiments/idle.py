"""Idle cost of a cluster (issue 3 §4): CPU and memory of N membership-mode hosts doing nothing.

`measure_local`: haa-hostd processes on loopback (psutil: user + system CPU time of each process over the
window). `measure_compose`: the compose cluster (the engine's cgroup accounting through the docker stats
API, per container), plus the engine's own processes (dockerd, containerd, shims, docker-proxy) by psutil.
Both bring a fresh cluster up, wait until the group has formed with every host, let it settle, then
measure over `duration` seconds, and take it down. CPU is given in % of one core (100 = one core busy); the
machine has `cpus` cores. `machine_busy` is the whole machine's CPU use over the window (everything, not
only the cluster) so that a busy neighbour shows.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.backend import Backend, wait_until

ENGINE_PROCS = ("dockerd", "containerd", "containerd-shim", "containerd-shim-runc-v2", "docker-proxy")


def _proc_cpu(pids: dict[str, int]) -> dict[str, tuple[float, int]]:
    out = {}
    for n, pid in pids.items():
        try:
            p = psutil.Process(pid)
            t = p.cpu_times()
            out[n] = (t.user + t.system, p.memory_info().rss)
        except psutil.NoSuchProcess:
            continue
    return out


def _tree_cpu(pids: dict[str, int]) -> dict[str, tuple[float, int]]:
    """Like `_proc_cpu`, over each host's whole process tree (haa-hostd, its agent fork server and any agent
    processes), as the compose measurement sees a container's cgroup; memory is the tree's proportional set
    size (PSS: pages the fork server shares with its children are counted once)."""
    out = {}
    for n, pid in pids.items():
        try:
            root = psutil.Process(pid)
            procs = [root, *root.children(recursive=True)]
        except psutil.NoSuchProcess:
            continue
        cpu = 0.0
        mem = 0
        for p in procs:
            try:
                t = p.cpu_times()
                cpu += t.user + t.system
                mem += p.memory_full_info().pss
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
        out[n] = (cpu, mem)
    return out


def _engine_pids() -> dict[str, int]:
    out = {}
    for p in psutil.process_iter(["name", "pid"]):
        if p.info["name"] in ENGINE_PROCS:
            out[f"{p.info['name']}:{p.info['pid']}"] = p.info["pid"]
    return out


def _summary(per_host: dict[str, float], rss: dict[str, int], seconds: float) -> dict[str, Any]:
    vals = sorted(per_host.values())
    total = sum(vals)
    return {
        "hosts": len(vals),
        "seconds": round(seconds, 2),
        "cpu_percent_per_host": {k: round(v, 3) for k, v in sorted(per_host.items())},
        "cpu_percent_total": round(total, 2),
        "cpu_percent_of_machine": round(total / (os.cpu_count() or 1), 2),
        "cpu_percent_host_min": round(vals[0], 3) if vals else 0.0,
        "cpu_percent_host_max": round(vals[-1], 3) if vals else 0.0,
        "rss_mib_mean": round(sum(rss.values()) / max(1, len(rss)) / 2**20, 1),
    }


def _window(sample: Callable[[], dict[str, tuple[float, int]]], duration: float) -> tuple[dict, dict, float, float]:
    m0 = psutil.cpu_times()
    t0 = time.monotonic()
    a = sample()
    time.sleep(duration)
    b = sample()
    secs = time.monotonic() - t0
    m1 = psutil.cpu_times()
    busy0 = m0.user + m0.system + m0.nice + getattr(m0, "irq", 0) + getattr(m0, "softirq", 0)
    busy1 = m1.user + m1.system + m1.nice + getattr(m1, "irq", 0) + getattr(m1, "softirq", 0)
    machine_busy = 100.0 * (busy1 - busy0) / secs
    per = {n: 100.0 * (b[n][0] - a[n][0]) / secs for n in a if n in b}
    rss = {n: b[n][1] for n in per}
    return per, rss, secs, machine_busy


def _traffic(backend: Backend) -> dict[str, dict[str, int]]:
    return {n: dict(r.counters.values) for n, r in backend.statuses().items() if not isinstance(r, Exception)}


def _rates(a: dict[str, dict[str, int]], b: dict[str, dict[str, int]], secs: float) -> dict[str, Any]:
    """Messages and frames each host sent per second over the window, and heartbeats per monitored pair."""
    names = [n for n in a if n in b]
    if not names:
        return {}

    def per_host(pred: Callable[[str], bool]) -> float:
        tot = sum(v - a[n].get(k, 0) for n in names for k, v in b[n].items() if pred(k))
        return tot / len(names) / secs

    peers = max(1, len(names) - 1)
    hb = per_host(lambda k: k == "tx_msgs.heartbeat")
    return {
        "tx_msgs_per_s_per_host": round(per_host(lambda k: k.startswith("tx_msgs.")), 2),
        "tx_frames_per_s_per_host": round(per_host(lambda k: k == "tx_frames"), 2),
        "acks_per_s_per_host": round(per_host(lambda k: k == "acks_sent"), 2),
        "heartbeats_per_s_per_pair": round(hb / peers, 2),
        "set_period_per_s_per_host": round(per_host(lambda k: k == "tx_msgs.set_period"), 3),
    }


def _formed(backend: Backend, names: list[str], timeout: float) -> float:
    check_started = getattr(backend, "check_started", None)

    def check() -> Any:
        if check_started:
            check_started()
        return backend.formation(names)

    return wait_until(check, timeout, what=f"{len(names)} hosts to form a group")[1]


def measure_local(hosts: int, duration: float, settle: float, log: Callable[[str], None] = print) -> dict[str, Any]:
    from haa.cluster.local_backend import LocalBackend

    with tempfile.TemporaryDirectory(prefix="haa-idle-") as tmp:
        backend = LocalBackend(Path(tmp))
        t0 = time.monotonic()
        names = backend.up(hosts, min(3, hosts))
        try:
            _formed(backend, names, 120)
            formed = time.monotonic() - t0
            log(f"local: {hosts} hosts formed a group in {formed:.2f} s; settle {settle:g} s, measure {duration:g} s")
            time.sleep(settle)
            pids = {h.name: h.pid for h in backend.hosts() if h.pid}
            t0 = _traffic(backend)

            def sample() -> dict[str, tuple[float, int]]:
                return {**_proc_cpu(pids), **{f"tree/{k}": v for k, v in _tree_cpu(pids).items()}}

            per_all, rss_all, secs, busy = _window(sample, duration)
            traffic = _rates(t0, _traffic(backend), secs)
            procs = {n: 1 + len(psutil.Process(pid).children(recursive=True)) for n, pid in pids.items()}
        finally:
            backend.down(grace=2.0, purge=True)
    per = {n: v for n, v in per_all.items() if not n.startswith("tree/")}
    rss = {n: v for n, v in rss_all.items() if not n.startswith("tree/")}
    tree = {n[len("tree/") :]: v for n, v in per_all.items() if n.startswith("tree/")}
    pss = [v for n, v in rss_all.items() if n.startswith("tree/")]
    return {
        **_summary(per, rss, secs),
        **traffic,
        "formed_seconds": round(formed, 2),
        "machine_busy_percent": round(busy, 1),
        "tree_processes_per_host": round(sum(procs.values()) / max(1, len(procs)), 1),
        "tree_cpu_percent_total": round(sum(tree.values()), 2),
        "tree_pss_mib_mean": round(sum(pss) / max(1, len(pss)) / 2**20, 1),
        "tree": "haa-hostd with its fork server and agents: CPU % of one core, PSS",
    }


def measure_compose(hosts: int, duration: float, settle: float, log: Callable[[str], None] = print) -> dict[str, Any]:
    from haa.cluster.compose_backend import ComposeBackend

    backend = ComposeBackend()
    t0 = time.monotonic()
    names = backend.up(hosts, log=log)
    try:
        _formed(backend, names, 180)
        formed = time.monotonic() - t0
        log(
            f"compose: {hosts} containers formed a group in {formed:.2f} s; settle {settle:g} s, measure {duration:g} s"
        )
        time.sleep(settle)
        containers = {n: c for n, c in backend.containers().items() if n in names}
        engine = _engine_pids()

        def sample() -> dict[str, tuple[float, int]]:
            def one(item: tuple[str, Any]) -> tuple[str, tuple[float, int]]:
                n, c = item
                s = c.stats(stream=False, one_shot=True)
                cpu = s["cpu_stats"]["cpu_usage"]["total_usage"] / 1e9
                mem = s.get("memory_stats", {})
                usage = mem.get("usage", 0) - (mem.get("stats", {}) or {}).get("cache", 0)
                return n, (cpu, usage)

            with ThreadPoolExecutor(max_workers=len(containers)) as pool:
                res = dict(pool.map(one, containers.items()))
            res.update({f"engine/{k}": v for k, v in _proc_cpu(engine).items()})
            return res

        t0 = _traffic(backend)
        per_all, rss_all, secs, busy = _window(sample, duration)
        traffic = _rates(t0, _traffic(backend), secs)
    finally:
        backend.down(grace=2.0)
    per = {n: v for n, v in per_all.items() if not n.startswith("engine/")}
    rss = {n: v for n, v in rss_all.items() if not n.startswith("engine/")}
    eng = {n[len("engine/") :]: v for n, v in per_all.items() if n.startswith("engine/")}
    by_kind: dict[str, float] = {}
    for k, v in eng.items():
        kind = k.split(":")[0]
        by_kind[kind] = by_kind.get(kind, 0.0) + v
    return {
        **_summary(per, rss, secs),
        **traffic,
        "formed_seconds": round(formed, 2),
        "machine_busy_percent": round(busy, 1),
        "engine_cpu_percent": {k: round(v, 2) for k, v in sorted(by_kind.items())},
        "engine_cpu_percent_total": round(sum(by_kind.values()), 2),
        "memory": "container cgroup usage without page cache (docker stats), MiB",
    }
