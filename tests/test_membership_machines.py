"""The machines `MembershipNode` is composed of, each driven alone: no `HostCore`, no runtime, no simulator.

Each machine takes `step(now, input)` and returns its effects; a small fake stands for the node it reads
(the `SeqHost` / `XferHost` protocols), and the tests carry out the effects the way the node does
(`ProposeBatch` with the id the machine reserved, `ApplyTx`/`Restore` -> `Continue`).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import pytest

from haa.core.effects import Log, Send, SetTimer
from haa.core.membership import formation as fm
from haa.core.membership import sequencer as sq
from haa.core.membership import statetransfer as xf
from haa.core.membership.globalstate import GlobalState, SeqApplied, SeqEntry, TxFormation
from haa.core.membership.groupeffects import NodeTimer, WriteDone
from haa.core.messages import Member, SeqWrite, StateRequest, TxId

ME = ("h2", 1)
LEADER = ("h1", 1)
OTHER = ("h3", 1)


# ------------------------------------------------------------------------------------------------ timer keys


def test_timer_keys_are_typed_hashable_and_print_as_the_old_tuples() -> None:
    k = NodeTimer("seqretry")
    assert k == NodeTimer("seqretry") and hash(k) == hash(NodeTimer("seqretry"))
    assert k != ("m", "seqretry")  # typed: no longer equal to a bare tuple
    assert str(k) == repr(k) == str(("m", "seqretry"))  # the simulator hashes f"{key}" into its trace
    assert sorted([NodeTimer("retry"), NodeTimer("catchup")]) == [NodeTimer("catchup"), NodeTimer("retry")]


# ------------------------------------------------------------------------------------------------ sequencer


@dataclass
class FakeSeqHost:
    member: bool = True
    left: bool = False
    open: bool = True
    seq_of: tuple[str, int] | None = LEADER
    done: dict[tuple[str, int], set[int]] = field(default_factory=dict)
    txids: int = 0
    formed: bool = True
    locked: bool = False
    catching: bool = False

    def new_txid(self) -> TxId:
        self.txids += 1
        return TxId(ME[0], ME[1], self.txids)

    def is_member(self) -> bool:
        return self.member

    def group_formed(self) -> bool:
        return self.formed

    def is_locked(self) -> bool:
        return self.locked

    def catching_up(self) -> bool:
        return self.catching

    def has_left(self) -> bool:
        return self.left

    def may_batch(self) -> bool:
        return self.open

    def sequencer(self) -> tuple[str, int] | None:
        return self.seq_of

    def settled(self, origin: tuple[str, int], cseq: int) -> bool:
        return cseq in self.done.get(origin, set())


class SeqDriver:
    """Carries out a sequencer's effects as `MembershipNode._seq` does (proposal ids come from the host: 1, 2, ...)."""

    def __init__(self, host: FakeSeqHost, **cfg: Any) -> None:
        self.m = sq.Sequencer(ME, host, sq.SeqConfig(**cfg))
        self.n = 0
        self.proposed: dict[TxId, tuple[SeqEntry, ...]] = {}
        self.counters: dict[str, int] = {}

    def step(self, now: float, inp: sq.SeqInput) -> list[sq.SeqEffect]:
        out: list[sq.SeqEffect] = []
        for e in self.m.step(now, inp):
            out.append(e)
            if isinstance(e, sq.ProposeBatch):
                self.n += 1
                assert e.txid == TxId(ME[0], ME[1], self.n)  # reserved from the host, in order
                self.proposed[e.txid] = e.entries
            elif isinstance(e, sq.Count):
                self.counters[e.name] = self.counters.get(e.name, 0) + e.n
        return out


def sends(effects: list[sq.SeqEffect]) -> list[Send]:
    return [e for e in effects if isinstance(e, Send)]


