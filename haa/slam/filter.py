"""Particle filter with history blocks and lazy belief propagation (thesis §5.2, Fig. 5.2-1, §5.2.3).

One `ParticleFilter` tracks one avatar's pose (x, y, θ). Its history is a list of `Block`s separated by
resampling events (Fig. 5.2-1). A block holds

* its time list and the particle states at those times (`states[k, i]` is particle i at `times[k]`, stored
  as float32: 12 bytes per particle per prediction, as the thesis counts),
* `parents`: for each particle, the index of the particle of the previous block it was resampled from,
* `weights`: the particle weights as last computed (they sum to 1),
* `log_acc`: the accumulated observation density per particle not yet folded into the weights, and
* `log_fwd`: the observation density still to be propagated forward to the next block.

Densities are kept as logarithms (a product of many densities underflows a float; a sum of logs does not);
"multiply by g" is "add log g". The filter also keeps a forward marker: the earliest block with densities
to propagate.

The five events of §5.2.3:

(a) initialization — `ParticleFilter(n, pose, t0, spread=...)`: equal weights, densities 1 (log 0);
(b) insertion of prediction updates — `predict(Prediction)` (eq. 5.1-3, haa.slam.motion) or `insert(t,
    states)`; in time order only;
(c) application of a correction at any past time, in any order — `correct(t, log_g)`: the block containing
    t gets log_g added to its accumulated density and, unless it is the newest block, to its forward
    density; the forward marker moves back to it. `states_at(t)` gives the particle states the density
    must be computed from (linear interpolation between two predictions, heading interpolated on the
    circle);
(d) state estimation at a query time — `estimate(t)`: densities are propagated forward to the query block
    through the parents (eq. 5.2-4: ²g^i = ¹g^{p_i}), the weights are recomputed once from all the
    accumulated densities (eq. 5.2-3 / 5.2-5) and the accumulated density is reset, and the weighted
    estimate is returned;
(e) resampling — `resample()`: systematic resampling (haa.slam.resample) of the newest block's particles
    into a new block with equal weights whose first states are the parents' states at the same time.

Why the newest block has no forward density: when it is closed by (e), its weights have just been
recomputed from everything applied to it, so its children already reflect those densities. Only
densities applied to a closed block *after* it was closed (late readings) must reach its descendants.

`forward_propagation=False` gives the thesis' NFP variant: corrections to closed blocks update only that
block's own weights and never reach the current particles.

Old blocks are pruned by `prune(now)` after `horizon` seconds (pending forward densities are pushed into the
next block first); a correction or query older than `now - horizon`, or than the oldest kept state, raises
`TooOld` naming the horizon; one newer than the newest prediction raises `NotYetPredicted`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from haa.slam.motion import Prediction, propagate, wrap_angle
from haa.slam.resample import n_eff, normalize_log, systematic_resample


class HistoryError(ValueError):
    """The filter's history cannot serve this time; `reason` says why in one line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class TooOld(HistoryError):
    """The time is before the retained history (pruned after the horizon)."""


class NotYetPredicted(HistoryError):
    """The time is after the newest prediction: the particle states there are not known yet."""


