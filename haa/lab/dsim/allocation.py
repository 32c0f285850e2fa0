"""Deterministic simulation of agent allocation (Alg. 4) on N hosts: the verifier, AP-3 and the quality study.

`AllocSim` drives one `haa.core.allocation.Allocator` (and one `RebalancePolicy`) per host:

* bid updates travel over reliable FIFO channels with random delays (`haa.lab.dsim.network.DelayModel`);
* OAC is modelled as an ideal totally ordered atomic broadcast: a proposal is decided after a random delay,
  aborted with probability `p_abort` (the proposer retries, Alg. 4 ll. 25-28 / 89-92) or appended to one global
  log that every member delivers in order, each after its own delay (the real OAC is verified separately);
* the group and the agent list are part of the same log ("world" entries), as they are in the real system
  (membership transactions and the replicated agent table): a crash is followed, after a detection delay, by
  a membership entry that removes the host; a host paused for longer than that, or falsely suspected, is
  removed too and, once it runs again, delivers its own removal and stops; hosts join at the end of the list;
  agents are added and removed, costs change; the operator pauses and resumes periodic rebalancing;
* the leader's `RebalancePolicy` starts sessions on changes (rate limited) and periodically.

`check_alloc` then checks the schedule (properties in `PROPS`):

* AA-Validity: every accepted allocation places each allocatable agent of the agent list current at that
  point of the total order exactly once, on a member of the current group that has its hardware (and is not
  draining), and reports exactly the agents no member can run as unallocatable;
* AA-Table-Fidelity: every bid a member sends is its own accepted bid at that moment, so that the leader's
  copy of each member's row is that member's real opinion (what the thesis' consensus check relies on);
* AA-Agreement: every host that delivers a given OAC(finish) takes the same accept/ignore decision, and all
  hosts accept the same allocation for a session id;
* AA-Session-Order: committed (valid) start ids strictly increase, a leader never proposes an id twice, and
  each host accepts sessions in increasing order;
* AA-Liveness: after the last fault or change, every live member accepts an allocation of a session started
  after it within `LIVENESS_BOUND` seconds, and the system then goes quiet;
* AA-Quiescent-Agreement: once quiet, every member's accepted bids (bidTable_p[p]) name the same winners
  (the conflict rules converge). Whether they are also the committed allocation is not a property: the
  leader checks consensus on the last bids each member sent, and a bid still in flight can change the
  outcome after that (`premature`, counted in the statistics; docs/allocation.md, "consensus");
* AA-Messages: the bid-update messages of each session stay below `message_bound(agents, hosts)`.
* AA-Per-Host-Limit (issue 15): no accepted allocation puts more agents of a limited kind on one host than
  the kind's `max_per_host`, and the agents it leaves out for lack of places are exactly those the rule of
  docs/allocation.md ("per-host limits") names (checked as part of AA-Validity's exact unallocatable list).
  Half of the schedules give some agents a limited kind (`_limited_kinds`).

Every schedule is drawn from its seed (`draw_alloc`) and reproducible; `haactl verify allocation` runs them.

The same engine measures AP-3 (`cpu=True`: the real CPU time of every Allocator call advances the virtual
clock of its host) and the allocation quality (`quality_instance`, `optimum`: exhaustive optimum of
eq. 4.7-1 on small instances).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import random
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from haa.core.allocation import (
    AgentSpec,
    Allocated,
    Allocator,
    HostSpec,
    ProposeFinish,
    ProposeStart,
    RebalancePolicy,
    SendUpdate,
    SessionStart,
    agent_reward,
    same_bid,
)
from haa.core.effects import Log
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.scheduler import EventHeap

PROPS = (
    "AA-Validity",
    "AA-Table-Fidelity",
    "AA-Agreement",
    "AA-Session-Order",
    "AA-Liveness",
    "AA-Quiescent-Agreement",
    "AA-Messages",
    "AA-Per-Host-Limit",
)
#: seconds after the last fault or change within which every live member must accept an allocation
LIVENESS_BOUND = 4.0
HARDWARE = ("gpu", "camera", "lidar")


def message_bound(agents: int, hosts: int) -> int:
    """Bid-update messages one session may send: every host broadcasting a change of every bid a few dozen
    times. Far above what a converging session sends (docs/allocation.md, "verification"), far below a
    livelock's count within the liveness window."""
    return 40 * (agents + 2) * hosts * max(1, hosts - 1)


