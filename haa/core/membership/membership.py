"""Host membership service HAA-HM (thesis §4.6, Appendix II Alg. 3, thesis L2358-2565), as a sans-I/O node.

`MembershipNode` is everything one host incarnation decides once it takes part in a group: it owns a
`HostCore` (failure detector + OAC, `haa.core.host.hostcore`) and the group's `GlobalState` (member list, view, DDB,
`haa.core.membership.globalstate`), and runs Alg. 3 on top. It is composed of machines that own their state and take
one `step(now, input)` returning effects, which the node carries out in order (`_form`, `_join`, `_up`,
`_xfer`, `_seq`):

* `haa.core.membership.formation.Formation` — formation by the first core process (ll. 41-43) and the
  FORMATION_TIMEOUT fallback with OAC(formationFallback) by the core head (ll. 44-49), and its vote
  (ll. 158-165);
* `haa.core.membership.join.Join` — apply / introduce / sponsor / connections (ll. 35-39, 50-75): an applicant contacts
  every core process, everyone who hears of it introduces it to everyone else, the leader sponsors it;
* `haa.core.membership.update.MembershipUpdate` — updateMembership (ll. 76-109): the leader commits OAC(remove) —
  removing members that every remaining member suspects (l. 113, HM-Weak-Validity) and, when members join or
  leave, locking the global state — waits for every lock acknowledgement and for every OAC it knows to be
  decided, then commits OAC(membership) with the new list, which unlocks; the votes on remove transactions
  (ll. 110-116) and the outcomes of the group transactions (ll. 117-157, 166-179);
* `haa.core.membership.statetransfer.StateTransfer` — the joiner's side of "send global state to a" (ll. 58-61,
  123-126, 174-177): the sponsor's snapshot and forwarded stream, catching up, state requests;
* `haa.core.membership.sequencer.Sequencer` — DDB and test writes forwarded to one sequencer and batched
  (docs/oac.md), held while the global state is locked (ll. 127-132).

The node itself routes inputs to them, keeps the address book and the links ("open connection to"),
applies the global sequence in total order (`_apply`: forwarding to sponsees, l. 61, view changes, then the
machines' part of each committed group transaction), and carries the global-state changes of `submit`:
agent-table transactions (and, without the sequencer, DDB batches and test payloads) are proposed to every
member by OAC, held while locked (ll. 127-132, 144-145, 153-155), acknowledged to the requester only once
committed, and re-proposed after an abort (held instead while this host suspects a member: until the
suspicion ends or the view changes, `haa.core.membership.groupwrites`); and voluntary leave (ll. 14-21).

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

from collections.abc import Hashable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, assert_never, cast

from haa.core.ddb.objects import MAX_BATCH_OPS
from haa.core.effects import Decided, Deliver, Effect, Log, PeerDead, Reincarnate, Send, SetTimer, Suspicion
from haa.core.host.hostcore import AppMessage, CoreConfig, GroupMessage, HostCore, VoteRequest
from haa.core.inputs import FdReport, LeaveGroup, NodeInput, PeerInfo, Receive, TimerFired
from haa.core.inputs import Start as NStart
from haa.core.inputs import Submit as NSubmit
from haa.core.membership.formation import (
    Aborted,
    DiscoveryDue,
    Formation,
    FormationConfig,
    FormationDue,
    FormationEffect,
    FormationInput,
    FormGroupOfOne,
    ProposeFallback,
)
from haa.core.membership.formation import Delivered as FDelivered
from haa.core.membership.formation import Start as FStart
from haa.core.membership.globalstate import (
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
from haa.core.membership.groupeffects import AppliedTx, Connect, Left, NodeEffect, NodeTimer, ViewChange, WriteDone
from haa.core.membership.groupleave import (
    Abandoned,
    Excluded,
    GroupLeave,
    LeaveCalled,
    LeaveEffect,
    LeaveSelf,
    RemovedHere,
)
from haa.core.membership.groupwrites import Aborted as WAborted
from haa.core.membership.groupwrites import Committed as WCommitted
from haa.core.membership.groupwrites import GroupWrites, ProposeWrite, WritesEffect
from haa.core.membership.groupwrites import Release as WRelease
from haa.core.membership.groupwrites import Request as WRequest
from haa.core.membership.join import (
    Abandon,
    Admitted,
    Hear,
    Heard,
    Join,
    Joined,
    JoinEffect,
    JoinInput,
    Link,
    MarkRemoved,
    PeerGone,
    ReapplyDue,
    Remember,
    RunUpdate,
    SendState,
    SponsorAll,
    ToHost,
    ViewChanged,
    Withdraw,
)
from haa.core.membership.join import Start as JStart
from haa.core.membership.nodeview import NodeView
from haa.core.membership.sequencer import (
    BatchAborted,
    BatchApplied,
    Count,
    Flush,
    Forwarded,
    ProposeBatch,
    Retarget,
    RetryDue,
    SeqConfig,
    SeqEffect,
    SeqInput,
    Sequencer,
    Submit,
)
from haa.core.membership.sequencer import Release as SRelease
from haa.core.membership.statetransfer import (
    Applied,
    ApplyTx,
    CatchupDue,
    CaughtUp,
    Continue,
    Delivered,
    Forward,
    InheritLock,
    Rejected,
    Request,
    Restore,
    SendSnapshot,
    Snapshot,
    StateTransfer,
    XferEffect,
    XferInput,
)
from haa.core.membership.update import (
    Admit,
    GroupOfOne,
    GroupTxApplied,
    LeaveAsked,
    LockedMsg,
    LockInherited,
    MembershipUpdate,
    NowMember,
    Poll,
    ProposeHeld,
    ProposeTx,
    Removed,
    Run,
    SuspicionChanged,
    TxAborted,
    TxDelivered,
    Unlocked,
    UpdateEffect,
    UpdateInput,
    Withdrawn,
)
from haa.core.membership.update import RetryDue as URetryDue
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

Proc = tuple[str, int]

#: what the machines' steps return, carried out by `MembershipNode._carry` (the state transfer's by `_xfer`)
MachineEffect = FormationEffect | JoinEffect | UpdateEffect | WritesEffect | SeqEffect | LeaveEffect | XferEffect

__all__ = ["AppliedTx", "Connect", "Left", "MembershipNode", "NodeConfig", "NodeEffect", "NodeTimer", "ViewChange",
           "WriteDone"]


# ------------------------------------------------------------------------------------------------ config


#: a global state larger than this crosses a link in parts of this size (`MembershipNode._send_snapshot`): the
#: largest agent message (`MAX_AGENT_MESSAGE`), so a part costs a link what other traffic already may, and a
#: state of any size joins through frames bounded by `MAX_MESSAGE` (64 MiB; a 72 MiB state used to fail every
#: link to the joiner with "INTERNAL: Internal error from Core")
SNAPSHOT_PART = 4 * 1024 * 1024
#: the most a host gathers of a state in parts from one sender (a memory guard; the DDB alone is bounded to
#: `MAX_DDB_BYTES`, and the agent table by its agents' bounded configs, states, backups and queues)
MAX_SNAPSHOT_BYTES = 1024 * 1024 * 1024


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
    #: a global-state change aborted this many times is reported failed (aborts while this host suspects a
    #: member are not counted: the change waits for the suspicion to end, `haa.core.membership.groupwrites`)
    max_write_attempts: int = 50
    #: compute the content hash after every applied transaction (the simulator's checks)
    hash_every_apply: bool = False
    #: DDB and test writes go through the sequencer: forwarded to the leader, batched into one OAC with the
    #: other members' writes, applied once per (origin, cseq) (docs/oac.md, "The sequencer"); False: every
    #: member proposes its own writes (Alg. 3 as printed: concurrent proposers, order conflicts)
    sequencer: bool = True
    #: sequencer batches of one host in OAC at a time (writes forwarded meanwhile wait and go out together)
    seq_inflight: int = 1
    #: at most this many writes / payload bytes in one sequencer batch
    seq_max_entries: int = 1024
    seq_max_bytes: int = 4 << 20
    #: a forwarded write not applied within this long is forwarded again (to the sequencer of the moment)
    seq_retry: float = 2.0
    #: ... and given up after this long (reported "may still commit": a copy may be in a batch somewhere)
    seq_abandon: float = 60.0
    #: at most this much apply cost (the writes' DDB ops) in one sequencer batch (haa.core.ddb.objects.MAX_BATCH_OPS)
    seq_max_cost: int = MAX_BATCH_OPS

    def core_bounds(self, core_names: tuple[str, ...]) -> tuple[int, int]:
        """(c_f, c_H) for this core process list (l. 1), checked: c_f < c/2 and c_f < c_H <= c."""
        if len(set(core_names)) != len(core_names) or not core_names:
            raise ValueError("core process list must be non-empty and without duplicates")
        c = len(core_names)
        c_f = self.c_f if self.c_f is not None else (c - 1) // 2
        if not c_f >= 0 or not 2 * c_f < c:
            raise ValueError(f"c_f = {c_f} violates c_f < c/2 with c = {c}")
        c_h = self.c_h if self.c_h is not None else min(c, c_f + 1)
        if not c_f < c_h <= c:
            raise ValueError(f"c_H = {c_h} violates c_f < c_H <= c")
        return c_f, c_h

    def __post_init__(self) -> None:
        if self.seq_inflight < 1 or self.seq_max_entries < 1 or self.seq_max_bytes < 1:
            raise ValueError("seq_inflight, seq_max_entries and seq_max_bytes must be at least 1")
        for n in ("formation_timeout", "formation_retry", "discovery", "reapply", "catchup_timeout", "retry_backoff",
                  "seq_retry", "seq_abandon"):
            if getattr(self, n) <= 0:
                raise ValueError(f"{n} must be positive")


# ------------------------------------------------------------------------------------------------ node


class MembershipNode:
    """One host incarnation running Alg. 3 over its `HostCore` (see the module docstring). Inputs go through
    `step(now, input)` (`haa.core.inputs`); after each the driver calls `drain()` and carries out the effects
    (`haa.core.effects` and `haa.core.membership.groupeffects`)."""

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
        self.name, self.inc, self.addr = name, inc, addr
        self.me: Proc = (name, inc)
        self.core_names = tuple(n for n, _ in core_processes)  # l. 1
        self.c_f, self.c_h = cfg.core_bounds(self.core_names)
        self.addrs: dict[str, str] = dict(core_processes)
        #: hosts a previous incarnation knew as members (`--data-dir`): a restarted host applies to them too,
        #: so that it finds its group even when every core process is down or is itself (docs/membership.md)
        self.known_hosts = [(n, a) for n, a in known_hosts if n != name and n not in self.addrs]
        for n, a in self.known_hosts:
            self.addrs[n] = a
        self.addrs[name] = addr
        self.core = HostCore(name, inc, [n for n in self.core_names if n != name], cfg.core, accept_group=True)
        #: node effects go through the core's outbox, in order (so it holds both kinds)
        self.out = cast("list[Effect | NodeEffect]", self.core.out)
        self.state = GlobalState(self.core_names, self.c_f)
        #: what the machines read of this node (their host protocols)
        self.view = v = NodeView(self)
        self.formation = Formation(self.me, addr, self.core_names, self.c_h, v,
                                   FormationConfig(cfg.formation_timeout, cfg.formation_retry, cfg.discovery))
        self.join = Join(self.me, addr, self.core_names, [n for n, _ in self.known_hosts], v, cfg.reapply)
        self.upd = MembershipUpdate(self.me, self.c_f, self.core_names, v, cfg.retry_backoff)
        self.wr = GroupWrites(v, cfg.max_write_attempts)
        self.lv = GroupLeave(self.me, v)
        self.xfer = StateTransfer(self.me, v, cfg.catchup_timeout)
        self.seq = Sequencer(self.me, v, SeqConfig(cfg.seq_inflight, cfg.seq_max_entries, cfg.seq_max_bytes,
                                                   cfg.seq_retry, cfg.seq_abandon, cfg.seq_max_cost))
        self.started = False
        self._now = 0.0
        #: peers that refused this process because another one under its name is live there (never forms alone)
        self.live_elsewhere: set[str] = set()
        #: a state in parts being received, per sender: (seq, anchor, anchor_seq, parts, slices, bytes so far)
        self._parts: dict[Proc, tuple[int, TxId | None, int, int, list[bytes], int]] = {}

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
        """Effects of the last input (OAC decisions on group transactions are consumed here, and passed on)."""
        res: list[Effect | NodeEffect] = []
        core = self.core
        while True:
            effects = cast("list[Effect | NodeEffect]", core.drain())  # the shared outbox (see __init__)
            if not effects:
                if self.upd.attempt is not None:  # re-check the waits of l. 103 after every input
                    self._up(Poll())
                if not core.out:
                    break
                continue
            for e in effects:
                if isinstance(e, Reincarnate) and self.lv.leaving:  # leaving anyway (GroupLeave, `Excluded`)
                    fx = self.lv.step(self._now, Excluded(e.by))  # its Log goes out next round, Left now
                    self.out += [x for x in fx if isinstance(x, Log)]
                    res += [x for x in fx if isinstance(x, Left)]
                    continue
                res.append(e)
                if isinstance(e, Deliver):
                    self._on_deliver(e)
                elif isinstance(e, Decided):
                    self._on_decided(e)
                elif isinstance(e, Suspicion):  # ll. 22-31 (removeList_p itself is computed on demand)
                    self._up(SuspicionChanged((e.peer, e.inc)))
                    if self.state.is_member((e.peer, e.inc)) and self.seq.pending:
                        self._seq(Retarget())
                    if not e.suspected and self.wr.held:  # l. 26: writes held since an abort under suspicion
                        self._carry(self.wr.step(self._now, WRelease()))
                elif isinstance(e, PeerDead):  # ll. 32-34
                    self._join(PeerGone((e.peer, e.inc)))
                    if self.seq.pending:
                        self._seq(Retarget())
        return res

    def note_live_elsewhere(self, peer: str) -> bool:
        """`peer` refused this process: another process under this host's name is live there. From now on this
        host never forms a group of its own (`NodeView.may_form`); True the first time."""
        if peer in self.live_elsewhere:
            return False
        self.live_elsewhere.add(peer)
        self.counters["refused_name_in_use"] += 1
        return True

    def _send(self, dst: Proc, msg: Message) -> None:
        if dst != self.me:
            self.out.append(Send(dst[0], dst[1], msg))

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

    def is_member(self) -> bool:
        return self.state.is_member(self.me)

    def status(self) -> dict[str, Any]:
        return self.view.status()

    @property
    def direct_q(self) -> list[tuple[TxId, bytes]]:
        """What a new member delivered and holds until its state has caught up (read by the agent layer and
        the simulator)."""
        return self.xfer.direct_q

    # ------------------------------------------------------------------ inputs

    def step(self, now: float, inp: NodeInput) -> AppMessage | None:
        """One input (`haa.core.inputs`); effects accumulate for `drain()`. An agent-layer message that passed
        the core's checks is returned (for the agent layer on top, if any)."""
        match inp:
            case Receive(src, src_inc, dst_inc, msg):
                return self.on_message(now, src, src_inc, dst_inc, msg)
            case TimerFired(key):
                self.on_timer(now, key)
            case NStart():
                self.start(now)
            case FdReport() | PeerInfo():  # the core's alone
                self._now = now
                self.core.step(now, inp)
            case NSubmit(payload, req, kind, cost):
                self.submit(now, payload, req, kind, cost)
            case LeaveGroup():
                self.leave(now)
            case _:
                assert_never(inp)
        return None

    def start(self, now: float) -> None:
        """groupJoin() (ll. 35-49)."""
        self._now = now
        if self.started:
            return
        self.started = True
        self.core.start(now)
        self._join(JStart())  # ll. 36-39
        self._form(FStart())  # ll. 40-45

    def on_message(self, now: float, src: str, src_inc: int, dst_inc: int, msg: Message) -> AppMessage | None:
        self._now = now
        g = self.core.on_message(now, src, src_inc, dst_inc, msg)
        if isinstance(g, GroupMessage):  # a membership message, handled right where the core let it through
            self._on_group(g.src, g.src_inc, g.msg)
        elif isinstance(g, VoteRequest):
            self._vote(g)
        return g if isinstance(g, AppMessage) else None

    def _on_group(self, src: str, src_inc: int, msg: Message) -> None:
        q = (src, src_inc)
        if self.lv.left:
            return
        match msg:
            case Apply() | Introduce() | Sponsor() | Connections():
                self._join(Heard(q, msg))
            case Leave():
                self._up(LeaveAsked(q))
            case Locked(key):
                self._up(LockedMsg(q, key))
            case StateForward(seq, txid, payload):
                self._xfer(Forward(seq, txid, payload))
            case StateSnapshot(seq, data, anchor, anchor_seq, _, parts, lock_key, lock_by):
                if parts <= 1:
                    lock = (lock_key, lock_by) if lock_key and lock_by is not None else None
                    self._xfer(Snapshot(seq, data, anchor, anchor_seq, lock))
                else:
                    self._snapshot_part(q, msg)
            case StateRequest(txid):
                self._xfer(Request(q, txid))
            case SeqWrite(floor, writes, costs):
                self._seq(Forwarded(q, floor, writes, costs))


    def on_timer(self, now: float, key: Hashable) -> None:
        self._now = now
        if not isinstance(key, NodeTimer):  # the core's
            self.core.on_timer(now, key)
            return
        match None if self.lv.left else key.what:
            case "discovery":
                self._form(DiscoveryDue())
            case "formation":
                self._form(FormationDue())
            case "reapply":
                self._join(ReapplyDue())
            case "catchup":
                self._xfer(CatchupDue())
            case "retry":
                self._up(URetryDue())
            case "seqretry":
                self._seq(RetryDue())

    def submit(self, now: float, payload: bytes, req: Hashable, kind: str = "ddb", cost: int = 1) -> None:
        """Request a global-state change: a DDB batch (`kind="ddb"`) or a test payload; `cost`: its apply cost
        (the batch's ops). The outcome comes as a `WriteDone` effect; a committed change has been applied here
        before `WriteDone`."""
        self._now = now
        tx: GroupTx = TxDdb(payload) if kind == "ddb" else TxAgent(payload) if kind == "agent" else TxTest(payload)
        if self.config.sequencer and kind in ("ddb", "test"):
            self._seq(Submit(req, encode_tx(tx), cost))
        else:
            self._carry(self.wr.step(now, WRequest(req, encode_tx(tx))))

    def leave(self, now: float) -> None:
        """groupLeave() (ll. 14-17): the `Left` effect follows once the group has removed this host."""
        self._now = now
        self._carry(self.lv.step(now, LeaveCalled()))

    # ------------------------------------------------------------------ the machines' effects, in order

    def _form(self, inp: FormationInput) -> None:
        self._carry(self.formation.step(self._now, inp))

    def _join(self, inp: JoinInput) -> None:
        self._carry(self.join.step(self._now, inp))

    def _up(self, inp: UpdateInput) -> None:
        self._carry(self.upd.step(self._now, inp))

    def _seq(self, inp: SeqInput) -> None:
        self._carry(self.seq.step(self._now, inp))

    def _release(self) -> None:
        """ll. 132, 145, 155: propose the changes held while locked (or while catching up)."""
        self._carry(self.wr.step(self._now, WRelease()))
        if self.seq.held:
            self._seq(SRelease())

    def _carry(self, effects: Sequence[MachineEffect]) -> None:
        """Carry out the effects of one step of a machine, in order; a proposal's txid goes back at once."""
        now = self._now
        for e in effects:
            match e:
                case Send() | SetTimer() | Log() | WriteDone() | Left() | Reincarnate():
                    self.out.append(e)
                case ProposeTx(txid, tx, parts):  # the membership update's
                    self._propose(txid, encode_tx(tx), parts)
                case ProposeFallback(txid, members):  # the formation's (ll. 46-49)
                    self._propose(txid, encode_tx(TxFormation(self.me, members)), [m.proc for m in members])
                case ProposeBatch(txid, entries):  # the sequencer's
                    self._propose(txid, encode_tx(TxSeq(entries)), self.state.procs())
                case ProposeWrite(txid, payload):
                    self._propose(txid, payload, self.state.procs())
                case FormGroupOfOne():  # ll. 42-43
                    self._up(GroupOfOne(Member(self.name, self.inc, self.addr)))
                case Link(name, addr):
                    self._connect(name, addr)
                case ToHost(name, msg):
                    self._send((name, self.core.peers[name].inc), msg)
                case Hear(name, inc, hearsay):
                    self.core.add_peer(now, name, inc, hearsay=hearsay)
                case MarkRemoved(name, inc):  # Alg. 3 l. 118, docs/membership.md
                    self.core.mark_dead(now, name, inc, "removed")
                case Remember(name, addr):
                    self.addrs.setdefault(name, addr)
                case SendState(to):
                    self._send_state(to)
                case Abandon(existing):  # docs/membership.md, "restarts"
                    self._carry(self.lv.step(now, Abandoned(existing)))
                case LeaveSelf():
                    self._up(LeaveAsked(self.me))
                case Withdrawn(p):
                    self._join(Withdraw(p))
                case Admit(procs, mine):
                    self._join(Admitted(procs, mine))
                case RunUpdate():
                    self._up(Run())
                case ProposeHeld() | CaughtUp():
                    self._release()
                case Unlocked():
                    self._release()
                    if self.seq.queue:  # (Flush proposes queued writes: nothing to do without them)
                        self._seq(Flush())
                case Removed():
                    self._carry(self.lv.step(now, RemovedHere()))
                case NowMember():
                    self._join(Joined())
                case SponsorAll():
                    self._join(SponsorAll())
                case Count(name, n):
                    self.core.counters[name] += n
                case ApplyTx(txid, payload, direct):  # the state transfer's
                    self._apply(txid, payload, direct)
                case Restore(data):
                    self._restore(data)
                case SendSnapshot(to, anchor, anchor_seq):
                    self._send_snapshot(to, self.state.seq, self.state.snapshot(), anchor, anchor_seq,
                                        self.upd.lock())
                case InheritLock(key, by):
                    self._up(LockInherited(key, by))
                case Rejected(reason):
                    self.counters["rejected_snapshot"] += 1
                    self._log("reject", reason=reason)
                case _:
                    assert_never(e)

    def _send_state(self, to: Proc) -> None:
        """l. 60: the global state to a sponsee (`haactl verify --mutate stale-snapshot` replaces this)."""
        self._send_snapshot(to, self.state.seq, self.state.snapshot(), None, 0)

    def _send_snapshot(self, to: Proc, seq: int, data: bytes, anchor: TxId | None, anchor_seq: int,
                       lock: tuple[str, Proc] | None = None) -> None:
        """The global state to `to`, in parts of at most `SNAPSHOT_PART` bytes when it is larger: every part is
        one link message, so a state of any size crosses links whose frames are bounded (`MAX_MESSAGE`), and
        the link's FIFO order and flow control carry the parts like any other traffic. `lock`: an answer to a
        `StateRequest` carries the lock this member holds (`StateSnapshot.lock_key`)."""
        key, by = lock if lock is not None else ("", None)
        n = -(-len(data) // SNAPSHOT_PART)
        if n <= 1:
            self._send(to, StateSnapshot(seq, data, anchor, anchor_seq, 0, 1, key, by))
            return
        view = memoryview(data)
        for i in range(n):
            part = bytes(view[i * SNAPSHOT_PART:(i + 1) * SNAPSHOT_PART])
            self._send(to, StateSnapshot(seq, part, anchor, anchor_seq, i, n, key, by))
        self.counters["snapshot_parts_sent"] += n

    def _snapshot_part(self, q: Proc, m: StateSnapshot) -> None:
        """One part of a state sent in parts (`_send_snapshot`): kept until the last one, then the whole state
        goes to the state transfer as one snapshot. Parts come in order on the sender's link; a part 0 starts
        over (a new snapshot), one out of order or beyond `MAX_SNAPSHOT_BYTES` drops what was gathered."""
        if m.part == 0:
            self._parts[q] = (m.seq, m.anchor, m.anchor_seq, m.parts, [], 0)
        got = self._parts.get(q)
        if got is None:
            self.counters["snapshot_part_dropped"] += 1
            return
        seq, anchor, anchor_seq, parts, slices, size = got
        size += len(m.data)
        if (m.seq, m.anchor, m.anchor_seq, m.parts, m.part) != (seq, anchor, anchor_seq, parts, len(slices)) or (
            size > MAX_SNAPSHOT_BYTES
        ):
            del self._parts[q]
            self.counters["snapshot_part_dropped"] += 1
            self._log("snapshot_parts_dropped", src=q[0], part=m.part, parts=m.parts, size=size)
            return
        slices.append(m.data)
        if len(slices) < parts:
            self._parts[q] = (seq, anchor, anchor_seq, parts, slices, size)
            return
        del self._parts[q]
        self.counters["snapshot_parts_joined"] += 1
        lock = (m.lock_key, m.lock_by) if m.lock_key and m.lock_by is not None else None  # (every part has it)
        self._xfer(Snapshot(seq, b"".join(slices), anchor, anchor_seq, lock))

    def _xfer(self, inp: XferInput) -> None:
        """After an `ApplyTx` or a `Restore`, step the state transfer with `Continue` (a loop, not recursion:
        a joiner may drain thousands of transactions)."""
        effects = self.xfer.step(self._now, inp)
        while effects:
            self._carry(effects)
            more = any(isinstance(e, (ApplyTx, Restore)) for e in effects)
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

    # ------------------------------------------------------------------ OAC votes and outcomes

    def _propose(self, txid: TxId, payload: bytes, participants: Iterable[Proc]) -> None:
        """Propose a machine's transaction by OAC, with the id the machine reserved; vote on it at once."""
        if (ask := self.core.propose_to(self._now, txid, payload, participants)) is not None:
            self._vote(ask)

    def _vote(self, ask: VoteRequest) -> None:
        """OAC asks this host's vote on a transaction (Alg. 2 l. 27): the group's rules decide it (`_evaluate`)."""
        self.core.vote(self._now, ask.txid, self._evaluate(ask.txid, ask.payload, ask.participants))

    def _evaluate(self, txid: TxId, payload: bytes, participants: tuple[Proc, ...]) -> bool:
        try:
            tx = decode_tx(payload)
        except GroupTxError:
            return True  # not ours to judge: it is applied as a no-op everywhere
        if isinstance(tx, (TxRemove, TxMembership)):
            return self.upd.vote(txid, tx, frozenset(participants))  # ll. 110-116
        if isinstance(tx, TxFormation):
            return self.formation.vote(tx, bool(self.state.members))  # ll. 158-165
        return True

    def _on_decided(self, e: Decided) -> None:
        txid = e.txid
        if e.commit:
            return  # handled at delivery, in total order
        if self.formation.owns(txid):
            self._form(Aborted(txid, bool(self.state.members)))  # l. 46: repeat
        self._up(TxAborted(txid))  # (a transaction is the formation's, the update's, a write or a batch)
        self._carry(self.wr.step(self._now, WAborted(txid)))
        if txid in self.seq.inflight:  # (only our own batches concern the sequencer)
            self._seq(BatchAborted(txid))

    def _on_deliver(self, e: Deliver) -> None:
        self._up(TxDelivered(e.txid))
        if self.formation.owns(e.txid):
            self._form(FDelivered(e.txid))
        if e.txid in self.state.recent:
            return  # already applied from the sponsor's forwarded stream
        joining = not self.direct_q and not self.is_member() and _needs_state(e.payload, self.me, self.state)
        if joining or self.xfer.catching_up():  # a new member: the state transfer buffers it
            self._xfer(Delivered(e.txid, e.payload, joining))
        else:
            self._apply(e.txid, e.payload, direct=True)

    # ------------------------------------------------------------------ applying the global sequence

    def _apply(self, txid: TxId, payload: bytes, direct: bool) -> None:
        was_member = self.is_member()
        was_leader = self.view.leader_now()
        st = self.state
        res = st.apply(txid, payload)
        h = st.content_hash() if self.config.hash_every_apply else ""
        front = st.members[0].proc if st.members else None
        self.out.append(AppliedTx(res.seq, txid, res.kind, payload, h, res.ddb_result, st.view, front))
        for a in sorted(self.join.sponsees):  # l. 61: forward to every applicant we sponsor (sorted: deterministic)
            self._send(a, StateForward(res.seq, txid, payload))
        if self.xfer.requests:  # state requests waiting for a transaction to be applied here
            self._xfer(Applied(txid, res.seq))
        try:
            tx: GroupTx | None = decode_tx(payload)
        except GroupTxError:
            tx = None
        if res.view_changed:
            self.out.append(ViewChange(st.view, res.seq, tuple(st.members), res.removed, res.added, txid, st.genesis,
                                       st.group_correct))
            self._log("view", view=st.view, members=[f"{m.name}.{m.inc}" for m in st.members],
                      removed=[m.name for m in res.removed], added=[m.name for m in res.added])
            self._join(ViewChanged(tuple(st.members), res.removed))
        if self.wr.writes:
            self._carry(self.wr.step(self._now, WCommitted(txid, res.seq, res.error, res.ddb_result)))
        if res.view_changed and self.wr.held:  # l. 117: a suspected member removed (writes held since an abort)
            self._carry(self.wr.step(self._now, WRelease()))
        if type(tx) is TxSeq:
            self._seq(BatchApplied(txid, res.seq, cast("tuple[SeqApplied, ...]", res.ddb_result)))
        elif txid in self.seq.inflight:  # (our batch, but it did not decode as one: cannot happen)
            self._seq(BatchApplied(txid, res.seq, ()))
        if res.view_changed and self.seq.pending:  # (Retarget does nothing without pending writes)
            self._seq(Retarget())
        if not (direct or self.is_member()):
            return  # an applicant following its sponsor's stream: state only
        if res.stale or isinstance(tx, (TxRemove, TxMembership, TxFormation)):  # ll. 117-157, 166-179
            self._up(GroupTxApplied(txid, tx, res.stale, was_member, self.lv.leaving,
                                    tuple(m.proc for m in res.added)))
        if self.is_member() and not was_leader and self.view.leader_now():
            self._log("leader", view=st.view)


def _needs_state(payload: bytes, me: Proc, state: GlobalState) -> bool:
    """A non-member delivers a transaction: the one that adds it to an existing group (it must first hold the
    state before it), or one that creates a group (formation, or its own group of one)."""
    try:
        tx = decode_tx(payload)
    except GroupTxError:
        return True
    if type(tx) is TxFormation:
        return False
    return not (type(tx) is TxMembership and tx.proposer == me and not state.members)
