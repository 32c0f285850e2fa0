"""Deliberately broken variants of the algorithms, to prove that the checkers can fail.

Each mutation patches `OrderedAtomicCommit` (or the failure detector) in the current process and returns a
function that undoes the patch. The verifier applies a mutation before it forks its workers
(`haactl verify oac --mutate NAME`), and `tests/test_mutations.py` asserts that every mutation is caught.

* `skip-order-gate`  Alg. 2 l. 37 without the order condition: a committed transaction is delivered as soon
                     as it is decided. Breaks AC-Total-Order.
* `thesis-close`     Alg. 2 l. 41 exactly as printed: a decide rebroadcast counts for closing even when its
                     sender has not yet passed l. 38. Breaks AC-Total-Order (docs/oac.md, "the closing
                     gate") — the verifier found this hole in the thesis' algorithm.
* `no-order-confirm` Alg. 2 l. 22-25 skipped: a participant accepts the proposer's order even when it
                     conflicts with a transaction it already holds. Breaks AC-Total-Order.
* `commit-on-quorum` Alg. 2 l. 51 with a quorum instead of all n estimates: pre-commit without every vote.
                     Breaks AC-Uniform-Validity.
* `never-precommit`  Alg. 2 l. 51-52 removed: the coordinator never proposes pre-commit. Breaks
                     AC-Non-Triviality.
* `deaf-detector`    the failure detector never suspects a process that stopped sending heartbeats
                     (Alg. 1 l. 17-18 removed). Breaks UFD-Completeness.

Host membership (Alg. 3) and the DDB, checked by `haactl verify membership|ddb` (`haa.lab.dsim.group`):

* `no-weak-validity` a member votes yes to any OAC(remove) (Alg. 3 ll. 113-114 removed). Breaks
                     HM-Weak-Validity.
* `no-quorum`        HAA's removal quorum is dropped: two halves that falsely suspect each other both remove
                     the other (docs/membership.md). Breaks HM-Agreement.
* `no-lock-wait`     OAC(membership) is proposed without waiting for the lock acknowledgements and for the
                     active OACs to be decided (Alg. 3 l. 103): a joiner misses writes. Breaks DDB-Durability.
* `stale-snapshot`   a sponsor sends the DDB as it was when it first sponsored anyone, labelled with its
                     current sequence number (Alg. 3 l. 60 with a cached state). Breaks
                     DDB-Joiner-Consistency.
* `reorder-restored` a replica restored from a snapshot (every joiner's) applies the ops of a batch in an
                     order of its own (reversed), as an iteration over a set might: replicas are no longer
                     identical by construction. Breaks DDB-Prefix.
* `no-dissolution`   a membership transaction with an empty member list does not decode (as before HAA let
                     a group dissolve): when every member leaves at once it is applied as a no-op and every
                     member stays locked. Breaks HM-Termination.

Agent allocation (Alg. 4), checked by `haactl verify allocation` (`haa.lab.dsim.allocation`):

* `thesis-accept`    Alg. 4 ll. 93-94 as printed: every committed OAC(finish) is accepted, even one whose
                     session expired (its group changed after its start). Breaks AA-Validity.
* `cbba-reset`       Table 4.7-1 "reset & broadcast" as in the CBBA/ACBBA papers: the receiver resets but
                     rebroadcasts the sender's bid instead of its own nil bid, so the leader's bid table no
                     longer shows the members' real rows (the thesis' reason for its change). Breaks
                     AA-Table-Fidelity.
* `no-unallocatable` consensus waits for every agent, also those no host of the group can run: the session
                     never ends. Breaks AA-Liveness.
* `ignore-hardware`  hosts bid for agents whose hardware they lack. Breaks AA-Validity.
* `ignore-per-host-limit` hosts bid for agents of a limited kind past its per-host limit (issue 15). Breaks
                     AA-Per-Host-Limit.

Agent transactions with out-of-bounds values (issue 13), checked by `haactl verify recovery`:

* `unbounded-values` the table's number checks as before issue 13 (`x >= lo` only): a create with cost=+inf
                     from a member that skips the edge checks is applied everywhere. Breaks AG-Refuse-Invalid.
* `raising-reaction` the agent layer raises while reacting to a committed agent-list change; the host's safety
                     net catches it. Breaks AG-No-Error (the net must not hide bugs from the verifiers).

Allocation after a host joins, checked by `haactl verify join` (`haa.lab.dsim.joins`):

* `joiner-default-capacity` a member whose capacity is not in the agent table yet (it just joined) bids as if it
                     had one core: the join's session gives it agents that the session its real capacity
                     triggers a second later moves again. Breaks AA-Join-Stable.

A real agent on virtual time, checked by `haactl verify executive` (`haa.lab.dsim.vagent`):

* `no-spawn-key`     spawning as before idempotent spawn: the agent table ignores a create's key
                     (`AgentTable.child_by_key` finds nothing), so a spawn that a recovered ExecutiveMission asks
                     for again after its first request had committed makes a second child. Breaks EX-Once.
"""

