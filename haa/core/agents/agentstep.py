"""What the agent layer's machines share: the host's instance record, the read-only view, the common effects.

`haa.core.agents.agentnode.AgentNode` composes the machines of thesis Alg. 5-8 — `haa.core.agents.transfer.Transfer`
(freeze/thaw) and `haa.core.agents.recovery.Recovery` (backup, failures, recovery) — with routing, allocation and
the agent table. Each machine owns its state and is driven through one `step(now, input)` that returns
effects; this module holds the pieces they have in common:

* `AgentView`: what a machine may *read* of the host around it — its name, the replicated agent table, the
  member list, and whether every OAC this host knows of is decided (Alg. 6 l. 9). A machine never changes
  them; it asks for changes with effects. A test drives a machine with a small fake view.
* `Local`: the node's record of one agent instance it runs or prepares (`AgentNode.local`; the operator's
  `agent list`, the metrics and the simulator read its `phase`). The machines do not hold it: they tell the
  node what to record with `SetPhase`, `Activate` and `Forget`.
* the effects both machines emit (`Cmd`, `Propose`, `HostSend`, `Timeline`, `Note`, `Route`, `SetPhase`,
  `Activate`, `Forget`, `Reconcile`, `ArmTimer`), frozen dataclasses; each machine's effect union is a
  subset of them plus its own (`transfer.Lost`, `recovery.Recovered`...). `AgentNode` carries them out in
  the order they come, which is the order in which the code before the split performed them.
* the inputs both machines take (`Hold`, `ShellUp`, `Committed`); each machine's input union names them next
  to its own. Their class does not say which machine an input is for: whoever makes one says it
  (`haa.core.agents.agentplan.ToTransfer`, `ToRecovery`).
* `AgentTimer`: the typed timer keys of the agent layer. Printed as the tuples they replaced
  (`('a', 'backoff', '<agent>')`), so the simulator's trace hash is unchanged.

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

from haa.core.agentio import DeliverAgent, FreezeAgent, KillAgent, SpawnShell, StartAgent
from haa.core.agents.routing import Inbox, Outbox
from haa.core.ddb import agenttable as at
from haa.pb import agenttx_pb2 as apb

#: a shell that dies before its agent was started is replaced this many times, then the attempt is abandoned
MAX_RESPAWNS = 3

#: the instance phases (`Local.phase`): starting (Alg. 6 claiming/thawing, Alg. 8 recovering), running, freezing
STARTING = ("claiming", "thawing", "recovering")


class AgentView(Protocol):
    """The host state a machine reads (never writes): `AgentNode` is one."""

    @property
    def name(self) -> str: ...

    @property
    def table(self) -> at.AgentTable: ...

    def members(self) -> list[str]:
        """The names of the group's members, in member-list order."""
        ...

    def oacs_settled(self) -> bool:
        """Alg. 6 l. 9 / Alg. 8 l. 3: every OAC this host knows of is decided and delivered."""
        ...


@dataclass(slots=True)
class Local:
    """An agent instance this host runs or is preparing (the host side of its process), as the node sees it."""

    id: str
    epoch: int
    phase: str  # claiming, thawing (Alg. 6), recovering (Alg. 8), active, freezing (Alg. 5)
    inbox: Inbox | None = None  # set when it becomes active
    outbox: Outbox = field(default_factory=Outbox)
    life: int = 0
    started: float = -1.0  # when StartAgent was issued (the start grace counts from it); -1: not yet


@dataclass(frozen=True, slots=True)
class AgentTimer:
    """A timer of the agent layer: `poll` (Alg. 6 l. 9 re-checked), `retry` (writes given up), `rebalance`
    (the next allocation session due), `drain` (graceful leave deadline), `backoff` (of one `agent`)."""

    what: str
    agent: str = ""

    def __str__(self) -> str:  # the printed form of the tuple keys before (the simulator hashes it)
        return str(("a", self.what, self.agent) if self.agent else ("a", self.what))


# ----------------------------------------------------------------------------------------------- inputs


@dataclass(frozen=True, slots=True)
class Hold:
    """A message for `m.dst`, which this host is freezing, thawing or recovering: the transfer holds it (queue1,
    Alg. 5 l. 4; a thaw's local queue, Alg. 6 l. 3) or answers `transfer.PassOn`; the recovery holds it for the
    shell (its local queue)."""

    m: apb.RoutedMsg


