"""The sequencer (docs/oac.md, "The sequencer"): members forward DDB and test writes to the leader, which
batches them into one OAC; replicas apply each write once per (origin, cseq). Deterministic group simulator
and the replicated state; the real daemons are covered by tests/test_runtime_membership.py and bench ap1."""

from haa.core.ddb import ops as ddb
from haa.core.membership.globalstate import GlobalState, SeqEntry, TxDdb, TxMembership, TxSeq, TxTest, encode_tx
from haa.core.messages import Member, TxId
from haa.lab.dsim.group import GroupScenario, GroupSim, check_group
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.schedule import Fault

A = ("h1", 1)
B = ("h2", 7)


def _state() -> GlobalState:
    st = GlobalState(("h1",), 0)
    members = (Member("h1", 1, "h1:1"), Member("h2", 7, "h2:1"))
    st.apply(TxId("h1", 1, 1), encode_tx(TxMembership("", A, members)))
    return st


def _put(key: str, v: int) -> bytes:
    return encode_tx(TxDdb(ddb.encode_batch([ddb.put(key, "json", {"v": v})], origin="x")))


def _batch(*entries: SeqEntry) -> bytes:
    return encode_tx(TxSeq(tuple(entries)))


def test_each_write_is_applied_once_whatever_batches_carry_it() -> None:
    st = _state()
    r1 = st.apply(TxId("h1", 1, 2), _batch(SeqEntry(A, 1, 1, _put("a", 1)), SeqEntry(B, 1, 1, _put("b", 1))))
    assert [(x.origin, x.cseq, x.applied, x.kind) for x in r1.ddb_result] == [(A, 1, True, "ddb"), (B, 1, True, "ddb")]
    # a second sequencer batched B's write 1 again (retried after a leader change) with its write 2
    r2 = st.apply(TxId("h2", 7, 1), _batch(SeqEntry(B, 1, 1, _put("b", 99)), SeqEntry(B, 2, 1, _put("b", 2))))
    assert [(x.cseq, x.applied, x.error) for x in r2.ddb_result] == [(1, False, "duplicate"), (2, True, "")]
    b = st.ddb.get("b")
    assert b is not None and b.raw == '{"v":2}' and (b.created, b.version) == (2, 3)  # 99 never applied
    # out of order (write 4 before 3: two batches in flight, the first aborted and retried) is fine
    st.apply(TxId("h1", 1, 3), _batch(SeqEntry(A, 4, 2, _put("a", 4))))
    r4 = st.apply(TxId("h1", 1, 4), _batch(SeqEntry(A, 3, 2, _put("a", 3)), SeqEntry(A, 4, 2, _put("a", 44))))
    assert [(x.cseq, x.applied) for x in r4.ddb_result] == [(3, True), (4, False)]
    # the floor settles everything below it: a late copy of write 2, given up by its origin, never applies
    st.apply(TxId("h1", 1, 5), _batch(SeqEntry(A, 5, 5, encode_tx(TxTest(b"t")))))
    r6 = st.apply(TxId("h1", 1, 6), _batch(SeqEntry(A, 2, 2, _put("a", 2))))
    assert not r6.ddb_result[0].applied
    assert st.seq_origins[A].floor == 5 and st.seq_origins[A].done == {5}  # bounded: below the floor forgotten


def test_writes_of_non_members_and_invalid_inner_transactions_are_refused_deterministically() -> None:
    st = _state()
    r = st.apply(
        TxId("h1", 1, 2),
        _batch(
            SeqEntry(("h3", 2), 1, 1, _put("c", 1)),  # not a member
            SeqEntry(A, 1, 1, encode_tx(TxMembership("", A, ()))),  # a batch carries only ddb / test writes
            SeqEntry(A, 2, 1, b"\xff\xff"),  # does not decode
        ),
    )
    assert [(x.applied, x.kind) for x in r.ddb_result] == [(False, ""), (True, "invalid"), (True, "invalid")]
    assert "not a member" in r.ddb_result[0].error and "cannot carry membership" in r.ddb_result[1].error
    assert st.ddb.get("c") is None and len(st.members) == 2


