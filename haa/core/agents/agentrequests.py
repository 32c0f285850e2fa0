"""The agent table transactions an operator (or an agent) asks for, built and checked before they are proposed.

`haa.core.agents.agentnode.AgentNode` takes operator requests (`haactl agent spawn|remove|move|pause`, the agents'
own `spawn_child` and `stop`, the measured costs of a `ReportCosts` input) and proposes them as `AgentTx`
transactions; this module builds those transactions. A request that cannot be valid is refused here with the
reason the table would give (`agenttable.check_create`), so an operator learns it at once instead of after an
OAC. Whether a valid-looking request takes effect is still decided by the table, identically on every member.

`Operations` keeps the requests in flight and answers each when its write's outcome comes back.
`AgentWrite` is the request key of the agent layer's own writes (`MembershipNode.submit(..., req)`): its
outcome comes back as a `WriteDone` carrying it.

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Hashable, Iterable, Mapping
from dataclasses import dataclass

from haa.core.agentio import AgentOpDone, AnswerAgent
from haa.core.agents.agentstep import Propose
from haa.core.ddb import agenttable as at
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
           hardware: Iterable[str], transfer_penalty: float, recovery: str, max_per_host: int,
           key: str = "") -> apb.AgentTx:
    tx = apb.AgentTx()
    c = tx.create
    c.id, c.type, c.config, c.parent, c.key = agent_id, type_name, config, parent, key
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


OpEffect = AgentOpDone | AnswerAgent | Propose


class Operations:
    """The operator requests (and agents' child requests) in flight: each is proposed as a write of kind
    "create" or "op" carrying the request's number, and answered when its outcome comes back (`done`): an
    `AgentOpDone` for the operator (keyed by the caller's `req`), an `AnswerAgent` command for an agent that
    asked for a child (`req` ("child", parent, epoch, request id))."""

    def __init__(self, table: Callable[[], at.AgentTable]) -> None:
        self._table = table
        self._reqs: dict[int, Hashable] = {}
        self._n = 0

    def propose(self, tx: apb.AgentTx, req: Hashable, agent: str = "", kind: str = "op") -> list[OpEffect]:
        self._n += 1
        self._reqs[self._n] = req
        return [Propose(tx, kind, agent, self._n)]

    def create(self, tx: apb.AgentTx, req: Hashable) -> list[OpEffect]:
        why = create_refused(tx)
        if why:
            return [AgentOpDone(req, False, tx.create.id, "", why)]
        return self.propose(tx, req, tx.create.id, "create")

    def remove(self, ref: str, host: str, req: Hashable) -> list[OpEffect]:
        """The operator (through `host`) asks to remove agent `ref` (an id or a name)."""
        r = self._table().resolve(ref)
        if r is None:
            return self.refuse(req, ref, "unknown agent")
        return self.propose(remove(r.id, host), req, r.id)

    def move(self, ref: str, host: str, members: Collection[str], req: Hashable) -> list[OpEffect]:
        """The operator asks to move agent `ref` to `host`, a member (allocated there until the next session)."""
        r = self._table().resolve(ref)
        if r is None:
            return self.refuse(req, ref, "unknown agent")
        if host not in members:
            return self.refuse(req, r.id, f"{host} is not a member of the group")
        return self.propose(move(r.id, host), req, r.id)

    def refuse(self, req: Hashable, agent: str, reason: str) -> list[OpEffect]:
        r = self._table().get(agent) if agent else None
        return [AgentOpDone(req, False, agent, r.name if r else "", reason)]

    def done(self, n: int, agent: str, ok: bool, reason: str, result: object) -> list[OpEffect]:
        """The write of request `n` committed (`ok`; `result` what the table made of it) or was given up."""
        req = self._reqs.pop(n, None)
        if not ok:
            reason = reason or "not committed"
        elif isinstance(result, at.AgentApplied):  # committed and applied here (WriteDone follows the apply)
            ok, agent, reason = result.ok, result.agent or agent, result.reason
        else:
            return []
        if isinstance(req, tuple) and req and req[0] == "child":
            _, parent, epoch, rid = req
            return [AnswerAgent(parent, epoch, rid, ok, agent if ok else "", reason)]
        r = self._table().get(agent) if agent else None
        return [AgentOpDone(req, ok, agent, r.name if r else "", reason)]
