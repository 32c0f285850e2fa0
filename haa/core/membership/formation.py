"""Group formation: the first group of the core processes (thesis Alg. 3 ll. 40-49 and 158-179).

Alg. 3 (thesis L2358-2565; described at L669-680 and L698) forms the group without a membership service to
ask: the first core process forms a provisional group of one at once (ll. 41-43: OAC(membership) to
itself, L2414-2416), which grows into a correct group as core processes apply; should it fail before that,
the other processes of the core head wait FORMATION_TIMEOUT (l. 45) and then, while they are not members,
propose OAC(formationFallback) of the unsuspected core head to the core head (ll. 46-49, L2417-2423), on
which every participant votes yes only while it has no group and the list is exactly its own (ll. 158-165,
L2545-2551). `Formation` is this part of one host incarnation, as a sans-I/O machine with its own state: the
role of the host (first core process, core head, neither), the fallback transaction in progress, and its
timers. HAA's completions (docs/membership.md, "restarts"): the first core process listens `discovery`
seconds for an existing group before forming its own, and no host forms a group once it knows of a correct
group, is leaving, or was a member before (`FormationHost.may_form`).

Interface: `step(now, input) -> list[FormationEffect]` over the closed unions `FormationInput` and
`FormationEffect`, plus the pure query `vote(tx)` (the OAC evaluate hook of ll. 158-165). What the machine
reads of its node (incarnations and suspicion of the core head, whether it may form) comes through the
read-only `FormationHost` protocol. Committing the formation (ll. 166-179) is the global state's
(`GlobalState.apply`) and the membership update's.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.effects import Log, SetTimer
from haa.core.membership.globalstate import TxFormation
from haa.core.membership.groupeffects import NodeTimer
from haa.core.messages import Member, TxId

Proc = tuple[str, int]

DISCOVERY_TIMER = NodeTimer("discovery")
FORMATION_TIMER = NodeTimer("formation")


@dataclass(frozen=True, slots=True)
class FormationConfig:
    """The formation's share of `haa.core.membership.membership.NodeConfig` (same names, same meaning)."""

    formation_timeout: float = 5.0
    formation_retry: float = 1.0
    discovery: float = 1.0


class FormationHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    def may_form(self) -> bool:
        """No group is known here: no member list, no correct group heard of, not leaving, never a member."""

    def peer_incarnation(self, name: str) -> int:
        """The incarnation of host `name` this host knows (0: never heard of)."""

    def is_suspected(self, name: str, inc: int) -> bool:
        """The failure detector suspects this incarnation (◇S_p)."""

    def address(self, name: str) -> str:
        """The address of host `name` ("" if unknown)."""

    def new_txid(self) -> TxId:
        """A fresh OAC transaction id of this host incarnation for a proposal (the one call that changes the node:
        it reserves the id, so the machine knows its transaction before it is proposed)."""


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Start:
    """groupJoin() (l. 35): arm the timer of this host's role."""


@dataclass(frozen=True, slots=True)
class DiscoveryDue:
    """`DISCOVERY_TIMER` fired (the first core process, l. 41)."""


@dataclass(frozen=True, slots=True)
class FormationDue:
    """`FORMATION_TIMER` fired (FORMATION_TIMEOUT, l. 45, or a retry after an abort, l. 46)."""


@dataclass(frozen=True, slots=True)
class Aborted:
    """OAC aborted transaction `txid`; `has_group`: this host has a member list by now."""

    txid: TxId
    has_group: bool


@dataclass(frozen=True, slots=True)
class Delivered:
    """OAC delivered (committed) transaction `txid`."""

    txid: TxId


FormationInput = Start | DiscoveryDue | FormationDue | Aborted | Delivered


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class FormGroupOfOne:
    """ll. 42-43: lock the global state with a new key and commit OAC(membership) with this host alone."""


@dataclass(frozen=True, slots=True)
class ProposeFallback:
    """l. 48: propose OAC(formationFallback, p, members) as `txid` to `members`."""

    txid: TxId
    members: tuple[Member, ...]


FormationEffect = FormGroupOfOne | ProposeFallback | SetTimer | Log


# ------------------------------------------------------------------------------------------------ machine


class Formation:
    """The formation part of host incarnation `me` (at `addr`). See the module docstring."""

    def __init__(self, me: Proc, addr: str, core_names: Sequence[str], c_h: int, host: FormationHost,
                 config: FormationConfig | None = None) -> None:
        self.me = me
        self.addr = addr
        self.core_head = tuple(core_names[:c_h])  # l. 40
        self.first = bool(core_names) and core_names[0] == me[0]  # l. 41
        self.host = host
        self.config = config or FormationConfig()
        self.txid: TxId | None = None  # our OAC(formationFallback) not yet decided (l. 49)
        self._out: list[FormationEffect] = []

    def step(self, now: float, inp: FormationInput) -> list[FormationEffect]:
        cfg = self.config
        match inp:
            case Start():
                if self.first:
                    self._out.append(SetTimer(DISCOVERY_TIMER, now + cfg.discovery))
                elif self.me[0] in self.core_head:  # l. 44
                    self._out.append(SetTimer(FORMATION_TIMER, now + cfg.formation_timeout))  # l. 45
            case DiscoveryDue():
                if self.host.may_form():  # ll. 41-43, after `discovery`
                    self._out.append(FormGroupOfOne())
            case FormationDue():
                # ll. 46-48: while p ∉ memberList_p, propose to the unsuspected core head; l. 49: one at a time
                if self.host.may_form() and self.txid is None:
                    self.txid = txid = self.host.new_txid()
                    members = self.head_list()
                    self._out.append(ProposeFallback(txid, members))
                    self._out.append(Log("formation_fallback", {"tx": str(txid), "members": [m.name for m in members]}))
            case Aborted(txid, has_group):
                if txid == self.txid:
                    self.txid = None
                    if not has_group:
                        self._out.append(SetTimer(FORMATION_TIMER, now + cfg.formation_retry))  # l. 46: repeat
            case Delivered(txid):
                if txid == self.txid:
                    self.txid = None
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    def owns(self, txid: TxId) -> bool:
        """`txid` is our OAC(formationFallback) in progress (the node steps `Aborted`/`Delivered` only then)."""
        return txid == self.txid

    def head_list(self) -> tuple[Member, ...]:
        """coreHead − (coreHead ∩ ◇S_p) (l. 47, l. 162)."""
        out = []
        for q in self.core_head:
            if q == self.me[0]:
                out.append(Member(q, self.me[1], self.addr))
                continue
            inc = self.host.peer_incarnation(q)
            if not inc or self.host.is_suspected(q, inc):
                continue
            out.append(Member(q, inc, self.host.address(q)))
        return tuple(out)

    def vote(self, tx: TxFormation, has_group: bool) -> bool:
        """ll. 158-165: yes only without a group (ll. 160-161) and for exactly our own list (ll. 162-163)."""
        if has_group:
            return False
        return [m.proc for m in tx.members] == [m.proc for m in self.head_list()]
