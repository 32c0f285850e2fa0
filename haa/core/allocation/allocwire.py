"""Bytes on the wire for agent allocation (proto/haa/pb/alloc.proto <-> haa.core.allocation objects).

* `encode_update` / `decode_update`: the `BidUpdate` hosts send each other during a session (Alg. 4 l. 84);
* `encode_start` / `decode_start`: the `SessionStart` payload of OAC(start) (l. 26);
* `encode_finish` / `decode_finish`: the `SessionFinish` payload of OAC(finish) (l. 90).

Decoding never trusts the bytes: anything malformed (not protobuf, a missing name, a NaN cost, a penalty
outside [0, 1], a duplicate agent, a leader that is not group[0], ...) raises `AllocWireError`, a ValueError
whose one-line message names the message, the field and the reason. Encodings are deterministic (repeated
fields, no maps), so equal objects give equal bytes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from google.protobuf.message import DecodeError

from haa.core.allocation.allocation import ProposeFinish
from haa.core.allocation.bids import Bid, BidUpdate
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart
from haa.pb import alloc_pb2 as apb


class AllocWireError(ValueError):
    """Malformed allocation bytes (the message names the field and the reason)."""


@dataclass(frozen=True)
class SessionFinish:
    """The payload of OAC(finish): the leader, the session and the agreed allocation (agent -> host)."""

    leader: str
    ses_id: int
    allocation: tuple[tuple[str, str], ...]
    unallocatable: tuple[str, ...] = ()

    @classmethod
    def of(cls, p: ProposeFinish) -> SessionFinish:
        return cls(p.leader, p.ses_id, tuple(p.allocation.items()), tuple(p.unallocatable))

    def as_dict(self) -> dict[str, str]:
        return dict(self.allocation)


def _parse(kind: type, data: bytes, what: str) -> object:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise AllocWireError(f"{what}: expected bytes, got {type(data).__name__}")
    m = kind()
    try:
        m.ParseFromString(bytes(data))
    except DecodeError as e:
        raise AllocWireError(f"{what}: not a valid protobuf message ({e})") from None
    return m


def _need(s: str, what: str) -> str:
    if not s:
        raise AllocWireError(f"{what}: must not be empty")
    return s


# --------------------------------------------------------------------------------------------- bid updates


def encode_update(upd: BidUpdate, sender: str | None = None) -> bytes:
    m = apb.AllocBidUpdate(sender=sender if sender is not None else upd.sender, ses_id=upd.ses_id)
    for b in upd.bids:
        m.bids.add(agent=b.agent, winner=b.winner or "", reward=b.reward, support=b.support, round=b.round)
    encoded: bytes = m.SerializeToString()
    return encoded


def decode_update(data: bytes) -> BidUpdate:
    m = _parse(apb.AllocBidUpdate, data, "AllocBidUpdate")
    assert isinstance(m, apb.AllocBidUpdate)
    if m.ses_id < 1:
        raise AllocWireError("AllocBidUpdate.ses_id: must be >= 1")
    bids = []
    for n, b in enumerate(m.bids):
        w = f"AllocBidUpdate.bids[{n}]"
        _need(b.agent, f"{w}.agent")
        if b.winner:
            if not (math.isfinite(b.reward) and math.isfinite(b.support)):
                raise AllocWireError(f"{w}: reward and support must be finite for a bid with a winner")
            bids.append(Bid(b.agent, b.winner, b.reward, b.support, b.round))
        else:
            if math.isnan(b.reward) or math.isnan(b.support):
                raise AllocWireError(f"{w}: NaN in a nil bid")
            bids.append(Bid(b.agent, None, 0.0, -math.inf, b.round))
    return BidUpdate(m.ses_id, tuple(bids), m.sender)


# --------------------------------------------------------------------------------------------- start


def encode_start(st: SessionStart) -> bytes:
    m = apb.AllocStart(leader=st.leader, ses_id=st.ses_id, group=list(st.group))
    for a in st.agents:
        pa = m.agents.add(
            id=a.id,
            cost=a.cost,
            hardware=sorted(a.hardware),
            transfer_penalty=a.transfer_penalty,
            current_host=a.current_host or "",
            kind=a.kind,
            max_per_host=a.max_per_host,
            placed=a.placed or "",
        )
        for k, v in a.affinity.items():
            pa.affinity.add(agent=k, alpha=v)
    for h in st.hosts:
        m.hosts.add(name=h.name, capacity=h.capacity, hardware=sorted(h.hardware), draining=h.draining)
    if st.auction is not None:
        m.has_auction = True
        m.auction.extend(st.auction)
    encoded: bytes = m.SerializeToString()
    return encoded


def decode_start(data: bytes) -> SessionStart:
    m = _parse(apb.AllocStart, data, "AllocStart")
    assert isinstance(m, apb.AllocStart)
    agents = []
    for n, a in enumerate(m.agents):
        w = f"AllocStart.agents[{n}]"
        aff: dict[str, float] = {}
        for x in a.affinity:
            if x.agent in aff:
                raise AllocWireError(f"{w}.affinity: duplicate agent {x.agent!r}")
            aff[x.agent] = x.alpha
        try:
            agents.append(
                AgentSpec(
                    a.id,
                    a.cost,
                    frozenset(a.hardware),
                    aff,
                    a.transfer_penalty,
                    a.current_host or None,
                    a.kind,
                    a.max_per_host,
                    a.placed or None,
                )
            )
        except ValueError as e:
            raise AllocWireError(f"{w}: {e}") from None
    hosts = []
    for n, h in enumerate(m.hosts):
        try:
            hosts.append(HostSpec(h.name, h.capacity, frozenset(h.hardware), h.draining))
        except ValueError as e:
            raise AllocWireError(f"AllocStart.hosts[{n}]: {e}") from None
    try:
        auction = tuple(m.auction) if m.has_auction else None
        if not m.has_auction and m.auction:
            raise ValueError("auction given without has_auction")
        return SessionStart(m.leader, m.ses_id, tuple(m.group), tuple(agents), tuple(hosts), auction)
    except ValueError as e:
        raise AllocWireError(f"AllocStart: {e}") from None


# --------------------------------------------------------------------------------------------- finish


def encode_finish(fin: SessionFinish | ProposeFinish) -> bytes:
    f = SessionFinish.of(fin) if isinstance(fin, ProposeFinish) else fin
    m = apb.AllocFinish(leader=f.leader, ses_id=f.ses_id, unallocatable=list(f.unallocatable))
    for agent, host in f.allocation:
        m.allocation.add(agent=agent, host=host)
    encoded: bytes = m.SerializeToString()
    return encoded


def decode_finish(data: bytes) -> SessionFinish:
    m = _parse(apb.AllocFinish, data, "AllocFinish")
    assert isinstance(m, apb.AllocFinish)
    _need(m.leader, "AllocFinish.leader")
    if m.ses_id < 1:
        raise AllocWireError("AllocFinish.ses_id: must be >= 1")
    seen: dict[str, str] = {}
    for n, p in enumerate(m.allocation):
        _need(p.agent, f"AllocFinish.allocation[{n}].agent")
        _need(p.host, f"AllocFinish.allocation[{n}].host")
        if p.agent in seen:
            raise AllocWireError(f"AllocFinish.allocation[{n}]: agent {p.agent!r} allocated twice")
        seen[p.agent] = p.host
    for n, u in enumerate(m.unallocatable):
        _need(u, f"AllocFinish.unallocatable[{n}]")
        if u in seen:
            raise AllocWireError(f"AllocFinish.unallocatable[{n}]: agent {u!r} is also allocated")
    return SessionFinish(m.leader, m.ses_id, tuple(seen.items()), tuple(m.unallocatable))


def finish_of(ses_id: int, leader: str, allocation: Mapping[str, str], unallocatable: tuple[str, ...] = ()) -> bytes:
    """Shortcut: the OAC(finish) payload for a `ProposeFinish`'s fields."""
    return encode_finish(SessionFinish(leader, ses_id, tuple(allocation.items()), unallocatable))
