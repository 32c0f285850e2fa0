"""Message delay distributions for the simulated network (seconds).

Channels are reliable and FIFO (thesis §4.3.1): a delay only decides when a message arrives, never whether,
and a later message on the same ordered host pair never overtakes an earlier one (`cluster` enforces it).
Heavy tails (Pareto, log-normal) are included because they are what real schedulers and GC pauses produce
and what breaks failure detectors tuned on a variance alone.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class DelayModel:
    """base + a random part of the given `kind`:

    * const: 0
    * uniform: U(0, scale)
    * exp: exponential with mean `scale`
    * lognormal: exp(N(ln scale, shape))
    * pareto: scale * (Pareto(shape) - 1), heavy-tailed with tail index `shape`
    """

    kind: str = "exp"
    base: float = 0.0005
    scale: float = 0.002
    shape: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("const", "uniform", "exp", "lognormal", "pareto"):
            raise ValueError(f"unknown delay kind {self.kind!r}")
        if self.base < 0 or self.scale < 0:
            raise ValueError("delays must be non-negative")
        if self.kind == "pareto" and self.shape <= 2.0:
            # finite variance is what the failure detector's analysis assumes (§4.4.1)
            raise ValueError("pareto shape must be > 2 (finite variance)")

    def sample(self, rng: random.Random) -> float:
        k = self.kind
        if k == "exp":
            return self.base + rng.expovariate(1.0 / self.scale) if self.scale > 0 else self.base
        if k == "uniform":
            return self.base + rng.random() * self.scale
        if k == "lognormal":
            return self.base + rng.lognormvariate(math.log(self.scale), self.shape)
        if k == "pareto":
            return self.base + self.scale * (rng.paretovariate(self.shape) - 1.0)
        return self.base

    def mean(self) -> float:
        k = self.kind
        if k in ("exp",):
            return self.base + self.scale
        if k == "uniform":
            return self.base + self.scale / 2
        if k == "lognormal":
            return self.base + self.scale * math.exp(self.shape**2 / 2)
        if k == "pareto":
            a = self.shape
            return self.base + self.scale * (a / (a - 1) - 1.0)
        return self.base

    def variance(self) -> float:
        k = self.kind
        if k == "exp":
            return self.scale**2
        if k == "uniform":
            return self.scale**2 / 12
        if k == "lognormal":
            s2 = self.shape**2
            return (math.exp(s2) - 1) * math.exp(2 * math.log(self.scale) + s2)
        if k == "pareto":
            a = self.shape
            return self.scale**2 * a / ((a - 1) ** 2 * (a - 2))
        return 0.0

    def describe(self) -> str:
        return f"{self.kind}(base={self.base * 1e3:.2f}ms, scale={self.scale * 1e3:.2f}ms, shape={self.shape:g})"
