"""Host-to-host messages as plain Python objects, the language of the sans-I/O cores.

The cores never see protobuf: `haa.core.wire` converts these to and from the `haa.v1.Envelope` of
`proto/haa/pb/hostlink.proto`. The simulator passes them between cores without encoding (fast), and a
property test round-trips every type through the wire codec.

Names follow thesis Appendix II: Alg. 1 (`Heartbeat`, `SetPeriod`), Alg. 2 (the OAC messages) and Alg. 3 (the
membership messages), with the pseudo-code line that sends each.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple


class TxId(NamedTuple):
    """Globally unique, totally ordered transaction id (proposer host, incarnation, counter)."""

    host: str
    inc: int
    seq: int

    def __str__(self) -> str:
        return f"{self.host}.{self.inc}.{self.seq}"


# --- Alg. 1 -------------------------------------------------------------------------------------------


@dataclass(slots=True)
class Heartbeat:
    """m_l = {l, period, p_tau_l} (Alg. 1 l. 8)."""

    seq: int
    period: float
    sent_at: float


@dataclass(slots=True)
class SetPeriod:
    """setPeriod = {newPeriod} (Alg. 1 l. 27)."""

    period: float


# --- Alg. 2 -------------------------------------------------------------------------------------------


@dataclass(slots=True)
class OacTransaction:
    """(id, transaction, participants, order), Alg. 2 l. 5 (and the lazy relay, docs/oac.md).

    `participants` are (host, incarnation) pairs in coordinator-rotation order (l. 46)."""

    id: TxId
    payload: bytes
    participants: tuple[tuple[str, int], ...]
    order: int


@dataclass(slots=True)
class OacOrder:
    """(id, p, order_p): a new order proposal, Alg. 2 l. 24 / l. 79."""

    id: TxId
    order: int


@dataclass(slots=True)
class OacEstimate:
    """(id, p, order_p, r_p, est_p, ts_p): step P1, Alg. 2 l. 47."""

    id: TxId
    order: int
    round: int
    precommit: bool
    ts: int


@dataclass(slots=True)
class OacProposal:
    """(id, p, order_p, r_p, est_p): step C1, Alg. 2 l. 56."""

    id: TxId
    order: int
    round: int
    precommit: bool


@dataclass(slots=True)
class OacAck:
    """(id, p, order_p, r_p, ack|nack): step P2, Alg. 2 l. 61 / l. 63."""

    id: TxId
    order: int
    round: int
    ack: bool


@dataclass(slots=True)
class OacDecide:
    """(id, p, order, r, outcome, decide): Alg. 2 l. 29, 36, 69, 71; abort carries order -1.

    Carries the participant list so that a participant that never received the transaction itself can
    relay the decision and close it (docs/oac.md, "placeholders"). `delivered` says that the sender has
    passed l. 38 (delivered a commit, or decided abort); only such a message counts for the l. 41 closing
    gate (docs/oac.md, "the closing gate": without it AC-Total-Order fails)."""

    id: TxId
    order: int
    round: int
    commit: bool
    participants: tuple[tuple[str, int], ...]
    delivered: bool


@dataclass(slots=True)
class Excluded:
    """Tells a peer incarnation that it has been permanently suspected (docs/ufd.md, "exclusion")."""

    incarnation: int


# --- Alg. 3 (host membership) ------------------------------------------------------------------------


class Member(NamedTuple):
    """A host life in a member list: name, incarnation and the address its peers connect to."""

    name: str
    inc: int
    addr: str

    @property
    def proc(self) -> tuple[str, int]:
        return (self.name, self.inc)


@dataclass(slots=True)
class Apply:
    """(apply, a): Alg. 3 l. 39, sent by an applicant to every core process. `addr` is where `a` listens."""

    addr: str


@dataclass(slots=True)
class Introduce:
    """(introduce, a, q): Alg. 3 l. 55, 56, 68; q is the envelope's sender.

    `group` is the id of the correct group whose state the sender holds ("" if none): a host that formed a
    provisional group of one learns this way that a correct group already exists (docs/membership.md,
    "restarts")."""

    name: str
    inc: int
    addr: str
    group: str


@dataclass(slots=True)
class Sponsor:
    """(sponsor, q): Alg. 3 l. 59, 124, 175."""


@dataclass(slots=True)
class Connections:
    """(connections, q, connectionList): Alg. 3 l. 70, 73 (q's two-way connections)."""

    peers: tuple[tuple[str, int], ...]


@dataclass(slots=True)
class Leave:
    """(leave, q): Alg. 3 l. 15."""


@dataclass(slots=True)
class Locked:
    """(locked, key, q): Alg. 3 l. 130."""

    key: str


@dataclass(slots=True)
class StateSnapshot:
    """The global state (Alg. 3 l. 60, 125, 176) at sequence number `seq`; also the answer to a
    `StateRequest`, then with `anchor` = the requested transaction and `anchor_seq` its sequence number."""

    seq: int
    data: bytes
    anchor: TxId | None
    anchor_seq: int
    part: int = 0  # of `parts` slices of the state, in order on the link; parts <= 1: the whole state
    parts: int = 1
    #: an answer only: the lock of a membership change in progress the answering member holds (Alg. 3 l. 127)
    #: and who took it; the new member that installs this state skips the remove that locked it, so it takes
    #: the lock and acknowledges it from here (docs/membership.md, "State transfer")
    lock_key: str = ""
    lock_by: tuple[str, int] | None = None


@dataclass(slots=True)
class StateForward:
    """A forwarded global state change (Alg. 3 l. 61): the `seq`-th applied transaction."""

    seq: int
    txid: TxId
    payload: bytes


@dataclass(slots=True)
class StateRequest:
    """A new member that delivered `txid` but lacks the state before it asks a member for a snapshot
    (docs/membership.md, "state transfer")."""

    txid: TxId


@dataclass(slots=True)
class SeqWrite:
    """Global-state changes a member forwards to the sequencer (docs/oac.md, "The sequencer"): `writes` are
    (cseq, GroupTx payload) in the origin's order; every cseq below `floor` is settled at the origin. `costs`:
    each write's apply cost (its DDB ops; () = 1 each), what the sequencer bounds a transaction by."""

    floor: int
    writes: tuple[tuple[int, bytes], ...]
    costs: tuple[int, ...] = ()


# --- the agent layer (Alg. 4-8) ----------------------------------------------------------------------

AGENT_HOST_KINDS = ("msg", "freeze_ack", "claim_ack", "alloc", "alloc_run", "op_reply")


@dataclass(slots=True)
class AgentHostMsg:
    """Host-to-host message of the agent layer (`haa.core.agents.agentnode`): kind "msg" (a routed agent message,
    `data` = haa.v1.RoutedMsg), "freeze_ack" (Alg. 5 l. 24), "claim_ack" (Alg. 6 l. 16), "alloc" (a bid
    update of Alg. 4 l. 84, `data` encoded by `haa.core.allocation.allocwire`) or "alloc_run" (an operator asked a
    member that is not the leader for an allocation session: passed on to the leader) or "op_reply" (an
    agent's reply to an operator request, sent back to the host the operator asked; `data` = RoutedMsg)."""

    kind: str
    agent: str
    epoch: int
    data: bytes


GroupMessage = (
    Apply
    | Introduce
    | Sponsor
    | Connections
    | Leave
    | Locked
    | StateSnapshot
    | StateForward
    | StateRequest
    | SeqWrite
)
GROUP_TYPES: tuple[type, ...] = (
    Apply,
    Introduce,
    Sponsor,
    Connections,
    Leave,
    Locked,
    StateSnapshot,
    StateForward,
    StateRequest,
    SeqWrite,
)

OacMessage = OacTransaction | OacOrder | OacEstimate | OacProposal | OacAck | OacDecide
Message = Heartbeat | SetPeriod | OacMessage | Excluded | GroupMessage | AgentHostMsg
APP_TYPES: tuple[type, ...] = (AgentHostMsg,)

OAC_TYPES: tuple[type, ...] = (OacTransaction, OacOrder, OacEstimate, OacProposal, OacAck, OacDecide)