from __future__ import annotations

import dataclasses
import heapq
import weakref
from collections.abc import Callable
from typing import Any

from google.protobuf.message import DecodeError

import haa.pb.ddb_pb2 as ddb_pb
from haa.core.allocation import allocation as alloc_mod
from haa.core.allocation.bids import Bid
from haa.core.allocation.conflicts import RESET
from haa.core.allocation.session import _Session
from haa.core.allocation.specs import SessionStart
from haa.core.ddb import ddb as ddb_mod
from haa.core.effects import Deliver
from haa.core.membership import globalstate as globalstate_mod
from haa.core.membership import membership as membership_mod
from haa.core.membership import update as update_mod
from haa.core.membership.globalstate import GlobalState
from haa.core.messages import OacDecide, OacProposal, StateSnapshot
from haa.core.oac import oac as oac_mod
from haa.core.ufd import ufd as ufd_mod

Undo = Callable[[], None]


def _patch(obj: object, name: str, new: object) -> Undo:
    old = getattr(obj, name)
    setattr(obj, name, new)
    return lambda: setattr(obj, name, old)


def skip_order_gate() -> Undo:
    cls = oac_mod.OrderedAtomicCommit

    def deliver_ready(self: oac_mod.OrderedAtomicCommit) -> None:
        for tx in list(self.txs.values()):
            if tx.state == oac_mod.DECIDED and tx.commit and tx.content:
                tx.state = oac_mod.DONE
                self.delivered += 1
                self._out.append(Deliver(tx.id, tx.order, tx.payload))
                tx.decide_from.add(self.name)
                if tx.relayed_decide:
                    self._announce_delivered(tx)
                self._close_check(tx)
        while self._gate and self._gate[0][1] not in self.txs:
            heapq.heappop(self._gate)

    return _patch(cls, "_deliver_ready", deliver_ready)


