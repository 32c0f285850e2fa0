"""The configuration procedure of Chen, Toueg & Aguilera used by Alg. 1 (haa.core.ufd.qos)."""

import math

import pytest

from haa.core.ufd.qos import CLUSTER_QOS, THESIS_QOS, QosTargets, configure, heartbeats_per_minute, log_f


def test_thesis_qos_costs_about_twelve_heartbeats_per_minute():
    # §4.4.2: T_D^U = 10 s, T_MR^L = 1 week, T_M^U = 30 s "cost roughly 12 messages/minute" on a LAN
    for p_loss in (1e-4, 1e-3):
        for std in (0.001, 0.01):
            rate = heartbeats_per_minute(configure(THESIS_QOS, p_loss, std**2))
            assert 11.5 <= rate <= 13.0, (p_loss, std, rate)


@pytest.mark.parametrize("p_loss", [0.0, 1e-4, 1e-2, 0.1])
@pytest.mark.parametrize("std", [0.0005, 0.01, 0.2])
def test_result_meets_every_target(p_loss, std):
    qos = CLUSTER_QOS
    p = configure(qos, p_loss, std**2)
    assert p.achievable
    assert math.isclose(p.eta + p.alpha, qos.td_upper)  # Step 3: detection bound T_D^U
    assert log_f(p.eta, qos.td_upper, p_loss, std**2) >= math.log(qos.tmr_lower) - 1e-9  # Step 2
    gamma = (1 - p_loss) * qos.td_upper**2 / (std**2 + qos.td_upper**2)
    assert p.eta <= min(gamma * qos.tm_upper, qos.td_upper) + 1e-12  # Step 1


def test_eta_is_the_largest_feasible():
    qos, p_loss, var = THESIS_QOS, 1e-3, 0.01**2
    p = configure(qos, p_loss, var)
    target = math.log(qos.tmr_lower)
    # slightly larger periods miss T_MR^L
    for k in (1.001, 1.01, 1.1):
        eta = min(p.eta * k, qos.td_upper)
        if eta > p.eta:
            assert log_f(eta, qos.td_upper, p_loss, var) < target


def test_worse_network_needs_more_heartbeats():
    rates = [heartbeats_per_minute(configure(CLUSTER_QOS, 1e-3, s**2)) for s in (0.001, 0.01, 0.1, 0.3)]
    assert rates == sorted(rates)
    losses = [heartbeats_per_minute(configure(CLUSTER_QOS, pl, 1e-4)) for pl in (0.0, 1e-3, 1e-2, 1e-1)]
    assert losses == sorted(losses)


def test_unachievable_qos_is_reported():
    qos = QosTargets(td_upper=0.01, tmr_lower=1e9, tm_upper=0.001)
    p = configure(qos, 0.2, 0.5**2, eta_min=0.005)
    assert not p.achievable and p.eta == 0.005


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError):
        QosTargets(td_upper=0, tmr_lower=1, tm_upper=1)
    with pytest.raises(ValueError):
        configure(CLUSTER_QOS, 1.0, 0.0)
    with pytest.raises(ValueError):
        configure(CLUSTER_QOS, 0.0, -1.0)