class Block:
    """Particle paths between two resampling events (one table of Fig. 5.2-1)."""

    __slots__ = ("has_fwd", "index", "length", "log_acc", "log_fwd", "n", "parents", "states", "times", "weights")

    def __init__(
        self, index: int, t0: float, states0: np.ndarray, parents: np.ndarray | None, dtype: type = np.float32
    ) -> None:
        self.index = index
        self.n = states0.shape[0]
        cap = 16
        self.times = np.empty(cap, dtype=np.float64)
        self.states: np.ndarray = np.empty((cap, self.n, 3), dtype=dtype)
        self.times[0] = t0
        self.states[0] = states0
        self.length = 1
        self.parents = parents
        self.weights = np.full(self.n, 1.0 / self.n)
        self.log_acc = np.zeros(self.n)
        self.log_fwd = np.zeros(self.n)
        self.has_fwd = False

    @property
    def start(self) -> float:
        return float(self.times[0])

    @property
    def end(self) -> float:
        return float(self.times[self.length - 1])

    def append(self, t: float, states: np.ndarray) -> None:
        if self.length == self.times.shape[0]:
            cap = 2 * self.length
            times = np.empty(cap, dtype=np.float64)
            times[: self.length] = self.times[: self.length]
            st = np.empty((cap, self.n, 3), dtype=self.states.dtype)
            st[: self.length] = self.states[: self.length]
            self.times, self.states = times, st
        self.times[self.length] = t
        self.states[self.length] = states
        self.length += 1

    def states_at(self, t: float) -> np.ndarray:
        """(N, 3) float64 particle states at time t (start <= t <= end), interpolated between predictions."""
        k = int(np.searchsorted(self.times[: self.length], t, side="right")) - 1
        k = max(k, 0)
        s0 = self.states[k].astype(np.float64)
        if k == self.length - 1 or self.times[k] == t:
            return s0
        t0, t1 = self.times[k], self.times[k + 1]
        a = (t - t0) / (t1 - t0)
        s1 = self.states[k + 1].astype(np.float64)
        out = s0 + a * (s1 - s0)
        out[:, 2] = wrap_angle(s0[:, 2] + a * wrap_angle(s1[:, 2] - s0[:, 2]))
        return out

    def trim_before(self, cutoff: float) -> None:
        """Drop rows older than the last row at or before `cutoff` (frees memory once half is unused)."""
        k = int(np.searchsorted(self.times[: self.length], cutoff, side="right")) - 1
        if k <= 0 or k < self.length // 2:
            return
        self.times = self.times[k : self.length].copy()
        self.states = self.states[k : self.length].copy()
        self.length -= k

    def nbytes(self) -> int:
        """Bytes of history actually used (times and states rows), plus the per-particle vectors."""
        used = self.length * (8 + self.n * 3 * self.states.itemsize)
        return used + self.n * 8 * 4


@dataclass
class Estimate:
    """Result of event (d): weighted pose estimate at time t."""

    t: float
    pose: np.ndarray  # (3,) x, y, θ (circular weighted mean)
    std_xy: float  # sqrt of the weighted positional variance (trace)
    n_eff: float
    block: int
    weights: np.ndarray = field(repr=False)


def _weighted_estimate(t: float, states: np.ndarray, w: np.ndarray, block: int) -> Estimate:
    """The weighted mean pose (circular mean for θ), positional std and n_eff of states (N, 3) at time t."""
    x, y = float(w @ states[:, 0]), float(w @ states[:, 1])
    th = math.atan2(float(w @ np.sin(states[:, 2])), float(w @ np.cos(states[:, 2])))
    var = float(w @ ((states[:, 0] - x) ** 2 + (states[:, 1] - y) ** 2))
    return Estimate(t, np.array([x, y, th]), math.sqrt(max(var, 0.0)), n_eff(w), block, w.copy())


