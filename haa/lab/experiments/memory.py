"""RSS of every host and event-loop stalls under maximum-size traffic (`haactl bench memory`), real processes.

A local group of 4 membership-mode `haa-hostd` processes (h1-h3 core, agents on) is driven for `seconds`
with the largest requests the limits accept (docs/limits.md, "Sizes and memory"), in a loop, each through
the next host in turn:

* `ddb`: a DDB batch of MAX_BATCH_BYTES (blob values of just under MAX_VALUE_BYTES; the same keys every
  time, so the replicas' contents stay the same size) and one of MAX_BATCH_JSON_BYTES of the costliest JSON
  there is to check (`[{},{},...]`);
* `ddb_ops_put`, `ddb_ops_add`, `ddb_ops_delete`: batches of MAX_BATCH_OPS tiny ops (bytes do not bound their
  work): puts that create as many keys, adds to counters, then deletes of those keys;
* `spawn`: a probe agent with a config of MAX_CONFIG bytes;
* `message`: operator messages of MAX_AGENT_MESSAGE bytes to it, and a request that makes its state (the
  probe's "value") MAX_STATE bytes large;
* `backup`: a backup of that state, committed to every host;
* `transfer`: a move of the agent to another host (freeze, release with its state, claim, thaw);
* `remove`: the agent is removed (a new one is spawned in the next round).

A sampler reads every host's RSS (psutil) every `interval` seconds. Each host's stall watchdog
(haa.hostd.resources.LoopWatch) logs every event-loop stall of 50 ms or more (`loop_stall`); the stalls are
attributed to the step that was running. The result (also written to bench-results/memory.json by the
command): per host the RSS at start, peak, at the end of the traffic and `settle` seconds later; the largest
stall per step; whether the view changed (a host removed = a failure of this bench's purpose).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from haa.cluster.hostprocs import MemberGroup, MemberHost, wait_for
from haa.core.ddb import agenttable as at
from haa.core.ddb import objects as ddb
from haa.core.ddb import ops
from haa.core.ddb.ops import encode_batch, put
from haa.sdk.channel import MAX_AGENT_MESSAGE

NAMES = ["h1", "h2", "h3", "h4"]
CORE = ["h1", "h2", "h3"]
ARGS = ["--rebalance-period", "0"]
MiB = 1 << 20


def start_group(root: Path, token: str, names: list[str] = NAMES, args: list[str] = ARGS) -> dict[str, MemberHost]:
    """Start a membership group on loopback and wait until every host sees every other as a member."""
    group = MemberGroup(root, names, core=[n for n in names if n in CORE], token=token, args=args)
    group.form(60, what="a group of 4")
    return group.hosts


def max_blob_batch(prefix: str = "bench/mem/blob") -> list[Any]:
    """Put ops of blob values that fill one batch up to MAX_BATCH_BYTES (each value just under the value limit)."""
    n = ddb.MAX_BATCH_BYTES // ddb.MAX_VALUE_BYTES
    size = ddb.MAX_VALUE_BYTES - 1024
    ops = [put(f"{prefix}/{i}", "blob", bytes([i]) * size) for i in range(n)]
    encode_batch(ops)  # raises if over the limit
    return ops


def max_json_batch(prefix: str = "bench/mem/json") -> list[Any]:
    """Put ops of JSON values of the costliest kind to check (arrays of empty objects), up to the JSON bounds."""
    per = min(ddb.MAX_JSON_VALUE_BYTES, ddb.MAX_BATCH_JSON_BYTES)
    n = max(1, ddb.MAX_BATCH_JSON_BYTES // per)
    text = ("[" + ",".join(["{}"] * ((per - 2) // 3)) + "]").encode()
    ops = [put(f"{prefix}/{i}", "json", json.loads(text)) for i in range(n)]
    encode_batch(ops)
    return ops


def max_config() -> bytes:
    """A probe agent config of exactly MAX_CONFIG bytes (valid JSON)."""
    head = b'{"record": false, "value": "'
    return head + b"c" * (at.MAX_CONFIG - len(head) - 2) + b'"}'


class Sampler(threading.Thread):
    """RSS of every host process every `interval` seconds."""

    def __init__(self, hosts: dict[str, MemberHost], interval: float) -> None:
        super().__init__(daemon=True)
        self.hosts = hosts
        self.interval = interval
        self.samples: dict[str, list[tuple[float, int]]] = {n: [] for n in hosts}
        self.halt = threading.Event()
        self.t0 = time.monotonic()

    def run(self) -> None:
        procs = {n: psutil.Process(h.proc.pid) for n, h in self.hosts.items() if h.proc is not None}
        while not self.halt.is_set():
            t = time.monotonic() - self.t0
            for n, p in procs.items():
                with contextlib.suppress(psutil.Error):
                    self.samples[n].append((round(t, 2), p.memory_info().rss))
            self.halt.wait(self.interval)


class Traffic:
    """The request loop (see the module docstring). `steps` records (step, start, end, ok, detail)."""

    def __init__(self, hosts: dict[str, MemberHost], log: Callable[[str], None] = print) -> None:
        self.hosts = hosts
        self.names = list(hosts)
        self.log = log
        self.turn = 0
        self.steps: list[dict[str, Any]] = []
        self.blob_ops = max_blob_batch()
        self.json_ops = max_json_batch()
        n = ddb.MAX_BATCH_OPS
        self.put_ops = [ops.put(f"bench/mem/ops/{i:05d}", "blob", b"x") for i in range(n)]
        self.add_ops = [ops.add(f"bench/mem/ctr/{i % 100}", 1) for i in range(n)]
        self.del_ops = [ops.delete(f"bench/mem/ops/{i:05d}") for i in range(n)]
        self.config = max_config()
        self.message = b"m" * MAX_AGENT_MESSAGE
        self.messages = 2
        # the probe's state is {"value": ..., "messages": [], "events": [...]}: a value this long fills MAX_STATE
        self.set_state = json.dumps({"op": "set", "value": "s" * (at.MAX_STATE - 4096)}).encode()

    def _next(self) -> MemberHost:
        self.turn += 1
        return self.hosts[self.names[self.turn % len(self.names)]]

    def _step(self, name: str, fn: Callable[[], Any]) -> Any:
        t0 = time.time()
        ok, detail, out = True, "", None
        try:
            out = fn()
        except Exception as e:  # a failed step is recorded, the loop goes on
            ok, detail = False, f"{type(e).__name__}: {str(e)[:200]}"
        self.steps.append({"step": name, "t0": t0, "t1": time.time(), "ok": ok, "detail": detail})
        return out

    def _ddb(self, ops: list[Any]) -> None:
        r = self._next().client.ddb_write(ops, timeout=30)
        if not r.committed:
            raise RuntimeError(r.reason)

    def round(self) -> None:
        self._step("ddb", lambda: self._ddb(self.blob_ops))
        self._step("ddb_json", lambda: self._ddb(self.json_ops))
        self._step("ddb_ops_put", lambda: self._ddb(self.put_ops))
        self._step("ddb_ops_add", lambda: self._ddb(self.add_ops))
        self._step("ddb_ops_delete", lambda: self._ddb(self.del_ops))
        h = self._next()
        r = self._step("spawn", lambda: h.client.agent_spawn("probe", self.config, timeout=30))
        if r is None or not r.ok:
            if r is not None:
                self.steps[-1].update(ok=False, detail=r.reason)
            return
        agent = r.id
        try:
            owner = wait_for(lambda: self._active_owner(agent), 30, "the probe active")
            for _ in range(self.messages):
                self._step("message", lambda: self._send(agent))
            self._step("set_state", lambda: self._request(agent, self.set_state))
            self._step("backup", lambda: self._backup(agent))
            target = next(n for n in self.names if n != owner)
            self._step("transfer", lambda: self._move(agent, target))
        finally:
            self._step("remove", lambda: self._next().client.agent_remove(agent, timeout=30))

    def _active_owner(self, agent: str) -> str | None:
        for a in self._next().client.agent_list().agents:
            if a.id == agent and a.status == "active":
                runners = [x for h in self.hosts.values() for x in h.client.agent_list().agents
                           if x.id == agent and x.local_phase == "active"]
                return a.owner if runners else None
        return None

    def _send(self, agent: str) -> None:
        r = self._next().client.agent_send(agent, self.message)
        if not r.ok:
            raise RuntimeError(r.reason)

    def _request(self, agent: str, payload: bytes) -> None:
        r = self._next().client.agent_request(agent, payload, timeout=20)
        if not r.ok:
            raise RuntimeError(r.error)

    def _backup(self, agent: str) -> None:
        h = self._next()
        before = {a.id: a.has_backup for a in h.client.agent_list().agents}.get(agent, False)
        r = h.client.agent_request(agent, b'{"op": "backup"}', timeout=20)
        if not r.ok:
            raise RuntimeError(r.error)
        if not before:
            wait_for(lambda: any(a.id == agent and a.has_backup for a in h.client.agent_list().agents), 30,
                     "the backup committed")

    def _move(self, agent: str, target: str) -> None:
        r = self._next().client.agent_move(agent, target, timeout=30)
        if not r.ok:
            raise RuntimeError(r.reason)
        wait_for(lambda: self._active_owner(agent) == target, 40, f"the probe active on {target}")


def stalls(hosts: dict[str, MemberHost], since: float) -> list[dict[str, Any]]:
    """Every `loop_stall` the hosts logged since `since` (unix time): host, ts, ms."""
    out = []
    for n, h in hosts.items():
        for e in h.events(since, {"loop_stall"}):
            out.append({"host": n, "ts": e["ts"], "ms": e["fields"]["ms"], "cpu_ms": e["fields"].get("cpu_ms", 0)})
    return sorted(out, key=lambda s: s["ts"])


def attribute(steps: list[dict[str, Any]], events: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The largest stall per step kind (a stall counts for every step it overlaps)."""
    out: dict[str, dict[str, Any]] = {}
    for s in steps:
        d = out.setdefault(s["step"], {"count": 0, "failed": 0, "max_stall_ms": 0, "max_stall_cpu_ms": 0,
                                       "max_seconds": 0.0})
        d["count"] += 1
        d["failed"] += 0 if s["ok"] else 1
        d["max_seconds"] = round(max(d["max_seconds"], s["t1"] - s["t0"]), 3)
        for e in events:
            if e["ts"] - e["ms"] / 1000 <= s["t1"] and e["ts"] >= s["t0"]:  # the stall overlaps the step
                d["max_stall_ms"] = max(d["max_stall_ms"], e["ms"])
                d["max_stall_cpu_ms"] = max(d["max_stall_cpu_ms"], min(e["ms"], e["cpu_ms"]))
        if not s["ok"]:
            d.setdefault("errors", []).append(s["detail"])
            del d["errors"][:-3]
    return out