def test_origin_forwards_to_the_sequencer_and_arms_the_retry_timer() -> None:
    d = SeqDriver(FakeSeqHost())
    out = d.step(1.0, sq.Submit("r1", b"w1"))
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((1, b"w1"),)))]
    assert SetTimer(sq.RETRY_TIMER, 3.0) in out
    out = d.step(1.5, sq.Submit("r2", b"w2"))  # the timer is armed once; the floor is the oldest pending cseq
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((2, b"w2"),)))]
    assert not [e for e in out if isinstance(e, SetTimer)]
    assert d.counters["seq_forwarded"] == 2


def test_origin_refuses_outside_a_formed_group_and_holds_while_catching_up() -> None:
    host = FakeSeqHost(member=False)
    d = SeqDriver(host)
    assert d.step(0.0, sq.Submit("r0", b"w0")) == [WriteDone("r0", False, None, 0, "not a member of the group")]
    host.member, host.formed = True, False
    assert d.step(0.0, sq.Submit("r1", b"w1")) == [WriteDone("r1", False, None, 0, "the group is not formed yet")]
    host.formed, host.catching = True, True  # a new member: held, no cseq taken, nothing sent, no timer
    assert d.step(1.0, sq.Submit("r2", b"w2")) == [] and d.step(1.0, sq.Submit("r3", b"w3")) == []
    assert d.m.held and not d.m.pending and d.m.busy()
    assert d.step(2.0, sq.Release()) == []  # still catching up: still held
    host.catching, host.locked = False, True
    assert d.step(2.0, sq.Release()) == []  # locked (Alg. 3 l. 129): still held
    host.locked = False
    out = d.step(3.0, sq.Release())  # released in submission order, cseq 1 and 2
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((1, b"w2"),))), Send("h1", 1, SeqWrite(1, ((2, b"w3"),)))]
    assert not d.m.held and list(d.m.pending) == [1, 2]


def test_origin_answers_its_writes_when_the_batch_is_applied() -> None:
    d = SeqDriver(FakeSeqHost())
    d.step(0.0, sq.Submit("r1", b"w1"))
    d.step(0.0, sq.Submit("r2", b"w2"))
    t = TxId("h1", 1, 7)
    res = (SeqApplied(ME, 1, True, "ddb", "ok", ""), SeqApplied(OTHER, 1, True, "ddb", None, ""),
           SeqApplied(ME, 2, False, "ddb", None, "not a member"))
    out = d.step(1.0, sq.BatchApplied(t, 12, res))
    assert out == [WriteDone("r1", True, t, 12, "", "ok"), WriteDone("r2", False, None, 0, "not a member")]
    assert not d.m.pending


def test_retry_reforwards_what_waited_and_abandons_what_is_too_old() -> None:
    d = SeqDriver(FakeSeqHost(), seq_retry=2.0, seq_abandon=5.0)
    d.step(0.0, sq.Submit("old", b"w1"))
    d.step(3.0, sq.Submit("new", b"w2"))
    out = d.step(4.0, sq.RetryDue())  # w1 last sent at 0 (due), w2 at 3 (not due)
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((1, b"w1"),)))]
    assert d.counters["seq_reforwarded"] == 1
    out = d.step(6.0, sq.RetryDue())
    assert out[0] == WriteDone("old", False, None, 0, "not committed within 5 s (it may still commit)")
    assert sends(out) == [Send("h1", 1, SeqWrite(2, ((2, b"w2"),)))]  # floor moved up to the oldest left
    assert SetTimer(sq.RETRY_TIMER, 8.0) in out


def test_retarget_forwards_every_pending_write_to_the_new_sequencer() -> None:
    host = FakeSeqHost()
    d = SeqDriver(host)
    d.step(0.0, sq.Submit("r1", b"w1"))
    assert sends(d.step(0.1, sq.Retarget())) == []  # same sequencer: nothing to do
    host.seq_of = OTHER
    out = d.step(0.2, sq.Retarget())
    assert sends(out) == [Send("h3", 1, SeqWrite(1, ((1, b"w1"),)))]
    assert d.counters["seq_retargeted"] == 1


def test_no_sequencer_or_not_a_member_waits_for_the_retry_timer() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=None))
    out = d.step(0.0, sq.Submit("r1", b"w1"))
    assert sends(out) == [] and out[-1] == SetTimer(sq.RETRY_TIMER, 2.0)


