"""Applying a committed transaction is total and deterministic.

One `AgentSpawn` with cost=+inf once wedged a live group: the agent table accepted it and the allocator raised
while the host reacted to the committed transaction. These tests feed two replicas of the group's global state
arbitrary transactions of every kind — hostile values from `haa.lab.dsim.hostile` and raw mutated bytes — and check
that no exception escapes, the replicas stay equal (content hash and hash chain), and everything the table
holds is something the allocator accepts (so the host's reaction cannot raise either).
"""

from __future__ import annotations

import math
import os
import random

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haa.core.allocation.specs import MAX_COST, AgentSpec, HostSpec
from haa.core.ddb import agenttable as at
from haa.core.membership.globalstate import GlobalState, TxAgent, TxDdb, TxFormation, encode_tx
from haa.core.messages import Member, TxId
from haa.lab.dsim import hostile
from haa.pb import agenttx_pb2 as apb

EXAMPLES = int(os.environ.get("HAA_FUZZ_EXAMPLES", "300"))
HOSTS = ("h1", "h2", "h3")
AGENTS = ("a1", "a2", "a3")


def _replica() -> GlobalState:
    g = GlobalState(HOSTS, 1)
    members = tuple(Member(h, 1, f"{h}:7000") for h in HOSTS)
    g.apply(TxId("h1", 1, 1), encode_tx(TxFormation(("h1", 1), members)))
    return g


def _agent_tx(kind: str, body: object) -> bytes:
    t = apb.AgentTx()
    getattr(t, kind).CopyFrom(body)
    return encode_tx(TxAgent(t.SerializeToString()))


def _setup() -> list[bytes]:
    """A few real agents, one active on each host, so hostile transactions can name them."""
    out = []
    for i, a in enumerate(AGENTS):
        out.append(_agent_tx("create", apb.AgentCreate(id=a, type="counter", cost=0.1, transfer_penalty=0.1,
                                                       recovery="backup", host="h1")))
        out.append(_agent_tx("move", apb.AgentMove(id=a, host=HOSTS[i])))
        out.append(_agent_tx("recovered", apb.AgentRecovered(id=a, host=HOSTS[i])))
    return out


def _check_allocatable(g: GlobalState) -> None:
    """What the agent layer builds from the table for the allocator (AgentNode._agent_specs/_host_specs) must
    construct: every number finite and within the allocator's bounds."""
    t = g.agents
    assert t.invalid_values() == []
    for r in t:
        AgentSpec(id=r.id, cost=r.cost(), hardware=frozenset(r.spec.hardware),
                  transfer_penalty=r.spec.transfer_penalty, current_host=r.owner or None)
        assert math.isfinite(r.cpu) and 0 <= r.cost() <= MAX_COST
    for h in t.hosts.values():
        HostSpec(h.name, h.capacity, frozenset(h.hardware), h.draining)
    for rate in t.affinity.values():
        assert math.isfinite(rate) and rate >= 0


def _apply_both(payloads: list[bytes]) -> tuple[GlobalState, GlobalState]:
    a, b = _replica(), _replica()
    for i, p in enumerate(payloads):
        tid = TxId("h2", 1, 100 + i)
        ra, rb = a.apply(tid, p), b.apply(tid, p)
        assert (ra.kind, ra.error, ra.stale, ra.view_changed) == (rb.kind, rb.error, rb.stale, rb.view_changed)
        if isinstance(ra.ddb_result, at.AgentApplied):
            assert ra.ddb_result == rb.ddb_result
    assert a.content_hash() == b.content_hash()
    assert a.chain == b.chain and a.seq == b.seq
    return a, b


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40))
def test_hostile_agent_and_ddb_transactions_apply_totally_and_identically(seed: int, n: int) -> None:
    rng = random.Random(seed)
    payloads = _setup()
    for _ in range(n):
        r = rng.random()
        if r < 0.7:
            payloads.append(encode_tx(TxAgent(hostile.hostile_agent_tx(rng, AGENTS, HOSTS))))
        elif r < 0.9:
            payloads.append(encode_tx(TxDdb(hostile.hostile_ddb_batch(rng))))
        else:  # a group transaction whose own bytes are mangled
            payloads.append(hostile.mutate(rng, encode_tx(TxAgent(hostile.hostile_agent_tx(rng, AGENTS, HOSTS)))))
    a, _ = _apply_both(payloads)
    _check_allocatable(a)


@settings(max_examples=EXAMPLES, deadline=None)
@given(data=st.binary(max_size=300))
def test_arbitrary_bytes_as_agent_transaction(data: bytes) -> None:
    a, _ = _apply_both([*_setup(), encode_tx(TxAgent(data))])
    _check_allocatable(a)


@pytest.mark.parametrize("kind", hostile.KINDS)
def test_every_kind_is_generated_and_applies(kind: str) -> None:
    rng = random.Random(kind)
    payloads = _setup() + [encode_tx(TxAgent(hostile.hostile_agent_tx(rng, AGENTS, HOSTS, kind=kind)))
                           for _ in range(200)]
    a, _ = _apply_both(payloads)
    _check_allocatable(a)


@pytest.mark.parametrize(
    ("field", "value"),
    [("cost", math.inf), ("cost", -math.inf), ("cost", math.nan), ("cost", 1e308), ("cost", MAX_COST * 1.01),
     ("transfer_penalty", math.inf), ("transfer_penalty", math.nan), ("transfer_penalty", -0.5)],
)
def test_create_with_a_bad_number_is_refused_at_the_edge_and_on_apply(field: str, value: float) -> None:
    """The probe's `AgentSpawn cost=+inf`: refused by check_create (the edge) and, proposed anyway by a peer that
    skips the edge, refused identically when it applies; the table stays allocatable."""
    c = apb.AgentCreate(id="bad", type="counter", cost=0.1, transfer_penalty=0.1, recovery="backup", host="h1")
    setattr(c, field, value)
    assert field in at.check_create(c)
    a, _ = _apply_both([*_setup(), _agent_tx("create", c)])
    assert a.agents.get("bad") is None
    _check_allocatable(a)


def test_bad_measurements_and_host_info_are_not_stored() -> None:
    costs = apb.AgentCosts(host="h1")
    costs.costs.add(id="a1", cpu=math.inf)
    costs.affinity.add(a="a1", b="a2", rate=math.inf)
    hosts = [apb.HostInfo(name="h2", capacity=v) for v in (math.inf, math.nan, 0.0, 1e-9, 1e308, -1.0)]
    hosts.append(apb.HostInfo(name="h3", capacity=1.0, hardware=["" for _ in range(2)]))
    payloads = [*_setup(), _agent_tx("costs", costs), *(_agent_tx("host", h) for h in hosts)]
    a, _ = _apply_both(payloads)
    assert a.agents.get("a1").cpu == 0.0
    assert not a.agents.affinity
    assert "h2" not in a.agents.hosts and "h3" not in a.agents.hosts
    _check_allocatable(a)


def test_unknown_body_kind_is_refused() -> None:
    """A transaction whose body is a field number this version does not know decodes with no body set."""
    res = at.AgentTable().apply(b"\xfa\x01\x00")  # field 31, length 0
    assert not res.ok
