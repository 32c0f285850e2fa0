"""Global-state changes requested on one host: proposed, held while locked, acknowledged once committed.

Alg. 3 applies every change of the global state in total order by OAC among the members (thesis L698-712,
ll. 127-132, 144-145, 153-155): a change requested while the global state is locked for a membership change
is held (l. 129) and proposed once it is unlocked (ll. 132, 145, 155). HAA acknowledges a change to whoever
requested it only once it committed and was applied here (`WriteDone`), re-proposes it after an abort (given
up after `max_attempts` aborts), and holds it too while this host is a new member whose state has not caught
up. An abort while this host suspects a member of its view (removeList_p not empty, ll. 22-31) is not
counted: OAC commits only if no participant is suspected (AC-Non-Triviality, thesis L549), so until the
suspicion ends — the member trusted again (l. 26) or removed (l. 117) — every proposal would abort. The
change is held instead and proposed again on `Release`, which the node steps when a suspicion ends or the
view changes as well as when the lock is released. (Re-proposed at once, 50 aborts took well under a second
of an asymmetric delay spike that made this host suspect a member the others still trusted, and an agent's
`spawn_child` or DDB write failed: `haactl verify executive --hosts 7`, seeds 1263, 1572, 1853.) These are
the agent-table changes (`TxAgent`), and DDB and test writes when the node runs without the sequencer
(`NodeConfig.sequencer` off, the thesis' own way); with it, the node hands DDB and test writes straight to
the sequencer (`haa.core.membership.sequencer`, docs/oac.md), which does its own holding.

`GroupWrites` is this part of one host incarnation as a sans-I/O machine with its own state: the changes
held, and the proposed ones by transaction id. Interface: `step(now, input) -> list[WritesEffect]` over the
closed unions `WritesInput` and `WritesEffect`; a proposal is the effect `ProposeWrite`, with the transaction
id the machine reserved (`new_txid`), which the node proposes at once. What it reads of the node comes through
`WritesHost`.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.membership.groupeffects import WriteDone
from haa.core.messages import TxId


class WritesHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def group_formed(self) -> bool:
        """The group is a correct group (not provisional)."""

    def is_locked(self) -> bool:
        """locked_p (l. 6): the global state is locked for a membership change."""

    def catching_up(self) -> bool:
        """A new member whose state has not caught up yet."""

    def suspects_member(self) -> bool:
        """This host suspects a member of its view (removeList_p is not empty, ll. 22-31)."""

    def new_txid(self) -> TxId:
        """A fresh OAC transaction id of this host incarnation for a proposal (the one call that changes the node:
        it reserves the id, so the machine knows its transaction before it is proposed)."""


@dataclass(slots=True)
class Write:
    req: Hashable
    payload: bytes
    #: aborts counted against `max_attempts` (not those while this host suspected a member)
    attempts: int = 0


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Request:
    """Change the global state by the encoded group transaction `payload`."""

    req: Hashable
    payload: bytes


@dataclass(frozen=True, slots=True)
class Release:
    """The global state may be unlocked, the new member caught up, a suspicion ended or the view changed:
    propose what is held."""


@dataclass(frozen=True, slots=True)
class Aborted:
    """OAC aborted `txid`."""

    txid: TxId


@dataclass(frozen=True, slots=True)
class Committed:
    """`txid` was applied here as the `seq`-th transaction, with `error` and `result` of the application."""

    txid: TxId
    seq: int
    error: str
    result: object


WritesInput = Request | Release | Aborted | Committed


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class ProposeWrite:
    """Propose `payload` by OAC as `txid` to every member."""

    txid: TxId
    payload: bytes


WritesEffect = ProposeWrite | WriteDone


# ------------------------------------------------------------------------------------------------ machine


class GroupWrites:
    """The global-state changes of one host incarnation (see the module docstring)."""

    def __init__(self, host: WritesHost, max_attempts: int) -> None:
        self.host = host
        self.max_attempts = max_attempts
        self.held: list[Write] = []  # changes held while locked (l. 129) or catching up
        self.writes: dict[TxId, Write] = {}  # proposed, not yet committed or aborted
        self._out: list[WritesEffect] = []

    def step(self, now: float, inp: WritesInput) -> list[WritesEffect]:
        self._out = []
        h = self.host
        match inp:
            case Request(req, payload):
                w = Write(req, payload)
                if h.catching_up():  # a new member catching up: hold until its state has caught up
                    self.held.append(w)
                elif not h.is_member():
                    self._out.append(WriteDone(req, False, None, 0, "not a member of the group"))
                elif not h.group_formed():
                    self._out.append(WriteDone(req, False, None, 0, "the group is not formed yet"))
                elif h.is_locked():  # l. 129: hold while locked
                    self.held.append(w)
                else:
                    self._propose(w)
            case Release():  # ll. 132, 145, 155
                if not (h.is_locked() or h.catching_up()):
                    held, self.held = self.held, []
                    for w in held:
                        self._propose(w)
            case Aborted(txid):
                w_ = self.writes.pop(txid, None)
                if w_ is None:
                    pass
                elif h.is_member() and h.suspects_member():  # AC-Non-Triviality: wait for the suspicion to end
                    self.held.append(w_)
                else:
                    w_.attempts += 1
                    self._retry(w_, "aborted")
            case Committed(txid, seq, error, result):
                w_ = self.writes.pop(txid, None)
                if w_ is not None:
                    self._out.append(WriteDone(w_.req, True, txid, seq, error, result))
            case _:
                assert_never(inp)
        return self._out

    def _propose(self, w: Write) -> None:
        txid = self.host.new_txid()
        self.writes[txid] = w
        self._out.append(ProposeWrite(txid, w.payload))

    def _retry(self, w: Write, why: str) -> None:
        h = self.host
        if w.attempts >= self.max_attempts:
            self._out.append(WriteDone(w.req, False, None, 0, f"gave up after {w.attempts} attempts ({why})"))
        elif not h.is_locked() and h.is_member() and not h.catching_up():
            self._propose(w)
        elif h.is_member():
            self.held.append(w)
        else:
            self._out.append(WriteDone(w.req, False, None, 0, "no longer a member of the group"))
