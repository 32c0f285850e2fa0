"""The DDB sequencer: one proposer for the group's global-state writes (docs/oac.md, "The sequencer").

Thesis Alg. 3 (§4.6, thesis L2358-2565; described at L690-731) has every member propose its own global-state
changes by OAC, held while the global state is locked (Alg. 3 ll. 127-132, 144-145, 153-155: L2508-2541).
With every host writing at once that makes n concurrent OAC proposers whose order conflicts Alg. 2 resolves
by restarted rounds. HAA avoids the conflicts: a member forwards its DDB and test writes to the
*sequencer* — the highest-ranked member it does not suspect, the leader of Alg. 3 l. 79 as it sees it —
which batches what it receives into one OAC transaction (`TxSeq`) to every member. `Sequencer` is both sides
for one host incarnation, as a sans-I/O machine with its own state:

* as an **origin**: a DDB or test write of this host comes here straight from the node (`Submit`): refused at
  once when this host is not a member or the group is not formed, held while this host is a new member whose
  state has not caught up (released by `Release`, like the held changes of Alg. 3 l. 132), else it gets the
  next client sequence number `cseq` and is forwarded (`SeqWrite`) to the sequencer of the moment; it is
  forwarded again when the sequencer changes (`Retarget`: a view change or a suspicion) or after `seq_retry`
  without being applied (`RetryDue`), given up after `seq_abandon`, and answered (`WriteDone`) when the batch
  entry that applied it is applied here (`BatchApplied`);
* as the **sequencer**: forwarded writes are queued once per (origin, cseq) unless the replicated dedup record
  (`GlobalState.seq_origins`) says they are settled, and proposed as batches of at most `seq_max_entries` writes /
  `seq_max_bytes` / `seq_max_cost` (the writes' DDB ops, so that applying one batch costs no more than one request
  of `MAX_BATCH_OPS` ops; a single write always goes, even over it), at most `seq_inflight` batches in OAC at once,
  only while the node lets global-state changes through (`SeqHost.may_batch`: a member, not locked — l. 129 — not
  catching up); an aborted batch goes back to the front of the queue (`BatchAborted`).

Interface: `step(now, input) -> list[SeqEffect]` with the closed unions `SeqInput` and `SeqEffect`. The
machine reads what it needs of its host through the narrow `SeqHost` protocol (membership, who the sequencer
is, the replicated dedup record; the one call that changes the node reserves a transaction id) and changes
nothing outside itself: sends, timers, answers, proposals and counter increments all come back as effects, in
the order the node must carry them out. A proposal (`ProposeBatch`) carries the transaction id the machine
reserved, so it matches the later decision to the batch.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.ddb.objects import MAX_BATCH_OPS
from haa.core.effects import Send, SetTimer
from haa.core.membership.globalstate import SeqApplied, SeqEntry
from haa.core.membership.groupeffects import NodeTimer, WriteDone
from haa.core.messages import SeqWrite, TxId

Proc = tuple[str, int]

#: writes a sequencer queues at most (beyond it, forwarded writes are dropped: their origins forward them again)
SEQ_MAX_QUEUE = 200_000

#: the key of the origin's retry timer
RETRY_TIMER = NodeTimer("seqretry")


@dataclass(frozen=True, slots=True)
class SeqConfig:
    """The sequencer's share of `haa.core.membership.membership.NodeConfig` (same names, same meaning)."""

    seq_inflight: int = 1
    seq_max_entries: int = 1024
    seq_max_bytes: int = 4 << 20
    seq_retry: float = 2.0
    seq_abandon: float = 60.0
    seq_max_cost: int = MAX_BATCH_OPS


class SeqHost(Protocol):
    """What the sequencer reads of the node it runs in (read-only)."""

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def has_left(self) -> bool:
        """This incarnation stopped taking part (left, removed, or restarting)."""

    def group_formed(self) -> bool:
        """The group is a correct group (not provisional)."""

    def is_locked(self) -> bool:
        """locked_p (l. 6): the global state is locked for a membership change."""

    def catching_up(self) -> bool:
        """A new member whose state has not caught up yet."""

    def may_batch(self) -> bool:
        """Global-state changes may be proposed now: a member, not locked (Alg. 3 l. 129), caught up, not left."""

    def sequencer(self) -> Proc | None:
        """The highest-ranked member this host neither suspects nor knows dead; None if there is none."""

    def settled(self, origin: Proc, cseq: int) -> bool:
        """The replicated dedup record says `origin`'s write `cseq` is applied or settled."""

    def new_txid(self) -> TxId:
        """A fresh OAC transaction id of this host incarnation for a proposal (the one call that changes the node:
        it reserves the id, so the machine knows its transaction before it is proposed)."""


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Submit:
    """A DDB or test write of this host (an encoded `TxDdb`/`TxTest`), answered by a `WriteDone`; `cost`: its
    apply cost (the DDB ops it carries)."""

    req: Hashable
    payload: bytes
    cost: int = 1


@dataclass(frozen=True, slots=True)
class Release:
    """The global state may be unlocked, or this new member caught up: forward the writes held meanwhile."""


