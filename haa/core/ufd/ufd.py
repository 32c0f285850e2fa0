"""Unreliable failure detector HAA-UFD (thesis §4.4, Appendix II Alg. 1).

NFD-U of Chen, Toueg & Aguilera [66] with the thesis' six changes (§4.4.2):

1. INITIAL_PERIOD set by the observer (Alg. 1 ll. 2-3): the observed process starts with
   `UfdConfig.initial_period`, chosen below any period the configuration procedure can return.
2. Each heartbeat carries the sender's current period and local send time p_tau_l (l. 8).
3. Worst-case initialization (l. 14): until N heartbeats have been measured the observer configures
   (eta, alpha) from `worst_loss` and `worst_delay_std`.
4. EA_{l+1} with unsynchronized clocks (eq. 4.4-1): EA_{l+1} = p_tau_l + period + mean(O_i), where
   O_i = (arrival time on q's clock) - p_tau_i is delay plus the constant clock offset.
5. Every N heartbeats the observer re-evaluates (eta, alpha) with `haa.core.ufd.qos.configure` from the
   loss rate and V(O) = V(D) measured over the last M heartbeats (ll. 25-26). The loss rate is the
   add-one (Laplace) estimate (lost + 1) / (expected + 2) over that window, so that a window without a
   loss does not read as "loss is impossible" (which makes f(eta) infinite and eta far too long).
6. The observer tells the sender the new period with setPeriod (l. 27); the sender adopts it after its
   next heartbeat (ll. 7, 11-12), so q's expectation of m_{l+1} is not disturbed.

Choices where the thesis is silent (docs/ufd.md):
* alpha is derived per heartbeat as T_D^U - period(m_l), i.e. from the period the sender actually uses for
  the next heartbeat, so T_D <= T_D^U + E(D) holds even while a setPeriod is in flight.
* Floors on the measured loss and delay spread (`min_loss`, `min_delay_std`): a window of M samples
  underestimates rare, long delays (GC pauses, scheduler stalls) that the Chebyshev bound cannot see.
* setPeriod is only sent when the period changes by more than `period_change` (relative).

Both halves are sans-I/O machines like every other of the core: one `step(now, input)` that returns the effects
(what to send, when to look again, a change of the output), so a driver — `haa.core.host.hostcore.HostCore` on a host,
the QoS simulator `haa.lab.dsim.ufdqos` — does the sending and the timing:

* `HeartbeatSender.step`: `Beat` (the local clock reached p_tau_l) -> `EmitHeartbeat(hb, next_at)`;
  `NewPeriod(period)` (setPeriod arrived, ll. 11-12) -> nothing, or `PeriodRefused` for a period that is no number
  above 0;
* `HeartbeatObserver.step`: `HeartbeatIn(hb)` (ll. 19-27) -> `ArmFreshness(at)` (look again at q_tau_{l+1}),
  then `AskPeriod(period)` if the sender should change its period (l. 27), then `Trust()` if the output changed
  to TRUSTED; `Deadline()` (the freshness point passed, ll. 17-18) -> `Suspect()` if the output changed to
  SUSPECTED, or `ArmFreshness(at)` if the timer fired early.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import assert_never

from haa.core.messages import Heartbeat
from haa.core.ufd.qos import CLUSTER_QOS, FdParams, QosTargets, configure


@dataclass(frozen=True, slots=True)
class Beat:
    """The sender's local clock reached the next send time p_tau_l (l. 6)."""


@dataclass(frozen=True, slots=True)
class NewPeriod:
    """setPeriod(period) arrived from the observer (ll. 11-12)."""

    period: float


@dataclass(frozen=True, slots=True)
class HeartbeatIn:
    """The observer received heartbeat m_j (ll. 19-27)."""

    hb: Heartbeat


@dataclass(frozen=True, slots=True)
class Deadline:
    """The observer's freshness point q_tau_{l+1} passed (ll. 17-18)."""


@dataclass(frozen=True, slots=True)
class EmitHeartbeat:
    """Send `hb` (m_l) now; the next one is due at `next_at` on the local clock."""

    hb: Heartbeat
    next_at: float


