"""Effects: what a sans-I/O core asks its driver to do.

A core never performs I/O, reads a clock or starts a task. Each input (a message, a timer, a suspicion
change, a local request) carries the current local time; the core appends effects to its outbox and the
driver (`haa.hostd.runtime` on asyncio/gRPC, `haa.lab.dsim.cluster` in simulation) drains and carries them out.
Timers are keyed: setting a key again replaces the earlier deadline.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

from haa.core.messages import Message, TxId


@dataclass(slots=True)
class Send:
    """Send `msg` to host `dst`, addressed to its incarnation `dst_inc` (0 = not known yet). `lazy`: nobody waits
    for this message in a failure-free run, so the transport may hold it a few milliseconds and send it with
    the next message on the same channel (order kept; docs/oac.md, "Lazy messages")."""

    dst: str
    dst_inc: int
    msg: Message
    lazy: bool = False


@dataclass(slots=True)
class SetTimer:
    """Call `on_timer(now, key)` once the local clock reaches `at` (replaces a timer with the same key)."""

    key: Hashable
    at: float


@dataclass(slots=True)
class CancelTimer:
    key: Hashable


@dataclass(slots=True)
class Decided:
    """Alg. 2 l. 35: this host learned the outcome of `txid` (before the l. 37 ordering gate)."""

    txid: TxId
    commit: bool


@dataclass(slots=True)
class Deliver:
    """Alg. 2 l. 38 with outcome commit: deliver `payload` to the application, in total order."""

    txid: TxId
    order: int
    payload: bytes


@dataclass(slots=True)
class Closed:
    """Alg. 2 l. 42: every participant acknowledged the decision (or is permanently suspected)."""

    txid: TxId


@dataclass(slots=True)
class Suspicion:
    """The failure detector's output about `peer` (incarnation `inc`) changed."""

    peer: str
    inc: int
    suspected: bool


@dataclass(slots=True)
class PeerDead:
    """`peer` incarnation `inc` is permanently suspected: excluded, or superseded by a new incarnation."""

    peer: str
    inc: int
    reason: str


@dataclass(slots=True)
class Reincarnate:
    """A peer excluded this incarnation: the driver must restart the core as a new incarnation."""

    by: str


@dataclass(slots=True)
class Log:
    """A structured log event for the driver's JSON-lines log."""

    event: str
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Voted:
    """This host voted `ok` on OAC transaction `txid` (Alg. 2 ll. 27-30; the verifiers check AC-Uniform-Validity
    against these)."""

    txid: TxId
    ok: bool


Effect = (Send | SetTimer | CancelTimer | Decided | Deliver | Closed | Suspicion | PeerDead | Reincarnate | Log
          | Voted)
