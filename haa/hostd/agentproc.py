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

Measurements (`stats()`, for the allocation's cost and affinity): per agent the CPU share of one core over
the last `cpu_window` seconds (psutil), total CPU seconds and RSS, and messages and bytes in and out per peer
agent id (peer "" = the host or the operator), counted where they cross this supervisor.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import time
import uuid
from collections import defaultdict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from haa.hostd.logs import log_event
from haa.pb import agent_pb2 as pb
from haa.sdk.channel import DEFAULT_MAX_FRAME, Channel, ChannelError, message_too_large
from haa.sdk.forkserver import ForkServer, SpawnError

__all__ = [
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

#: the window over which an agent's CPU share is compared with its type's CPU_LIMIT (seconds)
CPU_LIMIT_WINDOW = 10.0
#: how often every agent's RSS is compared with its type's MEMORY_LIMIT_MB (seconds)
MEM_PERIOD = 0.25
#: the address-space cap of an agent process: its size when it said hello + this times its memory limit
AS_MARGIN_FACTOR = 4
MIB = 1024 * 1024
#: how long a config check may wait for the fork server (it answers in milliseconds when it runs)
VALIDATE_TIMEOUT = 2.0

_LOG_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}
UINT64_MAX = 2**64 - 1


# ---------------------------------------------------------------------------------------------- values


@dataclass(frozen=True)
class InstanceSpec:
    """One instance of an agent on this host. `epoch` fences instances: a new one (thaw, recovery) gets a
    larger epoch than every earlier instance of the same agent."""

    agent_id: str
    name: str
    type_name: str
    config: bytes = b""
    epoch: int = 0
    parent: str | None = None

    def validate(self) -> None:
        """Raise ValueError naming the field and the reason."""
        try:
            if str(uuid.UUID(self.agent_id)) != self.agent_id.lower():
                raise ValueError
        except (ValueError, TypeError, AttributeError):
            raise ValueError(f"agent_id: not a UUID string: {self.agent_id!r}") from None
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("name: must be a non-empty string")
        if not isinstance(self.type_name, str) or not self.type_name:
            raise ValueError("type_name: must be a non-empty string")
        if not isinstance(self.config, bytes):
            raise ValueError(f"config: must be bytes, not {type(self.config).__name__}")
        if isinstance(self.epoch, bool) or not isinstance(self.epoch, int) or not 0 <= self.epoch <= UINT64_MAX:
            raise ValueError(f"epoch: must be an int in 0..2**64-1, got {self.epoch!r}")
        if self.parent is not None and not isinstance(self.parent, str):
            raise ValueError(f"parent: must be an agent id or None, got {self.parent!r}")


@dataclass(frozen=True)
class Envelope:
    """A message between agents as the host sees it. `src` = "" for the host/operator; `conv` != 0 makes it
    a request (reply False) or its response (reply True, `error` set if it failed)."""

    src: str
    dst: str
    payload: bytes
    conv: int = 0
    reply: bool = False
    error: str = ""

    def to_pb(self) -> pb.AgentMsg:
        return pb.AgentMsg(src=self.src, dst=self.dst, payload=self.payload, conv=self.conv, reply=self.reply,
                           error=self.error)

    @staticmethod
    def from_pb(m: pb.AgentMsg) -> Envelope:
        return Envelope(src=m.src, dst=m.dst, payload=bytes(m.payload), conv=m.conv, reply=m.reply, error=m.error)


# ---------------------------------------------------------------------------------------------- events


@dataclass(frozen=True)
class Ready:
    """The agent started (`how` = "start"), thawed ("thaw") or recovered ("recover") and handled the
    messages queued for it."""

    agent_id: str
    how: str = "start"


@dataclass(frozen=True)
class Sent:
    """A message the agent sent (including responses to requests), in the agent's send order. `env.src` is
    always the agent's id (the supervisor sets it; an agent cannot pose as another)."""

    agent_id: str
    env: Envelope


@dataclass(frozen=True)
class Backup:
    """Alg. 7 l. 3: the agent's backup, for DDB.agents[a].backup."""

    agent_id: str
    data: bytes


@dataclass(frozen=True)
class Frozen:
    """Alg. 5 l. 19: the agent's packed state; the process is exiting. Terminal."""

    agent_id: str
    state: bytes


@dataclass(frozen=True)
class SpawnChild:
    """The agent asks for a child; answer with `answer(agent_id, req_id, ok, child_id.encode())`."""

    agent_id: str
    req_id: int
    type_name: str
    config: bytes
    #: the spawn's idempotence key (docs/agents.md, "Idempotent spawn"; "" = always a new child)
    key: str = ""


@dataclass(frozen=True)
class DdbGet:
    """Answer with `answer(agent_id, req_id, True, value)` or `answer(..., True, b"", missing=True)`."""

    agent_id: str
    req_id: int
    key: str


@dataclass(frozen=True)
class DdbScan:
    """Answer with `answer(agent_id, req_id, True, b"", keys=[...], values=[...], truncated=...)`."""

    agent_id: str
    req_id: int
    prefix: str
    limit: int


@dataclass(frozen=True)
class DdbPut:
    """Answer with `answer(agent_id, req_id, ok, b"", error)` once the write is committed (or refused)."""

    agent_id: str
    req_id: int
    key: str
    value: bytes
    type_name: str = "blob"


@dataclass(frozen=True)
class DdbWrite:
    """Several DDB ops (`haa.pb.ddb_pb2.DdbOp`) in one batch; answer with `answer(agent_id, req_id, committed,
    b"", error, op_errors=[...])` once the batch is committed (or refused)."""

    agent_id: str
    req_id: int
    ops: tuple[object, ...]
    atomic: bool = False


@dataclass(frozen=True)
class DdbWatch:
    """Notify DDB events on keys starting with `prefix` with `notify_watch(agent_id, watch_id, ...)`."""

    agent_id: str
    watch_id: int
    prefix: str


@dataclass(frozen=True)
class DdbUnwatch:
    agent_id: str
    watch_id: int


@dataclass(frozen=True)
class Stopped:
    """The agent ended itself normally (or after `stop()`); the process is exiting. Terminal."""

    agent_id: str


@dataclass(frozen=True)
class Failed:
    """The agent failed; its process is gone. Terminal. `reason`: see the module docstring."""

    agent_id: str
    reason: str


AgentEvent = (
    Ready | Sent | Backup | Frozen | SpawnChild | DdbGet | DdbScan | DdbPut | DdbWrite | DdbWatch | DdbUnwatch
    | Stopped | Failed
)


@dataclass
class AgentStats:
    """A snapshot of one agent process (see the module docstring, "Measurements")."""

    agent_id: str
    name: str
    type_name: str
    epoch: int
    pid: int
    state: str
    cpu: float = 0.0  # fraction of one core over the last window
    cpu_seconds: float = 0.0
    rss: int = 0
    msgs_in: dict[str, int] = field(default_factory=dict)
    bytes_in: dict[str, int] = field(default_factory=dict)
    msgs_out: dict[str, int] = field(default_factory=dict)
    bytes_out: dict[str, int] = field(default_factory=dict)
    buffered: int = 0  # messages held here until the agent starts
    mailbox: int = 0  # items waiting in the agent's mailbox (its last heartbeat)
    handled: int = 0
    uptime: float = 0.0
    spawn_seconds: float = 0.0  # spawn() call -> Hello


# ---------------------------------------------------------------------------------------------- instances

LIVE_STATES = ("spawning", "shell", "running", "freezing", "stopping")


class _ProtocolError(Exception):
    pass


class _Instance:
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

    @property
    def id(self) -> str:
        return self.spec.agent_id

    def count_in(self, env: Envelope) -> None:
        self.msgs_in[env.src] += 1
        self.bytes_in[env.src] += len(env.payload)


def _alive(proc: psutil.Process | None) -> bool:
    """Whether the process still runs (a zombie does not); False if unknown."""
    if proc is None:
        return False
    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


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
        self._agents: dict[str, _Instance] = {}
        self._by_pid: dict[int, _Instance] = {}
        self._unclaimed_exits: dict[int, str] = {}
        self._fork: ForkServer | None = None
        self._fork_lock = asyncio.Lock()
        self._monitor: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()  # every instance's task, also of ended ones still exiting
        self._closing = False
        self._started = False
        #: counters for the host's stats
        self.spawned = 0
        self.failed = 0
        self.event_errors = 0
        self.forkserver_restarts = 0
        self.over_limit = 0
        self.unchecked_configs = 0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Start the fork server (it knows every agent type by name and imports each at its first use) and the
        monitor."""
        if self._started:
            return
        self._started = True
        if self.workdir is not None:
            (self.workdir / "agents").mkdir(parents=True, exist_ok=True)
        await self._ensure_forkserver()
        self._monitor = asyncio.create_task(self._monitor_loop(), name="agent-monitor")

    async def _ensure_forkserver(self) -> ForkServer:
        async with self._fork_lock:
            if self._fork is not None and self._fork.alive:
                return self._fork
            if self._fork is not None:
                await self._fork.close()
                self.forkserver_restarts += 1
            fs = ForkServer(self._on_exit, on_dead=self._on_forkserver_dead, workdir=self.workdir,
                            preload=self.preload, preload_types=self.preload_types)
            await fs.start()
            for e in fs.load_errors:
                log_event(self.log, logging.WARNING, "agent_type_load_error", error=e)
            log_event(self.log, logging.INFO, "agent_forkserver_started", pid=fs.pid, types=fs.known(),
                      imported=sorted(fs.types), seconds=round(fs.start_seconds, 3))
            self._fork = fs
            return fs

    async def close(self) -> None:
        """Kill every agent process and stop the fork server; no events are reported from here on."""
        self._closing = True
        if self._monitor is not None:
            self._monitor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._monitor
        insts = list({*self._agents.values(), *self._by_pid.values()})
        for inst in insts:
            self._signal(inst, signal.SIGKILL)
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for inst in insts:
            if inst.chan is not None:
                inst.chan.close()
        if self._fork is not None:
            await self._fork.close()
        self._agents.clear()

    # ------------------------------------------------------------------ information

    def known_types(self) -> list[str]:
        """The names of every agent type this host can start, imported or not."""
        return self._fork.known() if self._fork is not None else []

    def imported_type(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's info if the fork server has imported it already (no request needed), else None."""
        return self._fork.types.get(type_name) if self._fork is not None else None

    async def type_info(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's cost, hardware, transfer penalty, recovery, config model and limits; the fork server imports
        a type registered by name only at this first request. None if the type is unknown here or its module fails
        to import (logged once as `agent_type_load_error`, and in `load_errors`)."""
        fs = self._fork
        if fs is None or (type_name not in fs.types and type_name not in fs.lazy):
            return None
        try:
            return await fs.describe(type_name)
        except SpawnError as e:
            log_event(self.log, logging.WARNING, "agent_type_load_error", type=type_name, error=str(e))
            return None

    @property
    def load_errors(self) -> list[str]:
        return list(self._fork.load_errors) if self._fork is not None else []

    @property
    def forkserver_pid(self) -> int | None:
        return self._fork.pid if self._fork is not None else None

    def agents(self) -> list[str]:
        """Ids of the agents with a live process here (spawning, shell, running, freezing, stopping)."""
        return [a for a, inst in self._agents.items() if inst.state in LIVE_STATES]

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

    def _get(self, agent_id: str) -> _Instance:
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
        info = await self.type_info(type_name)
        if info is None or not info.has_config:
            return ""
        try:
            fs = await self._ensure_forkserver()
            return await fs.validate(type_name, config, timeout=timeout)
        except (SpawnError, OSError) as e:
            self.unchecked_configs += 1
            log_event(self.log, logging.WARNING, "agent_config_unchecked", type=type_name, bytes=len(config),
                      error=str(e))
            return ""

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
        inst = _Instance(spec)
        self._agents[spec.agent_id] = inst
        host_sock, agent_sock = socket.socketpair()
        try:
            fs = await self._ensure_forkserver()
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
            self._by_pid[pid] = inst
            early = self._unclaimed_exits.pop(pid, None)
            if early is not None:
                inst.exit_reason = early
                inst.exited.set()
                self._by_pid.pop(pid, None)
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
                    await self._wait_exit(inst, 1.0)
                    why = f"the process ended before hello ({inst.exit_reason or 'status unknown'})"
                else:
                    why = f"expected hello, got {kind}"
                raise SpawnError(f"agent {spec.name} ({spec.type_name}) did not start: {why}")
        except BaseException as e:
            agent_sock.close()
            self._signal(inst, signal.SIGKILL)
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
        self._set_limits(inst, fs)
        inst.spawn_seconds = time.perf_counter() - t0
        self.spawned += 1
        inst.task = asyncio.create_task(self._serve(inst), name=f"agent-{spec.name}")
        self._tasks.add(inst.task)
        inst.task.add_done_callback(self._tasks.discard)
        log_event(self.log, logging.INFO, "agent_spawned", agent=spec.agent_id, name=spec.name, type=spec.type_name,
                  epoch=spec.epoch, pid=inst.pid, ms=round(inst.spawn_seconds * 1e3, 2))

    def _set_limits(self, inst: _Instance, fs: ForkServer) -> None:
        """The type's resource limits for this instance; the address-space cap on its process."""
        info = fs.types.get(inst.spec.type_name)
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

    def _over_limit(self, inst: _Instance, reason: str) -> None:
        """Kill an agent over one of its type's limits; Failed(reason) follows."""
        if inst.fail_reason is not None or inst.terminal:
            return
        inst.fail_reason = reason
        self.over_limit += 1
        log_event(self.log, logging.WARNING, "agent_over_limit", agent=inst.id, name=inst.spec.name,
                  type=inst.spec.type_name, pid=inst.pid, reason=reason)
        self._signal(inst, signal.SIGKILL)

    # ------------------------------------------------------------------ driving an agent

    def _send(self, inst: _Instance, msg: pb.HostToAgent) -> bool:
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

    def kill(self, agent_id: str) -> bool:
        """SIGKILL the agent's process; event Failed("killed by signal 9") follows. False if it has none."""
        inst = self._agents.get(agent_id)
        if inst is None:
            return False
        log_event(self.log, logging.INFO, "agent_kill", agent=agent_id, name=inst.spec.name, pid=inst.pid)
        return self._signal(inst, signal.SIGKILL)

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

    def _on_frame(self, inst: _Instance, msg: pb.AgentToHost) -> None:
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

    def _agent_log(self, inst: _Instance, m: pb.AgentToHost.Log) -> None:
        level = _LOG_LEVELS.get(m.level, logging.INFO)
        try:
            fields = json.loads(m.fields_json) if m.fields_json else {}
            if not isinstance(fields, dict):
                fields = {"fields": fields}
        except ValueError:
            fields = {"fields_json": m.fields_json[:1000]}
        fields.update(agent=inst.id, agent_name=inst.spec.name, agent_type=inst.spec.type_name)
        log_event(self.log, level, m.event or "agent_log", **fields)

    async def _serve(self, inst: _Instance) -> None:
        """Read the agent's frames until it ends; then report Frozen/Stopped (already done) or Failed."""
        assert inst.chan is not None
        try:
            while True:
                msg = await inst.chan.recv()
                if msg is None:
                    break
                inst.last_heard = time.monotonic()
                self._on_frame(inst, msg)
                if inst.terminal:
                    break
        except (ChannelError, _ProtocolError) as e:
            # a process that dies with unread input resets its socket: then the exit status is the reason
            if inst.fail_reason is None and not await self._wait_exit(inst, 0.2):
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
            await self._wait_gone(inst, 3.0)
            return
        # close first: an agent that ended (a fatal error) half-closes and waits for us to close
        # (haa.sdk.runner._linger), so that our writes never break the pipe before we read its last frames
        inst.chan.close()
        if inst.fail_reason is None and not await self._wait_exit(inst, 1.0):
            inst.fail_reason = "channel error: the agent closed its channel but did not exit"
        if inst.fail_reason is not None:
            self._signal(inst, signal.SIGKILL)
        await self._wait_gone(inst, 5.0)
        reason = inst.fail_reason or inst.exit_reason or "exited (status unknown)"
        if inst.agent_error and inst.fail_reason is None:
            reason = f"{reason} (agent error: {inst.agent_error})"
        inst.state = "failed"
        inst.terminal = True
        self._retire(inst)
        self.failed += 1
        log_event(self.log, logging.WARNING, "agent_failed", agent=inst.id, name=inst.spec.name,
                  type=inst.spec.type_name, pid=inst.pid, reason=reason)
        self._emit(Failed(inst.id, reason))

    def _retire(self, inst: _Instance) -> None:
        if self._agents.get(inst.id) is inst:
            del self._agents[inst.id]

    async def _wait_exit(self, inst: _Instance, timeout: float) -> bool:
        """Wait up to `timeout` for the process's exit; True once it is gone. The fork server reports exits;
        if the one that forked this agent died (its children die with it), psutil tells instead."""
        end = time.monotonic() + timeout
        while not inst.exited.is_set():
            orphan = inst.fork is not None and not inst.fork.alive
            if orphan and not _alive(inst.proc):
                self._set_exited(inst, "fork server died: exit status unknown")
                break
            left = end - time.monotonic()
            if left <= 0:
                return False
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(inst.exited.wait(), min(left, 0.05) if orphan else left)
        return True

    def _set_exited(self, inst: _Instance, reason: str) -> None:
        if inst.exit_reason is None:
            inst.exit_reason = reason
        if self._by_pid.get(inst.pid) is inst:
            del self._by_pid[inst.pid]
        inst.exited.set()

    async def _wait_gone(self, inst: _Instance, timeout: float) -> None:
        """Wait until the process is gone; SIGKILL it if it does not go in time."""
        if await self._wait_exit(inst, timeout):
            return
        self._signal(inst, signal.SIGKILL)
        if await self._wait_exit(inst, 1.0):
            return
        # the fork server is slow or stuck: ask the kernel
        if inst.proc is not None:
            with contextlib.suppress(psutil.Error):
                await asyncio.to_thread(inst.proc.wait, 2.0)
        self._set_exited(inst, "exit status unknown: the fork server did not report it")

    def _signal(self, inst: _Instance, sig: int) -> bool:
        """Signal the agent's process unless it is known to be gone."""
        if not inst.pid or inst.exited.is_set():
            return False
        try:
            if inst.proc is not None:
                inst.proc.send_signal(sig)  # psutil checks the pid was not reused
            else:
                os.kill(inst.pid, sig)
            return True
        except (psutil.Error, ProcessLookupError, PermissionError):
            return False

    def _on_exit(self, pid: int, reason: str) -> None:
        inst = self._by_pid.pop(pid, None)
        if inst is None:
            self._unclaimed_exits[pid] = reason  # exited before spawn() recorded its pid
            while len(self._unclaimed_exits) > 1000:
                self._unclaimed_exits.pop(next(iter(self._unclaimed_exits)))
            return
        inst.exit_reason = reason
        inst.exited.set()

    def _on_forkserver_dead(self, reason: str) -> None:
        if self._closing:
            return
        log_event(self.log, logging.ERROR, "agent_forkserver_died", reason=reason,
                  agents=len(self._agents))

    # ------------------------------------------------------------------ monitor: hangs and CPU

    async def _monitor_loop(self) -> None:
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
                for inst in self._agents.values():
                    inst.last_heard = max(inst.last_heard, now)
                continue
            for inst in list(self._agents.values()):
                if inst.state in ("spawning",) or inst.fail_reason is not None or inst.terminal:
                    continue
                silent = now - inst.last_heard
                if silent > self.hang_timeout:
                    inst.fail_reason = f"hung: no heartbeat for {silent:.1f} s"
                    log_event(self.log, logging.WARNING, "agent_hung", agent=inst.id, name=inst.spec.name,
                              pid=inst.pid, silent=round(silent, 3))
                    self._signal(inst, signal.SIGKILL)
            if now - last_cpu >= self.cpu_window:
                last_cpu = now
                last_mem = now
                self._sample_cpu(now)
            elif now - last_mem >= self.mem_period:
                last_mem = now
                self._sample_memory()

    def _sample_memory(self) -> None:
        """RSS of the agents with a memory limit, checked against it (between CPU samples)."""
        for inst in list(self._agents.values()):
            if inst.proc is None or not inst.memory_limit or inst.fail_reason is not None or inst.terminal:
                continue
            try:
                inst.rss = inst.proc.memory_info().rss
            except psutil.Error:
                continue
            self._check_memory(inst)

    def _check_memory(self, inst: _Instance) -> None:
        if inst.memory_limit and inst.rss > inst.memory_limit:
            self._over_limit(inst, f"over its memory limit of {inst.memory_limit // MIB} MiB "
                                   f"(RSS {inst.rss / MIB:.0f} MiB)")

    def _check_cpu(self, inst: _Instance, now: float, total: float) -> None:
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
                self._over_limit(inst, f"over its CPU limit of {inst.cpu_limit:g} cores "
                                       f"({share:.2f} over {span:.0f} s)")

    def _sample_cpu(self, now: float) -> None:
        for inst in list(self._agents.values()):
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
                self._check_memory(inst)
                self._check_cpu(inst, now, total)
