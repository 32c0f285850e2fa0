"""Experiment AP-4 (thesis §7.2.4): spawn, freeze, transfer and recovery delays vs. group size, real processes.

`haactl bench ap4` starts n = 2, 4, 6, 8, 10 membership-mode `haa-hostd` processes on loopback (h1-h3 core,
`--rebalance-period 0`, so that only the benchmark's actions move agents) and runs, `reps` times each, on
agents of the `ballast` type (haa.lab.experiments.benchagents) whose state is 111 kB of incompressible bytes — the
thesis' average agent state:

* spawn: `AgentSpawn` (through h1, h2, ... in turn) of a new ballast agent; it is removed again after each
  sample, and each spawn waits until no allocation session has started for 1.2 s, so that the leader's rate
  limit (one session per `min_session_gap` = 1 s) does not add to it. Measured from the request to the host's
  timeline event "active" (the agent was allocated in a session, its process forked and told to start),
  and to the agent's own ready stamp (`bench/ready/<id>`, written by the agent when `on_start` runs).
  Breakdown: request -> "created" (the OAC(create) applied), -> "spawning" (the session's allocation applied
  at the chosen host).
* transfer: `AgentMove` of one ballast agent B to another host (targets in turn). freeze = request -> the
  old host's "frozen" event (OAC(release) with the 111 kB state applied: the thesis' "agent submitting its
  frozen state to the DDB"); transfer = request -> the new host's "thawed" event (the shell got the state
  and the queued messages), and -> B's ready stamp (`on_resume("thaw")` ran in the new process).
  First `reps` transfers with no traffic ("transfer_idle"), then `reps` while a `pinger` agent on h1 sends
  B the request b"ping" every 5 ms (as for the crashes below); `unreachable` is the longest gap between two
  consecutive replies around the action, `max_rtt` the longest round trip.
* agent crash: `AgentKill` (SIGKILL of B's process) on B's owner. detection = kill -> the owner's first
  "crashed" event (the supervisor saw the process die); recovery (after detection, as the thesis reports
  it: "does not include the time taken to detect an agent failure") = first "crashed" -> "recovered" (the
  shell got the latest backup, 111 kB); total = kill -> "recovered".
* host crash: SIGKILL of the haa-hostd that runs B (never h1, which runs the pinger and takes the control
  calls; B is moved off h1 first when needed). removal = kill -> the first survivor's view without it
  (from the hosts' JSON-lines logs); recovery after removal = that view -> "recovered" (this includes the
  allocation session that the membership change starts); total = kill -> "recovered". The host is then
  restarted (a new incarnation joins again) before the next sample. Only for n >= 3: a group of two blocks
  for ever if a transaction is in flight when one of its two hosts crashes (the OAC tolerates f < n/2,
  docs/oac.md, docs/membership.md "fault gate"), and with agents running one often is.

docs/bench-agents.md has the choices where the thesis is vague, the results and what the time is spent on.

Clocks: every timestamp is unix time taken on this one machine (the timeline events' `time`, the log
lines' `ts`, the agents' stamps, the benchmark's own `time.time()` before each request), so differences
across processes are meaningful. The timeline comes from each host's `AgentEvents` stream (a thread per
host, reconnecting across restarts). Nothing here fails on a timing: a sample whose end event does not
come within the timeout is recorded as missing and counted.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import grpc

from haa.cluster.hostprocs import MemberGroup, MemberHost, wait_for
from haa.lab.experiments.ap1 import percentile
from haa.lab.experiments.benchagents import THESIS_STATE_BYTES

HOSTS = (2, 4, 6, 8, 10)
CORE = 3
#: no periodic sessions; and an instance counts as up 0.2 s after its start: AP-4 measures one crash at a
#: time, but kills each agent again within a second of its recovery, which the default start grace (10 s)
#: would treat as a crash loop and back off (issue 14: that was the 0.8-1.2 s "recovery" of late 2026-11)
HOSTD_ARGS = ["--rebalance-period", "0", "--agent-start-grace", "0.2"]
#: the leader starts at most one session per second (AgentConfig.min_session_gap); spawns wait this long
SESSION_GAP = 1.2
#: how long one action may take before the sample is recorded as missing
ACTION_TIMEOUT = 30.0
#: a host crash whose agent is not recovered within this long is recorded as blocked
HOST_CRASH_TIMEOUT = 30.0

#: metric -> (sample kind, sample field, label, thesis figure, target) for the table
METRICS: dict[str, tuple[str, str, str, str, str]] = {
    "spawn": ("spawn", "spawn", "spawn (request -> active)", "1-2 s", "<= 0.5 s"),
    "spawn_ready": ("spawn", "spawn_ready", "spawn (request -> agent ready)", "1-2 s", "<= 0.5 s"),
    "freeze": ("transfer", "freeze", "freeze (move request -> frozen)", "~1/3-1/2 of transfer", "-"),
    "transfer": ("transfer", "transfer", "transfer (move request -> thawed)", "1.3-2.1 s", "<= 0.15 s"),
    "transfer_ready": ("transfer", "transfer_ready", "transfer (move request -> agent ready)", "1.3-2.1 s",
                       "<= 0.15 s"),
    "transfer_unreachable": ("transfer", "unreachable", "transfer: longest reply gap (5 ms pings)", "-", "-"),
    "freeze_idle": ("transfer_idle", "freeze", "freeze, no ping load", "~1/3-1/2 of transfer", "-"),
    "transfer_idle": ("transfer_idle", "transfer", "transfer, no ping load (-> thawed)", "1.3-2.1 s", "<= 0.15 s"),
    "crash_detect": ("agent_crash", "crash_detect", "agent crash: kill -> detected", "- (UFD, configurable)", "-"),
    "recovery": ("agent_crash", "recovery", "agent crash: recovery after detection", "0.7-2.9 s", "<= 0.3 s"),
    "recovery_total": ("agent_crash", "recovery_total", "agent crash: kill -> recovered", "-", "-"),
    "recovery_ready": ("agent_crash", "recovery_ready", "agent crash: kill -> agent ready", "-", "-"),
    "recovery_unreachable": ("agent_crash", "unreachable", "agent crash: longest reply gap", "-", "-"),
    "host_removal": ("host_crash", "host_removal", "host crash: kill -> removed from the view",
                     "- (UFD, configurable)", "-"),
    "host_recovery": ("host_crash", "host_recovery", "host crash: recovery after removal", "0.7-2.9 s", "<= 0.3 s"),
    "host_recovery_total": ("host_crash", "host_recovery_total", "host crash: kill -> recovered", "-", "-"),
    "host_recovery_ready": ("host_crash", "host_recovery_ready", "host crash: kill -> agent ready", "-", "-"),
    "host_unreachable": ("host_crash", "unreachable", "host crash: longest reply gap", "-", "-"),
}
#: the metric that carries each target in the summary line
TARGETS = {"spawn": 0.5, "transfer": 0.15, "recovery": 0.3, "host_recovery": 0.3}


# ----------------------------------------------------------------------------------------- timeline


class EventTap:
    """Every host's `AgentEvents` stream, collected by one thread per host (reconnecting after a restart)."""

    def __init__(self) -> None:
        self.events: list[dict[str, Any]] = []
        self._seen: set[tuple[Any, ...]] = set()
        self._cond = threading.Condition()
        self._calls: dict[str, Any] = {}
        self._stop = False
        self._threads: list[threading.Thread] = []

    def follow(self, host: MemberHost) -> None:
        t = threading.Thread(target=self._run, args=(host,), name=f"events-{host.name}", daemon=True)
        self._threads.append(t)
        t.start()

    def _run(self, host: MemberHost) -> None:
        while not self._stop:
            try:
                call = host.client.agent_events(history=True)
                self._calls[host.name] = call
                for e in call:
                    item = {"t": e.time, "agent": e.agent, "name": e.name, "event": e.event, "host": e.host,
                            "detail": e.detail}
                    key = (e.time, e.agent, e.event, e.host, e.detail)
                    with self._cond:
                        if key not in self._seen:
                            self._seen.add(key)
                            self.events.append(item)
                            self._cond.notify_all()
            except grpc.RpcError:
                pass
            if not self._stop:
                time.sleep(0.2)

    def find(self, agent: str, event: str, since: float, host: str | None = None,
             detail: Callable[[str], bool] | None = None) -> list[dict[str, Any]]:
        with self._cond:
            out = [e for e in self.events if e["agent"] == agent and e["event"] == event and e["t"] >= since
                   and (host is None or e["host"] == host) and (detail is None or detail(e["detail"]))]
        return sorted(out, key=lambda e: e["t"])

    def wait(self, agent: str, event: str, since: float, host: str | None = None, timeout: float = ACTION_TIMEOUT,
             detail: Callable[[str], bool] | None = None) -> dict[str, Any] | None:
        """The first `event` of `agent` at or after `since` (on `host`), waiting up to `timeout` for it."""
        deadline = time.monotonic() + timeout
        while True:
            found = self.find(agent, event, since, host, detail)
            if found:
                return found[0]
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            with self._cond:
                self._cond.wait(min(left, 0.1))

    def close(self) -> None:
        self._stop = True
        for call in list(self._calls.values()):
            with contextlib.suppress(Exception):
                call.cancel()


