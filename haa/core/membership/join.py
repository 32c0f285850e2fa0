"""Joining a group: the applicant's side and the members' (thesis Alg. 3 ll. 35-39, 50-75, 18-21, 32-34).

Alg. 3 (thesis L2358-2565, described at L669-690) lets a host join at run time: the applicant sends `apply`
to every core process (ll. 36-39); whoever hears of it records it in joinList_p, opens a connection to it,
introduces itself to it and introduces it to every member and applicant it knows (ll. 50-56); the leader
sponsors it: tells it so and sends it the global state, then forwards every later change (ll. 57-61, the
forwarding is the node's). An applicant that hears an introduction opens a connection to the host
introduced (ll. 62-68) and tells its sponsor whom it is connected to both ways (ll. 69-73); the sponsor keeps
the latest such list per applicant (ll. 74-75), which updateMembership reads (`haa.core.membership.update`).

`Join` is this part of one host incarnation as a sans-I/O machine with its own state — joinList_p (l. 2),
connectionsTo_p / connectionsFrom_p (ll. 8-9), sponsor_p (l. 10), sponsees_p (l. 11), the applicants'
connection lists — and HAA's completions (docs/membership.md): an applicant re-applies to the core processes
it has not heard from (`ReapplyDue`), also applies to every member of a correct group that introduces itself
(the leader need not be a core process), is introduced again once the introducer's view changed, and
withdraws its application when it leaves; a provisional group that learns of a different correct group is
abandoned (`Abandon`: the node restarts as a new incarnation).

Interface: `step(now, input) -> list[JoinEffect]` over the closed unions `JoinInput` and `JoinEffect`. What
the machine reads of its node (the global state, membership, suspicion, leadership) comes through the
read-only `JoinHost` protocol; links, sends, the state snapshot and a re-run of updateMembership are
effects, carried out by the node in the order returned.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.effects import Log, Send, SetTimer
from haa.core.membership.globalstate import GlobalState
from haa.core.membership.groupeffects import NodeTimer
from haa.core.messages import Apply, Connections, Introduce, Member, Message, Sponsor

Proc = tuple[str, int]

REAPPLY_TIMER = NodeTimer("reapply")


class JoinHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    @property
    def state(self) -> GlobalState:
        """The group's global state as applied here (member list, view, group id)."""

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def is_leaving(self) -> bool:
        """groupLeave() was called here (l. 14)."""

    def suspected(self, p: Proc) -> bool:
        """◇S_p suspects incarnation `p` (never this host itself)."""

    def known_dead(self, p: Proc) -> bool:
        """`p` is permanently suspected: excluded, removed, or superseded by a newer incarnation."""

    def leader_now(self) -> bool:
        """This host is front(memberList_p) (ll. 57, 121, 172)."""


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Start:
    """groupJoin() (ll. 35-39): apply to every contact."""


@dataclass(frozen=True, slots=True)
class ReapplyDue:
    """`REAPPLY_TIMER` fired: apply again until sponsored, introduce ourselves to silent members."""


@dataclass(frozen=True, slots=True)
class Heard:
    """A membership message from `src`: `apply` (ll. 50-61), an introduction of `src` itself or relayed about
    another host (ll. 62-70), `sponsor` (ll. 71-73), or an applicant's two-way connections (ll. 74-75)."""

    src: Proc
    msg: Apply | Introduce | Sponsor | Connections


@dataclass(frozen=True, slots=True)
class Withdraw:
    """Applicant `applicant` left before it joined: drop its application (docs/membership.md)."""

    applicant: Proc


@dataclass(frozen=True, slots=True)
class PeerGone:
    """`proc` is permanently suspected (ll. 32-34)."""

    proc: Proc


@dataclass(frozen=True, slots=True)
class Admitted:
    """A committed membership or formation list holds `procs` (ll. 137-140, 168); `mine`: this host proposed
    it, so it no longer sponsors them."""

    procs: frozenset[Proc]
    mine: bool


