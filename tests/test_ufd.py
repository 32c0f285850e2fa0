"""Alg. 1 (HAA-UFD): the observed sender and the observer, on hand-fed inputs."""

import math

import pytest

from haa.core.messages import Heartbeat
from haa.core.ufd.qos import QosTargets, configure
from haa.core.ufd.ufd import (
    ArmFreshness,
    AskPeriod,
    Beat,
    Deadline,
    EmitHeartbeat,
    HeartbeatIn,
    HeartbeatObserver,
    HeartbeatSender,
    NewPeriod,
    PeriodRefused,
    Suspect,
    Trust,
    UfdConfig,
)

QOS = QosTargets(td_upper=1.0, tmr_lower=3600.0, tm_upper=1.0)
CFG = UfdConfig(qos=QOS, initial_period=0.05, reevaluate_every=10, window=50, min_delay_std=0.001)


def beat(s: HeartbeatSender, now: float) -> Heartbeat:
    """The sender's `Beat` input: the heartbeat it emits (and it emits exactly one)."""
    (e,) = s.step(now, Beat())
    assert isinstance(e, EmitHeartbeat) and e.next_at == s.next_send
    return e.hb


def heard(obs: HeartbeatObserver, now: float, hb: Heartbeat) -> tuple[bool, float | None]:
    """The observer's `HeartbeatIn` input: (output changed to TRUSTED, the setPeriod asked for or None); it always
    re-arms its freshness timer first."""
    effects = obs.step(now, HeartbeatIn(hb))
    assert effects[0] == ArmFreshness(obs.freshness)
    periods = [e.period for e in effects if isinstance(e, AskPeriod)]
    return Trust() in effects, periods[0] if periods else None


def deadline(obs: HeartbeatObserver, now: float) -> bool:
    """The observer's `Deadline` input: whether the output changed to SUSPECTED."""
    return Suspect() in obs.step(now, Deadline())


def test_sender_adopts_a_new_period_after_its_next_heartbeat():
    s = HeartbeatSender(0.05, now=100.0)
    hb0 = beat(s, 100.0)
    assert (hb0.seq, hb0.period, hb0.sent_at) == (0, 0.05, 100.0)
    assert s.next_send == pytest.approx(100.05)
    assert s.step(100.01, NewPeriod(0.5)) == []  # l. 11-12
    hb1 = beat(s, 100.05)  # l. 7: the heartbeat sent now carries the new period...
    assert hb1.period == 0.5 and hb1.sent_at == pytest.approx(100.05)
    assert s.next_send == pytest.approx(100.55)  # ...and the next one follows it


def test_sender_skips_missed_slots_after_a_pause_instead_of_bursting():
    s = HeartbeatSender(0.1, now=0.0)
    beat(s, 0.0)
    beat(s, 5.03)  # woke up late
    assert 5.03 < s.next_send <= 5.13


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_sender_rejects_invalid_periods(bad):
    s = HeartbeatSender(0.1, 0.0)
    (refused,) = s.step(0.0, NewPeriod(bad))
    assert isinstance(refused, PeriodRefused) and s.next_period == 0.1


def test_observer_uses_eq_4_4_1_with_unsynchronized_clocks():
    """The sender's clock is 1000 s ahead; the delay is 10 ms. EA_{l+1} = p_tau_l + period + mean(O)."""
    obs = HeartbeatObserver(CFG, now=0.0)
    assert not obs.trusted  # l. 15-18: nothing received yet
    offset, delay, period = 1000.0, 0.010, 0.05
    for seq in range(5):
        sent = offset + 2.0 + seq * period  # sender clock
        now = sent - offset + delay  # observer clock
        became, _ = heard(obs, now, Heartbeat(seq, period, sent))
        assert became == (seq == 0)
    mean_o = -offset + delay
    expected_freshness = sent + period + mean_o + (QOS.td_upper - period)
    assert obs.freshness == pytest.approx(expected_freshness)
    assert obs.mean_offset() == pytest.approx(mean_o)
    # l. 17-18: suspicion exactly at the freshness point, T_D^U + delay after the last send
    assert not deadline(obs, obs.freshness - 1e-6)
    assert deadline(obs, obs.freshness)
    assert not obs.trusted
    last_send_on_observer_clock = sent - offset
    assert obs.freshness - last_send_on_observer_clock == pytest.approx(QOS.td_upper + delay)


