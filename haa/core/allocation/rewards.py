"""The rewards of agent allocation (thesis §4.7, eq. 4.7-1 to 4.7-3): what a bundle of agents is worth to a host.

`transfer_factor` (eq. 4.7-2's 1 - t_i), `agent_reward` r(a_i) (eq. 4.7-2) and `bundle_reward` R(b_h) (eq. 4.7-1
with the over-capacity penalty of eq. 4.7-3). The bundle building of `haa.core.allocation.bundle` computes the
same sums incrementally; the simulator's quality study (`haa.lab.dsim.allocquality`) scores allocations with
these. Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Iterable

from haa.core.allocation.specs import AgentSpec, HostSpec


def transfer_factor(agent: AgentSpec, host: str) -> float:
    """eq. 4.7-2: 1 on the current host (a_i in L_h), (1 - t_i) elsewhere. An agent that runs nowhere (new,
    crashed, or frozen in a transfer) is transferred by no allocation: 1 everywhere. Read literally, eq. 4.7-2
    gave it 1 - t_i on every host, so the session that placed it ranked it below what the next session did
    once it ran (t_i = 1: reward 0, placed last, over capacity) and that session moved agents again
    (docs/allocation.md, "Joins and hysteresis")."""
    h = agent.current_host
    return 1.0 if h is None or h == host else 1.0 - agent.transfer_penalty


def agent_reward(agent: AgentSpec, host: str, bundle: Iterable[str]) -> float:
    """r(a_i), eq. 4.7-2: (c_i + sum of alpha_ij over a_j in the bundle) x the transfer factor."""
    aff = agent.affinity
    bonus = sum(aff.get(j, 0.0) for j in bundle if j != agent.id)
    return (agent.cost + bonus) * transfer_factor(agent, host)


def bundle_reward(order: list[AgentSpec], host: HostSpec) -> float:
    """R(b_h), eq. 4.7-1 for one bundle order: r(a_i) while the running cost stays below K_h, then the
    penalty s(a_i) = (K_h - running cost) / K_h (eq. 4.7-3)."""
    ids = [a.id for a in order]
    k = host.capacity
    total = 0.0
    used = 0.0
    for a in order:
        used += a.cost
        total += agent_reward(a, host.name, ids) if used < k else (k - used) / k
    return total
