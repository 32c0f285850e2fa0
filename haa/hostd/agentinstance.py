"""One agent instance as its host's supervisor tracks it, and its OS process: `AgentInstance` (the spec, the
channel, the state, the counters and measurements, signalling the process) and `ProcessTable` (the exits the
fork server reports, matched to instances by pid; waiting for an instance's process to be gone, SIGKILL if it
does not go). `AgentSupervisor` (haa.hostd.agentproc) owns both; haa.hostd.agentmonitor reads and kills through
them.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from collections import defaultdict, deque

import psutil

from haa.hostd.agentevents import Envelope, InstanceSpec
from haa.pb import agent_pb2 as pb
from haa.sdk.channel import Channel
from haa.sdk.forkserver import ForkServer

__all__ = ["LIVE_STATES", "AgentInstance", "ProcessTable", "alive"]

#: the states of an instance whose process is (still) the agent's
LIVE_STATES = ("spawning", "shell", "running", "freezing", "stopping")


class AgentInstance:
    """One instance of an agent (one process): spawning -> shell -> running -> freezing/stopping -> frozen,
    stopped or failed."""

    def __init__(self, spec: InstanceSpec) -> None:
        self.spec = spec
        self.pid = 0
        self.proc: psutil.Process | None = None
        self.fork: ForkServer | None = None  # the fork server that forked it (and reports its exit)
        self.chan: Channel[pb.AgentToHost] | None = None
        self.state = "spawning"
        self.pending: deque[Envelope] = deque()
        self.task: asyncio.Task[None] | None = None
        self.exit_reason: str | None = None
        self.exited = asyncio.Event()
        self.fail_reason: str | None = None
        #: killed by the core as a shell it no longer needs (a thaw or recovery given up: "abandoned: ...",
        #: "stale shell ..."): its end is not an agent failure
        self.discarded = False
        self.agent_error = ""
        self.terminal = False
        self.t0 = time.monotonic()
        self.last_heard = self.t0
        self.spawn_seconds = 0.0
        self.msgs_in: defaultdict[str, int] = defaultdict(int)
        self.bytes_in: defaultdict[str, int] = defaultdict(int)
        self.msgs_out: defaultdict[str, int] = defaultdict(int)
        self.bytes_out: defaultdict[str, int] = defaultdict(int)
        self.cpu = 0.0
        self.cpu_seconds = 0.0
        self.cpu_sample: tuple[float, float] | None = None
        self.cpu_hist: deque[tuple[float, float]] = deque()  # (time, total CPU seconds), for the CPU limit
        self.rss = 0
        self.memory_limit = 0  # bytes (0: none)
        self.cpu_limit = 0.0  # cores (0: none)
        self.mailbox = 0
        self.handled = 0
        #: the host holds this agent's frames unread until a message it sent has room on its way (`held`, see
        #: haa.hostd.budget): the monitor does not count that time as silence
        self.held = False
        #: what the monitor last saw of the bytes the agent's socket took from this host (`taken`), and when they
        #: last grew or nothing was waiting (`reading`): an agent that reads nothing of what waits for it is hung
        self.taken = 0
        self.reading = self.t0

    @property
    def id(self) -> str:
        return self.spec.agent_id

    def count_in(self, env: Envelope) -> None:
        self.msgs_in[env.src] += 1
        self.bytes_in[env.src] += len(env.payload)

    def signal(self, sig: int) -> bool:
        """Signal the agent's process unless it is known to be gone."""
        if not self.pid or self.exited.is_set():
            return False
        try:
            if self.proc is not None:
                self.proc.send_signal(sig)  # psutil checks the pid was not reused
            else:
                os.kill(self.pid, sig)
            return True
        except (psutil.Error, ProcessLookupError, PermissionError):
            return False


def alive(proc: psutil.Process | None) -> bool:
    """Whether the process still runs (a zombie does not); False if unknown."""
    if proc is None:
        return False
    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


class ProcessTable:
    """The agent processes by pid, and their exits: the fork server reports each exit (`on_exit`), maybe before
    the spawn that forked the process has recorded its pid (`add` takes such an early exit)."""

    def __init__(self) -> None:
        self.by_pid: dict[int, AgentInstance] = {}
        self.unclaimed_exits: dict[int, str] = {}

    def add(self, inst: AgentInstance) -> None:
        """Record a forked instance (its `pid` set); an exit already reported for its pid is its own."""
        pid = inst.pid
        self.by_pid[pid] = inst
        early = self.unclaimed_exits.pop(pid, None)
        if early is not None:
            inst.exit_reason = early
            inst.exited.set()
            self.by_pid.pop(pid, None)

    def instances(self) -> list[AgentInstance]:
        return list(self.by_pid.values())

    def on_exit(self, pid: int, reason: str) -> None:
        """The fork server's report of an exit."""
        inst = self.by_pid.pop(pid, None)
        if inst is None:
            self.unclaimed_exits[pid] = reason  # exited before spawn() recorded its pid
            while len(self.unclaimed_exits) > 1000:
                self.unclaimed_exits.pop(next(iter(self.unclaimed_exits)))
            return
        inst.exit_reason = reason
        inst.exited.set()

    def set_exited(self, inst: AgentInstance, reason: str) -> None:
        if inst.exit_reason is None:
            inst.exit_reason = reason
        if self.by_pid.get(inst.pid) is inst:
            del self.by_pid[inst.pid]
        inst.exited.set()

    async def wait_exit(self, inst: AgentInstance, timeout: float) -> bool:
        """Wait up to `timeout` for the process's exit; True once it is gone. The fork server reports exits;
        if the one that forked this agent died (its children die with it), psutil tells instead."""
        end = time.monotonic() + timeout
        while not inst.exited.is_set():
            orphan = inst.fork is not None and not inst.fork.alive
            if orphan and not alive(inst.proc):
                self.set_exited(inst, "fork server died: exit status unknown")
                break
            left = end - time.monotonic()
            if left <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(inst.exited.wait(), min(left, 0.05) if orphan else left)
        return True

    async def wait_gone(self, inst: AgentInstance, timeout: float) -> None:
        """Wait until the process is gone; SIGKILL it if it does not go in time."""
        if await self.wait_exit(inst, timeout):
            return
        inst.signal(signal.SIGKILL)
        if await self.wait_exit(inst, 1.0):
            return
        # the fork server is slow or stuck: ask the kernel
        if inst.proc is not None:
            with contextlib.suppress(psutil.Error):
                await asyncio.to_thread(inst.proc.wait, 2.0)
        self.set_exited(inst, "exit status unknown: the fork server did not report it")
