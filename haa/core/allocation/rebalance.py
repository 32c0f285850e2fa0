"""When a host starts an agent allocation session (thesis Alg. 4 l. 17, §6.1): `RebalancePolicy`.

The leader's `AllocGlue` (`haa.core.agents.allocglue`) asks it whether a session is due after a change and when
the next periodic one is; the `Allocator` (`haa.core.allocation.allocation`) runs the session. Sans-I/O: time is
an argument.
"""

from __future__ import annotations

from haa.core.allocation.specs import INF, _finite


class RebalancePolicy:
    """When to start an allocation session (Alg. 4 l. 17 and §6.1: "every time a new agent is requested,
    whenever an agent or host fails, and at regular intervals in order to balance processing load").

    * `changed(now, urgent)`: the group or agent list changed. A session is due at once, but never sooner than
      `min_interval` after the previous one (rate limit: a burst of changes makes one session), and, unless
      `urgent` (the group changed: the running session cannot finish), not while a session is still running
      (at most `session_timeout`): the change waits for its finish and the next session takes it. A new start
      supersedes the running session, so restarting on every change of a stream of spawns finished none.
    * `more(now)`: the finished session left agents for the next one (bounded sessions): a session is due.
    * periodic load balance: every `period` seconds after the last start, unless paused by the operator
      (`pause()` / `resume()`) or a session is still running (at most `session_timeout`). Pausing stops only
      the periodic sessions: a change still needs one, or agents of a failed host would stay unallocated.
    * `due(now)` at `deadline()`: True when the host should call `Allocator.on_change(..., start=True)`.
    * `finished(now)`: the host accepted an allocation (`Allocated`).

    Sans-I/O: time is an argument; the host sets a timer for `deadline()`.
    """

    def __init__(self, period: float = 30.0, min_interval: float = 1.0, session_timeout: float = 10.0) -> None:
        self.period = _finite(period, "RebalancePolicy.period", 0.0, lo_open=True)
        self.min_interval = _finite(min_interval, "RebalancePolicy.min_interval", 0.0)
        self.session_timeout = _finite(session_timeout, "RebalancePolicy.session_timeout", 0.0, lo_open=True)
        self.paused = False
        self.pending = False
        self.running = False
        self.urgent = False
        self.last_start = -INF
        self.starts = 0

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    def changed(self, now: float, urgent: bool = False) -> bool:
        self.pending = True
        self.urgent = self.urgent or urgent
        return self.due(now)

    def more(self, now: float) -> None:
        self.pending = True

    def finished(self, now: float) -> None:
        self.running = False

    def force(self, now: float) -> None:
        """An operator asks for a session now: start one whatever the rate limit (counted like any start)."""
        self.pending = self.urgent = False
        self.running = True
        self.last_start = now
        self.starts += 1

    def deadline(self) -> float | None:
        if self.pending:
            if self.running and not self.urgent:
                return self.last_start + max(self.min_interval, self.session_timeout)
            return self.last_start + self.min_interval
        if self.paused:
            return None
        t = self.last_start + self.period
        if self.running:
            t = max(t, self.last_start + self.session_timeout)
        return t

    def due(self, now: float) -> bool:
        if self.pending:
            wait = now < self.last_start + self.min_interval
            wait = wait or (self.running and not self.urgent and now < self.last_start + self.session_timeout)
        else:  # periodic
            wait = self.paused or now < self.last_start + self.period
            wait = wait or (self.running and now < self.last_start + self.session_timeout)
        if wait:
            return False
        self.pending = self.urgent = False
        self.running = True
        self.last_start = now
        self.starts += 1
        return True
