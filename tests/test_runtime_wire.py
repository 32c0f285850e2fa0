"""The wire codec (haa.core.wire): every message type round-trips, every malformed envelope is rejected."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haa.core import messages as m
from haa.core import wire
from haa.hostd.transport import encode_frame, envelope_chunk
from haa.pb import hostlink_pb2 as pb

names = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789-_.", min_size=1, max_size=24)
incs = st.integers(min_value=1, max_value=2**64 - 1)
txids = st.builds(m.TxId, names, incs, st.integers(min_value=1, max_value=2**64 - 1))
orders = st.integers(min_value=0, max_value=wire.MAX_ORDER)
rounds = st.integers(min_value=0, max_value=wire.MAX_ROUND)
periods = st.floats(min_value=1e-9, max_value=wire.MAX_PERIOD, allow_nan=False, allow_infinity=False)
clock = st.floats(min_value=-wire.MAX_CLOCK, max_value=wire.MAX_CLOCK, allow_nan=False)


@st.composite
def participants(draw: st.DrawFn) -> tuple[tuple[str, int], ...]:
    hosts = draw(st.lists(names, min_size=1, max_size=8, unique=True))
    return tuple((h, draw(incs)) for h in hosts)


@st.composite
def decides(draw: st.DrawFn) -> m.OacDecide:
    commit = draw(st.booleans())
    order = draw(orders) if commit else -1
    rnd = draw(st.integers(min_value=-1, max_value=wire.MAX_ROUND))
    return m.OacDecide(draw(txids), order, rnd, commit, draw(participants()), draw(st.booleans()))


messages = st.one_of(
    st.builds(m.Heartbeat, st.integers(min_value=0, max_value=wire.MAX_HB_SEQ), periods, clock),
    st.builds(m.SetPeriod, periods),
    st.builds(m.OacTransaction, txids, st.binary(max_size=64), participants(), orders),
    st.builds(m.OacOrder, txids, orders),
    st.builds(m.OacEstimate, txids, orders, rounds, st.booleans(), st.integers(min_value=-1, max_value=wire.MAX_ROUND)),
    st.builds(m.OacProposal, txids, orders, rounds, st.booleans()),
    st.builds(m.OacAck, txids, orders, rounds, st.booleans()),
    decides(),
    st.builds(m.Excluded, incs),
    st.builds(
        m.AgentHostMsg,
        st.sampled_from(m.AGENT_HOST_KINDS),
        st.text(max_size=64),
        st.integers(min_value=0, max_value=2**64 - 1),
        st.binary(max_size=64),
    ),
)


def test_every_message_type_has_a_wire_kind() -> None:
    union = set(m.Message.__args__)  # type: ignore[attr-defined]
    assert set(wire.KIND) == union
    oneof = {f.name for f in pb.Envelope.DESCRIPTOR.oneofs_by_name["payload"].fields}
    assert set(wire.KIND.values()) == oneof


@settings(max_examples=300, deadline=None)
@given(sender=names, sender_inc=incs, dst_inc=st.integers(min_value=0, max_value=2**64 - 1), msg=messages)
def test_round_trip(sender: str, sender_inc: int, dst_inc: int, msg: m.Message) -> None:
    env = wire.encode(sender, sender_inc, dst_inc, msg)
    assert wire.payload_kind(env) == wire.KIND[type(msg)]
    back = pb.Envelope.FromString(env.SerializeToString())
    s, si, di, got = wire.decode(back)
    assert (s, si, di) == (sender, sender_inc, dst_inc)
    assert type(got) is type(msg)
    assert got == msg


@settings(max_examples=50, deadline=None)
@given(first=st.integers(min_value=1, max_value=2**64 - 1), msgs=st.lists(messages, max_size=6))
def test_hand_built_frame_is_a_valid_protobuf_frame(first: int, msgs: list[m.Message]) -> None:
    envs = [wire.encode("a", 1, 2, x) for x in msgs]
    data = encode_frame(first, [envelope_chunk(e.SerializeToString()) for e in envs])
    frame = pb.Frame.FromString(data)
    assert frame.first_seq == first
    assert list(frame.envelopes) == envs
    assert data == pb.Frame(first_seq=first, envelopes=envs).SerializeToString()


def test_encode_rejects_non_messages() -> None:
    with pytest.raises(TypeError):
        wire.encode("a", 1, 0, "hello")  # type: ignore[arg-type]


T = m.TxId("h1", 5, 1)
P3 = (("h1", 5), ("h2", 6), ("h3", 7))


def env_of(msg: m.Message, sender: str = "h1", inc: int = 5) -> pb.Envelope:
    return wire.encode(sender, inc, 0, msg)


def mutate(msg: m.Message, fn: Callable[[pb.Envelope], None]) -> pb.Envelope:
    env = env_of(msg)
    fn(env)
    return env


def _raw_hb(seq: int = 1, period: float = 0.1, sent_at: float = 1.0) -> pb.Envelope:
    env = pb.Envelope(sender="h1", sender_incarnation=5)
    h = env.heartbeat
    h.seq, h.period, h.sent_at = seq, period, sent_at
    return env


MALFORMED: list[tuple[str, Callable[[], pb.Envelope], str]] = [
    ("no payload", lambda: pb.Envelope(sender="h1", sender_incarnation=5), "payload not set"),
    ("empty sender", lambda: env_of(m.Excluded(3), sender=""), "empty host name"),
    ("long sender", lambda: env_of(m.Excluded(3), sender="x" * 300), "longer than"),
    ("sender inc 0", lambda: env_of(m.Excluded(3), inc=0), "sender incarnation 0"),
    ("hb nan period", lambda: _raw_hb(period=math.nan), "period"),
    ("hb inf period", lambda: _raw_hb(period=math.inf), "period"),
    ("hb zero period", lambda: _raw_hb(period=0.0), "period"),
    ("hb negative period", lambda: _raw_hb(period=-1.0), "period"),
    ("hb absurd period", lambda: _raw_hb(period=1e9), "period"),
    ("hb inf sent_at", lambda: _raw_hb(sent_at=math.inf), "sent_at"),
    ("hb nan sent_at", lambda: _raw_hb(sent_at=math.nan), "sent_at"),
    ("hb absurd sent_at", lambda: _raw_hb(sent_at=-1e300), "sent_at"),
    ("hb absurd seq", lambda: _raw_hb(seq=2**63), "seq"),
    ("set_period nan", lambda: mutate(m.SetPeriod(1.0), lambda e: setattr(e.set_period, "period", math.nan)), "period"),
    ("set_period 0", lambda: mutate(m.SetPeriod(1.0), lambda e: setattr(e.set_period, "period", 0.0)), "period"),
    ("missing txid", lambda: mutate(m.OacOrder(T, 3), lambda e: e.oac_order.ClearField("id")), "missing TxId"),
    ("txid empty host", lambda: mutate(m.OacOrder(T, 3), lambda e: setattr(e.oac_order.id, "host", "")), "empty"),
    ("txid inc 0", lambda: mutate(m.OacOrder(T, 3), lambda e: setattr(e.oac_order.id, "incarnation", 0)), "inc"),
    ("txid seq 0", lambda: mutate(m.OacOrder(T, 3), lambda e: setattr(e.oac_order.id, "seq", 0)), "seq 0"),
    ("negative order", lambda: env_of(m.OacOrder(T, -5)), "order -5"),
    ("absurd order", lambda: env_of(m.OacOrder(T, 2**63 - 1)), "order"),
    ("estimate negative round", lambda: env_of(m.OacEstimate(T, 1, -1, False, 0)), "round -1"),
    ("estimate absurd round", lambda: env_of(m.OacEstimate(T, 1, 2**40, False, 0)), "round"),
    ("estimate ts below the initial -1", lambda: env_of(m.OacEstimate(T, 1, 0, False, -3)), "ts -3"),
    ("proposal negative round", lambda: env_of(m.OacProposal(T, 1, -2, True)), "round -2"),
    ("ack negative round", lambda: env_of(m.OacAck(T, 1, -1, True)), "round -1"),
    ("decide round -2", lambda: env_of(m.OacDecide(T, -1, -2, False, P3, True)), "round -2"),
    ("commit with order -1", lambda: env_of(m.OacDecide(T, -1, 0, True, P3, False)), "order -1"),
    ("abort order -2", lambda: env_of(m.OacDecide(T, -2, 0, False, P3, True)), "order -2"),
    ("tx empty participants", lambda: env_of(m.OacTransaction(T, b"x", (), 1)), "empty participant list"),
    ("decide empty participants", lambda: env_of(m.OacDecide(T, 1, 0, True, (), False)), "empty participant list"),
    ("tx duplicate participants", lambda: env_of(m.OacTransaction(T, b"", (("h1", 5), ("h1", 6)), 1)), "duplicate"),
    ("decide duplicate participants", lambda: env_of(m.OacDecide(T, 1, 0, True, (("h2", 1),) * 2, False)), "duplicate"),
    ("participant inc 0", lambda: env_of(m.OacTransaction(T, b"", (("h1", 5), ("h2", 0)), 1)), "incarnation 0"),
    ("participant no name", lambda: env_of(m.OacTransaction(T, b"", (("h1", 5), ("", 2)), 1)), "empty host name"),
    (
        "too many participants",
        lambda: env_of(
            m.OacDecide(T, 1, 0, True, tuple((f"h{i}", 1) for i in range(wire.MAX_PARTICIPANTS + 1)), False)
        ),
        "participants (max",
    ),
    ("excluded inc 0", lambda: env_of(m.Excluded(0)), "incarnation 0"),
]


@pytest.mark.parametrize(("case", "build", "reason"), MALFORMED, ids=[c[0] for c in MALFORMED])
def test_decode_rejects_malformed(case: str, build: Callable[[], pb.Envelope], reason: str) -> None:
    env = pb.Envelope.FromString(build().SerializeToString())
    with pytest.raises(wire.WireError, match=None) as exc:
        wire.decode(env)
    assert reason in str(exc.value), f"{case}: {exc.value}"
    assert isinstance(exc.value, ValueError)


def test_decode_accepts_the_boundaries() -> None:
    # the values just inside every limit are legal
    ok = [
        m.Heartbeat(wire.MAX_HB_SEQ, wire.MAX_PERIOD, -wire.MAX_CLOCK),
        m.OacDecide(T, -1, -1, False, P3, True),  # unilateral abort before any round (Alg. 2 l. 29)
        m.OacDecide(T, wire.MAX_ORDER, wire.MAX_ROUND, True, P3, False),
        m.OacEstimate(T, 0, 0, False, 0),
        m.OacEstimate(T, 0, 0, False, -1),  # the initial timestamp (Alg. 2 l. 20, haa.core.oac.oac.INITIAL_TS)
        m.OacTransaction(T, b"", (("h1", 5),), 1),  # a single-host transaction
    ]
    for msg in ok:
        assert wire.decode(env_of(msg))[3] == msg


def test_membership_messages_round_trip_and_reject_incomplete_ids() -> None:
    msgs = [
        m.Apply("h1:7000"),
        m.Introduce("h2", 3, "h2:7000", "h1.1.1"),
        m.Sponsor(),
        m.Connections((("h1", 1), ("h2", 2))),
        m.Connections((("h1", 1), ("h1", 2))),  # an old and a new incarnation of a restarted host
        m.Connections(()),
        m.Leave(),
        m.Locked("h1.1.4"),
        m.StateSnapshot(5, b"state", None, 0),
        m.StateSnapshot(5, b"state", m.TxId("h1", 1, 2), 4),
        m.StateSnapshot(5, b"state", m.TxId("h1", 1, 2), 4, 0, 1, "h2.1.3", ("h2", 1)),  # holding a lock
        m.StateForward(3, m.TxId("h1", 1, 2), b"payload"),
        m.StateRequest(m.TxId("h1", 1, 2)),
        m.SeqWrite(3, ((3, b"a"), (5, b""), (6, b"c"))),
        m.SeqWrite(0, ((1, b"x"),)),
        m.SeqWrite(2, ((2, b"x"), (3, b"y")), (10_000, 1)),  # costs travel; all 1 decodes as ()
    ]
    for msg in msgs:
        env = wire.encode("h9", 7, 0, msg)
        assert wire.decode(pb.Envelope.FromString(env.SerializeToString()))[3] == msg
    bad = wire.encode("h9", 7, 0, m.StateRequest(m.TxId("h1", 1, 2)))
    bad.state_request.txid.incarnation = 0
    with pytest.raises(wire.WireError):
        wire.decode(bad)
    lockless = wire.encode("h9", 7, 0, m.StateSnapshot(5, b"s", m.TxId("h1", 1, 2), 4, 0, 1, "h2.1.3", ("h2", 1)))
    lockless.state_snapshot.lock_by_incarnation = 0
    with pytest.raises(wire.WireError, match="lock_by"):
        wire.decode(lockless)
    twice = wire.encode("h9", 7, 0, m.Connections((("h1", 1), ("h1", 1))))
    with pytest.raises(wire.WireError, match="duplicate"):
        wire.decode(twice)
    empty = wire.encode("h9", 7, 0, m.Apply("x"))
    empty.apply.addr = ""
    with pytest.raises(wire.WireError):
        wire.decode(empty)
    # sequencer forwards: writes in the origin's order, numbered from 1, none below the floor
    for floor, writes, why in [
        (0, (), "no writes"),
        (0, ((0, b"x"),), "increasing"),
        (0, ((2, b"x"), (2, b"y")), "increasing"),
        (0, ((3, b"x"), (2, b"y")), "increasing"),
        (4, ((3, b"x"),), "floor above"),
    ]:
        env = wire.encode("h9", 7, 0, m.SeqWrite(1, ((1, b""),)))
        env.seq_write.floor = floor
        del env.seq_write.writes[:]
        for c, p in writes:
            env.seq_write.writes.add(cseq=c, payload=p)
        with pytest.raises(wire.WireError, match=why):
            wire.decode(pb.Envelope.FromString(env.SerializeToString()))
