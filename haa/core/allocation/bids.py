"""Bids of agent allocation HAA-AA (thesis §4.7, Appendix II): one entry of a bid table, and their order.

* `Bid`: one entry of bidTable_p (agent, winner, reward, support, round); `nil_bid`, Table 4.7-1's "reset";
* `BidUpdate`: the update message hosts send each other during a session (Alg. 4 l. 59, l. 84);
* the order of bids, "HAA-AA Bid Comparison Operator" (Fig. II-1 as reconstructed, docs/allocation.md):
  `bid_key`, `bid_gt`, and `same_bid` (same winner and value, the test of consensus, l. 87).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from haa.core.allocation.specs import INF


class Bid(NamedTuple):
    """One entry of bidTable_p: {j, z_j (winner; None = none), y_j = {reward, support}, r_j (round)}."""

    agent: str
    winner: str | None
    reward: float
    support: float
    round: int


_NILS: dict[str, Bid] = {}


def nil_bid(agent: str) -> Bid:
    """Table 4.7-1 "reset": {j, none, {0, -inf}, 0}."""
    b = _NILS.get(agent)
    if b is None:
        b = Bid(agent, None, 0.0, -INF, 0)
        if len(_NILS) < 100_000:
            _NILS[agent] = b
    return b


@dataclass(frozen=True)
class BidUpdate:
    """(update, q, sesId_q, for each updated bid j: {j, z_qj, y_qj, r_qj}) (Alg. 4 l. 59, l. 84)."""

    ses_id: int
    bids: tuple[Bid, ...]
    sender: str = ""



# --------------------------------------------------------------------------------------------- bid order


def bid_key(b: Bid) -> tuple[int, float, float]:
    """The value part of the order (Fig. II-1 as reconstructed, docs/allocation.md): class 1 = within
    capacity (support > 0) ranked by (reward, support); class 0 = over capacity ranked by (support, reward);
    class -1 = the nil bid."""
    if b.winner is None:
        return (-1, 0.0, 0.0)
    if b.support > 0.0:
        return (1, b.reward, b.support)
    return (0, b.support, b.reward)


def bid_gt(a: Bid, b: Bid) -> bool:
    """a > b: the bid comparison operator, a strict total order on (values, winner). Equal values are
    broken by the lower host name (Appendix II: "ties can be broken by taking the bidder with the lower ID");
    two nil bids are equal. (`bid_key` spelled out, for speed.)"""
    _ja, wa, ra, sa, _ra = a
    _jb, wb, rb, sb, _rb = b
    if wa is None:
        return False
    if wb is None:
        return True
    fa = sa > 0.0
    if fa != (sb > 0.0):
        return fa
    if fa:
        if ra != rb:
            return ra > rb
        if sa != sb:
            return sa > sb
    else:
        if sa != sb:
            return sa > sb
        if ra != rb:
            return ra > rb
    return wa < wb


def _vals_key(reward: float, support: float) -> tuple[int, float, float]:
    """`bid_key` of a bid with a winner."""
    return (1, reward, support) if support > 0.0 else (0, support, reward)


def _beats(reward: float, support: float, me: str, t: Bid) -> bool:
    """bid_gt(Bid(j, me, reward, support, r), t), without building the bid."""
    tw = t[1]
    if tw is None:
        return True
    tr, ts = t[2], t[3]
    f = support > 0.0
    if f != (ts > 0.0):
        return f
    if f:
        if reward != tr:
            return reward > tr
        if support != ts:
            return support > ts
    else:
        if support != ts:
            return support > ts
        if reward != tr:
            return reward > tr
    return me < tw


def same_bid(a: Bid, b: Bid) -> bool:
    """Equal winner and value: the same bid, possibly confirmed in different rounds. Consensus (l. 87) and
    the "already sent" test compare bids this way; rounds only order information in Table 4.7-1."""
    return a[1] == b[1] and a[2] == b[2] and a[3] == b[3]
