"""Deterministic simulation of the agent layer: allocation, transfer, backup and recovery on a host group.

`draw_agents(seed, hosts, mix)` turns one seed into a scenario: a host group as in `haa.lab.dsim.group` (joins,
leaves, crashes, restarts, pauses, delay spikes that make the failure detector suspect correct hosts), plus
a team of simulated agents that exchange numbered messages, operator moves (transfers), agent kills and
hangs. `AgentSim` runs it: every host is an `AgentNode` (haa.core.agents.agentnode) over its `MembershipNode`, and
the agent instances are `SimAgent`s that execute the node's commands with a small, seeded latency, as agent
processes would. `check_agents` then checks (`haactl verify transfer|recovery`; `mix` chooses the faults):

* AA-Allocation: after healing every agent is active on exactly one member host, the one its last committed
  allocation gives it, and no host runs an instance the table does not know.
* AG-Single-Active (fencing): at no moment do two instances of one agent run on hosts that are members of the
  group; an instance whose host has been removed is fenced (its sends are dropped by the members) and does
  not count. Every (agent, epoch) has at most one instance.
* AT-Consistency (Lemmas AT-1/AT-2): for a receiver that never crashed, the messages of each sender life are
  processed exactly once and in order; if that sender life never crashed either, every message it sent was
  processed. For a receiver that crashed: within each of its lives, no message twice and sender order kept.
* AR-Recovery: an agent recovered from a backup starts from the latest backup committed before its recovery
  (in the group's total order), or fresh if there was none.
* AG-Refuse-Invalid: transactions with out-of-bounds values that members propose without the edge checks
  (`haa.lab.dsim.hostile.refusable_agent_tx`, a few per schedule, issue 13) are refused by every replica, and no
  table ever holds a value outside the allocator's bounds (`AgentTable.invalid_values`).
* AG-No-Error: the agent layer's safety net (`AgentNode.drain` turns an exception in its reaction to one
  committed transaction into an `agent_layer_error` log, so a live host goes on) caught nothing.
* AG-Liveness: after healing the run goes quiet with every message delivered and no agent left frozen,
  freezing, crashed or waiting.

Faults are gated as in `haa.lab.dsim.group` (the thesis' assumptions: a correct majority in every view and every
open OAC). Every schedule is reproducible from its seed.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import random
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from haa.core.agentio import (
    AgentOpDone,
    AgentTimeline,
    AnswerAgent,
    BackupMade,
    DeliverAgent,
    Failed,
    FreezeAgent,
    Frozen,
    KillAgent,
    Sent,
    ShellReady,
    SpawnShell,
    StartAgent,
)
from haa.core.agents.agentnode import AgentConfig, AgentNode
from haa.core.ddb import agenttable as at
from haa.core.inputs import CreateAgent, InstanceEvent, MoveAgent
from haa.core.membership.globalstate import TxAgent, decode_tx
from haa.core.membership.membership import AppliedTx, MembershipNode, ViewChange
from haa.lab.dsim import hostile
from haa.lab.dsim.cluster import ALIVE, CRASHED, EV_CALL, PAUSED, SimHost
from haa.lab.dsim.group import GroupScenario, GroupSim, GroupViolation, draw_group

Proc = tuple[str, int]

MIXES = ("transfer", "recovery")
#: agent-layer settings of the simulation (seconds of virtual time)
SIM_AGENT = AgentConfig(rebalance_period=0.0, min_session_gap=0.05, poll=0.005, drain_timeout=3.0)
#: simulated process latencies: spawn a shell, execute a command, emit an event
SPAWN_DELAY = (0.005, 0.03)
CMD_DELAY = (0.0002, 0.003)
SEND_PERIOD = (0.05, 0.2)
BACKUP_EVERY = 20  # processed messages between two backups


def node_of(h: SimHost) -> AgentNode | None:
    """The `AgentNode` an `AgentSim` host runs as its core (haa.lab.dsim.cluster.SimCore), None while crashed."""
    core = h.core
    return core if isinstance(core, AgentNode) else None


def live_node(h: SimHost) -> AgentNode:
    """The `AgentNode` of a host that has one (alive or paused)."""
    core = h.live_core
    if not isinstance(core, AgentNode):
        raise TypeError(f"{h.name}'s core is a {type(core).__name__}, not an AgentNode")
    return core


@dataclass
class AgentScenario:
    group: GroupScenario
    mix: str
    n_agents: int
    create_at: float
    moves: list[tuple[float, int, int]] = field(default_factory=list)  # (time, agent index, host index)
    kills: list[tuple[float, int]] = field(default_factory=list)  # (time, agent index)
    hangs: list[tuple[float, int]] = field(default_factory=list)
    sends_end: float = 0.0
    #: (time, seed) of transactions with out-of-bounds values that a member proposes without the edge checks
    #: (haa.lab.dsim.hostile.refusable_agent_tx): every replica must refuse them and nothing may raise (issue 13)
    hostile: list[tuple[float, int]] = field(default_factory=list)

    def describe(self) -> list[str]:
        out = self.group.describe()
        out.append(f"mix={self.mix} agents={self.n_agents} created at {self.create_at:.2f}")
        out += [f"t={t:.3f} move agent#{a} to host#{h}" for t, a, h in self.moves]
        out += [f"t={t:.3f} kill agent#{a}" for t, a in self.kills]
        out += [f"t={t:.3f} hang agent#{a}" for t, a in self.hangs]
        out += [f"t={t:.3f} hostile transaction (seed {s})" for t, s in self.hostile]
        return out


def draw_agents(seed: int, hosts: int = 7, mix: str = "transfer") -> AgentScenario:
    if mix not in MIXES:
        raise ValueError(f"unknown mix {mix!r}; choose from {MIXES}")
    g = draw_group(seed, hosts, "membership", dissolve=False)
    rng = random.Random(seed * 104729 + 17)
    g.writes = []  # the agents are the workload
    if mix == "transfer":
        # transfers under pauses, spikes (false suspicions), joins and graceful leaves; no crash
        g.faults = [f for f in g.faults if f.kind not in ("crash", "crash_mid", "restart")]
    g.deadline = 60.0
    sc = AgentScenario(g, mix, rng.randint(2, 6), rng.uniform(1.5, 2.0))
    n_hosts = len(g.names)
    for _ in range(rng.randint(2, 10)):
        sc.moves.append((rng.uniform(sc.create_at + 0.2, g.fault_end), rng.randrange(sc.n_agents),
                         rng.randrange(n_hosts)))
    if mix == "recovery":
        for _ in range(rng.randint(1, 4)):
            sc.kills.append((rng.uniform(sc.create_at + 0.2, g.fault_end), rng.randrange(sc.n_agents)))
        if rng.random() < 0.3:
            sc.hangs.append((rng.uniform(sc.create_at + 0.2, g.fault_end), rng.randrange(sc.n_agents)))
    # drawn from their own generator, so that the rest of a seed's scenario is what it was before they existed
    hr = random.Random(seed * 7919 + 5)
    sc.hostile = sorted((hr.uniform(sc.create_at, g.fault_end), hr.randrange(2**32)) for _ in range(hr.randint(0, 3)))
    sc.moves.sort()
    sc.kills.sort()
    sc.sends_end = g.fault_end
    return sc


# ------------------------------------------------------------------------------------------ simulated agents


@dataclass
class SimAgent:
    """One agent instance on one host: a counter agent that sends numbered messages to every other agent and
    records what it processes. Its state (packed as JSON bytes, as a real agent would pack its own) is the
    next number per receiver, the generation (a new one per recovery) and the processed count."""

    agent: str
    epoch: int
    host: Proc
    started: bool = False
    running: bool = True
    gen: int = 0
    next_n: dict[str, int] = field(default_factory=dict)
    processed: int = 0
    hung: bool = False

    def pack(self) -> bytes:
        return json.dumps({"gen": self.gen, "next": self.next_n, "processed": self.processed},
                          sort_keys=True).encode()

    def unpack(self, data: bytes) -> None:
        d = json.loads(data)
        self.gen, self.next_n, self.processed = d["gen"], dict(d["next"]), d["processed"]


@dataclass
class AgentHistory:
    #: per receiver agent: (time, receiver epoch, receiver life key, sender, sender gen, n)
    processed: dict[str, list[tuple[float, int, int, str, int, int]]] = field(
        default_factory=lambda: defaultdict(list))
    #: per (sender, gen, receiver): messages sent
    sent: dict[tuple[str, int, str], int] = field(default_factory=lambda: defaultdict(int))
    #: instance intervals: agent -> list of [host proc, epoch, start, end]
    intervals: dict[str, list[list[Any]]] = field(default_factory=lambda: defaultdict(list))
    #: per agent, in total order (as one member applied them): ("backup", data) / ("recovered", epoch it gave)
    order: dict[str, list[tuple[str, Any]]] = field(default_factory=lambda: defaultdict(list))
    epochs: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    #: first starts and recoveries, in the order the instances ran them: (agent, epoch, mode, state given)
    recovered_starts: list[tuple[str, int, str, bytes | None]] = field(default_factory=list)
    removed_at: dict[Proc, float] = field(default_factory=dict)  # first time a process left the group
    order_observer: Proc | None = None
    ids: list[str] = field(default_factory=list)
    timeline: list[tuple[float, str, str, str]] = field(default_factory=list)
    gens: int = 0
    #: encoded hostile agent transactions injected (data -> kind), and those some replica accepted
    hostile: dict[bytes, str] = field(default_factory=dict)
    hostile_accepted: list[str] = field(default_factory=list)
    gen_of_start: list[tuple[str, int]] = field(default_factory=list)  # (agent, generation) per start
    epochs_seen: dict[tuple[str, int], Proc] = field(default_factory=dict)
    double_epoch: list[str] = field(default_factory=list)


class AgentSim(GroupSim):
    """Runs one `AgentScenario` (see the module docstring)."""

    def __init__(self, sc: AgentScenario, trace: bool = False) -> None:
        super().__init__(sc.group, trace)
        # the agent checks do not use the per-apply state hash of the DDB checks (HM-Agreement and the
        # membership properties are verified by `haactl verify membership|ddb`): skip its cost
        self.node_cfg = dataclasses.replace(self.node_cfg, hash_every_apply=False)
        self.asc = sc
        self.ah = AgentHistory()
        self.arng = random.Random(sc.group.seed * 7 + 3)
        self.inst: dict[Proc, dict[str, SimAgent]] = defaultdict(dict)
        self.fifo: dict[tuple[str, int, str], float] = {}
        self.ah.ids = [f"{sc.group.seed:x}-a{i}" for i in range(sc.n_agents)]

    # ------------------------------------------------------------------ nodes

    def _make_node(self, h: SimHost, inc: int) -> AgentNode:  # type: ignore[override]
        node = super()._make_node(h, inc)
        return AgentNode(node, SIM_AGENT)

    def _on_effect(self, h: SimHost, e: Any) -> None:
        t = type(e)
        proc = (h.name, h.inc)
        if t in (SpawnShell, StartAgent, DeliverAgent, FreezeAgent, KillAgent, AnswerAgent):
            self._command(h, e)
            return
        if t is AgentTimeline:
            self.ah.timeline.append((self.cl.now, h.name, e.name, e.event))
            self.cl._note(f"agent {e.name} {e.event} on {h.name} {e.detail}")
            return
        if t is AgentOpDone:
            return  # a refused creation is asked again by `_ensure_created`
        if t is AppliedTx:
            self._observe_applied(proc, e)
        if t is ViewChange:
            for m in e.removed:
                self.ah.removed_at.setdefault(m.proc, self.cl.now)
                self._fence(m.proc)
        super()._on_effect(h, e)

    def _observe_applied(self, proc: Proc, e: AppliedTx) -> None:
        """The total order of backups and recoveries, as seen by one member (all agree: HM-Agreement)."""
        ah = self.ah
        if ah.hostile and e.kind == "agent":
            gtx = decode_tx(e.payload)
            hk = ah.hostile.get(gtx.data) if type(gtx) is TxAgent else None
            res0 = e.result
            # a costs transaction applies (ok) but ignores values out of bounds; every other kind is refused
            if hk is not None and hk != "costs" and isinstance(res0, at.AgentApplied) and res0.ok:
                ah.hostile_accepted.append(f"{hk} accepted at {proc[0]}#{proc[1]} seq {e.seq}")
        if ah.order_observer is None:
            ah.order_observer = proc
        if proc != ah.order_observer or e.kind != "agent":
            return
        tx = decode_tx(e.payload)
        if type(tx) is not TxAgent:
            return
        atx = at.decode(tx.data)
        kind = atx.WhichOneof("body")
        res = e.result
        if not isinstance(res, at.AgentApplied) or not res.ok:
            return
        if kind == "backup":
            ah.order[atx.backup.id].append(("backup", atx.backup.data))
        elif kind in ("claim", "recovered"):
            # every valid claim or recovery raises the agent's epoch by one: the epoch it gives
            agent = getattr(atx, kind).id
            ah.epochs[agent] += 1
            if kind == "recovered":
                ah.order[agent].append(("recovered", ah.epochs[agent]))

    def _fence(self, proc: Proc) -> None:
        """`proc` left the group: its instances are fenced (they no longer count as running)."""
        for a in self.inst.get(proc, {}).values():
            self._end(a)

    def _end(self, a: SimAgent) -> None:
        if a.running:
            a.running = False
            for iv in self.ah.intervals[a.agent]:
                if iv[0] == a.host and iv[1] == a.epoch and iv[3] is None:
                    iv[3] = self.cl.now

    # ------------------------------------------------------------------ executing commands

    def _later(self, h: SimHost, delay: tuple[float, float], fn: Any, chan: str = "") -> None:
        """Run `fn` at host `h` after a seeded delay; calls on one channel (an agent's command stream, or its
        event stream) keep their order, as a pipe between a host and an agent process does."""
        inc = h.inc
        cl = self.cl
        when = cl.now + self.arng.uniform(*delay)
        if chan:
            key = (h.name, inc, chan)
            when = max(when, self.fifo.get(key, 0.0))
            self.fifo[key] = when

        def run() -> None:
            if h.inc != inc or h.core is None or h.state == CRASHED:
                return
            if h.state == PAUSED:
                h.backlog.append((EV_CALL, run))
                return
            fn()
            cl._apply(h)

        cl.at(when, run)

    def _event(self, h: SimHost, ev: Any) -> None:
        node = node_of(h)
        if node is not None:
            node.step(h.local(self.cl.now), InstanceEvent(ev))

    def _command(self, h: SimHost, c: Any) -> None:
        proc = (h.name, h.inc)
        insts = self.inst[proc]
        t = type(c)
        if t is SpawnShell:
            def spawn() -> None:
                old = insts.get(c.agent)
                if old is not None:  # a shell left over (killed meanwhile, or never started): replaced
                    self._end(old)
                insts[c.agent] = SimAgent(c.agent, c.epoch, proc)
                self._event(h, ShellReady(c.agent, c.epoch))
            self._later(h, SPAWN_DELAY, spawn, "c:" + c.agent)
        elif t is StartAgent:
            def start() -> None:
                a = insts.get(c.agent)
                if a is None or a.epoch != c.epoch or not a.running:
                    return
                a.started = True
                key = (c.agent, c.epoch)
                prev = self.ah.epochs_seen.get(key)
                if prev is not None and prev != proc:
                    self.ah.double_epoch.append(f"{c.agent} epoch {c.epoch} on {prev} and {proc}")
                self.ah.epochs_seen[key] = proc
                if c.mode == "thaw":
                    a.unpack(c.state or b"{}")
                else:
                    self.ah.gens += 1
                    self.ah.recovered_starts.append((c.agent, c.epoch, c.mode, c.state))
                    self.ah.gen_of_start.append((c.agent, self.ah.gens))
                    if c.mode == "recover" and c.state is not None:
                        a.unpack(c.state)
                    # a fresh start or a recovery begins a new sender generation, numbered from 1
                    a.gen = self.ah.gens
                    a.next_n = {}
                self.ah.intervals[c.agent].append([proc, c.epoch, self.cl.now, None])
                for m in c.messages:
                    self._process(a, m)
                self._schedule_send(h, a)
            self._later(h, CMD_DELAY, start, "c:" + c.agent)
        elif t is DeliverAgent:
            def deliver() -> None:
                a = insts.get(c.agent)
                if a is not None and a.epoch == c.epoch and a.running and a.started and not a.hung:
                    self._process(a, c.msg)
                    if a.processed % BACKUP_EVERY == 0:
                        self._event(h, BackupMade(a.agent, a.epoch, a.pack()))
            self._later(h, CMD_DELAY, deliver, "c:" + c.agent)
        elif t is FreezeAgent:
            def freeze() -> None:
                a = insts.get(c.agent)
                if a is None or a.epoch != c.epoch or not a.running:
                    return
                state = a.pack()
                self._end(a)
                insts.pop(c.agent, None)
                self._event(h, Frozen(a.agent, a.epoch, state))
            self._later(h, CMD_DELAY, freeze, "c:" + c.agent)
        elif t is KillAgent:
            a = insts.get(c.agent)
            if a is not None and a.epoch == c.epoch:
                self._end(a)
                insts.pop(c.agent, None)

    def _process(self, a: SimAgent, m: Any) -> None:
        try:
            d = json.loads(m.payload)
        except ValueError:
            return
        a.processed += 1
        self.ah.processed[a.agent].append((self.cl.now, a.epoch, a.gen, d["s"], d["g"], d["n"]))

    def _schedule_send(self, h: SimHost, a: SimAgent) -> None:
        if self.cl.now >= self.asc.sends_end:
            return

        def tick() -> None:
            if not a.running or a.hung:
                return
            node = node_of(h)
            table = node.table if node is not None else None
            for dst in self.ah.ids:
                if dst == a.agent or table is None or table.get(dst) is None:
                    continue  # a real agent sends to the agents it knows of
                n = a.next_n.get(dst, 1)
                a.next_n[dst] = n + 1
                self.ah.sent[(a.agent, a.gen, dst)] += 1
                payload = json.dumps({"s": a.agent, "g": a.gen, "n": n}).encode()
                self._event(h, Sent(a.agent, a.epoch, dst, payload))
            self._schedule_send(h, a)

        self._later(h, SEND_PERIOD, tick)

    # ------------------------------------------------------------------ the scenario

    def _members(self) -> list[SimHost]:
        return [h for h in self.cl.by_idx if h.state == ALIVE and (nd := node_of(h)) is not None and nd.m.is_member()]

    def _create(self, only: int | None = None) -> None:
        """The operator creates the scenario's agents (`only`: agent #only) through a member drawn at random, as
        soon as there is one; `_create_agent` says what each agent is."""
        hs = self._members()
        if not hs:
            self.cl.at(self.cl.now + 0.1, lambda: self._create(only))
            return
        h = self.arng.choice(hs)
        node, now = live_node(h), h.local(self.cl.now)
        for i, agent in enumerate(self.ah.ids):
            if only is None or i == only:
                self._create_agent(node, now, i, agent)
        self.cl._apply(h)

    def _create_agent(self, node: AgentNode, now: float, i: int, agent: str) -> None:
        """Ask `node` to create agent #`i` (id `agent`): a counter of a random cost."""
        node.step(now, CreateAgent(agent, "counter", b"", cost=self.arng.uniform(0.05, 0.3), transfer_penalty=0.1,
                                   recovery="backup", req=("create", i)))

    def _ensure_created(self) -> None:
        """An operator whose request died with its host asks again (until the end of the fault window)."""
        hs = self._members()
        if hs:
            table = live_node(hs[0]).table
            for i, agent in enumerate(self.ah.ids):
                if table.get(agent) is None:
                    self._create(only=i)
        if self.cl.now + 0.5 <= self.asc.group.fault_end:
            self.cl.at(self.cl.now + 0.5, self._ensure_created)

    def _move(self, ai: int, hi: int) -> None:
        hs = self._members()
        if not hs:
            return
        h = self.arng.choice(hs)
        node = live_node(h)
        names = [m.name for m in node.m.state.members]
        target = names[hi % len(names)]
        node.step(h.local(self.cl.now), MoveAgent(self.ah.ids[ai], target))
        self.cl._apply(h)

    def _kill(self, ai: int, hang: bool) -> None:
        agent = self.ah.ids[ai]
        for proc, insts in self.inst.items():
            a = insts.get(agent)
            h = self.cl.hosts[proc[0]]
            if a is None or not a.running or h.inc != proc[1] or h.state != ALIVE:
                continue
            self._end(a)
            insts.pop(agent, None)
            reason = "hung: no heartbeat" if hang else "killed by signal 9"
            self._later(h, (0.01, 0.05) if not hang else (0.3, 0.6),
                        lambda h=h, a=a, reason=reason: self._event(h, Failed(a.agent, a.epoch, reason)))
            return

    def run(self) -> None:
        sc = self.asc
        self.cl.at(sc.create_at, self._create)
        self.cl.at(sc.create_at + 0.5, self._ensure_created)
        for t, ai, hi in sc.moves:
            self.cl.at(t, functools.partial(self._move, ai, hi))
        for t, ai in sc.kills:
            self.cl.at(t, functools.partial(self._kill, ai, False))
        for t, ai in sc.hangs:
            self.cl.at(t, functools.partial(self._kill, ai, True))
        for t, hs in sc.hostile:
            self.cl.at(t, functools.partial(self._hostile, hs))
        self.cl.on_restart = lambda name, inc: None
        super().run()

    def _hostile(self, seed: int) -> None:
        hs = self._members()
        if not hs:
            return
        rng = random.Random(seed)
        h = rng.choice(hs)
        node = live_node(h)
        kind, data = hostile.refusable_agent_tx(rng, self.ah.ids, [m.name for m in node.m.state.members])
        self.ah.hostile[data] = kind
        node.m.submit(h.local(self.cl.now), data, ("hostile", seed), kind="agent")
        self.cl._apply(h)

    def _crash(self, f: Any, restart_after: float | None) -> None:
        h = self.cl.hosts[f.host]
        proc = (f.host, h.inc)
        for a in self.inst.get(proc, {}).values():
            self._end(a)
        super()._crash(f, restart_after)

    def _quiet(self) -> bool:
        if not super()._quiet():
            return False
        for h in self.cl.by_idx:
            node = node_of(h)
            if node is None:
                continue
            for loc in node.local.values():
                if loc.phase != "active":
                    return False
            if node.recovery.orphans or node.router.pushes or node.recovery.backoff:  # e.g. a start-failure backoff
                return False
        return True


