"""The host group's global state: what every member holds identically (thesis Alg. 3, "global state").

Every transaction the group commits through OAC carries one `GroupTx` (proto/haa/pb/group.proto): a
membership change (OAC(remove), OAC(membership), OAC(formationFallback) of Alg. 3), a batch of DDB
operations, or a test payload. Every member applies the committed transactions in the OAC's total order, so
two members that applied the same number of transactions hold the same state; `content_hash()` makes that
checkable. The state is:

* `seq`: how many transactions were applied; `chain`: a hash chain over their ids and payloads;
* the member list (ordered by rank: insertion order, the leader first, Alg. 3 l. 3), the view id (one more
  for every committed change of the list), `group_correct` and `core_members` (Alg. 3 ll. 12-13, 146-149);
* the replicated database (`haa.core.ddb.ddb.Ddb`);
* `recent`: the global sequence number of the last few thousand applied transactions, so that a new
  member can find where its first delivered transaction sits in the sequence (docs/membership.md).

A remove or membership transaction changes the list only if its proposer is the leader of the list it is
applied to (the front, without the members it removes): votes (Alg. 3 l. 111) are cast on each voter's
list at the time, and OAC may order a former leader's transaction after the one that replaced it. Such a
stale transaction takes its place in the sequence as a no-op (`Applied.stale`), deterministically everywhere.

A sponsor sends `snapshot()` to an applicant (Alg. 3 l. 60) and then forwards every applied transaction
(l. 61); `restore()` installs it. Pure and deterministic: no I/O, no clock, no randomness.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from google.protobuf.message import DecodeError

from haa.core.ddb.agenttable import AgentTable, AgentTxError
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import DdbError
from haa.core.messages import Member, TxId
from haa.pb import group_pb2 as gpb

if TYPE_CHECKING:
    from google.protobuf.internal.containers import RepeatedCompositeFieldContainer

Proc = tuple[str, int]

#: how many applied transaction ids are remembered with their sequence number
RECENT = 4096
GENESIS = "0" * 64


class GroupTxError(ValueError):
    """A group transaction payload that does not decode."""


# --------------------------------------------------------------------------------------------- payloads


@dataclass(frozen=True, slots=True)
class TxRemove:
    """OAC(remove, key, q, removalList), Alg. 3 l. 102; key "" = no lock (l. 99)."""

    key: str
    proposer: Proc
    removal: tuple[Proc, ...]


@dataclass(frozen=True, slots=True)
class TxMembership:
    """OAC(membership, key, q, newMemberList), Alg. 3 l. 43 and l. 106.

    The list is empty when every member asked to leave at once (`haactl cluster down`, `docker-compose down`):
    the group dissolves and every member receives its `Left`. Alg. 3 assumes a group remains; without this the
    leader's l. 105 list was empty, the transaction did not decode, was applied as a no-op and left every member
    locked (docs/membership.md, "dissolution")."""

    key: str
    proposer: Proc
    members: tuple[Member, ...]


@dataclass(frozen=True, slots=True)
class TxFormation:
    """OAC(formationFallback, q, newMemberList), Alg. 3 l. 48."""

    proposer: Proc
    members: tuple[Member, ...]


@dataclass(frozen=True, slots=True)
class TxDdb:
    data: bytes


@dataclass(frozen=True, slots=True)
class TxTest:
    data: bytes


@dataclass(frozen=True, slots=True)
class TxAgent:
    """A change of the agent table (`haa.core.ddb.agenttable`, proto haa.v1.AgentTx)."""

    data: bytes


@dataclass(frozen=True, slots=True)
class SeqEntry:
    """One member's write in a sequencer batch (docs/oac.md, "The sequencer"): the `cseq`-th write of
    `origin`, whose writes below `floor` are all settled; `tx` is the encoded TxDdb or TxTest."""

    origin: Proc
    cseq: int
    floor: int
    tx: bytes
    #: its apply cost (DDB ops), what the sequencer bounds a batch by; not part of the transaction
    cost: int = field(default=1, compare=False)


@dataclass(frozen=True, slots=True)
class TxSeq:
    """Writes of many members, batched into one transaction by the sequencer."""

    entries: tuple[SeqEntry, ...]


GroupTx = TxRemove | TxMembership | TxFormation | TxDdb | TxTest | TxAgent | TxSeq


def _proc(m: gpb.GroupProc, p: Proc) -> None:
    m.name = p[0]
    m.incarnation = p[1]


def _members(rep: RepeatedCompositeFieldContainer[gpb.GroupMember], members: tuple[Member, ...]) -> None:
    for x in members:
        rep.add(name=x.name, incarnation=x.inc, addr=x.addr)


def encode_tx(tx: GroupTx) -> bytes:
    m = gpb.GroupTx()
    if isinstance(tx, TxRemove):
        _proc(m.remove.proposer, tx.proposer)
        m.remove.key = tx.key
        for p in tx.removal:
            _proc(m.remove.removal.add(), p)
    elif isinstance(tx, TxMembership):
        m.membership.key = tx.key
        _proc(m.membership.proposer, tx.proposer)
        _members(m.membership.members, tx.members)
    elif isinstance(tx, TxFormation):
        _proc(m.formation.proposer, tx.proposer)
        _members(m.formation.members, tx.members)
    elif isinstance(tx, TxDdb):
        m.ddb = tx.data
    elif isinstance(tx, TxTest):
        m.test = tx.data
    elif isinstance(tx, TxAgent):
        m.agent = tx.data
    elif isinstance(tx, TxSeq):
        add = m.seq.entries.add
        for e in tx.entries:
            add(origin=e.origin[0], origin_incarnation=e.origin[1], cseq=e.cseq, floor=e.floor, tx=e.tx)
        if not tx.entries:
            m.seq.SetInParent()
    else:
        raise TypeError(f"not a group transaction: {type(tx).__name__}")
    data: bytes = m.SerializeToString()
    return data


def _dec_proc(m: gpb.GroupProc, what: str) -> Proc:
    if not m.name or m.incarnation == 0:
        raise GroupTxError(f"{what}: host name and incarnation required")
    return (m.name, m.incarnation)


def _dec_members(rep: Iterable[gpb.GroupMember], what: str, allow_empty: bool = False) -> tuple[Member, ...]:
    out = [Member(x.name, x.incarnation, x.addr) for x in rep]
    names = [x.name for x in out]
    if not out and not allow_empty:
        raise GroupTxError(f"{what}: empty member list")
    if any(not x.name or x.inc == 0 for x in out):
        raise GroupTxError(f"{what}: a member without name/incarnation")
    if len(set(names)) != len(names):
        raise GroupTxError(f"{what}: duplicate member")
    return tuple(out)


def decode_tx(payload: bytes) -> GroupTx:
    m = gpb.GroupTx()
    try:
        m.ParseFromString(payload)
    except DecodeError as e:
        raise GroupTxError(f"group transaction does not decode: {e}") from None
    kind = m.WhichOneof("body")
    if kind == "remove":
        r = m.remove
        return TxRemove(
            r.key, _dec_proc(r.proposer, "remove.proposer"), tuple(_dec_proc(p, "remove") for p in r.removal)
        )
    if kind == "membership":
        r2 = m.membership
        members = _dec_members(r2.members, "membership", allow_empty=True)
        return TxMembership(r2.key, _dec_proc(r2.proposer, "membership.proposer"), members)
    if kind == "formation":
        r3 = m.formation
        return TxFormation(_dec_proc(r3.proposer, "formation.proposer"), _dec_members(r3.members, "formation"))
    if kind == "ddb":
        return TxDdb(m.ddb)
    if kind == "test":
        return TxTest(m.test)
    if kind == "agent":
        return TxAgent(m.agent)
    if kind == "seq":
        entries = []
        for en in m.seq.entries:
            if not en.origin or en.origin_incarnation == 0 or en.cseq == 0:
                raise GroupTxError("seq: an entry without origin, incarnation or cseq")
            entries.append(SeqEntry((en.origin, en.origin_incarnation), en.cseq, en.floor, en.tx))
        return TxSeq(tuple(entries))
    raise GroupTxError("group transaction: body not set")


def tx_kind(tx: GroupTx) -> str:
    return {
        TxRemove: "remove",
        TxMembership: "membership",
        TxFormation: "formation",
        TxDdb: "ddb",
        TxTest: "test",
        TxAgent: "agent",
        TxSeq: "seq",
    }[type(tx)]


# --------------------------------------------------------------------------------------------- the state


@dataclass(frozen=True, slots=True)
class Applied:
    """What applying one transaction did."""

    seq: int
    kind: str
    view_changed: bool
    removed: tuple[Member, ...]
    added: tuple[Member, ...]
    ddb_result: object | None
    error: str
    #: a remove or membership transaction of a process that is no longer the leader when it is applied (it
    #: was voted for under an earlier list, l. 111): applied as a no-op (docs/membership.md, "stale leader")
    stale: bool = False


@dataclass(frozen=True, slots=True)
class SeqApplied:
    """What became of one entry of a sequencer batch: `applied` False for a duplicate or a write of a host
    that is no longer a member (then `error` says which); `kind` "ddb" or "test"; `result` the DDB's
    ApplyResult of a ddb write."""

    origin: Proc
    cseq: int
    applied: bool
    kind: str
    result: object | None
    error: str


class _Dedup:
    """One origin's applied writes: every cseq below `floor` is settled, `done` holds those applied at or
    above it (exactly-once application of writes a sequencer may batch twice)."""

    __slots__ = ("done", "floor")

    def __init__(self, floor: int = 0, done: set[int] | None = None) -> None:
        self.floor = floor
        self.done: set[int] = done or set()

    def raise_floor(self, floor: int) -> None:
        if floor > self.floor:
            self.floor = floor
            self.done = {c for c in self.done if c >= floor}


class GlobalState:
    """See the module docstring."""

    def __init__(self, core_names: tuple[str, ...], c_f: int) -> None:
        self.core_names = core_names
        self.c_f = c_f
        self.seq = 0
        self.view = 0
        self.genesis = ""  # id of the transaction that created the group
        self.members: list[Member] = []
        self.group_correct = False
        self.core_members: set[str] = set()
        self.ddb = Ddb()
        self.agents = AgentTable()
        self.chain = GENESIS
        self.recent: OrderedDict[TxId, int] = OrderedDict()
        #: per origin member: which of its sequenced writes were applied (`_Dedup`)
        self.seq_origins: dict[Proc, _Dedup] = {}
        #: False only in the simulator's mutation "seq-no-dedup" (applies duplicates: DDB-Exactly-Once fails)
        self.dedup = True

    # ------------------------------------------------------------------ queries

    def procs(self) -> list[Proc]:
        return [m.proc for m in self.members]

    def is_member(self, p: Proc) -> bool:
        return any(m.proc == p for m in self.members)

    def leader(self) -> Member | None:
        return self.members[0] if self.members else None

    def group_id(self) -> str:
        """Identifies the group (its creating transaction) once it is correct, "" before."""
        return self.genesis if self.group_correct else ""

    def content_hash(self) -> str:
        h = hashlib.sha256()
        h.update(f"{self.seq}|{self.view}|{self.genesis}|{int(self.group_correct)}|".encode())
        h.update(",".join(sorted(self.core_members)).encode())
        for m in self.members:
            h.update(f"|{m.name}.{m.inc}@{m.addr}".encode())
        h.update(b"|")
        h.update(self.ddb.content_hash().encode())
        if len(self.agents) or self.agents.hosts or self.agents.ses_id:
            h.update(b"|agents:" + self.agents.content_hash().encode())
        for (name, inc), d in sorted(self.seq_origins.items()):
            h.update(f"|seq:{name}.{inc}:{d.floor}:{','.join(map(str, sorted(d.done)))}".encode())
        return h.hexdigest()

    # ------------------------------------------------------------------ apply

    def _note_core(self) -> None:
        """Alg. 3 ll. 146-149: a group is correct once more than c_f core processes have been members."""
        if not self.group_correct:
            self.core_members |= {m.name for m in self.members if m.name in self.core_names}
            if len(self.core_members) > self.c_f:
                self.group_correct = True

    def apply(self, txid: TxId, payload: bytes) -> Applied:
        """Apply the next committed transaction (the caller guarantees the total order)."""
        try:
            tx: GroupTx | None = decode_tx(payload)
        except GroupTxError as e:
            tx = None
            err = str(e)
        else:
            err = ""
        self.seq += 1
        h = hashlib.sha256(f"{self.chain}\n{txid.host}.{txid.inc}.{txid.seq}\n".encode())
        h.update(payload)
        self.chain = h.hexdigest()
        self.recent[txid] = self.seq
        if len(self.recent) > RECENT:
            self.recent.popitem(last=False)
        kind = tx_kind(tx) if tx is not None else "invalid"
        removed: tuple[Member, ...] = ()
        added: tuple[Member, ...] = ()
        ddb_result: object | None = None
        before = list(self.members)
        stale = False
        if isinstance(tx, TxRemove):
            gone = set(tx.removal)
            rest = [m for m in self.members if m.proc not in gone]
            if rest and rest[0].proc == tx.proposer:
                self.members = rest  # l. 118
            else:
                stale = True
        elif isinstance(tx, TxMembership):
            if not self.members and not self.genesis:
                if tx.members:
                    self.genesis = str(txid)  # l. 43: the first core process' group of one
                    self.members = list(tx.members)
            elif not self.members or self.members[0].proc == tx.proposer:
                # l. 141; an empty list dissolves the group (every member asked to leave, `TxMembership`)
                self.members = list(tx.members)  # l. 141
            else:
                stale = True
        elif isinstance(tx, TxFormation):
            if not self.members:  # l. 167: only accept one formation message
                self.genesis = str(txid)
                self.members = list(tx.members)  # l. 169
                self.group_correct = True  # l. 178
        elif isinstance(tx, TxDdb):
            try:
                ddb_result = self.ddb.apply(tx.data, self.seq)  # (meta: the global seq, for mirror catch-up)
            except DdbError as e:
                err = str(e)
            except Exception as e:  # a bug: the same bytes fail the same way on every replica (apply is total)
                err = f"ddb apply failed: {type(e).__name__}: {e}"
        elif isinstance(tx, TxAgent):
            # total: AgentTable.apply turns anything it cannot apply into a refusal (AgentApplied.ok False)
            ddb_result = self.agents.apply(tx.data, tuple(m.name for m in self.members))
        elif isinstance(tx, TxSeq):
            ddb_result = tuple(self._apply_entry(e) for e in tx.entries)
        changed = self.members != before
        if changed:
            self.view += 1
            old = {m.proc for m in before}
            new = {m.proc for m in self.members}
            removed = tuple(m for m in before if m.proc not in new)
            added = tuple(m for m in self.members if m.proc not in old)
            self._note_core()
            if removed:
                # the agents the removed hosts ran have crashed (Alg. 8); the result of a membership change
                # carries the agents whose owner changed
                ddb_result = self.agents.on_removed(m.name for m in removed)
                for m in removed:  # a removed incarnation never writes again: forget its writes
                    self.seq_origins.pop(m.proc, None)
        return Applied(self.seq, kind, changed, removed, added, ddb_result, err, stale)

    def _apply_entry(self, e: SeqEntry) -> SeqApplied:
        """One write of a sequencer batch: applied once per (origin, cseq), while the origin is a member."""
        if not self.is_member(e.origin):
            return SeqApplied(e.origin, e.cseq, False, "", None, "the origin is not a member")
        d = self.seq_origins.get(e.origin)
        if d is None:
            d = self.seq_origins[e.origin] = _Dedup()
        d.raise_floor(e.floor)
        if self.dedup and (e.cseq < d.floor or e.cseq in d.done):
            return SeqApplied(e.origin, e.cseq, False, "", None, "duplicate")
        d.done.add(e.cseq)
        try:
            inner = decode_tx(e.tx)
        except GroupTxError as ex:
            return SeqApplied(e.origin, e.cseq, True, "invalid", None, str(ex))
        if isinstance(inner, TxDdb):
            try:
                return SeqApplied(e.origin, e.cseq, True, "ddb", self.ddb.apply(inner.data, self.seq), "")
            except DdbError as ex:
                return SeqApplied(e.origin, e.cseq, True, "ddb", None, str(ex))
            except Exception as ex:  # a bug: the same bytes fail the same way on every replica (apply is total)
                return SeqApplied(e.origin, e.cseq, True, "ddb", None, f"ddb apply failed: {type(ex).__name__}: {ex}")
        if isinstance(inner, TxTest):
            return SeqApplied(e.origin, e.cseq, True, "test", None, "")
        return SeqApplied(e.origin, e.cseq, True, "invalid", None, f"a sequencer batch cannot carry {tx_kind(inner)}")

    # ------------------------------------------------------------------ snapshots

    def snapshot(self) -> bytes:
        s = gpb.GlobalSnapshot(
            seq=self.seq,
            view=self.view,
            group_correct=self.group_correct,
            core_members=sorted(self.core_members),
            ddb=self.ddb.snapshot(),
            agents=self.agents.snapshot(),
            chain=self.chain,
            genesis=self.genesis,
        )
        _members(s.members, tuple(self.members))
        for t, q in self.recent.items():
            s.recent.add(host=t.host, incarnation=t.inc, seq=t.seq, applied_seq=q)
        for (name, inc), d in sorted(self.seq_origins.items()):
            s.seq_origins.add(name=name, incarnation=inc, floor=d.floor, done=sorted(d.done))
        data: bytes = s.SerializeToString()
        return data

    @staticmethod
    def peek(data: bytes) -> tuple[int, str, bool]:
        """(seq, group id, group_correct) of a snapshot, without restoring it."""
        s = gpb.GlobalSnapshot()
        try:
            s.ParseFromString(data)
        except DecodeError as e:
            raise GroupTxError(f"global state snapshot does not decode: {e}") from None
        return s.seq, s.genesis, s.group_correct

    def restore(self, data: bytes) -> None:
        s = gpb.GlobalSnapshot()
        try:
            s.ParseFromString(data)
            ddb = Ddb.restore(s.ddb)
            agents = AgentTable.restore(s.agents)
        except (DecodeError, DdbError, AgentTxError) as e:
            raise GroupTxError(f"global state snapshot does not decode: {e}") from None
        self.seq = s.seq
        self.view = s.view
        self.members = [Member(m.name, m.incarnation, m.addr) for m in s.members]
        self.group_correct = s.group_correct
        self.core_members = set(s.core_members)
        self.ddb = ddb
        self.agents = agents
        self.chain = s.chain
        self.genesis = s.genesis
        self.recent = OrderedDict((TxId(r.host, r.incarnation, r.seq), r.applied_seq) for r in s.recent)
        self.seq_origins = {(o.name, o.incarnation): _Dedup(o.floor, set(o.done)) for o in s.seq_origins}