def test_the_dedup_memory_travels_with_a_snapshot_and_is_in_the_content_hash() -> None:
    st = _state()
    st.apply(TxId("h1", 1, 2), _batch(SeqEntry(A, 1, 1, _put("a", 1)), SeqEntry(B, 3, 2, _put("b", 3))))
    joiner = GlobalState(("h1",), 0)
    joiner.restore(st.snapshot())
    assert joiner.content_hash() == st.content_hash()
    late = _batch(SeqEntry(B, 3, 2, _put("b", 33)), SeqEntry(B, 4, 2, _put("b", 4)))
    ra, rb = st.apply(TxId("h1", 1, 3), late), joiner.apply(TxId("h1", 1, 3), late)
    assert [x.applied for x in ra.ddb_result] == [x.applied for x in rb.ddb_result] == [False, True]
    assert joiner.content_hash() == st.content_hash()
    other = _state()
    other.apply(TxId("h1", 1, 2), _batch(SeqEntry(A, 1, 1, _put("a", 1)), SeqEntry(B, 9, 2, _put("b", 3))))
    assert other.ddb.content_hash() == _ddb_after_same_ops().ddb.content_hash()
    assert other.content_hash() != _ddb_after_same_ops().content_hash()  # same data, other dedup memory


def _ddb_after_same_ops() -> GlobalState:
    st = _state()
    st.apply(TxId("h1", 1, 2), _batch(SeqEntry(A, 1, 1, _put("a", 1)), SeqEntry(B, 3, 2, _put("b", 3))))
    return st


def _scenario(n: int = 5, writes: int = 40, faults=(), burst_at: float | None = None) -> GroupScenario:
    names = [f"h{i + 1}" for i in range(n)]
    sc = GroupScenario(
        seed=3,
        names=names,
        core=names[:3],
        c_f=1,
        delay=DelayModel("exp", 0.0005, 0.002),
        offsets=[100.0 * i for i in range(n)],
        drifts=[0.0] * n,
        starts={nm: 0.01 * i for i, nm in enumerate(names)},
        features={},
        workload="ddb",
        batch_max=3,
    )
    sc.faults = list(faults)
    sc.writes = [(1.5 + 0.05 * i, names[i % n]) for i in range(writes)]
    if burst_at is not None:
        sc.writes += [(burst_at, nm) for nm in names for _ in range(5)]
        sc.writes.sort()
    return sc


def _live(sim: GroupSim) -> list:
    return [h for h in sim.cl.by_idx if h.state == 0 and h.core is not None]


def test_every_members_writes_go_through_the_leader_in_batches() -> None:
    sim = GroupSim(_scenario(burst_at=2.0))
    sim.run()
    assert check_group(sim) == []
    assert len(sim.gh.acked) == 40 + 25
    hosts = _live(sim)
    batches = {h.name: h.core.counters["seq_batches"] for h in hosts}
    assert set(k for k, v in batches.items() if v) == {"h1"}, batches  # only the leader proposes writes
    assert batches["h1"] < 40 + 25  # the burst (25 writes at one instant) went out in a few batches
    assert sum(h.core.counters["seq_forwarded"] for h in hosts) >= 40 + 25
    assert all(not h.core.seq.busy() for h in hosts)  # nothing pending, queued or in OAC


def test_writes_pending_at_a_crashed_leader_are_forwarded_to_the_next_and_applied_once() -> None:
    # h1 (leader, sequencer) crashes in the middle of the writes; the next member in rank becomes the leader
    sim = GroupSim(_scenario(writes=60, faults=[Fault(2.2, "crash", "h1")]))
    sim.run()
    assert check_group(sim) == []  # DDB-Exactly-Once and -Durability included
    hosts = _live(sim)
    assert "h1" not in {h.name for h in hosts}
    assert sum(h.core.counters["seq_retargeted"] for h in hosts) >= 1
    leader = hosts[0].core.state.members[0].name
    assert leader != "h1"
    assert next(h for h in hosts if h.name == leader).core.counters["seq_batches"] > 0  # it took over the writes
    assert {h.name for h in hosts if h.core.counters["seq_batches"]} == {leader}
    acked_by = {req[0] for req in sim.gh.acked}
    assert acked_by >= {"h2", "h3", "h4", "h5"}  # every survivor's writes committed


def test_without_the_sequencer_every_member_proposes_its_own_writes() -> None:
    sc = _scenario(burst_at=2.0)
    sc.sequencer = False
    sim = GroupSim(sc)
    sim.run()
    assert check_group(sim) == []
    assert len(sim.gh.acked) == 40 + 25
    assert all(h.core.counters["seq_batches"] == 0 for h in _live(sim))
