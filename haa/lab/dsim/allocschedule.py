"""The schedules of the allocation verifier (`haa.lab.dsim.allocation`): what `AllocSim` runs.

`draw_alloc(seed, hosts)` draws one schedule from its seed: hosts (capacity, hardware, draining), agents (cost,
hardware, affinities, transfer penalty, current host; in half of the schedules some of a kind with a per-host
limit, `_limited_kinds`), the delays of the bid-update channels and of OAC, OAC aborts, and the faults and changes
(`AFault`: crash, pause, false suspicion, join, agent added or removed, cost changed, rebalancing paused or
resumed). `AllocScenario` holds it; `describe()` prints it.
"""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass, field
from typing import Any

from haa.core.allocation.specs import AgentSpec, HostSpec
from haa.lab.dsim.network import DelayModel

#: seconds after the last fault or change within which every live member must accept an allocation
LIVENESS_BOUND = 4.0
HARDWARE = ("gpu", "camera", "lidar")

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
    session_agents: int = 0  # most agents a session auctions (0: the Allocator's own, specs.MAX_SESSION_AGENTS)

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
    _bursts(sc, next_agent, live_agents, all_hosts)
    _limited_kinds(sc)
    return sc


def _bursts(sc: AllocScenario, next_agent: int, live_agents: list[str], all_hosts: list[str]) -> None:
    """In a quarter of the schedules, a burst of 8-30 spawns within a few milliseconds, and sessions bounded to
    3-6 agents (specs.MAX_SESSION_AGENTS in small), so that windows, pinned agents and chained sessions meet the
    faults. Drawn from a random source of its own: the other schedules stay those drawn before bursts existed."""
    rng = random.Random(f"alloc-bursts-{sc.seed}")
    if rng.random() >= 0.25:
        return
    sc.session_agents = rng.choice([3, 4, 6])
    t = rng.uniform(0.05, 1.2)
    n = rng.randint(8, 30)
    for _ in range(n):
        t += rng.uniform(0.0, 0.002)
        aid = f"a{next_agent}"
        next_agent += 1
        sc.faults.append(AFault(round(t, 4), "agent_add", aid, _agent_spec(rng, aid, live_agents, all_hosts)))
        live_agents.append(aid)
    sc.faults.sort(key=lambda f: f.at)
    total = len(sc.agents) + sum(1 for f in sc.faults if f.kind == "agent_add")
    # chained sessions: each may meet a slow OAC round (up to 0.6 s more, `AllocSim._propose`) at its start and
    # at its finish
    sc.liveness = LIVENESS_BOUND + 1.2 * -(-total // sc.session_agents)


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
