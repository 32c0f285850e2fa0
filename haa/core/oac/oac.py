"""Totally ordered atomic commit HAA-OAC (thesis §4.5, Appendix II Alg. 2).

A transaction is proposed by one host to a set of participants (one of which is the proposer). Every
participant votes (unilateral abort, ll. 27-30), then the participants run rounds of a
rotating-coordinator consensus (the non-blocking atomic commit of [67], steps P1/C1/P2/C2) on the outcome.
Total order across transactions with different participant sets comes from the thesis' order proposals:
a participant proposes an order above every open transaction it knows when it first learns a transaction,
the highest proposal wins, and a committed transaction is delivered only when it has the lowest
(order, id) of all active transactions (the l. 37 gate). A decided transaction stays in
decidedTransactions until every participant has acknowledged the decision or is permanently suspected
(l. 41), and is then forgotten (closed).

This class is sans-I/O, a machine like every other of the core: one `step(now, input)` returns the effects.

* Inputs: `Propose(txid, payload, participants)` (startTransaction, ll. 3-5; the id is pre-assigned by the
  caller with `new_txid()`, so a proposer knows it before anything is sent), `Incoming(src, src_inc, msg)` (an
  OAC message from another host), `PeerChanged(peer)` (the failure detector's output about `peer` changed, or
  one of its incarnations became permanently suspected), `Vote(txid, ok)` (this host's vote, ll. 27-30).
* Effects: `Send` (to another host; `lazy` below), `Decided`, `Deliver`, `Closed`, `Log`, and for the host
  around it: `Evaluate(txid, payload)` (vote on this transaction: answered by a `Vote` input, until which the
  transaction waits and its messages are held), `Voted(txid, ok)` (the vote was taken, for the record) and
  `Learn(participants)` (a participant list names incarnations the host may not know yet).

What it reads of its host (`OacHost`): the failure detector's output, permanent suspicion and removal.
Line numbers in comments refer to Alg. 2.

Where the pseudo-code is silent or needs completing for liveness, the choices are (docs/oac.md):

* Participants are (host, incarnation) pairs. A message from another incarnation of a participant is not
  about this transaction; a participant whose incarnation is superseded or excluded is permanently
  suspected for it.
* Proposer first: `propose` puts the proposer at the head of the participant list, so it coordinates
  round 0 and a failure-free transaction decides in four message delays at the proposer.
* The coordinator's decide (l. 69) doubles as its own Task 1 rebroadcast (l. 36), and so does a no-voter's
  abort (l. 29); a failure-free commit costs (n-1)(n+4) messages between hosts.
* Relay: a participant that holds the transaction, is still undecided and suspects the proposer sends the
  transaction on to all participants once, so that a proposer that crashed part-way through l. 5 cannot
  leave a correct participant without it (which would block that participant's coordinator round and,
  through its placeholder, its l. 37 gate).
* Placeholders (l. 75) record who mentioned the transaction. Decide messages carry the participant list,
  so a placeholder that learns the outcome can relay it (l. 36) and close (l. 41). A placeholder that has
  neither the transaction nor an outcome is dropped once everyone who mentioned it is permanently
  suspected: no correct process can then be waiting on it, and if the transaction reaches it later it is
  simply learned afresh (rule 1 of §4.5.2 gives it an order above everything open).
* Decide alone: a transaction of exactly two participants whose other participant the group removed
  (`is_removed`, Alg. 3 l. 118) is decided by the survivor with its own estimate (`_decide_alone`). Its
  quorum is both participants, so it could never decide otherwise (the removed incarnation's messages are
  dropped), and every decision the removed host could have taken needed this host's ack, whose value this
  host's estimate still holds (docs/oac.md, "A partner the group removed").
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol, assert_never

from haa.core.effects import Closed, Decided, Deliver, Log, Send, Voted
from haa.core.messages import (
    OacAck,
    OacDecide,
    OacEstimate,
    OacMessage,
    OacOrder,
    OacProposal,
    OacTransaction,
    TxId,
)

Participant = tuple[str, int]


class OacHost(Protocol):
    """What OAC reads of its host (`haa.core.host.hostcore.HostCore`)."""

    def is_suspected(self, q: str, qi: int) -> bool:
        """The failure detector's current output (◇S_p); True also for a permanently suspected incarnation."""
        ...

    def is_dead(self, q: str, qi: int) -> bool:
        """Permanent suspicion (l. 41)."""
        ...

    def is_removed(self, q: str, qi: int) -> bool:
        """The group removed this incarnation (Alg. 3 l. 118): it is permanently suspected and its messages
        are dropped for good. Used only by `_decide_alone`."""
        ...


