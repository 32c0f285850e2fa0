"""The membership sub-machines of `MembershipNode`, each driven alone with a fake host:
`Join` (Alg. 3 ll. 35-39, 50-75), `MembershipUpdate` (ll. 76-157, 166-179), `GroupWrites` (ll. 127-132,
144-145, 153-155) and `GroupLeave` (ll. 14-21). No `HostCore`, no runtime, no simulator: a `GlobalState`
with a member list, a fake for the read-only host protocol, and the effects checked as returned.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from haa.core.effects import Log, Reincarnate, Send, SetTimer
from haa.core.membership import groupleave as gl
from haa.core.membership import groupwrites as gw
from haa.core.membership import join as jn
from haa.core.membership import update as up
from haa.core.membership.globalstate import GlobalState, TxMembership, TxRemove, encode_tx
from haa.core.membership.groupeffects import Left, WriteDone
from haa.core.messages import Apply, Connections, Introduce, Leave, Locked, Member, Sponsor, TxId

H1, H2, H3, H4 = ("h1", 1), ("h2", 1), ("h3", 1), ("h4", 1)
CORE = ("h1", "h2", "h3")


def group(*procs: tuple[str, int]) -> GlobalState:
    """A global state whose (correct) group is `procs`, front first."""
    st = GlobalState(CORE, 1)
    st.apply(TxId(procs[0][0], 1, 1), encode_tx(TxMembership("", procs[0], tuple(Member(n, i, n) for n, i in procs))))
    return st


@dataclass
class FakeHost:
    """JoinHost, UpdateHost, WritesHost and LeaveHost over a plain GlobalState."""

    me: tuple[str, int]
    state: GlobalState
    suspects: set[tuple[str, int]] = field(default_factory=set)
    dead: set[tuple[str, int]] = field(default_factory=set)
    leaving: bool = False
    left: bool = False
    join: jn.Join | None = None
    locked: bool = False
    catching: bool = False
    decided: bool = True
    txids: int = 0

    def is_member(self) -> bool:
        return self.state.is_member(self.me)

    def new_txid(self) -> TxId:
        self.txids += 1
        return TxId(self.me[0], self.me[1], self.txids)

    def is_leaving(self) -> bool:
        return self.leaving

    def has_left(self) -> bool:
        return self.left

    def suspected(self, p: tuple[str, int]) -> bool:
        return p != self.me and p in self.suspects

    def known_dead(self, p: tuple[str, int]) -> bool:
        return p in self.dead

    def superseded(self, p: tuple[str, int]) -> bool:
        return False

    def leader_now(self) -> bool:
        lead = self.state.leader()
        return lead is not None and lead.proc == self.me

    def applicants(self) -> Mapping[tuple[str, int], str]:
        return self.join.join_list if self.join else {}

    def sponsoring(self, a: tuple[str, int]) -> bool:
        return self.join is not None and a in self.join.sponsees

    def connections_of(self, a: tuple[str, int]) -> set[tuple[str, int]]:
        return self.join.conns_of.get(a, set()) if self.join else set()

    def all_decided(self) -> bool:
        return self.decided

    def group_formed(self) -> bool:
        return self.state.group_correct

    def is_locked(self) -> bool:
        return self.locked

    def catching_up(self) -> bool:
        return self.catching

    def suspects_member(self) -> bool:
        return any(self.suspected(m.proc) for m in self.state.members)

    def peer_list(self) -> list[tuple[str, int]]:
        return [H1, H2, H3]


def sends(effects: list, kind: type) -> list[tuple[str, int]]:
    return [(e.dst, e.dst_inc) for e in effects if isinstance(e, Send) and isinstance(e.msg, kind)]


# ------------------------------------------------------------------------------------------------ Join


def test_an_applicant_applies_to_every_core_process_and_reapplies_until_sponsored() -> None:
    host = FakeHost(H4, GlobalState(CORE, 1))
    j = jn.Join(H4, "h4", CORE, ["h9"], host, reapply=2.0)
    out = j.step(0.0, jn.Start())
    assert [e.name for e in out if isinstance(e, jn.ToHost) and isinstance(e.msg, Apply)] == ["h1", "h2", "h3", "h9"]
    assert [e.name for e in out if isinstance(e, jn.Link)] == ["h1", "h2", "h3", "h9"]
    assert any(isinstance(e, SetTimer) and e.at == 2.0 for e in out)
    j.step(0.5, jn.Heard(H1, Sponsor()))
    assert j.sponsor == H1
    again = j.step(2.0, jn.ReapplyDue())
    assert not [e for e in again if isinstance(e, jn.ToHost)]  # sponsored by an unsuspected leader: no apply
    host.suspects.add(H1)
    again = j.step(4.0, jn.ReapplyDue())
    assert len([e for e in again if isinstance(e, jn.ToHost)]) == 4  # its sponsor is suspected: apply again


def test_the_leader_introduces_and_sponsors_an_applicant_and_tells_it_again_when_it_reapplies() -> None:
    host = FakeHost(H1, group(H1, H2, H3))
    j = jn.Join(H1, "h1", CORE, [], host, reapply=2.0)
    host.join = j
    out = j.step(0.0, jn.Heard(H4, Apply("h4")))
    assert j.join_list == {H4: "h4"} and H4 in j.sponsees  # ll. 51, 58
    assert sends(out, Introduce) == [H4, H2, H3]  # l. 55 to a, l. 56 to every member
    assert sends(out, Sponsor) == [H4] and jn.SendState(H4) in out  # ll. 58-60
    assert isinstance(out[-1], jn.RunUpdate)
    out = j.step(1.0, jn.Heard(H4, Apply("h4")))
    assert sends(out, Sponsor) == [H4] and jn.SendState(H4) not in out  # repeated apply: Sponsor again only
    assert sends(out, Introduce) == [H4]  # the same view: introduced to the others once


def test_a_non_leader_introduces_but_does_not_sponsor() -> None:
    host = FakeHost(H2, group(H1, H2, H3))
    j = jn.Join(H2, "h2", CORE, [], host, reapply=2.0)
    out = j.step(0.0, jn.Heard(H4, Apply("h4")))
    assert not sends(out, Sponsor) and not j.sponsees and H4 in j.join_list


def test_an_applicant_reports_its_two_way_connections_to_its_sponsor() -> None:
    host = FakeHost(H4, GlobalState(CORE, 1))
    j = jn.Join(H4, "h4", CORE, [], host, reapply=2.0)
    j.step(0.0, jn.Start())
    j.step(0.1, jn.Heard(H1, Sponsor()))
    out = j.step(0.2, jn.Heard(H2, Introduce("h2", 1, "h2", "")))  # h2 introduces itself (ll. 63-68)
    assert H2 in j.conn_from and "h2" in j.conn_to
    conns = [e.msg.peers for e in out if isinstance(e, Send) and isinstance(e.msg, Connections)]
    assert conns == [(H2,)] and sends(out, Connections) == [H1]  # ll. 69-70: to the sponsor


def test_a_provisional_group_that_hears_of_a_correct_group_is_abandoned() -> None:
    st = GlobalState(CORE, 1)
    st.apply(TxId("h1", 1, 1), encode_tx(TxMembership("k", H1, (Member("h1", 1, "h1"),))))  # provisional
    assert not st.group_correct
    host = FakeHost(H1, st)
    j = jn.Join(H1, "h1", CORE, [], host, reapply=2.0)
    out = j.step(0.0, jn.Heard(H2, Introduce("h2", 1, "h2", "other-group")))
    assert jn.Abandon("other-group") in out and j.group_seen == "other-group"


def test_admitted_and_removed_hosts_leave_the_join_list() -> None:
    host = FakeHost(H1, group(H1, H2, H3))
    j = jn.Join(H1, "h1", CORE, [], host, reapply=2.0)
    j.step(0.0, jn.Heard(H4, Apply("h4")))
    j.step(0.0, jn.Heard(("h5", 1), Apply("h5")))
    j.step(1.0, jn.Admitted(frozenset({H4}), mine=True))
    assert H4 not in j.join_list and H4 not in j.sponsees and ("h5", 1) in j.join_list
    out = j.step(2.0, jn.ViewChanged((Member("h1", 1, "h1"), Member("h2", 1, "h2")), (Member("h5", 1, "h5"),)))
    assert jn.MarkRemoved("h5", 1) in out and ("h5", 1) not in j.join_list
    assert [e.name for e in out if isinstance(e, jn.Link)] == ["h2"]  # every member but itself


# ------------------------------------------------------------------------------------------------ MembershipUpdate


class UpdateDriver:
    """Carries out the machine's `ProposeTx` as the node does (the ids come from the host: 1, 2, ...)."""

    def __init__(self, host: FakeHost) -> None:
        self.m = up.MembershipUpdate(host.me, 1, CORE, host, retry_backoff=0.05)
        self.proposed: list[tuple[object, tuple]] = []
        self.effects: list = []

    def step(self, now: float, inp: up.UpdateInput) -> list:
        out = []
        for e in self.m.step(now, inp):
            out.append(e)
            if isinstance(e, up.ProposeTx):
                assert e.txid == TxId(*self.m.me, len(self.proposed) + 1)  # reserved from the host, in order
                self.proposed.append((e.tx, e.participants))
            elif isinstance(e, up.RunUpdate):
                out += self.step(now, up.Run())
        self.effects += out
        return out