@dataclass(frozen=True, slots=True)
class ShellUp:
    """The shell of a thaw (transfer) or of a recovery said hello."""

    agent: str


@dataclass(frozen=True, slots=True)
class Committed:
    """A transaction of the machine's was applied here (`res.kind`: OAC(freeze|release|claim) for the transfer,
    OAC(recovered|failed) for the recovery), by any host."""

    res: at.AgentApplied


# ----------------------------------------------------------------------------------------------- effects

Command = SpawnShell | StartAgent | FreezeAgent | KillAgent | DeliverAgent


@dataclass(frozen=True, slots=True)
class Cmd:
    """Give a command to whatever runs the instances (`haa.core.agentio`)."""

    cmd: Command


@dataclass(frozen=True, slots=True)
class Propose:
    """Commit `tx` to the agent table through OAC; its outcome comes back as a write of `kind` for
    (`agent`, `epoch`) (an `agentrequests.AgentWrite` request key)."""

    tx: apb.AgentTx
    kind: str
    agent: str
    epoch: int


@dataclass(frozen=True, slots=True)
class HostSend:
    """An `AgentHostMsg(kind, agent, epoch, data)` to another member (freeze_ack, claim_ack, alloc)."""

    host: str
    kind: str
    agent: str
    epoch: int
    data: bytes = b""


@dataclass(frozen=True, slots=True)
class Timeline:
    """One timeline event of `agent` at this host (`agentio.AgentTimeline`)."""

    agent: str
    event: str
    detail: str = ""


@dataclass(frozen=True, slots=True)
class Note:
    """A structured log event (`effects.Log`)."""

    event: str
    fields: dict[str, Any]


@dataclass(frozen=True, slots=True)
class Route:
    """Route these messages again, in order: the table now says where their agent is."""

    msgs: tuple[apb.RoutedMsg, ...]


@dataclass(frozen=True, slots=True)
class SetPhase:
    """Record instance (`agent`, `epoch`) in `phase` (a new record if the node has none)."""

    agent: str
    epoch: int
    phase: str


@dataclass(frozen=True, slots=True)
class Activate:
    """The instance was started (Alg. 6 l. 11, Alg. 8 l. 5): the node routes to it through `inbox` from now
    on, and stamps its messages with `outbox` and `life`."""

    agent: str
    epoch: int
    inbox: Inbox
    outbox: Outbox
    life: int


@dataclass(frozen=True, slots=True)
class Forget:
    """The node no longer runs or prepares an instance of `agent`."""

    agent: str


@dataclass(frozen=True, slots=True)
class Reconcile:
    """Compare `agent`'s table record with the instance here again (`AgentNode._reconcile_one`)."""

    agent: str


@dataclass(frozen=True, slots=True)
class ArmTimer:
    """Set the agent layer's timer `key` to fire at `at` (node-local time)."""

    key: AgentTimer
    at: float


def start_messages(inbox: Inbox, *queues: list[apb.RoutedMsg]) -> list[apb.RoutedMsg]:
    """The messages a starting instance gets with its StartAgent: the queues in order, through its inbox."""
    msgs: list[apb.RoutedMsg] = []
    for q in queues:
        for m in q:
            msgs += inbox.offer(m)
    return msgs


def spawn(r: at.AgentRecord, epoch: int) -> Cmd:
    """SpawnShell for `r` at `epoch` (Alg. 6 l. 2, Alg. 8 l. 2)."""
    return Cmd(SpawnShell(r.id, epoch, r.type, r.name, r.spec.config, r.parent))


class Retries:
    """The agent layer's writes to retry ("do ... while not committed", Alg. 4-8): a write that the membership
    node gave up (after its own re-proposals) or refused (not a member, group not formed) is handed back to its
    machine as not committed after `after` seconds — at once, a refusal would loop — all due ones together on
    one `AgentTimer("retry")`."""

    def __init__(self, after: float) -> None:
        self.after = after
        self._due: list[tuple[str, str, int]] = []
        self._armed = False

    def add(self, now: float, kind: str, agent: str, arg: int) -> list[ArmTimer]:
        self._due.append((kind, agent, arg))
        if self._armed:
            return []
        self._armed = True
        return [ArmTimer(AgentTimer("retry"), now + self.after)]

    def fire(self) -> list[tuple[str, str, int]]:
        """The retry timer fired: the writes to hand back, (kind, agent, arg) in the order they failed."""
        self._armed = False
        due, self._due = self._due, []
        return due
