"""The event heap every deterministic simulator runs on (issue 17, item 4): one virtual clock, one queue.

A discrete-event simulator is a loop: take the earliest pending event, set the clock to its time, carry it
out (which may schedule more events), repeat. `EventHeap` is that queue, shared by the simulators of
`haa.lab.dsim` — the host cluster (`haa.lab.dsim.cluster.SimCluster`, and through it the group, agent and join
simulations), the allocation simulator (`haa.lab.dsim.allocsim.AllocSim`) and the failure detector's QoS
runs (`haa.lab.dsim.ufdqos`) — and by the agents that run on virtual time inside the cluster
(`haa.lab.dsim.vagent`).

Determinism rests on one rule: **events are ordered by (time, sequence number)**, the sequence number
counting pushes from 1. Two events due at the same instant run in the order they were scheduled, never in an
order that depends on what they carry, on hashing or on memory addresses; so the same seed gives the same
run, event for event, and a run's trace hash can be compared across versions. An entry is the tuple
`(time, seq, item)`: `item` is never compared (the sequence numbers are unique).

`new_id()` draws a number from the same counter without scheduling anything. The cluster uses it for timer
generations (an event carries the generation it was armed with; a re-armed or cancelled timer's old event
finds a different generation and is skipped), which is also why its events keep the numbers they had
when each simulator kept its own heap: the counter advances exactly as it did then, and the traces of every
verifier are byte-identical to those of the three separate heaps this module replaced.

The heap does not read a clock and holds no "now": each simulator keeps its own current time (a host's
local time differs from the virtual time, a paused host processes events late), sets it from the entry it
pops, and may defer an entry by pushing it again.
"""

from __future__ import annotations

import heapq
import math
from typing import Generic, TypeVar

T = TypeVar("T")


class EventHeap(Generic[T]):
    """A min-heap of `(time, seq, item)` entries; see the module docstring."""

    __slots__ = ("entries", "seq")

    def __init__(self) -> None:
        #: the heap itself (heapq order); read it, do not reorder it
        self.entries: list[tuple[float, int, T]] = []
        #: the last sequence number drawn (pushes and `new_id`)
        self.seq = 0

    def push(self, t: float, item: T) -> int:
        """Schedule `item` at virtual time `t`; returns its sequence number."""
        self.seq += 1
        heapq.heappush(self.entries, (t, self.seq, item))
        return self.seq

    def new_id(self) -> int:
        """A fresh number from the sequence counter, nothing scheduled (e.g. a timer's generation)."""
        self.seq += 1
        return self.seq

    def pop(self) -> tuple[float, int, T]:
        """The earliest entry (the first pushed among those due at the same time); IndexError if empty."""
        return heapq.heappop(self.entries)

    def peek(self) -> tuple[float, int, T]:
        """The entry `pop()` would return, left in place; IndexError if empty."""
        return self.entries[0]

    def next_time(self) -> float:
        """The time of the earliest entry, `math.inf` if there is none."""
        return self.entries[0][0] if self.entries else math.inf

    def __len__(self) -> int:
        return len(self.entries)

    def __bool__(self) -> bool:
        return bool(self.entries)
