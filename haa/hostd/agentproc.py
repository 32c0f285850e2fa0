"""AgentSupervisor: the host's side of its agent processes — start, feed, freeze, kill, watch, measure.

Each agent runs in an OS process of its own, started by this host through a fork server
(`haa.sdk.forkserver`) and connected to it by one unix socket (`haa.sdk.channel`, frames of
proto/haa/pb/agent.proto). The supervisor lives in haa-hostd's event loop and does no routing and no
distributed algorithm: the daemon's agent layer calls it (spawn, start/thaw/recover, deliver, freeze, kill,
answer) and reacts to the events it reports (`events(ev)`, called from the loop). docs/agents.md has the
whole picture; the thesis steps it serves:

* `spawn(spec)` — "spawn shell for a" (Alg. 6 l. 2, Alg. 8 l. 2): the process is up, connected and has
  said Hello; it has not started. Messages given to `deliver()` meanwhile are buffered here, in order.
* `start_fresh(id)` — a new agent: on_start(), then the buffered messages, then event Ready.
* `thaw(id, state, messages)` — Alg. 6 l. 10 and ll. 19-22: unpack_state(state), then `messages` (queue1 and
  queue2, in order), then the messages buffered by `deliver()` (the local queue), then Ready.
* `recover(id, backup, messages)` — Alg. 8 l. 4 and ll. 10-12: recover(backup) (None: no backup was ever
  made), then the messages, then Ready.
* `freeze(id)` — Alg. 5 l. 2: the agent stops its timers, handles what was delivered before, packs its state
  and exits: event Frozen(state) (ll. 17-20), after every Sent it issued before packing.
* `kill(id)` — SIGKILL (operator kill, fencing).

Events, exactly once and in order per agent instance (all from one task per instance, which reads the
agent's frames in the order it wrote them): Ready, Sent, Backup, Frozen, SpawnChild, DdbGet, DdbScan, DdbPut,
DdbWrite, DdbWatch, DdbUnwatch, Stopped, Failed. Every instance that `spawn()` returned for ends with exactly one of
Frozen, Stopped or Failed (none after `close()`). `spawn()` that raises `SpawnError` reports nothing: no
agent came up. Failed reasons start with one of

    "exited code N"           the process exited by itself (an agent's fatal error adds " (agent error: ...)")
    "killed by signal S"      e.g. kill -9, the OOM killer, `kill()`
    "fork server died: ..."   the agents' parent died, and they with it (no exit status is known)
    "hung: no heartbeat for X s"   it stopped heartbeating for `hang_timeout`; the supervisor SIGKILLed it
    "over its memory limit ..."    / "over its CPU limit ...": the supervisor SIGKILLed it (Resource limits)
    "channel error: ..."      it sent a malformed, oversized or out-of-place frame, or closed its channel
                              while alive; the supervisor SIGKILLed it

and when Failed is reported the process is gone (reaped by the fork server, or found dead by psutil).

Failure detection: exit statuses come from the fork server, which reaps the agents; the channel's end of
stream tells that the process is closing; heartbeats (every `heartbeat_period` from the agent's own loop)
tell that it is alive: no frame for `hang_timeout` = hung. If haa-hostd's own loop was stalled (a monitor
tick came much later than due), no agent is judged hung on that tick: their frames may just be unread.

Resource limits (per agent type, `AgentBase.MEMORY_LIMIT_MB` and `AgentBase.CPU_LIMIT`, carried in the fork
server's type table): the monitor samples every agent's RSS every `mem_period` and its CPU every
`cpu_window`; an agent whose RSS exceeds its memory limit, or whose CPU share averaged over `cpu_limit_window`
exceeds its CPU limit, is SIGKILLed with the reason "over its memory limit of N MiB (RSS M MiB)" or "over its
CPU limit of X cores (Y over Z s)" (event Failed, logged as `agent_over_limit`). Between two samples the
address space is capped (RLIMIT_AS, set on the process once it said hello: its size then plus
`AS_MARGIN_FACTOR` times the limit), so that an agent cannot take the host's memory faster than the monitor
looks; an allocation past that cap raises MemoryError in the agent.

Config validation (`validate_config`): a type with a config model (`AgentTypeInfo.has_config`) has a config
checked by the fork server, which has the agent classes (the host does not import agent code), before the
host commits a spawn.

Back-pressure (docs/limits.md, "Messages in flight"): `backlog()` is what this host has written to its agents and they
have not read yet (the host's acks to other hosts wait while it is too large); before an agent's `sent` frame is
passed on, `send_room` (the host's byte budget, haa.hostd.budget) may ask to wait until the message has room on its
way — meanwhile that agent's frames stay unread (`AgentInstance.held`; the monitor does not count it as silence),
so an agent that sends faster than its messages leave fills its own socket and buffers, not its host.

Measurements (`stats()`, for the allocation's cost and affinity): per agent the CPU share of one core over
the last `cpu_window` seconds (psutil), total CPU seconds and RSS, and messages and bytes in and out per peer
agent id (peer "" = the host or the operator), counted where they cross this supervisor.

The supervisor's parts, each in a module of its own: the values and events (haa.hostd.agentevents, re-exported
here), one instance and its process's exit (haa.hostd.agentinstance), the monitor of hangs and resource limits
(haa.hostd.agentmonitor), the fork server and its agent types (haa.hostd.agenttypes). This module drives them:
spawning (fork, hello), feeding an agent, and reading its frames until it ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import signal
import socket
import time
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path

import psutil

from haa.hostd.agentevents import (
    AgentEvent,
    AgentStats,
    Backup,
    DdbGet,
    DdbPut,
    DdbScan,
    DdbUnwatch,
    DdbWatch,
    DdbWrite,
    Envelope,
    Failed,
    Frozen,
    InstanceSpec,
    Ready,
    Sent,
    SpawnChild,
    Stopped,
)
from haa.hostd.agentinstance import LIVE_STATES, AgentInstance, ProcessTable
from haa.hostd.agentmonitor import AS_MARGIN_FACTOR, CPU_LIMIT_WINDOW, MEM_PERIOD, MIB, AgentMonitor
from haa.hostd.agenttypes import VALIDATE_TIMEOUT, AgentTypes
from haa.hostd.logs import log_event
from haa.pb import agent_pb2 as pb
from haa.sdk.channel import DEFAULT_MAX_FRAME, Channel, ChannelError, message_too_large
from haa.sdk.forkserver import SpawnError

#: reasons of the core's KillAgent for a shell it no longer needs (haa.core.agents.transfer / recovery): the
#: process's end is logged as `agent_shell_discarded`, not as an agent failure
DISCARD_REASONS = ("abandoned:", "stale shell")

__all__ = [
    "AS_MARGIN_FACTOR",
    "CPU_LIMIT_WINDOW",
    "MEM_PERIOD",
    "MIB",
    "VALIDATE_TIMEOUT",
    "AgentEvent",
    "AgentStats",
    "AgentSupervisor",
    "Backup",
    "DdbGet",
    "DdbPut",
    "DdbScan",
    "DdbUnwatch",
    "DdbWatch",
    "DdbWrite",
    "Envelope",
    "Failed",
    "Frozen",
    "InstanceSpec",
    "Ready",
    "Sent",
    "SpawnChild",
    "SpawnError",
    "Stopped",
]

LOGGER = logging.getLogger("haa.hostd.agents")

_LOG_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}


class _ProtocolError(Exception):
    pass


class AgentSupervisor:
    """Starts and supervises this host's agent processes (module docstring)."""

    def __init__(
        self,
        host: str,
        events: Callable[[AgentEvent], None],
        *,
        heartbeat_period: float | None = None,
        hang_timeout: float = 3.0,
        workdir: Path | None = None,
        max_frame: int = DEFAULT_MAX_FRAME,
        spawn_timeout: float = 10.0,
        cpu_window: float = 1.0,
        cpu_limit_window: float = CPU_LIMIT_WINDOW,
        mem_period: float = MEM_PERIOD,
        cold_start: bool = False,
        preload: Sequence[str] = (),
        preload_types: Sequence[str] = (),
        logger: logging.Logger | None = None,
    ) -> None:
        if heartbeat_period is None:  # a hang is at least four missed heartbeats (0.5 s at the 3 s default)
            heartbeat_period = min(0.5, hang_timeout / 4) if hang_timeout > 0 else 0.5
        if not heartbeat_period > 0:
            raise ValueError(f"heartbeat_period: must be > 0, got {heartbeat_period}")
        if not hang_timeout > heartbeat_period:
            raise ValueError(f"hang_timeout: must exceed heartbeat_period ({heartbeat_period}), got {hang_timeout}")
        if not spawn_timeout > 0:
            raise ValueError(f"spawn_timeout: must be > 0, got {spawn_timeout}")
        if not cpu_window > 0:
            raise ValueError(f"cpu_window: must be > 0, got {cpu_window}")
        if not cpu_limit_window >= cpu_window:
            raise ValueError(f"cpu_limit_window: must be >= cpu_window ({cpu_window}), got {cpu_limit_window}")
        if not mem_period > 0:
            raise ValueError(f"mem_period: must be > 0, got {mem_period}")
        self.host = host
        self.events = events
        self.heartbeat_period = heartbeat_period
        self.hang_timeout = hang_timeout
        self.workdir = Path(workdir) if workdir is not None else None
        self.max_frame = max_frame
        self.spawn_timeout = spawn_timeout
        self.cpu_window = cpu_window
        self.cpu_limit_window = cpu_limit_window
        self.mem_period = mem_period
        self.cold_start = cold_start
        self.preload = list(preload)
        self.preload_types = list(preload_types)
        self.log = logger or LOGGER
        self._agents: dict[str, AgentInstance] = {}
        self._procs = ProcessTable()
        self._types = AgentTypes(self._procs.on_exit, self._on_forkserver_dead, workdir=self.workdir,
                                 preload=self.preload, preload_types=self.preload_types, log=self.log)
        self._limits = AgentMonitor(self._agents, heartbeat_period=heartbeat_period, hang_timeout=hang_timeout,
                                    cpu_window=cpu_window, cpu_limit_window=cpu_limit_window,
                                    mem_period=mem_period, log=self.log)
        self._monitor: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()  # every instance's task, also of ended ones still exiting
        self._closing = False
        self._started = False
        #: asked with (destination, size, gone) before an agent's `sent` frame is passed on: None if the message
        #: may go now, else an awaitable that ends when it may (or when `gone()`: the agent's process exited)
        self.send_room: Callable[[str, int, Callable[[], bool]], Awaitable[None] | None] | None = None
        #: counters for the host's stats
        self.spawned = 0
        self.failed = 0
        self.event_errors = 0

    @property
    def forkserver_restarts(self) -> int:
        return self._types.restarts

    @property
    def over_limit(self) -> int:
        """Agents killed for being over their type's memory or CPU limit."""
        return self._limits.over_limit

    @property
    def unchecked_configs(self) -> int:
        return self._types.unchecked_configs

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Start the fork server (it knows every agent type by name and imports each at its first use) and the
        monitor."""
        if self._started:
            return
        self._started = True
        if self.workdir is not None:
            (self.workdir / "agents").mkdir(parents=True, exist_ok=True)
        await self._types.ensure()
        self._monitor = asyncio.create_task(self._limits.run(), name="agent-monitor")

    async def close(self) -> None:
        """Kill every agent process and stop the fork server; no events are reported from here on."""
        self._closing = True
        if self._monitor is not None:
            self._monitor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._monitor
        insts = list({*self._agents.values(), *self._procs.instances()})
        for inst in insts:
            inst.signal(signal.SIGKILL)
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for inst in insts:
            if inst.chan is not None:
                inst.chan.close()
        await self._types.close()
        self._agents.clear()

    # ------------------------------------------------------------------ information

    def known_types(self) -> list[str]:
        """The names of every agent type this host can start, imported or not."""
        return self._types.known()

    def imported_type(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's info if the fork server has imported it already (no request needed), else None."""
        return self._types.imported(type_name)

    async def type_info(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's cost, hardware, transfer penalty, recovery, config model and limits; the fork server imports
        a type registered by name only at this first request. None if the type is unknown here or its module fails
        to import (logged once as `agent_type_load_error`, and in `load_errors`)."""
        return await self._types.info(type_name)

    @property
    def load_errors(self) -> list[str]:
        return self._types.load_errors

    @property
    def forkserver_pid(self) -> int | None:
        return self._types.pid

    def agents(self) -> list[str]:
        """Ids of the agents with a live process here (spawning, shell, running, freezing, stopping)."""
        return [a for a, inst in self._agents.items() if inst.state in LIVE_STATES]

    def backlog(self) -> int:
        """Bytes this host has given its agents that they have not read yet: what their channels hold, and the
        payloads buffered for agents that have not started."""
        n = 0
        for inst in self._agents.values():
            if inst.chan is not None:
                n += inst.chan.buffered()
            if inst.pending:
                n += sum(len(e.payload) for e in inst.pending)
        return n

    def pid(self, agent_id: str) -> int:
        """The pid of the agent's process (KeyError if it has none here)."""
        return self._get(agent_id).pid

    def state(self, agent_id: str) -> str | None:
        inst = self._agents.get(agent_id)
        return inst.state if inst is not None else None

    def stats(self) -> dict[str, AgentStats]:
        now = time.monotonic()
        return {
            a: AgentStats(
                agent_id=a,
                name=inst.spec.name,
                type_name=inst.spec.type_name,
                epoch=inst.spec.epoch,
                pid=inst.pid,
                state=inst.state,
                cpu=inst.cpu,
                cpu_seconds=inst.cpu_seconds,
                rss=inst.rss,
                msgs_in=dict(inst.msgs_in),
                bytes_in=dict(inst.bytes_in),
                msgs_out=dict(inst.msgs_out),
                bytes_out=dict(inst.bytes_out),
                buffered=len(inst.pending),
                mailbox=inst.mailbox,
                handled=inst.handled,
                uptime=now - inst.t0,
                spawn_seconds=inst.spawn_seconds,
            )
            for a, inst in self._agents.items()
        }

    def _get(self, agent_id: str) -> AgentInstance:
        inst = self._agents.get(agent_id)
        if inst is None:
            raise KeyError(f"agent {agent_id} has no process on host {self.host}")
        return inst

    async def validate_config(self, type_name: str, config: bytes, timeout: float = VALIDATE_TIMEOUT) -> str:
        """'' when `config` is valid for `type_name`, else the reason (one line). A type without a config
        model (`AgentTypeInfo.has_config` false) or unknown here is not checked (''): the caller refuses an
        unknown type itself. When the fork server cannot answer within `timeout` (stopped, restarting), the
        config passes unchecked, logged as `agent_config_unchecked` and counted: the spawn is not held up by a
        fork server that could not start the agent anyway, and a config that then fails to start ends with
        the agent `failed` after agenttable.MAX_START_FAILURES tries (docs/agents-host.md)."""
        return await self._types.validate(type_name, config, timeout)

    # ------------------------------------------------------------------ spawning

    async def spawn(self, spec: InstanceSpec) -> None:
        """Start a process for `spec` and wait for its Hello (a "shell"); SpawnError if it cannot start."""
        spec.validate()
        if self._closing:
            raise SpawnError("the agent supervisor is closed")
        if not self._started:
            raise SpawnError("the agent supervisor is not started (call start())")
        old = self._agents.get(spec.agent_id)
        if old is not None:
            raise ValueError(
                f"agent_id: {spec.agent_id} ({old.spec.name}) already has a process here (pid {old.pid}, {old.state})"
            )
        t0 = time.perf_counter()
        inst = AgentInstance(spec)
        self._agents[spec.agent_id] = inst
        host_sock, agent_sock = socket.socketpair()
        try:
            fs = await self._types.ensure()
            if spec.type_name in fs.lazy:  # imported in the zygote now, and its limits known before the fork
                await fs.describe(spec.type_name)
            inst.chan = await Channel.open(host_sock, pb.AgentToHost, max_frame=self.max_frame)
            init = pb.HostToAgent.Init(
                agent_id=spec.agent_id, name=spec.name, type_name=spec.type_name, config=spec.config,
                epoch=spec.epoch, parent=spec.parent or "", host=self.host,
                heartbeat_period=self.heartbeat_period, max_frame=self.max_frame,
            )
            inst.chan.send(pb.HostToAgent(init=init))
            log_path = str(self.workdir / "agents" / f"{spec.agent_id}.log") if self.workdir is not None else ""
            pid = await fs.fork(spec.type_name, spec.agent_id, agent_sock.fileno(), log_path=log_path,
                                exec_=self.cold_start)
            agent_sock.close()
            inst.pid = pid
            inst.fork = fs
            self._procs.add(inst)
            with contextlib.suppress(psutil.Error):
                inst.proc = psutil.Process(pid)
            try:
                msg = await asyncio.wait_for(inst.chan.recv(), self.spawn_timeout)
            except TimeoutError:
                why = f"did not say hello within {self.spawn_timeout:g} s"
                raise SpawnError(f"agent {spec.name} (pid {pid}) {why}") from None
            except ChannelError as e:
                raise SpawnError(f"agent {spec.name} (pid {pid}): channel error before hello: {e}") from None
            kind = msg.WhichOneof("msg") if msg is not None else None
            if kind != "hello":
                if msg is not None and kind == "error":
                    why = msg.error.message
                elif msg is None:
                    await self._procs.wait_exit(inst, 1.0)
                    why = f"the process ended before hello ({inst.exit_reason or 'status unknown'})"
                else:
                    why = f"expected hello, got {kind}"
                raise SpawnError(f"agent {spec.name} ({spec.type_name}) did not start: {why}")
        except BaseException as e:
            agent_sock.close()
            inst.signal(signal.SIGKILL)
            inst.state = "failed"
            inst.terminal = True
            if inst.chan is not None:
                inst.chan.close()
            else:
                host_sock.close()
            if self._agents.get(spec.agent_id) is inst:
                del self._agents[spec.agent_id]
            log_event(self.log, logging.WARNING, "agent_spawn_failed", agent=spec.agent_id, name=spec.name,
                      type=spec.type_name, error=str(e))
            if isinstance(e, SpawnError | ValueError) or not isinstance(e, Exception):
                raise
            raise SpawnError(f"agent {spec.name}: {type(e).__name__}: {e}") from e
        inst.state = "shell"
        inst.last_heard = time.monotonic()
        self._limits.set_limits(inst, fs.types.get(spec.type_name))
        inst.spawn_seconds = time.perf_counter() - t0
        self.spawned += 1
        inst.task = asyncio.create_task(self._serve(inst), name=f"agent-{spec.name}")
        self._tasks.add(inst.task)
        inst.task.add_done_callback(self._tasks.discard)
        log_event(self.log, logging.INFO, "agent_spawned", agent=spec.agent_id, name=spec.name, type=spec.type_name,
                  epoch=spec.epoch, pid=inst.pid, ms=round(inst.spawn_seconds * 1e3, 2))

    # ------------------------------------------------------------------ driving an agent

    def _send(self, inst: AgentInstance, msg: pb.HostToAgent) -> bool:
        """Queue a frame to the agent; False if its channel is already broken (its task reports that)."""
        assert inst.chan is not None
        try:
            inst.chan.send(msg)
            return True
        except ChannelError:
            return False

    def _begin(self, agent_id: str, first: pb.HostToAgent, how: str, messages: Sequence[Envelope]) -> None:
        inst = self._get(agent_id)
        if inst.state != "shell":
            raise RuntimeError(f"agent {inst.spec.name}: cannot {how} in state {inst.state} (expected shell)")
        frames = [first]
        for env in (*messages, *inst.pending):
            frames.append(pb.HostToAgent(deliver=env.to_pb()))
        frames.append(pb.HostToAgent(resume=pb.HostToAgent.Resume(how=how)))
        assert inst.chan is not None
        data = [inst.chan.encode(f) for f in frames]  # FrameTooLarge (ValueError) before anything is sent
        for env in messages:
            inst.count_in(env)
        inst.pending.clear()
        inst.state = "running"
        for d in data:
            try:
                inst.chan.send_raw(d)
            except ChannelError:
                break

    def start_fresh(self, agent_id: str) -> None:
        """A new agent: on_start(), then the messages buffered by deliver(), then Ready."""
        self._begin(agent_id, pb.HostToAgent(start=pb.HostToAgent.Start()), "start", ())

    def thaw(self, agent_id: str, state: bytes, messages: Sequence[Envelope]) -> None:
        """Alg. 6 l. 10, ll. 19-22: unpack_state(state), `messages` in order, the buffered ones, then Ready."""
        self._begin(agent_id, pb.HostToAgent(thaw=pb.HostToAgent.Thaw(state=state)), "thaw", messages)

    def recover(self, agent_id: str, backup: bytes | None, messages: Sequence[Envelope] = ()) -> None:
        """Alg. 8 l. 4, ll. 10-12: recover(backup) (None: there is no backup), the messages, then Ready."""
        rec = pb.HostToAgent.Recover(has_backup=backup is not None, backup=backup or b"")
        self._begin(agent_id, pb.HostToAgent(recover=rec), "recover", messages)

    def deliver(self, agent_id: str, env: Envelope) -> bool:
        """Give a message to the agent (FIFO per agent; buffered until it starts). False, and the message was
        not taken, if the agent has no process here or is freezing, stopping or gone. ValueError if the
        message exceeds the channel's frame limit."""
        inst = self._agents.get(agent_id)
        if inst is None or inst.state not in ("spawning", "shell", "running"):
            return False
        if inst.state == "running":
            assert inst.chan is not None
            data = inst.chan.encode(pb.HostToAgent(deliver=env.to_pb()))
            inst.count_in(env)
            with contextlib.suppress(ChannelError):
                inst.chan.send_raw(data)
        else:
            if len(env.payload) > self.max_frame:
                raise ValueError(f"message of {len(env.payload)} bytes exceeds the limit of {self.max_frame} bytes")
            inst.count_in(env)
            inst.pending.append(env)
        return True

    def freeze(self, agent_id: str) -> None:
        """Alg. 5 l. 2: ask the agent to freeze; event Frozen(state) follows (or Failed)."""
        inst = self._get(agent_id)
        if inst.state != "running":
            raise RuntimeError(f"agent {inst.spec.name}: cannot freeze in state {inst.state} (expected running)")
        inst.state = "freezing"
        self._send(inst, pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))

    def stop(self, agent_id: str) -> None:
        """Ask the agent to end itself (on_stop); event Stopped follows (or Failed)."""
        inst = self._get(agent_id)
        if inst.state not in ("shell", "running"):
            raise RuntimeError(f"agent {inst.spec.name}: cannot stop in state {inst.state}")
        inst.state = "stopping"
        self._send(inst, pb.HostToAgent(stop=pb.HostToAgent.Stop()))

    def kill(self, agent_id: str, reason: str = "") -> bool:
        """SIGKILL the agent's process; event Failed("killed by signal 9") follows — or, for a shell the core no
        longer needs (`reason` one of DISCARD_REASONS: a thaw that lost its claim), Failed(reason), logged as
        `agent_shell_discarded` rather than as an agent failure. False if it has none."""
        inst = self._agents.get(agent_id)
        if inst is None:
            return False
        log_event(self.log, logging.INFO, "agent_kill", agent=agent_id, name=inst.spec.name, pid=inst.pid,
                  reason=reason)
        if reason.startswith(DISCARD_REASONS) and inst.fail_reason is None and not inst.terminal:
            inst.fail_reason = reason
            inst.discarded = True
        return inst.signal(signal.SIGKILL)

    def answer(self, agent_id: str, req_id: int, ok: bool, value: bytes, error: str = "", *,
               missing: bool = False, op_errors: Sequence[str] = (), keys: Sequence[str] = (),
               values: Sequence[bytes] = (), truncated: bool = False) -> bool:
        """Answer a DdbGet / DdbPut / DdbWrite / SpawnChild request (`missing`: DdbGet of a key that does not
        exist; `op_errors`: DdbWrite, one reason per op, "" for an op that succeeded)."""
        inst = self._agents.get(agent_id)
        if inst is None or inst.chan is None or inst.state not in LIVE_STATES:
            return False
        ans = pb.HostToAgent.Answer(req_id=req_id, ok=ok, value=value, error=error, missing=missing,
                                    op_errors=op_errors, keys=keys, values=values, truncated=truncated)
        return self._send(inst, pb.HostToAgent(answer=ans))

    def notify_watch(self, agent_id: str, watch_id: int, event: str, key: str, value: bytes | None,
                     index: int = 0) -> bool:
        """A DDB event for a watch the agent registered (DdbWatch); `index`: a log item's (append) or the
        log's new first index (trim)."""
        inst = self._agents.get(agent_id)
        if inst is None or inst.chan is None or inst.state not in LIVE_STATES:
            return False
        w = pb.HostToAgent.WatchEvent(watch_id=watch_id, event=event, key=key, has_value=value is not None,
                                      value=value or b"", index=index)
        return self._send(inst, pb.HostToAgent(watch_event=w))

    # ------------------------------------------------------------------ the agent's frames

    def _emit(self, ev: AgentEvent) -> None:
        if self._closing:
            return
        try:
            self.events(ev)
        except Exception as e:
            self.event_errors += 1
            log_event(self.log, logging.ERROR, "agent_event_callback_error", kind=type(ev).__name__,
                      agent=ev.agent_id, error=f"{type(e).__name__}: {e}")

    def _on_frame(self, inst: AgentInstance, msg: pb.AgentToHost) -> None:
        kind = msg.WhichOneof("msg")
        a = inst.id
        if kind == "heartbeat":
            inst.mailbox = msg.heartbeat.queued
            inst.handled = msg.heartbeat.handled
        elif kind == "sent":
            m = msg.sent
            why = message_too_large(len(m.payload))
            if why:  # AgentContext.send refuses it in the agent: only an agent that bypasses it gets here
                raise _ProtocolError(why)
            env = Envelope(src=a, dst=m.dst, payload=bytes(m.payload), conv=m.conv, reply=m.reply, error=m.error)
            inst.msgs_out[env.dst] += 1
            inst.bytes_out[env.dst] += len(env.payload)
            self._emit(Sent(a, env))
        elif kind == "ready":
            self._emit(Ready(a, msg.ready.how or "start"))
        elif kind == "backup":
            self._emit(Backup(a, bytes(msg.backup.data)))
        elif kind == "frozen":
            if inst.state != "freezing":
                raise _ProtocolError(f"frozen frame in state {inst.state} (no freeze was asked)")
            inst.terminal = True
            inst.state = "frozen"
            self._retire(inst)  # before the event: its handler may spawn the next instance at once
            self._emit(Frozen(a, bytes(msg.frozen.state)))
        elif kind == "stopped":
            inst.terminal = True
            inst.state = "stopped"
            self._retire(inst)
            self._emit(Stopped(a))
        elif kind == "spawn_child":
            s = msg.spawn_child
            self._emit(SpawnChild(a, s.req_id, s.type_name, bytes(s.config), s.key))
        elif kind == "ddb_get":
            self._emit(DdbGet(a, msg.ddb_get.req_id, msg.ddb_get.key))
        elif kind == "ddb_scan":
            sc = msg.ddb_scan
            self._emit(DdbScan(a, sc.req_id, sc.prefix, sc.limit))
        elif kind == "ddb_put":
            p = msg.ddb_put
            self._emit(DdbPut(a, p.req_id, p.key, bytes(p.value), p.type_name or "blob"))
        elif kind == "ddb_write":
            w = msg.ddb_write
            self._emit(DdbWrite(a, w.req_id, tuple(w.ops), w.atomic))
        elif kind == "ddb_watch":
            self._emit(DdbWatch(a, msg.ddb_watch.watch_id, msg.ddb_watch.prefix))
        elif kind == "ddb_unwatch":
            self._emit(DdbUnwatch(a, msg.ddb_unwatch.watch_id))
        elif kind == "log":
            self._agent_log(inst, msg.log)
        elif kind == "error":
            inst.agent_error = msg.error.message[:1000]
            log_event(self.log, logging.ERROR, "agent_error", agent=a, name=inst.spec.name, error=inst.agent_error)
        else:  # hello again, or something unknown
            raise _ProtocolError(f"unexpected {kind} frame in state {inst.state}")

    def _agent_log(self, inst: AgentInstance, m: pb.AgentToHost.Log) -> None:
        level = _LOG_LEVELS.get(m.level, logging.INFO)
        try:
            fields = json.loads(m.fields_json) if m.fields_json else {}
            if not isinstance(fields, dict):
                fields = {"fields": fields}
        except ValueError:
            fields = {"fields_json": m.fields_json[:1000]}
        fields.update(agent=inst.id, agent_name=inst.spec.name, agent_type=inst.spec.type_name)
        log_event(self.log, level, m.event or "agent_log", **fields)

    async def _serve(self, inst: AgentInstance) -> None:
        """Read the agent's frames until it ends; then report Frozen/Stopped (already done) or Failed."""
        assert inst.chan is not None
        try:
            while True:
                msg = await inst.chan.recv()
                if msg is None:
                    break
                inst.last_heard = time.monotonic()
                if self.send_room is not None and msg.WhichOneof("msg") == "sent":
                    wait = self.send_room(msg.sent.dst, msg.sent.ByteSize(), inst.exited.is_set)
                    if wait is not None:
                        inst.held = True
                        try:
                            await wait
                        finally:
                            inst.held = False
                            inst.last_heard = time.monotonic()
                self._on_frame(inst, msg)
                if inst.terminal:
                    break
        except (ChannelError, _ProtocolError) as e:
            # a process that dies with unread input resets its socket: then the exit status is the reason
            if inst.fail_reason is None and not await self._procs.wait_exit(inst, 0.2):
                inst.fail_reason = f"channel error: {e}"
        except asyncio.CancelledError:
            inst.chan.close()
            raise
        except Exception as e:  # a bug here must still end the instance with exactly one event
            self.log.exception("agent_serve_error")
            inst.fail_reason = inst.fail_reason or f"channel error: internal error: {type(e).__name__}: {e}"
        if inst.terminal:
            # Frozen / Stopped were reported; the process exits by itself (or is made to)
            inst.chan.close()
            self._retire(inst)
            await self._procs.wait_gone(inst, 3.0)
            return
        # close first: an agent that ended (a fatal error) half-closes and waits for us to close
        # (haa.sdk.runner._linger), so that our writes never break the pipe before we read its last frames
        inst.chan.close()
        if inst.fail_reason is None and not await self._procs.wait_exit(inst, 1.0):
            inst.fail_reason = "channel error: the agent closed its channel but did not exit"
        if inst.fail_reason is not None:
            inst.signal(signal.SIGKILL)
        await self._procs.wait_gone(inst, 5.0)
        reason = inst.fail_reason or inst.exit_reason or "exited (status unknown)"
        if inst.agent_error and inst.fail_reason is None:
            reason = f"{reason} (agent error: {inst.agent_error})"
        inst.state = "failed"
        inst.terminal = True
        self._retire(inst)
        if inst.discarded:  # a shell the core gave up (a thaw that lost its claim): not an agent failure
            log_event(self.log, logging.INFO, "agent_shell_discarded", agent=inst.id, name=inst.spec.name,
                      type=inst.spec.type_name, pid=inst.pid, reason=reason)
        else:
            self.failed += 1
            log_event(self.log, logging.WARNING, "agent_failed", agent=inst.id, name=inst.spec.name,
                      type=inst.spec.type_name, pid=inst.pid, reason=reason)
        self._emit(Failed(inst.id, reason))

    def _retire(self, inst: AgentInstance) -> None:
        if self._agents.get(inst.id) is inst:
            del self._agents[inst.id]

    def _on_forkserver_dead(self, reason: str) -> None:
        if self._closing:
            return
        log_event(self.log, logging.ERROR, "agent_forkserver_died", reason=reason,
                  agents=len(self._agents))