def thesis_close() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._decide_msg

    def decide_msg(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> OacDecide:
        msg = original(self, tx)
        msg.delivered = True  # "received (id, q, -, -, outcome, decide) from q" as printed in l. 41
        return msg

    undo_msg = _patch(cls, "_decide_msg", decide_msg)
    undo_announce = _patch(cls, "_announce_delivered", lambda self, tx: None)  # l. 36 is the only rebroadcast

    def undo() -> None:
        undo_announce()
        undo_msg()

    return undo


def no_order_confirm() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._highest

    def highest(self: oac_mod.OrderedAtomicCommit, exclude: object = None) -> object:
        if exclude is not None:  # the l. 22 confirmation in atomicCommit sees no conflict
            return None
        return original(self, exclude)

    return _patch(cls, "_highest", highest)


def commit_on_quorum() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._progress

    def progress(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> None:
        if tx.phase == oac_mod.C1 and tx.state == oac_mod.UNDECIDED:
            got = tx.ests.get((tx.order, tx.r))
            if got is not None and len(got) >= tx.quorum:
                for q, _qi in tx.parts:  # pretend the missing estimates arrived and said yes
                    got.setdefault(q, (False, 0))
        original(self, tx)

    return _patch(cls, "_progress", progress)


def never_precommit() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._progress

    def progress(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> None:
        if tx.phase == oac_mod.C1 and tx.state == oac_mod.UNDECIDED:
            got = tx.ests.get((tx.order, tx.r))
            if got is not None and len(got) == tx.n:  # hide one estimate: l. 51 never holds
                q = next(q for q, _qi in tx.parts if q != self.name)
                saved = got.pop(q)
                try:
                    if all(q2 in got or self._suspected(q2, qi) for q2, qi in tx.parts if q2 != q):
                        tx.est = False
                        prop = OacProposal(tx.id, tx.order, tx.r, False)
                        self._send_all(tx, prop)
                        tx.props[(tx.order, tx.r)] = False
                        tx.phase = oac_mod.P2
                finally:
                    got[q] = saved
        original(self, tx)

    return _patch(cls, "_progress", progress)


def deaf_detector() -> Undo:
    """The observer never suspects: a passed freshness point changes nothing (a timer that fired early is still
    re-armed, as the real observer does)."""
    cls = ufd_mod.HeartbeatObserver
    step = cls.step

    def deaf(self: ufd_mod.HeartbeatObserver, now: float, inp: ufd_mod.ObserverInput) -> list[ufd_mod.ObserverEffect]:
        if isinstance(inp, ufd_mod.Deadline):
            return [ufd_mod.ArmFreshness(self.freshness)] if self.trusted and now < self.freshness else []
        return step(self, now, inp)

    return _patch(cls, "step", deaf)


def _always(cls: type, *methods: str) -> Callable[[], Undo]:
    """A variant of `cls` whose `methods` (predicates) always answer True: a check the algorithm makes, left
    out. The production class has no switch for it; the variant is patched in (and undone) here."""

    def apply() -> Undo:
        undos = [_patch(cls, m, lambda self, *args: True) for m in methods]

        def undo() -> None:
            for u in reversed(undos):
                u()

        return undo

    return apply


def seq_no_dedup() -> Undo:
    """Replicas apply a write forwarded twice twice: `GlobalState.dedup` off in every node's state."""
    cls = membership_mod.MembershipNode
    init = cls.__init__

    def __init__(self: membership_mod.MembershipNode, *args: Any, **kw: Any) -> None:
        init(self, *args, **kw)
        self.state.dedup = False

    return _patch(cls, "__init__", __init__)


def seq_no_cost_bound() -> Undo:
    """The sequencer packs batches by entries and bytes only, not by the writes' DDB ops (`seq_max_cost` off)."""
    cls = membership_mod.MembershipNode
    init = cls.__init__

    def __init__(self: membership_mod.MembershipNode, *args: Any, **kw: Any) -> None:
        init(self, *args, **kw)
        self.seq.config = dataclasses.replace(self.seq.config, seq_max_cost=10**9)

    return _patch(cls, "__init__", __init__)


def stale_snapshot() -> Undo:
    cls = membership_mod.MembershipNode
    cache: dict[int, bytes] = {}

    def send_state(self: membership_mod.MembershipNode, a: tuple[str, int]) -> None:
        now = self.state.snapshot()
        old = cache.setdefault(id(self), now)
        if old is not now:
            stale, cur = GlobalState(self.state.core_names, self.c_f), GlobalState(self.state.core_names, self.c_f)
            stale.restore(old)
            cur.restore(now)
            cur.ddb = stale.ddb  # the DDB of back then, under today's sequence number
            now = cur.snapshot()
        self._send(a, StateSnapshot(self.state.seq, now, None, 0))

    return _patch(cls, "_send_state", send_state)


def no_dissolution() -> Undo:
    dec = globalstate_mod._dec_members
    return _patch(globalstate_mod, "_dec_members", lambda rep, what, allow_empty=False: dec(rep, what))


def reorder_restored() -> Undo:
    cls = ddb_mod.Ddb
    restore = cls.restore.__func__  # type: ignore[attr-defined]
    apply = cls.apply
    restored: weakref.WeakSet[ddb_mod.Ddb] = weakref.WeakSet()

    def restore_marked(klass: type[ddb_mod.Ddb], data: bytes, *args: object, **kw: object) -> ddb_mod.Ddb:
        d = restore(klass, data, *args, **kw)
        restored.add(d)
        return d

    def apply_reordered(self: ddb_mod.Ddb, payload: bytes, meta: object = None) -> ddb_mod.ApplyResult:
        if self in restored:
            try:
                batch = ddb_pb.DdbBatch.FromString(bytes(payload))
            except DecodeError:
                pass
            else:  # the ops of a batch in an order of this replica's own
                ops = list(batch.ops)[::-1]
                del batch.ops[:]
                batch.ops.extend(ops)
                payload = batch.SerializeToString()
        return apply(self, payload, meta)

    raw = cls.__dict__["restore"]  # the classmethod object itself (getattr would give a bound method)
    cls.restore = classmethod(restore_marked)  # type: ignore[method-assign,assignment]
    undo_apply = _patch(cls, "apply", apply_reordered)

    def undo() -> None:
        undo_apply()
        cls.restore = raw  # type: ignore[method-assign]

    return undo


def thesis_accept() -> Undo:
    return _patch(alloc_mod.Allocator, "finish_valid", lambda self, ses_id, group, agent_ids: "")


def cbba_reset() -> Undo:
    def broadcast_bid(
        self: alloc_mod.Allocator, s: _Session, j: str, sender_bid: Bid, action: str
    ) -> Bid:
        return sender_bid if action == RESET else s.bid(j)

    return _patch(alloc_mod.Allocator, "_broadcast_bid", broadcast_bid)


def no_unallocatable() -> Undo:
    return _patch(SessionStart, "unallocatable", lambda self: ())


def ignore_hardware() -> Undo:
    cls = _Session
    original = cls.make_ready

    def make_ready(self: _Session, start: SessionStart, me: str) -> None:
        original(self, start, me)
        if self.spec is not None:
            self.eligible = tuple(a.id for a in start.agents if not self.spec.draining)

    return _patch(cls, "make_ready", make_ready)


def ignore_per_host_limit() -> Undo:
    return _patch(alloc_mod.Allocator, "PER_HOST_LIMIT", False)


def no_stream_order() -> Undo:
    """The receiver's host passes agent messages on as they arrive, without the sender-stream numbers
    (haa.core.agents.routing): a message that overtook an earlier one on another path is processed first, and one
    that reached the agent twice is processed twice."""
    from haa.core.agents import routing as routing_mod

    def offer(self: routing_mod.Inbox, m: object) -> list[object]:
        return [m]

    return _patch(routing_mod.Inbox, "offer", offer)


def oldest_backup() -> Undo:
    """Recovery starts from the first backup an agent ever committed instead of the latest (Alg. 7 l. 5 keeps
    only the first)."""
    from haa.core.ddb import agenttable as table_mod

    original = table_mod.AgentTable._tx_backup

    def tx_backup(self: table_mod.AgentTable, m: object) -> object:
        r = self.records.get(m.id)  # type: ignore[attr-defined]
        if r is not None and r.backup is not None:
            return table_mod.AgentApplied("backup", m.id, True, "", m.host)  # type: ignore[attr-defined]
        return original(self, m)  # type: ignore[arg-type]

    return _patch(table_mod.AgentTable, "_tx_backup", tx_backup)


def unchecked_claim() -> Undo:
    """OAC(claim) is accepted whatever the agent's state (Alg. 6 l. 13 without its test): a host that thaws an
    agent another host has already claimed runs a second instance."""
    from haa.core.ddb import agenttable as table_mod

    def tx_claim(self: table_mod.AgentTable, m: object) -> object:
        r = self.records.get(m.id)  # type: ignore[attr-defined]
        if r is None:
            return table_mod.AgentApplied("claim", m.id, False, "unknown agent", m.host)  # type: ignore[attr-defined]
        r.status = table_mod.ACTIVE
        r.owner = m.host  # type: ignore[attr-defined]
        r.epoch += 1
        return table_mod.AgentApplied("claim", m.id, True, "", m.host, msgs=self._take_queues(r))  # type: ignore[attr-defined]

    return _patch(table_mod.AgentTable, "_tx_claim", tx_claim)


def unbounded_values() -> Undo:
    """The agent table's number checks as before issue 13: only `x >= lo` (NaN refused; inf, 1e308 and values
    above the upper bounds accepted). A create with cost=+inf, proposed by a member that skips the edge checks,
    enters every table. Breaks AG-Refuse-Invalid."""
    from haa.core.ddb import agenttable as table_mod

    return _patch(table_mod, "_bad_number", lambda x, lo, hi: not x >= lo)


def raising_reaction() -> Undo:
    """The agent layer raises while it reacts to a committed agent-list change (as the allocator did on a
    cost=+inf agent before issue 13): the host's safety net catches it and goes on. Breaks AG-No-Error (the
    verifiers must not let the net hide a bug)."""
    from haa.core.agents import allocglue as glue_mod

    original = glue_mod.AllocGlue.change

    def change(self: glue_mod.AllocGlue, now: float, why: str, force: bool = False) -> list[glue_mod.GlueEffect]:
        if why == "agent list changed":
            raise ValueError("AgentSpec(x).cost: must be a finite number, got inf")
        return original(self, now, why, force)

    return _patch(glue_mod.AllocGlue, "change", change)


def joiner_default_capacity() -> Undo:
    """The agent layer as before the join fixes: a member whose `HostInfo` is not in the agent table yet (a host
    that just joined) is read as one core without hardware, and the join's session runs, so it bids in it."""
    from haa.core.agents import allocglue as glue_mod
    from haa.core.allocation.specs import MAX_CAPACITY, MIN_CAPACITY, HostSpec

    def host_specs(self: glue_mod.AllocGlue) -> tuple[HostSpec, ...]:
        out = []
        for n in self.view.members():
            h = self.view.table.hosts.get(n)
            cap = h.capacity if h is not None and MIN_CAPACITY <= h.capacity <= MAX_CAPACITY else 1.0
            out.append(HostSpec(n, cap, frozenset(h.hardware) if h else frozenset(), bool(h and h.draining)))
        return tuple(out)

    view_changed = glue_mod.AllocGlue.view_changed

    def every_view_a_session(
        self: glue_mod.AllocGlue, now: float, joined: bool, only_new_hosts: bool = False
    ) -> list[glue_mod.GlueEffect]:
        return view_changed(self, now, joined)  # and the join's session runs (no `only_new_hosts` skip)

    undo_specs = _patch(glue_mod.AllocGlue, "host_specs", host_specs)
    undo_view = _patch(glue_mod.AllocGlue, "view_changed", every_view_a_session)
    return lambda: (undo_view(), undo_specs())[-1]


def no_spawn_key() -> Undo:
    """The agent table as before idempotent spawn: a create's key names no existing child, every create makes one."""
    from haa.core.ddb import agenttable as table_mod

    def child_by_key(self: table_mod.AgentTable, parent: str, key: str) -> None:
        return None

    return _patch(table_mod.AgentTable, "child_by_key", child_by_key)


MUTATIONS: dict[str, tuple[Callable[[], Undo], str, str]] = {
    # name: (apply, algorithm to verify with, property the verifier must report)
    "skip-order-gate": (skip_order_gate, "oac", "AC-Total-Order"),
    "thesis-close": (thesis_close, "oac", "AC-Total-Order"),
    "no-order-confirm": (no_order_confirm, "oac", "AC-Total-Order"),
    "commit-on-quorum": (commit_on_quorum, "oac", "AC-Uniform-Validity"),
    "never-precommit": (never_precommit, "oac", "AC-Non-Triviality"),
    "deaf-detector": (deaf_detector, "ufd", "UFD-Completeness"),
    "no-weak-validity": (_always(update_mod.MembershipUpdate, "_vote_remove"), "membership", "HM-Weak-Validity"),
    "no-quorum": (_always(update_mod.MembershipUpdate, "_quorum"), "membership", "HM-Agreement"),
    "no-lock-wait": (_always(update_mod.MembershipUpdate, "_lock_wait_over", "_all_locked"), "ddb",
                     "DDB-Durability"),
    "stale-snapshot": (stale_snapshot, "ddb", "DDB-Joiner-Consistency"),
    "reorder-restored": (reorder_restored, "ddb", "DDB-Prefix"),
    "no-dissolution": (no_dissolution, "membership", "HM-Termination"),
    "seq-no-dedup": (seq_no_dedup, "ddb", "DDB-Exactly-Once"),
    "seq-no-cost-bound": (seq_no_cost_bound, "ddb", "DDB-Bounded-Batch"),
    "thesis-accept": (thesis_accept, "allocation", "AA-Validity"),
    "cbba-reset": (cbba_reset, "allocation", "AA-Table-Fidelity"),
    "no-unallocatable": (no_unallocatable, "allocation", "AA-Liveness"),
    "ignore-hardware": (ignore_hardware, "allocation", "AA-Validity"),
    "ignore-per-host-limit": (ignore_per_host_limit, "allocation", "AA-Per-Host-Limit"),
    "no-stream-order": (no_stream_order, "transfer", "AT-Consistency"),
    "oldest-backup": (oldest_backup, "recovery", "AR-Recovery"),
    "unchecked-claim": (unchecked_claim, "transfer", "AG-Single-Active"),
    "unbounded-values": (unbounded_values, "recovery", "AG-Refuse-Invalid"),
    "raising-reaction": (raising_reaction, "transfer", "AG-No-Error"),
    "joiner-default-capacity": (joiner_default_capacity, "join", "AA-Join-Stable"),
    "no-spawn-key": (no_spawn_key, "executive", "EX-Once"),
}


def apply(name: str) -> Undo:
    try:
        fn = MUTATIONS[name][0]
    except KeyError:
        raise ValueError(f"unknown mutation {name!r}; choose from {sorted(MUTATIONS)}") from None
    return fn()
