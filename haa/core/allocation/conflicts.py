"""Conflict resolution of agent allocation HAA-AA: Table 4.7-1 (thesis §4.7).

`resolve(p, q, sb, rb)` is the action receiver p takes on sender q's bid `sb` for an agent when p holds `rb`:
one of leave, update, reset, trim & update or update time, and whether to broadcast (`Rule`). The `Allocator`
(`haa.core.allocation.allocation`) applies it to every bid of a `BidUpdate` (Alg. 4 l. 70).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from typing import NamedTuple

from haa.core.allocation.bids import Bid, bid_gt

LEAVE = "leave"
UPDATE = "update"
RESET = "reset"
TRIM_UPDATE = "trim & update"
UPDATE_TIME = "update time"


#: the resets of Table 4.7-1 driven by round comparisons with a third host's bid
_GUARDED_RESETS = frozenset({10, 11, 28, 29})


class Rule(NamedTuple):
    row: int
    action: str
    broadcast: bool


def resolve(p: str, q: str, sb: Bid, rb: Bid) -> Rule:
    """Table 4.7-1: receiver p's action on sender q's bid `sb` for agent j, p holding `rb` (bidTable_p[p][j]).

    y comparisons use `bid_gt` (values, then the lower winner name), so rows 2 and 18 (equal y, lower z) are
    part of rows 1 and 17. r is the round of each bid. Default: leave & broadcast (the thesis' header)."""
    zq, zp = sb.winner, rb.winner
    rq, rp = sb.round, rb.round
    if zq == q:  # sender thinks it wins (rows 1-12)
        if zp == p:
            if bid_gt(sb, rb):
                return Rule(1, TRIM_UPDATE, True)
            return Rule(3, UPDATE_TIME, True)
        if zp == q:
            if rq > rp:
                return Rule(4, UPDATE, True)
            return Rule(5 if rq == rp else 6, LEAVE, False)
        if zp is None:
            return Rule(12, UPDATE, True)
        return _third_party(sb, rb, 7)
    if zq == p:  # sender thinks the receiver wins (rows 13-16)
        if zp == p:
            if rq == rp:
                return Rule(13, LEAVE, False)
            return Rule(13, LEAVE, True)
        if zp == q:
            return Rule(14, RESET, True)
        if zp is None:
            return Rule(16, LEAVE, True)
        return Rule(15, LEAVE, True)
    if zq is None:  # sender has no winner (rows 31-34)
        if zp == p:
            return Rule(31, LEAVE, True)
        if zp == q:
            return Rule(32, UPDATE, True)
        if zp is None:
            return Rule(34, LEAVE, False)
        if rq > rp:
            return Rule(33, UPDATE, True)
        return Rule(33, LEAVE, True)
    # sender thinks a third host m wins (rows 17-30)
    if zp == p:
        if bid_gt(sb, rb):
            return Rule(17, TRIM_UPDATE, True)
        return Rule(19, UPDATE_TIME, True)
    if zp == q:
        if rq >= rp:
            return Rule(20, UPDATE, True)
        return Rule(21, RESET, True)
    if zp == zq:
        if rq > rp:
            return Rule(22, UPDATE, True)
        return Rule(23 if rq == rp else 24, LEAVE, False)
    if zp is None:
        return Rule(30, UPDATE, True)
    return _third_party(sb, rb, 25)


def _third_party(sb: Bid, rb: Bid, base: int) -> Rule:
    """Rows 7-11 (sender q thinks q, receiver thinks m) and 25-29 (sender thinks m, receiver thinks n)."""
    gt, lt = bid_gt(sb, rb), bid_gt(rb, sb)
    rq, rp = sb.round, rb.round
    if gt and rq >= rp:
        return Rule(base, UPDATE, True)
    if lt and rq <= rp:
        return Rule(base + 1, LEAVE, True)
    if not gt and not lt:
        return Rule(base + 2, LEAVE, True)
    return Rule(base + 3 if lt else base + 4, RESET, True)
