"""Codec between the cores' message objects and the protobuf `haa.v1.Envelope` (proto/haa/pb/hostlink.proto).

The sans-I/O cores speak the dataclasses of `haa.core.messages`; the transport carries `Envelope`s.
`encode(sender, sender_inc, dst_inc, msg)` builds an Envelope and `decode(env)` gives back
`(sender, sender_inc, dst_inc, msg)`.

`decode` is the trust boundary of a host: everything a peer (or a process that stole the token) sends
passes through it before any core sees it, so it checks every field the cores rely on and raises
`WireError` (a `ValueError`) with a one-line reason otherwise — payload oneof not set, empty or oversized
names, zero incarnations, a missing `TxId`, negative or absurd rounds and orders, non-finite or
non-positive heartbeat periods, absurd clock readings, empty or duplicated participant lists. It does *not*
check protocol semantics (is the proposer a participant? is this round current?): the cores do that and count it.

Both directions are on the hot path (every heartbeat and every OAC step of every host), so each message type
has its own small encoder and decoder function, chosen through a dict keyed by type / oneof name; no
reflection over descriptors.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol

from haa.core.messages import (
    AGENT_HOST_KINDS,
    AgentHostMsg,
    Apply,
    Connections,
    Excluded,
    Heartbeat,
    Introduce,
    Leave,
    Locked,
    Message,
    OacAck,
    OacDecide,
    OacEstimate,
    OacOrder,
    OacProposal,
    OacTransaction,
    SeqWrite,
    SetPeriod,
    Sponsor,
    StateForward,
    StateRequest,
    StateSnapshot,
    TxId,
)
from haa.core.oac.oac import INITIAL_TS
from haa.pb import hostlink_pb2 as pb

#: longest host name accepted on the wire
MAX_NAME = 255
#: OAC rounds grow by one per failed coordinator; anything beyond this is garbage, not a slow cluster
MAX_ROUND = 2**32
#: OAC orders grow by one per transaction (at most); beyond this is garbage
MAX_ORDER = 2**62
#: heartbeat sequence numbers beyond this are garbage (one per millisecond for 146 million years)
MAX_HB_SEQ = 2**62
#: a heartbeat period above one hour is an attack, not a configuration
MAX_PERIOD = 3600.0
#: a local clock reading (seconds) beyond 31,000 years is garbage; one such value would also swamp the
#: observer's running sum of offset delays (haa.core.ufd.ufd) long after it left the window
MAX_CLOCK = 1e12
#: most participants an OAC transaction may name
MAX_PARTICIPANTS = 4096

Participants = tuple[tuple[str, int], ...]


class WireError(ValueError):
    """An envelope that does not decode into a well-formed core message."""


#: oneof field name of each message type (also the per-kind counter label)
KIND: dict[type, str] = {
    Heartbeat: "heartbeat",
    SetPeriod: "set_period",
    OacTransaction: "oac_transaction",
    OacOrder: "oac_order",
    OacEstimate: "oac_estimate",
    OacProposal: "oac_proposal",
    OacAck: "oac_ack",
    OacDecide: "oac_decide",
    Excluded: "excluded",
    Apply: "apply",
    Introduce: "introduce",
    Sponsor: "sponsor",
    Connections: "connections",
    Leave: "leave",
    Locked: "locked",
    StateSnapshot: "state_snapshot",
    StateForward: "state_forward",
    StateRequest: "state_request",
    SeqWrite: "seq_write",
    AgentHostMsg: "agent_host",
}
#: longest address, lock key or group id accepted on the wire
MAX_TEXT = 1024


# ----------------------------------------------------------------------------------------------- encode


def _set_txid(m: pb.TxId, t: TxId) -> None:
    m.host = t.host
    m.incarnation = t.inc
    m.seq = t.seq


def _set_parts(rep: Any, parts: Participants) -> None:
    add = rep.add  # a RepeatedCompositeFieldContainer[pb.Participant]
    for h, i in parts:
        add(host=h, incarnation=i)


# Fields are set in place on the Envelope's sub-message: with the upb backend this is 2-3x faster than
# building the sub-message and copying it in.


def _enc_heartbeat(env: pb.Envelope, m: Heartbeat) -> None:
    h = env.heartbeat
    h.seq = m.seq
    h.period = m.period
    h.sent_at = m.sent_at


def _enc_set_period(env: pb.Envelope, m: SetPeriod) -> None:
    env.set_period.period = m.period


def _enc_transaction(env: pb.Envelope, m: OacTransaction) -> None:
    t = env.oac_transaction
    _set_txid(t.id, m.id)
    t.payload = m.payload
    _set_parts(t.participants, m.participants)
    t.order = m.order


def _enc_order(env: pb.Envelope, m: OacOrder) -> None:
    t = env.oac_order
    _set_txid(t.id, m.id)
    t.order = m.order


def _enc_estimate(env: pb.Envelope, m: OacEstimate) -> None:
    t = env.oac_estimate
    _set_txid(t.id, m.id)
    t.order = m.order
    t.round = m.round
    t.precommit = m.precommit
    t.ts = m.ts


def _enc_proposal(env: pb.Envelope, m: OacProposal) -> None:
    t = env.oac_proposal
    _set_txid(t.id, m.id)
    t.order = m.order
    t.round = m.round
    t.precommit = m.precommit


def _enc_ack(env: pb.Envelope, m: OacAck) -> None:
    t = env.oac_ack
    _set_txid(t.id, m.id)
    t.order = m.order
    t.round = m.round
    t.ack = m.ack


def _enc_decide(env: pb.Envelope, m: OacDecide) -> None:
    t = env.oac_decide
    _set_txid(t.id, m.id)
    t.order = m.order
    t.round = m.round
    t.commit = m.commit
    _set_parts(t.participants, m.participants)
    t.delivered = m.delivered


def _enc_excluded(env: pb.Envelope, m: Excluded) -> None:
    env.excluded.incarnation = m.incarnation


# --- Alg. 3 (membership) ------------------------------------------------------------------------------


def _enc_apply(env: pb.Envelope, m: Apply) -> None:
    env.apply.addr = m.addr


def _enc_introduce(env: pb.Envelope, m: Introduce) -> None:
    t = env.introduce
    t.name = m.name
    t.incarnation = m.inc
    t.addr = m.addr
    t.group = m.group


def _enc_sponsor(env: pb.Envelope, m: Sponsor) -> None:
    env.sponsor.SetInParent()


def _enc_connections(env: pb.Envelope, m: Connections) -> None:
    env.connections.SetInParent()
    _set_parts(env.connections.peers, m.peers)


def _enc_leave(env: pb.Envelope, m: Leave) -> None:
    env.leave.SetInParent()


def _enc_locked(env: pb.Envelope, m: Locked) -> None:
    env.locked.key = m.key


def _enc_snapshot(env: pb.Envelope, m: StateSnapshot) -> None:
    t = env.state_snapshot
    t.seq = m.seq
    t.data = m.data
    if m.anchor is not None:
        _set_txid(t.anchor, m.anchor)
    if m.parts > 1:
        t.part, t.parts = m.part, m.parts
    t.anchor_seq = m.anchor_seq
    if m.lock_key and m.lock_by is not None:
        t.lock_key = m.lock_key
        t.lock_by, t.lock_by_incarnation = m.lock_by


def _enc_forward(env: pb.Envelope, m: StateForward) -> None:
    t = env.state_forward
    t.seq = m.seq
    _set_txid(t.txid, m.txid)
    t.payload = m.payload


def _enc_seq_write(env: pb.Envelope, m: SeqWrite) -> None:
    t = env.seq_write
    t.floor = m.floor
    add = t.writes.add
    costs = m.costs or (1,) * len(m.writes)
    for (cseq, payload), cost in zip(m.writes, costs, strict=True):
        add(cseq=cseq, payload=payload, cost=cost)


def _enc_state_request(env: pb.Envelope, m: StateRequest) -> None:
    _set_txid(env.state_request.txid, m.txid)


def _enc_agent_host(env: pb.Envelope, m: AgentHostMsg) -> None:
    a = env.agent_host
    a.kind = m.kind
    a.agent = m.agent
    a.epoch = m.epoch
    a.data = m.data


#: message type -> its encoder (each takes that type; the table is keyed by it, so the value type is loose)
_ENCODERS: dict[type, Callable[[pb.Envelope, Any], None]] = {
    Heartbeat: _enc_heartbeat,
    SetPeriod: _enc_set_period,
    OacTransaction: _enc_transaction,
    OacOrder: _enc_order,
    OacEstimate: _enc_estimate,
    OacProposal: _enc_proposal,
    OacAck: _enc_ack,
    OacDecide: _enc_decide,
    Excluded: _enc_excluded,
    Apply: _enc_apply,
    Introduce: _enc_introduce,
    Sponsor: _enc_sponsor,
    Connections: _enc_connections,
    Leave: _enc_leave,
    Locked: _enc_locked,
    StateSnapshot: _enc_snapshot,
    StateForward: _enc_forward,
    StateRequest: _enc_state_request,
    SeqWrite: _enc_seq_write,
    AgentHostMsg: _enc_agent_host,
}


def encode(sender: str, sender_inc: int, dst_inc: int, msg: Message) -> pb.Envelope:
    """Wrap `msg` from `sender` (incarnation `sender_inc`), addressed to incarnation `dst_inc`, in an Envelope."""
    enc = _ENCODERS.get(type(msg))
    if enc is None:
        raise TypeError(f"not a host message: {type(msg).__name__}")
    env = pb.Envelope(sender=sender, sender_incarnation=sender_inc, dest_incarnation=dst_inc)
    enc(env, msg)
    return env


# ----------------------------------------------------------------------------------------------- decode


def _name(s: str, what: str) -> str:
    if not s:
        raise WireError(f"{what}: empty host name")
    if len(s) > MAX_NAME:
        raise WireError(f"{what}: host name longer than {MAX_NAME}")
    return s


class _WithTxId(Protocol):
    """Any OAC message: it has an `id` field."""

    @property
    def id(self) -> pb.TxId: ...

    def HasField(self, field_name: str) -> bool: ...  # protobuf's method name


def _dec_txid(m: _WithTxId, kind: str, field: str = "id") -> TxId:
    """The TxId in `m.<field>` (every OAC message's `id`; the membership messages' `txid` / `anchor`)."""
    if not m.HasField(field):
        raise WireError(f"{kind}: missing TxId")
    t = getattr(m, field)
    host = _name(t.host, f"{kind}.{field}")
    if t.incarnation == 0:
        raise WireError(f"{kind}.{field}: incarnation 0")
    if t.seq == 0:
        raise WireError(f"{kind}.{field}: seq 0")
    return TxId(host, t.incarnation, t.seq)


def _dec_parts(rep: Iterable[pb.Participant], kind: str, lives: bool = False) -> Participants:
    """A participant list: distinct host names (OAC), or with `lives` distinct (host, incarnation) pairs — an
    applicant's connections may name an old and a new incarnation of a restarted host."""
    parts = []
    names: set[object] = set()
    for p in rep:
        h = p.host
        i = p.incarnation
        if not h or len(h) > MAX_NAME:
            _name(h, f"{kind}.participants")
        if i == 0:
            raise WireError(f"{kind}.participants: {h!r} has incarnation 0")
        names.add((h, i) if lives else h)
        parts.append((h, i))
    n = len(parts)
    if n == 0:
        raise WireError(f"{kind}: empty participant list")
    if n > MAX_PARTICIPANTS:
        raise WireError(f"{kind}: {n} participants (max {MAX_PARTICIPANTS})")
    if len(names) != n:
        raise WireError(f"{kind}: duplicate participants")
    return tuple(parts)


