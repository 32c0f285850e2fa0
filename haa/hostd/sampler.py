"""The statistics sampler of one haa-hostd: a time series of what this host measured, in its data dir.

Why: after a run (a mission, a chaos plan, a crash) you want to know what every host saw — how busy it and
each of its agents were, who talked to whom, how long commits took, how big the DDB grew, when the view
changed — also for hosts that crashed. So every host writes it down itself while it runs, to a file that
outlives the process; `haactl stats collect` later packs the file into the host's bundle (haa.lab.stats.collect)
and `haactl report` draws it (haa.lab.stats.report). Nothing here talks to other hosts.

How: `StatsSampler(rt, period, agents)` is started by the daemon (haa.hostd.daemon.serve) next to its `HostRuntime`
and agent driver (None without agents) and, every `period` seconds (default 1 s, `haa-hostd --stats-period`,
0 = off), appends one JSON line to `<data dir>/stats.jsonl` (flushed at once: a SIGKILL loses at most the
sample being built). It only *reads* what the runtime and the driver already keep; it adds no bookkeeping to
the hot paths. It lives next to the daemon, its only user; `haa.lab.stats` reads the files it writes.

Each sample's keys, and where they are read:

* `ts`, `host`, `inc`, `seq` — unix time, this host, its incarnation, the sample's number;
* `cpu`, `cpu_s`, `rss` — this haa-hostd process (psutil): its share of one core since the last sample, its
  CPU seconds, its RSS in bytes;
* `member`, `view`, `members`, `leader` — the group as this host sees it (membership state);
* `agents` — per agent process running here: name, type, epoch, state, `cpu` (share of one core), `rss`,
  `handled`, `mailbox` — the agent supervisor's own measurements (`AgentSupervisor.stats`);
* `table` — the replicated agent table (the same on every member): agents per status, backup bytes;
* `pairs` — messages and bytes an agent here sent to another agent since the last sample,
  `{"<src id>><dst id>": [n, bytes]}` (the supervisor's per-peer counters);
* `counters` — every runtime, transport and core counter (`HostRuntime.all_counters`: OAC committed,
  aborted, delivered, bytes per message kind, view changes, ...) whose value changed since the last sample,
  absolute values; every FULL_EVERY-th sample has them all (`full`);
* `oac` — histograms (bucket upper bounds `HIST_BOUNDS_MS`, counts) of the propose->decide (`p2d`) and
  decide->deliver (`d2d`) latencies of the transactions decided / delivered since the last sample (the
  runtime's own latency samples);
* `timeline` — the agent timeline events logged here since the last sample, by kind (spawning, active,
  freezing, thawed, crashed, recovered, ...: the agent driver's timeline);
* `ddb` — objects, bytes and bytes per key prefix (`ddb_prefix`) of the replica, recomputed only when the
  replica changed, at most every `ddb_every` samples;
* `cost_s` — the CPU seconds (time.thread_time) this sampler has spent so far: its own cost, measured.

A first line `{"kind": "config", ...}` holds the host's settings (the token left out) and the histogram
bounds; `config.json` in the data dir holds the same. The file is rotated to `stats.1.jsonl` at
`max_bytes` (64 MiB: ~10 hours of a busy host at 1 s).

Measured cost (docs/stats.md): ~0.1-0.3 ms of CPU per sample on a host with a few agents, i.e. well under
0.1 % of a core per host at 1 s — under 1 % of a core for a 10-host cluster.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import logging
import os
import time
from bisect import bisect_left
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import psutil

from haa.hostd.logs import log_event

if TYPE_CHECKING:
    from haa.hostd.agentdriver import AgentDriver
    from haa.hostd.runtime import HostRuntime

log = logging.getLogger("haa.hostd.stats")

STATS_FILE = "stats.jsonl"
OLD_STATS_FILE = "stats.1.jsonl"
CONFIG_FILE = "config.json"
#: histogram bucket upper bounds, milliseconds (the last bucket, above the last bound, is +inf)
HIST_BOUNDS_MS = (0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000)
#: every this many samples, all counters are written (not only those that changed)
FULL_EVERY = 60
#: settings keys never written (secrets)
SECRET_KEYS = frozenset({"token"})


def ddb_prefix(key: str) -> str:
    """The prefix a key is counted under: its first two path components when it has three or more
    (`slam/raw/s1/17` -> `slam/raw`, `chaos/log/A1` -> `chaos/log`) or lies in `slam/`, whose second level
    is the kind of data (`slam/map`); else its first (`demo/A1` -> `demo`, `mission/status` -> `mission`)."""
    parts = key.split("/", 2)
    if len(parts) >= 3 or (len(parts) == 2 and parts[0] == "slam"):
        return f"{parts[0]}/{parts[1]}"
    return parts[0]


def histogram(values_s: Any) -> list[int]:
    """Counts per bucket of `HIST_BOUNDS_MS` (+ one above the last bound) of latencies given in seconds."""
    counts = [0] * (len(HIST_BOUNDS_MS) + 1)
    for v in values_s:
        counts[bisect_left(HIST_BOUNDS_MS, v * 1000.0)] += 1
    return counts


def _plain(obj: Any) -> Any:
    """Settings as JSON: dataclasses to dicts, paths and others to strings, secrets dropped."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.name not in SECRET_KEYS}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items() if k not in SECRET_KEYS}
    if isinstance(obj, list | tuple | set | frozenset):
        return [_plain(v) for v in obj]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)


