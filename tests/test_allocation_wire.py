"""Allocation bytes on the wire (proto/haa/pb/alloc.proto via haa.core.allocation.allocwire): round trips, determinism,
and clear one-line errors naming the field for malformed bytes."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haa.core.allocation.allocation import ProposeFinish
from haa.core.allocation.allocwire import (
    AllocWireError,
    SessionFinish,
    decode_finish,
    decode_start,
    decode_update,
    encode_finish,
    encode_start,
    encode_update,
)
from haa.core.allocation.bids import Bid, BidUpdate, nil_bid
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart
from haa.pb import alloc_pb2 as apb

START = SessionStart(
    "h1",
    7,
    ("h1", "h2"),
    (
        AgentSpec("a1", 0.25, frozenset({"gpu", "cam"}), {"a2": 0.1}, 0.3, "h2"),
        AgentSpec("a2", 0.0, frozenset(), {}, 1.0, None),
    ),
    (HostSpec("h1", 1.5, frozenset({"gpu"})), HostSpec("h2", 0.5, draining=True)),
)


def test_bid_update_round_trip_with_a_nil_bid():
    upd = BidUpdate(3, (Bid("a1", "h2", 0.5, 0.25, 9), nil_bid("a2")), "h2")
    assert decode_update(encode_update(upd)) == upd


def test_start_round_trip_and_deterministic_bytes():
    data = encode_start(START)
    assert decode_start(data) == START
    assert encode_start(decode_start(data)) == data


def test_finish_round_trip_from_a_proposal():
    p = ProposeFinish(7, {"a1": "h1", "a2": "h2"}, "h1", ("a9",))
    f = decode_finish(encode_finish(p))
    assert f == SessionFinish("h1", 7, (("a1", "h1"), ("a2", "h2")), ("a9",))
    assert f.as_dict() == p.allocation


names = st.text("abcxyz123", min_size=1, max_size=4)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(0, 5, allow_nan=False),
            st.frozensets(names, max_size=2),
            st.floats(0, 1, allow_nan=False),
            st.sampled_from([None, "h1", "h2"]),
        ),
        max_size=5,
    )
)
def test_any_valid_start_round_trips(specs):
    ags = tuple(AgentSpec(f"a{i}", c, hw, {}, t, cur) for i, (c, hw, t, cur) in enumerate(specs))
    st_ = SessionStart("h1", 1, ("h1", "h2"), ags, (HostSpec("h1", 1.0), HostSpec("h2", 2.0)))
    assert decode_start(encode_start(st_)) == st_


def _start_pb() -> apb.AllocStart:
    m = apb.AllocStart()
    m.ParseFromString(encode_start(START))
    return m


def _bad_starts():
    m = _start_pb()
    m.agents[0].cost = math.nan
    yield m, "agents[0]: AgentSpec(a1).cost"
    m = _start_pb()
    m.agents[1].transfer_penalty = 1.5
    yield m, "agents[1]: AgentSpec(a2).transfer_penalty"
    m = _start_pb()
    m.agents[1].id = "a1"
    yield m, "duplicate agent"
    m = _start_pb()
    m.leader = "h2"
    yield m, "leader"
    m = _start_pb()
    m.hosts[1].capacity = -1
    yield m, "hosts[1]: HostSpec(h2).capacity"
    m = _start_pb()
    del m.hosts[1]
    yield m, "no HostSpec"
    m = _start_pb()
    m.agents[0].affinity.add(agent="a2", alpha=0.2)
    yield m, "affinity: duplicate"


@pytest.mark.parametrize(("msg", "words"), list(_bad_starts()), ids=lambda x: x if isinstance(x, str) else "")
def test_malformed_start_names_the_field(msg, words):
    with pytest.raises(AllocWireError) as e:
        decode_start(msg.SerializeToString())
    assert words in str(e.value) and str(e.value).startswith("AllocStart") and "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("data", "fn", "words"),
    [
        (b"\xff\xff\xff", decode_start, "AllocStart: not a valid protobuf message"),
        (b"\x0a", decode_update, "AllocBidUpdate: not a valid protobuf message"),
        ("text", decode_finish, "expected bytes"),
        (apb.AllocBidUpdate(ses_id=0).SerializeToString(), decode_update, "AllocBidUpdate.ses_id"),
        (
            apb.AllocBidUpdate(ses_id=1, bids=[apb.AllocBid(agent="", winner="h1")]).SerializeToString(),
            decode_update,
            "AllocBidUpdate.bids[0].agent",
        ),
        (
            apb.AllocBidUpdate(
                ses_id=1, bids=[apb.AllocBid(agent="a", winner="h1", reward=math.inf)]
            ).SerializeToString(),
            decode_update,
            "AllocBidUpdate.bids[0]: reward and support must be finite",
        ),
        (
            apb.AllocFinish(
                leader="h1",
                ses_id=1,
                allocation=[apb.AllocPlacement(agent="a", host="h1"), apb.AllocPlacement(agent="a", host="h2")],
            ).SerializeToString(),
            decode_finish,
            "allocated twice",
        ),
        (
            apb.AllocFinish(leader="h1", ses_id=1, allocation=[apb.AllocPlacement(agent="a")]).SerializeToString(),
            decode_finish,
            "AllocFinish.allocation[0].host",
        ),
        (apb.AllocFinish(ses_id=1).SerializeToString(), decode_finish, "AllocFinish.leader"),
    ],
)
def test_malformed_bytes_are_clear_errors(data, fn, words):
    with pytest.raises(AllocWireError) as e:
        fn(data)
    assert words in str(e.value) and "\n" not in str(e.value)
