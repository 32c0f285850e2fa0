"""Measure the QoS of Alg. 1 on one monitored pair over a long virtual time (thesis §4.4, eq. 4.4-2).

The failure detector promises T_D <= T_D^U + E(D), E(T_MR) >= T_MR^L and E(T_M) <= T_M^U for any network
whose message loss and delay fit its model (independent losses with probability p_L, delays with finite
mean and variance — §4.4.1). This module drives the real `HeartbeatSender` and `HeartbeatObserver` (the
same objects the host core uses, adaptive re-configuration included) through such a network for hours to
weeks of virtual time and measures:

* mistakes: transitions to SUSPECTED while the sender is alive; T_MR (time between mistakes), T_M (how
  long each lasts), the query accuracy probability P_A;
* detection time: the sender crashes at a random moment (many independent trials), T_D is the time to the
  permanent suspicion, compared with T_D^U + E(D);
* the heartbeat rate the detector settled on.

Heartbeats on this channel may be lost and may overtake each other (the model of [66]); setPeriod messages
travel with the same delays. Clocks have a random constant offset.
"""

from __future__ import annotations

import math
import random
from dataclasses import asdict, dataclass

from haa.core.messages import Heartbeat
from haa.core.ufd.qos import QosTargets
from haa.core.ufd.ufd import (
    AskPeriod,
    Beat,
    Deadline,
    EmitHeartbeat,
    HeartbeatIn,
    HeartbeatObserver,
    HeartbeatSender,
    NewPeriod,
    Trust,
    UfdConfig,
)
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.scheduler import EventHeap


@dataclass
class QosMeasurement:
    label: str
    td_upper: float
    tmr_lower: float
    tm_upper: float
    delay: str
    mean_delay: float
    p_loss: float
    horizon: float
    eta: float
    heartbeats_per_minute: float
    mistakes: int
    mean_tmr: float  # horizon / mistakes (inf when none)
    mean_tm: float
    max_tm: float
    query_accuracy: float
    crash_trials: int
    max_detection: float
    mean_detection: float
    detection_bound: float  # T_D^U + E(D)
    detection_violations: int  # trials with T_D > T_D^U + E(D) + the delay-estimate error of that trial

    @property
    def meets_targets(self) -> bool:
        return (
            self.mean_tmr >= self.tmr_lower
            and (self.mistakes == 0 or self.mean_tm <= self.tm_upper)
            and self.detection_violations == 0
        )

    def row(self) -> dict[str, object]:
        d = asdict(self)
        d["meets_targets"] = self.meets_targets
        return d