def _order(order: int, kind: str, low: int = 0) -> int:
    if order < low or order > MAX_ORDER:
        raise WireError(f"{kind}: order {order} out of range")
    return order


def _round(rnd: int, kind: str, low: int = 0) -> int:
    if rnd < low or rnd > MAX_ROUND:
        raise WireError(f"{kind}: round {rnd} out of range")
    return rnd


def _period(period: float, kind: str) -> float:
    # `not (x > 0)` is also true for NaN
    if not (period > 0.0) or period > MAX_PERIOD:
        raise WireError(f"{kind}: period {period!r} not in (0, {MAX_PERIOD}]")
    return period


def _dec_heartbeat(env: pb.Envelope) -> Heartbeat:
    m = env.heartbeat
    if m.seq > MAX_HB_SEQ:
        raise WireError(f"heartbeat: seq {m.seq} out of range")
    if not (abs(m.sent_at) <= MAX_CLOCK):  # also rejects NaN
        raise WireError(f"heartbeat: sent_at {m.sent_at!r} is not a clock reading")
    return Heartbeat(m.seq, _period(m.period, "heartbeat"), m.sent_at)


def _dec_set_period(env: pb.Envelope) -> SetPeriod:
    return SetPeriod(_period(env.set_period.period, "set_period"))