# ------------------------------------------------------------------------------------------------ checks

AGENT_PROPS = frozenset(
    {"AA-Allocation", "AG-Single-Active", "AT-Consistency", "AR-Recovery", "AG-Liveness", "AG-Refuse-Invalid",
     "AG-No-Error"}
)


def check_agents(sim: AgentSim) -> list[GroupViolation]:
    out: list[GroupViolation] = []
    ah = sim.ah
    cl = sim.cl

    def bad(prop: str, detail: str, *hosts: str) -> None:
        out.append(GroupViolation(prop, detail, sorted(set(hosts))))

    # AG-Single-Active
    for d in ah.double_epoch:
        bad("AG-Single-Active", f"two instances with one fencing epoch: {d}")
    for agent, ivs in ah.intervals.items():
        spans = []
        for proc, epoch, t0, t1 in ivs:
            end = t1 if t1 is not None else cl.now
            removed = ah.removed_at.get(proc)
            if removed is not None:
                end = min(end, removed)
            if end > t0:
                spans.append((t0, end, proc, epoch))
        spans.sort()
        for (a0, a1, ap, ae), (b0, _b1, bp, be) in itertools.pairwise(spans):
            if b0 < a1 - 1e-12:
                bad("AG-Single-Active", f"agent {agent}: epoch {ae} on {ap[0]}#{ap[1]} [{a0:.3f}, {a1:.3f}] "
                    f"overlaps epoch {be} on {bp[0]}#{bp[1]} from {b0:.3f}", ap[0], bp[0])
    # an agent crashed (from the group's point of view: its instance died, or its host left the group while
    # running or freezing it) exactly when it was recovered (started again other than by a thaw); every
    # generation but its last ended in a crash
    gens_of: dict[str, list[int]] = defaultdict(list)
    for agent, gen in ah.gen_of_start:
        gens_of[agent].append(gen)
    # (an agent whose first instance never ran — its host was removed before starting it — was recovered
    # too: it lost what was sent to it meanwhile, although it has one start only)
    crashed_agents = {a for a, gs in gens_of.items() if len(gs) > 1}
    crashed_agents |= {a for a, _e, mode, _s in ah.recovered_starts if mode == "recover"}
    crashed_gens = {(a, g) for a, gs in gens_of.items() for g in gs[:-1]}
    # AT-Consistency
    for recv in ah.ids:
        recs = ah.processed.get(recv, [])
        crashed_recv = recv in crashed_agents
        by_stream: dict[tuple[Any, ...], list[int]] = defaultdict(list)
        for _t, _epoch, rgen, s, g, n in recs:
            key = (s, g) if not crashed_recv else (s, g, rgen)
            by_stream[key].append(n)
        for key, ns in by_stream.items():
            for x, y in itertools.pairwise(ns):
                if y <= x:
                    bad("AT-Consistency", f"{recv} processed {key[0]} gen {key[1]} message {y} after {x} "
                        f"({'duplicate' if y == x else 'out of order'})")
                    break
            if crashed_recv:
                continue
            s, g = key[0], key[1]
            if ns and ns[0] != 1 and (s, g) not in crashed_gens:
                bad("AT-Consistency", f"{recv} lost {s} gen {g} messages before {ns[0]}")
            if (s, g) in crashed_gens:
                continue
            for x, y in itertools.pairwise(ns):
                if y != x + 1 and y > x:
                    bad("AT-Consistency", f"{recv} lost {s} gen {g} messages {x + 1}..{y - 1}")
                    break
        if not crashed_recv and sim.quiescent:
            got = {(k[0], k[1]): len(v) for k, v in by_stream.items()}
            for (s, g, dst), n in ah.sent.items():
                if dst != recv or (s, g) in crashed_gens:
                    continue
                if got.get((s, g), 0) != n:
                    bad("AT-Consistency", f"{recv} processed {got.get((s, g), 0)} of the {n} messages "
                        f"{s} gen {g} sent")
    # AR-Recovery: the state a recovered instance got is the latest backup committed before the OAC(recovered)
    # that gave it its epoch (some recoveries never start an instance: their host left first)
    for agent, epoch, mode, state in ah.recovered_starts:
        if mode != "recover":
            continue  # the first start of a new agent (it has no backup)
        order = ah.order.get(agent, [])
        at_ = next((i for i, (kind, e) in enumerate(order) if kind == "recovered" and e == epoch), None)
        if at_ is None:
            continue  # the observer did not see it (it left the group first)
        before = [d for kind, d in order[:at_] if kind == "backup"]
        want = before[-1] if before else None
        if state != want:
            bad("AR-Recovery", f"{agent} epoch {epoch} recovered from "
                f"{'no backup' if state is None else 'an older backup'} instead of the latest committed one")
    # AG-No-Error: the agent layer's safety net (AgentNode.drain) caught nothing — it keeps a live host going,
    # but in the simulator a caught exception is a bug like any crash
    for t, proc, event, detail in cl.history.core_errors:
        bad("AG-No-Error", f"{event} at {proc[0]}#{proc[1]} t={t:.3f}: {detail[:300]}", proc[0])
    # AG-Refuse-Invalid: out-of-bounds values proposed without the edge checks never enter a table (issue 13)
    for d in ah.hostile_accepted:
        bad("AG-Refuse-Invalid", f"a hostile transaction was applied: {d}")
    for h in cl.by_idx:
        node = node_of(h)
        if h.state == ALIVE and node is not None:
            for d in node.table.invalid_values():
                bad("AG-Refuse-Invalid", f"{h.name}'s table holds {d}", h.name)
    # AA-Allocation and AG-Liveness after healing
    if not sim.quiescent:
        bad("AG-Liveness", "the run did not get quiet after healing")
        return out
    members = [h for h in cl.by_idx if h.state == ALIVE and (nd := node_of(h)) is not None and nd.m.is_member()]
    if not members:
        return out
    table = live_node(members[0]).table
    names = {h.name for h in members}
    for r in table:
        if r.status != at.ACTIVE or r.owner not in names:
            bad("AG-Liveness", f"agent {r.name} ({r.id}) ends {r.status} owner={r.owner or '-'} alloc={r.alloc}")
            continue
        if r.alloc and r.alloc != r.owner and r.alloc in names:
            bad("AA-Allocation", f"agent {r.name} runs on {r.owner} but is allocated to {r.alloc}")
        runners = [h.name for h in members if r.id in live_node(h).local]
        if runners != [r.owner]:
            bad("AA-Allocation", f"agent {r.name} owned by {r.owner} runs on {runners}", *runners)
    for h in members:
        for agent in live_node(h).local:
            if table.get(agent) is None:
                bad("AA-Allocation", f"{h.name} runs unknown agent {agent}", h.name)
    if len(table) != len(ah.ids) and sim.cl.now > sim.asc.create_at + 1:
        bad("AG-Liveness", f"{len(table)} of {len(ah.ids)} agents were created")
    return out