class StatsSampler:
    """Samples one host's statistics every `period` s into `<data dir>/stats.jsonl` (module docstring)."""

    def __init__(self, rt: HostRuntime, period: float = 1.0, agents: AgentDriver | None = None,
                 path: Path | None = None, max_bytes: int = 64 << 20, ddb_every: int = 5) -> None:
        if not period > 0:
            raise ValueError(f"stats period must be > 0, got {period}")
        self.rt = rt
        self.agents = agents
        self.period = period
        d = rt.config.data_dir
        self.path = path or (Path(d) / STATS_FILE if d is not None else None)
        self.max_bytes = max_bytes
        self.ddb_every = max(1, ddb_every)
        self.seq = 0
        self.cost_s = 0.0
        self._proc = psutil.Process()
        self._task: asyncio.Task[None] | None = None
        self._file: Any = None
        self._last_cpu: tuple[float, float] | None = None  # (monotonic, cpu seconds)
        self._last_counters: dict[str, int] = {}
        self._last_pairs: dict[tuple[str, str], tuple[int, int]] = {}
        self._last_delivered = 0
        self._last_p2d_len = 0
        self._last_decided = 0
        self._last_timeline: object | None = None
        self._ddb_key: tuple[int, int] | None = None  # (replica object id, seq) of the last DDB breakdown
        self._ddb: dict[str, Any] = {}
        self._ddb_age = 0

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        if self.path is None or self._task is not None:
            return
        self._open()
        cfg = {"kind": "config", "ts": round(time.time(), 6), "host": self.rt.name, "period": self.period,
               "hist_bounds_ms": list(HIST_BOUNDS_MS), "pid": os.getpid(), "settings": _plain(self.rt.config)}
        self._write(cfg)
        with contextlib.suppress(OSError):
            (self.path.parent / CONFIG_FILE).write_text(json.dumps(cfg, indent=1, default=str) + "\n")
        self._task = asyncio.get_running_loop().create_task(self._loop())

    async def stop(self) -> None:
        """Take a last sample and close the file."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
            self.tick()
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None

    async def _loop(self) -> None:
        loop = asyncio.get_running_loop()
        due = loop.time()
        # a sample at once: a host killed within its first period still leaves one (a restarted container,
        # killed again as soon as it had joined, left none of its second life under load) — once the runtime
        # has its incarnation (0 until its node is made: a sample of incarnation 0 is nobody's life)
        await asyncio.sleep(0)
        while self.rt.ident.inc == 0 and loop.time() - due < self.period:
            await asyncio.sleep(0.01)
        self.tick()
        while True:
            due += self.period
            await asyncio.sleep(max(0.0, due - loop.time()))
            if loop.time() - due > self.period:  # the loop stalled: don't catch up with a burst
                due = loop.time()
            self.tick()

    def _open(self) -> None:
        assert self.path is not None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - kept open for the run

    def _write(self, rec: dict[str, Any]) -> None:
        f = self._file
        if f is None:
            return
        try:
            f.write(json.dumps(rec, separators=(",", ":"), default=str) + "\n")
            f.flush()
            if f.tell() > self.max_bytes and self.path is not None:
                f.close()
                os.replace(self.path, self.path.parent / OLD_STATS_FILE)
                self._open()
                self._last_counters = {}  # the new file starts with every counter
        except OSError as e:
            self._file = None
            log_event(log, logging.WARNING, "stats_unwritable", error=str(e))

    # ------------------------------------------------------------------ one sample

    def tick(self) -> None:
        """One sample, written. `cost_s` counts this sample's building and the previous samples' writing.
        None before the runtime has its incarnation."""
        if self.rt.ident.inc == 0:
            return
        t0 = time.thread_time()
        try:
            rec = self.sample()
        except Exception as e:  # never take the host down for a statistic
            log_event(log, logging.ERROR, "stats_failed", error=f"{type(e).__name__}: {e}")
            return
        rec["cost_s"] = round(self.cost_s + time.thread_time() - t0, 6)
        self._write(rec)
        self.cost_s += time.thread_time() - t0

    def sample(self) -> dict[str, Any]:
        rt = self.rt
        now, mono = time.time(), time.monotonic()
        self.seq += 1
        rec: dict[str, Any] = {"ts": round(now, 6), "host": rt.name, "inc": rt.ident.inc, "seq": self.seq}
        with self._proc.oneshot():
            ct = self._proc.cpu_times()
            rss = self._proc.memory_info().rss
        cpu_s = ct.user + ct.system
        if self._last_cpu is not None and mono > self._last_cpu[0]:
            rec["cpu"] = round(max(0.0, (cpu_s - self._last_cpu[1]) / (mono - self._last_cpu[0])), 4)
        self._last_cpu = (mono, cpu_s)
        rec["cpu_s"] = round(cpu_s, 3)
        rec["rss"] = rss
        self._group(rec)
        self._agents(rec)
        self._counters(rec)
        self._oac(rec)
        self._timeline(rec)
        return rec

    def _group(self, rec: dict[str, Any]) -> None:
        node = self.rt.mnode
        if node is None:
            return
        st = node.state
        rec["member"] = bool(node.is_member())
        rec["view"] = st.view
        rec["members"] = len(st.members)
        lead = st.leader()
        rec["leader"] = lead.name if lead else ""
        table = st.agents
        by_status: Counter[str] = Counter()
        backup_bytes = 0
        for r in table:
            by_status[r.status] += 1
            if r.backup:
                backup_bytes += len(r.backup)
        rec["table"] = {"agents": len(table), "status": dict(by_status), "backup_bytes": backup_bytes}
        self._ddb_age += 1
        ddb = st.ddb
        key = (id(ddb), ddb.seq)
        if key != self._ddb_key and (self._ddb_age >= self.ddb_every or self._ddb_key is None
                                     or key[0] != self._ddb_key[0]):
            by: Counter[str] = Counter()
            total = 0
            for k, obj in ddb._objects.items():
                by[ddb_prefix(k)] += obj.size
                total += obj.size
            self._ddb = {"objects": ddb.size, "bytes": total, "by_prefix": dict(by), "seq": ddb.seq}
            self._ddb_key, self._ddb_age = key, 0
        if self._ddb:
            rec["ddb"] = self._ddb

    def _agents(self, rec: dict[str, Any]) -> None:
        drv = self.agents
        if drv is None:
            return
        agents: dict[str, Any] = {}
        pairs: dict[str, list[int]] = {}
        seen: dict[tuple[str, str], tuple[int, int]] = {}
        for aid, st in drv.sup.stats().items():
            agents[aid] = {"name": st.name, "type": st.type_name, "epoch": st.epoch, "state": st.state,
                           "cpu": round(st.cpu, 4), "rss": st.rss, "handled": st.handled, "mailbox": st.mailbox}
            for dst, b in st.bytes_out.items():
                if not dst:
                    continue
                n = st.msgs_out.get(dst, 0)
                k = (aid, dst)
                seen[k] = (n, b)
                pn, pb = self._last_pairs.get(k, (0, 0))
                if n < pn or b < pb:  # a new instance counts from 0
                    pn = pb = 0
                if n > pn or b > pb:
                    pairs[f"{aid}>{dst}"] = [n - pn, b - pb]
        self._last_pairs = seen
        rec["agents"] = agents
        if pairs:
            rec["pairs"] = pairs

    def _counters(self, rec: dict[str, Any]) -> None:
        c = self.rt.all_counters()
        full = self.seq % FULL_EVERY == 1 or not self._last_counters
        last = self._last_counters
        changed = {k: v for k, v in c.items() if full or last.get(k) != v}
        self._last_counters = dict(c)
        if changed:
            rec["counters"] = changed
        if full:
            rec["full"] = True

    def _oac(self, rec: dict[str, Any]) -> None:
        rt = self.rt
        out: dict[str, list[int]] = {}
        d2d = rt.proposals.decide_to_deliver
        delivered = rt.counters.get("oac_delivered", 0)
        new = min(len(d2d), max(0, delivered - self._last_delivered))
        self._last_delivered = delivered
        if new:
            out["d2d"] = histogram(itertools.islice(reversed(d2d), new))
        # propose->decide: one sample per decided transaction this host proposed; the deque's growth says how
        # many are new (once it is full, the decided count since the last sample bounds them)
        p2d = rt.proposals.propose_to_decide
        n = len(p2d)
        decided = rt.counters.get("oac_committed", 0) + rt.counters.get("oac_aborted", 0)
        if n < self._last_p2d_len:  # cleared (Latencies with reset): all of them are new
            self._last_p2d_len = 0
        new = n - self._last_p2d_len
        if p2d.maxlen is not None and n == p2d.maxlen:
            new = min(n, max(new, decided - self._last_decided))
        self._last_p2d_len, self._last_decided = n, decided
        if new > 0:
            out["p2d"] = histogram(itertools.islice(reversed(p2d), new))
        if out:
            rec["oac"] = out

    def _timeline(self, rec: dict[str, Any]) -> None:
        drv = self.agents
        if drv is None or not drv.timeline:
            return
        kinds: Counter[str] = Counter()
        last = self._last_timeline
        for item in reversed(drv.timeline):
            if item is last:
                break
            kinds[item["event"]] += 1
        self._last_timeline = drv.timeline[-1]
        if kinds:
            rec["timeline"] = dict(kinds)
