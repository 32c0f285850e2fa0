"""A soak of a 5-host group under a mission-like load (`haactl bench soak`), real processes.

A local group of 5 membership-mode `haa-hostd` processes (h1-h3 core, agents on, the default rebalancing) is
driven for `minutes` with what a robot team does to it, all at once:

* DDB writes from `writers` threads, each through the next host in turn, paced (`write_rate` per second in all):
  small JSON and blob puts over a fixed set of keys (the replica's size stays bounded), adds to counters, log
  appends that are trimmed; the latency of every write (submit to committed reply) is recorded;
* spawns in bursts: every `burst_every` s a burst of `burst` counter agents (backups on), removed again one
  burst later, so that the agent table breathes instead of growing;
* agent messages: operator messages of 64 KiB to a live counter, a few per second;
* one host killed and restarted every `kill_every` s (SIGKILL, then the same name and data directory again
  after `down_s` seconds: it must be removed and rejoin), h4 and h5 in turn (never a core host, so that a kill
  never takes the core majority).

A sampler records every `interval` s each host's RSS (psutil) and the group's view; the hosts log their loop
stalls (`loop_stall`, 50 ms or more). The result (bench-results/soak.json, the figure docs/img/soak.png):
RSS per host over time (growth: the last fifth against the second fifth of the run), write latency per window
(p50 / p99 / failures), the largest stalls, and every view change with whether a kill explains it
("expulsions without a fault" must be 0).
"""

from __future__ import annotations

import contextlib
import json
import random
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.hostprocs import MemberGroup, MemberHost, wait_for
from haa.core.ddb import ops
from haa.lab.experiments.memory import stalls

NAMES = ["h1", "h2", "h3", "h4", "h5"]
CORE = ["h1", "h2", "h3"]
VICTIMS = ["h4", "h5"]
MiB = 1 << 20
MESSAGE = b"m" * (64 << 10)
WINDOW_S = 30.0


