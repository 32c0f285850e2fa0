"""Deterministic simulation of host joins and the allocation sessions they trigger (`haactl verify join`).

A chaos run or a mission showed agents moved to a host that had just joined and moved again about a second
later (`A3 freezing on h1 (to h5)`, then `A3 freezing on h5 (to h1)`): the join's session placed agents on the
joiner as if it had one core and no hardware (its `HostInfo` was not in the agent table yet), and the session
its `HostInfo` triggered `min_session_gap` later placed them on its real capacity. Every such second move
freezes the agent once more for nothing.

`draw_join(seed, hosts)` turns a seed into a quiet group — no fault, no operator move — that runs agents on
hosts of a drawn capacity K_h (the same on every host, as `haactl cluster up` and the mission runner give
them, or one per host), loaded to 30-160 % of the group's capacity, then sees one or two hosts join, a few
seconds apart. `JoinSim` runs it on `AgentNode`s (the whole agent layer, as `haa.lab.dsim.agents`) with the
daemon's rate limit between sessions (`AgentConfig.min_session_gap`, 1 s) and without periodic sessions, so
that a join and the sessions it causes are all that happens. `check_join` checks the agent layer's properties
(`haa.lab.dsim.agents.check_agents`) and:

* AA-Join-Stable: after a host joins, no agent is transferred twice before the next join (or the end). Nothing
  changes in between but the joiner's own `HostInfo`, so a second transfer undoes or redoes the first without
  any gain.

Statistics per seed: transfers after the joins, and how many of them went to the joiner.
"""

from __future__ import annotations

import dataclasses
import random
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from haa.core.agentio import AgentTimeline
from haa.core.agents.agentnode import AgentConfig, AgentNode
from haa.core.inputs import CreateAgent
from haa.core.membership.membership import ViewChange
from haa.lab.dsim.agents import SIM_AGENT, AgentScenario, AgentSim, check_agents, seed_fields
from haa.lab.dsim.cluster import SimHost
from haa.lab.dsim.group import GroupScenario, GroupViolation
from haa.lab.dsim.schedule import _delay_model

PROPS = frozenset({"AA-Join-Stable"})
#: the daemon's rate limit between sessions (AgentConfig's default); no periodic sessions
JOIN_AGENT = dataclasses.replace(SIM_AGENT, min_session_gap=AgentConfig().min_session_gap, rebalance_period=0.0)
#: capacities K_h drawn: `haactl cluster up --local` on 2 cores gives 2/N to each of N hosts
CAPACITIES = (0.25, 0.4, 0.5, 2 / 3, 1.0, 2.0)
#: the first join comes this long after the agents were created (the initial placement has settled)
FIRST_JOIN_AFTER = 3.0
#: and a second one this long after the first
JOIN_GAP = 4.0


@dataclass
class JoinScenario:
    agents: AgentScenario
    capacity: dict[str, float]
    costs: list[float]
    penalties: list[float]
    joiners: list[str] = field(default_factory=list)

    def describe(self) -> list[str]:
        g = self.agents.group
        out = [
            f"seed={g.seed} hosts={g.names} core={g.core} delay={g.delay.describe()}",
            "capacity: " + " ".join(f"{n}={self.capacity[n]:.3g}" for n in g.names),
            f"agents={self.agents.n_agents} created at {self.agents.create_at:.2f}: load "
            f"{sum(self.costs):.3g} on initial capacity "
            f"{sum(self.capacity[n] for n in g.names if n not in self.joiners):.3g}",
            "costs: " + " ".join(f"{c:.3g}" for c in self.costs),
            "transfer penalties: " + " ".join(f"{p:.3g}" for p in self.penalties),
        ]
        out += [f"t={g.starts[n]:.3f} {n} starts and joins" for n in self.joiners]
        return out


def draw_join(seed: int, hosts: int = 7) -> JoinScenario:
    rng = random.Random(seed * 7727 + 29)
    n_joiners = rng.choice((1, 1, 2))
    n = rng.randint(2 + n_joiners, max(2 + n_joiners, hosts))
    names = [f"h{i + 1}" for i in range(n)]
    first = n - n_joiners
    c = 3 if first >= 3 and rng.random() < 0.75 else 1
    core = names[:c]
    starts = {nm: rng.uniform(0.0, 0.3) for nm in names}
    create_at = rng.uniform(1.5, 2.0)
    joiners = names[first:]
    for k, nm in enumerate(joiners):
        starts[nm] = create_at + FIRST_JOIN_AFTER + k * JOIN_GAP + rng.uniform(0.0, 0.5)
    g = GroupScenario(
        seed, names, core, (c - 1) // 2, _delay_model(rng), [rng.uniform(-1000, 1000) for _ in names],
        [rng.uniform(-1e-4, 1e-4) for _ in names], starts, {},
    )
    g.fault_end = max(starts.values()) + 4.0
    g.deadline = g.fault_end + 30.0
    if rng.random() < 0.7:
        k = rng.choice(CAPACITIES)
        capacity = dict.fromkeys(names, k)
    else:
        capacity = {nm: rng.choice(CAPACITIES) for nm in names}
    n_agents = rng.randint(3, 14)
    load = rng.uniform(0.3, 1.6) * sum(capacity[nm] for nm in names[:first])
    weights = [rng.uniform(0.2, 1.0) for _ in range(n_agents)]
    costs = [round(load * w / sum(weights), 4) for w in weights]
    # most agent types declare no transfer penalty (haa.sdk.base); a few 0.5 (SLAM, avatars) or 1.0
    penalties = [rng.choice((0.0, 0.0, 0.0, 0.1, 0.5, 1.0)) for _ in range(n_agents)]
    sc = AgentScenario(g, "transfer", n_agents, create_at)
    sc.sends_end = g.fault_end
    return JoinScenario(sc, capacity, costs, penalties, joiners)