@dataclass(frozen=True, slots=True)
class Propose:
    txid: TxId
    payload: bytes
    participants: tuple[Participant, ...]


@dataclass(frozen=True, slots=True)
class Incoming:
    src: str
    src_inc: int
    msg: OacMessage


@dataclass(frozen=True, slots=True)
class PeerChanged:
    peer: str


@dataclass(frozen=True, slots=True)
class Vote:
    txid: TxId
    ok: bool


@dataclass(frozen=True, slots=True)
class Evaluate:
    """Vote on `txid` (ll. 27-30): answer with a `Vote` input."""

    txid: TxId
    payload: bytes
    participants: tuple[Participant, ...] = ()


@dataclass(frozen=True, slots=True)
class Learn:
    """A participant list: the host learns of the incarnations it names (and suspects those it cannot hear)."""

    participants: tuple[Participant, ...]


OacInput = Propose | Incoming | PeerChanged | Vote
OacEffect = Send | Decided | Deliver | Closed | Log | Evaluate | Voted | Learn

UNDECIDED = 0  # in activeTransactions, no outcome yet
DECIDED = 1  # in activeTransactions, outcome known, waiting at the l. 37 gate
DONE = 2  # in decidedTransactions (l. 40), waiting for l. 41

IDLE = 0  # Task 2 not running
C1 = 1  # coordinator waiting for estimates (l. 49)
P2 = 2  # participant waiting for the coordinator's proposal (l. 57)
C2 = 3  # coordinator waiting for acks (l. 65)

#: ts_p before any proposal was adopted. The thesis initialises it to 0 (l. 20, l. 82) but starts rounds at 0
#: (l. 19, l. 45), so adopting round 0's proposal (ts := 0, l. 60) looked like no adoption at all and a later
#: coordinator could drop a pre-commit that round 0 had already decided on (AC-Uniform-Agreement; found by
#: the verifier, seed 25965; docs/oac.md). [67] starts rounds at 1; we start timestamps at -1.
INITIAL_TS = -1

_STATE_NAMES = {UNDECIDED: "undecided", DECIDED: "decided", DONE: "done"}
_PHASE_NAMES = {IDLE: "idle", C1: "C1", P2: "P2", C2: "C2"}


class OacError(ValueError):
    """A request the OAC cannot accept (for example a participant list without the proposer)."""


class _Tx:
    """One transaction as seen by one participant (the variables of ll. 10-15 and its list entries)."""

    __slots__ = (
        "acks",
        "commit",
        "content",
        "decide_from",
        "est",
        "ests",
        "id",
        "n",
        "order",
        "parts",
        "payload",
        "pending",
        "phase",
        "pinc",
        "props",
        "quorum",
        "r",
        "relayed_content",
        "relayed_decide",
        "round_decided",
        "senders",
        "state",
        "ts",
        "voting",
    )

    def __init__(self, txid: TxId, order: int) -> None:
        self.id = txid
        self.order = order  # order_p (l. 15)
        self.content = False  # False: placeholder (l. 75)
        self.payload = b""
        self.parts: tuple[Participant, ...] = ()
        self.pinc: dict[str, int] = {}
        self.n = 0
        self.quorum = 0  # n - f with the largest f < n/2
        self.state = UNDECIDED  # state_p (l. 11)
        self.commit = False  # outcome (l. 10)
        self.phase = IDLE
        self.est = False  # est_p: True = pre-commit (l. 12)
        self.r = -1  # r_p (l. 13)
        self.ts = INITIAL_TS  # ts_p (l. 14)
        self.ests: dict[tuple[int, int], dict[str, tuple[bool, int]]] = {}
        self.props: dict[tuple[int, int], bool] = {}
        self.acks: dict[tuple[int, int], dict[str, bool]] = {}
        self.decide_from: set[str] = set()
        self.relayed_decide = False
        self.round_decided = -1
        self.relayed_content = False
        self.senders: set[Participant] = set()
        # Task 2 messages that reached a placeholder, replayed once the transaction arrives (or, while this
        # host's vote is asked for, once it is given)
        self.pending: list[tuple[str, int, OacMessage]] = []
        self.voting = False

    def set_participants(self, parts: tuple[Participant, ...]) -> None:
        self.parts = parts
        self.pinc = dict(parts)
        self.n = len(parts)
        self.quorum = self.n - (self.n - 1) // 2

    @property
    def key(self) -> tuple[int, TxId]:
        return (self.order, self.id)