def _dec_transaction(env: pb.Envelope) -> OacTransaction:
    m = env.oac_transaction
    k = "oac_transaction"
    return OacTransaction(_dec_txid(m, k), m.payload, _dec_parts(m.participants, k), _order(m.order, k))


def _dec_order(env: pb.Envelope) -> OacOrder:
    m = env.oac_order
    return OacOrder(_dec_txid(m, "oac_order"), _order(m.order, "oac_order"))


def _dec_estimate(env: pb.Envelope) -> OacEstimate:
    m = env.oac_estimate
    k = "oac_estimate"
    if m.ts < INITIAL_TS or m.ts > MAX_ROUND:  # -1: no proposal adopted yet (haa.core.oac.oac.INITIAL_TS)
        raise WireError(f"{k}: ts {m.ts} out of range")
    return OacEstimate(_dec_txid(m, k), _order(m.order, k), _round(m.round, k), m.precommit, m.ts)


def _dec_proposal(env: pb.Envelope) -> OacProposal:
    m = env.oac_proposal
    k = "oac_proposal"
    return OacProposal(_dec_txid(m, k), _order(m.order, k), _round(m.round, k), m.precommit)


def _dec_ack(env: pb.Envelope) -> OacAck:
    m = env.oac_ack
    k = "oac_ack"
    return OacAck(_dec_txid(m, k), _order(m.order, k), _round(m.round, k), m.ack)