class JoinSim(AgentSim):
    """`AgentSim` with per-host capacities, the drawn costs and penalties, and the moves recorded."""

    def __init__(self, js: JoinScenario, trace: bool = False) -> None:
        super().__init__(js.agents, trace)
        self.js = js
        #: (time, agent name, from host, to host) of every transfer begun (a "freezing" timeline event)
        self.transfers: list[tuple[float, str, str, str]] = []
        #: joiner -> the time the first member installed a view with it
        self.joined_at: dict[str, float] = {}

    def _make_node(self, h: SimHost, inc: int) -> AgentNode:  # type: ignore[override]
        node = super(AgentSim, self)._make_node(h, inc)
        cfg = dataclasses.replace(JOIN_AGENT, capacity=self.js.capacity[h.name])
        return AgentNode(node, cfg)

    def _create_agent(self, node: AgentNode, now: float, i: int, agent: str) -> None:
        """A counter of the drawn cost and transfer penalty."""
        node.step(now, CreateAgent(agent, "counter", b"", cost=self.js.costs[i], transfer_penalty=self.js.penalties[i],
                                   recovery="backup", req=("create", i)))

    def _on_effect(self, h: SimHost, e: Any) -> None:
        t = type(e)
        if t is AgentTimeline and e.event == "freezing":
            dst = e.detail.removeprefix("to ") if e.detail.startswith("to ") else "?"
            self.transfers.append((self.cl.now, e.name, h.name, dst))
        elif t is ViewChange:
            for m in e.added:
                if m.name in self.js.joiners and m.name != h.name:
                    self.joined_at.setdefault(m.name, self.cl.now)
        super()._on_effect(h, e)


def check_join(sim: JoinSim) -> list[GroupViolation]:
    out = check_agents(sim)
    for joiner, t0, t1, moves in join_windows(sim):
        per_agent: dict[str, list[tuple[float, str, str, str]]] = defaultdict(list)
        for mv in moves:
            per_agent[mv[1]].append(mv)
        for agent, mvs in per_agent.items():
            if len(mvs) > 1:
                path = ", ".join(f"{a}->{b} at {t:.2f}" for t, _n, a, b in mvs)
                out.append(GroupViolation(
                    "AA-Join-Stable",
                    f"{agent} transferred {len(mvs)} times after {joiner} joined at {t0:.2f} (until {t1:.2f}, "
                    f"nothing else changed): {path}",
                    sorted({h for _t, _n, a, b in mvs for h in (a, b) if h != "?"}),
                ))
    return out


def join_windows(sim: JoinSim) -> list[tuple[str, float, float, list[tuple[float, str, str, str]]]]:
    """Per join: (joiner, from the view that added it, until the next join or the end, transfers in it)."""
    joins = sorted((t, nm) for nm, t in sim.joined_at.items())
    out = []
    for k, (t0, nm) in enumerate(joins):
        t1 = joins[k + 1][0] if k + 1 < len(joins) else sim.cl.now
        out.append((nm, t0, t1, [mv for mv in sim.transfers if t0 <= mv[0] < t1]))
    return out


def run_join(seed: int, hosts: int = 7, trace: bool = False) -> tuple[JoinSim, list[GroupViolation]]:
    sim = JoinSim(draw_join(seed, hosts), trace)
    sim.run()
    return sim, check_join(sim)


# ------------------------------------------------------------------------------------------------ the verifier


def seed_result(seed: int, hosts: int) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed (`haactl verify join`)."""
    sim, vs = run_join(seed, hosts)
    windows = join_windows(sim)
    after = [mv for _j, _t0, _t1, mvs in windows for mv in mvs]
    to_joiner = sum(1 for j, _t0, _t1, mvs in windows for mv in mvs if mv[3] == j)
    return seed_fields(seed, sim, vs, {
        "joins": float(len(windows)),
        "transfers_after_joins": float(len(after)),
        "transfers_to_joiners": float(to_joiner),
        "agents_moved_twice": float(sum(1 for v in vs if v.prop == "AA-Join-Stable")),
    }, sim.js.describe())


def full_trace(seed: int, hosts: int) -> list[str]:
    sim, vs = run_join(seed, hosts, trace=True)
    out = [f"# {ln}" for ln in sim.js.describe()]
    out += [ln for ln in sim.cl.trace or [] if not any(k in ln for k in ("Heartbeat(", "SetPeriod("))]
    out += [f"# {v}" for v in vs]
    out.append(f"# trace hash {sim.cl.trace_hash()}")
    return out


def trace_excerpt(seed: int, hosts: int, bad_hosts: list[str], lines: int = 40) -> list[str]:
    """Scenario, the joins and every transfer after them."""
    sim, _vs = run_join(seed, hosts, trace=True)
    out = [f"  scenario: {ln}" for ln in sim.js.describe()]
    picked = [ln for ln in sim.cl.trace or [] if " view " in ln or "freezing" in ln or "allocation_session" in ln]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    return out + [f"  {ln}" for ln in picked]
