"""Failure-detector configuration from QoS targets (thesis §4.4.2, change 5; Chen, Toueg & Aguilera [66]).

Given the QoS requirements — an upper bound T_D^U on detection time, a lower bound T_MR^L on the mean
mistake recurrence time and an upper bound T_M^U on the mean mistake duration — and the message behaviour
(loss probability p_L and delay variance V(D)), the configuration procedure of [66] for NFD-U (clocks not
synchronized, E(D) unknown) chooses the heartbeat period eta and the safety margin alpha:

  Step 1. gamma' = (1 - p_L) (T_D^U)^2 / (V(D) + (T_D^U)^2);  eta_max = min(gamma' T_M^U, T_D^U).
          If eta_max = 0 the QoS cannot be achieved.
  Step 2. f(eta) = eta * prod_{j=1}^{ceil(T_D^U/eta) - 1} (V(D) + (T_D^U - j eta)^2) / (V(D) + p_L (T_D^U - j eta)^2)
          Find the largest eta <= eta_max with f(eta) >= T_MR^L.
  Step 3. alpha = T_D^U - eta.

so that T_D <= T_D^U + E(D), E(T_MR) >= T_MR^L and E(T_M) <= T_M^U (thesis eq. 4.4-2). f is a one-sided
Chebyshev bound, so the guarantee holds for every delay distribution with the given variance.

This module is pure arithmetic (it runs inside the sans-I/O observer every N heartbeats).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class QosTargets:
    """The three QoS requirements of [66], in seconds."""

    td_upper: float  # T_D^U
    tmr_lower: float  # T_MR^L
    tm_upper: float  # T_M^U

    def __post_init__(self) -> None:
        if not (self.td_upper > 0 and self.tmr_lower > 0 and self.tm_upper > 0):
            raise ValueError(f"QoS targets must be positive: {self}")


#: The thesis' QoS (§4.4.2): T_D^U = 10 s, T_MR^L = 1 week, T_M^U = 30 s.
THESIS_QOS = QosTargets(td_upper=10.0, tmr_lower=7 * 24 * 3600.0, tm_upper=30.0)

#: HAA's cluster default: crashes detected within 1 s + E(D), a false suspicion at most once a day on
#: average, and mistakes corrected within 1 s on average.
CLUSTER_QOS = QosTargets(td_upper=1.0, tmr_lower=24 * 3600.0, tm_upper=1.0)


@dataclass(frozen=True, slots=True)
class FdParams:
    eta: float  # heartbeat period
    alpha: float  # safety margin
    achievable: bool  # False when even the smallest allowed eta misses T_MR^L (best effort is returned)


def log_f(eta: float, td: float, p_loss: float, var: float) -> float:
    """log f(eta) of Step 2 (log space: the product overflows floats for small eta)."""
    k = math.ceil(td / eta - 1e-12) - 1
    total = math.log(eta)
    for j in range(1, k + 1):
        x2 = (td - j * eta) ** 2
        num = var + x2
        den = var + p_loss * x2
        if den <= 0.0:
            return math.inf
        total += math.log(num) - math.log(den)
    return total


def configure(
    qos: QosTargets, p_loss: float, var_delay: float, eta_min: float = 1e-3, grid: int = 400
) -> FdParams:
    """Run the configuration procedure; return (eta, alpha).

    The largest eta is found by scanning a geometric grid from eta_max down to eta_min and refining the
    first feasible point by bisection against its infeasible neighbour above. When no eta >= eta_min meets
    T_MR^L the QoS is not achievable for this network: eta_min is returned with `achievable=False`.
    """
    if not 0.0 <= p_loss < 1.0:
        raise ValueError(f"p_loss must be in [0, 1): {p_loss}")
    if var_delay < 0.0:
        raise ValueError(f"var_delay must be >= 0: {var_delay}")
    td = qos.td_upper
    gamma = (1.0 - p_loss) * td * td / (var_delay + td * td)
    eta_max = min(gamma * qos.tm_upper, td)
    if eta_max < eta_min:  # even T_M^U alone needs heartbeats faster than we allow
        return FdParams(eta=eta_min, alpha=max(td - eta_min, 0.0), achievable=False)
    target = math.log(qos.tmr_lower)

    def ok(eta: float) -> bool:
        return log_f(eta, td, p_loss, var_delay) >= target

    if ok(eta_max):
        return FdParams(eta=eta_max, alpha=td - eta_max, achievable=True)
    ratio = (eta_min / eta_max) ** (1.0 / grid) if eta_max > eta_min else 1.0
    hi = eta_max
    eta = eta_max
    for _ in range(grid):
        eta *= ratio
        if ok(eta):
            lo = eta  # feasible; hi infeasible: bisect
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                if ok(mid):
                    lo = mid
                else:
                    hi = mid
                if hi - lo < 1e-9 * hi:
                    break
            return FdParams(eta=lo, alpha=td - lo, achievable=True)
        hi = eta
    return FdParams(eta=eta_min, alpha=td - eta_min, achievable=False)


def heartbeats_per_minute(params: FdParams) -> float:
    return 60.0 / params.eta
