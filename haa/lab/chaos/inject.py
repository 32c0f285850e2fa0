"""Carrying out a plan's faults on a running cluster (docs/chaos.md, "Faults").

`Injector.run()` follows the plan's clock (seconds since the chaos started) until `duration_s`:

* host faults go through the cluster backend (`haa.cluster.backend.Backend`): `kill` = SIGKILL, `pause` =
  SIGSTOP for `for_s` then SIGCONT, `restart` = start a stopped host again (same data dir, new incarnation);
* agent faults go through the hosts' control API: `kill` = AgentKill on the host running the agent (SIGKILL of
  its process), `hang` = an operator request `haa.sdk.base.CHAOS_HANG` that makes the agent block its own
  event loop for `hang_s` and then fail — a stuck computation, not a SIGSTOP its host could read off /proc;
* `partition: [h1, h2]` for `for_s` (compose): each named host is cut off the cluster network (the
  backend's `disconnect`: `docker network disconnect`, haa.lab.chaos.compose), so it is isolated from every
  other host, and connected again with its address and name afterwards (`reconnect`); a partitioned host
  counts as not live for the majority gate below. It is refused on the local cluster before anything starts
  (`local_problems`): its hosts share loopback, there is no link to cut without root;
* `life_s: [lo, hi]` (the thesis' failure model): every targeted agent instance (agent id and epoch) draws
  a failure time uniformly in the window, counted from when the injector first sees it active; a recovered
  instance (a higher epoch) draws again.

A host fault that would leave the group without a live majority of at least MIN_LIVE hosts is not injected
(it is recorded as skipped, with the reason): OAC decides only while fewer than half of its participants have
failed (docs/membership.md), so such a fault stops the group instead of testing it. Every fault, done or
skipped, is an `Injected` record with its time and concrete target; the random choices come from the plan's
seed.
"""

from __future__ import annotations

import contextlib
import heapq
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from haa.cluster.agents import AgentRow, agent_lists, answering, merge_agents
from haa.cluster.backend import ALIVE, PAUSED, Backend, ClusterError
from haa.lab.chaos.plan import Fault, Plan
from haa.sdk.base import CHAOS_HANG

#: fewest live hosts a host fault may leave
MIN_LIVE = 3
#: seconds between two reads of the agent list (life_s draws, random agents)
AGENT_POLL = 1.0


@dataclass
class Injected:
    """One fault as carried out (or skipped)."""

    t: float  # seconds since the chaos started
    ts: float  # unix time
    action: str  # kill, pause, resume, restart, hang, partition, heal
    target: str  # the concrete host or agent name
    fault: int  # index in plan.faults (-1: the end of a pause)
    ok: bool = True
    detail: str = ""
    agent_id: str = ""
    epoch: int = 0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def local_problems(plan: Plan) -> list[str]:
    """What a plan asks that the local cluster cannot do, one line each (checked before anything starts)."""
    return [
        f"faults[{i}]: partition is not available on the local cluster (its hosts share loopback and there is "
        "no link to cut without root); run the plan with --compose, or remove this fault"
        for i, f in enumerate(plan.faults)
        if f.action == "partition"
    ]


@dataclass(order=True)
class _Due:
    t: float
    seq: int
    kind: str = field(compare=False)  # "fault" | "resume" | "heal" | "life"
    fault: int = field(compare=False, default=-1)
    target: str = field(compare=False, default="")
    epoch: int = field(compare=False, default=0)