def test_the_leader_removes_a_member_everyone_suspects_without_a_lock() -> None:
    host = FakeHost(H1, group(H1, H2, H3), suspects={H3})
    d = UpdateDriver(host)
    d.step(0.0, up.Run())
    (tx, parts), = d.proposed
    assert tx == TxRemove("", H1, (H3,)) and parts == (H1, H2)  # ll. 95-102: no one joins or leaves: no key
    assert d.m.updating and d.m.attempt is not None and d.m.attempt.stage == "remove"
    assert d.m.vote(TxId("h1", 1, 1), tx)  # ll. 110-116: we suspect h3 too


def test_a_non_leader_and_a_removal_without_quorum_propose_nothing() -> None:
    d = UpdateDriver(FakeHost(H2, group(H1, H2, H3), suspects={H3}))
    d.step(0.0, up.Run())
    assert not d.proposed  # l. 79: h1 is the leader
    host = FakeHost(H1, group(H1, H2, H3, H4), suspects={H3, H4, H2})
    d = UpdateDriver(host)
    d.step(0.0, up.Run())
    assert not d.proposed and any(isinstance(e, Log) and e.event == "removal_waits_for_quorum" for e in d.effects)


def test_votes_follow_weak_validity_and_the_accepted_leader() -> None:
    m = up.MembershipUpdate(H2, 1, CORE, FakeHost(H2, group(H1, H2, H3)), 0.05)
    assert not m.vote(TxId("h1", 1, 1), TxRemove("", H1, (H3,)))  # we do not suspect h3 (l. 113)
    m = up.MembershipUpdate(H2, 1, CORE, FakeHost(H2, group(H1, H2, H3), suspects={H3}), 0.05)
    assert not m.vote(TxId("h3", 1, 1), TxRemove("", H3, ()))  # h3 is not the accepted leader (l. 111)
    assert m.vote(TxId("h1", 1, 2), TxRemove("", H1, (H3,)))