# --------------------------------------------------------------------------------------------- scenario


@dataclass(frozen=True)
class AFault:
    """One scheduled event: crash / pause (arg = seconds) / suspect (false suspicion) / join (arg = HostSpec)
    / agent_add (arg = AgentSpec) / agent_remove / cost (arg = new cost) / rb_pause / rb_resume."""

    at: float
    kind: str
    target: str = ""
    arg: Any = None

    def describe(self) -> str:
        a = ""
        if isinstance(self.arg, float):
            a = f" {self.arg:.3f}"
        elif isinstance(self.arg, (AgentSpec, HostSpec)):
            a = f" {self.arg}"
        return f"t={self.at:.3f} {self.kind} {self.target}{a}".rstrip()


@dataclass
class AllocScenario:
    seed: int
    names: list[str]
    hosts: dict[str, HostSpec]
    agents: tuple[AgentSpec, ...]
    delay: DelayModel = field(default_factory=lambda: DelayModel("exp", 0.0005, 0.002))
    deliver: DelayModel = field(default_factory=lambda: DelayModel("uniform", 0.0002, 0.002))
    oac_base: float = 0.002
    oac_scale: float = 0.004
    p_abort: float = 0.0
    p_slow: float = 0.0  # probability that an OAC takes 50-600 ms longer
    detect: tuple[float, float] = (0.1, 0.3)
    period: float = 1.0
    min_interval: float = 0.05
    session_timeout: float = 1.0
    proc: float = 0.0002  # a host handles its inbox this long after the first message arrives (batching)
    faults: list[AFault] = field(default_factory=list)
    final_pause: bool = True  # pause periodic rebalancing after the last fault, so that the schedule goes quiet
    liveness: float = LIVENESS_BOUND

    def describe(self) -> list[str]:
        out = [
            f"seed={self.seed} hosts={len(self.names)} agents={len(self.agents)} delay={self.delay.describe()} "
            f"oac={self.oac_base * 1e3:.1f}+exp({self.oac_scale * 1e3:.1f})ms p_abort={self.p_abort:.2f} "
            f"p_slow={self.p_slow:.2f} "
            f"period={self.period:.2f}s min_interval={self.min_interval:.3f}s faults={len(self.faults)}"
        ]
        out += [f"host {h}" for h in self.hosts.values()]
        out += [f"agent {a}" for a in self.agents]
        out += [f"fault {f.describe()}" for f in self.faults]
        return out

    @property
    def fault_end(self) -> float:
        return max((f.at + (f.arg if f.kind == "pause" else 0.0) for f in self.faults), default=0.0)


#: how likely a host has each kind of hardware (lidar is rare: some agents have no capable host)
HARDWARE_P = {"gpu": 0.4, "camera": 0.4, "lidar": 0.1}


def _host_spec(rng: random.Random, name: str) -> HostSpec:
    hw = frozenset(h for h in HARDWARE if rng.random() < HARDWARE_P[h])
    return HostSpec(name, round(rng.uniform(0.4, 2.0), 3), hw, draining=rng.random() < 0.04)


def _agent_spec(rng: random.Random, aid: str, others: list[str], hosts: list[str]) -> AgentSpec:
    hw = frozenset([rng.choice(HARDWARE)]) if rng.random() < 0.2 else frozenset()
    aff = {o: round(rng.uniform(0.01, 0.4), 3) for o in others if rng.random() < 0.15}
    cur = rng.choice(hosts) if hosts and rng.random() < 0.6 else None
    return AgentSpec(aid, round(rng.uniform(0.02, 0.7), 3), hw, aff, round(rng.uniform(0.0, 0.6), 3), cur)