class Injector:
    """Runs a plan's faults against `backend` (module docstring)."""

    def __init__(self, plan: Plan, backend: Backend, on_fault: Callable[[Injected], None] | None = None,
                 clock: Callable[[], float] = time.time, sleep: Callable[[float], object] = time.sleep,
                 duration: float | None = None, wall_per_s: float = 1.0) -> None:
        """`clock` gives the plan's seconds (a mission's simulated time inside a mission), `sleep` waits that
        many of them; `duration` overrides the plan's `duration_s` (a mission's time limit); a `hang_s` is
        sent to the agent as `hang_s * wall_per_s` wall seconds (1 / speed in a mission)."""
        self.plan = plan
        dur = duration if duration is not None else plan.duration_s
        if dur is None:
            raise ValueError("duration_s: the plan has none and none was given (it runs until a mission ends)")
        self.duration = float(dur)
        self.wall_per_s = wall_per_s
        self.backend = backend
        self.rng = random.Random(plan.seed)
        self.on_fault = on_fault
        self.clock = clock
        self.sleep = sleep
        self.t0 = 0.0
        self.injected: list[Injected] = []
        self._queue: list[_Due] = []
        self._seq = 0
        self._drawn: set[tuple[int, str, int]] = set()  # (fault, agent id, epoch) with a life_s draw
        self._rows: list[AgentRow] = []
        self._rows_at = -1e9
        self.paused: set[str] = set()
        self.partitioned: set[str] = set()

    # ------------------------------------------------------------------ schedule
    def _push(self, t: float, kind: str, fault: int = -1, target: str = "", epoch: int = 0) -> None:
        self._seq += 1
        heapq.heappush(self._queue, _Due(t, self._seq, kind, fault, target, epoch))

    def _schedule(self) -> None:
        for i, f in enumerate(self.plan.faults):
            if f.every_s is not None:
                t = f.at_s if f.at_s is not None else f.every_s
                while t < self.duration:
                    self._push(t, "fault", i)
                    t += f.every_s
            elif f.at_s is not None:
                self._push(f.at_s, "fault", i)

    def now(self) -> float:
        return self.clock() - self.t0

    def run(self, stop: Callable[[], bool] | None = None, t0: float | None = None) -> list[Injected]:
        """Inject until `duration_s` (pauses still running are ended then); returns every record. The plan's
        0 is `t0` on `clock` (now by default; a mission's 0 inside a mission)."""
        self.t0 = self.clock() if t0 is None else t0
        self._schedule()
        has_life = any(f.life_s is not None for f in self.plan.faults)
        while True:
            t = self.now()
            if t >= self.duration or (stop is not None and stop()):
                break
            if has_life and t - self._rows_at >= AGENT_POLL:
                self._draw_lives(t)
            while self._queue and self._queue[0].t <= self.now():
                self._fire(heapq.heappop(self._queue))
            nxt = self._queue[0].t if self._queue else self.duration
            self.sleep(max(0.01, min(0.2, nxt - self.now())))
        self.end_pauses()
        self.end_partitions()
        return self.injected

    def end_pauses(self) -> None:
        """SIGCONT every host a pause of this run still holds."""
        for h in sorted(self.paused):
            self._resume(h)

    def end_partitions(self) -> None:
        """Reconnect every host a partition of this run still holds."""
        for h in sorted(self.partitioned):
            self._heal(h)

    # ------------------------------------------------------------------ recording
    def _record(self, action: str, target: str, fault: int, ok: bool = True, detail: str = "",
                agent_id: str = "", epoch: int = 0) -> Injected:
        rec = Injected(round(self.now(), 3), time.time(), action, target, fault, ok, detail, agent_id, epoch)
        self.injected.append(rec)
        if self.on_fault is not None:
            self.on_fault(rec)
        return rec

    # ------------------------------------------------------------------ agents
    def agents(self, fresh: bool = False) -> list[AgentRow]:
        if fresh or self.now() - self._rows_at >= AGENT_POLL:
            # on failure keep the last list (every live host busy or down for a moment)
            with contextlib.suppress(ClusterError):
                self._rows = merge_agents(answering(self.backend, agent_lists(self.backend)))
            self._rows_at = self.now()
        return self._rows

    def _matching(self, f: Fault, rows: list[AgentRow]) -> list[AgentRow]:
        t = f.target
        active = [r for r in rows if r.state == "active"]
        if t.kind == "agent":
            return [r for r in active if r.name == t.value]
        if t.kind == "agent-type":
            return [r for r in active if r.type == t.value]
        if t.kind == "agents":
            return active
        if t.kind == "random-agent":
            return [self.rng.choice(active)] if active else []
        return []

    def _draw_lives(self, t: float) -> None:
        rows = self.agents(fresh=True)
        for i, f in enumerate(self.plan.faults):
            if f.life_s is None:
                continue
            for r in self._matching(f, rows):
                key = (i, r.id, r.epoch)
                if key in self._drawn:
                    continue
                self._drawn.add(key)
                at = t + self.rng.uniform(*f.life_s)
                if at < self.duration:
                    self._push(at, "life", i, r.id, r.epoch)

    def _agent_fault(self, i: int, f: Fault, r: AgentRow) -> None:
        owner = next((h for h, p in r.phases.items() if p == "active"), r.owner)
        if not owner or r.state != "active":
            self._record(f.action, r.name, i, False, f"skipped: {r.name} is {r.state}", r.id, r.epoch)
            return
        try:
            if f.action == "kill":
                reply = self.backend.call(owner, lambda c: c.agent_kill(r.id), "AgentKill")
                ok, why = reply.ok, reply.reason
                detail = f"SIGKILL on {owner}" if ok else f"not killed on {owner}: {why}"
            else:
                hang_s = float(f.hang_s or 0)
                payload = CHAOS_HANG + f"{hang_s * self.wall_per_s:g}".encode()
                rep = self.backend.call(owner, lambda c: c.agent_request(r.id, payload, timeout=3.0),
                                        "AgentRequest", timeout=10.0)
                ok = rep.ok and bytes(rep.payload) == b"hanging"
                detail = f"event loop blocked {hang_s:g} s on {owner}" if ok else f"not hung: {rep.error}"
        except ClusterError as e:
            ok, detail = False, str(e)
        self._record(f.action, r.name, i, ok, detail, r.id, r.epoch)

    # ------------------------------------------------------------------ hosts
    def _live_after(self, losing: str | set[str]) -> tuple[int, int]:
        """(live hosts after `losing` fails, hosts up now): live = alive and not paused."""
        hosts = self.backend.hosts()
        up = [h for h in hosts if h.state in (ALIVE, PAUSED)]
        lose = {losing} if isinstance(losing, str) else set(losing)
        live = [h for h in up if h.state == ALIVE and h.name not in lose and h.name not in self.partitioned]
        return len(live), len(up)

    def _partition(self, i: int, f: Fault) -> None:
        names = set(f.target.hosts)
        text = ", ".join(f.target.hosts)
        states = {h.name: h.state for h in self.backend.hosts()}
        bad = [n for n in f.target.hosts if states.get(n) != ALIVE or n in self.partitioned]
        if bad:
            why = ", ".join(f"{n} is {'partitioned' if n in self.partitioned else states.get(n) or 'unknown'}"
                            for n in bad)
            self._record("partition", text, i, False, f"skipped: {why}")
            return
        live, up = self._live_after(names)
        if live < MIN_LIVE or live * 2 <= up:
            self._record("partition", text, i, False,
                         f"skipped: would leave {live} live hosts of {up} in the group (it needs a live majority of "
                         f"at least {MIN_LIVE} to remove a failed host)")
            return
        done = []
        cut = getattr(self.backend, "disconnect", None)
        if cut is None:
            self._record("partition", text, i, False, f"not available on the {self.backend.describe()}")
            return
        try:
            for n in f.target.hosts:
                cut(n)
                self.partitioned.add(n)
                done.append(n)
            self._record("partition", text, i, True, f"cut off the network for {f.for_s:g} s")
        except ClusterError as e:
            self._record("partition", text, i, False, f"{e} (cut: {', '.join(done) or 'none'})")
        for n in done:
            self._push(self.now() + float(f.for_s or 0), "heal", i, n)

    def _heal(self, name: str, fault: int = -1) -> None:
        if name not in self.partitioned:
            return
        self.partitioned.discard(name)
        try:
            self.backend.reconnect(name)  # type: ignore[attr-defined]
            self._record("heal", name, fault, True, "connected again (same address and name)")
        except ClusterError as e:
            self._record("heal", name, fault, False, str(e))

    def _host_fault(self, i: int, f: Fault) -> None:
        hosts = self.backend.hosts()
        t = f.target
        if t.kind == "host":
            name = t.value
        else:
            pool = [h.name for h in hosts if (h.state == ALIVE) == (f.action != "restart")
                    and (f.action != "restart" or h.state != PAUSED) and h.name not in self.partitioned]
            if not pool:
                self._record(f.action, "random-host", i, False, f"skipped: no host to {f.action}")
                return
            name = self.rng.choice(pool)
        state = next((h.state for h in hosts if h.name == name), "")
        if f.action == "restart":
            if state in (ALIVE, PAUSED):
                self._record("restart", name, i, False, f"skipped: {name} is {state}")
                return
            try:
                self.backend.restart(name)
                self._record("restart", name, i, True, "started again (same data dir, new incarnation)")
            except ClusterError as e:
                self._record("restart", name, i, False, str(e))
            return
        if state != ALIVE:
            self._record(f.action, name, i, False, f"skipped: {name} is {state or 'unknown'}")
            return
        live, up = self._live_after(name)
        if f.action == "kill":
            up -= 1
        if live < MIN_LIVE or live * 2 <= up:
            self._record(f.action, name, i, False,
                         f"skipped: would leave {live} live hosts of {up} in the group (it needs a live majority of "
                         f"at least {MIN_LIVE} to remove a failed host)")
            return
        try:
            if f.action == "kill":
                self.backend.kill(name)
                self._record("kill", name, i, True, "SIGKILL")
            else:
                self.backend.pause(name)
                self.paused.add(name)
                self._record("pause", name, i, True, f"SIGSTOP for {f.for_s:g} s")
                self._push(self.now() + float(f.for_s or 0), "resume", i, name)
        except ClusterError as e:
            self._record(f.action, name, i, False, str(e))

    def _resume(self, name: str, fault: int = -1) -> None:
        if name not in self.paused:
            return
        self.paused.discard(name)
        try:
            self.backend.resume(name)
            self._record("resume", name, fault, True, "SIGCONT")
        except ClusterError as e:
            self._record("resume", name, fault, False, str(e))

    # ------------------------------------------------------------------ dispatch
    def _fire(self, d: _Due) -> None:
        if d.kind == "resume":
            self._resume(d.target, d.fault)
            return
        if d.kind == "heal":
            self._heal(d.target, d.fault)
            return
        f = self.plan.faults[d.fault]
        if f.action == "partition":
            self._partition(d.fault, f)
            return
        if d.kind == "life":
            row = next((r for r in self.agents(fresh=True) if r.id == d.target), None)
            if row is None or row.epoch != d.epoch:
                return  # that instance is gone already (killed, moved to a new epoch): its successor draws anew
            self._agent_fault(d.fault, f, row)
            return
        if f.target.is_host:
            self._host_fault(d.fault, f)
            return
        rows = self._matching(f, self.agents(fresh=True))
        if not rows:
            self._record(f.action, f.target.text(), d.fault, False, "skipped: no active agent matches")
        for r in rows:
            self._agent_fault(d.fault, f, r)