def run_agents(seed: int, hosts: int = 7, mix: str = "transfer") -> tuple[AgentSim, list[GroupViolation]]:
    sc = draw_agents(seed, hosts, mix)
    sim = AgentSim(sc)
    sim.run()
    return sim, check_agents(sim)


def is_member_node(node: Any) -> MembershipNode | None:
    """The membership node of a simulated host's state machine (an `AgentNode` wraps one)."""
    m = getattr(node, "m", node)
    return m if isinstance(m, MembershipNode) else None


# ------------------------------------------------------------------------------------------------ the verifier


def seed_fields(seed: int, sim: AgentSim, vs: list[GroupViolation], stats: dict[str, float],
                scenario: list[str]) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed run by an `AgentSim` (this module's verifier,
    `haa.lab.dsim.joins`, `haa.lab.dsim.vagent`): its violations `vs`, the run's counts, the verifier's own `stats` and
    the first lines of the `scenario`'s description."""
    return {
        "seed": seed,
        "violations": [str(v) for v in vs],
        "liveness_checked": sim.quiescent,
        "trace_hash": sim.cl.trace_hash(),
        "events": sim.cl.events,
        "messages": sum(sim.cl.msg_counts.values()),
        "stats": stats,
        "hosts": [h for v in vs for h in v.hosts],
        "description": " | ".join(scenario[:3]),
    }