def test_sequencer_batches_within_limits_and_inflight_bound() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME), seq_inflight=2, seq_max_entries=2)
    writes = tuple((c, f"w{c}".encode()) for c in range(1, 6))
    out = d.step(0.0, sq.Forwarded(OTHER, 1, writes))
    batches = [e.entries for e in out if isinstance(e, sq.ProposeBatch)]
    assert [[x.cseq for x in b] for b in batches] == [[1, 2], [3, 4]]  # two in OAC, one write waits
    assert [x.cseq for x in d.m.queue] == [5]
    first = next(iter(d.m.inflight))
    out = d.step(1.0, sq.BatchApplied(first, 3, ()))
    assert [[x.cseq for x in e.entries] for e in out if isinstance(e, sq.ProposeBatch)] == [[5]]


def test_sequencer_respects_the_byte_limit() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME), seq_inflight=4, seq_max_bytes=10)
    d.step(0.0, sq.Forwarded(OTHER, 1, ((1, b"x" * 6), (2, b"y" * 6), (3, b"z" * 20))))
    assert [[x.cseq for x in b] for b in d.proposed.values()] == [[1], [2], [3]]  # an oversized write goes alone


def test_sequencer_keeps_a_batchs_ops_within_the_cost_bound() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME), seq_inflight=4, seq_max_cost=10)
    d.step(0.0, sq.Forwarded(OTHER, 1, ((1, b"a"), (2, b"b"), (3, b"c"), (4, b"d"), (5, b"e")), (4, 6, 3, 25, 1)))
    # 4+6 fit; 3 opens the next; 25 goes alone (a single write always goes); 1 after it
    assert [[x.cseq for x in b] for b in d.proposed.values()] == [[1, 2], [3], [4], [5]]
    assert [x.cost for b in d.proposed.values() for x in b] == [4, 6, 3, 25, 1]


def test_an_origin_forwards_each_writes_cost() -> None:
    d = SeqDriver(FakeSeqHost())
    out = d.step(0.0, sq.Submit("r1", b"w1", 7))
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((1, b"w1"),), (7,)))]
    out = d.step(0.0, sq.Submit("r2", b"w2"))  # cost 1 (a test write): no costs on the wire, as before
    assert sends(out) == [Send("h1", 1, SeqWrite(1, ((2, b"w2"),)))]


def test_sequencer_dedups_queued_and_settled_writes() -> None:
    host = FakeSeqHost(seq_of=ME, open=False, done={OTHER: {1}})
    d = SeqDriver(host)
    d.step(0.0, sq.Forwarded(OTHER, 1, ((1, b"a"), (2, b"b"))))
    d.step(0.1, sq.Forwarded(OTHER, 1, ((2, b"b"), (3, b"c"))))  # 2 again: forwarded twice by its origin
    assert [(e.origin, e.cseq) for e in d.m.queue] == [(OTHER, 2), (OTHER, 3)]
    assert d.proposed == {}  # held while the node does not let global-state changes through (l. 129)
    host.open = True
    d.step(0.2, sq.Flush())
    assert [[x.cseq for x in b] for b in d.proposed.values()] == [[2, 3]]


def test_aborted_batch_goes_back_to_the_front_of_the_queue() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME), seq_inflight=1)
    d.step(0.0, sq.Forwarded(OTHER, 1, ((1, b"a"),)))
    d.step(0.0, sq.Forwarded(OTHER, 1, ((2, b"b"),)))  # waits: one batch in OAC at a time
    t1 = next(iter(d.m.inflight))
    out = d.step(1.0, sq.BatchAborted(t1))
    assert sq.Count("seq_batches_aborted") in out
    again = [e.entries for e in out if isinstance(e, sq.ProposeBatch)]
    assert [[x.cseq for x in b] for b in again] == [[1, 2]]
    assert d.step(1.0, sq.BatchAborted(TxId("zz", 1, 1))) == []  # not ours


