"""What the membership machines read of their node: one read-only view of one host incarnation.

`haa.core.membership.membership.MembershipNode` is composed of machines (`Formation`, `Join`, `MembershipUpdate`,
`GroupWrites`, `GroupLeave`, `StateTransfer`, `Sequencer`), each of which reads what it must know of the rest through a
small read-only protocol of its own (`FormationHost`, `JoinHost`, `UpdateHost`, `WritesHost`, `LeaveHost`,
`XferHost`, `SeqHost`). `NodeView` implements all of them over the node's parts — its `HostCore` (suspicion,
incarnations, OAC), its `GlobalState` (member list, view, sequencer origins), the other machines' state
(applicants, sponsees, the lock) and its life-cycle flags — and computes the derived predicates of Alg. 3:
◇S_p on members (ll. 22-31), front(memberList_p) (ll. 57, 79, 121, 172), the sequencer (docs/oac.md).
It changes nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from haa.core.host.hostcore import HostCore
from haa.core.membership.globalstate import GlobalState
from haa.core.membership.groupleave import GroupLeave
from haa.core.membership.join import Join
from haa.core.membership.statetransfer import StateTransfer
from haa.core.membership.update import MembershipUpdate
from haa.core.messages import TxId
from haa.core.oac.oac import UNDECIDED

Proc = tuple[str, int]


class ViewedNode(Protocol):
    """The parts of `haa.core.membership.membership.MembershipNode` the view reads (the node composes the view, so the
    view names the parts, not the node's class)."""

    name: str
    inc: int
    me: Proc
    state: GlobalState
    core: HostCore
    addrs: dict[str, str]
    known_hosts: list[tuple[str, str]]
    live_elsewhere: set[str]
    join: Join
    upd: MembershipUpdate
    xfer: StateTransfer
    lv: GroupLeave


class NodeView:
    """The view of `node` that its machines are given as their host: reads, and one call that changes it,
    `new_txid` (a transaction id reserved for a proposal)."""

    def __init__(self, node: ViewedNode) -> None:
        self.node = node
        self.me = node.me

    @property
    def state(self) -> GlobalState:
        return self.node.state

    def new_txid(self) -> TxId:
        return self.node.core.new_txid()

    # ------------------------------------------------------------------ the failure detector, on processes

    def suspected(self, p: Proc) -> bool:
        """◇S_p suspects incarnation `p` (never this host itself)."""
        return p != self.me and self.node.core.is_suspected(p[0], p[1])

    def is_suspected(self, name: str, inc: int) -> bool:
        return self.node.core.is_suspected(name, inc)

    def suspects_member(self) -> bool:
        """◇S_p holds a member of the view (removeList_p is not empty, ll. 22-31)."""
        return any(self.suspected(m.proc) for m in self.node.state.members)

    def known_dead(self, p: Proc) -> bool:
        """Permanently suspected: excluded, removed, or superseded by a newer incarnation we heard of."""
        if p in self.node.core.dead:
            return True
        peer = self.node.core.peers.get(p[0])
        return peer is not None and peer.inc > p[1]

    def superseded(self, p: Proc) -> bool:
        """A newer incarnation of p's host has been heard of: p is not running."""
        peer = self.node.core.peers.get(p[0])
        return p != self.me and peer is not None and peer.inc > p[1]

    def peer_list(self) -> list[Proc]:
        return sorted((q, p.inc) for q, p in self.node.core.peers.items())

    def peer_incarnation(self, name: str) -> int:
        p = self.node.core.peers.get(name)
        return p.inc if p is not None else 0

    def address(self, name: str) -> str:
        return self.node.addrs.get(name, "")

    def all_decided(self) -> bool:
        """Every OAC transaction this host knows with content is decided (l. 103)."""
        return all(not (tx.content and tx.state == UNDECIDED) for tx in self.node.core.oac.txs.values())

    # ------------------------------------------------------------------ membership

    def is_member(self) -> bool:
        return self.node.state.is_member(self.me)

    def is_leaving(self) -> bool:
        return self.node.lv.leaving

    def has_left(self) -> bool:
        return self.node.lv.left

    def leader_now(self) -> bool:
        """p = front(memberList_p): the undisputed leader (ll. 57, 121, 172)."""
        lead = self.node.state.leader()
        return lead is not None and lead.proc == self.me

    def group_formed(self) -> bool:
        return self.node.state.group_correct

    def may_form(self) -> bool:
        """A host that was a member before (it knows hosts from a previous incarnation) never forms a group:
        its group may still exist and only be slow to answer; it applies until it is joined."""
        n = self.node
        # nor one that a peer refused because another process under its name is live there (that process has a
        # group; a copied certificate or a second daemon used to form a one-host group beside it)
        return not (n.state.members or n.join.group_seen or n.lv.leaving or n.known_hosts or n.live_elsewhere)

    def applicants(self) -> Mapping[Proc, str]:
        return self.node.join.join_list

    def sponsoring(self, a: Proc) -> bool:
        return a in self.node.join.sponsees

    def connections_of(self, a: Proc) -> set[Proc]:
        return self.node.join.conns_of.get(a, set())

    # ------------------------------------------------------------------ global-state changes

    def is_locked(self) -> bool:
        return self.node.upd.locked is not None

    def catching_up(self) -> bool:
        return self.node.xfer.catching_up()

    def may_batch(self) -> bool:
        """Global-state changes may be proposed now: a member, not locked (l. 129), caught up, not left."""
        return not self.is_locked() and not self.catching_up() and not self.node.lv.left and self.is_member()

    def sequencer(self) -> Proc | None:
        """The sequencer this host forwards to: the highest-ranked member it does not suspect (the leader of
        Alg. 3 l. 79 as this host sees it; every member agrees on it while nobody is suspected)."""
        for m in self.node.state.members:
            if not self.suspected(m.proc) and not self.known_dead(m.proc):
                return m.proc
        return None

    def settled(self, origin: Proc, cseq: int) -> bool:
        d = self.node.state.seq_origins.get(origin)
        return d is not None and (cseq < d.floor or cseq in d.done)

    def request_target(self, txid: TxId) -> Proc:
        """A catching-up member asks the first unsuspected member that is not itself, else its sponsor, else
        the proposer of the transaction that added it."""
        for m in self.node.state.members:
            if m.proc != self.me and not self.suspected(m.proc):
                return m.proc
        if self.node.join.sponsor is not None:
            return self.node.join.sponsor
        return (txid.host, txid.inc)

    # ------------------------------------------------------------------ introspection

    def status(self) -> dict[str, Any]:
        n = self.node
        st = n.state
        lead = st.leader()
        return {
            "name": n.name,
            "incarnation": n.inc,
            "member": self.is_member(),
            "members": [m.name for m in st.members],
            "leader": lead.name if lead else "",
            "view": st.view,
            "rank": next((i for i, m in enumerate(st.members) if m.proc == self.me), -1),
            "group_correct": st.group_correct,
            "seq": st.seq,
            "locked": n.upd.locked or "",
            "applicants": [p[0] for p in n.join.join_list],
            "suspected": sorted(m.name for m in st.members if self.suspected(m.proc)),
            "ddb_size": st.ddb.size,
            "state_hash": st.content_hash(),
        }
