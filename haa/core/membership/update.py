"""updateMembership: the leader's membership changes and everyone's votes (thesis Alg. 3 ll. 76-157).

Alg. 3 (thesis L2358-2565, described at L690-712) changes the member list in two OACs: the leader — the
highest-ranked member it does not suspect (l. 79) — commits OAC(remove) of the members that every remaining
member suspects (ll. 95-102, HM-Weak-Validity: each participant votes yes only for members it suspects too,
ll. 110-116); when members join or leave, that transaction also locks the global state under a new key
(ll. 98-101, 127-130), the leader waits until every active member acknowledged the lock (or is suspected) and
every OAC it knows is decided (l. 103), then commits OAC(membership) with the new list (ll. 104-106), which
unlocks (ll. 144-145); a failed attempt is repeated (ll. 107-109, 134-135, 152-157).

`MembershipUpdate` is this part of one host incarnation as a sans-I/O machine with its own state — the
attempt in progress (ll. 95-109), updating_p (l. 7), leaveList_p (l. 5), locked_p (l. 6), the group
transactions in progress here (l. 77), the lock keys of membership transactions voted on (l. 153) — and HAA's
completions (docs/membership.md): a removal must leave a quorum of the members (`_quorum`), a failed attempt
is retried after `retry_backoff` instead of at once, a former leader's remove or membership transaction
ordered after the change that replaced it is a no-op that unlocks (`Stale`), and every participant, not only
the proposer, unlocks when OAC(membership) aborts.

Interface: `step(now, input) -> list[UpdateEffect]` over the closed unions `UpdateInput` and `UpdateEffect`,
plus the query `vote(txid, tx)` (the OAC evaluate hook of ll. 110-116; it records the transaction as a
group transaction in progress). A proposal is the effect `ProposeTx`, with the transaction id the machine
reserved (`new_txid`): the node proposes it at once. What the machine reads of its node — the global state,
suspicion, the applicants of `haa.core.membership.join` and whether every OAC is decided — comes through `UpdateHost`.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal, Protocol, assert_never

from haa.core.effects import Log, Send, SetTimer
from haa.core.membership.globalstate import GlobalState, GroupTx, TxFormation, TxMembership, TxRemove
from haa.core.membership.groupeffects import NodeTimer
from haa.core.membership.join import RunUpdate, SponsorAll
from haa.core.messages import Locked, Member, TxId

Proc = tuple[str, int]

RETRY_TIMER = NodeTimer("retry")
#: how many lock keys released by an aborted membership transaction a host remembers (`LockInherited`)
RELEASED_KEEP = 64


class UpdateHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    @property
    def state(self) -> GlobalState:
        """The group's global state as applied here."""

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def has_left(self) -> bool:
        """This incarnation is out of the group for good (left, removed, or restarting)."""

    def suspected(self, p: Proc) -> bool:
        """◇S_p suspects incarnation `p` (never this host itself)."""

    def superseded(self, p: Proc) -> bool:
        """A newer incarnation of p's host has been heard of: p is not running."""

    def leader_now(self) -> bool:
        """This host is front(memberList_p)."""

    def applicants(self) -> Mapping[Proc, str]:
        """joinList_p (l. 2): applicant -> address, in application order."""

    def sponsoring(self, a: Proc) -> bool:
        """This host sponsors applicant `a` (sponsees_p, l. 11)."""

    def connections_of(self, a: Proc) -> set[Proc]:
        """The latest two-way connection list applicant `a` reported (ll. 74-75)."""

    def all_decided(self) -> bool:
        """Every OAC transaction this host knows with content is decided (l. 103)."""

    def new_txid(self) -> TxId:
        """A fresh OAC transaction id of this host incarnation for a proposal (the one call that changes the node:
        it reserves the id, so the machine knows its transaction before it is proposed)."""


@dataclass(slots=True)
class Attempt:
    """One run of updateMembership's commit part (ll. 95-109)."""

    txid: TxId
    key: str
    active: list[Proc]
    accept: list[Member]
    stage: str  # "remove" | "locking" | "membership"
    locks: set[Proc] = field(default_factory=set)
    membership_txid: TxId | None = None


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Run:
    """updateMembership() (ll. 76-102): propose a change if this host is the leader and one is due."""


@dataclass(frozen=True, slots=True)
class RetryDue:
    """`RETRY_TIMER` fired (l. 109 after `retry_backoff`)."""