@dataclass(frozen=True, slots=True)
class Forwarded:
    """A `SeqWrite` from `origin` (or from this host to itself): writes `(cseq, payload)`, all below `floor`
    settled at the origin; `costs`: theirs (() = 1 each)."""

    origin: Proc
    floor: int
    writes: tuple[tuple[int, bytes], ...]
    costs: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class RetryDue:
    """The retry timer (`RETRY_TIMER`) fired."""


@dataclass(frozen=True, slots=True)
class Retarget:
    """The sequencer may have changed (a view change, a suspicion, a peer found dead)."""


@dataclass(frozen=True, slots=True)
class Flush:
    """Global-state changes are let through again (the lock was released): propose what is queued."""


@dataclass(frozen=True, slots=True)
class BatchApplied:
    """Transaction `txid` was applied here as the `seq`-th global transaction. `results`: what became of each
    entry when it was a sequencer batch (anyone's), () otherwise."""

    txid: TxId
    seq: int
    results: tuple[SeqApplied, ...]


@dataclass(frozen=True, slots=True)
class BatchAborted:
    """OAC aborted transaction `txid` (ignored unless it is one of this sequencer's batches)."""

    txid: TxId


SeqInput = Submit | Release | Forwarded | RetryDue | Retarget | Flush | BatchApplied | BatchAborted


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class ProposeBatch:
    """Propose `TxSeq(entries)` by OAC as `txid` to every member."""

    txid: TxId
    entries: tuple[SeqEntry, ...]


@dataclass(frozen=True, slots=True)
class Count:
    """Add `n` to the host's counter `name` (metrics only)."""

    name: str
    n: int = 1


SeqEffect = Send | SetTimer | WriteDone | ProposeBatch | Count


# ------------------------------------------------------------------------------------------------ machine


@dataclass(slots=True)
class _Pending:
    """A write this host forwarded to the sequencer and has not yet seen applied."""

    req: Hashable
    payload: bytes
    cost: int
    first: float  # first forwarded
    sent: float = 0.0  # last forwarded


