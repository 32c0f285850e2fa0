"""Agent runtime benchmark: spawn latency through the fork server (AP-4's local part), cold start for
comparison, memory per agent, and the local steps of a transfer (freeze -> Frozen, spawn + thaw -> Ready)
and of a failure (kill -9 -> Failed).

    haactl bench agents [-n 50] [--cold-n 10]     # prints markdown tables, writes bench-results/agents.json

`run_agents_bench(n, cold_n, messages)` is what `haactl bench agents` calls; `measure_spawn(n)` returns a dict
of figures (seconds) and never fails on a timing. Everything runs on this machine with real processes: one
AgentSupervisor driven directly for the spawn figures; `measure_throughput` routes one agent's messages to
another through one supervisor (haa.lab.experiments.localhosts.LocalHosts: agent -> host -> agent, the local hop
of every routed message). The agent runtime sits below the host's (haa.hostd.agentproc), so the benchmark that
drives both lives here, above the runtime.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import platform
import signal
import statistics
import time
from typing import Any

import psutil

from haa.hostd.agentproc import AgentEvent, AgentSupervisor, Failed, Frozen, InstanceSpec, Ready
from haa.sdk.base import new_agent_id


def _summary(xs: list[float]) -> dict[str, float]:
    if not xs:
        return {"n": 0}
    xs = sorted(xs)
    p90 = xs[min(len(xs) - 1, round(0.9 * (len(xs) - 1)))]
    return {"n": len(xs), "median": statistics.median(xs), "p90": p90, "max": xs[-1], "min": xs[0],
            "mean": statistics.fmean(xs)}


class _Waiter:
    def __init__(self) -> None:
        self.events: list[AgentEvent] = []
        self.cond: asyncio.Event = asyncio.Event()

    def __call__(self, ev: AgentEvent) -> None:
        self.events.append(ev)
        self.cond.set()

    async def wait(self, pred: Any, timeout: float = 30.0) -> AgentEvent:
        end = time.monotonic() + timeout
        while True:
            for ev in self.events:
                if pred(ev):
                    self.events.remove(ev)
                    return ev
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError("benchmark: event not seen")
            self.cond.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.cond.wait(), left)


async def ameasure_spawn(n: int = 50, *, cold: bool = False, type_name: str = "probe", transfers: int = 10,
                         kills: int = 5) -> dict[str, Any]:
    """The figures of `measure_spawn` (async)."""
    w = _Waiter()
    sup = AgentSupervisor("bench", w, heartbeat_period=0.5, hang_timeout=5.0, cold_start=cold)
    t0 = time.perf_counter()
    await sup.start()
    start_s = time.perf_counter() - t0
    hello: list[float] = []
    ready: list[float] = []
    freeze: list[float] = []
    thaw: list[float] = []
    kill: list[float] = []
    rss: list[int] = []
    uss: list[int] = []
    ids: list[str] = []
    try:
        for i in range(n):
            a = new_agent_id()
            t0 = time.perf_counter()
            await sup.spawn(InstanceSpec(a, f"A{i + 1}", type_name, b"{}", epoch=1))
            t1 = time.perf_counter()
            sup.start_fresh(a)
            await w.wait(lambda ev, a=a: isinstance(ev, Ready) and ev.agent_id == a)
            t2 = time.perf_counter()
            hello.append(t1 - t0)
            ready.append(t2 - t0)
            ids.append(a)
        for a in ids:
            try:
                mem = psutil.Process(sup.pid(a)).memory_full_info()
                rss.append(mem.rss)
                uss.append(mem.uss)
            except (psutil.Error, KeyError):
                pass
        for a in ids[:transfers]:
            t0 = time.perf_counter()
            sup.freeze(a)
            ev = await w.wait(lambda ev, a=a: isinstance(ev, Frozen) and ev.agent_id == a)
            t1 = time.perf_counter()
            assert isinstance(ev, Frozen)
            await sup.spawn(InstanceSpec(a, "T", type_name, b"{}", epoch=2))
            sup.thaw(a, ev.state, [])
            await w.wait(lambda ev, a=a: isinstance(ev, Ready) and ev.agent_id == a)
            t2 = time.perf_counter()
            freeze.append(t1 - t0)
            thaw.append(t2 - t1)
        for a in ids[transfers:transfers + kills]:
            pid = sup.pid(a)
            t0 = time.perf_counter()
            os.kill(pid, signal.SIGKILL)
            await w.wait(lambda ev, a=a: isinstance(ev, Failed) and ev.agent_id == a)
            kill.append(time.perf_counter() - t0)
    finally:
        await sup.close()
    return {
        "mode": "cold (exec)" if cold else "fork server",
        "type": type_name,
        "agents": n,
        "forkserver_start_s": start_s,
        "spawn_to_hello_s": _summary(hello),
        "spawn_to_ready_s": _summary(ready),
        "freeze_to_frozen_s": _summary(freeze),
        "spawn_thaw_to_ready_s": _summary(thaw),
        "kill9_to_failed_s": _summary(kill),
        "rss_mib_mean": statistics.fmean(rss) / 2**20 if rss else None,
        "uss_mib_mean": statistics.fmean(uss) / 2**20 if uss else None,
    }


def measure_spawn(n: int = 50, *, cold: bool = False, type_name: str = "probe", transfers: int = 10,
                  kills: int = 5) -> dict[str, Any]:
    """Spawn `n` agents one after the other (keeping them alive) and time each step; see the module docstring.

    Returns {"spawn_to_ready_s": {"median", "p90", "max", ...}, "spawn_to_hello_s": ..., "freeze_to_frozen_s",
    "spawn_thaw_to_ready_s", "kill9_to_failed_s", "forkserver_start_s", "rss_mib_mean", "uss_mib_mean"}.
    """
    from haa.sdk.runner import run_loop  # uvloop unless HAA_EVENT_LOOP=asyncio, as in haa-hostd

    return run_loop(ameasure_spawn(n, cold=cold, type_name=type_name, transfers=transfers, kills=kills))


async def ameasure_throughput(count: int = 20000, size: int = 100) -> dict[str, Any]:
    """Messages/s from one agent to another through their host (both on one supervisor)."""
    from haa.lab.experiments.localhosts import LocalHosts

    async with LocalHosts(("h1",), heartbeat_period=0.5, hang_timeout=10.0) as hosts:
        a = await hosts.create("probe", {"record": False})
        b = await hosts.create("probe", {"record": False})
        t0 = time.perf_counter()
        await hosts.request(a, {"op": "send", "to": b, "count": count, "size": size}, timeout=300)
        t1 = time.perf_counter()
        got = await hosts.request_json(b, {"op": "state"}, timeout=300)  # queued behind every message
        t2 = time.perf_counter()
    return {"count": count, "size": size, "received": got["received"], "send_s": t1 - t0, "total_s": t2 - t0,
            "msgs_per_s": count / (t2 - t0), "mib_per_s": count * size / (t2 - t0) / 2**20}


def measure_throughput(count: int = 20000, size: int = 100) -> dict[str, Any]:
    from haa.sdk.runner import run_loop

    return run_loop(ameasure_throughput(count, size))


def machine() -> dict[str, Any]:
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "load_1min": os.getloadavg()[0],
            "event_loop": os.environ.get("HAA_EVENT_LOOP", "uvloop")}


def run_agents_bench(n: int = 50, cold_n: int = 10, messages: int = 20000) -> dict[str, Any]:
    """The whole benchmark (`haactl bench agents`): `n` spawns through the fork server, `cold_n` by exec (0 =
    skip), and the throughput of `messages` messages of 100 and 10 000 bytes. Returns {"machine", "rows",
    "throughput"}, what bench-results/agents.json holds."""
    logging.getLogger("haa.hostd.agents").setLevel(logging.ERROR)  # the kills are on purpose
    rows = [measure_spawn(n)]
    if cold_n:
        rows.append(measure_spawn(cold_n, cold=True, transfers=min(5, cold_n), kills=0))
    tput = [measure_throughput(messages, size) for size in (100, 10_000)]
    return {"machine": machine(), "rows": rows, "throughput": tput}