def test_observer_ignores_stale_heartbeats_and_retrusts_on_a_fresh_one():
    obs = HeartbeatObserver(CFG, now=0.0)
    heard(obs, 0.01, Heartbeat(3, 0.05, 0.0))
    assert deadline(obs, obs.freshness)
    assert heard(obs, 5.0, Heartbeat(2, 0.05, 0.0)) == (False, None)  # l. 20: j <= l
    became, _ = heard(obs, 5.0, Heartbeat(4, 0.05, 4.99))
    assert became and obs.trusted


def test_observer_requests_worst_case_period_then_measured_one():
    obs = HeartbeatObserver(CFG, now=0.0)
    _, first = heard(obs, 0.001, Heartbeat(0, 0.05, 0.0))
    worst = configure(QOS, CFG.worst_loss, CFG.worst_delay_std**2, eta_min=CFG.eta_min).eta
    assert first == pytest.approx(worst)  # change 3: worst-case initialization
    requested = []
    t = 0.0
    for seq in range(1, 40):  # a quiet network: 1 ms delay, no loss, no jitter
        t += 0.05
        _, p = heard(obs, t + 0.001, Heartbeat(seq, 0.05, t))
        if p is not None:
            requested.append((seq, p))
    assert requested, "no setPeriod after N heartbeats (l. 25-27)"
    seq, eta = requested[0]
    assert seq + 1 == CFG.reevaluate_every  # after exactly N heartbeats (seq counts from 0)
    # add-one loss estimate over N heartbeats without a loss: 1 / (N + 2)
    p_loss = 1 / (CFG.reevaluate_every + 2)
    measured = configure(QOS, p_loss, CFG.min_delay_std**2, eta_min=CFG.eta_min).eta
    assert eta == pytest.approx(measured) and eta > worst  # a calm network allows slower heartbeats


def test_observer_estimates_loss_from_sequence_gaps():
    obs = HeartbeatObserver(CFG, now=0.0)
    for seq in range(0, 100, 2):  # every other heartbeat lost
        heard(obs, seq * 0.05 + 0.001, Heartbeat(seq, 0.05, seq * 0.05))
        if seq // 2 + 1 >= CFG.reevaluate_every:
            break
    assert obs.loss_estimate() == pytest.approx(0.5, abs=0.06)


def test_invalid_heartbeats_are_ignored():
    obs = HeartbeatObserver(CFG, now=0.0)
    assert heard(obs, 0.0, Heartbeat(0, math.nan, 0.0)) == (False, None)
    assert heard(obs, 0.0, Heartbeat(0, -1.0, 0.0)) == (False, None)
    assert not obs.trusted and obs.l == -1


def test_running_offset_sum_is_reanchored():
    obs = HeartbeatObserver(UfdConfig(qos=QOS, window=10, reevaluate_every=10), now=0.0)
    heard(obs, 0.0, Heartbeat(0, 0.05, -1e11))  # one absurd clock reading
    for seq in range(1, 40):
        heard(obs, seq * 0.05 + 0.001, Heartbeat(seq, 0.05, seq * 0.05))
    assert obs.mean_offset() == pytest.approx(0.001, abs=1e-9)


def test_a_freshness_timer_that_fires_early_is_rearmed():
    """A driver whose clock conversion loses an ulp may fire the timer just before q_tau_{l+1}: the
    core must wait for the deadline again, or a crashed peer stays trusted forever (found by the
    100,000-schedule sweep, seed 7020)."""
    from haa.core.effects import SetTimer, Suspicion
    from haa.core.host.hostcore import CoreConfig, HostCore

    core = HostCore("q", 1, ["q", "p"], CoreConfig(ufd=CFG))
    core.start(0.0)
    core.on_message(0.01, "p", 1, 0, Heartbeat(0, 0.05, 0.0))
    core.drain()
    fresh = core.peers["p"].observer.freshness
    core.on_timer(fresh - 1e-12, ("fd", "p"))
    out = core.drain()
    assert not any(isinstance(e, Suspicion) for e in out)
    assert SetTimer(("fd", "p"), fresh) in out
    core.on_timer(fresh, ("fd", "p"))
    assert any(isinstance(e, Suspicion) and e.suspected for e in core.drain())