def _through_parents(log_fwd: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Eq. 5.2-4: the density of child i is the density of its parent p_i."""
    return log_fwd[parents]


class ParticleFilter:
    """One avatar's particle filter with history (see the module docstring)."""

    # module-level function held as a class attribute so that tests can break it on purpose
    through_parents: Callable[[np.ndarray, np.ndarray], np.ndarray] = staticmethod(_through_parents)

    def __init__(
        self,
        n: int,
        pose: tuple[float, float, float],
        t0: float = 0.0,
        *,
        spread: tuple[float, float, float] = (0.0, 0.0, 0.0),
        seed: int = 0,
        horizon: float = math.inf,
        forward_propagation: bool = True,
        store_dtype: type = np.float32,
        name: str = "",
    ) -> None:
        if n < 1:
            raise ValueError(f"n: number of particles must be >= 1, got {n}")
        if not horizon > 0:
            raise ValueError(f"horizon: must be > 0 seconds, got {horizon}")
        if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
            raise ValueError(f"pose: must be three finite numbers (x, y, theta), got {pose}")
        self.n = n
        self.name = name
        self.horizon = horizon
        self.forward_propagation = forward_propagation
        self.rng = np.random.default_rng(seed)
        self._dtype = store_dtype
        s0 = np.empty((n, 3))
        noise = self.rng.standard_normal((n, 3))
        for j in range(3):
            s0[:, j] = pose[j] + spread[j] * noise[:, j]
        s0[:, 2] = wrap_angle(s0[:, 2])
        self._current = s0  # float64 copy of the newest states (the stored history is float32)
        self.blocks: list[Block] = [Block(0, t0, s0, None, store_dtype)]
        self._starts: list[float] = [t0]
        self.marker: int | None = None  # absolute index of the earliest block with a forward density
        # counters (AP-5.2 and the benches)
        self.corrections = 0
        self.weight_updates = 0  # weight computations of the newest block with observations since the last one
        self.weight_requests = 0  # estimate() calls on the newest block
        self.resamples = 0
        self.pending_obs = 0  # corrections since the last weight computation of the newest block
        self.obs_per_update: list[int] = []

    # ----- structure ---------------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Time of the newest prediction."""
        return self.blocks[-1].end

    @property
    def last(self) -> Block:
        return self.blocks[-1]

    def block(self, index: int) -> Block:
        """Block by absolute index (indices keep counting after pruning)."""
        first = self.blocks[0].index
        if index < first:
            raise TooOld(f"block {index} was pruned (oldest kept is {first})")
        return self.blocks[index - first]

    def locate(self, t: float) -> Block:
        """The block whose time span contains t ([start, next start), the newest up to its end)."""
        if not math.isfinite(t):
            raise HistoryError(f"t: must be finite, got {t}")
        if t > self.time:
            raise NotYetPredicted(f"t={t:.3f}: after the newest prediction (t={self.time:.3f})")
        if t < self.time - self.horizon:
            raise TooOld(f"t={t:.3f}: older than the history horizon ({self.horizon:g} s before t={self.time:.3f})")
        if t < self._starts[0]:
            raise TooOld(f"t={t:.3f}: before the oldest retained state (t={self._starts[0]:.3f})")
        k = bisect.bisect_right(self._starts, t) - 1
        return self.blocks[k]

    def states_at(self, t: float) -> tuple[np.ndarray, Block]:
        """Particle states (N, 3) at time t and the block they belong to."""
        b = self.locate(t)
        return b.states_at(t), b

    def memory_bytes(self) -> int:
        return sum(b.nbytes() for b in self.blocks)

    # ----- (b) predictions -------------------------------------------------------------------------------
    def insert(self, t: float, states: np.ndarray) -> None:
        """Event (b): append the particle states predicted for time t (after the newest prediction)."""
        if not t > self.time:
            raise ValueError(f"prediction.t: predictions must be in time order, got {t} after {self.time}")
        if states.shape != (self.n, 3):
            raise ValueError(f"prediction states: shape must be ({self.n}, 3), got {states.shape}")
        self._current = np.array(states, dtype=np.float64)
        self.last.append(t, self._current)

    def predict(self, p: Prediction) -> None:
        """Event (b) with the velocity model of eq. 5.1-3."""
        if not p.t > self.time:
            raise ValueError(f"prediction.t: predictions must be in time order, got {p.t} after {self.time}")
        self._current = propagate(self._current, p, p.t - self.time, self.rng)
        self.last.append(p.t, self._current)

    # ----- (c) corrections -------------------------------------------------------------------------------
    def correct(self, t: float, log_g: np.ndarray) -> int:
        """Event (c): apply the log observation density log g(y_t | x_t^i) of a reading taken at t.

        Returns the absolute index of the block it was applied to.
        """
        b = self.locate(t)
        if log_g.shape != (self.n,):
            raise ValueError(f"log_g: shape must be ({self.n},), got {log_g.shape}")
        if not np.all(np.isfinite(log_g)):
            raise ValueError("log_g: observation log densities must be finite")
        b.log_acc += log_g
        if b is not self.last and self.forward_propagation:
            b.log_fwd += log_g
            b.has_fwd = True
            if self.marker is None or b.index < self.marker:
                self.marker = b.index
        self.corrections += 1
        if b is self.last or self.forward_propagation:
            self.pending_obs += 1
        return b.index

    # ----- (d) estimation --------------------------------------------------------------------------------
    def _propagate_forward(self, to: int) -> None:
        if self.marker is None or self.marker >= to:
            return
        for k in range(self.marker, to):
            src, dst = self.block(k), self.block(k + 1)
            if not src.has_fwd:
                continue
            assert dst.parents is not None
            d = self.through_parents(src.log_fwd, dst.parents)
            dst.log_acc += d
            if dst is not self.last:
                dst.log_fwd += d
                dst.has_fwd = True
            src.log_fwd[:] = 0.0
            src.has_fwd = False
        self.marker = next((b.index for b in self.blocks if b.index >= to and b.has_fwd), None)

    def _fold(self, b: Block) -> bool:
        """Recompute b's weights from its accumulated density (eq. 5.2-3); reset the density."""
        if not np.any(b.log_acc):
            return False
        with np.errstate(divide="ignore"):
            lw = np.log(b.weights)
        b.weights = normalize_log(lw + b.log_acc)
        b.log_acc[:] = 0.0
        return True

    def estimate(self, t: float | None = None) -> Estimate:
        """Event (d): weighted state estimate at time t (default: the newest prediction)."""
        b = self.last if t is None else self.locate(t)
        tq = self.time if t is None else t
        self._propagate_forward(b.index)
        self._fold(b)
        if b is self.last:
            self.weight_requests += 1
            if self.pending_obs:  # a weight computation that the observations since the last one needed
                self.weight_updates += 1
                self.obs_per_update.append(self.pending_obs)
                self.pending_obs = 0
        return _weighted_estimate(tq, b.states_at(tq), b.weights, b.index)

    def peek(self) -> Estimate:
        """Event (d) at the newest time *without changing anything*: the estimate `estimate()` would return now.

        The densities `estimate()` would propagate forward and fold are combined into a temporary (the same
        additions in the same order, so the weights are bit-identical), and no counter moves: the replica
        (haa.slam.replica) publishes estimates between log events with it, and its state must depend on the
        log alone.
        """
        last = self.last
        carry: np.ndarray | None = None
        if self.marker is not None:
            for k in range(self.marker, last.index):
                src, dst = self.block(k), self.block(k + 1)
                if not src.has_fwd and carry is None:
                    continue
                fwd = src.log_fwd if carry is None else src.log_fwd + carry
                assert dst.parents is not None
                carry = self.through_parents(fwd, dst.parents)
        acc = last.log_acc if carry is None else last.log_acc + carry
        w = last.weights
        if np.any(acc):
            with np.errstate(divide="ignore"):
                lw = np.log(w)
            w = normalize_log(lw + acc)
        return _weighted_estimate(self.time, last.states_at(self.time), w, last.index)

    def weights_at(self, t: float) -> np.ndarray:
        """The weights last computed for the block containing t (no densities folded; a read-only view)."""
        return self.locate(t).weights

    # ----- (e) resampling --------------------------------------------------------------------------------
    def resample(self) -> np.ndarray:
        """Event (e): close the newest block and open a resampled one at the same time. Returns the parents."""
        self.estimate()  # fold everything applied so far into the weights being resampled
        last = self.last
        parents = systematic_resample(last.weights, self.rng)
        self._current = self._current[parents]  # fancy indexing: a fresh array, no sharing
        nb = Block(last.index + 1, last.end, self._current, parents, self._dtype)
        self.blocks.append(nb)
        self._starts.append(nb.start)
        self.resamples += 1
        return parents

    def maybe_resample(self, threshold: float = 0.5) -> tuple[Estimate, bool]:
        """Estimate now; resample if n_eff < threshold · N (the usual trigger, §5.1.1)."""
        if not 0.0 < threshold <= 1.0:
            raise ValueError(f"threshold: must be in (0, 1], got {threshold}")
        est = self.estimate()
        if est.n_eff < threshold * self.n:
            self.resample()
            return est, True
        return est, False

    # ----- pruning -------------------------------------------------------------------------------------
    def prune(self, now: float | None = None) -> int:
        """Drop blocks entirely older than now - horizon; returns how many were dropped."""
        if math.isinf(self.horizon):
            return 0
        cutoff = (self.time if now is None else now) - self.horizon
        dropped = 0
        while len(self.blocks) > 1 and self.blocks[1].start <= cutoff:
            first = self.blocks[0]
            if first.has_fwd:
                self._propagate_forward(first.index + 1)
            self.blocks.pop(0)
            self._starts.pop(0)
            dropped += 1
        if self.marker is not None and self.marker < self.blocks[0].index:
            self.marker = None
        self.blocks[0].trim_before(cutoff)
        self._starts[0] = self.blocks[0].start
        return dropped
