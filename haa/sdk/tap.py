"""The agent-side tap of AgentPlayback (thesis §6.1.4, docs/playback.md): what the agent process calls, and how
the host chooses what implements it.

`Tap` is the interface `AgentContext` (haa.sdk.base) and `SimLink` (haa.agents.simlink) call: every input
where the agent consumes it (mailbox items, the host's answers, replies, timeouts, each `now()` and random
number, thread completions), every frame the agent emits, and an avatar agent's calls to haa-sim (`wrap_stub`).
The recorder (haa.sdk.recorder.Recorder) implements it; haa.lab.playback sits above the agents, so the agents
never import it: the host injects it.

Injection: the host names a factory `module:callable` in the environment variable `HAA_AGENT_TAP` (haa-hostd
`--record-dir` sets `haa.sdk.recorder:from_env`, with `HAA_RECORD_DIR`); the fork server and every agent
process inherit it. `open_tap(init)` imports that module by name at run time (importlib, not a static import),
calls the factory with the agent's Init frame and returns its tap, or None (no recording). A factory that
cannot be loaded or fails stops the recording with one line on stderr, never the agent.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import random
import sys
from collections.abc import Callable
from typing import Any, Protocol

from haa.pb import agent_pb2 as pb
from haa.sdk.base import Clock

#: the environment variable naming the tap factory (`module:callable`) of the host's agent processes
TAP_ENV = "HAA_AGENT_TAP"


class Tap(Protocol):
    """What the agent process reports to AgentPlayback (module docstring; haa.sdk.recorder.Recorder)."""

    def wrap_emit(self, emit: Callable[[pb.AgentToHost], None]) -> Callable[[pb.AgentToHost], None]: ...

    def wrap_clock(self, clock: Clock) -> Clock: ...

    def wrap_random(self, rnd: random.Random) -> random.Random: ...

    def perf_counter(self, v: float) -> None: ...

    def thread_done(self, n: int) -> None: ...

    def freeze_fed(self) -> None: ...

    def item(self, kind: str, data: Any) -> None: ...

    def answer(self, req_id: int, ans: pb.HostToAgent.Answer | None) -> None: ...

    def reply(self, conv: int, env: pb.AgentMsg | None) -> None: ...

    def wrap_stub(self, source: str, service: Any, stub: Any) -> Any: ...

    def close(self) -> None: ...


#: builds the tap of one agent instance from its Init frame (None: nothing to record)
TapFactory = Callable[[pb.HostToAgent.Init], "Tap | None"]


def load_factory(spec: str) -> TapFactory:
    """The callable named `module:callable` (ValueError if malformed, ImportError / AttributeError if missing)."""
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"{TAP_ENV}={spec!r}: expected module:callable")
    fn: TapFactory = getattr(importlib.import_module(module), name)
    if not callable(fn):
        raise ValueError(f"{TAP_ENV}={spec!r}: {name} is not callable")
    return fn


def preload() -> None:
    """Import the tap factory's module now, if one is named (the fork server, before it forks: each agent
    process then finds the recorder loaded). A broken name is reported per agent by `open_tap`."""
    spec = os.environ.get(TAP_ENV, "")
    if spec:
        with contextlib.suppress(Exception):  # reported by open_tap, in the agent's own stderr
            load_factory(spec)


def open_tap(init: pb.HostToAgent.Init) -> Tap | None:
    """The tap of this agent instance: the factory `HAA_AGENT_TAP` names, called with `init`; None when no
    factory is named, or (one line on stderr) when it cannot be loaded or fails."""
    spec = os.environ.get(TAP_ENV, "")
    if not spec:
        return None
    try:
        return load_factory(spec)(init)
    except Exception as e:  # a recording problem never stops the agent
        print(f"agent {init.name}: no recording ({TAP_ENV}={spec!r}: {type(e).__name__}: {e})", file=sys.stderr)
        return None
