"""LocalHosts: a stand-in for the hosts' agent layer, wiring several AgentSupervisors in one process.

It is what the tests, the agent benchmark (haa.lab.experiments.agents) and quick experiments use to run real
agent processes without a cluster: each "host" is an `AgentSupervisor`; routing is a dict (agent id -> host) and a
direct `deliver` (so it is trivially FIFO); the DDB is a dict with prefix watchers; spawn_child, backups,
transfers and recoveries are done the simplest correct way on one machine. It shows the calls the real agent layer
(haa-hostd) makes, in the order it makes them:

* new agent: `spawn(spec)`, `start_fresh(id)`, wait Ready;
* transfer (Alg. 5-6): hold the messages addressed to it, `freeze(id)` on the old host, Frozen(state),
  `spawn(spec with a larger epoch)` on the new host, `thaw(id, state, held)`, then route to the new host;
* recovery (Alg. 7-8): Backup events keep the latest backup; after Failed, `spawn` + `recover(id, backup)`.

Messages to an agent that is being transferred are held (queue1/queue2 of the thesis collapse into one list
here); messages to a failed agent are dropped and counted (Alg. 8 is lossy); a request to an agent that does
not exist gets an error reply from the "host". Not a distributed system: no OAC, no allocation.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
from collections import defaultdict
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from haa.hostd.agentproc import (
    AgentEvent,
    AgentSupervisor,
    Backup,
    DdbGet,
    DdbPut,
    DdbUnwatch,
    DdbWatch,
    Envelope,
    Failed,
    Frozen,
    InstanceSpec,
    Ready,
    Sent,
    SpawnChild,
    Stopped,
)
from haa.sdk.base import child_name, new_agent_id, root_name


class LocalHosts:
    """Several supervisors ("hosts") with one routing table and one dict DDB (module docstring)."""

    def __init__(self, names: tuple[str, ...] = ("h1", "h2"), *,
                 placement: Callable[[str | None], str] | None = None, **supervisor_kwargs: Any) -> None:
        self.sups: dict[str, AgentSupervisor] = {
            n: AgentSupervisor(n, self._handler(n), **supervisor_kwargs) for n in names
        }
        self.placement = placement
        self.location: dict[str, str] = {}  # agent id -> host
        self.specs: dict[str, InstanceSpec] = {}
        self.held: dict[str, list[Envelope]] = {}  # agent id -> messages held during a transfer
        self.backups: dict[str, bytes] = {}
        self.frozen: dict[str, asyncio.Future[bytes]] = {}
        self.ready: dict[str, asyncio.Future[str]] = {}
        self.ended: dict[str, asyncio.Future[AgentEvent]] = {}
        self.children: defaultdict[str, int] = defaultdict(int)
        self.roots = itertools.count(1)
        self.ddb: dict[str, tuple[str, bytes]] = {}
        self.watches: dict[tuple[str, int], str] = {}  # (agent id, watch id) -> prefix
        self.replies: dict[int, asyncio.Future[Envelope]] = {}
        self.operator_inbox: list[Envelope] = []
        self.events: list[tuple[str, AgentEvent]] = []
        self.dropped: list[Envelope] = []
        self.failures: dict[str, str] = {}
        self._conv = itertools.count(1)
        self._tasks: set[asyncio.Task[Any]] = set()

    async def start(self) -> None:
        await asyncio.gather(*(s.start() for s in self.sups.values()))

    async def close(self) -> None:
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await asyncio.gather(*(s.close() for s in self.sups.values()))

    async def __aenter__(self) -> LocalHosts:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------------ agents

    def _new_waiters(self, agent_id: str) -> None:
        loop = asyncio.get_running_loop()
        self.ready[agent_id] = loop.create_future()
        self.ended[agent_id] = loop.create_future()

    async def create(self, type_name: str, config: bytes | dict[str, Any] = b"", host: str | None = None, *,
                     agent_id: str | None = None, parent: str | None = None, name: str | None = None,
                     wait_ready: bool = True, timeout: float = 10.0) -> str:
        """Spawn and start a new agent; returns its id (after Ready unless wait_ready is False)."""
        if isinstance(config, dict):
            config = json.dumps(config).encode()
        agent_id = agent_id or new_agent_id()
        if name is None:
            if parent is not None:
                self.children[parent] += 1
                name = child_name(self.specs[parent].name, self.children[parent])
            else:
                name = root_name(next(self.roots))
        if host is None:
            host = self.placement(parent) if self.placement else next(iter(self.sups))
        spec = InstanceSpec(agent_id, name, type_name, config, epoch=1, parent=parent)
        self.specs[agent_id] = spec
        self._new_waiters(agent_id)
        self.location[agent_id] = host
        try:
            await self.sups[host].spawn(spec)
        except BaseException:
            self.location.pop(agent_id, None)
            raise
        self.sups[host].start_fresh(agent_id)
        if wait_ready:
            await asyncio.wait_for(asyncio.shield(self.ready[agent_id]), timeout)
        return agent_id

    async def transfer(self, agent_id: str, to_host: str, *, timeout: float = 10.0) -> int:
        """Alg. 5-6 in miniature; returns how many messages were held and handed over with the state."""
        old = self.location[agent_id]
        self.held[agent_id] = []  # Alg. 5 l. 4: from now on messages for it are queued
        self.frozen[agent_id] = asyncio.get_running_loop().create_future()
        self.sups[old].freeze(agent_id)
        state = await asyncio.wait_for(self.frozen[agent_id], timeout)
        spec = replace(self.specs[agent_id], epoch=self.specs[agent_id].epoch + 1)
        self.specs[agent_id] = spec
        self._new_waiters(agent_id)
        await self.sups[to_host].spawn(spec)  # Alg. 6 l. 2
        held = self.held.pop(agent_id)
        self.sups[to_host].thaw(agent_id, state, held)  # Alg. 6 l. 10
        self.location[agent_id] = to_host  # Alg. 6 l. 11 (no await since the pop: no message can slip by)
        await asyncio.wait_for(asyncio.shield(self.ready[agent_id]), timeout)
        return len(held)

    async def recover(self, agent_id: str, host: str, *, timeout: float = 10.0) -> bytes | None:
        """Alg. 8 in miniature, for an agent that Failed: respawn it from its latest backup."""
        backup = self.backups.get(agent_id)
        spec = replace(self.specs[agent_id], epoch=self.specs[agent_id].epoch + 1)
        self.specs[agent_id] = spec
        self._new_waiters(agent_id)
        self.held[agent_id] = []
        await self.sups[host].spawn(spec)
        held = self.held.pop(agent_id)
        self.sups[host].recover(agent_id, backup, held)
        self.location[agent_id] = host
        await asyncio.wait_for(asyncio.shield(self.ready[agent_id]), timeout)
        return backup

    async def wait_end(self, agent_id: str, timeout: float = 10.0) -> AgentEvent:
        """The terminal event (Frozen, Stopped, Failed) of the agent's current instance."""
        return await asyncio.wait_for(asyncio.shield(self.ended[agent_id]), timeout)

    def pid(self, agent_id: str) -> int:
        return self.sups[self.location[agent_id]].pid(agent_id)

    # ------------------------------------------------------------------ operator messages

    def send(self, agent_id: str, payload: bytes) -> None:
        self._route(Envelope("", agent_id, payload))

    async def request(self, agent_id: str, payload: bytes | dict[str, Any], timeout: float = 10.0) -> bytes:
        """An operator request; returns the response payload, raises RuntimeError on an error reply."""
        if isinstance(payload, dict):
            payload = json.dumps(payload).encode()
        conv = next(self._conv)
        fut: asyncio.Future[Envelope] = asyncio.get_running_loop().create_future()
        self.replies[conv] = fut
        try:
            self._route(Envelope("", agent_id, payload, conv=conv))
            env = await asyncio.wait_for(fut, timeout)
        finally:
            self.replies.pop(conv, None)
        if env.error:
            raise RuntimeError(env.error)
        return env.payload

    async def request_json(self, agent_id: str, payload: bytes | dict[str, Any], timeout: float = 10.0) -> Any:
        return json.loads(await self.request(agent_id, payload, timeout))

    # ------------------------------------------------------------------ routing

    def _route(self, env: Envelope) -> None:
        dst = env.dst
        if dst == "":
            if env.reply and env.conv in self.replies:
                fut = self.replies[env.conv]
                if not fut.done():
                    fut.set_result(env)
            else:
                self.operator_inbox.append(env)
            return
        if dst in self.held:
            self.held[dst].append(env)
            return
        host = self.location.get(dst)
        if host is not None and self.sups[host].deliver(dst, env):
            return
        if env.conv and not env.reply:  # the host answers a request nobody can take
            self._route(Envelope("", env.src, b"", conv=env.conv, reply=True, error=f"no agent {dst} to answer"))
            return
        self.dropped.append(env)

    def _handler(self, host: str) -> Callable[[AgentEvent], None]:
        def on_event(ev: AgentEvent) -> None:
            self.events.append((host, ev))
            self._on_event(host, ev)

        return on_event

    def _spawn_task(self, coro: Any) -> None:
        t = asyncio.create_task(coro)
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    def _end(self, agent_id: str, ev: AgentEvent) -> None:
        fut = self.ended.get(agent_id)
        if fut is not None and not fut.done():
            fut.set_result(ev)
        for key in [k for k in self.watches if k[0] == agent_id]:
            del self.watches[key]

    def _on_event(self, host: str, ev: AgentEvent) -> None:
        sup = self.sups[host]
        a = ev.agent_id
        if isinstance(ev, Sent):
            self._route(ev.env)
        elif isinstance(ev, Ready):
            fut = self.ready.get(a)
            if fut is not None and not fut.done():
                fut.set_result(ev.how)
        elif isinstance(ev, Backup):
            self.backups[a] = ev.data
        elif isinstance(ev, Frozen):
            self._end(a, ev)
            fut_f = self.frozen.get(a)
            if fut_f is not None and not fut_f.done():
                fut_f.set_result(ev.state)
        elif isinstance(ev, Stopped | Failed):
            if isinstance(ev, Failed):
                self.failures[a] = ev.reason
                if self.frozen.get(a) is not None and not self.frozen[a].done():
                    self.frozen[a].set_exception(RuntimeError(f"agent failed while freezing: {ev.reason}"))
            if self.location.get(a) == host and a not in self.held:
                del self.location[a]
            self._end(a, ev)
        elif isinstance(ev, DdbGet):
            item = self.ddb.get(ev.key)
            if item is None:
                sup.answer(a, ev.req_id, True, b"", missing=True)
            else:
                sup.answer(a, ev.req_id, True, item[1])
        elif isinstance(ev, DdbPut):
            kind = "write" if ev.key in self.ddb else "add"
            self.ddb[ev.key] = (ev.type_name, ev.value)
            sup.answer(a, ev.req_id, True, b"")
            for (agent, wid), prefix in list(self.watches.items()):
                if ev.key.startswith(prefix) and agent in self.location:
                    self.sups[self.location[agent]].notify_watch(agent, wid, kind, ev.key, ev.value)
        elif isinstance(ev, DdbWatch):
            self.watches[(a, ev.watch_id)] = ev.prefix
        elif isinstance(ev, DdbUnwatch):
            self.watches.pop((a, ev.watch_id), None)
        elif isinstance(ev, SpawnChild):
            self._spawn_task(self._spawn_child(host, ev))

    async def _spawn_child(self, host: str, ev: SpawnChild) -> None:
        sup = self.sups[host]
        try:
            child_host = self.placement(ev.agent_id) if self.placement else host
            child = await self.create(ev.type_name, ev.config, child_host, parent=ev.agent_id)
        except Exception as e:
            sup.answer(ev.agent_id, ev.req_id, False, b"", f"{type(e).__name__}: {e}")
            return
        with contextlib.suppress(KeyError):
            self.sups[self.location[ev.agent_id]].answer(ev.agent_id, ev.req_id, True, child.encode())
