"""Host membership service HAA-HM (thesis §4.6, Appendix II Alg. 3, thesis L2358-2565), as a sans-I/O node.

`MembershipNode` is everything one host incarnation decides once it takes part in a group: it owns a
`HostCore` (failure detector + OAC, `haa.core.hostcore`) and the group's `GlobalState` (member list, view, DDB,
`haa.core.globalstate`), and runs Alg. 3 on top. It is composed of machines that own their state and take
one `step(now, input)` returning effects, which the node carries out in order (`_form`, `_xfer`, `_seq`):

* `haa.core.formation.Formation` — formation by the first core process (ll. 41-43) and the
  FORMATION_TIMEOUT fallback with OAC(formationFallback) by the core head (ll. 44-49), and its vote
  (ll. 158-165);
* `haa.core.statetransfer.StateTransfer` — the joiner's side of "send global state to a" (ll. 58-61,
  123-126, 174-177): the sponsor's snapshot and forwarded stream, catching up, state requests;
* `haa.core.sequencer.Sequencer` — DDB and test writes forwarded to one sequencer and batched
  (docs/oac.md), held while the global state is locked (ll. 127-132).

The node itself routes inputs to them and runs the rest of Alg. 3:

* apply / introduce / sponsor / connections (ll. 35-39, 50-75): an applicant contacts every core process,
  everyone who hears of it introduces it to everyone else, the leader sponsors it: sends it the global state
  and forwards every later change until it has joined;
* updateMembership (ll. 76-109): the leader (highest-ranked member it does not suspect) commits
  OAC(remove) — removing members that every remaining member suspects (l. 113, HM-Weak-Validity) and,
  when members join or leave, locking the global state — waits for every lock acknowledgement and for
  every OAC it knows to be decided, then commits OAC(membership) with the new list, which unlocks;
* votes on remove transactions (ll. 110-116), global-state changes held while locked (ll. 127-132,
  144-145, 153-155), voluntary leave (ll. 14-21);
* global-state changes: agent-table transactions (and, without the sequencer, DDB batches and test
  payloads) are proposed to every member by OAC, applied in total order, acknowledged to the requester only
  once committed, and re-proposed after an abort.

Line numbers in comments refer to Alg. 3. Where the pseudo-code is silent or had to be completed, the
choices are documented in docs/membership.md; in short:

* Members are host incarnations with their address (`Member`); a restarted host is a new incarnation that
  applies again, and its old incarnation is removed like a crashed one.
* A member removed from the view is permanently suspected (`HostCore.mark_dead`), so that OAC can close
  transactions it took part in (Alg. 2 l. 41), and told so: a correct host removed by mistake restarts as a
  new incarnation and re-applies.
* The leader also sponsors waiting applicants when it commits a membership change that made it the
  leader (the first core process' group of one: ll. 136-151 have no sponsor step, so applicants that
  applied before it existed would never be sponsored).
* Applicants re-send `apply` to core processes they have not heard from (a core process that was down
  when the applicant started would otherwise never learn of it), and also apply to every member that
  introduces itself (the leader need not be a core process); a leader answers a repeated `apply` of an
  applicant it sponsors with `Sponsor` again.
* ll. 152-155 (unlock when OAC(membership) aborts) run on every participant; a removal quorum leaves out
  incarnations superseded by a restart.
* The first core process waits `discovery` seconds before forming its group of one, and neither it nor
  the core head forms a group once an introduction shows that a correct group exists; a provisional
  group that learns of a different correct group restarts as a new incarnation and applies to it.
* State transfer: applied transactions are numbered (`GlobalState.seq`). A new member buffers what it
  delivers until its state has caught up to the transaction that added it — from its sponsor's forwarded
  stream, or, if that does not arrive within `catchup_timeout`, from a `StateRequest` to a member.

The class does no I/O, reads no clock and uses no randomness.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any, assert_never, cast

from haa.core.effects import Decided, Deliver, Effect, Log, PeerDead, Reincarnate, Send, SetTimer, Suspicion
from haa.core.formation import (
    Aborted,
    DiscoveryDue,
    Formation,
    FormationConfig,
    FormationDue,
    FormationInput,
    FormGroupOfOne,
    ProposeFallback,
)
from haa.core.formation import Delivered as FDelivered
from haa.core.formation import Proposed as FProposed
from haa.core.formation import Start as FStart
from haa.core.globalstate import (
    GlobalState,
    GroupTx,
    GroupTxError,
    SeqApplied,
    TxAgent,
    TxDdb,
    TxFormation,
    TxMembership,
    TxRemove,
    TxSeq,
    TxTest,
    decode_tx,
    encode_tx,
)
from haa.core.groupeffects import AppliedTx, Connect, Left, NodeEffect, NodeTimer, TimerWhat, ViewChange, WriteDone
from haa.core.hostcore import CoreConfig, HostCore
from haa.core.messages import (
    Apply,
    Connections,
    Introduce,
    Leave,
    Locked,
    Member,
    Message,
    SeqWrite,
    Sponsor,
    StateForward,
    StateRequest,
    StateSnapshot,
    TxId,
)
from haa.core.oac import UNDECIDED
from haa.core.sequencer import (
    BatchAborted,
    BatchApplied,
    Count,
    Flush,
    Forwarded,
    ProposeBatch,
    Proposed,
    Retarget,
    RetryDue,
    SeqConfig,
    SeqInput,
    Sequencer,
    Submit,
)
from haa.core.statetransfer import (
    Applied,
    ApplyTx,
    CatchupDue,
    CaughtUp,
    Continue,
    Delivered,
    Forward,
    Rejected,
    Request,
    Restore,
    SendSnapshot,
    Snapshot,
    StateTransfer,
    XferInput,
)

Proc = tuple[str, int]

__all__ = ["AppliedTx", "Connect", "Left", "MembershipNode", "NodeConfig", "NodeEffect", "NodeTimer", "ViewChange",
           "WriteDone"]


# ------------------------------------------------------------------------------------------------ config


@dataclass(frozen=True, slots=True)
class NodeConfig:
    core: CoreConfig = field(default_factory=CoreConfig)
    #: c_f: core processes that may fail (c_f < c/2); None = the largest such value
    c_f: int | None = None
    #: c_H: size of the core head that runs the fallback formation (c_f < c_H <= c); None = c_f + 1
    c_h: int | None = None
    #: FORMATION_TIMEOUT (l. 45), seconds after start
    formation_timeout: float = 5.0
    #: wait between two formationFallback attempts
    formation_retry: float = 1.0
    #: the first core process listens this long for an existing group before forming its own
    discovery: float = 1.0
    #: an applicant re-sends `apply` to core processes it has not heard from, this often
    reapply: float = 2.0
    #: a new member whose state has not caught up after this long asks a member for a snapshot
    catchup_timeout: float = 2.0
    #: wait between a failed membership update attempt and the next
    retry_backoff: float = 0.05
    #: a global-state change aborted this many times is reported failed
    max_write_attempts: int = 50
    #: compute the content hash after every applied transaction (the simulator's checks)
    hash_every_apply: bool = False
    #: DDB and test writes go through the sequencer: forwarded to the leader, batched into one OAC with the
    #: other members' writes, applied once per (origin, cseq) (docs/oac.md, "The sequencer"); False: every
    #: member proposes its own writes (Alg. 3 as printed: concurrent proposers, order conflicts)
    sequencer: bool = True
    #: sequencer batches of one host in OAC at a time (writes forwarded meanwhile wait and go out together)
    seq_inflight: int = 2
    #: at most this many writes / payload bytes in one sequencer batch
    seq_max_entries: int = 1024
    seq_max_bytes: int = 4 << 20
    #: a forwarded write not applied within this long is forwarded again (to the sequencer of the moment)
    seq_retry: float = 2.0
    #: ... and given up after this long (reported "may still commit": a copy may be in a batch somewhere)
    seq_abandon: float = 60.0

    def __post_init__(self) -> None:
        if self.seq_inflight < 1 or self.seq_max_entries < 1 or self.seq_max_bytes < 1:
            raise ValueError("seq_inflight, seq_max_entries and seq_max_bytes must be at least 1")
        for n in ("formation_timeout", "formation_retry", "discovery", "reapply", "catchup_timeout", "retry_backoff",
                  "seq_retry", "seq_abandon"):
            if getattr(self, n) <= 0:
                raise ValueError(f"{n} must be positive")


@dataclass(slots=True)
class _Attempt:
    """One run of updateMembership's commit part (ll. 95-109)."""

    txid: TxId
    key: str
    active: list[Proc]
    accept: list[Member]
    stage: str  # "remove" | "locking" | "membership"
    locks: set[Proc] = field(default_factory=set)
    membership_txid: TxId | None = None