def _dec_decide(env: pb.Envelope) -> OacDecide:
    m = env.oac_decide
    k = "oac_decide"
    # an abort carries order -1 (Alg. 2 l. 29 / l. 71); a unilateral abort before any round carries round -1
    order = _order(m.order, k, low=0 if m.commit else -1)
    return OacDecide(
        _dec_txid(m, k), order, _round(m.round, k, low=-1), m.commit, _dec_parts(m.participants, k), m.delivered
    )


def _dec_excluded(env: pb.Envelope) -> Excluded:
    inc = env.excluded.incarnation
    if inc == 0:
        raise WireError("excluded: incarnation 0")
    return Excluded(inc)


def _text(v: str, what: str, empty_ok: bool = True) -> str:
    if not v and not empty_ok:
        raise WireError(f"{what}: empty")
    if len(v) > MAX_TEXT:
        raise WireError(f"{what}: longer than {MAX_TEXT}")
    return v


def _dec_apply(env: pb.Envelope) -> Apply:
    return Apply(_text(env.apply.addr, "apply.addr", empty_ok=False))


def _dec_introduce(env: pb.Envelope) -> Introduce:
    m = env.introduce
    if m.incarnation == 0:
        raise WireError("introduce: incarnation 0")
    return Introduce(
        _name(m.name, "introduce"), m.incarnation, _text(m.addr, "introduce.addr"), _text(m.group, "introduce.group")
    )


def _dec_sponsor(env: pb.Envelope) -> Sponsor:
    return Sponsor()


def _dec_connections(env: pb.Envelope) -> Connections:
    rep = env.connections.peers
    if len(rep) == 0:
        return Connections(())
    return Connections(_dec_parts(rep, "connections", lives=True))


def _dec_leave(env: pb.Envelope) -> Leave:
    return Leave()


