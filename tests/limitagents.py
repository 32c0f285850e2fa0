"""Agent types for tests/test_agent_limits.py, loaded by the fork server through HAA_AGENT_MODULES (the test
puts tests/ on PYTHONPATH): agents that cannot start, and agents that take more memory or CPU than their type
allows. Not a test module itself (pytest does not collect it)."""

from __future__ import annotations

import time

from haa.sdk.base import AgentBase
from haa.sdk.registry import register


@register
class StartFailAgent(AgentBase):
    """Every start raises: a fresh start (on_start) and a recovery (recover) alike."""

    TYPE = "limits-startfail"
    RECOVERY = "backup"

    async def on_start(self) -> None:
        raise RuntimeError("this agent cannot start (limits-startfail)")

    def recover(self, backup: bytes | None) -> None:
        raise RuntimeError("this agent cannot start (limits-startfail)")


@register
class GreedyAgent(AgentBase):
    """Takes memory on request: b"grow" allocates (and touches) 8 MiB every 20 ms, past its 96 MiB limit,
    without blocking its loop (it keeps heartbeating: only the memory limit can stop it). b"pid" -> its pid."""

    TYPE = "limits-greedy"
    RECOVERY = "backup"
    MEMORY_LIMIT_MB = 96

    def __init__(self, ctx: object) -> None:
        super().__init__(ctx)  # type: ignore[arg-type]
        self.hoard: list[bytes] = []

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"grow":
            self.every(0.02, self._grow, first=0.0)
            return b"growing"
        if payload == b"pid":
            import os

            return str(os.getpid()).encode()
        raise ValueError(f"unknown request {payload[:20]!r}")

    def _grow(self) -> None:
        if len(self.hoard) < 128:  # 1 GiB at most, should the limit fail to act (the RLIMIT_AS cap is lower)
            self.hoard.append(b"m" * (8 << 20))


@register
class SpinAgent(AgentBase):
    """Burns its CPU on request: b"spin" runs a timer that is busy 90 % of the time (it still heartbeats, so
    it does not look hung: only the CPU limit of 0.1 cores can stop it)."""

    TYPE = "limits-spin"
    RECOVERY = "restart"
    CPU_LIMIT = 0.1

    async def on_request(self, src: str, payload: bytes) -> bytes:
        if payload == b"spin":
            self.every(0.01, self._spin, first=0.0)
            return b"spinning"
        raise ValueError(f"unknown request {payload[:20]!r}")

    def _spin(self) -> None:
        end = time.perf_counter() + 0.009
        while time.perf_counter() < end:
            pass