def test_own_writes_go_straight_into_the_queue_when_we_are_the_sequencer() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME))
    out = d.step(0.0, sq.Submit("r1", b"w1"))
    assert sends(out) == []
    assert [[(x.origin, x.cseq) for x in b] for b in d.proposed.values()] == [[(ME, 1)]]


def test_a_host_that_left_drops_forwarded_writes() -> None:
    d = SeqDriver(FakeSeqHost(seq_of=ME, left=True))
    assert d.step(0.0, sq.Forwarded(OTHER, 1, ((1, b"a"),))) == [sq.Count("seq_dropped", 1)]


# ------------------------------------------------------------------------------------------------ state transfer


@dataclass
class FakeState:
    seq: int = 0
    genesis: str = "g"
    group_correct: bool = True
    recent: OrderedDict[TxId, int] = field(default_factory=OrderedDict)


@dataclass
class FakeXferHost:
    state: FakeState = field(default_factory=FakeState)
    member: bool = False
    target: tuple[str, int] = LEADER

    def is_member(self) -> bool:
        return self.member

    def request_target(self, txid: TxId) -> tuple[str, int]:
        return self.target


class XferDriver:
    """Carries out the effects as `MembershipNode._xfer` does; `applied` records (txid, direct)."""

    def __init__(self, host: FakeXferHost) -> None:
        self.host = host
        self.m = xf.StateTransfer(ME, host, catchup_timeout=2.0)
        self.applied: list[tuple[TxId, bool]] = []

    def step(self, now: float, inp: xf.XferInput) -> list[xf.XferEffect]:
        seen: list[xf.XferEffect] = []
        effects = self.m.step(now, inp)
        while effects:
            more = False
            for e in effects:
                seen.append(e)
                if isinstance(e, xf.ApplyTx):
                    st = self.host.state
                    st.seq += 1
                    st.recent[e.txid] = st.seq
                    self.applied.append((e.txid, e.direct))
                    seen += self.m.step(now, xf.Applied(e.txid, st.seq))
                    more = True
                elif isinstance(e, xf.Restore):
                    seq, gid, correct = GlobalState.peek(e.data)
                    self.host.state = FakeState(seq, gid, correct)
                    more = True
            effects = self.m.step(now, xf.Continue()) if more else []
        return seen


def snapshot(seq: int, genesis: str = "g", correct: bool = True) -> bytes:
    gs = GlobalState(("h1", "h2", "h3"), 1)
    gs.seq, gs.genesis, gs.group_correct = seq, genesis, correct
    return gs.snapshot()


def tx(n: int) -> TxId:
    return TxId("h1", 1, n)


def test_the_sponsors_stream_is_applied_in_order_state_only() -> None:
    d = XferDriver(FakeXferHost())
    assert d.step(0.0, xf.Forward(2, tx(2), b"b")) == []  # a gap: buffered
    d.step(0.0, xf.Forward(1, tx(1), b"a"))
    assert d.applied == [(tx(1), False), (tx(2), False)]
    d.step(0.0, xf.Forward(2, tx(2), b"b"))  # old news
    assert d.applied == [(tx(1), False), (tx(2), False)] and not d.m.fwd_buffer


def test_sponsor_snapshot_installs_then_drains_the_stream() -> None:
    d = XferDriver(FakeXferHost())
    d.step(0.0, xf.Forward(6, tx(6), b"f"))
    out = d.step(0.0, xf.Snapshot(5, snapshot(5), None, 0))
    assert isinstance(out[0], xf.Restore)
    assert d.host.state.seq == 6 and d.applied == [(tx(6), False)]
    # an older snapshot of the same group is not installed
    assert d.step(0.0, xf.Snapshot(3, snapshot(3), None, 0)) == []


def test_a_snapshot_that_does_not_decode_is_rejected() -> None:
    d = XferDriver(FakeXferHost())
    out = d.step(0.0, xf.Snapshot(1, b"\xff\xff\xff", None, 0))
    assert len(out) == 1 and isinstance(out[0], xf.Rejected)