@dataclass(frozen=True, slots=True)
class ViewChanged:
    """A committed change made `members` the member list and removed `removed`: open a connection to every
    member (ll. 144-151: the next leader may be any of them); the removed are permanently suspected (l. 118,
    docs/membership.md) and no applicants either."""

    members: tuple[Member, ...]
    removed: tuple[Member, ...]


@dataclass(frozen=True, slots=True)
class Joined:
    """This host became a member: it has no sponsor any more."""


@dataclass(frozen=True, slots=True)
class SponsorAll:
    """The leader sponsors every applicant it does not sponsor yet (ll. 121-126, 172-177, and after a change
    that made it the leader: docs/membership.md)."""


JoinInput = (
    Start | ReapplyDue | Heard | Withdraw | PeerGone | Admitted | ViewChanged | Joined | SponsorAll
)


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class Link:
    """"open connection to" host `name` (ll. 37, 53, 66): monitor it and link to it (at `addr` if given)."""

    name: str
    addr: str | None = None


@dataclass(frozen=True, slots=True)
class ToHost:
    """Send `msg` to host `name`'s incarnation as the node knows it when it sends."""

    name: str
    msg: Message


@dataclass(frozen=True, slots=True)
class Hear:
    """Host `name` runs incarnation `inc` (`hearsay`: a third host said so; `HostCore.add_peer`)."""

    name: str
    inc: int
    hearsay: bool


@dataclass(frozen=True, slots=True)
class MarkRemoved:
    """Permanently suspect host `name`'s incarnation `inc`: the group removed it (`HostCore.mark_dead`)."""

    name: str
    inc: int


@dataclass(frozen=True, slots=True)
class Remember:
    """Host `name` is at `addr`, if no address is known for it yet."""

    name: str
    addr: str


@dataclass(frozen=True, slots=True)
class SendState:
    """l. 60: send the global state to sponsee `to`."""

    to: Proc


@dataclass(frozen=True, slots=True)
class Abandon:
    """Someone holds the state of the correct group `existing`: this provisional group restarts and applies."""

    existing: str


@dataclass(frozen=True, slots=True)
class RunUpdate:
    """Run updateMembership() now (ll. 75, 133, 151, 179: the machine's state it reads has changed)."""


JoinEffect = Link | ToHost | Hear | MarkRemoved | Remember | SendState | Abandon | RunUpdate | Send | SetTimer | Log


# ------------------------------------------------------------------------------------------------ machine