@dataclass(slots=True)
class _Write:
    req: Hashable
    payload: bytes
    attempts: int = 0
    seq: bool = False  # through the sequencer


# ------------------------------------------------------------------------------------------------ node


class MembershipNode:
    """One host incarnation running Alg. 3 over its `HostCore`. See the module docstring.

    Inputs (each with the local time): `start`, `on_message`, `on_timer`, `on_suspicion`, `on_peer_info`,
    `submit` (a DDB batch or test payload), `leave`. The driver calls `drain()` after each input and carries
    out the effects: those of `haa.core.effects` plus `Connect`, `ViewChange`, `AppliedTx`, `WriteDone`
    and `Left`.
    """

    def __init__(
        self,
        name: str,
        inc: int,
        addr: str,
        core_processes: Sequence[tuple[str, str]],
        config: NodeConfig | None = None,
        known_hosts: Sequence[tuple[str, str]] = (),
    ) -> None:
        self.config = cfg = config or NodeConfig()
        self.name = name
        self.inc = inc
        self.me: Proc = (name, inc)
        self.addr = addr
        self.core_names = tuple(n for n, _ in core_processes)  # l. 1
        if len(set(self.core_names)) != len(self.core_names) or not self.core_names:
            raise ValueError("core process list must be non-empty and without duplicates")
        c = len(self.core_names)
        self.c_f = cfg.c_f if cfg.c_f is not None else (c - 1) // 2
        if not self.c_f >= 0 or not 2 * self.c_f < c:
            raise ValueError(f"c_f = {self.c_f} violates c_f < c/2 with c = {c}")
        self.c_h = cfg.c_h if cfg.c_h is not None else min(c, self.c_f + 1)
        if not self.c_f < self.c_h <= c:
            raise ValueError(f"c_H = {self.c_h} violates c_f < c_H <= c")
        self.addrs: dict[str, str] = dict(core_processes)
        #: hosts a previous incarnation knew as members (`--data-dir`): a restarted host applies to them too,
        #: so that it finds its group even when every core process is down or is itself (docs/membership.md)
        self.known_hosts = [(n, a) for n, a in known_hosts if n != name and n not in self.addrs]
        for n, a in self.known_hosts:
            self.addrs[n] = a
        self.addrs[name] = addr
        self.core = HostCore(name, inc, [n for n in self.core_names if n != name], cfg.core, evaluate=self._evaluate,
                             accept_group=True)
        #: node effects go through the core's outbox, in order (so it holds both kinds)
        self.out = cast("list[Effect | NodeEffect]", self.core.out)
        self.state = GlobalState(self.core_names, self.c_f)
        # Alg. 3 ll. 2-13 (removeList_p is computed on demand: members ∩ ◇S_p, see `_remove_list`)
        self.join_list: dict[Proc, str] = {}  # l. 2, applicant -> address, in application order
        self.leave_list: set[Proc] = set()  # l. 5
        self.locked: str | None = None  # l. 6
        self.updating = False  # l. 7
        self.conn_to: set[str] = set()  # l. 8 (a link is per host name)
        self.conn_from: set[Proc] = set()  # l. 9
        self.sponsor: Proc | None = None  # l. 10
        self.sponsees: set[Proc] = set()  # l. 11
        self.conns_of: dict[Proc, set[Proc]] = {}  # the latest (connections, a, list) per applicant
        self.attempt: _Attempt | None = None
        self.group_txs: set[TxId] = set()  # remove / membership transactions in progress here (l. 77)
        self.held: list[_Write] = []  # global-state changes held while locked (l. 129)
        self.writes: dict[TxId, _Write] = {}
        self.lock_keys: dict[TxId, str] = {}  # membership transactions we voted on -> the lock they release
        self.key_seq = 0
        self.group_seen = ""  # id of a correct group someone introduced to us
        self.group_hosts: dict[str, None] = {}  # hosts that introduced themselves with a correct group (ordered)
        self.introduced: dict[Proc, tuple[str, int]] = {}  # applicant -> (group, view) when we introduced it
        self.leaving = False
        self.left = False
        # formation (ll. 40-49, 158-179; `haa.core.formation`)
        self.formation = Formation(self.me, addr, self.core_names, self.c_h, self,
                                   FormationConfig(cfg.formation_timeout, cfg.formation_retry, cfg.discovery))
        # state transfer to a new member (docs/membership.md, `haa.core.statetransfer`)
        self.xfer = StateTransfer(self.me, self, cfg.catchup_timeout)
        # the sequencer (docs/oac.md, `haa.core.sequencer`): this host as an origin and as the sequencer
        self.seq = Sequencer(self.me, self, SeqConfig(cfg.seq_inflight, cfg.seq_max_entries, cfg.seq_max_bytes,
                                                      cfg.seq_retry, cfg.seq_abandon))
        self.started = False
        self._now = 0.0

    # ------------------------------------------------------------------ plumbing shared with the driver

    @property
    def peers(self) -> dict[str, Any]:
        return self.core.peers

    @property
    def oac(self) -> Any:
        return self.core.oac

    @property
    def counters(self) -> Any:
        return self.core.counters

    def drain(self) -> list[Effect | NodeEffect]:
        """Effects of the last input. OAC decisions about group transactions are consumed here (and also
        passed on, for logs and the simulator's history)."""
        res: list[Effect | NodeEffect] = []
        core = self.core
        while True:
            effects = cast("list[Effect | NodeEffect]", core.drain())  # the shared outbox (see __init__)
            if not effects:
                self._poll()
                if not core.out:
                    break
                continue
            for e in effects:
                if isinstance(e, Reincarnate) and self.leaving:
                    # we are leaving on purpose: a peer's removal notice is no reason to come back. Removed
                    # (excluded) before our leave committed, we are out of the group all the same (seen when
                    # the whole group leaves at once and the last two members suspect each other)
                    if not self.left:
                        self.left = True
                        self._log("left", view=self.state.view, excluded_by=e.by)
                        res.append(Left())
                    continue
                res.append(e)
                if isinstance(e, Deliver):
                    self._on_deliver(e)
                elif isinstance(e, Decided):
                    self._on_decided(e)
                elif isinstance(e, Suspicion):
                    self._on_suspicion_change((e.peer, e.inc), e.suspected)
                elif isinstance(e, PeerDead):
                    self._on_peer_dead((e.peer, e.inc))
        return res

    def _send(self, dst: Proc, msg: Message) -> None:
        if dst == self.me:
            return
        self.out.append(Send(dst[0], dst[1], msg))

    def _timer(self, what: TimerWhat, at: float) -> None:
        self.out.append(SetTimer(NodeTimer(what), at))

    def _log(self, event: str, **fields: Any) -> None:
        self.out.append(Log(event, fields))

    def _connect(self, name: str, addr: str | None = None) -> None:
        """ "open connection to" (ll. 37, 53, 66): start monitoring the host and have the driver link to it."""
        if name == self.name:
            return
        if addr:
            self.addrs[name] = addr
        self.core.add_peer(self._now, name)
        a = self.addrs.get(name)
        if a:
            self.out.append(Connect(name, a))

    def _suspected(self, p: Proc) -> bool:
        return p != self.me and self.core.is_suspected(p[0], p[1])

    def _known_dead(self, p: Proc) -> bool:
        """Permanently suspected: excluded, removed, or superseded by a newer incarnation we heard of."""
        if p in self.core.dead:
            return True
        peer = self.core.peers.get(p[0])
        return peer is not None and peer.inc > p[1]

    def _remove_list(self) -> set[Proc]:
        """removeList_p = memberList_p ∩ ◇S_p (ll. 22-31, 119, 142)."""
        return {m.proc for m in self.state.members if self._suspected(m.proc)}

    def is_member(self) -> bool:
        return self.state.is_member(self.me)

    def _leader_now(self) -> bool:
        """p = front(memberList_p): the undisputed leader (ll. 57, 121, 172)."""
        lead = self.state.leader()
        return lead is not None and lead.proc == self.me

    def _two_way(self) -> tuple[Proc, ...]:
        """connectionsTo_p ∩ connectionsFrom_p (ll. 70, 73)."""
        return tuple(sorted(p for p in self.conn_from if p[0] in self.conn_to))

    # ------------------------------------------------------------------ inputs

    def start(self, now: float) -> None:
        """groupJoin() (ll. 35-49)."""
        self._now = now
        if self.started:
            return
        self.started = True
        self.core.start(now)
        for q in self._contacts():  # ll. 36-39
            self._connect(q)
            self.conn_to.add(q)
            self._send((q, self.core.peers[q].inc), Apply(self.addr))
        self._timer("reapply", now + self.config.reapply)
        self._form(FStart())  # ll. 40-45

    def _contacts(self) -> list[str]:
        """Where an applicant sends `apply`: every core process (l. 36), the hosts it knew before, and the hosts
        that introduced themselves as holding a correct group (docs/membership.md, "apply to the members")."""
        out = [q for q in self.core_names if q != self.name] + [n for n, _ in self.known_hosts]
        return out + [q for q in self.group_hosts if q not in out and q != self.name]

    def on_message(self, now: float, src: str, src_inc: int, dst_inc: int, msg: Message) -> None:
        self._now = now
        g = self.core.on_message(now, src, src_inc, dst_inc, msg)
        if g is not None:  # a membership message, handled right where the core let it through
            self._on_group(g.src, g.src_inc, g.msg)

    def on_suspicion(self, now: float, peer: str, suspected: bool) -> None:
        self._now = now
        self.core.on_suspicion(now, peer, suspected)

    def on_peer_info(self, now: float, peer: str, inc: int) -> None:
        self._now = now
        self.core.on_peer_info(now, peer, inc)

    def on_timer(self, now: float, key: Hashable) -> None:
        self._now = now
        if not isinstance(key, NodeTimer):  # the core's
            self.core.on_timer(now, key)
            return
        k = key.what
        if self.left:
            return
        if k == "discovery":
            self._form(DiscoveryDue())
        elif k == "formation":
            self._form(FormationDue())
        elif k == "reapply":
            # until a leader sponsors us, apply again: an `apply` sent before a core process was up is lost,
            # and one received by a core process that was not yet a member made no leader sponsor us
            if not self.is_member() and (self.sponsor is None or self._suspected(self.sponsor)):
                for q in self._contacts():
                    self._send((q, self.core.peers[q].inc), Apply(self.addr))
            if not self.is_member():
                for m in self.state.members:  # members we never heard from: introduce ourselves again
                    if m.proc not in self.conn_from and not self._known_dead(m.proc):
                        self._connect(m.name, m.addr)
                        self.conn_to.add(m.name)
                        self._send(m.proc, Introduce(self.name, self.inc, self.addr, self.state.group_id()))
                self._timer("reapply", now + self.config.reapply)
        elif k == "catchup":
            self._xfer(CatchupDue())
        elif k == "retry":
            if self.attempt is None:
                self.updating = False
                self._update()
        elif k == "seqretry":
            self._seq(RetryDue())

    def submit(self, now: float, payload: bytes, req: Hashable, kind: str = "ddb") -> None:
        """Request a global-state change: a DDB batch (`kind="ddb"`) or a test payload. The outcome comes as a
        `WriteDone` effect; a committed change has been applied here before `WriteDone`."""
        self._now = now
        tx: GroupTx = TxDdb(payload) if kind == "ddb" else TxAgent(payload) if kind == "agent" else TxTest(payload)
        w = _Write(req, encode_tx(tx), seq=self.config.sequencer and kind in ("ddb", "test"))
        if self.direct_q:  # a new member catching up: hold until its state has caught up
            self.held.append(w)
            return
        if not self.is_member():
            self.out.append(WriteDone(req, False, None, 0, "not a member of the group"))
            return
        if not self.state.group_correct:
            self.out.append(WriteDone(req, False, None, 0, "the group is not formed yet"))
            return
        if self.locked is not None and not w.seq:  # l. 129: hold while locked (the sequencer holds its batches)
            self.held.append(w)
            return
        self._propose_write(w)

    def leave(self, now: float) -> None:
        """groupLeave() (ll. 14-17): the `Left` effect follows once the group has removed this host."""
        self._now = now
        if self.leaving:
            return
        self.leaving = True
        self._log("leave_requested")
        if not self.is_member():
            # an applicant withdraws: every host it knows drops it from its join list (`_on_leave`), so that
            # no leader proposes a group with it after it is gone (that transaction would wait for it)
            for q, peer in sorted(self.core.peers.items()):
                self._send((q, peer.inc), Leave())  # inc 0: any incarnation (as our Apply went)
            self.left = True
            self.out.append(Left())
            return
        if len(self.state.members) == 1:
            # the last member: nobody remains to commit its removal (Alg. 3 assumes a group remains)
            self.left = True
            self._log("left", view=self.state.view, last_member=True)
            self.out.append(Left())
            return
        for m in self.state.members:  # l. 15
            if m.proc == self.me:
                self._on_leave(self.me)
            else:
                self._send(m.proc, Leave())

    # ------------------------------------------------------------------ formation (ll. 40-49)

    def _form(self, inp: FormationInput) -> None:
        """Step the formation machine and carry out its effects, in order."""
        for e in self.formation.step(self._now, inp):
            match e:
                case FormGroupOfOne():
                    self._form_group_of_one()
                case ProposeFallback(members):
                    txid = self.core.propose_to(self._now, encode_tx(TxFormation(self.me, members)),
                                                [m.proc for m in members])
                    self._form(FProposed(txid, members))
                case SetTimer() | Log():
                    self.out.append(e)
                case _:
                    assert_never(e)

    def _form_group_of_one(self) -> None:
        """ll. 42-43 (docs/membership.md, "restarts"): a provisional group of one, locked with a new key."""
        self.key_seq += 1
        key = f"{self.name}.{self.inc}.{self.key_seq}"
        self.locked = key  # l. 42
        tx = TxMembership(key, self.me, (Member(self.name, self.inc, self.addr),))
        txid = self.core.propose_to(self._now, encode_tx(tx), [self.me])  # l. 43
        self.group_txs.add(txid)
        self._log("group_of_one", tx=str(txid))

    # FormationHost: what the formation reads of this node

    def may_form(self) -> bool:
        """A host that was a member before (it knows hosts from a previous incarnation) never forms a group:
        its group may still exist and only be slow to answer; it applies until it is joined."""
        return not (self.state.members or self.group_seen or self.leaving or self.known_hosts)

    def peer_incarnation(self, name: str) -> int:
        p = self.core.peers.get(name)
        return p.inc if p is not None else 0

    def is_suspected(self, name: str, inc: int) -> bool:
        return self.core.is_suspected(name, inc)

    def address(self, name: str) -> str:
        return self.addrs.get(name, "")

    # ------------------------------------------------------------------ OAC votes (ll. 110-116, 158-165)

    def _evaluate(self, txid: TxId, payload: bytes) -> bool:
        try:
            tx = decode_tx(payload)
        except GroupTxError:
            return True  # not ours to judge: it is applied as a no-op everywhere
        if isinstance(tx, TxRemove):
            self.group_txs.add(txid)
            return self._vote_remove(tx)
        if isinstance(tx, TxMembership):
            self.group_txs.add(txid)
            if tx.key:
                self.lock_keys[txid] = tx.key  # for l. 153 if it aborts
            return True
        if isinstance(tx, TxFormation):
            return self.formation.vote(tx, bool(self.state.members))  # ll. 158-165
        return True

    # ------------------------------------------------------------------ OAC outcomes

    def _on_decided(self, e: Decided) -> None:
        txid = e.txid
        if e.commit:
            return  # handled at delivery, in total order
        self.group_txs.discard(txid)
        if self.formation.owns(txid):
            self._form(Aborted(txid, bool(self.state.members)))  # l. 46: repeat
        key = self.lock_keys.pop(txid, None)
        if key is not None and self.locked == key and (self.attempt is None or self.attempt.key != key):
            # ll. 152-155 on every participant, not only the proposer: a member that stayed locked after the
            # membership transaction aborted would hold its global-state changes forever
            self._unlock()
        w = self.writes.pop(txid, None)
        if w is not None:
            self._retry_write(w, "aborted")
        if txid in self.seq.inflight:  # (only our own batches concern the sequencer)
            self._seq(BatchAborted(txid))
        a = self.attempt
        if a is not None and txid == a.txid:  # l. 134-135 / l. 103: remove aborted
            self.attempt = None
            self._retry_later()
        elif a is not None and txid == a.membership_txid:  # l. 152-157
            self.attempt = None
            if self.locked == a.key:
                self._unlock()
            self._retry_later()

    def _on_deliver(self, e: Deliver) -> None:
        self.group_txs.discard(e.txid)
        self.lock_keys.pop(e.txid, None)
        if self.formation.owns(e.txid):
            self._form(FDelivered(e.txid))
        if e.txid in self.state.recent:
            return  # already applied from the sponsor's forwarded stream
        joining = not self.direct_q and not self.is_member() and self._needs_state(e.payload)
        if joining or self.xfer.catching_up():  # a new member: the state transfer buffers it
            self._xfer(Delivered(e.txid, e.payload, joining))
        else:
            self._apply(e.txid, e.payload, direct=True)

    def _needs_state(self, payload: bytes) -> bool:
        """A non-member delivers a transaction: the one that adds it to an existing group (it must first
        hold the state before it), or one that creates a group (formation, or our own group of one)."""
        try:
            tx = decode_tx(payload)
        except GroupTxError:
            return True
        if type(tx) is TxFormation:
            return False
        return not (type(tx) is TxMembership and tx.proposer == self.me and not self.state.members)

    # ------------------------------------------------------------------ applying the global sequence

    def _apply(self, txid: TxId, payload: bytes, direct: bool) -> None:
        was_member = self.is_member()
        was_leader = self._leader_now()
        res = self.state.apply(txid, payload)
        h = self.state.content_hash() if self.config.hash_every_apply else ""
        st = self.state
        front = st.members[0].proc if st.members else None
        self.out.append(AppliedTx(res.seq, txid, res.kind, payload, h, res.ddb_result, st.view, front))
        for a in sorted(self.sponsees):  # l. 61: forward to every applicant we sponsor (sorted: deterministic)
            self._send(a, StateForward(res.seq, txid, payload))
        if self.xfer.requests:  # state requests waiting for a transaction to be applied here
            self._xfer(Applied(txid, res.seq))
        try:
            tx = decode_tx(payload)
        except GroupTxError:
            tx = None
        if res.view_changed:
            st = self.state
            self.out.append(
                ViewChange(
                    st.view, res.seq, tuple(st.members), res.removed, res.added, txid, st.genesis, st.group_correct
                )
            )
            self._log(
                "view",
                view=self.state.view,
                members=[f"{m.name}.{m.inc}" for m in self.state.members],
                removed=[m.name for m in res.removed],
                added=[m.name for m in res.added],
            )
            for m in self.state.members:
                if m.proc != self.me:
                    self._connect(m.name, m.addr)
                    self.core.add_peer(self._now, m.name, m.inc)
            for m in res.removed:
                if m.proc != self.me:
                    self.core.mark_dead(self._now, m.name, m.inc, "removed")
                    self.join_list.pop(m.proc, None)
        w = self.writes.pop(txid, None)
        if w is not None:
            self.out.append(WriteDone(w.req, True, txid, res.seq, res.error, res.ddb_result))
        if type(tx) is TxSeq:
            self._seq(BatchApplied(txid, res.seq, cast("tuple[SeqApplied, ...]", res.ddb_result)))
        elif txid in self.seq.inflight:  # (our batch, but it did not decode as one: cannot happen)
            self._seq(BatchApplied(txid, res.seq, ()))
        if res.view_changed and self.seq.pending:  # (Retarget does nothing without pending writes)
            self._seq(Retarget())
        if not (direct or self.is_member()):
            return  # an applicant following its sponsor's stream: state only
        if res.stale:
            self._on_stale(txid)
        elif isinstance(tx, TxRemove):
            if was_member:
                self._on_remove_committed(tx)
        elif isinstance(tx, TxMembership):
            self._on_membership_committed(txid, tx, was_member)
        elif isinstance(tx, TxFormation):
            self._on_formation_committed(tx)
        if self.is_member() and not was_leader and self._leader_now():
            self._log("leader", view=self.state.view)

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
        if not self.is_member():
            self._removed()
            return
        self.leave_list &= {m.proc for m in self.state.members}  # l. 120
        if self._leader_now():  # ll. 121-126
            self._sponsor_all()
        key = tx.key or None
        self.locked = key  # l. 127
        if key is not None:  # ll. 128-130
            self._send(tx.proposer, Locked(key))
            if tx.proposer == self.me:
                self._on_locked(self.me, key)
        else:
            self._propose_held()  # l. 132
        a = self.attempt
        if a is not None and a.stage == "remove" and tx.proposer == self.me and key == (a.key or None):
            if key is None:  # l. 103 first case, then ll. 108-109
                self.attempt = None
                self.updating = False
            else:
                a.stage = "locking"
        self._update()  # l. 133

    def _on_membership_committed(self, txid: TxId, tx: TxMembership, was_member: bool) -> None:
        """ll. 136-151."""
        new = {m.proc for m in tx.members}
        if tx.proposer == self.me:  # ll. 137-139
            self.sponsees -= new
        for p in list(self.join_list):  # l. 140
            if p in new:
                del self.join_list[p]
        self.leave_list &= new  # l. 143
        if self.me not in new:
            if was_member or self.leaving:
                self._removed()
            return
        if not was_member:
            self._log("joined", view=self.state.view, tx=str(txid))
            self.sponsor = None
        self.locked = None  # l. 144
        self._propose_held()  # l. 145
        a = self.attempt
        if a is not None and a.membership_txid == txid:
            self.attempt = None
        self.updating = False  # l. 150
        if self._leader_now():
            self._sponsor_all()  # docs/membership.md: a new leader sponsors waiting applicants
        self._update()  # l. 151

    def _on_formation_committed(self, tx: TxFormation) -> None:
        """ll. 166-179 (the state part, ll. 167-171 and 178, is in GlobalState.apply)."""
        new = {m.proc for m in tx.members}
        for p in list(self.join_list):  # l. 168
            if p in new:
                del self.join_list[p]
        self.leave_list &= new  # l. 171
        if self._leader_now():  # ll. 172-177
            self._sponsor_all()
        self._update()  # l. 179

    def _removed(self) -> None:
        """This incarnation is no longer a member: after a leave, stop (l. 17); otherwise re-apply as a new
        incarnation (docs/membership.md)."""
        if self.left:
            return
        if self.leaving:
            self.left = True
            self._log("left", view=self.state.view)
            self.out.append(Left())
        else:
            self._log("removed", view=self.state.view)
            self.out.append(Reincarnate(by=self.name))
            self.left = True

    # ------------------------------------------------------------------ updateMembership (ll. 76-109)

    def _group_tx_in_progress(self) -> bool:
        return bool(self.group_txs)

    def _update(self) -> None:
        if self.left or not self.is_member():
            return
        if self.updating or self._group_tx_in_progress():  # l. 77-78
            return
        procs = self.state.procs()
        rl = self._remove_list()
        cand = [p for p in procs if p not in rl]
        if not cand or cand[0] != self.me:  # l. 79
            return
        cur = {p for p in procs if p not in rl and p not in self.leave_list}  # l. 82
        gc = self.state.group_correct
        potential: list[Proc] = []
        for a in self.join_list:  # ll. 83-87
            if self._suspected(a) or a not in self.sponsees or (not gc and a[0] not in self.core_names):
                continue  # l. 84-85: disqualified
            if cur <= self.conns_of.get(a, set()):
                potential.append(a)
        accept: list[Proc] = []
        for a in list(potential):  # ll. 88-91
            if a not in potential:
                continue
            conns = self.conns_of.get(a, set())
            if set(accept) <= conns:
                potential = [x for x in potential if x == a or x in conns]
                accept.append(a)
        if not gc and len(accept) < self.c_f:  # l. 92-93
            accept = []
        leave = {p for p in self.leave_list if p in set(procs) or p in self.join_list}
        if not (accept or rl or leave):  # l. 94
            return
        if rl and not self._quorum(tuple(rl)):
            self._log("removal_waits_for_quorum", suspected=[p[0] for p in sorted(rl)])
            return
        active = [p for p in procs if p not in rl]  # l. 95
        removal = tuple(sorted(rl))  # l. 96
        self.updating = True  # l. 97
        if not accept and not leave:  # ll. 98-99
            key = ""
        else:  # l. 101
            self.key_seq += 1
            key = f"{self.name}.{self.inc}.{self.key_seq}"
        tx = TxRemove(key, self.me, removal)
        txid = self.core.propose_to(self._now, encode_tx(tx), active)  # l. 102
        self.group_txs.add(txid)
        members = [Member(a[0], a[1], self.join_list[a]) for a in accept]
        self.attempt = _Attempt(txid, key, active, members, "remove")
        self._log(
            "update_membership",
            tx=str(txid),
            removal=[f"{p[0]}.{p[1]}" for p in removal],
            accept=[m.name for m in members],
            leave=[p[0] for p in leave],
            lock=bool(key),
        )

    def _retry_later(self) -> None:
        """l. 109 after a failed attempt: updateMembership() again, after `retry_backoff` (the pseudo-code
        retries at once, which spins while a false suspicion lasts)."""
        self.updating = True  # nothing new starts until the retry
        self._timer("retry", self._now + self.config.retry_backoff)

    def _vote_remove(self, tx: TxRemove) -> bool:
        """ll. 110-116: vote for a removal only from the accepted leader (the first member not to be removed),
        removing only members this host suspects too (weak validity), and leaving a quorum (`_quorum`).
        (`haactl verify --mutate no-weak-validity` replaces this method by one that always votes yes.)"""
        rl = self._remove_list()
        cand = [m.proc for m in self.state.members if m.proc not in rl]
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
        procs = [p for p in self.state.procs() if not self._superseded(p)]
        gone = {p for p in removal if not self._superseded(p)}
        if not gone:
            return True
        stay = [p for p in procs if p not in gone]
        n = len(procs)
        if 2 * len(stay) > n:
            return True
        return 2 * len(stay) == n and bool(procs) and procs[0] in stay

    def _superseded(self, p: Proc) -> bool:
        """A newer incarnation of p's host has been heard of: p is not running."""
        peer = self.core.peers.get(p[0])
        return p != self.me and peer is not None and peer.inc > p[1]

    def _on_locked(self, src: Proc, key: str) -> None:
        a = self.attempt
        if a is not None and a.key == key and a.stage in ("remove", "locking"):
            a.locks.add(src)

    def _lock_wait_over(self, a: _Attempt) -> bool:
        """l. 103: every active member answered the lock or is suspected, and all active OACs are decided.
        (`--mutate no-lock-wait` replaces this and `_all_locked` by methods that never wait.)"""
        for q in a.active:
            if q not in a.locks and not self._suspected(q):
                return False
        # "all active OACs are decided"
        return all(not (tx.content and tx.state == UNDECIDED) for tx in self.core.oac.txs.values())

    def _all_locked(self, a: _Attempt) -> bool:
        """l. 104: every active member locked (otherwise the attempt fails)."""
        return all(q in a.locks for q in a.active)

    def _poll(self) -> None:
        """Re-check the waits of l. 103 (and the new member's catch-up) after every input."""
        a = self.attempt
        if a is None or a.stage != "locking" or self.left:
            return
        if not self._lock_wait_over(a):
            return
        if self._all_locked(a):  # l. 104
            leave = self.leave_list
            new = [m for m in self.state.members if m.proc not in leave]  # l. 105
            have = {m.proc for m in new}
            new += [m for m in a.accept if m.proc not in have and m.proc not in leave]
            mtx = TxMembership(a.key, self.me, tuple(new))
            parts = list(dict.fromkeys([*a.active, *(m.proc for m in a.accept)]))
            a.stage = "membership"
            a.membership_txid = self.core.propose_to(self._now, encode_tx(mtx), parts)  # l. 106
            self.group_txs.add(a.membership_txid)
            self._log("membership_proposed", tx=str(a.membership_txid), members=[m.name for m in new])
            if not new:  # every member asked to leave: the group dissolves (`TxMembership`)
                self._log("group_dissolving", leaving=sorted(q[0] for q in leave))
        else:  # ll. 107-109
            self.attempt = None
            self._retry_later()

    # ------------------------------------------------------------------ global-state changes

    def _propose_write(self, w: _Write) -> None:
        if w.seq:
            self._seq(Submit(w.req, w.payload))
            return
        w.attempts += 1
        txid = self.core.propose_to(self._now, w.payload, self.state.procs())
        self.writes[txid] = w

    def _retry_write(self, w: _Write, why: str) -> None:
        if w.attempts >= self.config.max_write_attempts:
            self.out.append(WriteDone(w.req, False, None, 0, f"gave up after {w.attempts} attempts ({why})"))
            return
        if self.locked is not None or not self.is_member() or self.direct_q:
            if self.is_member():
                self.held.append(w)
            else:
                self.out.append(WriteDone(w.req, False, None, 0, "no longer a member of the group"))
            return
        self._propose_write(w)

    def _propose_held(self) -> None:
        """ll. 132, 145, 155: propose the changes held while locked."""
        if self.locked is not None or self.direct_q:
            return
        held, self.held = self.held, []
        for w in held:
            self._propose_write(w)

    def _unlock(self) -> None:
        self.locked = None
        self._propose_held()
        if self.seq.queue:  # (Flush proposes queued writes: nothing to do without them)
            self._seq(Flush())

    # ------------------------------------------------------------------ the sequencer (docs/oac.md)

    def _seq(self, inp: SeqInput) -> None:
        """Step the sequencer and carry out its effects, in order."""
        for e in self.seq.step(self._now, inp):
            match e:
                case Send():
                    self.out.append(e)
                case SetTimer():
                    self.out.append(e)
                case WriteDone():
                    self.out.append(e)
                case ProposeBatch(entries):
                    txid = self.core.propose_to(self._now, encode_tx(TxSeq(entries)), self.state.procs())
                    self._seq(Proposed(txid))
                case Count(name, n):
                    self.core.counters[name] += n
                case _:
                    assert_never(e)

    # SeqHost: what the sequencer reads of this node

    def has_left(self) -> bool:
        return self.left

    def may_batch(self) -> bool:
        return self.locked is None and not self.direct_q and not self.left and self.is_member()

    def sequencer(self) -> Proc | None:
        """The sequencer this host forwards to: the highest-ranked member it does not suspect (the leader of
        Alg. 3 l. 79 as this host sees it; every member agrees on it while nobody is suspected)."""
        for m in self.state.members:
            if not self._suspected(m.proc) and not self._known_dead(m.proc):
                return m.proc
        return None

    def settled(self, origin: Proc, cseq: int) -> bool:
        d = self.state.seq_origins.get(origin)
        return d is not None and (cseq < d.floor or cseq in d.done)

    # ------------------------------------------------------------------ sponsoring and state transfer

    def _sponsor(self, a: Proc) -> None:
        """ll. 58-61 (and 123-126, 174-177)."""
        self.sponsees.add(a)
        self._send(a, Sponsor())
        self._send(a, StateSnapshot(self.state.seq, self.state.snapshot(), None, 0))

    def _sponsor_all(self) -> None:
        for a in list(self.join_list):
            if a not in self.sponsees and not self._known_dead(a):
                self._sponsor(a)

    def _xfer(self, inp: XferInput) -> None:
        """Step the state transfer and carry out its effects, in order; after an `ApplyTx` or a `Restore`
        step it with `Continue` (a loop, not recursion: a joiner may drain thousands of transactions)."""
        effects = self.xfer.step(self._now, inp)
        while effects:
            more = False
            for e in effects:
                match e:
                    case ApplyTx(txid, payload, direct):
                        self._apply(txid, payload, direct)
                        more = True
                    case Restore(data):
                        self._restore(data)
                        more = True
                    case SendSnapshot(to, anchor, anchor_seq):
                        self._send(to, StateSnapshot(self.state.seq, self.state.snapshot(), anchor, anchor_seq))
                    case Send(dst, dst_inc, msg):
                        self._send((dst, dst_inc), msg)
                    case SetTimer() | Log():
                        self.out.append(e)
                    case CaughtUp():
                        self._propose_held()
                    case Rejected(reason):
                        self.counters["rejected_snapshot"] += 1
                        self._log("reject", reason=reason)
                    case _:
                        assert_never(e)
            effects = self.xfer.step(self._now, Continue()) if more else []

    def _restore(self, data: bytes) -> None:
        try:
            self.state.restore(data)
        except GroupTxError as e:
            self.counters["rejected_snapshot"] += 1
            self._log("reject", reason=str(e))
            return
        for m in self.state.members:
            if m.proc != self.me:
                self.addrs.setdefault(m.name, m.addr)

    # XferHost: what the state transfer reads of this node (`state`, `is_member`)

    def request_target(self, txid: TxId) -> Proc:
        """A catching-up member asks the first unsuspected member that is not itself, else its sponsor, else
        the proposer of the transaction that added it."""
        for m in self.state.members:
            if m.proc != self.me and not self._suspected(m.proc):
                return m.proc
        if self.sponsor is not None:
            return self.sponsor
        return (txid.host, txid.inc)

    @property
    def direct_q(self) -> list[tuple[TxId, bytes]]:
        """What a new member delivered and holds until its state has caught up (read by the agent layer and
        the simulator)."""
        return self.xfer.direct_q

    # ------------------------------------------------------------------ membership messages

    def _on_group(self, src: str, src_inc: int, msg: Message) -> None:
        q = (src, src_inc)
        if self.left:
            return
        if isinstance(msg, Apply):
            self._on_apply(q, msg.addr)
        elif isinstance(msg, Introduce):
            self._on_introduce(q, msg)
        elif isinstance(msg, Sponsor):  # ll. 71-73
            if not self.is_member():
                self.sponsor = q
                self._send(q, Connections(self._two_way()))
        elif isinstance(msg, Connections):  # ll. 74-75
            self.conns_of[q] = set(msg.peers)
            self._update()
        elif isinstance(msg, Leave):
            self._on_leave(q)
        elif isinstance(msg, Locked):
            self._on_locked(q, msg.key)
        elif isinstance(msg, StateForward):
            self._xfer(Forward(msg.seq, msg.txid, msg.payload))
        elif isinstance(msg, StateSnapshot):
            self._xfer(Snapshot(msg.seq, msg.data, msg.anchor, msg.anchor_seq))
        elif isinstance(msg, StateRequest):
            self._xfer(Request(q, msg.txid))
        elif isinstance(msg, SeqWrite):
            self._seq(Forwarded(q, msg.floor, msg.writes))

    def _on_apply(self, a: Proc, addr: str) -> None:
        """ll. 50-61."""
        if self.state.is_member(a) or self._known_dead(a):
            return
        # introduce a to everyone (l. 56) when we first hear of it, and again once our view has changed since:
        # a host that was itself applying when `a` applied to it knew no members then (docs/membership.md)
        here = (self.state.genesis, self.state.view)
        fresh = a not in self.join_list or self.introduced.get(a) != here
        self.join_list[a] = addr  # l. 51
        self.conn_from.add(a)  # l. 52
        self._connect(a[0], addr)  # l. 53
        self.conn_to.add(a[0])  # l. 54
        gid = self.state.group_id()
        self._send(a, Introduce(self.name, self.inc, self.addr, gid))  # l. 55
        if fresh:
            self.introduced = {p: v for p, v in self.introduced.items() if p in self.join_list}
            self.introduced[a] = here
            for p in [*self.state.procs(), *self.join_list]:  # l. 56
                if p != a and p != self.me:
                    self._send(p, Introduce(a[0], a[1], addr, gid))
        if self._leader_now():  # ll. 57-61
            if a not in self.sponsees:
                self._sponsor(a)
            else:
                # an applicant we sponsor applies again: it lost track of its sponsor (a stale leader's Sponsor,
                # sent after a pause, replaced ours and then died); tell it again (docs/membership.md, "sponsor")
                self._send(a, Sponsor())
        # an applicant that another applicant applied to (a host it knew from a previous life) gains a two-way
        # link here, and no introduction follows: tell the sponsor now, as ll. 69-70 do on an introduction
        self._report_connections()
        self._update()

    def _on_introduce(self, q: Proc, msg: Introduce) -> None:
        """ll. 62-70."""
        a = (msg.name, msg.inc)
        if msg.group:
            self._group_evidence(msg.group)
        if a == self.me or self._known_dead(a):
            return
        # the first word from this incarnation itself: our link to its host name may date from an earlier
        # incarnation, which is no connection to this one (docs/membership.md, "lost introductions")
        first = a == q and q not in self.conn_from
        if a == q:  # ll. 63-64
            self.conn_from.add(q)
            if msg.group and not self.is_member() and not self.leaving and q[0] not in self.group_hosts:
                # a member of a correct group: apply to it too, so that the leader (which need not be a core
                # process) hears our application and sponsors us (l. 57); docs/membership.md
                self.group_hosts[q[0]] = None
                if q[0] not in self.core_names and (self.sponsor is None or self._suspected(self.sponsor)):
                    self._send(q, Apply(self.addr))
        if a[0] not in self.conn_to or (a != q and a not in self.conn_from) or first:  # ll. 65-68
            # (also when we "opened" the link before but never heard from `a`: our `apply` or introduction
            # may have reached it before it was running; docs/membership.md, "lost introductions")
            self._connect(a[0], msg.addr)
            self.conn_to.add(a[0])
            # a relayed introduction (a != q) is hearsay about a's incarnation (HostCore._believe_hearsay)
            self.core.add_peer(self._now, a[0], a[1], hearsay=a != q)
            self._send(a, Introduce(self.name, self.inc, self.addr, self.state.group_id()))
        elif msg.addr:
            self.addrs.setdefault(a[0], msg.addr)
            self.core.add_peer(self._now, a[0], a[1], hearsay=a != q)
        self._report_connections()  # ll. 69-70

    def _report_connections(self) -> None:
        """ll. 69-70: an applicant tells its sponsor whom it is connected to both ways."""
        if not self.is_member() and self.sponsor is not None:
            self._send(self.sponsor, Connections(self._two_way()))

    def _group_evidence(self, gid: str) -> None:
        """docs/membership.md, "restarts": someone holds the state of a correct group `gid`."""
        self.group_seen = gid
        st = self.state
        if st.members and not st.group_correct and st.genesis != gid and self.is_member():
            self._log("provisional_group_abandoned", group=st.genesis, existing=gid)
            self.left = True
            self.out.append(Reincarnate(by=self.name))

    def _on_leave(self, q: Proc) -> None:
        """ll. 18-21. An applicant that leaves also withdraws its application: it is dropped from the join
        list (the pseudo-code keeps it there, and a later update would accept a host that is gone)."""
        if self.state.is_member(q) or q in self.join_list:
            self.leave_list.add(q)
            if not self.state.is_member(q):
                del self.join_list[q]
                self.sponsees.discard(q)
                self.conns_of.pop(q, None)
                self._log("application_withdrawn", applicant=f"{q[0]}.{q[1]}")
            self._update()

    # ------------------------------------------------------------------ failure detector changes

    def _on_suspicion_change(self, p: Proc, suspected: bool) -> None:
        """ll. 22-31 (removeList_p itself is computed on demand)."""
        if self.state.is_member(p) or p in self.join_list:
            self._update()
        if self.state.is_member(p) and self.seq.pending:
            self._seq(Retarget())

    def _on_peer_dead(self, p: Proc) -> None:
        """ll. 32-34."""
        if p in self.join_list:
            del self.join_list[p]
        self.sponsees.discard(p)
        self.conns_of.pop(p, None)
        if self.sponsor == p:
            self.sponsor = None
        self._update()
        if self.seq.pending:
            self._seq(Retarget())

    # ------------------------------------------------------------------ introspection

    def status(self) -> dict[str, Any]:
        st = self.state
        lead = st.leader()
        return {
            "name": self.name,
            "incarnation": self.inc,
            "member": self.is_member(),
            "members": [m.name for m in st.members],
            "leader": lead.name if lead else "",
            "view": st.view,
            "rank": next((i for i, m in enumerate(st.members) if m.proc == self.me), -1),
            "group_correct": st.group_correct,
            "seq": st.seq,
            "locked": self.locked or "",
            "applicants": [p[0] for p in self.join_list],
            "suspected": sorted(m.name for m in st.members if self._suspected(m.proc)),
            "ddb_size": st.ddb.size,
            "state_hash": st.content_hash(),
        }
