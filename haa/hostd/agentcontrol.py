"""The agent part of the control API (`haa.v1.HostControl`, proto/haa/pb/control.proto), and its client.

Served by `HostControlService` (haa.hostd.control), which inherits `AgentControl`; every call needs the
cluster token like the rest of the API. The service reaches the agent layer through the runtime
(`HostRuntime.agent_ops`, `feed`) and the agent processes through the `AgentDriver` the composition root
(haa.hostd.daemon.build_host) gives it. Operator requests go through the host's agent layer
(`haa.core.agents.agentnode.AgentNode`) and are committed to the replicated agent table:

* `AgentList`: the table as this host holds it (identical on every member), with what this host knows of
  the instances it runs (phase, CPU, pid), the allocation session ids and the paused flag.
* `AgentSpawn`: create an agent of a registered type (a new UUID; display name A<n>, or the parent's name
  plus a number); the allocation then places it. Defaults for cost, hardware, transfer penalty and recovery
  come from the type's class attributes.
* `AgentKill`: SIGKILL the agent's process — an agent failure, recovered by the group (only the host that
  runs it can; other hosts answer with the owner's name).
* `AgentRemove`: end an agent for good. `AgentMove`: allocate it to a host until the next session.
* `AgentSend`: an operator message to an agent (no sender agent). `AgentRequest`: an operator request (the
  agent's `on_request`), answered through the host that was asked, wherever the agent runs. A payload over
  `haa.sdk.channel.MAX_AGENT_MESSAGE` (4 MiB) is refused up front (ok=false and the reason; counted as
  `control_oversized`) instead of being accepted and then dropped by the agent's owner. A message enters the
  agent layer only when it has room on its way (the host's byte budgets, haa.hostd.budget): the call waits for
  it, at most `budget.OPERATOR_WAIT` and while this client's and this host's waiting messages are within their
  bounds; otherwise it is refused with `RESOURCE_EXHAUSTED` naming the bound, and nothing was sent.
* `Alloc`: status | pause | resume | run (pause/resume the periodic rebalancing; run starts a session).
* `AgentEvents`: the allocation timeline of this host (spawning, active, freezing, frozen, thawing, thawed,
  crashed, recovering, recovered, removed), kept entries first if asked, then live.
"""

from __future__ import annotations

import asyncio
import math
import uuid
from collections.abc import AsyncIterator, Iterator
from typing import TYPE_CHECKING, Any

import grpc
from grpc import aio

from haa.core.agents.agentnode import AgentNode
from haa.core.ddb.agenttable import MAX_CONFIG
from haa.core.inputs import CreateAgent, MoveAgent, OperatorSend, RemoveAgent, RunAllocation, SetPaused
from haa.hostd.outcomes import NotMembershipMode
from haa.pb import control_pb2 as cpb
from haa.rpcguard import MAX_DETAILS, client_address
from haa.sdk.channel import message_too_large

if TYPE_CHECKING:
    from haa.hostd.agentdriver import AgentDriver
    from haa.hostd.runtime import HostRuntime

MD_TOKEN = "x-haa-token"
#: the longest an `AgentRequest` waits for the agent's reply, s (a larger or infinite `timeout` is cut to it)
MAX_REQUEST_TIMEOUT = 3600.0