def _delay_model(rng: random.Random) -> DelayModel:
    kind = rng.choice(["uniform", "exp", "lognormal", "pareto"])
    base = rng.uniform(0.0001, 0.001)
    if kind == "uniform":
        return DelayModel("uniform", base, rng.uniform(0.0005, 0.01))
    if kind == "exp":
        return DelayModel("exp", base, rng.uniform(0.0005, 0.005))
    if kind == "lognormal":
        return DelayModel("lognormal", base, rng.uniform(0.0005, 0.003), rng.uniform(0.3, 0.9))
    return DelayModel("pareto", base, rng.uniform(0.0005, 0.004), rng.uniform(2.2, 3.5))


def draw_alloc(seed: int, hosts: int = 7) -> AllocScenario:
    """One random schedule: hosts, agents, delays, OAC aborts, faults and changes (see the module docstring)."""
    rng = random.Random(f"alloc-{seed}")
    names = [f"h{i + 1}" for i in range(hosts)]
    specs = {n: _host_spec(rng, n) for n in names}
    n_agents = rng.randint(0, 9)
    ids = [f"a{i + 1}" for i in range(n_agents)]
    agents = tuple(_agent_spec(rng, a, [o for o in ids if o != a], names) for a in ids)
    sc = AllocScenario(
        seed=seed,
        names=names,
        hosts=specs,
        agents=agents,
        delay=_delay_model(rng),
        deliver=DelayModel("uniform", rng.uniform(0.0001, 0.001), rng.uniform(0.0005, 0.004)),
        oac_base=rng.uniform(0.0005, 0.004),
        oac_scale=rng.uniform(0.001, 0.01),
        p_abort=rng.choice([0.0, 0.0, 0.1, 0.3]),
        p_slow=rng.choice([0.0, 0.05, 0.2]),
        detect=(0.05, rng.uniform(0.1, 0.3)),
        period=rng.uniform(0.2, 1.5),
        min_interval=rng.uniform(0.0, 0.1),
        session_timeout=rng.uniform(0.3, 1.0),
        proc=rng.uniform(0.0003, 0.003),
    )
    # faults and changes within [0.05, 1.5] s; at least one initial host is never crashed, paused or suspected
    survivors = {rng.choice(names)}
    killable = [n for n in names if n not in survivors]
    t = 0.0
    next_host = hosts + 1
    next_agent = n_agents + 1
    live_agents = list(ids)
    all_hosts = list(names)
    for _ in range(rng.randint(0, 6)):
        t += rng.expovariate(1 / 0.25)
        if t > 1.5:
            break
        kind = rng.choice(
            ["crash", "pause", "pause", "suspect", "join", "agent_add", "agent_remove", "cost", "rb_pause", "rb_resume"]
        )
        at = round(t, 4)
        if kind in ("crash", "pause", "suspect"):
            if not killable:
                continue
            h = rng.choice(killable)
            if kind == "pause":
                sc.faults.append(AFault(at, "pause", h, round(rng.choice([0.02, 0.08, 0.2, 0.5]), 3)))
            else:
                killable.remove(h)
                sc.faults.append(AFault(at, kind, h))
        elif kind == "join":
            name = f"h{next_host}"
            next_host += 1
            all_hosts.append(name)
            sc.faults.append(AFault(at, "join", name, _host_spec(rng, name)))
        elif kind == "agent_add":
            aid = f"a{next_agent}"
            next_agent += 1
            spec = _agent_spec(rng, aid, live_agents, all_hosts)
            live_agents.append(aid)
            sc.faults.append(AFault(at, "agent_add", aid, spec))
        elif kind == "agent_remove":
            if not live_agents:
                continue
            aid = rng.choice(live_agents)
            live_agents.remove(aid)
            sc.faults.append(AFault(at, "agent_remove", aid))
        elif kind == "cost":
            if not live_agents:
                continue
            sc.faults.append(AFault(at, "cost", rng.choice(live_agents), round(rng.uniform(0.02, 0.7), 3)))
        else:
            sc.faults.append(AFault(at, kind))
    _limited_kinds(sc)
    return sc


