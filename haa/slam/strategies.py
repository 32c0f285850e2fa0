"""Reading schedulers (Table 7.2-2 and Table 7.2-4) over one `SlamSystem`, on a simulated processing clock.

A replay is a time-ordered stream of `StreamEvent`s: predictions (applied at once, in order — event (b)),
reading arrivals, and weight requests (an avatar asks for its pose: event (d), then (e) if needed).
Processing is modelled, not measured: each reading kind has `Capacity.workers` processors of its own (the
thesis' system runs one sensor processing agent per type per host: Cooccupancy, Sonar, Landmark, FloorFinder)
and a reading of kind k occupies one for `Capacity.cost[k]` simulated seconds times a log-normal factor
(σ = `Capacity.jitter`, mean 1, a hash of the reading: real processing times vary, and without it the share
Discard processes moves in coarse steps because sensors fire periodically); its effect (density + map
update) is applied when it completes. Held readings are kept per kind too. So a run is deterministic for a
seed and does not depend on the machine's load; the costs are our implementation's measured per-reading
costs (haactl bench slam), each kind's scaled so that Discard processes ~90% (nominal) or ~50%
(constrained) of that kind's readings (haa.slam.replay.calibrate).

Strategies (all share the filter, map and sensor models; they differ only in what is processed when):

| name     | arrival                               | a processor frees                  | filter         |
|----------|---------------------------------------|------------------------------------|----------------|
| baseline | processed at once, no cost (ideal)    | —                                  | propagation on |
| discard  | processed if a processor is free,     | —                                  | propagation on |
|          | else dropped                          |                                    |                |
| jcslam   | pushed on a stack                     | newest held reading (LIFO)         | propagation on |
| fifo     | queued                                | oldest held reading                | propagation on |
| random   | pooled                                | a uniformly random held reading    | propagation on |
| nfp      | pushed on a stack                     | newest held reading (LIFO)         | propagation off|
| delay    | processed in order; if no processor   | —                                  | propagation on |
|          | is free the recording's clock stops   |                                    |                |
|          | until one is (the avatars wait)       |                                    |                |

A reading is *out of order* when a reading of the same queue (kind) generated later had already started. The delay of a
reading is its completion time minus its generation time. Held readings are never dropped by the
scheduler; the filter rejects those older than its history horizon (`rejected`).
"""

from __future__ import annotations

import heapq
import math
import zlib
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any

import numpy as np

from haa.slam.filter import Estimate, HistoryError
from haa.slam.motion import Prediction
from haa.slam.sensors import Reading
from haa.slam.system import SlamSystem

PREDICTION, READING, REQUEST = 0, 1, 2


@dataclass(frozen=True)
class StreamEvent:
    t: float
    kind: int  # PREDICTION, READING or REQUEST
    avatar: str
    payload: Any = None  # Prediction, Reading or None


@dataclass(frozen=True)
class Strategy:
    name: str
    policy: str  # instant | discard | lifo | fifo | random | delay
    forward_propagation: bool = True
    description: str = ""


STRATEGIES: dict[str, Strategy] = {
    s.name: s
    for s in (
        Strategy("baseline", "instant", True, "all readings processed in order as they arrive (no capacity limit)"),
        Strategy("discard", "discard", True, "in order as they arrive; dropped when no processor is free"),
        Strategy("jcslam", "lifo", True, "LIFO, unprocessed readings held, delayed weights, forward propagation"),
        Strategy("fifo", "fifo", True, "as JC-SLAM but first-in-first-out"),
        Strategy("random", "random", True, "as JC-SLAM but a random held reading next"),
        Strategy("nfp", "lifo", False, "JC-SLAM without forward propagation through resampling"),
        Strategy("delay", "delay", True, "in order; the avatars wait while no processor is free"),
    )
}


def strategy(name: str) -> Strategy:
    s = STRATEGIES.get(name)
    if s is None:
        raise ValueError(f"strategy: unknown {name!r} (known: {', '.join(STRATEGIES)})")
    return s