@dataclass(frozen=True, slots=True)
class PeriodRefused:
    """A setPeriod value that is no finite number above 0: ignored."""

    period: float


@dataclass(frozen=True, slots=True)
class ArmFreshness:
    """Look again (a `Deadline` input) at `at`, the freshness point q_tau_{l+1}."""

    at: float


@dataclass(frozen=True, slots=True)
class AskPeriod:
    """Tell the sender to use this heartbeat period (setPeriod, l. 27)."""

    period: float


@dataclass(frozen=True, slots=True)
class Trust:
    """The output about the observed process changed to TRUSTED (l. 24)."""


@dataclass(frozen=True, slots=True)
class Suspect:
    """The output about the observed process changed to SUSPECTED (l. 18)."""


SenderInput = Beat | NewPeriod
SenderEffect = EmitHeartbeat | PeriodRefused
ObserverInput = HeartbeatIn | Deadline
ObserverEffect = ArmFreshness | AskPeriod | Trust | Suspect


@dataclass(frozen=True, slots=True)
class UfdConfig:
    qos: QosTargets = CLUSTER_QOS
    initial_period: float = 0.05  # INITIAL_PERIOD (change 1)
    reevaluate_every: int = 50  # N (change 5)
    window: int = 1000  # M most recent heartbeats used for E(O), V(O) and p_L (change 5)
    worst_loss: float = 0.01  # worst-case initialization (change 3)
    worst_delay_std: float = 0.1
    min_loss: float = 0.0
    min_delay_std: float = 0.002
    eta_min: float = 0.005
    period_change: float = 0.05

    def __post_init__(self) -> None:
        if self.initial_period <= 0 or self.initial_period >= self.qos.td_upper:
            raise ValueError("initial_period must be in (0, T_D^U)")
        if self.reevaluate_every < 2 or self.window < 2:
            raise ValueError("reevaluate_every and window must be >= 2")


class HeartbeatSender:
    """Process p, the observed side (Alg. 1 ll. 1-12), for one observer."""

    __slots__ = ("l", "next_period", "next_send", "period")

    def __init__(self, initial_period: float, now: float) -> None:
        self.period = initial_period  # l. 2
        self.next_period = initial_period  # l. 3
        self.next_send = now  # l. 4: p_tau_0
        self.l = 0  # l. 5

    def step(self, now: float, inp: SenderInput) -> list[SenderEffect]:
        """One input (module docstring)."""
        match inp:
            case Beat():
                hb = self._beat(now)
                return [EmitHeartbeat(hb, self.next_send)]
            case NewPeriod(period):
                if not (period > 0.0 and math.isfinite(period)):
                    return [PeriodRefused(period)]
                self.next_period = period  # l. 11-12: adopted after the next heartbeat is sent (l. 7)
                return []
            case _:
                assert_never(inp)

    def _beat(self, now: float) -> Heartbeat:
        """l. 6-10: the local clock reached p_tau_l; returns m_l. Next send at `next_send`."""
        self.period = self.next_period  # l. 7
        sent_at = self.next_send
        hb = Heartbeat(seq=self.l, period=self.period, sent_at=sent_at)  # l. 8
        # l. 9 (if the process was paused past p_tau_{l+1}, skip the missed slots rather than burst)
        nxt = sent_at + self.period
        if nxt <= now:
            nxt = now + self.period - ((now - sent_at) % self.period)
        self.next_send = nxt
        self.l += 1  # l. 10
        return hb