#: kinds with a per-host limit the scenarios give agents (issue 15): name -> hardware every agent of it needs
LIMITED_KINDS = {"sonar": frozenset(), "landmark": frozenset(), "floor": frozenset({"camera"})}


def _limited_kinds(sc: AllocScenario) -> None:
    """In half of the schedules, give some agents (initial and added) a kind with a per-host limit (1 mostly,
    sometimes 2); its agents take the kind's hardware, as agents of one type do. Drawn from a random source of
    its own, so that the other half of the schedules are those drawn before limits existed."""
    rng = random.Random(f"alloc-limits-{sc.seed}")
    if rng.random() < 0.5:
        return
    kinds = rng.sample(sorted(LIMITED_KINDS), rng.randint(1, 2))
    limit = {k: rng.choice([1, 1, 1, 2]) for k in kinds}
    share = rng.uniform(0.3, 0.8)

    def limited(a: AgentSpec) -> AgentSpec:
        if rng.random() >= share:
            return a
        k = rng.choice(kinds)
        return dataclasses.replace(a, hardware=LIMITED_KINDS[k], kind=k, max_per_host=limit[k])

    sc.agents = tuple(limited(a) for a in sc.agents)
    sc.faults = [
        dataclasses.replace(f, arg=limited(f.arg)) if f.kind == "agent_add" else f for f in sc.faults
    ]


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
        return _Node(name, Allocator(name, committed), pol, first_entry, self.world)

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
        start = e.kind == "world" and node.policy.changed(self.now)
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


# --------------------------------------------------------------------------------------------- checks


@dataclass(frozen=True)
class AViolation:
    prop: str
    detail: str
    hosts: tuple[str, ...] = ()

    def __str__(self) -> str:
        return f"{self.prop}: {self.detail}"


def _no_place(start: SessionStart | None, capable: dict[str, list[str]]) -> set[str]:
    """The agents of limited kinds an allocation of `start` must leave out (a reference implementation of
    docs/allocation.md "per-host limits", independent of `haa.core.allocation.over_limit`): a kind has
    max_per_host places on each capable member; agents running on a capable member keep theirs first (at most
    max_per_host per member), then the others in the start's order."""
    if start is None:
        return set()
    out: set[str] = set()
    for kind in sorted({a.kind for a in start.agents if a.max_per_host}):
        members = [a for a in start.agents if a.kind == kind and a.max_per_host and capable.get(a.id)]
        if not members:
            continue
        hosts = capable[members[0].id]
        places = members[0].max_per_host * len(hosts)
        seated: Counter[str] = Counter()
        order = []
        for a in members:
            if a.current_host in hosts and seated[a.current_host] < a.max_per_host:
                seated[a.current_host] += 1
                order.append(a.id)
        order += [a.id for a in members if a.id not in order]
        out.update(order[places:])
    return out


def _per_host_limit(e: Entry) -> str:
    """AA-Per-Host-Limit: why an accepted allocation puts too many agents of a limited kind on a host."""
    assert e.finish is not None
    spec = {a.id: a for a in e.world.agents}
    count: Counter[tuple[str, str]] = Counter()
    for a, h in e.finish.allocation.items():
        s = spec.get(a)
        if s is not None and s.max_per_host:
            count[(h, s.kind)] += 1
            if count[(h, s.kind)] > s.max_per_host:
                return (
                    f"session {e.finish.ses_id} puts {count[(h, s.kind)]} agents of kind {s.kind!r} on {h} "
                    f"(at most {s.max_per_host}): {sorted(x for x, y in e.finish.allocation.items() if y == h)}"
                )
    return ""


