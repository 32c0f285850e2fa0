"""The engine of the allocation verifier (`haa.lab.dsim.allocation`): `AllocSim` runs one `AllocScenario`.

One `haa.core.allocation.allocation.Allocator` and one `RebalancePolicy` per host; bid updates over reliable FIFO
channels with random delays; OAC as an ideal totally ordered atomic broadcast (a global log of `Entry`s, each
member delivering it in order after its own delay); the group and the agent list as "world" entries of the same
log; crashes, pauses, false suspicions and joins (see `haa.lab.dsim.allocation` for the whole model). The
properties are checked afterwards by `haa.lab.dsim.alloccheck`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from haa.core.allocation.allocation import Allocated, Allocator, ProposeFinish, ProposeStart, SendUpdate
from haa.core.allocation.bids import same_bid
from haa.core.allocation.rebalance import RebalancePolicy
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart
from haa.core.effects import Log
from haa.lab.dsim.allocschedule import AFault, AllocScenario
from haa.lab.dsim.scheduler import EventHeap

# --------------------------------------------------------------------------------------------- simulation


@dataclass
class World:
    group: tuple[str, ...]
    agents: tuple[AgentSpec, ...]
    hosts: dict[str, HostSpec]
    paused: bool = False

    @property
    def agent_ids(self) -> tuple[str, ...]:
        return tuple(a.id for a in self.agents)


@dataclass
class Entry:
    """One committed item of the total order."""

    index: int
    at: float
    kind: str  # world | start | finish | costs | control
    world: World  # the world after this entry
    start: SessionStart | None = None
    finish: ProposeFinish | None = None
    proposer: str = ""
    accepted: bool = False  # start valid / finish accepted, by the reference ledger
    reason: str = ""


class _Node:
    def __init__(self, name: str, alloc: Allocator, policy: RebalancePolicy, first_entry: int, world: World) -> None:
        self.name = name
        self.alloc = alloc
        self.policy = policy
        self.alive = True
        self.member = True
        self.paused_until = -math.inf
        self.deferred: list[tuple[float, str, tuple[Any, ...]]] = []  # (time, kind, args) while paused
        self.inbox: list[tuple[str, Any]] = []
        self.process_at: float | None = None
        self.next_entry = first_entry
        self.deliver_last = 0.0
        self.view = world
        self.timer_at: float | None = None
        self.busy_until = 0.0
        self.accepted: list[tuple[int, int, float, dict[str, str]]] = []  # (entry index, ses, time, allocation)
        self.decisions: dict[int, bool] = {}  # finish entry index -> accepted
        self.proposed: list[int] = []


class AllocSim:
    """See the module docstring. `cpu=True` measures every Allocator call with `clock` and advances the
    host's virtual clock by it (AP-3); `oac_delay(rng, n)` overrides the decide delay for n participants."""

    def __init__(
        self,
        sc: AllocScenario,
        trace: bool = False,
        cpu: bool = False,
        oac_delay: Callable[[random.Random, int], float] | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.sc = sc
        self.clock = clock
        self.rng = random.Random(f"alloc-sim-{sc.seed}")
        self.now = 0.0
        self.cpu = cpu
        self.cpu_time = 0.0
        self.oac_delay = oac_delay
        self.trace: list[str] | None = [] if trace else None
        #: the pending events (haa.lab.dsim.scheduler): items (kind, args); args[0] names the node, except for
        #: the global kinds fault, detect, append and oac
        self._q: EventHeap[tuple[str, tuple[Any, ...]]] = EventHeap()
        self.log: list[Entry] = []
        self.world = World(tuple(sc.names), sc.agents, dict(sc.hosts))
        self.ledger = Allocator("~ledger")  # the reference: validity of starts/finishes in the total order
        self.nodes: dict[str, _Node] = {}
        self.chan_last: dict[tuple[str, str], float] = {}
        self.messages = 0
        self.msgs_by_ses: dict[int, int] = {}
        self.oac_proposals = 0
        self.last_change = 0.0  # time of the last fault or world change
        self.last_world_entry = -1
        self.events = 0
        self.violations: list[tuple[str, str, list[str]]] = []
        self.ses_started: dict[int, float] = {}
        self.ses_consensus: dict[int, float] = {}
        self.hash = hashlib.sha256()
        for n in sc.names:
            self.nodes[n] = self._new_node(n, 0, 0)
        self._append("world", self.world, reason="initial group")
        for f in sc.faults:
            self._push(f.at, "fault", (f,))
        if sc.final_pause:
            self._push(sc.fault_end, "append", ("final pause",))

    # ------------------------------------------------------------------ plumbing

    def _new_node(self, name: str, first_entry: int, committed: int) -> _Node:
        sc = self.sc
        pol = RebalancePolicy(sc.period, sc.min_interval, sc.session_timeout)
        alloc = Allocator(name, committed)
        if sc.session_agents:  # bounded sessions with the few agents of a schedule (docs/allocation.md)
            alloc.SESSION_AGENTS = sc.session_agents
        return _Node(name, alloc, pol, first_entry, self.world)

    def _push(self, at: float, kind: str, args: tuple[Any, ...]) -> None:
        self._q.push(at, (kind, args))

    def _t(self, line: str, hashed: bool = True) -> None:
        if hashed:
            self.hash.update(line.encode())
        if self.trace is not None:
            self.trace.append(f"{self.now:.6f} {line}")

    def _bad(self, prop: str, detail: str, hosts: list[str]) -> None:
        self.violations.append((prop, detail, hosts))

    def run(self, until: float | None = None) -> None:
        horizon = until if until is not None else self.horizon()
        q = self._q
        while q:
            if q.next_time() > horizon:
                break
            at, _seq, (kind, args) = q.pop()
            self.now = at
            self.events += 1
            if kind in ("fault", "detect", "append", "oac"):
                getattr(self, f"_ev_{kind}")(*args)
                continue
            node = self.nodes[args[0]]
            if not node.alive or not node.member:
                continue
            if node.paused_until > at and kind != "resume":
                node.deferred.append((at, kind, args))
                continue
            if self.cpu and node.busy_until > at and kind != "resume":
                self._push(node.busy_until, kind, args)
                continue
            getattr(self, f"_ev_{kind}")(node, *args[1:])

    def horizon(self) -> float:
        sc = self.sc
        return sc.fault_end + sc.detect[1] + sc.liveness + 1.0

    @property
    def quiet(self) -> bool:
        return not self._q

    # ------------------------------------------------------------------ the allocator calls

    def _call(self, node: _Node, fn: Callable[..., None], *args: Any) -> None:
        if self.cpu:
            t0 = self.clock()
            fn(*args)
            dt = self.clock() - t0
            self.cpu_time += dt
            node.busy_until = max(node.busy_until, self.now) + dt
            t_out = node.busy_until
        else:
            fn(*args)
            t_out = self.now
        self._effects(node, t_out)

    def _effects(self, node: _Node, t_out: float) -> None:
        for e in node.alloc.drain():
            if isinstance(e, SendUpdate):
                self._fidelity(node, e)
                n = 0
                for d in e.dsts:
                    dn = self.nodes.get(d)
                    if dn is None or not dn.alive:
                        continue
                    arr = t_out + self.sc.delay.sample(self.rng)
                    key = (node.name, d)
                    arr = max(arr, self.chan_last.get(key, 0.0) + 1e-9)
                    self.chan_last[key] = arr
                    self._push(arr, "msg", (d, node.name, e.update))
                    n += 1
                self.messages += n
                ses = e.update.ses_id
                self.msgs_by_ses[ses] = self.msgs_by_ses.get(ses, 0) + n
                if self.trace is not None:
                    self._t(f"{node.name}# send ses={ses} bids={len(e.update.bids)} to {n}", hashed=False)
            elif isinstance(e, ProposeStart):
                st = e.start
                if st.ses_id in node.proposed and node.proposed[-1] != st.ses_id:
                    self._bad("AA-Session-Order", f"{node.name} proposed session {st.ses_id} again", [node.name])
                if not node.proposed or node.proposed[-1] != st.ses_id:
                    if node.proposed and st.ses_id < node.proposed[-1]:
                        self._bad(
                            "AA-Session-Order",
                            f"{node.name} proposed session {st.ses_id} after {node.proposed[-1]}",
                            [node.name],
                        )
                    node.proposed.append(st.ses_id)
                self.ses_started.setdefault(st.ses_id, t_out)
                self._propose(node, "start", st, t_out)
            elif isinstance(e, ProposeFinish):
                self.ses_consensus.setdefault(e.ses_id, t_out)
                self._propose(node, "finish", e, t_out)
            elif isinstance(e, Allocated):
                node.policy.finished(t_out)
                if e.deferred and node.view.group and node.view.group[0] == node.name:
                    node.policy.more(t_out)  # a bounded session left agents for the next (armed below)
                self._t(f"{node.name}# allocated ses={e.ses_id} {sorted(e.allocation.items())}")
            elif isinstance(e, Log):
                if self.trace is not None:
                    f = {k: v for k, v in e.fields.items() if k != "host"}
                    self._t(f"{node.name}# {e.event} {f}")
        self._arm_timer(node)

    def _fidelity(self, node: _Node, e: SendUpdate) -> None:
        """AA-Table-Fidelity: a member only ever sends its own accepted bids (bidTable_q[q] at every other
        host is then q's real row, which the leader's consensus check relies on, §4.7.2 l. 70)."""
        s = node.alloc.session
        if s is None or s.ses_id != e.update.ses_id:
            self._bad(
                "AA-Table-Fidelity", f"{node.name} sent bids of session {e.update.ses_id} it is not in", [node.name]
            )
            return
        for b in e.update.bids:
            own = s.bid(b.agent)
            if not same_bid(own, b):
                self._bad(
                    "AA-Table-Fidelity",
                    f"{node.name} sent {b.agent} -> {b.winner} ({b.reward:.3f}/{b.support:.3f}) in session "
                    f"{s.ses_id} while it accepts {own.winner} ({own.reward:.3f}/{own.support:.3f})",
                    [node.name],
                )
                return

    def _arm_timer(self, node: _Node) -> None:
        d = node.policy.deadline()
        if d is not None and d != node.timer_at:
            node.timer_at = d
            self._push(max(d, self.now), "timer", (node.name, d))

    def _propose(self, node: _Node, kind: str, payload: Any, t_out: float) -> None:
        self.oac_proposals += 1
        n = len(self.world.group)
        if self.oac_delay is not None:
            d = self.oac_delay(self.rng, n)
        else:
            d = self.sc.oac_base + self.rng.expovariate(1 / self.sc.oac_scale)
            if self.rng.random() < self.sc.p_slow:  # a slow round (a suspected coordinator, retried phases)
                d += self.rng.uniform(0.05, 0.6)
        self._push(t_out + d, "oac", (node.name, kind, payload))

    # ------------------------------------------------------------------ the total order

    def _append(self, kind: str, world: World, **kw: Any) -> Entry:
        e = Entry(len(self.log), self.now, kind, world, **kw)
        lg = self.ledger
        if kind == "start":
            assert e.start is not None
            e.reason = lg.start_valid(e.start, world.group, world.agent_ids)
            e.accepted = not e.reason
            lg.on_start_committed(e.start, world.group, world.agent_ids)
        elif kind == "finish":
            assert e.finish is not None
            e.reason = lg.finish_valid(e.finish.ses_id, world.group, world.agent_ids)
            e.accepted = not e.reason
            lg.on_finish_committed(e.finish.ses_id, e.finish.allocation, world.group, world.agent_ids)
            if e.accepted:  # the agents now run where the allocation put them (current host, eq. 4.7-2)
                alloc = e.finish.allocation
                self.world = World(
                    world.group,
                    # an agent of a limited kind left out for lack of places stops (agenttable._tx_finish)
                    tuple(
                        _moved(a, alloc.get(a.id, None if a.max_per_host else a.current_host)) for a in world.agents
                    ),
                    world.hosts,
                    world.paused,
                )
                e.world = self.world
        else:
            lg.on_change(world.group, world.agents, world.hosts.values(), start=False)
        lg.drain()
        if kind == "world":
            self.last_change = self.now
            self.last_world_entry = e.index
        self.log.append(e)
        self._t(f"log[{e.index}] {kind} {e.proposer} {self._entry_text(e)} {e.reason}".rstrip())
        for node in self.nodes.values():
            if node.alive and node.member and e.index >= node.next_entry:
                at = max(self.now + self.sc.deliver.sample(self.rng), node.deliver_last)
                node.deliver_last = at
                self._push(at, "deliver", (node.name, e.index))
        return e

    @staticmethod
    def _entry_text(e: Entry) -> str:
        if e.kind == "start" and e.start is not None:
            return f"ses={e.start.ses_id} group={list(e.start.group)} agents={len(e.start.agents)}"
        if e.kind == "finish" and e.finish is not None:
            return f"ses={e.finish.ses_id} alloc={sorted(e.finish.allocation.items())}"
        if e.kind == "world":
            return f"group={list(e.world.group)} agents={list(e.world.agent_ids)}"
        if e.kind == "control":
            return f"paused={e.world.paused}"
        return ""

    def _ev_oac(self, proposer: str, kind: str, payload: Any) -> None:
        node = self.nodes[proposer]
        commit = self.rng.random() >= self.sc.p_abort  # a removed proposer's transaction may still commit
        if commit:
            if kind == "start":
                self._append("start", self.world, start=payload, proposer=proposer)
            else:
                self._append("finish", self.world, finish=payload, proposer=proposer)
        self._t(f"{proposer}# oac {kind} {'commit' if commit else 'abort'}")
        if node.alive:
            self._push(self.now + self.sc.deliver.sample(self.rng) / 2, "decided", (proposer, kind, payload, commit))

    def _ev_decided(self, node: _Node, kind: str, payload: Any, commit: bool) -> None:
        v = node.view
        if kind == "start":
            self._call(node, node.alloc.on_start_decided, payload, commit, v.group, v.agents)
        else:
            self._call(node, node.alloc.on_finish_decided, payload.ses_id, commit)

    def _ev_deliver(self, node: _Node, upto: int) -> None:
        while node.next_entry <= upto and node.member:
            e = self.log[node.next_entry]
            node.next_entry += 1
            self._deliver_entry(node, e)

    def _deliver_entry(self, node: _Node, e: Entry) -> None:
        a = node.alloc
        if e.kind == "start":
            assert e.start is not None
            self._call(node, a.on_start_committed, e.start, node.view.group, node.view.agent_ids)
            if node.policy.running and not a.busy():  # as AllocGlue: an expired session is not waited for
                node.policy.finished(self.now)
                self._arm_timer(node)
            return
        if e.kind == "finish":
            assert e.finish is not None
            before = a.finished_ses
            v = node.view
            self._call(node, a.on_finish_committed, e.finish.ses_id, e.finish.allocation, v.group, v.agent_ids)
            ok = a.finished_ses != before
            node.decisions[e.index] = ok
            if ok:
                node.accepted.append((e.index, e.finish.ses_id, self.now, dict(e.finish.allocation)))
                node.view = e.world
                self._call(node, a.on_change, e.world.group, e.world.agents, e.world.hosts.values(), False)
            return
        grew_or_shrank = node.view.group != e.world.group
        node.view = e.world
        if e.kind == "control":
            if e.world.paused:
                node.policy.pause()
            else:
                node.policy.resume()
            self._arm_timer(node)
            return
        if node.name not in e.world.group:
            self._t(f"{node.name}# removed from the group")
            self._call(node, a.on_change, e.world.group, e.world.agents, e.world.hosts.values(), False)
            node.member = False
            return
        if node.policy.running and not a.busy():  # as AllocGlue: an expired session is not waited for
            node.policy.finished(self.now)
        start = e.kind == "world" and node.policy.changed(self.now, urgent=grew_or_shrank)
        self._call(node, a.on_change, e.world.group, e.world.agents, e.world.hosts.values(), start)

    # ------------------------------------------------------------------ messages and timers

    def _ev_msg(self, node: _Node, src: str, upd: Any) -> None:
        node.inbox.append((src, upd))
        if node.process_at is None:
            node.process_at = self.now + self.sc.proc
            self._push(node.process_at, "process", (node.name,))

    def _ev_process(self, node: _Node) -> None:
        node.process_at = None
        inbox, node.inbox = node.inbox, []
        a = node.alloc

        def handle() -> None:
            for src, upd in inbox:
                a.on_update(src, upd)
            a.end_of_inbox()

        self._call(node, handle)

    def _ev_timer(self, node: _Node, at: float) -> None:
        if node.timer_at != at:
            return
        node.timer_at = None
        if node.policy.running and not node.alloc.busy():
            node.policy.finished(self.now)  # as AllocGlue: an expired session is not waited for
        if node.policy.due(self.now):
            v = node.view
            self._call(node, node.alloc.on_change, v.group, v.agents, v.hosts.values(), True)
        else:
            self._arm_timer(node)

    def _ev_resume(self, node: _Node) -> None:
        if node.paused_until > self.now:
            return
        self._t(f"{node.name}# resumes")
        for _at, kind, args in node.deferred:
            self._push(self.now, kind, args)
        node.deferred = []

    # ------------------------------------------------------------------ faults and membership

    def _ev_fault(self, f: AFault) -> None:
        self._t(f"fault {f.describe()}")
        self.last_change = max(self.last_change, self.now)
        w = self.world
        if f.kind == "crash":
            self.nodes[f.target].alive = False
            self._push(self.now + self.rng.uniform(*self.sc.detect), "detect", (f.target,))
        elif f.kind == "pause":
            node = self.nodes[f.target]
            node.paused_until = max(node.paused_until, self.now + f.arg)
            self._push(self.now + f.arg, "resume", (f.target,))
            self.last_change = max(self.last_change, self.now + f.arg)
            d = self.rng.uniform(*self.sc.detect)
            if f.arg > d:  # suspected by everyone before it runs again: removed
                self._push(self.now + d, "detect", (f.target,))
        elif f.kind == "suspect":
            self._push(self.now + self.rng.uniform(*self.sc.detect), "detect", (f.target,))
        elif f.kind == "join":
            spec: HostSpec = f.arg
            nw = World((*w.group, f.target), w.agents, {**w.hosts, f.target: spec}, w.paused)
            self.world = nw
            node = self._new_node(f.target, len(self.log) + 1, self.ledger.committed_ses)
            node.view = nw
            self.nodes[f.target] = node
            self._append("world", nw, reason=f"join {f.target}")
            self._call(node, node.alloc.on_change, nw.group, nw.agents, nw.hosts.values(), False)
        elif f.kind == "agent_add":
            self.world = World(w.group, (*w.agents, f.arg), w.hosts, w.paused)
            self._append("world", self.world, reason=f"add {f.target}")
        elif f.kind == "agent_remove":
            if f.target in w.agent_ids:
                self.world = World(w.group, tuple(a for a in w.agents if a.id != f.target), w.hosts, w.paused)
                self._append("world", self.world, reason=f"remove {f.target}")
        elif f.kind == "cost":
            if f.target in w.agent_ids:
                self.world = World(
                    w.group, tuple(_with_cost(a, f.arg) if a.id == f.target else a for a in w.agents), w.hosts, w.paused
                )
                self._append("costs", self.world)
        elif f.kind in ("rb_pause", "rb_resume"):
            self.world = World(w.group, w.agents, w.hosts, f.kind == "rb_pause")
            self._append("control", self.world)

    def _ev_detect(self, h: str) -> None:
        w = self.world
        if h not in w.group or len(w.group) == 1:
            return
        self.world = World(tuple(g for g in w.group if g != h), w.agents, w.hosts, w.paused)
        self._append("world", self.world, reason=f"remove {h}")

    def _ev_append(self, why: str) -> None:
        """The operator pauses periodic rebalancing after the last fault, so that the schedule goes quiet."""
        w = self.world
        self.world = World(w.group, w.agents, w.hosts, True)
        self._append("control", self.world, reason="final pause")


def _moved(a: AgentSpec, host: str | None) -> AgentSpec:
    if a.current_host == host:
        return a
    return dataclasses.replace(a, current_host=host)


def _with_cost(a: AgentSpec, cost: float) -> AgentSpec:
    return dataclasses.replace(a, cost=cost)