@dataclass(frozen=True)
class Capacity:
    """Processors and per-reading costs (simulated seconds one reading of a kind occupies a processor).

    `per_kind=True` (the default, as in the thesis' system, where each host runs at most one sensor
    processing agent of each type — Table 7.2-4): every reading kind has its own `workers` processors and
    its own held readings; `per_kind=False`: one shared pool of `workers` processors for everything.
    """

    workers: int
    cost: dict[str, float]
    per_kind: bool = True
    jitter: float = 0.5  # σ of the log-normal factor on each reading's cost (mean 1); 0: constant costs

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError(f"capacity.workers: must be >= 1, got {self.workers}")
        for k, c in self.cost.items():
            if not (math.isfinite(c) and c >= 0):
                raise ValueError(f"capacity.cost[{k}]: must be finite and >= 0, got {c}")
        if not (math.isfinite(self.jitter) and self.jitter >= 0):
            raise ValueError(f"capacity.jitter: must be finite and >= 0, got {self.jitter}")

    def scaled(self, factor: float) -> Capacity:
        return Capacity(self.workers, {k: c * factor for k, c in self.cost.items()}, self.per_kind, self.jitter)

    def of(self, kind: str) -> float:
        c = self.cost.get(kind)
        if c is None:
            raise ValueError(f"capacity.cost: no cost for reading kind {kind!r}")
        return c

    def duration(self, r: Reading) -> float:
        """Simulated seconds reading `r` occupies a processor: its kind's cost times a log-normal factor.

        The factor is a pure function of the reading (a hash of avatar, kind and time), so a reading costs the
        same under every strategy, and a run is reproducible in any process.
        """
        c = self.of(r.kind)
        if self.jitter == 0 or c == 0:
            return c
        return c * cost_factor(r, self.jitter)

    def pool_of(self, kind: str) -> str:
        """The processor pool a reading kind uses."""
        return kind if self.per_kind else "all"


@dataclass
class RunStats:
    strategy: str
    arrived: int = 0
    processed: int = 0
    dropped: int = 0  # Discard: no processor free at arrival
    rejected: int = 0  # the filter refused it (older than the history horizon)
    held_at_end: int = 0  # still queued or in progress when the recording ended
    out_of_order: int = 0
    delay_sum: float = 0.0
    requests: int = 0
    resamples: int = 0
    duration: float = 0.0  # recording length, s
    waited: float = 0.0  # Delay: total time the recording's clock was stopped
    order: list[tuple[float, float]] = field(default_factory=list)  # (completion time, reading time)

    def row(self) -> dict[str, float | int | str]:
        done = max(self.processed, 1)
        return {
            "strategy": self.strategy,
            "arrived": self.arrived,
            "processed": self.processed,
            "processed_share": self.processed / self.arrived if self.arrived else math.nan,
            "dropped": self.dropped,
            "rejected": self.rejected,
            "held_at_end": self.held_at_end,
            "ooo_share": self.out_of_order / done,
            "mean_delay_s": self.delay_sum / done,
            "requests": self.requests,
            "resamples": self.resamples,
            "resample_rate_per_min": 60 * self.resamples / self.duration if self.duration else math.nan,
            "processing_rate_per_s": self.processed / self.duration if self.duration else math.nan,
            "waited_s": self.waited,
        }


class _Pool:
    """Held readings with the strategy's pick order."""

    def __init__(self, policy: str, rng: np.random.Generator) -> None:
        self.policy = policy
        self.rng = rng
        self.items: deque[tuple[int, Reading]] | list[tuple[int, Reading]] = deque() if policy == "fifo" else []

    def __len__(self) -> int:
        return len(self.items)

    def push(self, item: tuple[int, Reading]) -> None:
        self.items.append(item)

    def pop(self) -> tuple[int, Reading]:
        if self.policy == "fifo":
            assert isinstance(self.items, deque)
            return self.items.popleft()
        if self.policy == "random":
            assert isinstance(self.items, list)
            i = int(self.rng.integers(len(self.items)))
            self.items[i], self.items[-1] = self.items[-1], self.items[i]
        return self.items.pop()


OnRequest = Callable[[str, float, Estimate, bool], None]
OnProcessed = Callable[[Reading, float], None]