def test_a_join_locks_waits_for_every_lock_then_proposes_the_new_list() -> None:
    host = FakeHost(H1, group(H1, H2, H3))
    j = jn.Join(H1, "h1", CORE, [], host, reapply=2.0)
    host.join = j
    j.step(0.0, jn.Heard(H4, Apply("h4")))
    j.step(0.1, jn.Heard(H4, Connections((H1, H2, H3))))
    d = UpdateDriver(host)
    d.step(0.2, up.Run())
    (tx, parts), = d.proposed
    assert isinstance(tx, TxRemove) and tx.key and parts == (H1, H2, H3)  # ll. 98-102: lock with a new key
    d.step(0.3, up.GroupTxApplied(TxId("h1", 1, 1), tx, False, True, False))  # l. 127: locked here too
    assert d.m.locked == tx.key and d.m.attempt is not None and d.m.attempt.stage == "locking"
    d.step(0.3, up.Poll())
    assert len(d.proposed) == 1  # l. 103: h2, h3 have not acknowledged
    d.step(0.4, up.LockedMsg(H2, tx.key))
    d.step(0.4, up.LockedMsg(H3, tx.key))
    host.decided = False
    d.step(0.4, up.Poll())
    assert len(d.proposed) == 1  # ... and an OAC is undecided
    host.decided = True
    d.step(0.5, up.Poll())
    mtx, mparts = d.proposed[1]
    assert isinstance(mtx, TxMembership) and [m.name for m in mtx.members] == ["h1", "h2", "h3", "h4"]
    assert mparts == (H1, H2, H3, H4)  # l. 106
    out = d.step(0.6, up.GroupTxApplied(TxId("h1", 1, 2), mtx, False, True, False))
    assert d.m.locked is None and not d.m.updating and d.m.attempt is None  # ll. 144-150
    assert up.Admit(frozenset({H1, H2, H3, H4}), True) in out and up.ProposeHeld() in out


