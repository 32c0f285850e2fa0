"""The failure detector's cost and quality of service (thesis §4.4, Alg. 1; `haactl bench ufd`).

Two parts:

* `heartbeat_rates()`: the heartbeat rate that the configuration procedure of §4.4 (haa.core.ufd.qos.configure:
  eq. 4.4-2 solved for η and α) chooses for the thesis' QoS (T_D^U = 10 s, T_MR^L = 1 week, T_M^U = 30 s) and
  for the cluster default (1 s, 1 day, 1 s), over message loss probabilities p_L and delay deviations σ(D) —
  the cost of a monitored pair per minute.
* `measured_qos(quick, seed)`: the QoS measured in simulation (haa.lab.dsim.ufdqos: the real `HeartbeatSender`
  and `HeartbeatObserver` on one pair, adaptive re-configuration on) on the networks of `CASES` — exponential,
  lognormal and Pareto delays with loss, for weeks of virtual time on the thesis' targets — each compared
  with the targets it was configured for.

`haactl bench ufd` prints the rates first (the measurement takes minutes) and writes bench-results/ufd.json:
"rates" (these rows), "measured" (`QosMeasurement.row()` of each), "seconds", "quick".
"""

from __future__ import annotations

from typing import Any

from haa.core.ufd.qos import CLUSTER_QOS, THESIS_QOS, QosTargets, configure, heartbeats_per_minute
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.ufdqos import QosMeasurement, measure

#: targets whose mistakes are frequent enough to count in hours of virtual time
MEASURABLE_QOS = QosTargets(td_upper=0.5, tmr_lower=60.0, tm_upper=0.5)

#: (label, targets, delays, p_L, horizon in s of virtual time) of each measured network
CASES: list[tuple[str, QosTargets, DelayModel, float, float]] = [
    ("measurable: exp 20 ms, 1% loss", MEASURABLE_QOS, DelayModel("exp", 0.001, 0.02), 0.01, 20000),
    ("measurable: lognormal σ=0.8", MEASURABLE_QOS, DelayModel("lognormal", 0.001, 0.01, 0.8), 0.01, 20000),
    ("measurable: Pareto α=2.5 (heavy tail)", MEASURABLE_QOS, DelayModel("pareto", 0.001, 0.02, 2.5), 0.01, 20000),
    ("measurable: exp 50 ms, 5% loss", MEASURABLE_QOS, DelayModel("exp", 0.001, 0.05), 0.05, 20000),
    ("cluster: LAN exp 1 ms, 0.1% loss", CLUSTER_QOS, DelayModel("exp", 0.0002, 0.001), 0.001, 10 * 86400),
    ("thesis: LAN exp 1 ms, 0.1% loss", THESIS_QOS, DelayModel("exp", 0.0002, 0.001), 0.001, 8 * 7 * 86400),
    ("thesis: WLAN lognormal 20 ms, 1% loss", THESIS_QOS, DelayModel("lognormal", 0.002, 0.015, 0.7), 0.01,
     8 * 7 * 86400),
]


def heartbeat_rates() -> list[dict[str, Any]]:
    """Heartbeat rate of the configuration procedure for the thesis' QoS and our cluster default."""
    rows = []
    for qname, qos in (("thesis (10 s, 1 week, 30 s)", THESIS_QOS), ("cluster (1 s, 1 day, 1 s)", CLUSTER_QOS)):
        for p_loss in (0.0, 1e-4, 1e-3, 1e-2):
            for std in (0.001, 0.01, 0.05):
                # the observer's add-one loss estimate over its window of 1000 heartbeats never reads 0
                p_est = max(p_loss, 1 / 1002)
                params = configure(qos, p_est, std**2)
                rows.append(
                    {
                        "qos": qname,
                        "p_loss": p_loss,
                        "delay_std_ms": std * 1e3,
                        "eta_s": params.eta,
                        "alpha_s": params.alpha,
                        "heartbeats_per_minute": heartbeats_per_minute(params),
                    }
                )
    return rows


def measured_qos(quick: bool = False, seed: int = 1) -> list[QosMeasurement]:
    """Every network of `CASES` for its horizon (a tenth of it with `quick`: a smoke run, not a measurement),
    100 crash trials each."""
    scale = 0.1 if quick else 1.0
    return [measure(label, qos, delay, p_loss, horizon * scale, seed=seed, crash_trials=100)
            for label, qos, delay, p_loss, horizon in CASES]