def test_a_joiner_buffers_its_deliveries_requests_the_state_and_catches_up() -> None:
    host = FakeXferHost(state=FakeState(seq=2))
    d = XferDriver(host)
    out = d.step(0.0, xf.Delivered(tx(6), b"join", joining=True))
    assert out == [SetTimer(xf.CATCHUP_TIMER, 2.0)] and d.m.catching_up()
    d.step(0.5, xf.Delivered(tx(7), b"next", joining=False))  # buffered too: the queue is not empty
    out = d.step(2.0, xf.CatchupDue())
    assert out == [Send("h1", 1, StateRequest(tx(6))), Log("state_request", {"to": "h1", "tx": str(tx(6))}),
                   SetTimer(xf.CATCHUP_TIMER, 4.0)]
    out = d.step(2.1, xf.Snapshot(5, snapshot(5), tx(6), 6))
    assert d.applied == [(tx(6), True), (tx(7), True)] and host.state.seq == 7
    assert out[-2:] == [Log("caught_up", {"seq": 7}), xf.CaughtUp()]
    assert not d.m.catching_up()
    assert d.step(3.0, xf.CatchupDue()) == []  # caught up: the timer has nothing to do


def test_the_sponsors_stream_reaching_the_first_delivery_ends_the_catch_up() -> None:
    host = FakeXferHost(state=FakeState(seq=4))
    d = XferDriver(host)
    d.step(0.0, xf.Delivered(tx(6), b"join", joining=True))
    d.step(0.1, xf.Forward(5, tx(5), b"e"))
    assert d.applied == [(tx(5), False)]
    out = d.step(0.2, xf.Forward(6, tx(6), b"join"))  # the forwarded copy of what we delivered ourselves
    assert d.applied == [(tx(5), False), (tx(6), True)]
    assert out[-1] == xf.CaughtUp()


def test_a_member_answers_a_state_request_once_the_anchor_is_applied() -> None:
    host = FakeXferHost(member=True, state=FakeState(seq=3))
    d = XferDriver(host)
    assert d.step(0.0, xf.Request(OTHER, tx(4))) == []
    out = d.step(0.1, xf.Delivered(tx(4), b"d", joining=False))
    assert d.applied == [(tx(4), True)]
    assert xf.SendSnapshot(OTHER, tx(4), 4) in out
    assert d.step(0.2, xf.Request(OTHER, tx(4))) == [xf.SendSnapshot(OTHER, tx(4), 4)]  # already applied
    assert d.step(0.3, xf.Forward(9, tx(9), b"x")) == []  # a caught-up member ignores a sponsor's stream


def test_a_second_drain_while_one_waits_for_continue_is_refused() -> None:
    d = XferDriver(FakeXferHost())
    d.m.fwd_buffer[1] = (tx(1), b"a")
    out = d.m.step(0.0, xf.Forward(2, tx(2), b"b"))
    assert out == [xf.ApplyTx(tx(1), b"a", False)]
    with pytest.raises(RuntimeError):
        d.m.step(0.0, xf.Forward(3, tx(3), b"c"))


# ------------------------------------------------------------------------------------------------ formation


@dataclass
class FakeFormationHost:
    form: bool = True
    incs: dict[str, int] = field(default_factory=dict)
    suspected: set[tuple[str, int]] = field(default_factory=set)
    txids: int = 0

    def new_txid(self) -> TxId:
        self.txids += 1
        return TxId("h2", 1, self.txids)

    def may_form(self) -> bool:
        return self.form

    def peer_incarnation(self, name: str) -> int:
        return self.incs.get(name, 0)

    def is_suspected(self, name: str, inc: int) -> bool:
        return (name, inc) in self.suspected

    def address(self, name: str) -> str:
        return f"{name}:1"


CORE = ("h1", "h2", "h3")
FCFG = fm.FormationConfig(formation_timeout=5.0, formation_retry=1.0, discovery=0.5)


def formation(me: tuple[str, int], host: FakeFormationHost, c_h: int = 2) -> fm.Formation:
    return fm.Formation(me, f"{me[0]}:1", CORE, c_h, host, FCFG)