def test_an_aborted_membership_transaction_unlocks_and_retries_later() -> None:
    host = FakeHost(H2, group(H1, H2, H3))
    d = UpdateDriver(host)
    txid = TxId("h1", 1, 7)
    assert d.m.vote(txid, TxMembership("k1", H1, ()))
    d.m.locked = "k1"
    out = d.step(1.0, up.TxAborted(txid))
    assert d.m.locked is None and up.Unlocked() in out  # ll. 152-155 on a participant


def test_a_former_leaders_stale_transaction_retries_our_own_attempt() -> None:
    host = FakeHost(H1, group(H1, H2, H3), suspects={H3})
    d = UpdateDriver(host)
    d.step(0.0, up.Run())
    out = d.step(0.5, up.GroupTxApplied(TxId("h1", 1, 1), None, True, True, False))
    assert d.m.attempt is None and any(isinstance(e, SetTimer) and e.at == 0.55 for e in out)


# ------------------------------------------------------------------------------------------------ GroupWrites


def test_writes_are_held_while_locked_and_acknowledged_once_committed() -> None:
    host = FakeHost(H2, group(H1, H2, H3), locked=True)
    w = gw.GroupWrites(host, max_attempts=2)
    assert w.step(0.0, gw.Request("r1", b"agent")) == [] and len(w.held) == 1  # l. 129
    host.locked = False
    assert w.step(1.0, gw.Release()) == [gw.ProposeWrite(TxId("h2", 1, 1), b"agent")]  # ll. 132, 145, 155
    assert w.step(2.0, gw.Aborted(TxId("h2", 1, 1))) == [gw.ProposeWrite(TxId("h2", 1, 2), b"agent")]  # re-proposed
    out = w.step(3.0, gw.Aborted(TxId("h2", 1, 2)))
    assert isinstance(out[0], WriteDone) and not out[0].ok and "gave up after 2 attempts" in out[0].reason
    assert w.step(4.0, gw.Request("r3", b"agent")) == [gw.ProposeWrite(TxId("h2", 1, 3), b"agent")]
    (done,) = w.step(5.0, gw.Committed(TxId("h2", 1, 3), 9, "", None))
    assert done.ok and done.seq == 9 and done.req == "r3" and not w.writes


def test_an_abort_while_suspecting_a_member_holds_the_write_uncounted() -> None:
    """OAC commits only if no participant is suspected (AC-Non-Triviality): an abort while this host suspects a
    member is not counted against `max_attempts`; the write waits for a Release (the suspicion ended, the view
    changed) instead of being re-proposed at once (`haactl verify executive --hosts 7` seeds 1263, 1572, 1853:
    50 immediate re-proposals went in under a second of a delay spike, and an agent's spawn failed)."""
    host = FakeHost(H2, group(H1, H2, H3), suspects={H3})
    w = gw.GroupWrites(host, max_attempts=1)
    assert w.step(0.0, gw.Request("r", b"agent")) == [gw.ProposeWrite(TxId("h2", 1, 1), b"agent")]
    for i in range(1, 4):  # aborted again and again while h3 is suspected: held, never given up
        assert w.step(float(i), gw.Aborted(TxId("h2", 1, i))) == [] and len(w.held) == 1
        assert w.step(float(i), gw.Release()) == [gw.ProposeWrite(TxId("h2", 1, i + 1), b"agent")]
    host.suspects.clear()  # trusted again (l. 26): an abort now counts, and the one attempt is used up
    out = w.step(5.0, gw.Aborted(TxId("h2", 1, 4)))
    assert isinstance(out[0], WriteDone) and not out[0].ok and "gave up after 1 attempts" in out[0].reason


def test_a_write_is_refused_outside_a_formed_group() -> None:
    w = gw.GroupWrites(FakeHost(H4, group(H1, H2, H3)), max_attempts=5)
    (done,) = w.step(0.0, gw.Request("r", b"x"))
    assert not done.ok and done.reason == "not a member of the group"


# ------------------------------------------------------------------------------------------------ GroupLeave


def test_a_member_asks_every_member_and_stops_once_removed() -> None:
    g = gl.GroupLeave(H2, FakeHost(H2, group(H1, H2, H3)))
    out = g.step(0.0, gl.LeaveCalled())
    assert g.leaving and not g.left
    assert sends(out, Leave) == [H1, H3] and gl.LeaveSelf() in out  # l. 15
    assert g.step(0.1, gl.LeaveCalled()) == []  # once
    out = g.step(1.0, gl.RemovedHere())
    assert g.left and Left() in out and not [e for e in out if isinstance(e, Reincarnate)]  # l. 17


