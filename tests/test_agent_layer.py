"""The agent layer's sans-I/O parts: the replicated agent table, sender streams, and short simulations."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from haa.core.agents.routing import Inbox, Outbox
from haa.core.ddb import agenttable as at
from haa.lab.dsim.agents import draw_agents, run_agents
from haa.pb import agenttx_pb2 as apb

MEMBERS = ("h1", "h2", "h3")


def tx(**kw: object) -> bytes:
    t = apb.AgentTx()
    (kind, body), = kw.items()
    getattr(t, kind).CopyFrom(body)
    return at.encode(t)


def create(table: at.AgentTable, agent: str, parent: str = "", host: str = "h1") -> at.AgentApplied:
    c = apb.AgentCreate(id=agent, type="counter", parent=parent, cost=0.1, transfer_penalty=0.1,
                        recovery="backup", host=host)
    return table.apply(tx(create=c), MEMBERS)


def activate(table: at.AgentTable, agent: str, host: str) -> None:
    table.apply(tx(move=apb.AgentMove(id=agent, host=host)), MEMBERS)
    res = table.apply(tx(recovered=apb.AgentRecovered(id=agent, host=host)), MEMBERS)
    assert res.ok, res.reason


def test_names_follow_parentage() -> None:
    t = at.AgentTable()
    assert create(t, "a").ok and create(t, "b").ok
    assert create(t, "a1", parent="a").ok and create(t, "a2", parent="a").ok
    assert create(t, "a11", parent="a1").ok
    assert [t.get(x).name for x in ("a", "b", "a1", "a2", "a11")] == ["A1", "A2", "A1.1", "A1.2", "A1.1.1"]
    assert t.resolve("A1.1").id == "a1"
    bad = create(t, "a", parent="")
    assert not bad.ok and "already exists" in bad.reason
    assert "unknown parent" in create(t, "z", parent="nope").reason


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [("transfer_penalty", 1.5, "transfer_penalty"), ("cost", -1.0, "cost"), ("recovery", "maybe", "recovery"),
     ("id", "", "agent id"), ("type", "", "type name")],
)
def test_malformed_create_is_refused_with_a_reason(field: str, value: object, reason: str) -> None:
    c = apb.AgentCreate(id="a", type="counter", recovery="backup")
    setattr(c, field, value)
    assert reason in at.check_create(c)


def test_garbage_transaction_is_a_no_op_with_a_reason() -> None:
    t = at.AgentTable()
    res = t.apply(b"\xff\xff\xff", MEMBERS)
    assert not res.ok and "does not decode" in res.reason
    assert not t.apply(b"", MEMBERS).ok  # body not set


def test_freeze_release_claim_hand_over_queues_and_fence_epochs() -> None:
    t = at.AgentTable()
    create(t, "a")
    activate(t, "a", "h1")
    r = t.get("a")
    assert (r.status, r.owner, r.epoch, r.life) == (at.ACTIVE, "h1", 1, 1)
    # a freeze by a host that does not own it, or with a stale epoch, is refused
    assert not t.apply(tx(freeze=apb.AgentFreeze(id="a", host="h2", epoch=1)), MEMBERS).ok
    assert not t.apply(tx(freeze=apb.AgentFreeze(id="a", host="h1", epoch=0)), MEMBERS).ok
    assert t.apply(tx(freeze=apb.AgentFreeze(id="a", host="h1", epoch=1)), MEMBERS).ok
    # queue2 while freezing (Alg. 5 l. 23)
    m2 = apb.RoutedMsg(src="b", src_life=1, seq=2, dst="a", payload=b"2")
    assert t.apply(tx(push=apb.AgentPush(id="a", queue=2, msgs=[m2])), MEMBERS).ok
    m1 = apb.RoutedMsg(src="b", src_life=1, seq=1, dst="a", payload=b"1")
    rel = apb.AgentRelease(id="a", host="h1", epoch=1, state=b"S", pending=[m1],
                           inbox=[apb.StreamPos(src="b", src_life=1, next=1)])
    assert t.apply(tx(release=rel), MEMBERS).ok
    assert (r.status, r.owner, r.state) == (at.FROZEN, "", b"S")
    # a claim by a host the allocation does not give it is abandoned (Alg. 6 l. 18)
    assert not t.apply(tx(claim=apb.AgentClaim(id="a", host="h2")), MEMBERS).ok
    t.apply(tx(move=apb.AgentMove(id="a", host="h2")), MEMBERS)
    res = t.apply(tx(claim=apb.AgentClaim(id="a", host="h2")), MEMBERS)
    assert res.ok and [m.payload for m in res.msgs] == [b"1", b"2"]  # queue1 then queue2 (Alg. 6 l. 21)
    assert (r.status, r.owner, r.epoch, r.life, r.queue1, r.queue2) == (at.ACTIVE, "h2", 2, 1, [], [])
    # a second claim finds it active: refused
    assert not t.apply(tx(claim=apb.AgentClaim(id="a", host="h2")), MEMBERS).ok
    # a push proposed before the claim committed is not stored: the owner gets it
    late = t.apply(tx(push=apb.AgentPush(id="a", queue=2, msgs=[m2])), MEMBERS)
    assert late.reason == "deliver" and late.host == "h2" and r.queue2 == []


def test_backups_only_from_the_current_epoch_and_recovery_takes_the_latest() -> None:
    t = at.AgentTable()
    create(t, "a")
    activate(t, "a", "h1")
    assert t.apply(tx(backup=apb.AgentBackup(id="a", host="h1", epoch=1, data=b"b1")), MEMBERS).ok
    assert t.apply(tx(backup=apb.AgentBackup(id="a", host="h1", epoch=1, data=b"b2")), MEMBERS).ok
    assert not t.apply(tx(backup=apb.AgentBackup(id="a", host="h1", epoch=0, data=b"old")), MEMBERS).ok
    assert not t.apply(tx(backup=apb.AgentBackup(id="a", host="h2", epoch=1, data=b"x")), MEMBERS).ok
    touched = t.on_removed(["h1"])  # its host left the group: the agent crashed
    assert touched == ("a",)
    r = t.get("a")
    assert (r.status, r.owner, r.alloc) == (at.CRASHED, "", "")
    assert not t.apply(tx(recovered=apb.AgentRecovered(id="a", host="h2")), MEMBERS).ok  # not allocated to h2
    t.apply(tx(move=apb.AgentMove(id="a", host="h2")), MEMBERS)
    assert t.apply(tx(recovered=apb.AgentRecovered(id="a", host="h2")), MEMBERS).ok
    assert (r.backup, r.epoch, r.life) == (b"b2", 2, 2)
    # a backup of the dead epoch arriving late cannot overwrite the new life's
    assert not t.apply(tx(backup=apb.AgentBackup(id="a", host="h1", epoch=1, data=b"zombie")), MEMBERS).ok


def test_a_move_to_a_host_that_is_no_member_when_it_commits_is_refused() -> None:
    """The operator named a member, which left the group before the move committed (`haactl verify recovery
    --hosts 7` seeds 1802 and 1954): the table refuses it, so an agent is never allocated to a non-member."""
    t = at.AgentTable()
    create(t, "a")
    activate(t, "a", "h1")
    res = t.apply(tx(move=apb.AgentMove(id="a", host="h3")), ("h1", "h2"))
    assert not res.ok and res.reason == "h3 is not a member of the group"
    assert t.get("a").alloc == "h1"
    assert t.apply(tx(move=apb.AgentMove(id="a", host="h2")), ("h1", "h2")).ok


def test_allocation_start_and_finish_validity() -> None:
    t = at.AgentTable()
    create(t, "a")
    assert not t.apply(tx(start=apb.AllocStartTx(ses_id=1, leader="h2", group=list(MEMBERS), agents=["a"])),
                       MEMBERS).ok  # not the leader
    # the expired start used its id up (as the allocator does): the leader's must be higher
    assert not t.apply(tx(start=apb.AllocStartTx(ses_id=1, leader="h1", group=list(MEMBERS), agents=["a"])),
                       MEMBERS).ok
    start = apb.AllocStartTx(ses_id=2, leader="h1", group=list(MEMBERS), agents=["a"])
    assert t.apply(tx(start=start), MEMBERS).ok
    assert not t.apply(tx(start=start), MEMBERS).ok  # session ids increase
    assert not t.apply(tx(finish=apb.AllocFinishTx(ses_id=1, leader="h1", allocation={"a": "h2"})), MEMBERS).ok
    fin = apb.AllocFinishTx(ses_id=2, leader="h1", allocation={"a": "h3"})
    assert not t.apply(tx(finish=fin), ("h1", "h2")).ok  # the group changed since the start
    assert t.apply(tx(finish=fin), MEMBERS).ok and t.get("a").alloc == "h3"
    assert not t.apply(tx(finish=fin), MEMBERS).ok  # finished once
    create(t, "b")
    t.apply(tx(start=apb.AllocStartTx(ses_id=3, leader="h1", group=list(MEMBERS), agents=["a", "b"])), MEMBERS)
    create(t, "c")  # the agent list changed: the start is a snapshot, its finish still counts ("c" waits)
    assert t.apply(tx(finish=apb.AllocFinishTx(ses_id=3, leader="h1", allocation={"a": "h1", "b": "h2"})),
                   MEMBERS).ok
    assert (t.get("b").alloc, t.get("c").alloc) == ("h2", "")
    # a start proposed before "c" existed commits after it: valid all the same
    assert t.apply(tx(start=apb.AllocStartTx(ses_id=4, leader="h1", group=list(MEMBERS), agents=["a", "b"])),
                   MEMBERS).ok


def test_snapshot_round_trip_keeps_the_content_hash() -> None:
    t = at.AgentTable()
    create(t, "a")
    create(t, "a1", parent="a")
    activate(t, "a", "h1")
    t.apply(tx(backup=apb.AgentBackup(id="a", host="h1", epoch=1, data=b"b")), MEMBERS)
    t.apply(tx(host=apb.HostInfo(name="h1", capacity=2.0, hardware=["cam"])), MEMBERS)
    t.apply(tx(costs=apb.AgentCosts(host="h1", costs=[apb.AgentCost(id="a", cpu=0.3)],
                                    affinity=[apb.Affinity(a="a", b="a1", rate=500.0)])), MEMBERS)
    back = at.AgentTable.restore(t.snapshot())
    assert back.content_hash() == t.content_hash()
    assert back.get("a1").name == "A1.1" and back.get("a").cpu == 0.3
    with pytest.raises(at.AgentTxError):
        at.AgentTable.restore(b"\xff\x01garbage")


def test_queues_are_bounded() -> None:
    t = at.AgentTable()
    create(t, "a")
    msgs = [apb.RoutedMsg(src="b", src_life=1, seq=i + 1, dst="a") for i in range(50)]
    old = at.MAX_QUEUE
    at.MAX_QUEUE = 20
    try:
        t.apply(tx(push=apb.AgentPush(id="a", queue=2, msgs=msgs)), MEMBERS)
    finally:
        at.MAX_QUEUE = old
    assert len(t.get("a").queue2) == 20 and t.get("a").dropped == 30


# ------------------------------------------------------------------------------------------------ streams


def msg(src: str, seq: int, life: int = 1) -> apb.RoutedMsg:
    return apb.RoutedMsg(src=src, src_life=life, seq=seq, dst="r", payload=str(seq).encode())


@settings(max_examples=200, deadline=None)
@given(st.permutations(list(range(1, 30))), st.lists(st.integers(1, 29), max_size=10))
def test_inbox_delivers_each_message_once_in_sender_order(order: list[int], dups: list[int]) -> None:
    box = Inbox()
    got = []
    for seq in order + dups:
        got += [int(m.payload) for m in box.offer(msg("s", seq))]
    assert got == list(range(1, 30))
    assert box.stats.duplicates == len(dups)


def test_inbox_positions_travel_with_the_agent() -> None:
    a = Inbox()
    for i in (1, 2, 4):
        a.offer(msg("s", i))
    b = Inbox(a.positions())  # thawed elsewhere; the held message travels in `pending` (AgentRelease)
    assert [int(m.payload) for m in b.offer(msg("s", 3))] == [3]
    assert [int(m.payload) for m in b.offer(msg("s", 4))] == [4]
    assert b.offer(msg("s", 2)) == []  # already processed before the transfer


def test_inbox_flushes_the_stream_of_a_dead_sender_life() -> None:
    box = Inbox()
    box.offer(msg("s", 1))
    assert box.offer(msg("s", 3)) == [] and box.waiting() == [("s", 1)]
    assert [int(m.payload) for m in box.flush([("s", 1)])] == [3]
    assert box.stats.skipped == 1
    assert [int(m.payload) for m in box.offer(msg("s", 1, life=2))] == [1]  # the new life starts at 1


def test_recovered_inbox_adopts_the_first_message_of_each_stream() -> None:
    box = Inbox(adopt=True)
    assert [int(m.payload) for m in box.offer(msg("s", 17))] == [17]
    assert box.offer(msg("s", 16)) == []


def test_a_recovered_inbox_keeps_adopting_after_a_move_for_the_streams_it_has_not_seen() -> None:
    """Recovered (adopt), then frozen before a sender it had heard from in its previous life spoke again: on
    the next host that sender's stream is new to the inbox and far along (seq 57). Without the mode travelling
    with the positions the thawed inbox waited for message 1 and held the stream back for good."""
    rec = Inbox(adopt=True)
    assert [int(m.payload) for m in rec.offer(msg("t", 9))] == [9]
    moved = Inbox(rec.positions())
    assert moved.adopt and [int(m.payload) for m in moved.offer(msg("s", 57))] == [57]
    assert [int(m.payload) for m in moved.offer(msg("t", 10))] == [10] and moved.offer(msg("t", 8)) == []
    assert [int(m.payload) for m in moved.offer(msg("s", 59))] == [] and moved.waiting() == [("s", 1)]
    # a fresh agent's inbox does not adopt, here or after a move: its streams start at 1
    fresh = Inbox()
    assert fresh.offer(msg("s", 2)) == [] and not Inbox(fresh.positions()).adopt
    assert all(p.src for p in fresh.positions())


def test_outbox_numbers_per_receiver_and_travels() -> None:
    o = Outbox()
    assert [o.stamp("x"), o.stamp("x"), o.stamp("y")] == [1, 2, 1]
    assert Outbox(o.positions()).stamp("x") == 3


# ------------------------------------------------------------------------------------------------ simulation


@pytest.mark.parametrize("mix", ["transfer", "recovery"])
def test_short_agent_simulations_hold_the_properties(mix: str) -> None:
    for seed in range(6):
        sim, vs = run_agents(seed, 5, mix)
        assert not vs, f"seed {seed}: {[str(v) for v in vs]}"
        assert sim.quiescent


def test_agent_simulation_is_deterministic() -> None:
    a, _ = run_agents(3, 5, "recovery")
    b, _ = run_agents(3, 5, "recovery")
    assert a.cl.trace_hash() == b.cl.trace_hash()
    assert draw_agents(3, 5, "recovery").describe() == draw_agents(3, 5, "recovery").describe()
    with pytest.raises(ValueError, match="unknown mix"):
        draw_agents(1, 5, "nope")


def test_the_agent_table_is_bounded_and_a_refused_create_names_the_bound() -> None:
    """The reliability probe had 2,000 unrunnable agents accepted into an unbounded table; every change of the
    table re-reads all of them for the allocation. At MAX_AGENTS a create is refused in the total order (so
    concurrent spawns on several hosts cannot pass it), naming the bound; a retried keyed spawn still gets its
    child back."""
    t = at.AgentTable()
    assert create(t, "parent").ok

    def keyed(aid: str) -> bytes:
        return tx(create=apb.AgentCreate(id=aid, type="counter", cost=0.01, host="h1", key="spawn-1",
                                         parent="parent", recovery="backup"))

    assert t.apply(keyed("k"), MEMBERS).ok
    for i in range(at.MAX_AGENTS - 2):
        assert create(t, f"a{i}").ok
    res = create(t, "one-too-many")
    assert not res.ok and "MAX_AGENTS" in res.reason and str(at.MAX_AGENTS) in res.reason
    again = t.apply(keyed("k2"), MEMBERS)
    assert again.ok and again.existing and again.agent == "k"
    t.apply(tx(remove=apb.AgentRemove(id="a0", host="h1")), MEMBERS)
    assert create(t, "fits-again").ok