class AgentControl:
    """Mixin of `HostControlService`: the agent RPCs."""

    rt: HostRuntime
    agents: AgentDriver | None

    async def _agent_node(self, context: aio.ServicerContext) -> AgentNode:
        node = self.rt.node
        if not isinstance(node, AgentNode) or self.agents is None:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION,
                                f"{self.rt.name} does not run the agent layer (static mode or --no-agents)")
            raise NotMembershipMode("no agent layer")
        return node

    def _list(self, node: AgentNode) -> cpb.AgentListReply:
        t = node.table
        drv = self.agents
        stats = drv.sup.stats() if drv is not None else {}
        out = []
        members = node.members()
        placed = t.placements()
        for r in sorted(t, key=lambda x: x.name):
            loc = node.local.get(r.id)
            st = stats.get(r.id)
            out.append(
                cpb.AgentInfo(
                    id=r.id, name=r.name, type=r.type, parent=r.parent, status=r.status, owner=r.owner,
                    alloc=r.alloc, epoch=r.epoch, life=r.life, cpu=r.cpu,
                    local_phase=loc.phase if loc is not None else "",
                    local_cpu=st.cpu if st is not None else 0.0,
                    pid=st.pid if st is not None else 0,
                    has_backup=r.backup is not None, queued=len(r.queue1) + len(r.queue2), dropped=r.dropped,
                    recovery=r.spec.recovery, fail_reason=r.fail_reason, failures=r.failures,
                    msgs_in=sum(st.msgs_in.values()) if st is not None else 0,
                    msgs_out=sum(st.msgs_out.values()) if st is not None else 0,
                    bytes_in=sum(st.bytes_in.values()) if st is not None else 0,
                    bytes_out=sum(st.bytes_out.values()) if st is not None else 0,
                    waiting=t.waiting(r, members, placed),
                )
            )
        types = drv.sup.known_types() if drv is not None else []
        return cpb.AgentListReply(host=self.rt.name, agents=out, session=t.ses_id, finished_session=t.finished_ses,
                                  paused=t.paused, agent_types=types)

    async def AgentList(self, request: cpb.AgentListRequest, context: aio.ServicerContext) -> cpb.AgentListReply:
        node = await self._agent_node(context)
        return self._list(node)

    @staticmethod
    def _reply(done: Any) -> cpb.AgentOpReply:
        return cpb.AgentOpReply(ok=done.ok, id=done.agent, name=done.name, reason=done.reason)

    async def AgentSpawn(self, request: cpb.AgentSpawnRequest, context: aio.ServicerContext) -> cpb.AgentOpReply:
        node = await self._agent_node(context)
        # 0 asks for the type's cost and a negative penalty for the type's penalty (control.proto); anything else
        # that is not a number (NaN, a negative cost, an infinity) is refused, not silently replaced by a default
        if not (math.isfinite(request.cost) and request.cost >= 0):
            return cpb.AgentOpReply(ok=False, reason=f"cost {request.cost!r}: must be a finite number >= 0 "
                                                     "(0: the type's declared cost)")
        if math.isnan(request.transfer_penalty) or math.isinf(request.transfer_penalty):
            return cpb.AgentOpReply(ok=False, reason=f"transfer_penalty {request.transfer_penalty!r}: must be a "
                                                     "finite number (negative: the type's)")
        drv = self.agents
        info = await drv.sup.type_info(request.type) if drv is not None else None
        if info is None:
            return cpb.AgentOpReply(ok=False, reason=drv.unknown_type(request.type) if drv is not None
                                    else f"unknown agent type {request.type!r} (this host runs no agents)")
        parent = ""
        if request.parent:
            r = node.table.resolve(request.parent)
            if r is None:
                return cpb.AgentOpReply(ok=False, reason=f"unknown parent {request.parent!r}")
            parent = r.id
        if drv is not None and len(request.config) <= MAX_CONFIG:  # larger: refused by the CreateAgent input
            # a config the type's model refuses would commit an agent that can never start (issue 13, defect 3):
            # the fork server, which has the agent classes, checks it before anything is proposed
            why = await drv.sup.validate_config(request.type, request.config)
            if why:
                return cpb.AgentOpReply(ok=False, reason=f"{request.type}: {why}")
        agent_id = str(uuid.uuid4())
        done = await self.rt.agent_ops.agent_op(lambda req: CreateAgent(
            agent_id, request.type, request.config,
            parent=parent,
            cost=request.cost if request.cost > 0 else info.cost,
            hardware=tuple(request.hardware) or tuple(info.hardware),
            transfer_penalty=request.transfer_penalty if request.transfer_penalty >= 0 else info.transfer_penalty,
            recovery=request.recovery or info.recovery or "backup",
            max_per_host=info.max_per_host,  # declared by the type (AgentBase.MAX_PER_HOST)
            req=req,
        ))
        return self._reply(done)

    async def AgentKill(self, request: cpb.AgentRef, context: aio.ServicerContext) -> cpb.AgentOpReply:
        node = await self._agent_node(context)
        r = node.table.resolve(request.ref)
        if r is None:
            return cpb.AgentOpReply(ok=False, reason=f"unknown agent {request.ref!r}")
        drv = self.agents
        if drv is None or r.id not in drv.sup.agents():
            return cpb.AgentOpReply(ok=False, id=r.id, name=r.name, owner=r.owner,
                                    reason=f"not running here; its owner is {r.owner or 'nobody'}")
        loc = node.local.get(r.id)
        if loc is not None and loc.phase in ("claiming", "thawing", "recovering"):
            # its process is still a shell (the agent is not in it yet): killed, it would only be replaced
            # (recovery.py, "shell_respawn") and no recovery would follow
            return cpb.AgentOpReply(ok=False, id=r.id, name=r.name,
                                    reason=f"still starting on {self.rt.name} ({loc.phase}): kill it once it is active")
        drv.sup.kill(r.id)
        return cpb.AgentOpReply(ok=True, id=r.id, name=r.name)

    async def AgentRemove(self, request: cpb.AgentRef, context: aio.ServicerContext) -> cpb.AgentOpReply:
        await self._agent_node(context)
        return self._reply(await self.rt.agent_ops.agent_op(lambda req: RemoveAgent(request.ref, req)))

    async def AgentMove(self, request: cpb.AgentMoveRequest, context: aio.ServicerContext) -> cpb.AgentOpReply:
        await self._agent_node(context)
        return self._reply(await self.rt.agent_ops.agent_op(lambda req: MoveAgent(request.ref, request.host, req)))

    async def AgentSend(self, request: cpb.AgentSendRequest, context: aio.ServicerContext) -> cpb.AgentOpReply:
        node = await self._agent_node(context)
        size = len(request.payload)  # (each read of a bytes field copies it: 4 MiB, on the event loop)
        too_large = message_too_large(size)
        if too_large:
            self.rt.counters["control_oversized"] += 1
            return cpb.AgentOpReply(ok=False, reason=too_large)
        if node.table.resolve(request.ref) is None:
            return cpb.AgentOpReply(ok=False, reason=f"unknown agent {request.ref!r}")
        if not await self._room(request.ref, size, context, "AgentSend"):
            return cpb.AgentOpReply()
        self.rt.feed(node.step, OperatorSend(request.ref, request.payload))
        return cpb.AgentOpReply(ok=True)

    async def _room(self, ref: str, size: int, context: aio.ServicerContext, method: str) -> bool:
        """Wait until a message of `size` bytes to `ref` has room on its way from this host (haa.hostd.budget):
        True. False: the call's status is set to RESOURCE_EXHAUSTED naming the bound (the caller returns an empty
        reply, which gRPC does not send). Not `context.abort`: its exception's traceback holds the handler frames,
        and with them the request (raw and decoded: twice its size) until the garbage collector's next full pass —
        refused 4 MiB sends retried by a client took a host to 798-972 MiB that way."""
        why = await self.rt.budget.operator(ref, size, client_address(context.peer()), context.time_remaining())
        if not why:
            return True
        context.set_code(grpc.StatusCode.RESOURCE_EXHAUSTED)
        context.set_details(f"{method} to {ref[:64]}: {why}"[:MAX_DETAILS])
        return False

    async def AgentRequest(self, request: cpb.AgentSendRequest,
                           context: aio.ServicerContext) -> cpb.AgentRequestReply:
        await self._agent_node(context)
        size = len(request.payload)
        too_large = message_too_large(size)
        if too_large:
            self.rt.counters["control_oversized"] += 1
            return cpb.AgentRequestReply(ok=False, error=too_large)
        timeout = min(request.timeout, MAX_REQUEST_TIMEOUT) if request.timeout > 0 else 5.0  # NaN: 5 s
        if self.rt.agent_ops.agent_node().table.resolve(request.ref) is not None and \
                not await self._room(request.ref, size, context, "AgentRequest"):
            return cpb.AgentRequestReply()
        try:
            rep = await self.rt.agent_ops.agent_request(request.ref, request.payload, timeout=timeout)
        except LookupError as e:
            return cpb.AgentRequestReply(ok=False, error=str(e).strip("'\""))
        except TimeoutError:
            return cpb.AgentRequestReply(ok=False, error=f"no reply within {timeout:g} s")
        return cpb.AgentRequestReply(ok=not rep.error, payload=rep.payload, error=rep.error)

    async def Alloc(self, request: cpb.AllocRequest, context: aio.ServicerContext) -> cpb.AgentListReply:
        node = await self._agent_node(context)
        a = request.action or "status"
        if a in ("pause", "resume"):
            done = await self.rt.agent_ops.agent_op(lambda req: SetPaused(a == "pause", req))
            if not done.ok:
                await context.abort(grpc.StatusCode.UNAVAILABLE, done.reason)
        elif a == "run":
            self.rt.feed(node.step, RunAllocation())
        elif a != "status":
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"unknown action {a!r} (status|pause|resume|run)")
        return self._list(node)

    async def AgentEvents(self, request: cpb.AgentEventsRequest,
                          context: aio.ServicerContext) -> AsyncIterator[cpb.AgentEvent]:
        await self._agent_node(context)
        drv = self.agents
        assert drv is not None
        q: asyncio.Queue[dict[str, Any]] = asyncio.Queue(maxsize=10_000)

        def push(item: dict[str, Any]) -> None:
            if not q.full():
                q.put_nowait(item)

        history = list(drv.timeline) if request.history else []
        drv.subscribers.add(push)
        task = asyncio.current_task()
        if task is not None:
            self.rt.stream_tasks.add(task)
        try:
            for item in history:
                yield _event(item)
            while True:
                yield _event(await q.get())
        except asyncio.CancelledError:
            if not self.rt.stopping:
                raise
        finally:
            drv.subscribers.discard(push)
            if task is not None:
                self.rt.stream_tasks.discard(task)


