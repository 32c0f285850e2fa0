"""Alg. 1 meets its QoS targets (eq. 4.4-2) on networks that fit its model, measured in simulation."""

import pytest

from haa.core.ufd.qos import THESIS_QOS, QosTargets
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.ufdqos import measure

QOS = QosTargets(td_upper=0.5, tmr_lower=60.0, tm_upper=0.5)


@pytest.mark.parametrize(
    ("delay", "p_loss"),
    [
        (DelayModel("exp", 0.001, 0.02), 0.01),
        (DelayModel("pareto", 0.001, 0.02, 2.5), 0.01),
        (DelayModel("lognormal", 0.001, 0.01, 0.8), 0.02),
    ],
)
def test_measured_mistake_recurrence_duration_and_detection_meet_targets(delay, p_loss):
    m = measure("t", QOS, delay, p_loss, horizon=8000.0, seed=7, crash_trials=40)
    assert m.mistakes >= 3, "too few mistakes for the measurement to mean anything"
    assert m.mean_tmr >= QOS.tmr_lower
    assert m.mean_tm <= QOS.tm_upper
    assert m.detection_violations == 0
    assert m.max_detection <= QOS.td_upper + delay.mean() + 0.02


def test_thesis_qos_costs_twelve_heartbeats_a_minute_on_a_lan():
    m = measure("t", THESIS_QOS, DelayModel("exp", 0.0002, 0.001), 0.001, horizon=3 * 86400, crash_trials=5)
    assert 11.5 <= m.heartbeats_per_minute <= 12.5
    assert m.mistakes == 0 and m.detection_violations == 0


def test_a_detector_with_a_too_small_margin_misses_the_target(monkeypatch):
    """The measurement can fail: a detector that believes the network has no jitter and no loss picks
    eta = T_D^U and alpha = 0, and then suspects at every late heartbeat."""
    from haa.core.ufd.ufd import HeartbeatObserver

    monkeypatch.setattr(HeartbeatObserver, "delay_variance", lambda self: 0.0)
    monkeypatch.setattr(HeartbeatObserver, "loss_estimate", lambda self: 0.0)
    m = measure("t", QOS, DelayModel("exp", 0.001, 0.02), 0.01, horizon=2000.0, crash_trials=0)
    assert m.eta == pytest.approx(QOS.td_upper)
    assert m.mean_tmr < QOS.tmr_lower