class OrderedAtomicCommit:
    """Alg. 2 for one host (`name`, incarnation `inc`): see the module docstring."""

    def __init__(self, name: str, inc: int, host: OacHost) -> None:
        self.name = name
        self.inc = inc
        self._host = host
        self._out: list[OacEffect] = []
        self.txs: dict[TxId, _Tx] = {}  # activeTransactions_p ∪ decidedTransactions_p (ll. 1-2)
        self._gate: list[tuple[int, TxId]] = []  # min-heap over active (order, id), lazily invalidated
        self._seq = 0
        self.delivered = 0

    def new_txid(self) -> TxId:
        """A fresh transaction id of this host incarnation, for a `Propose` (ids are never reused)."""
        self._seq += 1
        return TxId(self.name, self.inc, self._seq)

    def step(self, now: float, inp: OacInput) -> list[OacEffect]:
        """One input (module docstring); returns its effects in the order they were produced."""
        match inp:
            case Propose(txid, payload, participants):
                self._propose(txid, payload, participants)
            case Incoming(src, src_inc, msg):
                self._on_message(src, src_inc, msg)
            case PeerChanged(peer):
                self._on_peer_change(peer)
            case Vote(txid, ok):
                self._on_vote(txid, ok)
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    # ------------------------------------------------------------------ helpers

    def _send_fn(self, dst: str, dst_inc: int, msg: OacMessage, lazy: bool) -> None:
        self._out.append(Send(dst, dst_inc, msg, lazy))

    def _send(self, dst: str, dst_inc: int, msg: OacMessage) -> None:
        if dst == self.name:
            return  # self-sends are applied directly by the callers
        self._send_fn(dst, dst_inc, msg, False)

    def _send_all(self, tx: _Tx, msg: OacMessage, lazy: bool = False) -> None:
        for q, qi in tx.parts:
            if q != self.name:
                self._send_fn(q, qi, msg, lazy)

    def _suspected(self, q: str, qi: int) -> bool:
        return q != self.name and self._host.is_suspected(q, qi)

    def _highest(self, exclude: TxId | None = None) -> tuple[int, TxId] | None:
        """Highest (order, id) of activeTransactions_p ∪ decidedTransactions_p (l. 4, l. 22)."""
        best: tuple[int, TxId] | None = None
        for tx in self.txs.values():
            if tx.id == exclude:
                continue
            k = (tx.order, tx.id)
            if best is None or k > best:
                best = k
        return best

    def _push_gate(self, tx: _Tx) -> None:
        heapq.heappush(self._gate, (tx.order, tx.id))

    def _log(self, event: str, **fields: Any) -> None:
        self._out.append(Log(event, fields))

    # ------------------------------------------------------------------ inputs

    def _propose(self, txid: TxId, payload: bytes, participants: Iterable[Participant]) -> None:
        """startTransaction (ll. 3-5). The proposer is moved to the head of the list (docs/oac.md)."""
        parts = [p for p in participants if p[0] != self.name]
        names = [p[0] for p in parts]
        if len(set(names)) != len(names):
            raise OacError(f"duplicate participant in {names}")
        if (txid.host, txid.inc) != (self.name, self.inc) or txid in self.txs:
            raise OacError(f"{txid} is not a fresh transaction id of {self.name}#{self.inc} (new_txid)")
        parts_t: tuple[Participant, ...] = ((self.name, self.inc), *parts)
        # l. 4: back of the queue (docs/oac.md, "Orders never go back", tried and taken back)
        high = self._highest()
        order = (high[0] if high else 0) + 1
        msg = OacTransaction(txid, bytes(payload), parts_t, order)
        for q, qi in parts_t:  # l. 5
            if q != self.name:
                self._send_fn(q, qi, msg, False)
        self._on_transaction(self.name, self.inc, msg)  # our own copy (l. 6)

    def _on_message(self, src: str, src_inc: int, msg: OacMessage) -> None:
        """Any OAC message from another host (ll. 6-8 and ll. 72-84, then the waits it may release)."""
        if type(msg) is OacTransaction:
            self._on_transaction(src, src_inc, msg)
            return
        tx = self.txs.get(msg.id)
        if tx is not None and tx.parts:
            if tx.pinc.get(src) != src_inc:
                self._log("oac_foreign_sender", tx=str(msg.id), src=src, inc=src_inc)
                return
        if tx is None:  # ll. 73-75: learn of the transaction from someone else: placeholder
            if type(msg) is OacDecide:
                if (src, src_inc) not in msg.participants:
                    self._log("oac_foreign_sender", tx=str(msg.id), src=src, inc=src_inc)
                    return
            tx = _Tx(msg.id, max(msg.order, 0))
            self.txs[msg.id] = tx
            self._push_gate(tx)
        tx.senders.add((src, src_inc))
        if tx.state == DONE:
            if isinstance(msg, OacDecide) and msg.delivered:
                tx.decide_from.add(src)
                self._close_check(tx)
            return
        if msg.order > tx.order and tx.state == UNDECIDED:  # l. 76
            self._accept_order(tx, msg.order)
        if isinstance(msg, OacDecide):
            self._on_decide(tx, src, msg)
            return
        if not tx.content or tx.voting:
            if not isinstance(msg, OacOrder) and tx.state == UNDECIDED:
                tx.pending.append((src, src_inc, msg))
            return
        if isinstance(msg, OacEstimate):
            if msg.order == tx.order and msg.round >= tx.r:
                tx.ests.setdefault((msg.order, msg.round), {})[src] = (msg.precommit, msg.ts)
        elif isinstance(msg, OacProposal):
            if msg.order == tx.order and msg.round >= tx.r and self._coord_name(tx, msg.round) == src:
                tx.props[(msg.order, msg.round)] = msg.precommit
        elif isinstance(msg, OacAck):
            if msg.order == tx.order and msg.round >= tx.r:
                tx.acks.setdefault((msg.order, msg.round), {})[src] = msg.ack
        self._progress(tx)

    def _on_peer_change(self, peer: str) -> None:
        """The failure detector's output about `peer` changed, or one of its incarnations became
        permanently suspected: re-check every wait that involves it (ll. 49, 57, 41), relay transactions
        whose proposer is now suspected, and drop placeholders nobody alive can resolve."""
        for tx in list(self.txs.values()):
            if peer in tx.pinc:
                if tx.state == UNDECIDED:
                    if tx.id.host == peer and self._suspected(peer, tx.id.inc):
                        self._relay_content(tx)
                    self._progress(tx)
                self._close_check(tx)
            elif not tx.parts and tx.state == UNDECIDED:
                # placeholder that knows neither the transaction nor its outcome
                if tx.senders and all(self._host.is_dead(q, qi) for q, qi in tx.senders):
                    self._log("oac_placeholder_dropped", tx=str(tx.id))
                    del self.txs[tx.id]
        self._deliver_ready()

    # ------------------------------------------------------------------ ll. 6-32

    def _on_transaction(self, src: str, src_inc: int, msg: OacTransaction) -> None:
        txid = msg.id
        parts = tuple(msg.participants)
        pinc = dict(parts)
        if pinc.get(self.name) != self.inc or pinc.get(src) != src_inc or len(pinc) != len(parts):
            self._log("oac_bad_transaction", tx=str(txid), src=src)
            return
        if parts[0] != (txid.host, txid.inc) and (txid.host, txid.inc) not in parts:
            self._log("oac_bad_transaction", tx=str(txid), src=src, why="proposer not a participant")
            return
        tx = self.txs.get(txid)
        if tx is not None:
            if tx.parts and tx.parts != parts:
                self._log("oac_bad_transaction", tx=str(txid), src=src, why="participants differ")
                return
            tx.senders.add((src, src_inc))
            if tx.state == DONE:  # l. 7: already in decidedTransactions_p
                return
            if tx.content:  # a relayed copy: only its order proposal matters (l. 76)
                if msg.order > tx.order and tx.state == UNDECIDED:
                    self._accept_order(tx, msg.order)
                    self._progress(tx)
                return
        self._atomic_commit(tx, msg, parts, src, src_inc)

    def _atomic_commit(
        self, tx: _Tx | None, msg: OacTransaction, parts: tuple[Participant, ...], src: str, src_inc: int
    ) -> None:
        """procedure atomicCommit: initialization and voting (ll. 16-32)."""
        if tx is not None and tx.state != UNDECIDED:
            # the outcome reached us before the transaction (placeholder): the order is final, Task 1 only
            tx.content = True
            tx.payload = msg.payload
            self._deliver_ready()
            return
        order = msg.order
        if tx is not None:  # l. 21: we hold a placeholder with an updated order
            order = max(order, tx.order)
        high = self._highest(exclude=msg.id)
        if high is not None and (order, msg.id) < high:  # l. 22: confirm the order
            order_p = high[0] + 1  # l. 23: back of the queue
            bump = True
        else:
            order_p = order  # l. 25
            bump = False
        if tx is None:
            tx = _Tx(msg.id, order_p)
            self.txs[msg.id] = tx
        tx.order = order_p
        self._push_gate(tx)
        tx.content = True  # l. 26
        tx.payload = msg.payload
        tx.set_participants(parts)
        tx.senders.add((src, src_inc))
        self._out.append(Learn(parts))
        if bump:
            self._send_all(tx, OacOrder(tx.id, order_p))  # l. 24
        tx.voting = True  # l. 27: the host votes; the transaction waits for its `Vote`
        self._out.append(Evaluate(tx.id, tx.payload, tx.parts))

    def _on_vote(self, txid: TxId, ok: bool) -> None:
        """ll. 27-32: this host's vote on a transaction it was asked to evaluate."""
        tx = self.txs.get(txid)
        if tx is None or not tx.voting:
            self._log("oac_vote_unasked", tx=str(txid))
            return
        tx.voting = False
        self._out.append(Voted(txid, ok))
        if tx.state != UNDECIDED:  # the outcome reached us while the vote was asked for: nothing to do
            return
        if not ok:  # l. 27-30: unilateral abort
            self._log("oac_vote_no", tx=str(tx.id))
            self._decide(tx, commit=False, order=-1, rnd=tx.r)
            return
        self._start_task2(tx)  # l. 32
        if tx.id.host != self.name and self._suspected(tx.id.host, tx.id.inc):
            self._relay_content(tx)
        pending, tx.pending = tx.pending, []
        for psrc, pinc, pmsg in pending:
            if tx.pinc.get(psrc) == pinc and tx.state == UNDECIDED:
                self._on_message(psrc, pinc, pmsg)

    def _relay_content(self, tx: _Tx) -> None:
        if tx.content and not tx.relayed_content and tx.state == UNDECIDED:
            tx.relayed_content = True
            msg = OacTransaction(tx.id, tx.payload, tx.parts, tx.order)
            for q, qi in tx.parts:
                if q != self.name and q != tx.id.host:
                    self._send_fn(q, qi, msg, False)
            self._log("oac_relay", tx=str(tx.id))

    # ------------------------------------------------------------------ ll. 72-84

    def _accept_order(self, tx: _Tx, order: int) -> None:
        tx.order = order  # l. 77
        self._push_gate(tx)
        if tx.phase != IDLE:  # l. 78: Task 2 is active
            # l. 79, lazy: whoever raised the order sent it to every participant (l. 24); this copy only matters
            # if that host crashed part-way through its broadcast
            self._send_all(tx, OacOrder(tx.id, order), lazy=True)
            self._start_task2(tx)  # ll. 80-84

    # ------------------------------------------------------------------ Task 2 (ll. 43-71)

    def _coord(self, tx: _Tx, rnd: int) -> Participant:
        return tx.parts[rnd % tx.n]  # l. 46

    def _coord_name(self, tx: _Tx, rnd: int) -> str:
        return tx.parts[rnd % tx.n][0]

    def _start_task2(self, tx: _Tx) -> None:
        tx.est = False  # l. 18 / l. 80: pre-abort
        tx.r = -1  # l. 19 / l. 81
        tx.ts = INITIAL_TS  # l. 20 / l. 82 (see INITIAL_TS)
        self._next_round(tx)
        self._progress(tx)

    def _next_round(self, tx: _Tx, lazy: bool = False) -> None:
        tx.r += 1  # l. 45
        order, r = tx.order, tx.r
        # forget messages of rounds and orders this participant has left behind
        for store in (tx.ests, tx.props, tx.acks):
            for k in [k for k in store if k[0] != order or k[1] < r]:
                del store[k]
        cname, cinc = self._coord(tx, r)  # l. 46
        if cname == self.name:  # l. 47 to ourselves
            tx.ests.setdefault((order, r), {})[self.name] = (tx.est, tx.ts)
            tx.phase = C1
        else:
            self._send_fn(cname, cinc, OacEstimate(tx.id, order, r, tx.est, tx.ts), lazy)  # l. 47 (P1)
            tx.phase = P2

    def _partner_removed(self, tx: _Tx) -> bool:
        """A transaction of two participants whose other participant the group removed."""
        if tx.n != 2:
            return False
        q, qi = tx.parts[1] if tx.parts[0][0] == self.name else tx.parts[0]
        return q != self.name and self._host.is_removed(q, qi)

    def _decide_alone(self, tx: _Tx) -> None:
        """Decide a two-participant transaction whose partner the group removed, with this host's estimate
        (docs/oac.md, "A partner the group removed"). With n = 2 the quorum is 2 (f = 0): every decision,
        at either participant, needed this host's positive ack of the value it decided, and this host's
        estimate still holds that value (a later round could only propose it again, l. 54-55); the partner's
        unilateral abort (l. 29) leaves this host with its initial pre-abort, since a pre-commit needs every
        estimate (l. 51-52). The removed incarnation's messages are dropped, so it can decide nothing new."""
        self._log("oac_decide_alone", tx=str(tx.id), commit=tx.est, round=tx.r)
        if tx.est:
            self._decide(tx, commit=True, order=tx.order, rnd=tx.r)
        else:
            self._decide(tx, commit=False, order=-1, rnd=tx.r)

    def _progress(self, tx: _Tx) -> None:
        """Advance Task 2 as far as the messages and suspicions at hand allow."""
        if tx.state == UNDECIDED and tx.phase != IDLE and self._partner_removed(tx):
            self._decide_alone(tx)
            return
        while tx.state == UNDECIDED and tx.phase != IDLE:
            key = (tx.order, tx.r)
            if tx.phase == C1:  # ll. 48-56
                got = tx.ests.get(key)
                if got is None or len(got) < tx.quorum:
                    return
                for q, qi in tx.parts:  # l. 49
                    if q not in got and not self._suspected(q, qi):
                        return
                if len(got) == tx.n:  # l. 51-52
                    tx.est = True
                else:  # l. 54-55: the estimate with the largest timestamp (first in rotation order)
                    best_ts = max(ts for _e, ts in got.values())
                    for q, _qi in tx.parts:
                        e = got.get(q)
                        if e is not None and e[1] == best_ts:
                            tx.est = e[0]
                            break
                self._send_all(tx, OacProposal(tx.id, tx.order, tx.r, tx.est))  # l. 56
                tx.props[key] = tx.est
                tx.phase = P2
            elif tx.phase == P2:  # ll. 57-63
                cname, cinc = self._coord(tx, tx.r)
                proposed = tx.props.get(key)
                if proposed is not None:  # l. 58-61
                    tx.est = proposed
                    tx.ts = tx.r
                    ack = True
                elif self._suspected(cname, cinc):  # l. 62-63
                    ack = False
                else:
                    return
                if cname == self.name:
                    tx.acks.setdefault(key, {})[self.name] = ack
                    tx.phase = C2
                else:
                    self._send_fn(cname, cinc, OacAck(tx.id, tx.order, tx.r, ack), False)
                    # after a positive ack the next round only matters if this one fails: its estimate is lazy
                    self._next_round(tx, lazy=ack)
            else:  # C2, ll. 64-71
                got_acks = tx.acks.get(key)
                if got_acks is None or len(got_acks) < tx.quorum:  # l. 65
                    return
                if sum(1 for a in got_acks.values() if a) >= tx.quorum:  # l. 66
                    if tx.est:  # l. 68-69
                        self._decide(tx, commit=True, order=tx.order, rnd=tx.r)
                    else:  # l. 71
                        self._decide(tx, commit=False, order=-1, rnd=tx.r)
                    return
                self._next_round(tx)

    # ------------------------------------------------------------------ Task 1 (ll. 33-42)

    def _on_decide(self, tx: _Tx, src: str, msg: OacDecide) -> None:
        if not tx.parts:  # a placeholder learns the participants from the decision
            parts = tuple(msg.participants)
            if (self.name, self.inc) not in parts:
                self._log("oac_bad_decide", tx=str(tx.id), src=src)
                return
            tx.set_participants(parts)
            self._out.append(Learn(parts))
        if msg.delivered:
            tx.decide_from.add(src)
        if tx.state == UNDECIDED:  # l. 34
            self._decide(tx, commit=msg.commit, order=msg.order, rnd=msg.round, learned=True)
        else:
            self._close_check(tx)

    def _decide(self, tx: _Tx, commit: bool, order: int, rnd: int, learned: bool = False) -> None:
        """l. 35-40 for this host: record the outcome, pass the l. 37 gate if possible, rebroadcast. `learned`:
        the outcome came in a decide message, so this host's rebroadcast (l. 36) is lazy — every participant
        normally has it from the same source already."""
        tx.state = DECIDED  # l. 35
        tx.commit = commit
        tx.round_decided = rnd
        tx.phase = IDLE  # Task 2 ends (l. 44)
        if commit:
            tx.order = order  # the final order (Lemma OAC-2)
            self._push_gate(tx)
        self._out.append(Decided(tx.id, commit))
        if not commit:  # l. 37: abort needs no order
            tx.state = DONE  # ll. 38-40
        self._deliver_ready()  # this transaction, or others it was holding back at the gate
        # l. 36 (also l. 29 and l. 69, see the module docstring), after the gate was tried so that, in the
        # common case, one message says both "decided" and "delivered"
        if not tx.relayed_decide:
            tx.relayed_decide = True
            self._send_all(tx, self._decide_msg(tx), lazy=learned)
        if tx.state == DONE:
            tx.decide_from.add(self.name)
        self._close_check(tx)

    def _decide_msg(self, tx: _Tx) -> OacDecide:
        order = tx.order if tx.commit else -1
        return OacDecide(tx.id, order, tx.round_decided, tx.commit, tx.parts, tx.state == DONE)

    def _deliver_ready(self) -> None:
        """l. 37-40: deliver committed transactions while they have the lowest (order, id) of all active."""
        gate = self._gate
        txs = self.txs
        while gate:
            order, txid = gate[0]
            tx = txs.get(txid)
            if tx is None or tx.state == DONE or tx.order != order:
                heapq.heappop(gate)  # stale entry
                continue
            if tx.state != DECIDED or not tx.content:
                return
            heapq.heappop(gate)
            tx.state = DONE  # l. 39-40
            self.delivered += 1
            self._out.append(Deliver(tx.id, tx.order, tx.payload))  # l. 38
            tx.payload = b""
            tx.decide_from.add(self.name)
            if tx.relayed_decide:
                self._announce_delivered(tx)
            self._close_check(tx)

    def _announce_delivered(self, tx: _Tx) -> None:
        """We rebroadcast the decision while held at the l. 37 gate: now tell everyone we passed l. 38."""
        self._send_all(tx, self._decide_msg(tx), lazy=True)

    def _close_check(self, tx: _Tx) -> None:
        """l. 41-42: forget the transaction once no further message about it can arrive."""
        if tx.state != DONE or not tx.parts:
            return
        for q, qi in tx.parts:
            if q not in tx.decide_from and not self._host.is_dead(q, qi):
                return
        if self.txs.pop(tx.id, None) is not None:
            self._out.append(Closed(tx.id))

    # ------------------------------------------------------------------ introspection

    @property
    def active_count(self) -> int:
        return sum(1 for tx in self.txs.values() if tx.state != DONE)

    @property
    def decided_count(self) -> int:
        return sum(1 for tx in self.txs.values() if tx.state == DONE)

    def describe(self, txid: TxId) -> dict[str, Any] | None:
        tx = self.txs.get(txid)
        if tx is None:
            return None
        return {
            "id": str(tx.id),
            "order": tx.order,
            "content": tx.content,
            "state": _STATE_NAMES[tx.state],
            "phase": _PHASE_NAMES[tx.phase],
            "round": tx.r,
            "est": "pre-commit" if tx.est else "pre-abort",
            "participants": [f"{q}#{qi}" for q, qi in tx.parts],
            "decide_from": sorted(tx.decide_from),
        }
