"""The agent table transactions an operator (or an agent) asks for, built and checked before they are proposed.

`haa.hostd.agentnode.AgentNode` takes operator requests (`haactl agent spawn|remove|move|pause`, the agents'
own `spawn_child` and `stop`, the measured costs of `AgentNode.report_costs`) and proposes them as `AgentTx`
transactions; this module builds those transactions. A request that cannot be valid is refused here with the
reason the table would give (`agenttable.check_create`), so an operator learns it at once instead of after an
OAC. Whether a valid-looking request takes effect is still decided by the table, identically on every member.

`AgentWrite` is the request key of the agent layer's own writes (`MembershipNode.submit(..., req)`): its
outcome comes back as a `WriteDone` carrying it.

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from haa.hostd import agenttable as at
from haa.pb import agenttx_pb2 as apb


@dataclass(frozen=True, slots=True)
class AgentWrite:
    """The request key of a write the agent layer proposed: its `kind` (the transaction, or "op"/"create" for
    an operator request), the `agent`, `arg` (an epoch, a session id, or the operator request's number) and the
    write's own number `n`."""

    kind: str
    agent: str
    arg: int
    n: int


def create(agent_id: str, type_name: str, config: bytes, parent: str, host: str, cost: float,
           hardware: Iterable[str], transfer_penalty: float, recovery: str, max_per_host: int) -> apb.AgentTx:
    tx = apb.AgentTx()
    c = tx.create
    c.id, c.type, c.config, c.parent = agent_id, type_name, config, parent
    c.max_per_host = max(0, min(int(max_per_host), 2**32 - 1))  # check_create refuses > MAX_PER_HOST
    c.cost, c.transfer_penalty, c.recovery, c.host = cost, transfer_penalty, recovery, host
    c.hardware.extend(sorted(set(hardware)))
    return tx


def create_refused(tx: apb.AgentTx) -> str:
    """Why the table would refuse this create ("" if it would not)."""
    return at.check_create(tx.create)


def remove(agent: str, host: str, epoch: int = 0) -> apb.AgentTx:
    """Remove `agent` (an operator's request; with `epoch`, the agent's own stop from that instance)."""
    tx = apb.AgentTx()
    tx.remove.id, tx.remove.host = agent, host
    if epoch:
        tx.remove.epoch = epoch
    return tx


def move(agent: str, host: str) -> apb.AgentTx:
    tx = apb.AgentTx()
    tx.move.id, tx.move.host = agent, host
    return tx


def pause(paused: bool) -> apb.AgentTx:
    tx = apb.AgentTx()
    tx.control.paused = paused
    return tx


def costs(table: at.AgentTable, host: str, cpu: Mapping[str, float],
          affinity: Mapping[tuple[str, str], float]) -> apb.AgentTx | None:
    """The significant changes of measured CPU (of agents `host` owns) and message rates between agent pairs
    (bytes/s) for the allocation (Alg. 4 ll. 22-23); None if nothing changed enough to be worth an OAC."""
    tx = apb.AgentTx()
    tx.costs.host = host
    changed = False
    for agent, c in sorted(cpu.items()):
        r = table.get(agent)
        if r is not None and r.owner == host and abs(r.cpu - c) > max(0.02, 0.2 * r.cpu):
            tx.costs.costs.add(id=agent, cpu=round(c, 4))
            changed = True
    for (a, b), rate in sorted(affinity.items()):
        key = (a, b) if a < b else (b, a)
        old = table.affinity.get(key, 0.0)
        if abs(old - rate) > max(100.0, 0.3 * old):
            tx.costs.affinity.add(a=key[0], b=key[1], rate=round(rate, 1))
            changed = True
    return tx if changed else None
