"""The replicated agent table: which agents exist, who owns each, what is queued for it (thesis "DDB.agents").

Part of the group's global state (`haa.core.membership.globalstate`): every member applies the same `AgentTx`
transactions (proto/haa/pb/agenttx.proto) in the OAC's total order, so every member holds the same table and
every decision below is taken identically everywhere. The table is what Alg. 4-8 read and write:

* records: id (UUID), type, config, parent and display name (A3, A3.1, A3.1.2: thesis naming by parentage),
  declared cost / hardware / transfer penalty / recovery strategy, measured CPU;
* ownership: `status` (new, active, freezing, frozen, crashed), `owner` (the host running it), `alloc` (the
  host the last committed allocation gives it, Alg. 4 l. 94), `epoch` (fencing epoch: bumped by every claim
  and recovery, so at most one instance holds the current epoch) and `life` (bumped by every recovery only:
  it names the sender stream of the agent's messages, docs/agents-host.md);
* `state` (Alg. 5 l. 12), `backup` (Alg. 7 l. 5), `queue1` / `queue2` (Alg. 5 ll. 3-4, 11, 23), and the
  host-kept stream positions that travel with a frozen agent (inbox: next expected message per sender
  stream; outbox: next sequence number per receiver; pending: messages received but not processed);
* allocation bookkeeping: session id of the last committed OAC(start) and OAC(finish), paused flag, hosts'
  capacity / hardware / draining flag, measured affinities.

Validity rules, applied identically everywhere (an invalid transaction is a no-op with a reason):

* freeze (Alg. 5 l. 21): the proposer owns the agent, it is active, epochs match -> freezing;
* release (l. 14): the proposer owns the freezing agent -> frozen, state stored (with queue1), owner cleared;
* claim (Alg. 6 ll. 12-18): the agent is frozen and allocated to the claimer -> active, owned, epoch + 1;
  otherwise the claim is abandoned (l. 18);
* recovered (Alg. 8 l. 13-14): the agent is new or crashed and allocated to the claimer -> active, owned,
  epoch + 1, life + 1. Unlike Alg. 8, the new host commits this *before* it hands the backup to the new
  shell (docs/agents-host.md, "recovery claims first"): with overlapping allocation sessions two hosts could
  otherwise both run the agent;
* backup: only from the owner's current epoch (a zombie instance cannot overwrite a newer backup);
* failed: from the owner's current epoch, or implied when the owner is removed from the group -> crashed;
  an early failure (`AgentFailed.early`: the instance was not up yet, or died within its host's start grace)
  adds one to `failures`, any other failure resets it; at MAX_START_FAILURES consecutive early failures the
  agent is "failed" (terminal: not recovered; `fail_reason` says why) until an operator move retries it;
* create with a key (`AgentCreate.key`, a parent's `spawn_child(key=)`): when the parent already has a live
  child (any status but failed) with that key, the create applies as that child (`AgentApplied.existing`) and
  creates nothing: a spawn retried after a transfer or a recovery of the parent, whose first request had
  already committed, gets the first child instead of a second one (docs/agents.md, "Idempotent spawn");
* move: allocates the agent to a host, which must be a member at that point of the order; a failed agent
  becomes crashed again with failures 0 (a retry);
* claim and recovered hand queue1 + queue2 to the new owner (`AgentApplied.msgs`) and clear them;
* push: appends to queue2 (bounded: MAX_QUEUE messages, then counted as dropped); a push that finds the
  agent active again is not stored but handed to the owner.

Pure and deterministic: no I/O, no clock, no randomness.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

from google.protobuf.message import DecodeError

from haa.core.allocation.specs import MAX_CAPACITY, MAX_COST, MAX_NAME, MAX_PER_HOST, MIN_CAPACITY
from haa.pb import agenttx_pb2 as apb

NEW = "new"
ACTIVE = "active"
FREEZING = "freezing"
FROZEN = "frozen"
CRASHED = "crashed"
#: crashed MAX_START_FAILURES times in a row before it was up: not recovered any more (an operator move retries)
FAILED = "failed"
STATUSES = (NEW, ACTIVE, FREEZING, FROZEN, CRASHED, FAILED)
RECOVERY_MODES = ("backup", "restart", "none")

#: consecutive early failures (start failures) after which an agent is "failed" instead of "crashed"
MAX_START_FAILURES = 5
#: characters of a failure reason the table keeps
MAX_FAIL_REASON = 300

#: messages kept per queue of one agent; more are counted as dropped
MAX_QUEUE = 10_000
#: bytes of one agent's config (AgentSpawn): a config is parameters, not data. Checked at the edge and again
#: when the create applies (docs/limits.md, "Sizes and memory")
MAX_CONFIG = 1024 * 1024
#: bytes of one agent's state (frozen for a transfer) or backup: what one OAC transaction carries to every
#: host, and every host keeps (the backup). Like a DDB batch (haa.core.ddb.objects.MAX_BATCH_BYTES) it is copied and
#: decoded many times within one event-loop callback on every host, at 50-140 ms per MiB measured on a loaded
#: group: 2 MiB keeps the stall well below the failure detector's margin (bench-results/memory.json)
MAX_STATE = 2 * 1024 * 1024
#: (the former name of MAX_STATE)
MAX_BLOB = MAX_STATE
#: payload bytes kept per queue of one agent (messages for it while it is frozen or crashed); more are
#: counted as dropped, like messages beyond MAX_QUEUE
MAX_QUEUE_BYTES = 4 * 1024 * 1024
#: agents the table holds (docs/limits.md, "Agent and host numbers"). Every change of the table re-reads every
#: agent for the allocation (`AllocGlue.agent_specs`) and every session start carries them all: at 2,000 agents
#: that is ~36 ms of CPU per change on the leader and a 43 kB OAC(start) (measured; 4,000: 51 ms, 87 kB), and
#: 32 chained sessions of `MAX_SESSION_AGENTS` place a burst of that size. A create beyond it is refused
MAX_AGENTS = 2048
#: characters of a spawn key (AgentCreate.key)
MAX_SPAWN_KEY = 256
#: hardware names one agent may require or one host may offer
MAX_HARDWARE = 64
#: measured message rate between two agents (bytes/s) a host may report; beyond it the value is refused
MAX_RATE = 1e12


class AgentTxError(ValueError):
    """An agent transaction that does not decode or is malformed."""


@dataclass(slots=True)
class AgentRecord:
    spec: apb.AgentCreate
    name: str
    children: int = 0
    status: str = NEW
    owner: str = ""
    alloc: str = ""
    epoch: int = 0
    life: int = 0
    state: bytes | None = None
    backup: bytes | None = None
    backup_epoch: int = 0
    queue1: list[apb.RoutedMsg] = field(default_factory=list)
    queue2: list[apb.RoutedMsg] = field(default_factory=list)
    inbox: list[apb.StreamPos] = field(default_factory=list)
    outbox: list[apb.SendPos] = field(default_factory=list)
    pending: list[apb.RoutedMsg] = field(default_factory=list)
    cpu: float = 0.0
    dropped: int = 0
    failures: int = 0
    fail_reason: str = ""

    @property
    def id(self) -> str:
        return self.spec.id

    @property
    def type(self) -> str:
        return self.spec.type

    @property
    def parent(self) -> str:
        return self.spec.parent

    def cost(self) -> float:
        """Measured CPU (fraction of one core) when known, else the declared cost."""
        return self.cpu if self.cpu > 0 else self.spec.cost

    def to_pb(self) -> apb.AgentRecordPb:
        r = apb.AgentRecordPb(
            name=self.name,
            children=self.children,
            status=self.status,
            owner=self.owner,
            alloc=self.alloc,
            epoch=self.epoch,
            life=self.life,
            state=self.state or b"",
            has_state=self.state is not None,
            backup=self.backup or b"",
            has_backup=self.backup is not None,
            backup_epoch=self.backup_epoch,
            cpu=self.cpu,
            dropped=self.dropped,
            failures=self.failures,
            fail_reason=self.fail_reason,
        )
        r.spec.CopyFrom(self.spec)
        r.queue1.extend(self.queue1)
        r.queue2.extend(self.queue2)
        r.inbox.extend(self.inbox)
        r.outbox.extend(self.outbox)
        r.pending.extend(self.pending)
        return r

    @staticmethod
    def from_pb(r: apb.AgentRecordPb) -> AgentRecord:
        return AgentRecord(
            spec=r.spec,
            name=r.name,
            children=r.children,
            status=r.status,
            owner=r.owner,
            alloc=r.alloc,
            epoch=r.epoch,
            life=r.life,
            state=r.state if r.has_state else None,
            backup=r.backup if r.has_backup else None,
            backup_epoch=r.backup_epoch,
            queue1=list(r.queue1),
            queue2=list(r.queue2),
            inbox=list(r.inbox),
            outbox=list(r.outbox),
            pending=list(r.pending),
            cpu=r.cpu,
            dropped=r.dropped,
            failures=r.failures,
            fail_reason=r.fail_reason,
        )


@dataclass(frozen=True, slots=True)
class AgentApplied:
    """What applying one agent transaction did (the host layer reacts to it)."""

    kind: str
    agent: str  # agent id ("" for table-wide transactions)
    ok: bool
    reason: str = ""
    host: str = ""  # the proposing host
    req: int = 0  # the requester's id (create)
    #: agents whose owner or allocation changed as a side effect (finish, failed, removals)
    touched: tuple[str, ...] = ()
    #: messages appended to a queue by this push
    msgs: tuple[apb.RoutedMsg, ...] = ()
    #: create: the parent already had a live child with the create's key; `agent` is that child, nothing was
    #: created (docs/agents.md, "Idempotent spawn")
    existing: bool = False


def encode(tx: apb.AgentTx) -> bytes:
    encoded: bytes = tx.SerializeToString()
    return encoded


def decode(data: bytes) -> apb.AgentTx:
    tx = apb.AgentTx()
    try:
        tx.ParseFromString(data)
    except DecodeError as e:
        raise AgentTxError(f"agent transaction does not decode: {e}") from None
    if tx.WhichOneof("body") is None:
        raise AgentTxError("agent transaction: body not set")
    return tx


def _bad_number(x: float, lo: float, hi: float) -> bool:
    """True unless lo <= x <= hi and x is finite (NaN compares false everywhere)."""
    return not (math.isfinite(x) and lo <= x <= hi)


def _bad_names(names: Iterable[str]) -> str:
    """'' when every name is 1-MAX_NAME characters and there are at most MAX_HARDWARE of them, else the reason."""
    names = list(names)
    if len(names) > MAX_HARDWARE:
        return f"at most {MAX_HARDWARE} hardware names, got {len(names)}"
    for h in names:
        if not h or len(h) > MAX_NAME:
            return f"hardware names must be 1-{MAX_NAME} characters, got {h[:80]!r}"
    return ""


def check_create(c: apb.AgentCreate) -> str:
    """'' when an AgentCreate is well formed, else the reason. Called at the edge (before proposing) and again
    when the transaction applies, so a create proposed by a buggy or hostile peer is refused identically on
    every replica instead of reaching the allocator (docs/limits.md, "Agent and host numbers")."""
    if not c.id or len(c.id) > MAX_NAME:
        return f"create: agent id must be 1-{MAX_NAME} characters"
    if not c.type or len(c.type) > MAX_NAME:
        return f"create: type name must be 1-{MAX_NAME} characters"
    if len(c.parent) > MAX_NAME:
        return f"create: parent id must be at most {MAX_NAME} characters"
    if len(c.host) > MAX_NAME:
        return f"create: host name must be at most {MAX_NAME} characters"
    if _bad_number(c.transfer_penalty, 0.0, 1.0):
        return f"create: transfer_penalty must be a finite number in [0, 1], got {c.transfer_penalty!r}"
    if _bad_number(c.cost, 0.0, MAX_COST):  # also rejects NaN and +-inf
        return f"create: cost must be a finite number in [0, {MAX_COST:g}], got {c.cost!r}"
    why = _bad_names(c.hardware)
    if why:
        return f"create: {why}"
    if c.recovery not in RECOVERY_MODES:
        return f"create: recovery must be one of {', '.join(RECOVERY_MODES)}"
    if c.max_per_host > MAX_PER_HOST:  # uint32 on the wire: never negative
        return f"create: max_per_host must be an integer in [0, {MAX_PER_HOST}], got {c.max_per_host}"
    if len(c.key) > MAX_SPAWN_KEY:
        return f"create: key must be at most {MAX_SPAWN_KEY} characters"
    if c.key and not c.parent:
        return "create: a key needs a parent (it names one of the parent's children)"
    if len(c.config) > MAX_CONFIG:
        return f"create: config of {len(c.config)} bytes exceeds the limit of {MAX_CONFIG} bytes (MAX_CONFIG)"
    return ""


def check_host(m: apb.HostInfo) -> str:
    """'' when a HostInfo is well formed, else the reason (same bounds as `haa.core.allocation.specs.HostSpec`)."""
    if not m.name or len(m.name) > MAX_NAME:
        return f"host info: name must be 1-{MAX_NAME} characters"
    if _bad_number(m.capacity, MIN_CAPACITY, MAX_CAPACITY):
        bounds = f"[{MIN_CAPACITY:g}, {MAX_CAPACITY:g}]"
        return f"host info: capacity must be a finite number in {bounds}, got {m.capacity!r}"
    why = _bad_names(m.hardware)
    return f"host info: {why}" if why else ""


class AgentTable:
    """See the module docstring."""

    def __init__(self) -> None:
        self.records: dict[str, AgentRecord] = {}
        self.ses_id = 0  # highest committed OAC(start) id, valid or expired (Alg. 4 ll. 41-43)
        self.valid_ses = 0  # the last valid one
        self.finished_ses = 0  # last committed OAC(finish)
        self.top = 0  # top-level agents named so far (A1, A2, ...)
        self.hosts: dict[str, apb.HostInfo] = {}
        self.paused = False
        self.affinity: dict[tuple[str, str], float] = {}
        self.start_group: tuple[str, ...] = ()
        self.start_agents: tuple[str, ...] = ()
        self._members: tuple[str, ...] = ()

    # ------------------------------------------------------------------ queries

    def get(self, agent: str) -> AgentRecord | None:
        return self.records.get(agent)

    def __iter__(self) -> Iterator[AgentRecord]:
        return iter(self.records.values())

    def __len__(self) -> int:
        return len(self.records)

    def agent_ids(self) -> tuple[str, ...]:
        """Alg. 4 `agentList`: every agent, in a deterministic order."""
        return tuple(sorted(self.records))

    def owned_by(self, host: str) -> list[AgentRecord]:
        return [r for r in self.records.values() if r.owner == host]

    def by_name(self, name: str) -> AgentRecord | None:
        for r in self.records.values():
            if r.name == name:
                return r
        return None

    def child_by_key(self, parent: str, key: str) -> AgentRecord | None:
        """The live child (any status but failed) of `parent` created with spawn key `key`, or None ('' has
        none). Should two match (not by this table's creates), the one with the lowest id: the same everywhere."""
        if not key:
            return None
        hits = [r for r in self.records.values() if r.spec.key == key and r.spec.parent == parent
                and r.status != FAILED]
        return min(hits, key=lambda r: r.id) if hits else None

    def resolve(self, ref: str) -> AgentRecord | None:
        """An agent by id, display name or unique id prefix (>= 4 characters)."""
        r = self.records.get(ref) or self.by_name(ref)
        if r is None and len(ref) >= 4:
            hits = [x for x in self.records.values() if x.id.startswith(ref)]
            if len(hits) == 1:
                r = hits[0]
        return r

    def content_hash(self) -> str:
        h = hashlib.sha256()
        h.update(f"{self.ses_id}|{self.valid_ses}|{self.finished_ses}|{self.top}|{int(self.paused)}|".encode())
        for name in sorted(self.hosts):
            h.update(self.hosts[name].SerializeToString(deterministic=True))
        for k in sorted(self.affinity):
            h.update(f"{k[0]}:{k[1]}={self.affinity[k]!r}|".encode())
        for agent in sorted(self.records):
            h.update(self.records[agent].to_pb().SerializeToString(deterministic=True))
        h.update(("|".join(self.start_group) + "/" + "|".join(self.start_agents)).encode())
        return h.hexdigest()

    def invalid_values(self) -> list[str]:
        """What the table holds outside the bounds its transactions are checked against ([] normally): the
        allocator builds its problem from these values, so one of them would make it raise (issue 13)."""
        out = []
        for r in self.records.values():
            why = check_create(r.spec)
            if why:
                out.append(f"agent {r.name}: {why}")
            if _bad_number(r.cpu, 0.0, MAX_COST):
                out.append(f"agent {r.name}: cpu {r.cpu!r}")
            if r.status not in STATUSES or r.failures > MAX_START_FAILURES or len(r.fail_reason) > MAX_FAIL_REASON:
                out.append(f"agent {r.name}: status {r.status!r}, failures {r.failures}")
        for name, h in self.hosts.items():
            why = check_host(h)
            if why or name != h.name:
                out.append(f"host {name}: {why or 'name mismatch'}")
        for k, v in self.affinity.items():
            if _bad_number(v, 0.0, MAX_RATE):
                out.append(f"affinity {k}: {v!r}")
        return out

    # ------------------------------------------------------------------ apply

    def apply(self, data: bytes, members: tuple[str, ...] = ()) -> AgentApplied:
        """Apply one committed agent transaction (the caller guarantees the total order); `members` is the
        group's member list (rank order) at this point of the order (Alg. 4's hostGroup)."""
        try:
            tx = decode(data)
        except AgentTxError as e:
            return AgentApplied("invalid", "", False, str(e))
        kind = tx.WhichOneof("body")
        self._members = members
        handler = _HANDLERS.get(kind)
        if handler is None:  # a body this version does not know (decode keeps unknown oneof cases unset)
            return AgentApplied("invalid", "", False, f"unknown agent transaction kind {kind!r}")
        try:
            applied: AgentApplied = getattr(self, handler)(getattr(tx, kind))
            return applied
        except Exception as e:  # pragma: no cover - a bug; the handlers validate before they change anything
            # Applying a committed transaction is total: every replica runs the same code on the same bytes,
            # so it fails the same way everywhere and the outcome is a deterministic refusal, not a crash that
            # would leave this replica behind the others (issue 13, defect 1).
            return AgentApplied(kind, "", False, f"apply failed: {type(e).__name__}: {e}")

    def _tx_create(self, c: apb.AgentCreate) -> AgentApplied:
        why = check_create(c)
        if not why and c.id in self.records:
            why = "create: agent id already exists"
        if not why and len(self.records) >= MAX_AGENTS and self.child_by_key(c.parent, c.key) is None:
            why = f"create: the agent table is full ({len(self.records)} agents, at most MAX_AGENTS = {MAX_AGENTS})"
        parent = self.records.get(c.parent) if c.parent else None
        if not why and c.parent and parent is None:
            why = "create: unknown parent"
        if not why and (old := self.child_by_key(c.parent, c.key)) is not None:
            # a retried spawn (docs/agents.md, "Idempotent spawn"): the child its first request created
            return AgentApplied("create", old.id, True, "", c.host, c.req, existing=True)
        if not why:
            why = self._limit_conflict(c)
        if why:
            return AgentApplied("create", c.id, False, why, c.host, c.req)
        if parent is not None:
            parent.children += 1
            name = f"{parent.name}.{parent.children}"
        else:
            self.top += 1
            name = f"A{self.top}"
        self.records[c.id] = AgentRecord(spec=c, name=name)
        return AgentApplied("create", c.id, True, "", c.host, c.req)

    def _limit_conflict(self, c: apb.AgentCreate) -> str:
        """Agents of a type with a per-host limit must all declare the same limit and hardware (issue 15), so that
        the allocator counts the places of a type instead of matching agents to hosts
        (`haa.core.allocation.specs.limit_conflict`, docs/allocation.md "per-host limits"). An agent type declares
        both, so only a hand-made spawn with other hardware or a different version of the type meets this."""
        for r in self.records.values():
            if r.spec.type != c.type or not (r.spec.max_per_host or c.max_per_host):
                continue
            if r.spec.max_per_host != c.max_per_host or set(r.spec.hardware) != set(c.hardware):
                return (
                    f"create: agents of type {c.type!r} must declare the same max_per_host and hardware "
                    f"({r.name} has {r.spec.max_per_host}, {sorted(set(r.spec.hardware))}; this one "
                    f"{c.max_per_host}, {sorted(set(c.hardware))[:8]})"
                )
            return ""
        return ""

    def _tx_remove(self, m: apb.AgentRemove) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("remove", m.id, False, "unknown agent", m.host)
        if m.epoch and m.epoch != r.epoch:
            return AgentApplied("remove", m.id, False, "stale epoch", m.host)
        del self.records[m.id]
        self.affinity = {k: v for k, v in self.affinity.items() if m.id not in k}
        return AgentApplied("remove", m.id, True, "", m.host)

    def _tx_start(self, s: apb.AllocStartTx) -> AgentApplied:
        """OAC(start) committed, Alg. 4 ll. 38-40: valid only if proposed by the leader of the current group,
        with a session id above the last valid one. The agent list is the start's snapshot: a change since does
        not expire it (the same rule as `Allocator.start_valid`)."""
        members = self._members
        why = ""
        if not members or s.leader != members[0]:
            why = "proposer is not the leader"
        elif tuple(s.group) != members:
            why = "group changed"
        elif s.ses_id <= self.ses_id:
            why = f"session id not above the last committed ({self.ses_id})"
        # every committed start id is used up, even an expired one (as in `Allocator.on_start_committed`)
        self.ses_id = max(self.ses_id, s.ses_id)
        if why:
            return AgentApplied("start", "", False, why, s.leader)
        self.valid_ses = s.ses_id
        self.start_group = tuple(s.group)
        self.start_agents = tuple(s.agents)
        return AgentApplied("start", "", True, "", s.leader)

    def _tx_finish(self, f: apb.AllocFinishTx) -> AgentApplied:
        """OAC(finish) committed, Alg. 4 ll. 93-96: accepted only for the last valid start, once, while the
        group is still the start's (the same rule as `Allocator.finish_valid`: agents added since wait for the
        next session, the places of agents removed since are ignored)."""
        why = ""
        if f.ses_id != self.valid_ses:
            why = f"not the last valid session ({self.valid_ses})"
        elif f.ses_id <= self.finished_ses:
            why = "session already finished"
        elif self.start_group != self._members:
            why = "group changed since the start"
        if why:
            return AgentApplied("finish", "", False, why, f.leader)
        self.finished_ses = f.ses_id
        touched = []
        for agent, host in sorted(f.allocation.items()):
            r = self.records.get(agent)
            if r is not None and r.alloc != host and len(host) <= MAX_NAME:
                r.alloc = host
                touched.append(agent)
        for agent in sorted(self.records):
            # an agent of a type with a per-host limit that the allocation leaves out found no place (issue 15):
            # it is allocated nowhere, so that it is not recovered or kept on a host that now has another
            # agent of its type (its owner freezes it: haa.core.agents.agentnode). Other unallocatable agents keep
            # their allocation, as before
            r = self.records[agent]
            if r.spec.max_per_host and r.alloc and agent not in f.allocation:
                r.alloc = ""
                touched.append(agent)
        return AgentApplied("finish", "", True, "", f.leader, touched=tuple(touched))

    def _tx_move(self, m: apb.AgentMove) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("move", m.id, False, "unknown agent")
        if len(m.host) > MAX_NAME:
            return AgentApplied("move", m.id, False, f"host name must be at most {MAX_NAME} characters")
        if m.host and m.host not in self._members:
            # the operator named a member (`Operations.move` checks), but it left or was removed before the move
            # committed; its removal already cleared its allocations (`on_removed`), and an allocation to a
            # non-member would stay until the next session, which nothing may start: a crashed agent would not
            # be recovered (Alg. 8 l. 14 needs the claimer allocated), a frozen one never claimed (Alg. 6 l. 13)
            # (`haactl verify recovery --hosts 7` seeds 1954 and 1802)
            return AgentApplied("move", m.id, False, f"{m.host} is not a member of the group")
        limit = r.spec.max_per_host
        if limit and m.host:
            there = sum(1 for x in self.records.values() if x is not r and x.spec.type == r.type and x.alloc == m.host)
            if there >= limit:  # issue 15: an operator move does not break a type's per-host limit either
                why = f"{m.host} already has {there} agent(s) of type {r.type!r} (at most {limit} per host)"
                return AgentApplied("move", m.id, False, why)
        r.alloc = m.host
        if r.status == FAILED:  # an operator retries a failed agent: recovered again, from a clean count
            r.status = CRASHED
            r.failures = 0
        return AgentApplied("move", m.id, True, "", m.host, touched=(m.id,))

    def _tx_freeze(self, m: apb.AgentFreeze) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("freeze", m.id, False, "unknown agent", m.host)
        if r.owner != m.host or r.status != ACTIVE or r.epoch != m.epoch:
            return AgentApplied("freeze", m.id, False, f"not active on {m.host} at epoch {m.epoch}", m.host)
        # Alg. 5 l. 3 clears the queues: they are empty whenever an agent is active (claim and recovered hand
        # them over, a push to an active agent is not stored), so nothing is cleared here
        r.status = FREEZING
        return AgentApplied("freeze", m.id, True, "", m.host)

    def _tx_release(self, m: apb.AgentRelease) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("release", m.id, False, "unknown agent", m.host)
        if r.owner != m.host or r.status != FREEZING or r.epoch != m.epoch:
            return AgentApplied("release", m.id, False, f"not freezing on {m.host} at epoch {m.epoch}", m.host)
        r.status = FROZEN  # Alg. 5 ll. 12-16
        r.owner = ""
        r.state = m.state
        r.inbox = list(m.inbox)
        r.outbox = list(m.outbox)
        # queue1 (Alg. 5 l. 4): what the old host received after it asked the agent to freeze; it is written
        # with the release (one OAC instead of one per message; nobody reads queue1 before the release)
        r.queue1 = list(m.pending) + r.queue1
        r.failures = 0  # it ran until it was frozen: it was up
        return AgentApplied("release", m.id, True, "", m.host)

    def _tx_claim(self, m: apb.AgentClaim) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("claim", m.id, False, "unknown agent", m.host)
        if r.alloc != m.host or r.status != FROZEN:  # Alg. 6 l. 13
            return AgentApplied("claim", m.id, False, f"not frozen and allocated to {m.host}", m.host)
        r.status = ACTIVE
        r.owner = m.host
        r.epoch += 1
        return AgentApplied("claim", m.id, True, "", m.host, msgs=self._take_queues(r))

    def _tx_recovered(self, m: apb.AgentRecovered) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("recovered", m.id, False, "unknown agent", m.host)
        if r.alloc != m.host or r.status not in (NEW, CRASHED):  # Alg. 8 l. 14
            return AgentApplied("recovered", m.id, False, f"not new/crashed and allocated to {m.host}", m.host)
        r.status = ACTIVE
        r.owner = m.host
        r.epoch += 1
        r.life += 1
        # a recovered agent starts new streams: what the dead life expected or had numbered is gone
        r.inbox, r.outbox, r.pending, r.state = [], [], [], None
        return AgentApplied("recovered", m.id, True, "", m.host, msgs=self._take_queues(r))

    @staticmethod
    def _take_queues(r: AgentRecord) -> tuple[apb.RoutedMsg, ...]:
        """queue1 then queue2 (Alg. 6 l. 21), handed to the new owner and cleared."""
        out = (*r.queue1, *r.queue2)
        r.queue1, r.queue2 = [], []
        return out

    def _tx_backup(self, m: apb.AgentBackup) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("backup", m.id, False, "unknown agent", m.host)
        if r.owner != m.host or r.epoch != m.epoch or r.status not in (ACTIVE, FREEZING):
            return AgentApplied("backup", m.id, False, "stale epoch or not the owner", m.host)
        if len(m.data) > MAX_STATE:
            return AgentApplied("backup", m.id, False, f"backup larger than {MAX_STATE} bytes (MAX_STATE)", m.host)
        r.backup = m.data  # Alg. 7 l. 5
        r.backup_epoch = m.epoch
        return AgentApplied("backup", m.id, True, "", m.host)

    def _tx_failed(self, m: apb.AgentFailed) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("failed", m.id, False, "unknown agent", m.host)
        if r.owner != m.host or r.epoch != m.epoch or r.status not in (ACTIVE, FREEZING):
            return AgentApplied("failed", m.id, False, "stale epoch or not the owner", m.host)
        self._crash(r)
        # bounded: whatever a proposer puts in the transaction, the table keeps a short line
        r.fail_reason = " ".join(m.reason[: MAX_FAIL_REASON * 4].split())[:MAX_FAIL_REASON]
        r.failures = min(r.failures + 1, MAX_START_FAILURES) if m.early else 0
        if r.failures >= MAX_START_FAILURES:
            r.status = FAILED
        return AgentApplied("failed", m.id, True, m.reason[:MAX_FAIL_REASON], m.host, touched=(m.id,))

    def _crash(self, r: AgentRecord) -> None:
        r.status = CRASHED
        r.owner = ""
        r.queue1 = r.queue1 + r.queue2 if r.queue1 or r.queue2 else []
        r.queue2 = []

    def _tx_push(self, m: apb.AgentPush) -> AgentApplied:
        r = self.records.get(m.id)
        if r is None:
            return AgentApplied("push", m.id, False, "unknown agent")
        if m.queue not in (1, 2):
            return AgentApplied("push", m.id, False, "queue must be 1 or 2")
        if r.status == ACTIVE:
            # the agent is running again (the push was proposed before its owner's claim committed): nothing is
            # stored, its owner passes the messages on (their stream numbers put them in order)
            return AgentApplied("push", m.id, True, "deliver", r.owner, msgs=tuple(m.msgs))
        q = r.queue1 if m.queue == 1 else r.queue2
        room = max(0, MAX_QUEUE - len(q))
        room_bytes = MAX_QUEUE_BYTES - sum(len(x.payload) for x in q)
        kept = []
        for x in m.msgs[:room]:
            room_bytes -= len(x.payload)
            if room_bytes < 0:
                break
            kept.append(x)
        q.extend(kept)
        r.dropped += len(m.msgs) - len(kept)
        return AgentApplied("push", m.id, True, "", msgs=tuple(kept))

    def _tx_costs(self, m: apb.AgentCosts) -> AgentApplied:
        for c in m.costs:
            r = self.records.get(c.id)
            # a measured CPU share beyond MAX_COST (or inf, NaN, negative) is not a measurement: ignored
            if r is not None and r.owner == m.host and not _bad_number(c.cpu, 0.0, MAX_COST):
                r.cpu = c.cpu
        for a in m.affinity:
            if a.a in self.records and a.b in self.records and a.a != a.b and not _bad_number(a.rate, 0.0, MAX_RATE):
                key = (a.a, a.b) if a.a < a.b else (a.b, a.a)
                if a.rate > 0:
                    self.affinity[key] = a.rate
                else:
                    self.affinity.pop(key, None)
        return AgentApplied("costs", "", True, "", m.host)

    def _tx_host(self, m: apb.HostInfo) -> AgentApplied:
        why = check_host(m)
        if why:
            return AgentApplied("host", "", False, why)
        self.hosts[m.name] = m
        return AgentApplied("host", "", True, "", m.name)

    def _tx_control(self, m: apb.AllocControl) -> AgentApplied:
        self.paused = m.paused
        return AgentApplied("control", "", True)

    def placements(self) -> dict[str, dict[str, int]]:
        """Agent type -> host -> agents of that type allocated there (for `waiting`, counted once per listing)."""
        out: dict[str, dict[str, int]] = {}
        for o in self.records.values():
            if o.alloc:
                per_host = out.setdefault(o.spec.type, {})
                per_host[o.alloc] = per_host.get(o.alloc, 0) + 1
        return out

    def waiting(self, r: AgentRecord, members: Iterable[str],
                placements: Mapping[str, Mapping[str, int]] | None = None) -> str:
        """Why agent `r`, allocated nowhere, cannot run now ('' if nothing stands in its way but the next
        allocation session): no member offers its hardware, every member already runs its type's per-host limit,
        or allocation is paused. Read from the table as it is (not replicated: each host computes the same).
        `placements`: `self.placements()`, computed once when many agents are asked about (else per call: a
        listing of n waiting agents of a limited type was O(n^2))."""
        if r.alloc or r.status not in ("new", "frozen", "crashed"):
            return ""
        hosts = [self.hosts[m] for m in members if m in self.hosts and not self.hosts[m].draining]
        need = set(r.spec.hardware)
        if need and not any(need <= set(h.hardware) for h in hosts):
            offered = sorted({hw for h in hosts for hw in h.hardware})
            return (f"no host of the group offers the hardware it needs ({', '.join(sorted(need))}; offered: "
                    f"{', '.join(offered) or 'none'})")
        limit = r.spec.max_per_host
        if limit:
            per_host = (placements if placements is not None else self.placements()).get(r.spec.type, {})
            able = [h for h in hosts if need <= set(h.hardware)]
            if able and all(per_host.get(h.name, 0) >= limit for h in able):
                return (f"every host that can run it already runs {limit} agent(s) of type {r.spec.type!r} "
                        f"(at most {limit} per host)")
        if self.paused:
            return "allocation is paused (haactl alloc resume)"
        return ""

    def on_removed(self, hosts: Iterable[str]) -> tuple[str, ...]:
        """Members removed from the group: the agents they ran crashed (Alg. 8 "its host is removed"), their
        allocations are void. Returns the agents whose owner changed."""
        gone = set(hosts)
        touched = []
        for r in self.records.values():
            if r.owner in gone and r.status in (ACTIVE, FREEZING):
                self._crash(r)
                touched.append(r.id)
            if r.alloc in gone:
                r.alloc = ""
                if r.id not in touched:
                    touched.append(r.id)
        for h in gone:
            self.hosts.pop(h, None)
        return tuple(touched)

    # ------------------------------------------------------------------ snapshots

    def snapshot(self) -> bytes:
        s = apb.AgentTableSnapshot(
            ses_id=self.ses_id,
            finished_ses=self.finished_ses,
            top=self.top,
            paused=self.paused,
            start_group=self.start_group,
            start_agents=self.start_agents,
            valid_ses=self.valid_ses,
        )
        for agent in sorted(self.records):
            s.records.append(self.records[agent].to_pb())
        for name in sorted(self.hosts):
            s.hosts.append(self.hosts[name])
        for (a, b), rate in sorted(self.affinity.items()):
            s.affinity.add(a=a, b=b, rate=rate)
        encoded: bytes = s.SerializeToString()
        return encoded

    @staticmethod
    def restore(data: bytes) -> AgentTable:
        s = apb.AgentTableSnapshot()
        try:
            s.ParseFromString(data)
        except DecodeError as e:
            raise AgentTxError(f"agent table snapshot does not decode: {e}") from None
        t = AgentTable()
        t.ses_id, t.finished_ses, t.top, t.paused = s.ses_id, s.finished_ses, s.top, s.paused
        t.start_group, t.start_agents, t.valid_ses = tuple(s.start_group), tuple(s.start_agents), s.valid_ses
        for r in s.records:
            t.records[r.spec.id] = AgentRecord.from_pb(r)
        for h in s.hosts:
            t.hosts[h.name] = h
        for a in s.affinity:
            t.affinity[(a.a, a.b)] = a.rate
        return t


#: `AgentTx.body` case -> the name of its apply method (a closed table: a kind missing here is refused as
#: unknown; looked up by name so that haa.lab.dsim.mutations can patch a method)
_HANDLERS = {kind: f"_tx_{kind}" for kind in (
    "create", "remove", "start", "finish", "move", "freeze", "release", "claim", "recovered", "backup", "failed",
    "push", "costs", "host", "control",
)}