@dataclass(frozen=True, slots=True)
class SuspicionChanged:
    """◇S_p changed its mind about `proc` (ll. 22-31: removeList_p is computed on demand)."""

    proc: Proc


@dataclass(frozen=True, slots=True)
class Poll:
    """Re-check the waits of l. 103 (the node steps this after every input)."""


@dataclass(frozen=True, slots=True)
class LockedMsg:
    """`src` acknowledged the lock `key` (l. 130)."""

    src: Proc
    key: str


@dataclass(frozen=True, slots=True)
class LockInherited:
    """This new member installed a state, answered by a member holding the lock `key` that `by` took (l. 127),
    past the remove that took it: lock and acknowledge as applying the remove would have (ll. 127-130)."""

    key: str
    by: Proc


@dataclass(frozen=True, slots=True)
class LeaveAsked:
    """Member or applicant `proc` asked to leave (ll. 18-21)."""

    proc: Proc


@dataclass(frozen=True, slots=True)
class GroupOfOne:
    """ll. 42-43: the first core process forms a provisional group of one, locked with a new key."""

    member: Member


@dataclass(frozen=True, slots=True)
class TxAborted:
    """OAC aborted `txid` (ll. 134-135, 152-157)."""

    txid: TxId


@dataclass(frozen=True, slots=True)
class TxDelivered:
    """OAC delivered `txid` (it is no longer in progress)."""

    txid: TxId


@dataclass(frozen=True, slots=True)
class GroupTxApplied:
    """A group transaction `tx` was applied here in total order (ll. 117-157, 166-179): OAC(remove),
    OAC(membership) or OAC(formationFallback); `stale`: a former leader's, applied as a no-op; `was_member` and
    `leaving`: this host before it."""

    txid: TxId
    tx: GroupTx | None
    stale: bool
    was_member: bool
    leaving: bool
    #: the members it added to the list
    added: tuple[Proc, ...] = ()


UpdateInput = (
    Run | RetryDue | SuspicionChanged | Poll | LockedMsg | LockInherited | LeaveAsked | GroupOfOne | TxAborted
    | TxDelivered | GroupTxApplied
)


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class ProposeTx:
    """Propose `tx` by OAC as `txid` to exactly `participants`."""

    txid: TxId
    tx: GroupTx
    participants: tuple[Proc, ...]


@dataclass(frozen=True, slots=True)
class ProposeHeld:
    """The global state is unlocked: propose the changes held while it was locked (ll. 132, 145, 155)."""


@dataclass(frozen=True, slots=True)
class Unlocked:
    """The lock was released outside a committed change (ll. 152-155): propose what was held and flush the
    sequencer's queue."""


@dataclass(frozen=True, slots=True)
class Removed:
    """This incarnation is no longer a member (l. 17, or removed: it restarts and applies)."""


@dataclass(frozen=True, slots=True)
class Withdrawn:
    """Applicant `proc` left before it joined: drop its application (`haa.core.membership.join.Withdraw`)."""

    proc: Proc


@dataclass(frozen=True, slots=True)
class Admit:
    """A committed list holds `procs`: they are no applicants any more (`haa.core.membership.join.Admitted`)."""

    procs: frozenset[Proc]
    mine: bool


@dataclass(frozen=True, slots=True)
class NowMember:
    """This host joined: it has no sponsor any more (`haa.core.membership.join.Joined`)."""


UpdateEffect = (
    ProposeTx | ProposeHeld | Unlocked | Removed | Withdrawn | Admit | NowMember | SponsorAll | RunUpdate | Send
    | SetTimer | Log
)


@dataclass(slots=True)
class _Pending:
    """What a `ProposeTx` is: the attempt it belongs to, what to log."""

    what: Literal["remove", "membership", "group_of_one"]
    attempt: Attempt | None
    log: dict[str, object]
    members: list[Member]


# ------------------------------------------------------------------------------------------------ machine