class HeartbeatObserver:
    """Process q, the observer (Alg. 1 ll. 13-27), of one observed process p."""

    __slots__ = (
        "config",
        "contacted",
        "count",
        "eta",
        "freshness",
        "l",
        "last_params",
        "offsets",
        "requested_period",
        "seqs",
        "sum_offsets",
        "trusted",
    )

    def __init__(self, config: UfdConfig, now: float) -> None:
        self.config = config
        # l. 14: worst-case initialization of (eta, alpha) (change 3)
        self.last_params: FdParams = configure(
            config.qos, config.worst_loss, config.worst_delay_std**2, eta_min=config.eta_min
        )
        self.eta = self.last_params.eta
        self.requested_period = config.initial_period
        self.freshness = now  # l. 15: q_tau_0
        self.l = -1  # l. 16
        self.trusted = False
        self.offsets: deque[float] = deque(maxlen=config.window)
        self.seqs: deque[int] = deque(maxlen=config.window)  # sequence numbers of the same heartbeats
        self.sum_offsets = 0.0
        self.count = 0  # heartbeats received since the last re-evaluation
        self.contacted = False

    def step(self, now: float, inp: ObserverInput) -> list[ObserverEffect]:
        """One input (module docstring)."""
        match inp:
            case HeartbeatIn(hb):
                became_trusted, new_period = self._on_heartbeat(now, hb)
                out: list[ObserverEffect] = [ArmFreshness(self.freshness)]
                if new_period is not None:
                    out.append(AskPeriod(new_period))
                if became_trusted:
                    out.append(Trust())
                return out
            case Deadline():
                if now >= self.freshness and self.trusted:  # l. 17-18
                    self.trusted = False
                    return [Suspect()]
                if self.trusted and now < self.freshness:  # fired early (a driver's clock rounding): wait again
                    return [ArmFreshness(self.freshness)]
                return []
            case _:
                assert_never(inp)

    def _on_heartbeat(self, now: float, hb: Heartbeat) -> tuple[bool, float | None]:
        """l. 19-27. Returns (output changed to TRUSTED, new setPeriod value or None); `freshness` is the new
        freshness point."""
        if hb.seq <= self.l:  # l. 20: stale or duplicate
            return False, None
        if not (math.isfinite(hb.period) and hb.period > 0.0 and math.isfinite(hb.sent_at)):
            return False, None
        self.l = hb.seq  # l. 21
        # eq. 4.4-1 (change 4): O_j = arrival - p_tau_j; EA_{l+1} = p_tau_l + period + mean(O)
        o = now - hb.sent_at
        if len(self.offsets) == self.offsets.maxlen:
            self.sum_offsets -= self.offsets[0]
        self.offsets.append(o)
        self.seqs.append(hb.seq)
        self.sum_offsets += o
        ea = hb.sent_at + hb.period + self.sum_offsets / len(self.offsets)
        alpha = self.config.qos.td_upper - hb.period  # alpha = T_D^U - eta for the period in use
        self.freshness = ea + alpha  # l. 22
        became_trusted = False
        if now < self.freshness and not self.trusted:  # l. 23-24
            self.trusted = True
            became_trusted = True
        self.count += 1
        new_period = None
        if not self.contacted:
            self.contacted = True
            new_period = self._request(self.eta)  # first contact: move to the worst-case eta
        elif self.count >= self.config.reevaluate_every:  # l. 25
            self.count = 0
            new_period = self._reevaluate()  # l. 26-27
        return became_trusted, new_period

    def _request(self, eta: float) -> float | None:
        old = self.requested_period
        if abs(eta - old) <= self.config.period_change * old:
            return None
        self.requested_period = eta
        return eta

    def loss_estimate(self) -> float:
        """Add-one estimate of p_L over the heartbeats of the window (those received, and the gaps)."""
        if not self.seqs:
            return self.config.worst_loss
        expected = self.seqs[-1] - self.seqs[0] + 1
        lost = max(0, expected - len(self.seqs))
        return (lost + 1) / (expected + 2)

    def delay_variance(self) -> float:
        n = len(self.offsets)
        if n < 2:
            return self.config.worst_delay_std**2
        mean = self.sum_offsets / n
        return sum((x - mean) ** 2 for x in self.offsets) / (n - 1)

    def _reevaluate(self) -> float | None:
        """l. 26: (eta, alpha) from the measured network (change 5)."""
        cfg = self.config
        self.sum_offsets = math.fsum(self.offsets)  # the running sum drifts; re-anchor it every N
        p_loss = min(max(self.loss_estimate(), cfg.min_loss), 0.99)
        var = max(self.delay_variance(), cfg.min_delay_std**2)
        self.last_params = configure(cfg.qos, p_loss, var, eta_min=cfg.eta_min)
        self.eta = self.last_params.eta
        return self._request(self.eta)

    def mean_offset(self) -> float:
        return self.sum_offsets / len(self.offsets) if self.offsets else 0.0