def _validity(e: Entry, start: SessionStart | None = None) -> str:
    """Why an accepted allocation is invalid in the world of its entry ("" = valid). `start`: the session's
    committed start (the current hosts the per-host limits' places depend on)."""
    assert e.finish is not None
    w = e.world
    alloc = e.finish.allocation
    hosts = [w.hosts[g] for g in w.group]
    capable = {a.id: [h.name for h in hosts if h.can_run(a)] for a in w.agents}
    no_place = _no_place(start, capable)
    allocatable = [a for a, hs in capable.items() if hs and a not in no_place]
    missing = [a for a in allocatable if a not in alloc]
    if missing:
        return f"session {e.finish.ses_id} leaves allocatable agent(s) {missing} unallocated"
    extra = [a for a in alloc if a not in capable]
    if extra:
        return f"session {e.finish.ses_id} allocates agent(s) {extra} not in the agent list {list(w.agent_ids)}"
    for a, h in alloc.items():
        if h not in w.group:
            return f"session {e.finish.ses_id} puts {a} on {h}, not in the group {list(w.group)}"
        if h not in capable[a]:
            return f"session {e.finish.ses_id} puts {a} on {h}, which lacks its hardware or is draining"
    unalloc = sorted(a for a, hs in capable.items() if not hs or a in no_place)
    if sorted(e.finish.unallocatable) != unalloc:
        return f"session {e.finish.ses_id} reports unallocatable {sorted(e.finish.unallocatable)}, expected {unalloc}"
    return ""


def check_alloc(sim: AllocSim) -> list[AViolation]:
    """The properties of the module docstring, on a finished run."""
    out = [AViolation(p, d, tuple(h)) for p, d, h in sim.violations]
    starts: dict[int, SessionStart] = {}
    last_valid = 0
    for e in sim.log:
        if e.kind == "start" and e.accepted and e.start is not None:
            if e.start.ses_id <= last_valid:
                out.append(AViolation("AA-Session-Order", f"start {e.start.ses_id} committed after {last_valid}"))
            last_valid = max(last_valid, e.start.ses_id)
            starts.setdefault(e.start.ses_id, e.start)
        if e.kind != "finish" or e.finish is None:
            continue
        deciders = {n.name: n.decisions[e.index] for n in sim.nodes.values() if e.index in n.decisions}
        if len(set(deciders.values())) > 1:
            yes = sorted(h for h, v in deciders.items() if v)
            no = sorted(h for h, v in deciders.items() if not v)
            out.append(
                AViolation(
                    "AA-Agreement",
                    f"finish of session {e.finish.ses_id} (log[{e.index}]) accepted by {yes}, ignored by {no}",
                    tuple(yes + no),
                )
            )
        if any(deciders.values()) or (e.accepted and not deciders):
            why = _validity(e, starts.get(e.finish.ses_id))
            if why:
                out.append(AViolation("AA-Validity", why, (e.proposer,)))
            why = _per_host_limit(e)
            if why:
                out.append(AViolation("AA-Per-Host-Limit", why, (e.proposer,)))
    by_ses: dict[int, tuple[str, dict[str, str]]] = {}
    for n in sim.nodes.values():
        prev = 0
        for _idx, ses, _t, alloc in n.accepted:
            if ses <= prev:
                out.append(AViolation("AA-Session-Order", f"{n.name} accepted session {ses} after {prev}", (n.name,)))
            prev = ses
            other = by_ses.setdefault(ses, (n.name, alloc))
            if other[1] != alloc:
                out.append(
                    AViolation(
                        "AA-Agreement",
                        f"session {ses}: {n.name} accepted {sorted(alloc.items())}, {other[0]} "
                        f"{sorted(other[1].items())}",
                        (n.name, other[0]),
                    )
                )
    for ses, count in sim.msgs_by_ses.items():
        st = starts.get(ses)
        if st is None:
            continue
        bound = message_bound(len(st.agents), len(st.group))
        if count > bound:
            out.append(AViolation("AA-Messages", f"session {ses} sent {count} bid updates (bound {bound})"))
    out += _check_liveness(sim)
    return out


