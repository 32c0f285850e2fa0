"""The allocation quality study (AP-3's quality table; docs/allocation.md): how close Alg. 4 gets to the optimum.

`quality_instance` draws a small instance (`roomy` or `tight` capacities, `REGIMES`), `AllocSim` runs it to its
first committed allocation, and `optimum` finds the exhaustive optimum of eq. 4.7-1 on it (`host_reward`: the
best bundle order of one host, `total_reward`: the sum); `run_quality` compares the two (`QualityResult`).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

from haa.core.allocation.rewards import agent_reward
from haa.core.allocation.specs import AgentSpec, HostSpec
from haa.lab.dsim.allocschedule import AllocScenario, _delay_model
from haa.lab.dsim.allocsim import AllocSim

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