class Sequencer:
    """Both sides of the sequencer for host incarnation `me`. See the module docstring."""

    def __init__(self, me: Proc, host: SeqHost, config: SeqConfig | None = None) -> None:
        self.me = me
        self.host = host
        self.config = config or SeqConfig()
        # as an origin
        self.next_cseq = 1
        self.held: list[tuple[Hashable, bytes, int]] = []  # submitted while catching up (no cseq yet)
        self.pending: dict[int, _Pending] = {}  # forwarded, not yet applied here (in cseq order)
        self.target: Proc | None = None  # where they were forwarded last
        self.timer_armed = False
        # as the sequencer
        self.queue: deque[SeqEntry] = deque()
        self.known: set[tuple[Proc, int]] = set()  # (origin, cseq) queued or in a batch of ours
        self.inflight: dict[TxId, tuple[SeqEntry, ...]] = {}
        self._now = 0.0
        self._out: list[SeqEffect] = []

    def step(self, now: float, inp: SeqInput) -> list[SeqEffect]:
        self._now = now
        match inp:
            case Submit(req, payload, cost):
                h = self.host
                if h.catching_up():  # a new member: hold until its state has caught up
                    self.held.append((req, payload, cost))
                elif not h.is_member():
                    self._out.append(WriteDone(req, False, None, 0, "not a member of the group"))
                elif not h.group_formed():
                    self._out.append(WriteDone(req, False, None, 0, "the group is not formed yet"))
                else:
                    self._submit(req, payload, cost)
            case Release():
                if self.held and not (self.host.is_locked() or self.host.catching_up()):
                    held, self.held = self.held, []
                    for req, payload, cost in held:
                        self._submit(req, payload, cost)
            case Forwarded(origin, floor, writes, costs):
                self._accept(origin, floor, writes, costs or (1,) * len(writes))
            case RetryDue():
                self.timer_armed = False
                self._retry()
            case Retarget():
                if self.pending and self.host.sequencer() != self.target:
                    self._out.append(Count("seq_retargeted"))
                    self._forward(list(self.pending))
            case Flush():
                self._flush()
            case BatchApplied(txid, seq, results):
                self._applied(txid, seq, results)
            case BatchAborted(txid):
                self._done(txid, False)
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    def busy(self) -> bool:
        """Writes are held or pending here or batches of ours are queued or in OAC."""
        return bool(self.held or self.pending or self.queue or self.inflight)

    # ------------------------------------------------------------------ origin

    def _submit(self, req: Hashable, payload: bytes, cost: int) -> None:
        cseq = self.next_cseq
        self.next_cseq += 1
        self.pending[cseq] = _Pending(req, payload, max(1, cost), self._now)
        self._forward([cseq])

    def _forward(self, cseqs: Sequence[int]) -> None:
        """Forward these pending writes (in cseq order) to the sequencer of the moment."""
        target = self.host.sequencer()
        if target is None or not self.host.is_member():
            self._arm()  # nobody to forward to: the retry timer tries again
            return
        self.target = target
        pending = self.pending
        floor = next(iter(pending)) if pending else self.next_cseq
        most, most_bytes = self.config.seq_max_entries, self.config.seq_max_bytes
        batch: list[tuple[int, bytes]] = []
        costs: list[int] = []
        size = 0
        for c in cseqs:
            w = pending.get(c)
            if w is None:
                continue
            w.sent = self._now
            if batch and (len(batch) >= most or size + len(w.payload) > most_bytes):
                self._send(target, floor, batch, costs)
                batch, costs, size = [], [], 0
            batch.append((c, w.payload))
            costs.append(w.cost)
            size += len(w.payload)
        if batch:
            self._send(target, floor, batch, costs)
        self._arm()

    def _send(self, target: Proc, floor: int, batch: list[tuple[int, bytes]], costs: list[int]) -> None:
        self._out.append(Count("seq_forwarded", len(batch)))
        cost = tuple(costs) if any(c != 1 for c in costs) else ()  # (() : 1 each, as on the wire)
        if target == self.me:
            self._accept(self.me, floor, tuple(batch), tuple(costs))
        else:
            self._out.append(Send(target[0], target[1], SeqWrite(floor, tuple(batch), cost)))

    def _arm(self) -> None:
        if self.pending and not self.timer_armed:
            self.timer_armed = True
            self._out.append(SetTimer(RETRY_TIMER, self._now + self.config.seq_retry))

    def _retry(self) -> None:
        """Forward again what has waited `seq_retry` (a forward lost with a sequencer that crashed, or one that
        never got to propose it); give up what has waited `seq_abandon`."""
        now = self._now
        for c, w in list(self.pending.items()):
            if now - w.first >= self.config.seq_abandon:
                del self.pending[c]
                self._out.append(WriteDone(w.req, False, None, 0,
                                           f"not committed within {self.config.seq_abandon:g} s (it may still commit)"))
        due = [c for c, w in self.pending.items() if now - w.sent >= self.config.seq_retry]
        if due:
            self._out.append(Count("seq_reforwarded", len(due)))
            self._forward(due)
        self._arm()

    def _applied(self, txid: TxId, seq: int, results: tuple[SeqApplied, ...]) -> None:
        """A transaction was applied here: answer our own writes in it, and settle it if it was our batch."""
        for r in results:
            if r.origin != self.me:
                continue
            w = self.pending.pop(r.cseq, None)
            if w is None:
                continue
            if r.applied:
                self._out.append(WriteDone(w.req, True, txid, seq, r.error, r.result))
            else:  # (a duplicate of an applied write was answered then; this is "origin is not a member")
                self._out.append(WriteDone(w.req, False, None, 0, r.error))
        self._done(txid, True)

    # ------------------------------------------------------------------ sequencer

    def _accept(
        self, origin: Proc, floor: int, writes: tuple[tuple[int, bytes], ...], costs: tuple[int, ...]
    ) -> None:
        """Writes forwarded to us (we are, or were, or are about to be the sequencer): queue each one that is
        neither queued here nor applied, and propose."""
        # (an origin that is not a member yet here may be one we have not applied the addition of: its writes
        # are queued all the same; applying a batch skips the writes of non-members, deterministically)
        if self.host.has_left() or len(self.queue) + len(writes) > SEQ_MAX_QUEUE:
            self._out.append(Count("seq_dropped", len(writes)))
            return
        for (cseq, payload), cost in zip(writes, costs, strict=True):
            key = (origin, cseq)
            if key in self.known or self.host.settled(origin, cseq):
                continue
            self.known.add(key)
            self.queue.append(SeqEntry(origin, cseq, floor, payload, max(1, cost)))
        self._flush()

    def _flush(self) -> None:
        """Propose the queued writes as batches, at most `seq_inflight` at a time; held while the global state
        is locked (l. 129), like any global-state change."""
        q = self.queue
        if not self.host.may_batch():
            return
        cfg = self.config
        while q and len(self.inflight) < cfg.seq_inflight:
            entries: list[SeqEntry] = []
            size = cost = 0
            while q and len(entries) < cfg.seq_max_entries and (
                not entries or (size + len(q[0].tx) <= cfg.seq_max_bytes and cost + q[0].cost <= cfg.seq_max_cost)
            ):
                e = q.popleft()
                entries.append(e)
                size += len(e.tx)
                cost += e.cost
            batch = tuple(entries)
            txid = self.host.new_txid()
            self.inflight[txid] = batch
            self._out.append(ProposeBatch(txid, batch))
            self._out.append(Count("seq_batches"))

    def _done(self, txid: TxId, commit: bool) -> None:
        """One of our batches was applied (commit) or aborted: an aborted batch goes back to the queue's front."""
        batch = self.inflight.pop(txid, None)
        if batch is None:
            return
        if commit:
            for e in batch:
                self.known.discard((e.origin, e.cseq))
        else:
            self._out.append(Count("seq_batches_aborted"))
            self.queue.extendleft(reversed(batch))
        self._flush()