def _final_members(sim: AllocSim) -> list[_Node]:
    return [n for n in sim.nodes.values() if n.alive and n.member and n.name in sim.world.group]


def _check_liveness(sim: AllocSim) -> list[AViolation]:
    out: list[AViolation] = []
    deadline = sim.last_change + sim.sc.liveness
    for n in _final_members(sim):
        ok = [t for idx, _ses, t, _a in n.accepted if idx > sim.last_world_entry]
        if not ok or ok[0] > deadline:
            when = f"at {ok[0]:.3f} s" if ok else "never"
            out.append(
                AViolation(
                    "AA-Liveness",
                    f"{n.name} accepted no allocation within {sim.sc.liveness:g} s of the last change at "
                    f"{sim.last_change:.3f} s ({when}; sessions proposed {n.proposed[-5:]}, "
                    f"ledger at {sim.ledger.committed_ses}/{sim.ledger.finished_ses})",
                    (n.name,),
                )
            )
    if out or not sim.sc.final_pause:
        return out
    if not sim.quiet:
        return [AViolation("AA-Liveness", f"still busy at the horizon ({len(sim._q)} events queued)")]
    views: dict[str, dict[str, str]] = {}
    for n in _final_members(sim):
        s = n.alloc.session
        if s is None or not s.ready:
            continue
        views[n.name] = {j: b.winner for j, b in s.own.items() if b.winner is not None}
    distinct = {tuple(sorted(v.items())) for v in views.values()}
    if len(distinct) > 1:
        ref_name, ref = next(iter(views.items()))
        for name, v in views.items():
            if v != ref:
                diff = sorted(j for j in set(v) | set(ref) if v.get(j) != ref.get(j))
                out.append(
                    AViolation(
                        "AA-Quiescent-Agreement",
                        f"quiet, but {name} and {ref_name} accept different winners for {diff}: "
                        f"{[(j, v.get(j), ref.get(j)) for j in diff][:4]}",
                        (name, ref_name),
                    )
                )
    return out


def premature(sim: AllocSim) -> bool:
    """The last committed allocation differs from the winners every member holds once quiet: the leader's
    bid table showed agreement while older bids were still in flight (docs/allocation.md, "consensus")."""
    last = next((e for e in reversed(sim.log) if e.kind == "finish" and e.accepted), None)
    if last is None or last.finish is None or not sim.quiet:
        return False
    for n in _final_members(sim):
        s = n.alloc.session
        if s is not None and s.ses_id == last.finish.ses_id and s.ready:
            got = {j: b.winner for j, b in s.own.items() if b.winner is not None}
            return got != last.finish.allocation
    return False


# --------------------------------------------------------------------------------------------- sweep adapters


def run_schedule(seed: int, hosts: int, trace: bool = False) -> tuple[AllocScenario, AllocSim, list[AViolation]]:
    sc = draw_alloc(seed, hosts)
    sim = AllocSim(sc, trace=trace)
    sim.run()
    return sc, sim, check_alloc(sim)