# ----------------------------------------------------------------------------------------- the cluster


class BenchCluster(MemberGroup):
    """n membership-mode hosts h1..hn on loopback (h1-h3 core), their timeline, and helpers."""

    def __init__(self, root: Path, n: int, args: Iterable[str] = HOSTD_ARGS) -> None:
        super().__init__(root, n, core=CORE, args=list(args))
        self.tap = EventTap()

    def __enter__(self) -> BenchCluster:
        return self

    def close(self) -> None:
        self.tap.close()
        super().close()

    def form(self, timeout: float = 120.0, *, what: str | None = None, interval: float = 0.1) -> float:
        """Start the hosts, wait until they form one group, then follow every host's timeline."""
        took = super().form(timeout, what=what, interval=interval)
        for h in self.hosts.values():
            self.tap.follow(h)
        return took

    def wait_group(self, timeout: float = 120.0, names: list[str] | None = None) -> None:
        self.wait_members(timeout, names, interval=0.1)

    @property
    def h1(self) -> MemberHost:
        return self.hosts["h1"]

    def agents(self) -> dict[str, Any]:
        return {a.id: a for a in self.h1.client.agent_list().agents}

    def owner(self, agent: str) -> str:
        a = self.agents().get(agent)
        return a.owner if a is not None and a.status == "active" else ""

    def wait_quiet(self, timeout: float = 60.0, settle: float = 0.3) -> None:
        """Every agent active with an owner, and no allocation session started or open for `SESSION_GAP`
        (a change during a session makes the leader start another one when its rate limit allows)."""
        seen: dict[str, Any] = {"ses": -1, "since": 0.0}

        def quiet() -> bool:
            r = self.h1.client.agent_list()
            now = time.monotonic()
            if r.session != seen["ses"]:
                seen["ses"], seen["since"] = r.session, now
            return (r.session == r.finished_session and now - seen["since"] >= SESSION_GAP
                    and all(a.status == "active" and a.owner for a in r.agents))

        wait_for(quiet, timeout, "the agents to settle", interval=0.05)
        time.sleep(settle)

    def ddb_json(self, key: str) -> Any:
        objs = self.h1.client.ddb_get(keys=[key]).objects
        return json.loads(objs[0].value) if objs else None

    def wait_stamp(self, agent: str, how: str, since: float, timeout: float = 10.0) -> float | None:
        """The agent's own ready stamp (`bench/ready/<id>`) of `how` taken at or after `since`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(grpc.RpcError):
                st = self.ddb_json(f"bench/ready/{agent}")
                if st is not None and st.get("how") == how and float(st["t"]) >= since:
                    return float(st["t"])
            time.sleep(0.02)
        return None

    def view_removed(self, victim: str, since: float) -> float | None:
        """The first survivor's `view` log event at or after `since` that removes `victim`."""
        ts = [float(e["ts"]) for x, h in self.hosts.items() if x != victim
              for e in h.events(since, {"view"}) if victim in e["fields"].get("removed", [])]
        return min(ts) if ts else None

    def spawn(self, type_name: str, config: dict[str, Any], via: str = "h1") -> str:
        r = self.hosts[via].client.agent_spawn(type_name, json.dumps(config).encode())
        if not r.ok:
            raise RuntimeError(f"spawn of a {type_name} agent failed: {r.reason}")
        return str(r.id)

    def move(self, agent: str, host: str, wait: bool = True) -> float:
        t = time.time()
        r = self.h1.client.agent_move(agent, host)
        if not r.ok:
            raise RuntimeError(f"move of {agent[:8]} to {host} failed: {r.reason}")
        if wait and self.tap.wait(agent, "thawed", t, host=host) is None:
            raise RuntimeError(f"{agent[:8]} was not thawed on {host} within {ACTION_TIMEOUT:.0f} s")
        return t


