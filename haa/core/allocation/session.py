"""The per-session state of agent allocation HAA-AA (thesis Alg. 4 ll. 3-16): one `_Session` per session a host
takes part in — its id, the bid tables, the outbox, the bundle, the round and flags — and the incremental
consensus bookkeeping over its tables (how many bids differ from a member's row, how many agents are
unclaimed). Written by the `Allocator` (`haa.core.allocation.allocation`) and its bundle building
(`haa.core.allocation.bundle`).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from typing import NamedTuple

from haa.core.allocation.bids import Bid, nil_bid, same_bid
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart


class _Entry(NamedTuple):
    agents: tuple[str, ...]
    reward: float
    support: float


class _Cluster(NamedTuple):
    agents: tuple[str, ...]
    cost: float  # of the members not already reserved
    inner: tuple[float, ...]  # per member: sum of its affinities with the other members


class _Session:
    """The per-session state of Alg. 4 ll. 3-16 (sesId, bidTable, outbox, bundle, r, flags)."""

    def __init__(self, ses_id: int, me: str) -> None:
        self.ses_id = ses_id
        self.me = me
        self.start: SessionStart | None = None
        self.ready = False  # sesReady_p
        self.decided = False  # decided_p
        self.build_queued = False
        self.distribute_queued = False
        self.r = 0  # r_p
        self.round_used = -1  # lastBuildRound_p, and rounds used by "update time"
        self.own: dict[str, Bid] = {}  # bidTable_p[p]
        self.rows: dict[str, dict[str, Bid]] = {}  # bidTable_p[q] for q != p
        self.outbox: dict[str, Bid] = {}
        self.replies: dict[str, dict[str, Bid]] = {}  # q -> bids only q needs (Allocator._broadcast)
        self.sent: dict[str, Bid] = {}  # the bid of each agent this host last sent to every member
        self.bundle: list[_Entry] = []
        self.entry_of: dict[str, int] = {}
        # known once ready
        self.group: tuple[str, ...] = ()
        self.others: tuple[str, ...] = ()
        self.agents: dict[str, AgentSpec] = {}
        self.allocatable: frozenset[str] = frozenset()
        self.unallocatable: tuple[str, ...] = ()
        self.spec: HostSpec | None = None
        self.eligible: tuple[str, ...] = ()
        self.exclusive: frozenset[str] = frozenset()
        self.limits: dict[str, tuple[str, int]] = {}  # agent -> (kind, max_per_host), limited eligible agents
        self.rev: dict[str, list[tuple[str, float]]] = {}  # j -> [(i, alpha_ij)]: who gains from j
        self.nbrs: dict[str, tuple[str, ...]] = {}  # affinity (either way) among eligible agents
        self.clusters: list[_Cluster] | None = None  # enumerated at the first build
        self.mismatch = 0  # (q, j) with bidTable_p[q][j] != bidTable_p[p][j]
        self.unclaimed = 0  # allocatable j with bidTable_p[p][j].z == none
        self.messages_sent = 0
        self.builds = 0
        # sessions of a bounded size (SessionStart.auction): agents outside the auction that keep their host
        self.pinned: dict[str, str] = {}
        self.pinned_mine: tuple[str, ...] = ()  # those on this host, in the start's order
        self.base_used = 0.0  # their cost: capacity this host's bundle starts with

    def bid(self, j: str) -> Bid:
        b = self.own.get(j)
        return b if b is not None else nil_bid(j)

    def row_bid(self, q: str, j: str) -> Bid:
        b = self.rows.get(q, {}).get(j)
        return b if b is not None else nil_bid(j)

    # --- table maintenance (incremental consensus bookkeeping)

    def set_own(self, j: str, b: Bid) -> None:
        old = self.bid(j)
        if old == b:
            return
        self.own[j] = b
        if not self.ready:
            return
        if j in self.allocatable:
            self.unclaimed += (b.winner is None) - (old.winner is None)
        if same_bid(old, b):
            return
        for q in self.others:
            t = self.row_bid(q, j)
            self.mismatch += (not same_bid(t, b)) - (not same_bid(t, old))

    def set_row(self, q: str, j: str, b: Bid) -> None:
        row = self.rows.get(q)
        if row is None:
            row = self.rows[q] = {}
        old = row.get(j)
        if old is None:
            old = nil_bid(j)
        row[j] = b
        if self.ready and not same_bid(old, b):
            own = self.bid(j)
            self.mismatch += (not same_bid(b, own)) - (not same_bid(old, own))

    def make_ready(self, start: SessionStart, me: str) -> None:
        """ll. 45-49: take the session's parameters; drop what does not belong to it."""
        self.start = start
        self.group = start.group
        self.others = tuple(h for h in start.group if h != me)
        self.agents = {a.id: a for a in start.agents}
        self.spec = start.host(me) if me in start.group else None
        self.unallocatable = start.unallocatable()
        self.allocatable = frozenset(self.agents) - frozenset(self.unallocatable)
        spec = self.spec
        unalloc = frozenset(self.unallocatable)  # an agent left out for its kind's limit gets no bid either
        if start.auction is not None:  # a bounded session: only its auction is bid for and agreed on
            auction = frozenset(start.auction)
            self.allocatable = self.allocatable & auction
            self.pinned = start.pinned()
            self.pinned_mine = tuple(j for j, h in self.pinned.items() if h == me)
            base = 0.0
            for j in self.pinned_mine:  # a fixed order (the start's), so the sum is the same on every run
                base += self.agents[j].cost
            self.base_used = base
        else:
            auction = frozenset(self.agents)
        self.eligible = tuple(
            a.id
            for a in start.agents
            if spec is not None and spec.can_run(a) and a.id not in unalloc and a.id in auction
        )
        # per-host limits (issue 15): eligible agent -> (kind, max_per_host)
        self.limits = {a.id: (a.kind, a.max_per_host) for a in start.agents if a.max_per_host and a.id in self.eligible}
        hosts = [start.host(g) for g in start.group]
        self.exclusive = frozenset(  # agents only this host of the group can run
            a.id for a in start.agents if a.id in self.eligible and sum(h.can_run(a) for h in hosts) == 1
        )
        rev: dict[str, list[tuple[str, float]]] = {}
        for a in start.agents:
            for j, alpha in a.affinity.items():
                if alpha > 0.0 and j in self.agents:
                    rev.setdefault(j, []).append((a.id, alpha))
        self.rev = rev
        el = set(self.eligible)
        self.nbrs = {
            i: tuple(
                j
                for j in self.eligible
                if j != i and self.agents[i].affinity.get(j, 0.0) + self.agents[j].affinity.get(i, 0.0) > 0.0
            )
            for i in self.eligible
            if i in el
        }
        known = self.agents
        self.own = {j: b for j, b in self.own.items() if j in known and (b.winner is None or b.winner in self.group)}
        self.outbox = {j: b for j, b in self.outbox.items() if j in known}
        self.rows = {
            q: {j: b for j, b in row.items() if j in known} for q, row in self.rows.items() if q in self.others
        }
        self.ready = True
        self.unclaimed = sum(1 for j in self.allocatable if self.bid(j).winner is None)
        self.mismatch = sum(
            1 for q in self.others for j in self.agents if not same_bid(self.row_bid(q, j), self.bid(j))
        )
