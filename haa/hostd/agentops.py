"""AgentOps: the runtime's side of the agent layer — operator operations in, the agent driver's inputs.

The sans-I/O `AgentNode` (thesis Alg. 4-8) runs inside the runtime; the agent processes are run by a
*backend* the composition root (haa.hostd.daemon.build_host) gives the runtime: `haa.hostd.agentdriver.
AgentDriver` in the daemon. The runtime knows the backend only as the `AgentBackend` protocol below (what it
calls: start with its host port, the agent commands the node emits, the timeline, replica changes,
`kill_all` on a new incarnation), so it imports nothing of the driver; the driver knows the runtime only as
the `AgentOps` object it gets at `start` (its `AgentHost` protocol), so it never reads the runtime back.

`AgentOps` serves two sides:

* operators (the control API, haa.hostd.agentcontrol): `agent_op` runs an operator request of the node
  (create, remove, move, pause) and waits for its `AgentOpDone`; `agent_request` sends an operator request
  to an agent and waits for its `OperatorReply`; `feed` runs any other node input (send, run allocation);
* the backend: `on_agent_event` (what an instance did), `undeliverable`, `report_costs`, the local replica
  and agent table (reads, fencing), `ddb_write` (the agents' writes, through haa.hostd.writes) and `send_room`
  (whether an agent's message has room on its way: the host's byte budgets, haa.hostd.budget).

Request numbers come from the runtime's one sequence (`next_req`, shared with the writes).
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Awaitable, Callable, Hashable
from typing import TYPE_CHECKING, Any, Protocol

from haa.core import agentio as io
from haa.core.agents.agentnode import AgentNode
from haa.core.ddb.agenttable import AgentTable
from haa.core.ddb.ddb import Ddb
from haa.core.inputs import AgentLayerInput, InstanceEvent, OperatorSend, ReportCosts, Undeliverable
from haa.core.membership.membership import MembershipNode
from haa.hostd.outcomes import DdbWriteResult, NotMembershipMode
from haa.pb import agenttx_pb2 as apb

if TYPE_CHECKING:
    from haa.hostd.budget import MessageBudget

#: the commands `AgentNode` gives whatever runs its agent instances (haa.core.agentio)
AgentCommand = io.SpawnShell | io.StartAgent | io.DeliverAgent | io.FreezeAgent | io.KillAgent | io.AnswerAgent


class AgentBackend(Protocol):
    """What the runtime needs of whatever runs its agent processes (haa.hostd.agentdriver.AgentDriver)."""

    async def start(self, host: AgentOps) -> None: ...

    async def close(self) -> None: ...

    def command(self, c: AgentCommand) -> None: ...

    def on_timeline(self, e: io.AgentTimeline) -> None: ...

    def check_replica(self) -> None: ...

    def kill_all(self, reason: str) -> None: ...

    def backlog(self) -> int:
        """Bytes this host gave its agents that they have not read yet."""
        ...


class AgentOps:
    """See the module docstring."""

    def __init__(
        self,
        name: str,
        counters: Counter[str],
        node: Callable[[], object],
        feed: Callable[..., Any],
        ddb_write: Callable[[list[Any], bool], Awaitable[DdbWriteResult]],
        next_req: Callable[[], int],
    ) -> None:
        self.name = name
        self.counters = counters
        self._node = node
        self.feed = feed
        self._ddb_write = ddb_write
        self._next_req = next_req
        self._ops: dict[Hashable, asyncio.Future[io.AgentOpDone]] = {}
        self._requests: dict[int, asyncio.Future[io.OperatorReply]] = {}
        #: the host's byte budgets of messages in flight (set by the runtime); None: none
        self.budget: MessageBudget | None = None

    def agent_node(self) -> AgentNode:
        node = self._node()
        if not isinstance(node, AgentNode):
            raise NotMembershipMode(f"{self.name} does not run the agent layer")
        return node

    # ------------------------------------------------------------------ operators

    async def agent_op(self, request: Callable[[Hashable], AgentLayerInput], timeout: float = 10.0) -> io.AgentOpDone:
        """Run an operator request of the agent layer (`CreateAgent`, `RemoveAgent`, `MoveAgent`, `SetPaused`,
        built by `request(req)`) and wait for its `AgentOpDone`."""
        node = self.agent_node()
        req = ("op", self._next_req())
        fut: asyncio.Future[io.AgentOpDone] = asyncio.get_running_loop().create_future()
        self._ops[req] = fut
        try:
            self.feed(node.step, request(req))
            return await asyncio.wait_for(fut, timeout)
        finally:
            self._ops.pop(req, None)

    async def agent_request(self, ref: str, payload: bytes, timeout: float = 5.0) -> io.OperatorReply:
        """Send an operator request to an agent and wait for its reply (TimeoutError; LookupError for an
        unknown agent)."""
        node = self.agent_node()
        conv = self._next_req()
        fut: asyncio.Future[io.OperatorReply] = asyncio.get_running_loop().create_future()
        self._requests[conv] = fut
        try:
            if node.table.resolve(ref) is None:
                raise LookupError(f"unknown agent {ref!r}")
            # the reply travels back from the agent's host: the request's sender is "@<this host>"
            self.feed(node.step, OperatorSend(ref, payload, conv, "@" + node.name))
            return await asyncio.wait_for(fut, timeout)
        finally:
            self._requests.pop(conv, None)

    def op_done(self, e: io.AgentOpDone) -> None:
        fut = self._ops.pop(e.req, None)
        if fut is not None and not fut.done():
            fut.set_result(e)

    def replied(self, e: io.OperatorReply) -> None:
        fut = self._requests.pop(e.conv, None)
        if fut is not None and not fut.done():
            fut.set_result(e)

    # ------------------------------------------------------------------ the backend's inputs (AgentHost)

    def on_agent_event(self, ev: io.AgentEvent) -> None:
        node = self._node()
        if isinstance(node, AgentNode):
            self.feed(node.step, InstanceEvent(ev))

    def undeliverable(self, agent: str, epoch: int, msg: apb.RoutedMsg) -> None:
        node = self._node()
        if isinstance(node, AgentNode):
            self.feed(node.step, Undeliverable(agent, epoch, msg))

    def report_costs(self, cpu: dict[str, float], rates: dict[tuple[str, str], float]) -> None:
        node = self._node()
        if isinstance(node, AgentNode):
            self.feed(node.step, ReportCosts(cpu, rates))

    def send_room(self, dst: str, size: int, gone: Callable[[], bool]) -> Awaitable[None] | None:
        """None if an agent's message of `size` bytes to `dst` may go now, else what to wait for (haa.hostd.budget)."""
        return None if self.budget is None else self.budget.agent_room(dst, size, gone)

    def local_replica(self) -> Ddb | None:
        """This host's DDB replica (it is replaced when a joiner installs its sponsor's state)."""
        node = self._node()
        m = node.m if isinstance(node, AgentNode) else node
        return m.state.ddb if isinstance(m, MembershipNode) else None

    def agent_table(self) -> AgentTable | None:
        node = self._node()
        return node.table if isinstance(node, AgentNode) else None

    async def ddb_write(self, ops: list[Any], atomic: bool = False) -> DdbWriteResult:
        return await self._ddb_write(ops, atomic)