def _dec_locked(env: pb.Envelope) -> Locked:
    return Locked(_text(env.locked.key, "locked.key", empty_ok=False))


def _dec_snapshot(env: pb.Envelope) -> StateSnapshot:
    m = env.state_snapshot
    anchor = _dec_txid(m, "state_snapshot", "anchor") if m.HasField("anchor") else None
    parts = max(1, m.parts)
    if m.part >= parts:
        raise WireError(f"state_snapshot.part: {m.part} of {parts} parts")
    lock_by = None
    if m.lock_key:
        if not m.lock_by or m.lock_by_incarnation == 0:
            raise WireError("state_snapshot.lock_by: a lock without the host and incarnation that took it")
        lock_by = (m.lock_by, m.lock_by_incarnation)
    return StateSnapshot(m.seq, m.data, anchor, m.anchor_seq, m.part, parts, m.lock_key, lock_by)


def _dec_forward(env: pb.Envelope) -> StateForward:
    m = env.state_forward
    if m.seq == 0:
        raise WireError("state_forward: seq 0")
    return StateForward(m.seq, _dec_txid(m, "state_forward", "txid"), m.payload)


def _dec_seq_write(env: pb.Envelope) -> SeqWrite:
    m = env.seq_write
    writes = tuple((w.cseq, w.payload) for w in m.writes)
    if not writes:
        raise WireError("seq_write: no writes")
    last = 0
    for cseq, _ in writes:
        if cseq <= last:  # numbered from 1, increasing: the origin's order
            raise WireError("seq_write: cseqs must be positive and increasing")
        last = cseq
    if m.floor > writes[0][0]:
        raise WireError("seq_write: floor above a write it carries")
    costs = tuple(w.cost or 1 for w in m.writes)  # (0: a sender that did not say; the least a write costs)
    return SeqWrite(m.floor, writes, costs if any(c != 1 for c in costs) else ())


def _dec_state_request(env: pb.Envelope) -> StateRequest:
    return StateRequest(_dec_txid(env.state_request, "state_request", "txid"))


def _dec_agent_host(env: pb.Envelope) -> AgentHostMsg:
    a = env.agent_host
    if a.kind not in AGENT_HOST_KINDS:
        raise WireError(f"agent_host: unknown kind {a.kind[:40]!r}")
    if len(a.agent) > 64:
        raise WireError("agent_host: agent id longer than 64 characters")
    return AgentHostMsg(a.kind, a.agent, a.epoch, a.data)


_DECODERS: dict[str, Callable[[pb.Envelope], Message]] = {
    "heartbeat": _dec_heartbeat,
    "set_period": _dec_set_period,
    "oac_transaction": _dec_transaction,
    "oac_order": _dec_order,
    "oac_estimate": _dec_estimate,
    "oac_proposal": _dec_proposal,
    "oac_ack": _dec_ack,
    "oac_decide": _dec_decide,
    "excluded": _dec_excluded,
    "apply": _dec_apply,
    "introduce": _dec_introduce,
    "sponsor": _dec_sponsor,
    "connections": _dec_connections,
    "leave": _dec_leave,
    "locked": _dec_locked,
    "state_snapshot": _dec_snapshot,
    "state_forward": _dec_forward,
    "state_request": _dec_state_request,
    "seq_write": _dec_seq_write,
    "agent_host": _dec_agent_host,
}


def payload_kind(env: pb.Envelope) -> str | None:
    """Name of the payload oneof field that is set (None if none is)."""
    kind: str | None = env.WhichOneof("payload")
    return kind


def decode(env: pb.Envelope) -> tuple[str, int, int, Message]:
    """Unwrap an Envelope into (sender, sender_inc, dst_inc, msg); raise `WireError` if it is malformed."""
    kind = env.WhichOneof("payload")
    if kind is None:
        raise WireError("envelope: payload not set")
    sender = _name(env.sender, "envelope.sender")
    if env.sender_incarnation == 0:
        raise WireError("envelope: sender incarnation 0")
    return sender, env.sender_incarnation, env.dest_incarnation, _DECODERS[kind](env)