def seed_result(seed: int, hosts: int) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed."""
    sc, sim, vs = run_schedule(seed, hosts)
    return {
        "seed": seed,
        "violations": [str(v) for v in vs],
        "liveness_checked": sim.quiet,
        "trace_hash": sim.hash.hexdigest()[:16],
        "events": sim.events,
        "messages": sim.messages,
        "stats": {
            "sessions": float(sim.ledger.committed_ses),
            "allocations": float(sum(1 for e in sim.log if e.kind == "finish" and e.accepted)),
            "faults": float(len(sc.faults)),
            "premature": float(premature(sim)),
        },
        "hosts": [h for v in vs for h in v.hosts],
        "description": sc.describe()[0],
    }


def full_trace(seed: int, hosts: int) -> list[str]:
    sc, sim, vs = run_schedule(seed, hosts, trace=True)
    out = [f"# {ln}" for ln in sc.describe()]
    out += sim.trace or []
    out += [f"# {v}" for v in vs]
    out.append(f"# trace hash {sim.hash.hexdigest()[:16]}")
    return out


def trace_excerpt(seed: int, hosts: int, bad_hosts: list[str], lines: int = 40) -> list[str]:
    """Scenario, then the log entries, faults and the concerned hosts' events (messages left to --trace)."""
    sc, sim, _vs = run_schedule(seed, hosts, trace=True)
    keys = tuple(f"{h}#" for h in sorted(set(bad_hosts)))
    picked = [
        ln
        for ln in sim.trace or []
        if " send ses=" not in ln and (" log[" in ln or " fault " in ln or not keys or any(k in ln for k in keys))
    ]
    out = [f"  scenario: {ln}" for ln in sc.describe()[:16]]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    return out + [f"  {ln}" for ln in picked]


# --------------------------------------------------------------------------------------------- quality


@dataclass
class QualityResult:
    seed: int
    regime: str
    agents: int
    hosts: int
    reward: float  # sum over hosts of eq. 4.7-1 (best bundle order) for the committed allocation
    optimum: float  # the exhaustive optimum of the same objective
    messages: int
    seconds: float  # virtual time from the leader's proposal to the committed finish

    @property
    def ratio(self) -> float:
        return self.reward / self.optimum if self.optimum > 0 else math.nan


#: instance families of the quality study
REGIMES = ("roomy", "tight")


def quality_instance(seed: int, regime: str = "roomy", max_agents: int = 8, max_hosts: int = 4) -> AllocScenario:
    """A random small instance: 2..max_agents agents and 2..max_hosts hosts with random costs, affinities,
    transfer penalties, current hosts and hardware (some agents need a gpu that only some hosts have).
    Capacities: `roomy` gives the hosts together 1.2-2x the total cost (split at random, each host at least
    5% above the largest agent: a good allocation usually exists without overload); `tight` draws each
    capacity from U(0.5, 1.6) whatever the load (about half of these instances cannot avoid overloading a
    host)."""
    if regime not in REGIMES:
        raise ValueError(f"regime: must be one of {REGIMES}, got {regime!r}")
    rng = random.Random(f"alloc-quality-{regime}-{seed}")
    nh = rng.randint(2, max_hosts)
    na = rng.randint(2, max_agents)
    names = [f"h{i + 1}" for i in range(nh)]
    ids = [f"a{i + 1}" for i in range(na)]
    agents = []
    for a in ids:
        aff = {o: round(rng.uniform(0.02, 0.3), 3) for o in ids if o != a and rng.random() < 0.3}
        agents.append(
            AgentSpec(
                a,
                round(rng.uniform(0.05, 0.6), 3),
                frozenset(["gpu"]) if rng.random() < 0.15 else frozenset(),
                aff,
                round(rng.uniform(0.0, 0.5), 3),
                rng.choice(names) if rng.random() < 0.6 else None,
            )
        )
    if regime == "roomy":
        per_host = sum(a.cost for a in agents) * rng.uniform(1.2, 2.0) / nh
        biggest = max(a.cost for a in agents)
        caps = [round(max(biggest * 1.05, per_host * rng.uniform(0.6, 1.4)), 3) for _ in names]
    else:
        caps = [round(rng.uniform(0.5, 1.6), 3) for _ in names]
    hosts = {
        n: HostSpec(n, caps[i], frozenset(["gpu"]) if rng.random() < 0.5 else frozenset()) for i, n in enumerate(names)
    }
    return AllocScenario(
        seed=seed,
        names=names,
        hosts=hosts,
        agents=tuple(agents),
        delay=_delay_model(rng),
        proc=rng.uniform(0.0003, 0.003),
        final_pause=True,
    )