class Join:
    """The join part of one host incarnation (see the module docstring)."""

    def __init__(self, me: Proc, addr: str, core_names: Sequence[str], known_hosts: Sequence[str], host: JoinHost,
                 reapply: float) -> None:
        self.me = me
        self.addr = addr
        self.core_names = tuple(core_names)
        self.known_hosts = tuple(known_hosts)
        self.host = host
        self.reapply = reapply
        self.join_list: dict[Proc, str] = {}  # l. 2, applicant -> address, in application order
        self.conn_to: set[str] = set()  # l. 8 (a link is per host name)
        self.conn_from: set[Proc] = set()  # l. 9
        self.sponsor: Proc | None = None  # l. 10
        self.sponsees: set[Proc] = set()  # l. 11
        self.conns_of: dict[Proc, set[Proc]] = {}  # the latest (connections, a, list) per applicant
        self.group_seen = ""  # id of a correct group someone introduced to us
        self.group_hosts: dict[str, None] = {}  # hosts that introduced themselves with a correct group (ordered)
        self.introduced: dict[Proc, tuple[str, int]] = {}  # applicant -> (group, view) when we introduced it
        self._out: list[JoinEffect] = []

    def step(self, now: float, inp: JoinInput) -> list[JoinEffect]:
        out: list[JoinEffect] = []
        self._out = out
        match inp:
            case Start():
                for q in self._contacts():  # ll. 36-39
                    out.append(Link(q))
                    self.conn_to.add(q)
                    out.append(ToHost(q, Apply(self.addr)))
                out.append(SetTimer(REAPPLY_TIMER, now + self.reapply))
            case ReapplyDue():
                self._reapply(now)
            case Heard(q, msg):
                self._heard(q, msg)
            case Withdraw(q):
                del self.join_list[q]
                self.sponsees.discard(q)
                self.conns_of.pop(q, None)
                out.append(Log("application_withdrawn", {"applicant": f"{q[0]}.{q[1]}"}))
            case PeerGone(p):  # ll. 32-34
                self.join_list.pop(p, None)
                self.sponsees.discard(p)
                self.conns_of.pop(p, None)
                if self.sponsor == p:
                    self.sponsor = None
                out.append(RunUpdate())
            case Admitted(procs, mine):
                if mine:  # ll. 137-139
                    self.sponsees -= procs
                for p in list(self.join_list):  # ll. 140, 168
                    if p in procs:
                        del self.join_list[p]
            case ViewChanged(members, removed):
                for m in members:
                    if m.proc != self.me:
                        out += [Link(m.name, m.addr), Hear(m.name, m.inc, False)]
                for m in removed:
                    if m.proc != self.me:
                        out.append(MarkRemoved(m.name, m.inc))
                        self.join_list.pop(m.proc, None)
            case Joined():
                self.sponsor = None
            case SponsorAll():
                for a in list(self.join_list):
                    if a not in self.sponsees and not self.host.known_dead(a):
                        self._sponsor(a)
            case _:
                assert_never(inp)
        return out

    def _heard(self, q: Proc, msg: Apply | Introduce | Sponsor | Connections) -> None:
        match msg:
            case Apply(addr):
                self._on_apply(q, addr)
            case Introduce():
                self._on_introduce(q, msg)
            case Sponsor():  # ll. 71-73
                if not self.host.is_member():
                    self.sponsor = q
                    self._send(q, Connections(self._two_way()))
            case Connections(peers):  # ll. 74-75
                self.conns_of[q] = set(peers)
                self._out.append(RunUpdate())
            case _:
                assert_never(msg)

    # ------------------------------------------------------------------ the applicant

    def _contacts(self) -> list[str]:
        """Where an applicant sends `apply`: every core process (l. 36), the hosts it knew before, and the hosts
        that introduced themselves as holding a correct group (docs/membership.md, "apply to the members")."""
        name = self.me[0]
        out = [q for q in self.core_names if q != name] + list(self.known_hosts)
        return out + [q for q in self.group_hosts if q not in out and q != name]

    def _reapply(self, now: float) -> None:
        """Until a leader sponsors us, apply again: an `apply` sent before a core process was up is lost, and one
        received by a core process that was not yet a member made no leader sponsor us."""
        h = self.host
        if h.is_member():
            return
        if self.sponsor is None or h.suspected(self.sponsor):
            for q in self._contacts():
                self._out.append(ToHost(q, Apply(self.addr)))
        st = h.state
        for m in st.members:  # members we never heard from: introduce ourselves again
            if m.proc not in self.conn_from and not h.known_dead(m.proc):
                self._out.append(Link(m.name, m.addr))
                self.conn_to.add(m.name)
                self._send(m.proc, Introduce(self.me[0], self.me[1], self.addr, st.group_id()))
        self._out.append(SetTimer(REAPPLY_TIMER, now + self.reapply))

    def _on_introduce(self, q: Proc, msg: Introduce) -> None:
        """ll. 62-70."""
        h = self.host
        a = (msg.name, msg.inc)
        if msg.group:
            self._group_evidence(msg.group)
        if a == self.me or h.known_dead(a):
            return
        # the first word from this incarnation itself: our link to its host name may date from an earlier
        # incarnation, which is no connection to this one (docs/membership.md, "lost introductions")
        first = a == q and q not in self.conn_from
        if a == q:  # ll. 63-64
            self.conn_from.add(q)
            if msg.group and not h.is_member() and not h.is_leaving() and q[0] not in self.group_hosts:
                # a member of a correct group: apply to it too, so that the leader (which need not be a core
                # process) hears our application and sponsors us (l. 57); docs/membership.md
                self.group_hosts[q[0]] = None
                if q[0] not in self.core_names and (self.sponsor is None or h.suspected(self.sponsor)):
                    self._send(q, Apply(self.addr))
        if a[0] not in self.conn_to or (a != q and a not in self.conn_from) or first:  # ll. 65-68
            # (also when we "opened" the link before but never heard from `a`: our `apply` or introduction
            # may have reached it before it was running; docs/membership.md, "lost introductions")
            self._out.append(Link(a[0], msg.addr))
            self.conn_to.add(a[0])
            # a relayed introduction (a != q) is hearsay about a's incarnation (HostCore._believe_hearsay)
            self._out.append(Hear(a[0], a[1], a != q))
            self._send(a, Introduce(self.me[0], self.me[1], self.addr, h.state.group_id()))
        elif msg.addr:
            self._out.append(Remember(a[0], msg.addr))
            self._out.append(Hear(a[0], a[1], a != q))
        self._report_connections()  # ll. 69-70

    def _report_connections(self) -> None:
        """ll. 69-70: an applicant tells its sponsor whom it is connected to both ways."""
        if not self.host.is_member() and self.sponsor is not None:
            self._send(self.sponsor, Connections(self._two_way()))

    def _group_evidence(self, gid: str) -> None:
        """docs/membership.md, "restarts": someone holds the state of a correct group `gid`."""
        self.group_seen = gid
        st = self.host.state
        if st.members and not st.group_correct and st.genesis != gid and self.host.is_member():
            self._out.append(Abandon(gid))

    def _two_way(self) -> tuple[Proc, ...]:
        """connectionsTo_p ∩ connectionsFrom_p (ll. 70, 73)."""
        return tuple(sorted(p for p in self.conn_from if p[0] in self.conn_to))

    # ------------------------------------------------------------------ the members

    def _on_apply(self, a: Proc, addr: str) -> None:
        """ll. 50-61."""
        h = self.host
        st = h.state
        if st.is_member(a) or h.known_dead(a):
            return
        # introduce a to everyone (l. 56) when we first hear of it, and again once our view has changed since:
        # a host that was itself applying when `a` applied to it knew no members then (docs/membership.md)
        here = (st.genesis, st.view)
        fresh = a not in self.join_list or self.introduced.get(a) != here
        self.join_list[a] = addr  # l. 51
        self.conn_from.add(a)  # l. 52
        self._out.append(Link(a[0], addr))  # l. 53
        self.conn_to.add(a[0])  # l. 54
        gid = st.group_id()
        self._send(a, Introduce(self.me[0], self.me[1], self.addr, gid))  # l. 55
        if fresh:
            self.introduced = {p: v for p, v in self.introduced.items() if p in self.join_list}
            self.introduced[a] = here
            for p in [*st.procs(), *self.join_list]:  # l. 56
                if p != a and p != self.me:
                    self._send(p, Introduce(a[0], a[1], addr, gid))
        if h.leader_now():  # ll. 57-61
            if a not in self.sponsees:
                self._sponsor(a)
            else:
                # an applicant we sponsor applies again: it lost track of its sponsor (a stale leader's Sponsor,
                # sent after a pause, replaced ours and then died); tell it again (docs/membership.md, "sponsor")
                self._send(a, Sponsor())
        # an applicant that another applicant applied to (a host it knew from a previous life) gains a two-way
        # link here, and no introduction follows: tell the sponsor now, as ll. 69-70 do on an introduction
        self._report_connections()
        self._out.append(RunUpdate())

    def _sponsor(self, a: Proc) -> None:
        """ll. 58-61 (and 123-126, 174-177)."""
        self.sponsees.add(a)
        self._send(a, Sponsor())
        self._out.append(SendState(a))

    def _send(self, dst: Proc, msg: Message) -> None:
        if dst != self.me:
            self._out.append(Send(dst[0], dst[1], msg))