def _event(item: dict[str, Any]) -> cpb.AgentEvent:
    return cpb.AgentEvent(time=item["t"], agent=item["agent"], name=item["name"], event=item["event"],
                          host=item["host"], detail=item["detail"])


class AgentClientMixin:
    """Blocking client calls of the agent RPCs (mixed into `haa.hostd.control.ControlClient`)."""

    _stub: Any
    _md: tuple[tuple[str, str], ...]
    timeout: float

    def agent_list(self) -> cpb.AgentListReply:
        return self._stub.AgentList(cpb.AgentListRequest(), metadata=self._md, timeout=self.timeout)

    def agent_spawn(self, type_name: str, config: bytes = b"", parent: str = "", recovery: str = "",
                    hardware: tuple[str, ...] = (), timeout: float = 15.0) -> cpb.AgentOpReply:
        req = cpb.AgentSpawnRequest(type=type_name, config=config, parent=parent, recovery=recovery,
                                    hardware=list(hardware), transfer_penalty=-1.0)
        return self._stub.AgentSpawn(req, metadata=self._md, timeout=timeout)

    def agent_kill(self, ref: str) -> cpb.AgentOpReply:
        return self._stub.AgentKill(cpb.AgentRef(ref=ref), metadata=self._md, timeout=self.timeout)

    def agent_remove(self, ref: str, timeout: float = 15.0) -> cpb.AgentOpReply:
        return self._stub.AgentRemove(cpb.AgentRef(ref=ref), metadata=self._md, timeout=timeout)

    def agent_move(self, ref: str, host: str, timeout: float = 15.0) -> cpb.AgentOpReply:
        return self._stub.AgentMove(cpb.AgentMoveRequest(ref=ref, host=host), metadata=self._md, timeout=timeout)

    def agent_send(self, ref: str, payload: bytes) -> cpb.AgentOpReply:
        return self._stub.AgentSend(cpb.AgentSendRequest(ref=ref, payload=payload), metadata=self._md,
                                    timeout=self.timeout)

    def agent_request(self, ref: str, payload: bytes, timeout: float = 5.0) -> cpb.AgentRequestReply:
        """An operator request to an agent (its `on_request`); the reply, or ok=False with the error."""
        req = cpb.AgentSendRequest(ref=ref, payload=payload, timeout=timeout)
        return self._stub.AgentRequest(req, metadata=self._md, timeout=timeout + 5.0)

    def alloc(self, action: str = "status", timeout: float = 15.0) -> cpb.AgentListReply:
        return self._stub.Alloc(cpb.AllocRequest(action=action), metadata=self._md, timeout=timeout)

    def agent_events(self, history: bool = True, timeout: float | None = None) -> Iterator[cpb.AgentEvent]:
        return self._stub.AgentEvents(cpb.AgentEventsRequest(history=history), metadata=self._md, timeout=timeout)