def test_a_member_removed_without_leaving_restarts_and_an_applicant_withdraws_at_once() -> None:
    g = gl.GroupLeave(H2, FakeHost(H2, group(H1, H2, H3)))
    out = g.step(1.0, gl.RemovedHere())
    assert g.left and Reincarnate(by="h2") in out and Left() not in out
    g = gl.GroupLeave(H4, FakeHost(H4, group(H1, H2, H3)))
    out = g.step(0.0, gl.LeaveCalled())
    assert g.left and Left() in out and sends(out, Leave) == [H1, H2, H3]  # to every host it knows


# ------------------------------------------------------------------------------------------------ lock and votes


def test_a_new_member_that_installed_a_locked_state_takes_the_lock_and_acknowledges_it() -> None:
    """A joiner whose state came from a member's answer skipped the remove that locked the group: it takes the
    lock from the answer and acknowledges it to the leader (ll. 127-130), or the leader waits at l. 103."""
    d = UpdateDriver(FakeHost(H4, group(H1, H2, H3, H4)))
    out = d.step(1.0, up.LockInherited("h2.1.3", H2))
    assert d.m.locked == "h2.1.3" and d.m.lock() == ("h2.1.3", H2)
    assert sends(out, Locked) == [H2]


def test_a_lock_whose_membership_transaction_aborted_here_is_not_taken_from_a_later_answer() -> None:
    d = UpdateDriver(FakeHost(H4, group(H1, H2, H3, H4)))
    txid = TxId("h2", 1, 4)
    assert d.m.vote(txid, TxMembership("h2.1.3", H2, ()), frozenset({H1, H2, H3, H4}))
    d.step(1.0, up.TxAborted(txid))  # ll. 152-155: released before the answer arrived
    out = d.step(1.1, up.LockInherited("h2.1.3", H2))
    assert d.m.locked is None and not sends(out, Locked)


def test_a_group_transaction_that_leaves_out_a_member_admitted_here_is_voted_down() -> None:
    """OAC orders a transaction only among its participants: one ordered after the admission of a member it
    leaves out would never reach that member, whose global sequence would fall one behind (HM-Agreement)."""
    host = FakeHost(H2, group(H1, H2, H3, H4), suspects={H3, H4})
    d = UpdateDriver(host)
    members = tuple(Member(n, i, n) for n, i in (H1, H2, H3, H4))
    d.step(0.5, up.GroupTxApplied(TxId("h1", 1, 2), TxMembership("k", H1, members), False, True, False, (H4,)))
    remove = TxRemove("", H1, (H3,))
    assert not d.m.vote(TxId("h1", 1, 3), remove, frozenset({H1, H2}))  # proposed before h4 was admitted
    assert d.m.vote(TxId("h1", 1, 4), remove, frozenset({H1, H2, H4}))
    # a transaction that removes the new member itself may leave it out
    assert d.m.vote(TxId("h1", 1, 5), TxRemove("", H1, (H3, H4)), frozenset({H1, H2}))


def test_a_remove_and_a_membership_transaction_that_admits_a_member_the_remove_leaves_out_cannot_both_pass() -> None:
    """A member that suspects the leader proposes its removal under the old list while the leader admits a new
    member: the common participants vote against whichever of the two they see second."""
    members = tuple(Member(n, i, n) for n, i in (H1, H2, H3, H4))
    admit, remove = TxMembership("k", H1, members), TxRemove("", H2, (H1,))
    m = up.MembershipUpdate(H3, 1, CORE, FakeHost(H3, group(H1, H2, H3), suspects={H1}), 0.05)
    assert m.vote(TxId("h1", 1, 9), admit, frozenset({H1, H2, H3, H4}))
    assert not m.vote(TxId("h2", 1, 1), remove, frozenset({H2, H3}))
    m = up.MembershipUpdate(H3, 1, CORE, FakeHost(H3, group(H1, H2, H3), suspects={H1}), 0.05)
    assert m.vote(TxId("h2", 1, 1), remove, frozenset({H2, H3}))
    assert not m.vote(TxId("h1", 1, 9), admit, frozenset({H1, H2, H3, H4}))
    m.step(1.0, up.TxDelivered(TxId("h2", 1, 1)))  # once the remove is delivered, nothing is in flight
    assert m.vote(TxId("h1", 1, 10), admit, frozenset({H1, H2, H3, H4}))