def _run_pair(
    cfg: UfdConfig,
    delay: DelayModel,
    p_loss: float,
    rng: random.Random,
    horizon: float,
    crash_at: float | None,
    warmup: float,
) -> tuple[list[tuple[float, float]], float, float | None, float, float]:
    """Run one sender/observer pair. Returns (mistakes as (start, end), final eta, detection time or None,
    time suspected after warm-up, E(D) estimate of the observer at the crash)."""
    offset = rng.uniform(-1000.0, 1000.0)  # sender clock = virtual + offset
    sender = HeartbeatSender(cfg.initial_period, offset)
    observer = HeartbeatObserver(cfg, 0.0)
    events: EventHeap[tuple[int, object]] = EventHeap()  # items (kind, data) (haa.lab.dsim.scheduler)
    ARRIVE, SETP, SEND = 0, 1, 2

    def push(t: float, kind: int, data: object) -> None:
        events.push(t, (kind, data))

    push(0.0, SEND, None)
    suspected = True
    since = 0.0
    mistakes: list[tuple[float, float]] = []
    suspected_time = 0.0
    detect: float | None = None
    ed_at_crash = 0.0
    end = horizon if crash_at is None else crash_at + 10.0 * cfg.qos.td_upper + 10.0

    def set_state(t: float, s: bool) -> None:
        nonlocal suspected, since, suspected_time
        if s == suspected:
            return
        if not s:  # trust again: a mistake ends
            if since >= warmup and (crash_at is None or since < crash_at):
                mistakes.append((since, t))
            if since >= warmup:
                suspected_time += t - since
        suspected = s
        since = t

    while True:
        t = events.next_time()
        fresh = observer.freshness
        if observer.trusted and fresh <= t and fresh <= end:  # l. 17-18 fires before this event
            set_state(fresh, True)
            observer.step(fresh, Deadline())
            if crash_at is not None and fresh >= crash_at:
                detect = fresh - crash_at  # the last transition after the crash is the permanent one
            continue
        if t > end or not events:
            break
        _t, _s, (kind, data) = events.pop()
        if kind == SEND:
            if crash_at is not None and t >= crash_at:
                continue
            for s in sender.step(t + offset, Beat()):
                if isinstance(s, EmitHeartbeat):
                    if rng.random() >= p_loss:
                        push(t + delay.sample(rng), ARRIVE, s.hb)
                    push(s.next_at - offset, SEND, None)
        elif kind == ARRIVE:
            assert isinstance(data, Heartbeat)
            effects = observer.step(t, HeartbeatIn(data))
            if any(isinstance(e, Trust) for e in effects):
                set_state(t, False)
            for e in effects:
                if isinstance(e, AskPeriod):
                    push(t + delay.sample(rng), SETP, e.period)
        elif crash_at is None or t < crash_at:
            sender.step(t + offset, NewPeriod(float(data)))  # type: ignore[arg-type]
    ed_at_crash = observer.mean_offset() + offset  # O_i = D_i - offset (eq. 4.4-1)
    if suspected and since >= warmup and crash_at is None:
        suspected_time += end - since
    return mistakes, observer.eta, detect, suspected_time, ed_at_crash


def measure(
    label: str,
    qos: QosTargets,
    delay: DelayModel,
    p_loss: float,
    horizon: float,
    seed: int = 1,
    crash_trials: int = 100,
    config: UfdConfig | None = None,
) -> QosMeasurement:
    cfg = config or UfdConfig(qos=qos, min_delay_std=0.0, min_loss=0.0)
    rng = random.Random(seed)
    warmup = max(60.0, 200 * cfg.initial_period)
    mistakes, eta, _d, susp, _ed = _run_pair(cfg, delay, p_loss, rng, horizon, None, warmup)
    n = len(mistakes)
    span = horizon - warmup
    durations = [b - a for a, b in mistakes]
    detections: list[float] = []
    violations = 0
    bound = qos.td_upper + delay.mean()
    for k in range(crash_trials):
        trng = random.Random(seed * 1_000_003 + k)
        crash_at = warmup + trng.uniform(0.0, 100.0 * cfg.qos.td_upper)
        _m, _eta, det, _s, ed_hat = _run_pair(cfg, delay, p_loss, trng, crash_at + 1.0, crash_at, warmup)
        if det is None:  # already suspected at the crash: the suspicion at the crash is permanent
            det = 0.0
        detections.append(det)
        # the algorithm's guarantee is T_D^U + the mean delay *it estimated* (eq. 4.4-1)
        if det > qos.td_upper + max(ed_hat, delay.mean()) + 1e-6:
            violations += 1
    return QosMeasurement(
        label=label,
        td_upper=qos.td_upper,
        tmr_lower=qos.tmr_lower,
        tm_upper=qos.tm_upper,
        delay=delay.describe(),
        mean_delay=delay.mean(),
        p_loss=p_loss,
        horizon=horizon,
        eta=eta,
        heartbeats_per_minute=60.0 / eta,
        mistakes=n,
        mean_tmr=span / n if n else math.inf,
        mean_tm=sum(durations) / n if n else 0.0,
        max_tm=max(durations, default=0.0),
        query_accuracy=1.0 - susp / span if span > 0 else 1.0,
        crash_trials=crash_trials,
        max_detection=max(detections, default=0.0),
        mean_detection=sum(detections) / len(detections) if detections else 0.0,
        detection_bound=bound,
        detection_violations=violations,
    )