def run_memory_bench(
    seconds: float = 600.0,
    interval: float = 1.0,
    settle: float = 20.0,
    root: Path | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="haa-mem-") as tmp:
        base = root or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        hosts = start_group(base, "mem-bench-" + str(time.time_ns()))
        try:
            return _run(hosts, seconds, interval, settle, log)
        finally:
            for h in hosts.values():
                h.kill()


def _run(
    hosts: dict[str, MemberHost], seconds: float, interval: float, settle: float, log: Callable[[str], None]
) -> dict[str, Any]:
    first = next(iter(hosts.values()))
    view0 = first.status().view
    incs0 = {n: h.status().incarnation for n, h in hosts.items()}
    sampler = Sampler(hosts, interval)
    sampler.start()
    time.sleep(min(3 * interval, 3.0))
    traffic = Traffic(hosts, log)
    t_start = time.time()
    t_end = time.monotonic() + seconds
    rounds = 0
    while time.monotonic() < t_end:
        traffic.round()
        rounds += 1
        if rounds % 5 == 0:
            log(f"  {rounds} rounds, {len(traffic.steps)} requests, "
                f"RSS {', '.join(f'{n} {s[-1][1] / MiB:.0f}' for n, s in sampler.samples.items() if s)} MiB")
    t_traffic = time.monotonic() - sampler.t0
    time.sleep(settle)
    sampler.halt.set()
    sampler.join()
    events = stalls(hosts, t_start)
    st = {n: h.status() for n, h in hosts.items()}
    per_host = {}
    for n, samples in sampler.samples.items():
        during = [r for t, r in samples if t <= t_traffic]
        after = [r for t, r in samples if t > t_traffic]
        per_host[n] = {
            "rss_start_mib": round(samples[0][1] / MiB, 1) if samples else None,
            "rss_peak_mib": round(max(r for _, r in samples) / MiB, 1) if samples else None,
            "rss_end_of_traffic_mib": round(during[-1] / MiB, 1) if during else None,
            "rss_after_settle_mib": round(after[-1] / MiB, 1) if after else None,
            "loop_lag_max_ms": st[n].counters.values.get("loop_lag_max_ms", 0),
            "loop_stalls_over_250ms": st[n].counters.values.get("loop_stalls_over_250ms", 0),
            "malloc_trims": st[n].counters.values.get("malloc_trims", 0),
            "samples": [[t, round(r / MiB, 1)] for t, r in samples],
        }
    return {
        "seconds": seconds,
        "settle": settle,
        "rounds": rounds,
        "requests": len(traffic.steps),
        "limits": {
            "agent_config": at.MAX_CONFIG,
            "agent_state": at.MAX_STATE,
            "agent_message": MAX_AGENT_MESSAGE,
            "ddb_value": ddb.MAX_VALUE_BYTES,
            "ddb_json_value": ddb.MAX_JSON_VALUE_BYTES,
            "ddb_batch": ddb.MAX_BATCH_BYTES,
            "ddb_batch_json": ddb.MAX_BATCH_JSON_BYTES,
            "ddb_batch_ops": ddb.MAX_BATCH_OPS,
        },
        "steps": attribute(traffic.steps, events),
        "largest_stall_ms": max((e["ms"] for e in events), default=0),
        "largest_stall_cpu_ms": max((min(e["ms"], e["cpu_ms"]) for e in events), default=0),
        "load_average": list(os.getloadavg()),
        "view_changed": any(s.view != view0 for s in st.values()),
        "incarnations_changed": [n for n in hosts if st[n].incarnation != incs0[n]],
        "members": {n: sorted(s.members) for n, s in st.items()},
        "hosts": per_host,
    }
