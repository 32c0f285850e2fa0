"""AgentDriver: carries out the agent layer's commands on real agent processes, and feeds their events back.

The sans-I/O `AgentNode` (haa.core.agents.agentnode) says what should happen to this host's agent instances
(`haa.core.agentio` commands); `AgentSupervisor` (haa.hostd.agentproc) runs OS processes. The driver joins
the two. The daemon's composition root (haa.hostd.daemon.build_host) builds it and hands it to the
`HostRuntime` as its agent backend (the `AgentBackend` protocol of haa.hostd.agentops); at `start` the runtime
gives it an `AgentHost` — the runtime's `AgentOps` — which is everything the driver reaches of its host: node
inputs (events, undeliverable messages, costs), the local replica and agent table, and DDB writes. The driver
never imports or reads the runtime itself:

* SpawnShell -> `supervisor.spawn` (a task; ShellReady when the process said hello, Failed if it could not
  start); StartAgent -> start_fresh / thaw / recover with the messages; DeliverAgent -> deliver (a message
  the process no longer takes goes back to the node, an `Undeliverable` input); FreezeAgent -> freeze;
  KillAgent -> kill; AnswerAgent -> answer;
* supervisor events -> `InstanceEvent` inputs of the `AgentNode` (with the instance's epoch: the supervisor runs one
  instance per agent id here); an agent's `spawn_child` of an unknown type, or with a config the child
  type's model refuses (`AgentSupervisor.validate_config`, asked of the fork server), is answered with the
  error at once instead of being committed as an agent that can never start; and the agents' DDB requests,
  served from the local replica (reads, watches) or through the group (writes — DdbPut, and DdbWrite, a batch
  of ops checked with `ddb.check_op` before anything is proposed — through the host's writes (haa.hostd.writes), fenced
  by the instance's epoch);
* every `stats_period`, the measured CPU of each agent and the bytes exchanged between agent pairs go to
  a `ReportCosts` input, which commits the significant changes for the allocation (Alg. 4 ll. 22-23).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
import uuid
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any, Protocol, assert_never

from haa.core import agentio as io
from haa.core.ddb import ops as ddbmod
from haa.core.ddb.agenttable import MAX_CONFIG, AgentTable
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import MAX_KEY
from haa.hostd import agentproc as ap
from haa.hostd.agentops import AgentCommand
from haa.hostd.logs import log_event
from haa.hostd.outcomes import DdbWriteResult
from haa.pb import agent_pb2
from haa.pb import agenttx_pb2 as apb

#: most keys one DdbScan answers, and most value bytes (the answer must fit one channel frame, 16 MiB)
SCAN_LIMIT = 10_000
SCAN_MAX_BYTES = 8 * 1024 * 1024

log = logging.getLogger("haa.hostd.agents")

#: timeline entries kept for `AgentEvents` subscribers that connect late
TIMELINE_KEEP = 2000


def to_env(m: apb.RoutedMsg) -> ap.Envelope:
    return ap.Envelope(src=m.src, dst=m.dst, payload=m.payload, conv=m.conv, reply=m.reply, error=m.error)


class AgentHost(Protocol):
    """What the driver reaches of the host it runs in (the runtime's `haa.hostd.agentops.AgentOps`)."""

    @property
    def name(self) -> str: ...

    @property
    def counters(self) -> Counter[str]: ...

    def on_agent_event(self, ev: io.AgentEvent) -> None: ...

    def undeliverable(self, agent: str, epoch: int, msg: apb.RoutedMsg) -> None: ...

    def report_costs(self, cpu: dict[str, float], rates: dict[tuple[str, str], float]) -> None: ...

    def send_room(self, dst: str, size: int, gone: Callable[[], bool]) -> Awaitable[None] | None: ...

    def local_replica(self) -> Ddb | None: ...

    def agent_table(self) -> AgentTable | None: ...

    async def ddb_write(self, ops: list[Any], atomic: bool = False) -> DdbWriteResult: ...


class AgentDriver:
    """See the module docstring. `host` is given at `start`."""

    host: AgentHost

    def __init__(self, name: str, workdir: Path | None, stats_period: float = 2.0, hang_timeout: float = 3.0,
                 preload_types: Sequence[str] = ()) -> None:
        self.name = name
        self.sup = ap.AgentSupervisor(name, self._on_event, workdir=workdir, hang_timeout=hang_timeout,
                                      preload_types=preload_types)
        self.epochs: dict[str, int] = {}  # agent id -> epoch of the instance the supervisor runs here
        self.stats_period = stats_period
        self._tasks: set[asyncio.Task[Any]] = set()
        self._stats_task: asyncio.Task[None] | None = None
        self._watches: dict[tuple[str, int], str] = {}  # (agent, watch id) -> key prefix
        self._ddb_ref: object | None = None
        self._ddb_watch = 0
        self._last_bytes: dict[tuple[str, str], int] = {}
        self._last_stats = 0.0
        self.timeline: deque[dict[str, Any]] = deque(maxlen=TIMELINE_KEEP)
        self.subscribers: set[Callable[[dict[str, Any]], None]] = set()
        self.started = False

    # ------------------------------------------------------------------ lifecycle

    async def start(self, host: AgentHost) -> None:
        self.host = host
        self.sup.send_room = host.send_room  # back-pressure on what the agents send (haa.hostd.budget)
        await self.sup.start()
        self.started = True
        self._stats_task = asyncio.create_task(self._stats_loop(), name="agent-stats")

    async def close(self) -> None:
        if self._stats_task is not None:
            self._stats_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._stats_task
        for t in list(self._tasks):
            t.cancel()
        await self.sup.close()
        self.epochs.clear()

    def backlog(self) -> int:
        """Bytes this host gave its agents that they have not read yet (`AgentSupervisor.backlog`)."""
        return self.sup.backlog()

    def kill_all(self, reason: str) -> None:
        """A new incarnation of this host: the old one's agents are not ours any more."""
        for agent in list(self.sup.agents()):
            self.sup.kill(agent)
        self.epochs.clear()
        log_event(log, logging.WARNING, "agents_killed", reason=reason)

    # ------------------------------------------------------------------ commands from the node

    def command(self, c: AgentCommand) -> None:
        sup = self.sup
        try:
            match c:
                case io.SpawnShell():
                    self._spawn(c)
                case io.StartAgent():
                    msgs = [to_env(m) for m in c.messages]
                    if c.mode == "fresh":
                        for e in msgs:  # messages sent to the agent before it first started
                            sup.deliver(c.agent, e)
                        sup.start_fresh(c.agent)
                    elif c.mode == "thaw":
                        sup.thaw(c.agent, c.state or b"", msgs)
                    else:
                        sup.recover(c.agent, c.state, msgs)
                case io.DeliverAgent():
                    if not sup.deliver(c.agent, to_env(c.msg)):
                        self.host.undeliverable(c.agent, c.epoch, c.msg)
                case io.FreezeAgent():
                    if sup.state(c.agent) == "running":
                        sup.freeze(c.agent)
                case io.KillAgent():
                    if self.epochs.get(c.agent) == c.epoch:
                        sup.kill(c.agent, c.reason)
                case io.AnswerAgent():
                    sup.answer(c.agent, c.req, c.ok, c.value.encode(), c.error)
                case _:
                    assert_never(c)
        except (KeyError, RuntimeError, ValueError) as e:
            log_event(log, logging.WARNING, "agent_command_failed", command=type(c).__name__, agent=c.agent,
                      error=str(e))

    def _spawn(self, c: io.SpawnShell) -> None:
        spec = ap.InstanceSpec(c.agent, c.name, c.type, c.config, c.epoch, c.parent or None)
        self.epochs[c.agent] = c.epoch

        async def run() -> None:
            try:
                await self.sup.spawn(spec)
            except (ap.SpawnError, ValueError) as e:
                if self.epochs.get(c.agent) == c.epoch:
                    self.epochs.pop(c.agent, None)
                self._feed_event(io.Failed(c.agent, c.epoch, f"spawn failed: {e}"))
                return
            self._feed_event(io.ShellReady(c.agent, c.epoch))

        self._task(run(), f"spawn-{c.name}")

    def unknown_type(self, type_name: str) -> str:
        """The refusal of a spawn of a type this host cannot start."""
        known = ", ".join(self.sup.known_types())
        for e in self.sup.load_errors:
            if repr(type_name) in e:
                return f"agent type {type_name[:64]!r} failed to load: {e}"
        return f"unknown agent type {type_name[:64]!r} (registered: {known})"

    def _spawn_child(self, agent: str, epoch: int, ev: ap.SpawnChild) -> None:
        """Check the child's type and config (module docstring), then pass the request to the node. A type the
        fork server has imported is checked at once (the request keeps its place among the agent's events); one
        it knows by name only is imported first."""
        info = self.sup.imported_type(ev.type_name)
        if info is not None:
            self._checked_child(agent, epoch, ev, info)
            return

        async def describe() -> None:
            info = await self.sup.type_info(ev.type_name)
            if info is None:
                self.sup.answer(agent, ev.req_id, False, b"", self.unknown_type(ev.type_name))
            else:
                self._checked_child(agent, epoch, ev, info)

        self._task(describe(), "agent-spawn-child-type")

    def _checked_child(self, agent: str, epoch: int, ev: ap.SpawnChild, info: agent_pb2.AgentTypeInfo) -> None:
        child = io.SpawnChild(agent, epoch, ev.req_id, ev.type_name, ev.config, str(uuid.uuid4()), info.max_per_host,
                              ev.key)
        if not info.has_config or len(ev.config) > MAX_CONFIG:  # too large: the node refuses it (check_create)
            self._feed_event(child)
            return

        async def run() -> None:
            why = await self.sup.validate_config(ev.type_name, ev.config)
            if why:
                self.sup.answer(agent, ev.req_id, False, b"", f"{ev.type_name}: {why}")
                return
            self._feed_event(child)

        self._task(run(), "agent-spawn-child-check")

    def _task(self, coro: Coroutine[Any, Any, None], name: str) -> None:
        task = asyncio.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _feed_event(self, ev: io.AgentEvent) -> None:
        self.host.on_agent_event(ev)

    # ------------------------------------------------------------------ events of the processes

    def _on_event(self, ev: ap.AgentEvent) -> None:
        a = ev.agent_id
        epoch = self.epochs.get(a)
        if epoch is None:
            return
        match ev:
            case ap.Sent():
                e = ev.env
                self._feed_event(io.Sent(a, epoch, e.dst, e.payload, e.conv, e.reply, e.error))
            case ap.Backup():
                self._feed_event(io.BackupMade(a, epoch, ev.data))
            case ap.Frozen():
                self.epochs.pop(a, None)
                self._feed_event(io.Frozen(a, epoch, ev.state))
            case ap.Failed():
                self.epochs.pop(a, None)
                self._feed_event(io.Failed(a, epoch, ev.reason))
            case ap.Stopped():
                self.epochs.pop(a, None)
                self._feed_event(io.Stopped(a, epoch))
            case ap.SpawnChild():
                self._spawn_child(a, epoch, ev)
            case ap.DdbGet():
                self._ddb_get(ev)
            case ap.DdbPut():
                self._ddb_put(ev)
            case ap.DdbScan():
                self._ddb_scan(ev)
            case ap.DdbWrite():
                self._ddb_write(ev)
            case ap.DdbWatch():
                self._watches[(a, ev.watch_id)] = ev.prefix
                self._ensure_ddb_watch()
            case ap.DdbUnwatch():
                self._watches.pop((a, ev.watch_id), None)
            case ap.Ready():
                pass  # the supervisor's own (the hello of a process); spawn() returns on it
            case _:
                assert_never(ev)

    # ------------------------------------------------------------------ DDB for agents

    def _replica(self) -> Ddb | None:
        return self.host.local_replica()

    def _ddb_get(self, ev: ap.DdbGet) -> None:
        ddb = self._replica()
        obj = ddb.get(ev.key) if ddb is not None else None
        if obj is None:
            self.sup.answer(ev.agent_id, ev.req_id, True, b"", missing=True)
        else:
            self.sup.answer(ev.agent_id, ev.req_id, True, obj.data)

    def _ddb_scan(self, ev: ap.DdbScan) -> None:
        """The objects under a prefix from the local replica, in key order: at most `limit` keys (default and
        bound SCAN_LIMIT) and SCAN_MAX_BYTES of values (the answer must fit one channel frame)."""
        ddb = self._replica()
        limit = min(ev.limit or SCAN_LIMIT, SCAN_LIMIT)
        keys: list[str] = []
        values: list[bytes] = []
        size, truncated = 0, False
        if ddb is not None and len(ev.prefix) <= MAX_KEY:
            for obj in ddb.items(ev.prefix):
                data = obj.data
                if len(keys) >= limit or size + len(data) + len(obj.key) > SCAN_MAX_BYTES:
                    truncated = True
                    break
                keys.append(obj.key)
                values.append(data)
                size += len(data) + len(obj.key)
        self.sup.answer(ev.agent_id, ev.req_id, True, b"", keys=keys, values=values, truncated=truncated)

    def _fenced(self, agent: str) -> str:
        """'' if this host's instance of `agent` holds the agent's current epoch in the table (its outputs are
        accepted), else the reason: an instance displaced by a newer one elsewhere writes nothing (issue 13)."""
        table = self.host.agent_table()
        r = table.get(agent) if table is not None else None
        epoch = self.epochs.get(agent)
        if r is None or r.owner != self.host.name or epoch is None or r.epoch != epoch:
            where = f"epoch {r.epoch} on {r.owner or 'nobody'}" if r is not None else "nothing"
            return f"stale instance (epoch {epoch}): the table gives {agent[:8]} {where}"
        return ""

    def _ddb_put(self, ev: ap.DdbPut) -> None:
        async def run() -> None:
            why = self._fenced(ev.agent_id)
            if why:
                self.host.counters["agent_ddb_put_fenced"] += 1
                self.sup.answer(ev.agent_id, ev.req_id, False, b"", why)
                return
            try:
                op = ddbmod.put(ev.key, ev.type_name, _decode_value(ev.type_name, ev.value))
                res = await self.host.ddb_write([op])
                bad = [r.reason for r in res.results if not r.ok]
                self.sup.answer(ev.agent_id, ev.req_id, not bad, b"", "; ".join(bad))
            except Exception as e:
                self.sup.answer(ev.agent_id, ev.req_id, False, b"", f"{type(e).__name__}: {e}")

        self._task(run(), "agent-ddb-put")

    def _ddb_write(self, ev: ap.DdbWrite) -> None:
        """Like `_ddb_put` (fencing, the host's writes), for a batch of ops; every op is checked first (bad key,
        unknown or unwritable type, an oversized value, item or log append: an error answer, nothing proposed).
        The answer of a committed batch carries one reason per op ("" = it succeeded)."""
        why = "" if ev.ops else "empty batch"
        for i, op in enumerate(ev.ops):
            bad = ddbmod.check_op(op)  # type: ignore[arg-type]
            if bad:
                why = f"op {i}: {bad}"
                break
        if why:
            self.host.counters["agent_ddb_write_refused"] += 1
            self.sup.answer(ev.agent_id, ev.req_id, False, b"", why)
            return

        async def run() -> None:
            why = self._fenced(ev.agent_id)
            if why:
                self.host.counters["agent_ddb_write_fenced"] += 1
                self.sup.answer(ev.agent_id, ev.req_id, False, b"", why)
                return
            try:
                res = await self.host.ddb_write(list(ev.ops), ev.atomic)
                errors = ["" if r.ok else (r.reason or "failed") for r in res.results]
                self.sup.answer(ev.agent_id, ev.req_id, True, b"", op_errors=errors)
            except Exception as e:
                self.sup.answer(ev.agent_id, ev.req_id, False, b"", f"{type(e).__name__}: {e}")

        self._task(run(), "agent-ddb-write")

    def _ensure_ddb_watch(self) -> None:
        ddb = self._replica()
        if ddb is None or ddb is self._ddb_ref:
            return
        self._ddb_ref = ddb
        self._ddb_watch = ddb.watch(self._on_ddb_event)

    def check_replica(self) -> None:
        """The replica object changed (a joiner's snapshot, a new incarnation): watch the new one."""
        if self._watches:
            self._ensure_ddb_watch()

    def _on_ddb_event(self, ev: Any) -> None:
        value: bytes | None = None
        encoded = False
        for (agent, wid), prefix in list(self._watches.items()):
            if ev.key.startswith(prefix):
                if not encoded:  # once per event, for every watch it matches
                    encoded = True
                    if ev.kind in ("add", "write") and ev.value is not None:
                        with contextlib.suppress(Exception):
                            value = ddbmod.encode_value(ev.type_name, ev.value)
                    elif ev.kind == "append" and ev.type_name == "log":
                        value = ev.value  # the item; its index goes with it
                self.sup.notify_watch(agent, wid, ev.kind, ev.key, value, ev.index)

    # ------------------------------------------------------------------ measurements

    async def _stats_loop(self) -> None:
        while True:
            await asyncio.sleep(self.stats_period)
            try:
                self._report()
            except Exception:
                log.exception("agent stats failed")

    def _report(self) -> None:
        now = time.monotonic()
        dt = now - self._last_stats if self._last_stats else self.stats_period
        self._last_stats = now
        cpu: dict[str, float] = {}
        pair_bytes: dict[tuple[str, str], int] = {}
        for agent, st in self.sup.stats().items():
            cpu[agent] = st.cpu
            for peer, b in st.bytes_out.items():
                if peer:
                    key = (agent, peer) if agent < peer else (peer, agent)
                    pair_bytes[key] = pair_bytes.get(key, 0) + b
        rates: dict[tuple[str, str], float] = {}
        for key, total in pair_bytes.items():
            prev = self._last_bytes.get(key, 0)
            rates[key] = max(0.0, (total - prev) / dt)
        self._last_bytes = pair_bytes
        self.host.report_costs(cpu, rates)

    # ------------------------------------------------------------------ the timeline

    def on_timeline(self, e: io.AgentTimeline) -> None:
        item = {"t": time.time(), "agent": e.agent, "name": e.name, "event": e.event, "host": e.host,
                "detail": e.detail}
        self.timeline.append(item)
        log_event(log, logging.INFO, "agent_" + e.event, agent=e.agent, name=e.name, detail=e.detail)
        for sub in list(self.subscribers):
            sub(item)

    def status(self) -> dict[str, Any]:
        return {
            "agents_running": len(self.sup.agents()),
            "spawned": self.sup.spawned,
            "failed": self.sup.failed,
            "forkserver_pid": self.sup.forkserver_pid or 0,
        }


def _decode_value(type_name: str, value: bytes) -> Any:
    if type_name == "json":
        return json.loads(value)
    return value