def test_each_role_arms_its_own_timer() -> None:
    assert formation(("h1", 1), FakeFormationHost()).step(1.0, fm.Start()) == [
        SetTimer(fm.DISCOVERY_TIMER, 1.5)]  # l. 41: the first core process
    assert formation(("h2", 1), FakeFormationHost()).step(1.0, fm.Start()) == [
        SetTimer(fm.FORMATION_TIMER, 6.0)]  # ll. 44-45: the core head
    assert formation(("h3", 1), FakeFormationHost()).step(1.0, fm.Start()) == []  # outside the core head


def test_the_first_core_process_forms_a_group_of_one_unless_a_group_is_known() -> None:
    host = FakeFormationHost()
    m = formation(("h1", 1), host)
    assert m.step(0.5, fm.DiscoveryDue()) == [fm.FormGroupOfOne()]
    host.form = False
    assert m.step(0.5, fm.DiscoveryDue()) == []


def test_fallback_proposes_the_unsuspected_core_head_once_at_a_time_and_retries_after_an_abort() -> None:
    host = FakeFormationHost(incs={"h1": 3, "h3": 1}, suspected={("h1", 3)})
    m = formation(("h2", 1), host, c_h=3)
    out = m.step(5.0, fm.FormationDue())
    t = TxId("h2", 1, 1)
    assert out == [fm.ProposeFallback(t, (Member("h2", 1, "h2:1"), Member("h3", 1, "h3:1"))),  # h1 suspected (l. 47)
                   Log("formation_fallback", {"tx": str(t), "members": ["h2", "h3"]})]
    assert m.step(5.5, fm.FormationDue()) == []  # l. 49: wait until decided
    assert m.step(5.6, fm.Aborted(TxId("h3", 1, 9), False)) == []  # not ours
    assert m.step(5.7, fm.Aborted(t, False)) == [SetTimer(fm.FORMATION_TIMER, 6.7)]  # l. 46: repeat
    assert m.txid is None
    (again, _log) = m.step(6.7, fm.FormationDue())
    assert isinstance(again, fm.ProposeFallback) and again.txid == TxId("h2", 1, 2) == m.txid
    assert m.step(7.0, fm.Delivered(TxId("h2", 1, 2))) == [] and m.txid is None
    m.txid = TxId("h2", 1, 3)
    assert m.step(7.5, fm.Aborted(TxId("h2", 1, 3), True)) == []  # aborted, but a group exists: no retry


def test_formation_vote_is_yes_only_without_a_group_and_for_our_own_list() -> None:
    host = FakeFormationHost(incs={"h1": 1})
    m = formation(("h2", 1), host)
    mine = TxFormation(("h1", 1), (Member("h1", 1, "h1:1"), Member("h2", 1, "h2:1")))
    assert m.vote(mine, has_group=False)
    assert not m.vote(mine, has_group=True)  # ll. 160-161
    host.suspected.add(("h1", 1))
    assert not m.vote(mine, has_group=False)  # ll. 162-163: our list is [h2] now


def test_a_joiner_that_installs_an_answer_holding_a_lock_inherits_it() -> None:
    """The answer skips the joiner's own deliveries it covers, among them the remove that locked the group: the
    lock the answering member holds comes with it (`InheritLock`), after the state is installed."""
    host = FakeXferHost(state=FakeState(seq=2))
    d = XferDriver(host)
    d.step(0.0, xf.Delivered(tx(6), b"join", joining=True))
    out = d.step(2.1, xf.Snapshot(8, snapshot(8), tx(6), 6, ("h2.1.3", ("h2", 1))))
    kinds = [type(e).__name__ for e in out]
    assert kinds.index("Restore") < kinds.index("InheritLock")
    assert xf.InheritLock("h2.1.3", ("h2", 1)) in out
    # an answer that is not installed (not ahead of our state) hands on no lock
    host = FakeXferHost(state=FakeState(seq=9))
    d = XferDriver(host)
    d.step(0.0, xf.Delivered(tx(10), b"join", joining=True))
    out = d.step(2.1, xf.Snapshot(8, snapshot(8), tx(10), 10, ("h2.1.3", ("h2", 1))))
    assert not any(isinstance(e, xf.InheritLock) for e in out)