# ----------------------------------------------------------------------------------------- the pinger


class Pinger:
    """The `pinger` agent on h1 that requests b"ping" from B every `period` (haa.lab.experiments.benchagents)."""

    def __init__(self, c: BenchCluster, target: str, period: float) -> None:
        self.c = c
        self.id = c.spawn("pinger", {"target": target, "period": period, "paused": True})
        self.n = 0

    def place(self) -> None:
        if self.c.owner(self.id) != "h1":
            self.c.move(self.id, "h1")

    def send(self, cmd: dict[str, Any]) -> None:
        r = self.c.h1.client.agent_send(self.id, json.dumps(cmd).encode())
        if not r.ok:
            raise RuntimeError(f"pinger: {r.reason}")

    def report(self, t0: float, t1: float, timeout: float = 10.0) -> dict[str, Any]:
        """Ask for the reply gaps in [t0, t1]; {} if the report does not arrive."""
        self.n += 1
        key = f"ap4/{self.id[:8]}/{self.n}"
        self.send({"op": "report", "key": key, "t0": t0, "t1": t1})
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(grpc.RpcError):
                rep = self.c.ddb_json(f"bench/{key}")
                if rep is not None:
                    return dict(rep)
            time.sleep(0.02)
        return {}


# ----------------------------------------------------------------------------------------- the actions