def host_reward(host: HostSpec, agents: list[AgentSpec]) -> float:
    """R(b_h) of eq. 4.7-1 for the agents on one host, in the best bundle order: the agents within capacity
    first (any order), then the overflowing ones, the smallest that overflows first and the rest by cost."""
    ids = [a.id for a in agents]
    r = [agent_reward(a, host.name, ids) for a in agents]
    c = [a.cost for a in agents]
    k = host.capacity
    n = len(agents)
    if sum(c) < k:
        return sum(r)
    best = -math.inf
    for w in range(1 << n):
        cw = 0.0
        rw = 0.0
        rest = []
        for i in range(n):
            if w >> i & 1:
                cw += c[i]
                rw += r[i]
            else:
                rest.append(c[i])
        if cw >= k:
            continue
        rem = k - cw
        rest.sort()
        first = next((x for x in rest if x >= rem), None)
        if first is None:
            continue  # some "overflowing" agent would fit: that order is another W
        rest.remove(first)
        cum = first
        val = (rem - cum) / k
        for x in rest:
            cum += x
            val += (rem - cum) / k
        best = max(best, rw + val)
    return best


def total_reward(sc: AllocScenario, allocation: dict[str, str]) -> float:
    by_host: dict[str, list[AgentSpec]] = {h: [] for h in sc.hosts}
    for a in sc.agents:
        if a.id in allocation:
            by_host[allocation[a.id]].append(a)
    return sum(host_reward(sc.hosts[h], ags) for h, ags in by_host.items() if ags)


def optimum(sc: AllocScenario) -> tuple[float, dict[str, str]]:
    """The exhaustive optimum of sum_h R(b_h) over every allocation of the allocatable agents to hosts that
    have their hardware (dynamic programming over hosts and agent subsets)."""
    agents = [a for a in sc.agents if any(h.can_run(a) for h in sc.hosts.values())]
    n = len(agents)
    full = (1 << n) - 1
    hosts = list(sc.hosts.values())
    table: list[list[float]] = []
    for h in hosts:
        ok = 0
        for i, a in enumerate(agents):
            if h.can_run(a):
                ok |= 1 << i
        row = [-math.inf] * (full + 1)
        for m in range(full + 1):
            if m & ~ok:
                continue
            row[m] = host_reward(h, [agents[i] for i in range(n) if m >> i & 1]) if m else 0.0
        table.append(row)
    best = [0.0] + [-math.inf] * full  # best[m]: the agents of m placed on the hosts seen so far
    choice: list[list[int]] = []
    for row in table:
        nb = [-math.inf] * (full + 1)
        ch = [0] * (full + 1)
        for m in range(full + 1):
            t = m
            while True:  # every submask t of m goes to this host
                v = best[m ^ t] + row[t]
                if v > nb[m]:
                    nb[m] = v
                    ch[m] = t
                if t == 0:
                    break
                t = (t - 1) & m
        best = nb
        choice.append(ch)
    alloc: dict[str, str] = {}
    m = full
    for hi in range(len(hosts) - 1, -1, -1):
        t = choice[hi][m]
        for i in range(n):
            if t >> i & 1:
                alloc[agents[i].id] = hosts[hi].name
        m ^= t
    return best[full], alloc


def run_quality(seed: int, regime: str = "roomy") -> QualityResult:
    """Run one instance to its first committed allocation and compare it with the exhaustive optimum."""
    sc = quality_instance(seed, regime)
    sim = AllocSim(sc)
    sim.run(until=30.0)
    fin = next((e for e in sim.log if e.kind == "finish" and e.accepted), None)
    alloc = dict(fin.finish.allocation) if fin is not None and fin.finish is not None else {}
    opt, _ = optimum(sc)
    t0 = sim.ses_started.get(1, 0.0)
    return QualityResult(
        seed,
        regime,
        len(sc.agents),
        len(sc.hosts),
        total_reward(sc, alloc) if fin is not None else -math.inf,
        opt,
        sim.msgs_by_ses.get(1, 0),
        (fin.at - t0) if fin is not None else math.inf,
    )