class MembershipUpdate:
    """The membership-update part of one host incarnation (see the module docstring)."""

    def __init__(self, me: Proc, c_f: int, core_names: tuple[str, ...], host: UpdateHost,
                 retry_backoff: float) -> None:
        self.me = me
        self.c_f = c_f
        self.core_names = core_names
        self.host = host
        self.retry_backoff = retry_backoff
        self.leave_list: set[Proc] = set()  # l. 5
        self.locked: str | None = None  # l. 6
        self.locked_by: Proc | None = None  # who took the lock (the proposer of its remove, l. 102)
        #: lock keys of membership transactions that aborted here (ll. 152-155), the last `RELEASED_KEEP`
        self.released: dict[str, None] = {}
        self.updating = False  # l. 7
        self.attempt: Attempt | None = None
        self.group_txs: set[TxId] = set()  # remove / membership transactions in progress here (l. 77)
        self.lock_keys: dict[TxId, str] = {}  # membership transactions we voted on -> the lock they release
        #: group transactions voted yes here, not yet delivered or aborted: (their participants, the members
        #: they add); and the members this host saw added by a membership transaction (`_excludes_new_member`)
        self.voted: dict[TxId, tuple[frozenset[Proc], frozenset[Proc]]] = {}
        self.admitted: set[Proc] = set()
        self.key_seq = 0
        self._out: list[UpdateEffect] = []
        self._now = 0.0

    def step(self, now: float, inp: UpdateInput) -> list[UpdateEffect]:
        self._now = now
        self._out = []
        match inp:
            case Run():
                self._update()
            case RetryDue():
                if self.attempt is None:
                    self.updating = False
                    self._update()
            case SuspicionChanged(p):
                if self.host.state.is_member(p) or p in self.host.applicants():
                    self._update()
            case Poll():
                self._poll()
            case LockedMsg(src, key):
                self._on_locked(src, key)
            case LockInherited(key, by):
                if key not in self.released and self.host.is_member():
                    self._lock(key, by)
            case LeaveAsked(p):  # ll. 18-21
                st = self.host.state
                if st.is_member(p) or p in self.host.applicants():
                    if not st.is_member(p):  # an applicant that leaves also withdraws its application (the
                        self._out.append(Withdrawn(p))  # pseudo-code keeps it, and would accept a host gone)
                    self.leave_list.add(p)
                    self._out.append(RunUpdate())
            case GroupOfOne(member):
                key = self._new_key()
                self._set_lock(key, self.me)  # l. 42
                self._propose(TxMembership(key, self.me, (member,)), (self.me,), _Pending("group_of_one", None, {}, []))
            case TxAborted(txid):
                self._aborted(txid)
            case TxDelivered(txid):
                self.group_txs.discard(txid)
                self.lock_keys.pop(txid, None)
                self.voted.pop(txid, None)
            case GroupTxApplied(txid, _, True, _, _):
                self._on_stale(txid)
            case GroupTxApplied(_, TxRemove() as tx, _, was_member, _):
                if was_member:
                    self._on_remove_committed(tx)
            case GroupTxApplied(txid, TxMembership() as tx, _, was_member, leaving, added):
                self.admitted = (self.admitted | set(added)) & {m.proc for m in tx.members}
                self._out.append(Admit(frozenset(m.proc for m in tx.members), tx.proposer == self.me))
                self._on_membership_committed(txid, tx, was_member, leaving)
            case GroupTxApplied(_, TxFormation() as tx, _, _, _):  # ll. 166-179 (the state part is GlobalState's)
                procs = frozenset(m.proc for m in tx.members)
                self._out.append(Admit(procs, False))  # l. 168
                self.leave_list &= procs  # l. 171
                if self.host.leader_now():  # ll. 172-177
                    self._out.append(SponsorAll())
                self._out.append(RunUpdate())  # l. 179
            case GroupTxApplied():
                pass
            case _:
                assert_never(inp)
        return self._out

    def vote(self, txid: TxId, tx: TxRemove | TxMembership, participants: frozenset[Proc] = frozenset()) -> bool:
        """The OAC evaluate hook for group transactions (ll. 110-116; a membership list is always accepted),
        with HAA's rule that no group transaction may be ordered after the admission of a member it leaves out
        (`_excludes_new_member`)."""
        self.group_txs.add(txid)
        if isinstance(tx, TxRemove):
            adds: frozenset[Proc] = frozenset()
            ok = self._vote_remove(tx)
        else:
            if tx.key:
                self.lock_keys[txid] = tx.key  # for l. 153 if it aborts
            adds = frozenset(m.proc for m in tx.members) - set(self.host.state.procs())
            ok = True
        if ok and self._excludes_new_member(tx, participants, adds):
            ok = False
        if ok:
            self.voted[txid] = (participants, adds)
        return ok

    def _excludes_new_member(self, tx: TxRemove | TxMembership, parts: frozenset[Proc],
                             adds: frozenset[Proc]) -> bool:
        """A group transaction must not commit after a membership transaction that admits a member it leaves
        out of its participants. OAC orders a transaction only among its participants, so the new member would
        never deliver it, and every later transaction would sit one place lower in its global sequence than in
        everyone else's (HM-Agreement; `haactl verify ddb --hosts 7` seed 2358 with the held writes of a
        suspicion: a non-leader's OAC(remove) of the crashed leader, proposed under the old list, was ordered
        after the leader's OAC(membership) adding two hosts). Alg. 3 keeps writes out of a membership change by
        the lock (l. 103), but a remove proposed by a member that suspects the leader is not held. The common
        participants of the two vote against the second one they see: a transaction that leaves out a member
        admitted here (unless it removes it) or one a membership transaction voted yes and undecided here
        admits, and a membership transaction admitting a member that a group transaction voted yes and
        undecided here leaves out. At worst a no aborts a transaction that would have been safe (this host has
        not yet applied a removal its proposer applied); it is retried like any aborted group transaction."""
        removal = set(tx.removal) if isinstance(tx, TxRemove) else set()
        here = set(self.host.state.procs())
        if any(m not in parts and m not in removal for m in self.admitted & here):
            return True
        return any((a2 - parts - removal) or (adds - p2) for p2, a2 in self.voted.values())

    def lock(self) -> tuple[str, Proc] | None:
        """The lock this host holds (l. 6) and who took it, None when unlocked."""
        if self.locked is None or self.locked_by is None:
            return None
        return self.locked, self.locked_by

    def remove_list(self) -> set[Proc]:
        """removeList_p = memberList_p ∩ ◇S_p (ll. 22-31, 119, 142)."""
        return {m.proc for m in self.host.state.members if self.host.suspected(m.proc)}

    # ------------------------------------------------------------------ helpers

    def _log(self, event: str, **fields: object) -> None:
        self._out.append(Log(event, fields))

    def _new_key(self) -> str:
        self.key_seq += 1
        return f"{self.me[0]}.{self.me[1]}.{self.key_seq}"

    def _propose(self, tx: GroupTx, parts: tuple[Proc, ...], pending: _Pending) -> None:
        txid = self.host.new_txid()
        self._out.append(ProposeTx(txid, tx, parts))
        self._proposed(txid, pending)

    def _retry_later(self) -> None:
        """l. 109 after a failed attempt: updateMembership() again, after `retry_backoff` (the pseudo-code
        retries at once, which spins while a false suspicion lasts)."""
        self.updating = True  # nothing new starts until the retry
        self._out.append(SetTimer(RETRY_TIMER, self._now + self.retry_backoff))

    # ------------------------------------------------------------------ updateMembership (ll. 76-109)

    def _update(self) -> None:
        h = self.host
        if h.has_left() or not h.is_member():
            return
        if self.updating or self.group_txs:  # l. 77-78
            return
        procs = h.state.procs()
        rl = self.remove_list()
        cand = [p for p in procs if p not in rl]
        if not cand or cand[0] != self.me:  # l. 79
            return
        cur = {p for p in procs if p not in rl and p not in self.leave_list}  # l. 82
        gc = h.state.group_correct
        join_list = h.applicants()
        potential: list[Proc] = []
        for a in join_list:  # ll. 83-87
            if h.suspected(a) or not h.sponsoring(a) or (not gc and a[0] not in self.core_names):
                continue  # l. 84-85: disqualified
            if cur <= h.connections_of(a):
                potential.append(a)
        accept: list[Proc] = []
        for a in list(potential):  # ll. 88-91
            if a not in potential:
                continue
            conns = h.connections_of(a)
            if set(accept) <= conns:
                potential = [x for x in potential if x == a or x in conns]
                accept.append(a)
        if not gc and len(accept) < self.c_f:  # l. 92-93
            accept = []
        leave = {p for p in self.leave_list if p in set(procs) or p in join_list}
        if not (accept or rl or leave):  # l. 94
            return
        if rl and not self._quorum(tuple(rl)):
            self._log("removal_waits_for_quorum", suspected=[p[0] for p in sorted(rl)])
            return
        active = [p for p in procs if p not in rl]  # l. 95
        removal = tuple(sorted(rl))  # l. 96
        self.updating = True  # l. 97
        key = "" if not accept and not leave else self._new_key()  # ll. 98-101
        members = [Member(a[0], a[1], join_list[a]) for a in accept]
        fields: dict[str, object] = {"removal": [f"{p[0]}.{p[1]}" for p in removal],
                                     "accept": [m.name for m in members], "leave": [p[0] for p in leave],
                                     "lock": bool(key)}
        a_ = Attempt(TxId("", 0, 0), key, active, members, "remove")
        self._propose(TxRemove(key, self.me, removal), tuple(active), _Pending("remove", a_, fields, []))  # l. 102

    def _proposed(self, txid: TxId, p: _Pending) -> None:
        self.group_txs.add(txid)
        a = p.attempt
        if p.what == "group_of_one":
            self._log("group_of_one", tx=str(txid))
        elif p.what == "remove":
            assert a is not None
            a.txid = txid
            self.attempt = a
            self._log("update_membership", tx=str(txid), **p.log)
        else:
            assert a is not None
            a.membership_txid = txid
            self._log("membership_proposed", tx=str(txid), members=[m.name for m in p.members])
            if not p.members:  # every member asked to leave: the group dissolves (`TxMembership`)
                self._log("group_dissolving", leaving=sorted(q[0] for q in self.leave_list))

    def _vote_remove(self, tx: TxRemove) -> bool:
        """ll. 110-116: vote for a removal only from the accepted leader (the first member not to be removed),
        removing only members this host suspects too (weak validity), and leaving a quorum (`_quorum`).
        (`haactl verify --mutate no-weak-validity` replaces this method by one that always votes yes.)"""
        rl = self.remove_list()
        cand = [m.proc for m in self.host.state.members if m.proc not in rl]
        if not cand or cand[0] != tx.proposer:
            return False  # l. 111-112: not the accepted leader
        if not set(tx.removal) <= rl:  # l. 113-114
            return False
        return self._quorum(tx.removal)

    def _quorum(self, removal: tuple[Proc, ...]) -> bool:
        """HAA's addition to l. 113 (docs/membership.md, "quorum"): a removal must leave more than half of
        the current members, or exactly half including the front of the list. Two disjoint sets of members
        that falsely suspect each other can then never both remove the other (a split group), which the
        thesis rules out only by assumption (no erroneous removal, §4.6.1).

        Members superseded by a newer incarnation of their host are certainly gone (a host runs one
        incarnation at a time): they are left out of the count, and removing them needs no quorum. Otherwise
        a group of two whose front crashed and restarted would wait for the old incarnation forever."""
        sup = self.host.superseded
        procs = [p for p in self.host.state.procs() if not sup(p)]
        gone = {p for p in removal if not sup(p)}
        if not gone:
            return True
        stay = [p for p in procs if p not in gone]
        n = len(procs)
        if 2 * len(stay) > n:
            return True
        return 2 * len(stay) == n and bool(procs) and procs[0] in stay

    def _on_locked(self, src: Proc, key: str) -> None:
        a = self.attempt
        if a is not None and a.key == key and a.stage in ("remove", "locking"):
            a.locks.add(src)

    def _lock_wait_over(self, a: Attempt) -> bool:
        """l. 103: every active member answered the lock or is suspected, and all active OACs are decided.
        (`--mutate no-lock-wait` replaces this and `_all_locked` by methods that never wait.)"""
        for q in a.active:
            if q not in a.locks and not self.host.suspected(q):
                return False
        return self.host.all_decided()  # "all active OACs are decided"

    def _all_locked(self, a: Attempt) -> bool:
        """l. 104: every active member locked (otherwise the attempt fails)."""
        return all(q in a.locks for q in a.active)

    def _poll(self) -> None:
        a = self.attempt
        if a is None or a.stage != "locking" or self.host.has_left():
            return
        if not self._lock_wait_over(a):
            return
        if self._all_locked(a):  # l. 104
            leave = self.leave_list
            new = [m for m in self.host.state.members if m.proc not in leave]  # l. 105
            have = {m.proc for m in new}
            new += [m for m in a.accept if m.proc not in have and m.proc not in leave]
            parts = tuple(dict.fromkeys([*a.active, *(m.proc for m in a.accept)]))
            a.stage = "membership"
            self._propose(TxMembership(a.key, self.me, tuple(new)), parts, _Pending("membership", a, {}, new))  # l. 106
        elif a.key and self.locked == a.key:
            # ll. 107-109 would drop the attempt and call updateMembership() again, but the members that
            # locked (l. 127) stay locked until some later OAC(membership) commits (l. 144) or aborts (ll.
            # 152-155) — and if the next attempt has nothing to accept (its applicant was excluded meanwhile)
            # none ever comes: every member holds its global-state changes for good (`haactl verify
            # membership` seed 6628). HAA releases the lock it took: OAC(membership) with this key and the
            # member list unchanged (no applicant), which every member applies as an unlock (l. 144), then
            # updates again (l. 151). docs/membership.md, "a failed lock wait".
            self._log("lock_wait_failed", key=a.key, unlocked=[q[0] for q in a.active if q not in a.locks])
            a.accept = []
            a.stage = "membership"
            members = tuple(self.host.state.members)
            self._propose(TxMembership(a.key, self.me, members), tuple(a.active),
                          _Pending("membership", a, {}, list(members)))
        else:  # ll. 107-109
            self.attempt = None
            self._retry_later()

    # ------------------------------------------------------------------ outcomes

    def _set_lock(self, key: str | None, by: Proc | None) -> None:
        self.locked = key
        self.locked_by = by if key is not None else None

    def _lock(self, key: str, by: Proc) -> None:
        """ll. 127-130: lock, and acknowledge the lock to whoever took it."""
        self._set_lock(key, by)
        if by != self.me:
            self._out.append(Send(by[0], by[1], Locked(key)))
        else:
            self._on_locked(self.me, key)

    def _unlock(self) -> None:
        self._set_lock(None, None)
        self._out.append(Unlocked())

    def _aborted(self, txid: TxId) -> None:
        self.group_txs.discard(txid)
        self.voted.pop(txid, None)
        key = self.lock_keys.pop(txid, None)
        if key is not None:  # a state installed later may still hold it (`LockInherited`)
            self.released[key] = None
            while len(self.released) > RELEASED_KEEP:
                del self.released[next(iter(self.released))]
        a = self.attempt
        if key is not None and self.locked == key and (a is None or a.key != key):
            # ll. 152-155 on every participant, not only the proposer: a member that stayed locked after the
            # membership transaction aborted would hold its global-state changes forever
            self._unlock()
        if a is not None and txid == a.txid:  # l. 134-135 / l. 103: remove aborted
            self.attempt = None
            self._retry_later()
        elif a is not None and txid == a.membership_txid:  # l. 152-157
            self.attempt = None
            if self.locked == a.key:
                self._unlock()
            self._retry_later()

    def _on_stale(self, txid: TxId) -> None:
        """A remove or membership transaction of a former leader, ordered after the change that replaced it:
        the state applied it as a no-op (`Applied.stale`), so it neither locks (l. 127) nor changes the list.
        Without this a former leader's lock, committed after its removal, held every member's writes until
        the next membership change (docs/membership.md, "stale leader")."""
        self._log("stale_group_tx", tx=str(txid), proposer=f"{txid.host}.{txid.inc}")
        a = self.attempt
        if a is not None and txid in (a.txid, a.membership_txid):  # our own attempt: we are not the leader
            self.attempt = None
            if self.locked == a.key:
                self._unlock()
            self._retry_later()
        self._update()

    def _on_remove_committed(self, tx: TxRemove) -> None:
        """ll. 117-133."""
        h = self.host
        if not h.is_member():
            self._out.append(Removed())
            return
        self.leave_list &= {m.proc for m in h.state.members}  # l. 120
        if h.leader_now():  # ll. 121-126
            self._out.append(SponsorAll())
        key = tx.key or None
        if key is not None:  # ll. 127-130
            self._lock(key, tx.proposer)
        else:
            self._set_lock(None, None)  # l. 127
            self._out.append(ProposeHeld())  # l. 132
        a = self.attempt
        if a is not None and a.stage == "remove" and tx.proposer == self.me and key == (a.key or None):
            if key is None:  # l. 103 first case, then ll. 108-109
                self.attempt = None
                self.updating = False
            else:
                a.stage = "locking"
        self._out.append(RunUpdate())  # l. 133

    def _on_membership_committed(self, txid: TxId, tx: TxMembership, was_member: bool, leaving: bool) -> None:
        """ll. 136-151 (the applicants' part, ll. 137-140, is `haa.core.membership.join.Admitted`)."""
        new = {m.proc for m in tx.members}
        self.leave_list &= new  # l. 143
        if self.me not in new:
            if was_member or leaving:
                self._out.append(Removed())
            return
        if not was_member:
            self._log("joined", view=self.host.state.view, tx=str(txid))
            self._out.append(NowMember())
        self._set_lock(None, None)  # l. 144
        self._out.append(ProposeHeld())  # l. 145
        a = self.attempt
        if a is not None and a.membership_txid == txid:
            self.attempt = None
        self.updating = False  # l. 150
        if self.host.leader_now():
            self._out.append(SponsorAll())  # docs/membership.md: a new leader sponsors waiting applicants
        self._out.append(RunUpdate())  # l. 151