def run(
    events: Iterable[StreamEvent],
    strat: Strategy,
    capacity: Capacity | None,
    system: SlamSystem,
    *,
    seed: int = 0,
    on_request: OnRequest | None = None,
    on_processed: OnProcessed | None = None,
    keep_order: bool = False,
) -> RunStats:
    """Replay `events` (time-ordered) through `system` under strategy `strat` and `capacity`.

    `on_request(avatar, t, estimate, resampled)` is called at each weight request (e.g. to measure the
    localization error); `on_processed(reading, t_done)` after each processed reading.
    """
    if strat.policy != "instant" and capacity is None:
        raise ValueError(f"capacity: strategy {strat.name!r} needs a processing capacity")
    if system.config.forward_propagation != strat.forward_propagation:
        raise ValueError(
            f"system.config.forward_propagation: must be {strat.forward_propagation} for strategy {strat.name!r}"
        )
    stats = RunStats(strat.name)
    rng = np.random.default_rng(seed)
    pools: dict[str, _Pool] = {}  # held readings per processor pool
    free: dict[str, int] = {}  # idle processors per pool
    busy: list[tuple[float, int, Reading]] = []  # heap of (completion time, seq, reading)
    seq = 0
    max_started: dict[str, float] = {}  # newest reading time started, per pool (out-of-order is per queue)
    shift = 0.0  # Delay: how long the recording's clock has been stopped so far
    t_first: float | None = None
    t_last = 0.0

    def pool_key(r: Reading) -> str:
        assert capacity is not None
        key = capacity.pool_of(r.kind)
        if key not in free:
            free[key] = capacity.workers
            pools[key] = _Pool(strat.policy, rng)
        return key

    def start(r: Reading, key: str, now: float) -> None:
        nonlocal seq
        assert capacity is not None
        if r.t < max_started.get(key, -math.inf):
            stats.out_of_order += 1
        max_started[key] = max(max_started.get(key, -math.inf), r.t)
        free[key] -= 1
        seq += 1
        heapq.heappush(busy, (now + capacity.duration(r), seq, r))

    def apply(r: Reading, now: float) -> None:
        try:
            system.process(r)
        except HistoryError:
            stats.rejected += 1
            return
        stats.processed += 1
        stats.delay_sum += now - r.t
        if keep_order:
            stats.order.append((now, r.t))
        if on_processed is not None:
            on_processed(r, now)

    def complete_until(now: float) -> None:
        while busy and busy[0][0] <= now:
            t_done, _, r = heapq.heappop(busy)
            key = pool_key(r)
            free[key] += 1
            apply(r, t_done - shift)
            pool = pools[key]
            while free[key] > 0 and len(pool):
                start(pool.pop()[1], key, t_done)

    for ev in events:
        if t_first is None:
            t_first = ev.t
        t_last = ev.t
        now = ev.t + shift
        complete_until(now)
        if ev.kind == PREDICTION:
            assert isinstance(ev.payload, Prediction)
            system.predict(ev.avatar, ev.payload)
        elif ev.kind == READING:
            r: Reading = ev.payload
            stats.arrived += 1
            seq += 1
            if strat.policy == "instant":
                apply(r, ev.t)
                continue
            key = pool_key(r)
            if strat.policy == "discard":
                if free[key] > 0:
                    start(r, key, now)
                else:
                    stats.dropped += 1
            elif strat.policy == "delay":
                while free[key] == 0:  # the avatars wait: the recording's clock stops
                    t_free = busy[0][0]
                    shift += t_free - now
                    now = t_free
                    complete_until(now)
                start(r, key, now)
            else:
                pool = pools[key]
                pool.push((seq, r))
                while free[key] > 0 and len(pool):
                    start(pool.pop()[1], key, now)
        elif ev.kind == REQUEST:
            est, resampled = system.request(ev.avatar)
            stats.requests += 1
            if on_request is not None:
                on_request(ev.avatar, ev.t, est, resampled)
        else:
            raise ValueError(f"event.kind: unknown {ev.kind}")
    complete_until(t_last + shift)  # what finishes exactly at the end still counts
    stats.held_at_end = sum(len(p) for p in pools.values()) + len(busy)
    stats.duration = t_last - (t_first or 0.0)
    stats.waited = shift
    stats.resamples = sum(pf.resamples for pf in system.filters.values())
    return stats


_NORMAL = NormalDist()


def cost_factor(r: Reading, sigma: float) -> float:
    """exp(σ z − σ²/2), z standard normal from a hash of the reading: mean 1, the same in every process."""
    h = zlib.crc32(f"{r.avatar}|{r.kind}|{r.t:.6f}".encode())
    z = _NORMAL.inv_cdf((h + 0.5) / 2**32)
    return math.exp(sigma * z - sigma * sigma / 2)


def discard_share(readings: list[Reading], capacity: Capacity, kind: str | None = None) -> float:
    """Share of readings (of `kind`, or all) Discard would process: scheduling only, no filter."""
    busy: dict[str, list[float]] = {}
    done = total = 0
    for r in readings:
        if kind is not None and r.kind != kind:
            continue
        total += 1
        heap = busy.setdefault(capacity.pool_of(r.kind), [])
        while heap and heap[0] <= r.t:
            heapq.heappop(heap)
        if len(heap) < capacity.workers:
            heapq.heappush(heap, r.t + capacity.duration(r))
            done += 1
    return done / total if total else math.nan