def seed_result(seed: int, hosts: int, mix: str) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed (`haactl verify transfer|recovery`)."""
    sim, vs = run_agents(seed, hosts, mix)
    ah = sim.ah
    transfers = sum(1 for _t, _h, _n, ev in ah.timeline if ev == "thawed")
    recoveries = sum(1 for _a, _e, mode, _s in ah.recovered_starts if mode == "recover")
    return seed_fields(seed, sim, vs, {
        "transfers": float(transfers),
        "recoveries": float(recoveries),
        "processed": float(sum(len(v) for v in ah.processed.values())),
        "faults_dropped": float(len(sim.gh.dropped)),
    }, sim.asc.describe())


_NOISE = ("Heartbeat(", "SetPeriod(", "StateSnapshot(", "StateForward(")


def full_trace(seed: int, hosts: int, mix: str) -> list[str]:
    sc = draw_agents(seed, hosts, mix)
    sim = AgentSim(sc, trace=True)
    sim.run()
    vs = check_agents(sim)
    out = [f"# {ln}" for ln in sc.describe()]
    out += [ln for ln in sim.cl.trace or [] if not any(k in ln for k in _NOISE)]
    out += [f"# {v}" for v in vs]
    out.append(f"# trace hash {sim.cl.trace_hash()}")
    return out


def trace_excerpt(seed: int, hosts: int, mix: str, bad_hosts: list[str], lines: int = 40) -> list[str]:
    """Scenario, then the agent timeline, views and faults (and the concerned hosts' logs)."""
    sc = draw_agents(seed, hosts, mix)
    sim = AgentSim(sc, trace=True)
    sim.run()
    keys = tuple(f"{h}#" for h in sorted(set(bad_hosts)))
    words = (" agent ", " view ", "crash", "pause")

    def wanted(ln: str) -> bool:
        if " -> " in ln or " <- " in ln:
            return False
        return any(w in ln for w in words) or bool(keys and any(k in ln for k in keys))

    picked = [ln for ln in sim.cl.trace or [] if wanted(ln)]
    out = [f"  scenario: {ln}" for ln in sc.describe()[:16]]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    return out + [f"  {ln}" for ln in picked]
