"""Sender streams: exactly-once, per-sender-ordered delivery of agent messages whatever path they take.

Alg. 5-6 route a message addressed to agent a (m.a.a.) to a, to DDB queue1, to queue2, to the new host's
local queue, and to a again; Lemma AT-2 shows that one *host's* messages keep their order along that path.
An agent's messages do not all leave from one host, though: when the *sender* moves too, its messages before
and after the move leave from different hosts over different channels and can overtake each other. The
hosts therefore number every message: the sender's host stamps it with (sender id, sender life, seq), seq =
1, 2, ... per receiver, and the counters travel with the sender when it is frozen (`Outbox`). The receiver's
host passes messages to the agent through an `Inbox`: in order per stream, each exactly once, holding back a
message that overtook an earlier one until the earlier one arrives. The inbox positions travel with a frozen
receiver too. (docs/agents-host.md, "streams")

A sender *life* ends when the sender crashes (recovery starts a new life, `AgentRecord.life`): messages of
the dead life that never left its host are gone, so the receiver's host flushes that stream (delivers what it
holds back, skipping the gap) once the table shows the sender in a newer life or removed. A *recovered*
receiver starts with an empty inbox in `adopt` mode: the first message of each stream sets the position (its
older messages were processed by a life that is lost, or never will be). The mode travels with the positions
when the receiver is frozen — as the entry (src "", life 0, next 0), `ADOPT` — and holds for the streams the
inbox has not seen yet: a recovered agent moved before it heard from a sender whose stream is far along
(every stream it had before its crash) would otherwise wait at the new host for that stream's message 1, and
hold back everything of it for good (a SupervisorForage recovered, moved, and deaf to its avatar's "reached"
for the rest of a forage mission).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from haa.pb import agenttx_pb2 as apb

#: messages one inbox holds back (waiting for a gap to fill) before it gives up on the gap
MAX_HELD = 10_000
#: the position entry that says "adopt mode" (no agent has the empty id)
ADOPT = apb.StreamPos(src="", src_life=0, next=0)


@dataclass(slots=True)
class _Stream:
    next: int
    held: dict[int, apb.RoutedMsg] = field(default_factory=dict)


@dataclass(slots=True)
class InboxStats:
    delivered: int = 0
    duplicates: int = 0
    held_back: int = 0  # messages that arrived before an earlier one of their stream
    skipped: int = 0  # gap positions given up (dead sender life, or MAX_HELD)


class Inbox:
    """The receiver side of the sender streams of one agent."""

    def __init__(self, positions: Iterable[apb.StreamPos] = (), adopt: bool = False) -> None:
        pos = list(positions)
        self.streams: dict[tuple[str, int], _Stream] = {(p.src, p.src_life): _Stream(p.next) for p in pos if p.src}
        self.adopt = adopt or any(not p.src for p in pos)
        self.stats = InboxStats()

    def offer(self, m: apb.RoutedMsg) -> list[apb.RoutedMsg]:
        """Accept one arriving message; return the messages now deliverable, in order."""
        if m.seq == 0:  # unsequenced (operator, host-generated error replies)
            self.stats.delivered += 1
            return [m]
        key = (m.src, m.src_life)
        s = self.streams.get(key)
        if s is None:
            s = self.streams[key] = _Stream(m.seq if self.adopt else 1)
        if m.seq < s.next or m.seq in s.held:
            self.stats.duplicates += 1
            return []
        if m.seq > s.next:
            s.held[m.seq] = m
            self.stats.held_back += 1
            if sum(len(x.held) for x in self.streams.values()) > MAX_HELD:
                return self._skip_to_held(s)
            return []
        out = [m]
        s.next += 1
        while s.next in s.held:
            out.append(s.held.pop(s.next))
            s.next += 1
        self.stats.delivered += len(out)
        return out

    def _skip_to_held(self, s: _Stream) -> list[apb.RoutedMsg]:
        first = min(s.held)
        self.stats.skipped += first - s.next
        s.next = first
        out = []
        while s.next in s.held:
            out.append(s.held.pop(s.next))
            s.next += 1
        self.stats.delivered += len(out)
        return out

    def flush(self, dead: Iterable[tuple[str, int]]) -> list[apb.RoutedMsg]:
        """Sender lives that ended: deliver what their streams hold back, skipping the gaps."""
        out: list[apb.RoutedMsg] = []
        for key in dead:
            s = self.streams.get(key)
            while s is not None and s.held:
                out += self._skip_to_held(s)
        return out

    def waiting(self) -> list[tuple[str, int]]:
        """Streams holding messages back (a gap before them)."""
        return [k for k, s in self.streams.items() if s.held]

    def held(self) -> list[apb.RoutedMsg]:
        return [m for s in self.streams.values() for _, m in sorted(s.held.items())]

    def positions(self) -> list[apb.StreamPos]:
        """Where each stream stands, for a frozen receiver's next host; with ADOPT first in adopt mode."""
        out = [apb.StreamPos(src=k[0], src_life=k[1], next=s.next) for k, s in sorted(self.streams.items())]
        return [apb.StreamPos(src="", src_life=0, next=0), *out] if self.adopt else out


class Outbox:
    """The sender side: the next sequence number per receiver, for one agent life."""

    def __init__(self, positions: Iterable[apb.SendPos] = ()) -> None:
        self.next: dict[str, int] = {p.dst: p.next for p in positions}

    def stamp(self, dst: str) -> int:
        n = self.next.get(dst, 1)
        self.next[dst] = n + 1
        return n

    def positions(self) -> list[apb.SendPos]:
        return [apb.SendPos(dst=d, next=n) for d, n in sorted(self.next.items())]