class Soak:
    """The load and the sampling of one soak (see the module docstring)."""

    def __init__(self, group: MemberGroup, *, minutes: float, writers: int, write_rate: float, burst: int,
                 burst_every: float, kill_every: float, down_s: float, interval: float,
                 log: Callable[[str], None]) -> None:
        self.group = group
        self.seconds = minutes * 60.0
        self.writers = writers
        self.write_rate = write_rate
        self.burst = burst
        self.burst_every = burst_every
        self.kill_every = kill_every
        self.down_s = down_s
        self.interval = interval
        self.log = log
        self.halt = threading.Event()
        self.t0 = time.monotonic()
        self.lock = threading.Lock()
        self.writes: list[tuple[float, float, bool]] = []  # (t, latency s, committed)
        self.rss: dict[str, list[tuple[float, float]]] = {n: [] for n in NAMES}
        self.views: list[tuple[float, list[str]]] = []
        self.kills: list[tuple[float, str, str]] = []  # (t, host, "kill" | "restart")
        self.spawned = 0
        self.removed = 0
        self.messages = 0
        self.message_failures = 0

    def now(self) -> float:
        return time.monotonic() - self.t0

    def host(self, name: str) -> MemberHost:
        return self.group.hosts[name]

    def alive_hosts(self) -> list[MemberHost]:
        return [h for h in self.group.hosts.values() if h.alive()]

    # ------------------------------------------------------------------ load

    def writer(self, k: int) -> None:
        rng = random.Random(f"soak-writer-{k}")
        period = self.writers / self.write_rate
        i = 0
        while not self.halt.is_set():
            hs = self.alive_hosts()
            if not hs:
                time.sleep(period)
                continue
            h = hs[(k + i) % len(hs)]
            kind = i % 4
            if kind == 0:
                batch = [ops.put(f"soak/json/{k}/{rng.randrange(200)}", "json", {"i": i, "x": rng.random()})]
            elif kind == 1:
                batch = [ops.put(f"soak/blob/{k}/{rng.randrange(200)}", "blob", rng.randbytes(rng.randrange(64, 4096)))]
            elif kind == 2:
                batch = [ops.add(f"soak/ctr/{rng.randrange(20)}", 1)]
            else:
                batch = [ops.log_append(f"soak/log/{k}", [rng.randbytes(256)])]
                if i % 400 == 3:
                    batch.append(ops.log_trim(f"soak/log/{k}", max(0, i // 4 - 50)))
            t = time.monotonic()
            ok = False
            with contextlib.suppress(Exception):
                ok = h.client.ddb_write(batch, timeout=10).committed
            with self.lock:
                self.writes.append((round(t - self.t0, 3), time.monotonic() - t, ok))
            i += 1
            self.halt.wait(max(0.0, period - (time.monotonic() - t)))

    def spawner(self) -> None:
        cohorts: list[list[str]] = []
        while not self.halt.wait(self.burst_every):
            hs = self.alive_hosts()
            if not hs:
                continue
            ids = []
            for j in range(self.burst):
                with contextlib.suppress(Exception):
                    r = hs[j % len(hs)].client.agent_spawn(
                        "counter", json.dumps({"period": 1.0, "backup_every": 5, "ddb": False}).encode(), timeout=20)
                    if r.ok:
                        ids.append(r.id)
            self.spawned += len(ids)
            cohorts.append(ids)
            if len(cohorts) > 1:  # the burst before the last goes: the table breathes
                for a in cohorts.pop(0):
                    with contextlib.suppress(Exception):
                        if self.alive_hosts()[0].client.agent_remove(a, timeout=20).ok:
                            self.removed += 1

    def messenger(self) -> None:
        while not self.halt.wait(0.3):
            hs = self.alive_hosts()
            if not hs:
                continue
            with contextlib.suppress(Exception):
                agents = [a for a in hs[0].client.agent_list().agents if a.status == "active"]
                if agents:
                    a = agents[self.messages % len(agents)]
                    ok = hs[self.messages % len(hs)].client.agent_send(a.id, MESSAGE).ok
                    self.messages += 1
                    self.message_failures += 0 if ok else 1

    def killer(self) -> None:
        turn = 0
        while not self.halt.wait(self.kill_every):
            name = VICTIMS[turn % len(VICTIMS)]
            turn += 1
            h = self.host(name)
            self.kills.append((round(self.now(), 2), name, "kill"))
            self.log(f"  t={self.now():6.0f} s: kill -9 {name}")
            with contextlib.suppress(Exception):
                h.kill9()
            if self.halt.wait(self.down_s):
                break
            h.start()
            self.kills.append((round(self.now(), 2), name, "restart"))

    def sampler(self) -> None:
        last: list[str] | None = None
        while not self.halt.is_set():
            t = round(self.now(), 2)
            for n, h in self.group.hosts.items():
                if h.proc is not None and h.alive():
                    with contextlib.suppress(psutil.Error):
                        self.rss[n].append((t, psutil.Process(h.proc.pid).memory_info().rss / MiB))
            with contextlib.suppress(Exception):
                members = sorted(self.host("h1").status().members)
                if members != last:
                    self.views.append((t, members))
                    last = members
            self.halt.wait(self.interval)

    # ------------------------------------------------------------------ the run

    def run(self) -> dict[str, Any]:
        t_start = time.time()
        threads = [threading.Thread(target=self.writer, args=(k,), daemon=True) for k in range(self.writers)]
        threads += [threading.Thread(target=f, daemon=True)
                    for f in (self.spawner, self.messenger, self.killer, self.sampler)]
        for th in threads:
            th.start()
        next_log = 60.0
        while self.now() < self.seconds:
            time.sleep(1.0)
            if self.now() >= next_log:
                next_log += 60.0
                with self.lock:
                    recent = [w for w in self.writes if w[0] > self.now() - 60]
                lat = sorted(w[1] for w in recent if w[2])
                p99 = lat[int(0.99 * (len(lat) - 1))] * 1e3 if lat else float("nan")
                self.log(f"  t={self.now():6.0f} s: {len(recent)} writes in the last minute, p99 {p99:.0f} ms, "
                         f"RSS {', '.join(f'{n} {s[-1][1]:.0f}' for n, s in self.rss.items() if s)} MiB, "
                         f"{self.spawned} spawned / {self.removed} removed")
        self.halt.set()
        for th in threads:
            th.join(30)
        for name in VICTIMS:  # a victim still down at the end comes back, so that every host's stalls are read
            h = self.host(name)
            if not h.alive():
                h.start()
        with contextlib.suppress(Exception):
            wait_for(lambda: len(self.host("h1").status().members) == len(NAMES), 60, "every host back")
        return self.result(stalls(self.group.hosts, t_start))

    def result(self, stall_events: list[dict[str, Any]]) -> dict[str, Any]:
        n = int(self.seconds // WINDOW_S) + 1
        windows = []
        for i in range(n):
            ws = [w for w in self.writes if i * WINDOW_S <= w[0] < (i + 1) * WINDOW_S]
            lat = sorted(w[1] * 1e3 for w in ws if w[2])
            windows.append({
                "t": i * WINDOW_S, "writes": len(ws), "failed": sum(not w[2] for w in ws),
                "p50_ms": round(statistics.median(lat), 1) if lat else None,
                "p99_ms": round(lat[int(0.99 * (len(lat) - 1))], 1) if lat else None,
            })
        growth = {}
        for name, samples in self.rss.items():
            fifth = self.seconds / 5
            early = [r for t, r in samples if fifth <= t < 2 * fifth]
            late = [r for t, r in samples if t >= 4 * fifth]
            growth[name] = {
                "rss_second_fifth_mib": round(statistics.median(early), 1) if early else None,
                "rss_last_fifth_mib": round(statistics.median(late), 1) if late else None,
                "rss_peak_mib": round(max((r for _, r in samples), default=0.0), 1),
            }
        # a view change is explained by a kill when a victim left within 30 s after its kill, or came back
        removals = []
        prev: list[str] | None = None
        for t, members in self.views:
            if prev is not None:
                for gone in sorted(set(prev) - set(members)):
                    killed = any(h == gone and k == "kill" and 0 <= t - tk <= 30 for tk, h, k in self.kills)
                    removals.append({"t": t, "host": gone, "after_kill": killed})
            prev = members
        lat_all = sorted(w[1] * 1e3 for w in self.writes if w[2])
        return {
            "minutes": self.seconds / 60,
            "hosts": NAMES,
            "writes": len(self.writes),
            "writes_failed": sum(not w[2] for w in self.writes),
            "write_p50_ms": round(statistics.median(lat_all), 1) if lat_all else None,
            "write_p99_ms": round(lat_all[int(0.99 * (len(lat_all) - 1))], 1) if lat_all else None,
            "spawned": self.spawned,
            "removed": self.removed,
            "messages": self.messages,
            "message_failures": self.message_failures,
            "kills": self.kills,
            "removals": removals,
            "expulsions_without_fault": sum(not r["after_kill"] for r in removals),
            "largest_stalls": sorted(stall_events, key=lambda s: -s["ms"])[:10],
            "stalls_over_500ms": sum(s["ms"] >= 500 for s in stall_events),
            "rss": growth,
            "windows": windows,
            "rss_samples": {n: [[t, round(r, 1)] for t, r in s] for n, s in self.rss.items()},
        }


def run_soak(minutes: float = 30.0, *, writers: int = 4, write_rate: float = 40.0, burst: int = 20,
             burst_every: float = 60.0, kill_every: float = 180.0, down_s: float = 15.0, interval: float = 2.0,
             root: Path | None = None, log: Callable[[str], None] = print) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="haa-soak-") as tmp:
        base = root or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        group = MemberGroup(base, NAMES, core=CORE, token="soak-" + str(time.time_ns()))
        try:
            group.form(60, what="a group of 5")
            soak = Soak(group, minutes=minutes, writers=writers, write_rate=write_rate, burst=burst,
                        burst_every=burst_every, kill_every=kill_every, down_s=down_s, interval=interval, log=log)
            res = soak.run()
            res["load"] = {"writers": writers, "write_rate": write_rate, "burst": burst, "burst_every": burst_every,
                           "kill_every": kill_every, "down_s": down_s, "message_bytes": len(MESSAGE)}
            return res
        finally:
            group.close()


def plot_soak(res: dict[str, Any], path: Path) -> None:
    """RSS per host, write latency per window and the kills over time (docs/img/soak.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for name, samples in res["rss_samples"].items():
        if samples:
            a1.plot([t / 60 for t, _ in samples], [r for _, r in samples], label=name, lw=1)
    a1.set_ylabel("RSS (MiB)")
    a1.legend(ncol=5, fontsize=8)
    ws = [w for w in res["windows"] if w["p99_ms"] is not None]
    a2.plot([w["t"] / 60 for w in ws], [w["p50_ms"] for w in ws], label="write p50")
    a2.plot([w["t"] / 60 for w in ws], [w["p99_ms"] for w in ws], label="write p99")
    a2.set_yscale("log")
    a2.set_ylabel(f"commit latency per {WINDOW_S:.0f} s (ms)")
    a2.set_xlabel("minutes")
    for t, _h, k in res["kills"]:
        if k == "kill":
            for ax in (a1, a2):
                ax.axvline(t / 60, color="grey", lw=0.6, ls=":")
    a2.legend(fontsize=8)
    fig.suptitle(f"soak: 5 hosts, {res['minutes']:.0f} min, kill -9 of h4/h5 every "
                 f"{res['load']['kill_every']:.0f} s (dotted)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
