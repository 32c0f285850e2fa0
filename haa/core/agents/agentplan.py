"""The agent layer's decisions that need no state of their own: which machine an input goes to, and what the
table asks of this host for one agent.

`haa.core.agents.agentnode.AgentNode` composes the machines (`haa.core.agents.transfer.Transfer`,
`haa.core.agents.recovery.Recovery`, allocation glue, routing); what it does with an input is decided here, as pure
functions of the input, the agent table and the node's record of the instance:

* `reconcile` (thesis §4.8-4.9, run after every committed change): compare one agent's record in the
  replicated table with the instance this host runs — an agent it runs but is no longer allocated is frozen
  (Alg. 5), a frozen agent allocated to it is thawed (Alg. 6), a new or crashed agent allocated to it is
  recovered (Alg. 8), an agent it should run but does not is reported failed;
* `instance_input`: an event of a local instance (`haa.core.agentio`) as the input of the machine that owns
  the instance in its current phase;
* `applied_input`: a committed agent transaction as the input of the machine it concerns.

Both return the input addressed to its machine (`ToTransfer`, `ToRecovery`; `haa.core.agents.agentroute.Router` hands
the messages it holds and the acknowledgements on the same way): some inputs are of the same class for either
machine (`haa.core.agents.agentstep.Hold`, `ShellUp`, `Committed`), so the class cannot say where an input goes.

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from haa.core.agentio import BackupMade, Failed, Frozen, ShellReady
from haa.core.agents import recovery as rc
from haa.core.agents import transfer as tr
from haa.core.agents.agentstep import Committed, Local, ShellUp
from haa.core.ddb import agenttable as at
from haa.pb import agenttx_pb2 as apb


@dataclass(frozen=True, slots=True)
class ToTransfer:
    """Step the transfer machine (`haa.core.agents.transfer.Transfer`) with `inp`."""

    inp: tr.TransferInput


@dataclass(frozen=True, slots=True)
class ToRecovery:
    """Step the recovery machine (`haa.core.agents.recovery.Recovery`) with `inp`."""

    inp: rc.RecoveryInput


@dataclass(frozen=True, slots=True)
class FreezeLocal:
    """Freeze this host's running instance of `agent` (Alg. 5: another host won the bid for it, this host is
    leaving, or a per-host limit left it no place)."""

    agent: str


Action = tr.Thaw | rc.Recover | rc.ReportFailed | FreezeLocal


def reconcile(r: at.AgentRecord, loc: Local | None, me: str, draining: bool,
              members: Callable[[], Collection[str]], hosts: Mapping[str, apb.HostInfo]) -> Action | None:
    """What the table asks of host `me` for agent `r`, given its instance here (`loc`); `members` gives the
    member names (asked only when needed), `hosts` the table's host entries."""
    if loc is None:
        if r.owner == me and r.status in (at.ACTIVE, at.FREEZING):
            # the table says we run it but we do not (a restarted host, a lost instance): it failed
            return rc.ReportFailed(r.id, r.epoch, "not running on its owner")
        if r.alloc == me and not draining:
            if r.status == at.FROZEN:
                return tr.Thaw(r.id)
            if r.status == at.NEW or (r.status == at.CRASHED and r.spec.recovery != "none"):
                return rc.Recover(r.id)  # after a start-failure backoff, if any
        return None
    if loc.phase == "active" and r.owner == me and r.status == at.ACTIVE:
        target = r.alloc
        h = hosts.get(target)
        if draining or (target and target != me and target in members() and not (h and h.draining)):
            return FreezeLocal(r.id)  # Alg. 5: we lost the bid for a (or we are leaving, thesis AF-1)
        if not target and r.spec.max_per_host:
            # issue 15: an agent of a type with a per-host limit that the allocation found no place for
            # (agenttable._tx_finish cleared its allocation): frozen, its state kept until a place frees up
            return FreezeLocal(r.id)
    return None


def instance_input(loc: Local, ev: object, now: float, start_grace: float) -> ToTransfer | ToRecovery | None:
    """The machine input of an event of instance `loc` (the node checked its epoch); None: not a machine's."""
    phase = loc.phase
    if isinstance(ev, ShellReady):
        if phase in ("claiming", "thawing"):
            return ToTransfer(ShellUp(loc.id))
        return ToRecovery(ShellUp(loc.id)) if phase == "recovering" else None
    if isinstance(ev, BackupMade):  # Alg. 7 l. 3
        return ToRecovery(rc.Backup(loc.id, loc.epoch, ev.data)) if phase in ("active", "freezing") else None
    if isinstance(ev, Frozen):  # Alg. 5 l. 19
        return ToTransfer(tr.StateArrived(loc.id, ev.state)) if phase == "freezing" else None
    if isinstance(ev, Failed):
        # early: not up yet, or within its start grace (a start failure: counted, backed off)
        early = phase != "active" or loc.started < 0 or now - loc.started < start_grace
        if phase == "recovering":
            return ToRecovery(rc.ShellDied(loc.id, ev.reason))
        if phase == "active":
            return ToRecovery(rc.InstanceFailed(loc.id, loc.epoch, ev.reason, early))
        return ToTransfer(tr.ShellDied(loc.id, ev.reason, early))  # freezing, claiming, thawing
    return None


def applied_input(res: at.AgentApplied) -> ToTransfer | ToRecovery | None:
    """The machine input of a committed transfer or recovery transaction (None for the other kinds)."""
    if res.kind in ("freeze", "release", "claim"):
        return ToTransfer(Committed(res))
    if res.kind in ("recovered", "failed"):
        return ToRecovery(Committed(res))
    return None