def _d(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else b - a


def _t(e: dict[str, Any] | None) -> float | None:
    return None if e is None else float(e["t"])


def ballast_config(state_bytes: int, seed: int) -> dict[str, Any]:
    return {"state_bytes": state_bytes, "seed": seed, "backup": True, "report_ready": True}


def spawn_sample(c: BenchCluster, i: int, state_bytes: int) -> dict[str, Any]:
    via = c.names[i % len(c.names)]
    c.wait_quiet()  # includes SESSION_GAP since the last session (the removal of the previous sample's agent)
    t0 = time.time()
    agent = c.spawn("ballast", ballast_config(state_bytes, 1000 + i), via=via)
    rpc = time.time()
    active = c.tap.wait(agent, "active", t0)
    stamp = c.wait_stamp(agent, "start", t0) if active is not None else None
    created = c.tap.find(agent, "created", t0)
    spawning = c.tap.find(agent, "spawning", t0)
    s = {
        "via": via, "host": active["host"] if active else None,
        "rpc": rpc - t0,
        "created": _d(t0, _t(created[0]) if created else None),
        "spawning": _d(t0, _t(spawning[0]) if spawning else None),
        "spawn": _d(t0, _t(active)),
        "spawn_ready": _d(t0, stamp),
    }
    r = c.h1.client.agent_remove(agent)
    if not r.ok:
        raise RuntimeError(f"remove of {agent[:8]} failed: {r.reason}")
    c.tap.wait(agent, "removed", t0, timeout=10.0)
    return s


def transfer_sample(c: BenchCluster, b: str, pinger: Pinger | None, i: int) -> dict[str, Any]:
    owner = c.owner(b)
    others = [x for x in c.names if x != owner]
    target = others[i % len(others)]
    t0 = time.time()
    r = c.h1.client.agent_move(b, target)
    rpc = time.time()
    if not r.ok:
        raise RuntimeError(f"move of B to {target} failed: {r.reason}")
    thawed = c.tap.wait(b, "thawed", t0, host=target)
    frozen = c.tap.wait(b, "frozen", t0, host=owner, timeout=5.0)
    freezing = c.tap.find(b, "freezing", t0, host=owner)
    thawing = c.tap.find(b, "thawing", t0, host=target)
    stamp = c.wait_stamp(b, "thaw", t0) if thawed is not None else None
    time.sleep(0.3)
    rep = pinger.report(t0, time.time()) if pinger is not None else {}
    return {
        "from": owner, "to": target, "rpc": rpc - t0,
        "freezing": _d(t0, _t(freezing[0]) if freezing else None),
        "freeze": _d(t0, _t(frozen)),
        "thawing": _d(t0, _t(thawing[0]) if thawing else None),
        "transfer": _d(t0, _t(thawed)),
        "transfer_ready": _d(t0, stamp),
        "unreachable": rep.get("max_gap"), "gap_at": _d(t0, rep.get("gap_start")),
        "max_rtt": rep.get("max_rtt"),
        "pings_failed": rep.get("failed"),
    }


def agent_crash_sample(c: BenchCluster, b: str, pinger: Pinger) -> dict[str, Any]:
    owner = c.owner(b)
    t0 = time.time()
    r = c.hosts[owner].client.agent_kill(b)
    deadline = time.monotonic() + 10
    while not r.ok and "still starting" in r.reason and time.monotonic() < deadline:
        time.sleep(0.05)  # its process has not said hello yet (the table is active once OAC(recovered) commits)
        t0 = time.time()
        r = c.hosts[owner].client.agent_kill(b)
    if not r.ok:
        raise RuntimeError(f"kill of B on {owner} failed: {r.reason}")
    recovered = c.tap.wait(b, "recovered", t0)
    stamp = c.wait_stamp(b, "recover", t0) if recovered is not None else None
    time.sleep(0.3)
    crashed = c.tap.find(b, "crashed", t0)
    first = _t(crashed[0]) if crashed else None
    rep = pinger.report(t0, time.time())
    return {
        "owner": owner, "host": recovered["host"] if recovered else None,
        "from_backup": recovered["detail"] == "from backup" if recovered else None,
        "crash_detect": _d(t0, first),
        "recovery": _d(first, _t(recovered)),
        "recovery_total": _d(t0, _t(recovered)),
        "recovery_ready": _d(t0, stamp),
        "unreachable": rep.get("max_gap"), "gap_at": _d(t0, rep.get("gap_start")),
        "max_rtt": rep.get("max_rtt"),
        "pings_failed": rep.get("failed"),
    }


def host_crash_sample(c: BenchCluster, b: str, pinger: Pinger, i: int) -> dict[str, Any]:
    owner = c.owner(b)
    if owner == "h1" or not owner:
        others = c.names[1:]
        c.move(b, others[i % len(others)])
        c.wait_quiet()
        owner = c.owner(b)
    victim = c.hosts[owner]
    t0 = time.time()
    victim.kill()
    recovered = c.tap.wait(b, "recovered", t0, timeout=HOST_CRASH_TIMEOUT)
    stamp = c.wait_stamp(b, "recover", t0) if recovered is not None else None
    time.sleep(0.3)
    removed = c.view_removed(owner, t0)
    rep = pinger.report(t0, time.time()) if recovered is not None else {}
    s = {
        "victim": owner, "host": recovered["host"] if recovered else None,
        "blocked": recovered is None,
        "from_backup": recovered["detail"] == "from backup" if recovered else None,
        "host_removal": _d(t0, removed),
        "host_recovery": _d(removed, _t(recovered)),
        "host_recovery_total": _d(t0, _t(recovered)),
        "host_recovery_ready": _d(t0, stamp),
        "unreachable": rep.get("max_gap"), "gap_at": _d(t0, rep.get("gap_start")),
        "max_rtt": rep.get("max_rtt"),
        "pings_failed": rep.get("failed"),
    }
    if recovered is None:  # the group is stuck (see the report of `run_one`): no restart, no more samples
        return s
    t_restart = time.monotonic()
    victim.start()
    c.wait_group(timeout=120.0)
    c.wait_quiet()
    s["rejoin"] = time.monotonic() - t_restart
    return s


# ----------------------------------------------------------------------------------------- the run


def summarize(xs: list[float | None]) -> dict[str, float]:
    vals = [x for x in xs if x is not None]
    if not vals:
        return {"n": 0, "missing": len(xs)}
    return {
        "n": len(vals),
        "missing": len(xs) - len(vals),
        "median": statistics.median(vals),
        "p90": percentile(vals, 90),
        "max": max(vals),
        "min": min(vals),
        "mean": statistics.fmean(vals),
    }


def run_one(n: int, reps: int, root: Path, state_bytes: int = THESIS_STATE_BYTES, period: float = 0.005,
            host_crash: bool = True, log: Callable[[str], None] = print) -> dict[str, Any]:
    """All four actions on a fresh group of n hosts; the samples and their summaries."""
    load0 = os.getloadavg()[0]
    with BenchCluster(root, n) as c:
        took = c.form()
        log(f"n={n}: group formed in {took:.1f} s")
        c.wait_quiet()
        samples: dict[str, list[dict[str, Any]]] = {
            "spawn": [], "transfer_idle": [], "transfer": [], "agent_crash": [], "host_crash": []}
        for i in range(reps):
            samples["spawn"].append(spawn_sample(c, i, state_bytes))
        c.wait_quiet()
        b = c.spawn("ballast", ballast_config(state_bytes, 1))
        if c.tap.wait(b, "active", 0.0) is None:
            raise RuntimeError("the ballast agent B did not start")
        pinger = Pinger(c, b, period)
        c.wait_quiet()
        pinger.place()
        c.wait_quiet()
        for i in range(reps):
            samples["transfer_idle"].append(transfer_sample(c, b, None, i))
            time.sleep(0.2)
        pinger.send({"op": "resume"})
        time.sleep(0.5)
        for i in range(reps):
            samples["transfer"].append(transfer_sample(c, b, pinger, i))
            time.sleep(0.2)
        for _ in range(reps):
            samples["agent_crash"].append(agent_crash_sample(c, b, pinger))
            time.sleep(0.2)
        blocked = False
        skipped = ""
        if host_crash and n < 3:
            skipped = ("a group of two cannot decide an OAC that is in flight when one of its two participants "
                       "crashes (f < n/2, docs/oac.md, docs/membership.md 'fault gate'): it would block")
            log(f"n={n}: host crash skipped ({skipped})")
        elif host_crash:
            for i in range(reps):
                pinger.place()
                c.wait_quiet()
                samples["host_crash"].append(host_crash_sample(c, b, pinger, i))
                if samples["host_crash"][-1]["blocked"]:
                    blocked = True
                    log(f"n={n}: B was not recovered within {HOST_CRASH_TIMEOUT:.0f} s of the host crash "
                        f"(removed from the view: {samples['host_crash'][-1]['host_removal'] is not None}); "
                        "no more host-crash samples on this group")
                    break
        if not blocked:
            pinger.send({"op": "pause"})
        summary = {k: summarize([x.get(field) for x in samples[kind]])
                   for k, (kind, field, *_rest) in METRICS.items() if samples[kind]}
        log(f"n={n}: " + ", ".join(f"{k} {v['median'] * 1e3:.0f} ms" for k, v in summary.items()
                                    if k in ("spawn", "freeze", "transfer", "recovery", "host_recovery")
                                    and v.get("n")))
        return {"hosts": n, "reps": reps, "state_bytes": state_bytes, "ping_period": period,
                "load_avg_1min": [load0, os.getloadavg()[0]],
                "host_crash_blocked": blocked, "host_crash_skipped": skipped, "summary": summary,
                "samples": samples}


def run_ap4(hosts: Iterable[int] = HOSTS, reps: int = 10, root: Path | None = None,
            state_bytes: int = THESIS_STATE_BYTES, period: float = 0.005, host_crash: bool = True,
            log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    rows = []
    with contextlib.ExitStack() as stack:
        if root is None:
            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="haa-ap4-")))
        for n in hosts:
            try:
                rows.append(run_one(n, reps, root / f"n{n}", state_bytes, period, host_crash, log))
            except (grpc.RpcError, AssertionError, RuntimeError) as e:  # a broken group: the next size goes on
                log(f"n={n}: stopped: {e}")
                rows.append({"hosts": n, "reps": reps, "error": str(e)[:500], "summary": {}, "samples": {}})
    return rows


def parse_hosts(text: str) -> tuple[int, ...]:
    """"2,4,6" -> (2, 4, 6); a clear error naming --hosts otherwise."""
    try:
        sizes = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"--hosts: expected comma-separated group sizes such as 2,4,6, got {text!r}") from None
    if not sizes or any(not 2 <= n <= 16 for n in sizes):
        raise ValueError(f"--hosts: every group size must be in 2..16, got {text!r}")
    return sizes
