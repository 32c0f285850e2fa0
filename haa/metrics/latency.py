"""Cumulative latency histograms folded from a daemon's bounded buffers of latency samples (haa.hostd.metrics).

`Histogram` keeps bucket counts and a sum that only grow, as Prometheus wants them; `SampleTail` tells which
items of a bounded deque of samples are new since the last look, so that each sample is counted once.
"""

from __future__ import annotations

import itertools
from bisect import bisect_left
from collections.abc import Iterable
from typing import Any

from prometheus_client.core import HistogramMetricFamily


class Histogram:
    """A cumulative histogram (bucket counts, sum) that grows by folding in new samples."""

    def __init__(self, bounds: tuple[float, ...]) -> None:
        self.bounds = bounds
        self.counts = [0] * (len(bounds) + 1)
        self.sum = 0.0

    def add(self, values: Iterable[float]) -> None:
        for v in values:
            self.counts[bisect_left(self.bounds, v)] += 1
            self.sum += v

    def family(self, name: str, doc: str) -> HistogramMetricFamily:
        cum = list(itertools.accumulate(self.counts))
        buckets = [(repr(b), c) for b, c in zip(self.bounds, cum, strict=False)] + [("+Inf", cum[-1])]
        return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=self.sum)


class SampleTail:
    """Which items of a bounded deque of latency samples are new since the last look.

    `by_count`: the runtime appends exactly one sample per increment of a counter (decide->deliver: one per
    `oac_delivered`), so the counter's growth is the number of new samples. Otherwise (propose->decide: one per
    decided transaction this host proposed, not counted apart) the newest item seen is remembered *as an
    object* and the deque is read from the right until it: each sample is a float computed anew
    (`now - t0`), so identity tells it from an equal value. Either way the new samples are exact unless more
    than the deque holds (`MAX_SAMPLES`, 100,000) arrived between two scrapes."""

    def __init__(self) -> None:
        self.last_count = 0
        self.last_item: object | None = None

    def new_by_count(self, samples: Any, count: int) -> list[float]:
        n = min(len(samples), max(0, count - self.last_count))
        self.last_count = count
        return list(itertools.islice(reversed(samples), n)) if n else []

    def new_by_identity(self, samples: Any) -> list[float]:
        out: list[float] = []
        last = self.last_item
        for v in reversed(samples):
            if v is last:
                break
            out.append(v)
        if samples:
            self.last_item = samples[-1]
        return out
