"""The monitor of a host's agent processes: hang detection and resource limits (haa.hostd.agentproc's docstring,
"Failure detection" and "Resource limits").

One task (`AgentMonitor.run`) ticks over the supervisor's live instances: an instance silent (no frame) for
`hang_timeout` is SIGKILLed as hung — unless this loop itself was stalled, when their frames may just be unread,
or the host holds its frames unread (`AgentInstance.held`: back-pressure, haa.hostd.budget); so is one that reads
nothing of what its host wrote to it for `hang_timeout` (its socket takes no byte while bytes wait: the host's
acks wait for its agents to read, docs/limits.md "Messages in flight");
every `cpu_window` it samples each agent's CPU time and RSS (the figures of `AgentSupervisor.stats()`), and
every `mem_period` in between the RSS of the agents with a memory limit. An agent over its type's memory limit,
or over its CPU limit averaged over `cpu_limit_window`, is SIGKILLed with that reason. `set_limits` gives a new
instance its type's limits and caps its address space (RLIMIT_AS).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time

import psutil

from haa.hostd.agentinstance import AgentInstance
from haa.hostd.logs import log_event
from haa.pb import agent_pb2 as pb

__all__ = ["AS_MARGIN_FACTOR", "CPU_LIMIT_WINDOW", "MEM_PERIOD", "MIB", "AgentMonitor"]

#: the window over which an agent's CPU share is compared with its type's CPU_LIMIT (seconds)
CPU_LIMIT_WINDOW = 10.0
#: how often every agent's RSS is compared with its type's MEMORY_LIMIT_MB (seconds)
MEM_PERIOD = 0.25
#: the address-space cap of an agent process: its size when it said hello + this times its memory limit
AS_MARGIN_FACTOR = 4
MIB = 1024 * 1024


class AgentMonitor:
    """Watches the instances in `agents` (the supervisor's own table of live instances, read at every tick)."""

    def __init__(self, agents: dict[str, AgentInstance], *, heartbeat_period: float, hang_timeout: float,
                 cpu_window: float, cpu_limit_window: float, mem_period: float, log: logging.Logger) -> None:
        self.agents = agents
        self.heartbeat_period = heartbeat_period
        self.hang_timeout = hang_timeout
        self.cpu_window = cpu_window
        self.cpu_limit_window = cpu_limit_window
        self.mem_period = mem_period
        self.log = log
        #: agents killed for being over a limit
        self.over_limit = 0

    async def run(self) -> None:
        tick = max(0.02, min(self.heartbeat_period / 4, self.mem_period))
        last = time.monotonic()
        last_cpu = 0.0
        last_mem = 0.0
        while True:
            await asyncio.sleep(tick)
            now = time.monotonic()
            gap = now - last
            last = now
            if gap > max(tick * 4, self.hang_timeout / 2):
                # this loop did not run for a while: the agents' frames may be sitting unread in the sockets
                log_event(self.log, logging.WARNING, "agent_monitor_stalled", seconds=round(gap, 3))
                for inst in self.agents.values():
                    inst.last_heard = max(inst.last_heard, now)
                    inst.reading = max(inst.reading, now)
                continue
            for inst in list(self.agents.values()):
                if inst.state in ("spawning",) or inst.fail_reason is not None or inst.terminal:
                    continue
                if inst.held:
                    inst.last_heard = now
                silent = now - inst.last_heard
                unread = self.unread(inst, now)
                if silent > self.hang_timeout:
                    inst.fail_reason = f"hung: no heartbeat for {silent:.1f} s"
                elif unread:
                    inst.fail_reason = f"hung: read nothing of its channel for {now - inst.reading:.1f} s " \
                                       f"({unread} bytes waiting)"
                else:
                    continue
                log_event(self.log, logging.WARNING, "agent_hung", agent=inst.id, name=inst.spec.name,
                          pid=inst.pid, silent=round(silent, 3), unread=unread, reason=inst.fail_reason)
                inst.signal(signal.SIGKILL)
            if now - last_cpu >= self.cpu_window:
                last_cpu = now
                last_mem = now
                self.sample_cpu(now)
            elif now - last_mem >= self.mem_period:
                last_mem = now
                self.sample_memory()

    def unread(self, inst: AgentInstance, now: float) -> int:
        """The bytes waiting for `inst` if its socket has taken none of them for `hang_timeout`, else 0."""
        chan = inst.chan
        if chan is None:
            return 0
        waiting = chan.buffered()
        taken = chan.bytes_out - waiting
        if not waiting or taken != inst.taken:
            inst.taken = taken
            inst.reading = now
            return 0
        return waiting if now - inst.reading > self.hang_timeout else 0

    # ------------------------------------------------------------------ limits

    def set_limits(self, inst: AgentInstance, info: pb.AgentTypeInfo | None) -> None:
        """The type's resource limits for this instance; the address-space cap on its process."""
        if info is None:
            return
        inst.memory_limit = int(info.memory_limit_mb) * MIB
        inst.cpu_limit = float(info.cpu_limit)
        if not inst.memory_limit or inst.proc is None:
            return
        try:
            vms = inst.proc.memory_info().vms
            cap = vms + AS_MARGIN_FACTOR * inst.memory_limit
            inst.proc.rlimit(psutil.RLIMIT_AS, (cap, cap))
        except (psutil.Error, OSError, ValueError, AttributeError) as e:
            log_event(self.log, logging.WARNING, "agent_rlimit_failed", agent=inst.id, name=inst.spec.name,
                      error=f"{type(e).__name__}: {e}")

    def kill_over_limit(self, inst: AgentInstance, reason: str) -> None:
        """Kill an agent over one of its type's limits; Failed(reason) follows."""
        if inst.fail_reason is not None or inst.terminal:
            return
        inst.fail_reason = reason
        self.over_limit += 1
        log_event(self.log, logging.WARNING, "agent_over_limit", agent=inst.id, name=inst.spec.name,
                  type=inst.spec.type_name, pid=inst.pid, reason=reason)
        inst.signal(signal.SIGKILL)

    # ------------------------------------------------------------------ samples

    def sample_memory(self) -> None:
        """RSS of the agents with a memory limit, checked against it (between CPU samples)."""
        for inst in list(self.agents.values()):
            if inst.proc is None or not inst.memory_limit or inst.fail_reason is not None or inst.terminal:
                continue
            try:
                inst.rss = inst.proc.memory_info().rss
            except psutil.Error:
                continue
            self.check_memory(inst)

    def check_memory(self, inst: AgentInstance) -> None:
        if inst.memory_limit and inst.rss > inst.memory_limit:
            self.kill_over_limit(inst, f"over its memory limit of {inst.memory_limit // MIB} MiB "
                                       f"(RSS {inst.rss / MIB:.0f} MiB)")

    def check_cpu(self, inst: AgentInstance, now: float, total: float) -> None:
        """The CPU share over the last `cpu_limit_window` seconds (once that much has been sampled)."""
        if not inst.cpu_limit:
            return
        h = inst.cpu_hist
        h.append((now, total))
        while len(h) > 2 and now - h[1][0] >= self.cpu_limit_window:
            h.popleft()
        t0, c0 = h[0]
        span = now - t0
        if span >= self.cpu_limit_window * 0.95:
            share = (total - c0) / span
            if share > inst.cpu_limit:
                self.kill_over_limit(inst, f"over its CPU limit of {inst.cpu_limit:g} cores "
                                           f"({share:.2f} over {span:.0f} s)")

    def sample_cpu(self, now: float) -> None:
        for inst in list(self.agents.values()):
            if inst.proc is None:
                continue
            try:
                with inst.proc.oneshot():
                    t = inst.proc.cpu_times()
                    inst.rss = inst.proc.memory_info().rss
            except psutil.Error:
                continue
            total = t.user + t.system
            if inst.cpu_sample is not None:
                t_prev, c_prev = inst.cpu_sample
                if now > t_prev:
                    inst.cpu = max(0.0, (total - c_prev) / (now - t_prev))
            inst.cpu_sample = (now, total)
            inst.cpu_seconds = total
            if inst.fail_reason is None and not inst.terminal and inst.state != "spawning":
                self.check_memory(inst)
                self.check_cpu(inst, now, total)
