"""Byte budgets of the agent messages in flight through one host (docs/limits.md, "Messages in flight").

A message between agents, or from an operator (`AgentSend`, `AgentRequest`), crosses one or two hosts; on each it
sits in a buffer until the next hop takes it: a host link's queue (`OutLink`: written, then kept until the
receiver acknowledges it), an agent's channel (written, not read yet by the agent process), or the router's
pushes to a frozen agent's queue in the table. Nothing used to bound them in bytes: 300 `AgentSend` of 4 MiB with
32 in flight took the client's host to 718-1,267 MiB (424 MiB of it the link's queue) and the agent's host to
172-580 MiB (the agent's channel: 387 MiB), with loop stalls up to 1.3 s and a host removed in 4 of 6 runs. Now a
message enters this host's agent layer only when its next buffer has room (`blocked`):

* to an agent that runs here: this host's agents have less than `DELIVERY_BYTES` unread (all channels together);
* to an agent active on host X (or the reply to an operator request made through X): the link to X holds less
  than `LINK_QUEUE_BYTES`, every message counted until X acknowledges it. X acknowledges a frame only while its
  own agents have less than `DELIVERY_BYTES` unread (`may_ack`, the transport's ack gate), so the sender's link
  budget also holds what X buffers for its agents: back-pressure from the agent that reads to the client that
  writes. (X acknowledges at once after `haa.hostd.transport.ACK_BYTES`, not a second later.)
* to a frozen, new or crashed agent (into its queue in the table through OAC): the router holds less than
  `PUSH_BYTES` of payload in pushes (`Router.held_bytes`).
* held by a transfer or a recovery in progress here (Alg. 5 l. 4, Alg. 6 l. 3, Alg. 8): not bounded here; they
  last as long as the operation.

An empty buffer always takes a message, whatever its size (at most `MAX_AGENT_MESSAGE`). What waits, and where:

* an operator message: its RPC waits, at most `OPERATOR_WAIT` (or the call's deadline), while this client has
  less than `CLIENT_WAITING_BYTES` and the host less than `HOST_WAITING_BYTES` of operator messages waiting
  (each counted with `MESSAGE_OVERHEAD`); beyond either bound, or at the end of the wait, the call is refused
  with `RESOURCE_EXHAUSTED` and the bound named (`operator`); nothing was sent;
* an agent's message: its host stops reading the agent's frames until the message has room (`agent_room`): the
  agent's socket and its own send buffer fill, within its memory limit; no message is dropped, and the sender
  stream's order is kept. The monitor does not count the wait as a hang.

Heartbeats never wait on a budget: they go as datagrams (docs/transport.md), and the links' control traffic
(OAC, membership, DDB) is never held or refused here; on a link without datagram heartbeats, a heartbeat queues
behind at most `LINK_QUEUE_BYTES` of agent messages (before, behind all of them).

Waits are re-checked on one shared tick every `POLL` seconds. Every wait and refusal is counted (`budget.*`).
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Awaitable, Callable

from haa.core.agents.agentnode import AgentNode
from haa.core.ddb import agenttable as at
from haa.hostd.logs import LOGGER_NAME, RateLimiter, log_event

log = logging.getLogger(LOGGER_NAME + ".budget")

MiB = 1024 * 1024
# The numbers are measured (haa.lab.bench.agent_send_flood: 300 sends of 4 MiB, 32 in flight, 4 hosts on 2 shared
# cores at load 7-10; docs/limits.md, "Messages in flight"). Link and delivery budgets of 4 / 8 / 16 / 64 MiB: the
# flood took 142-222 / 50-51 / 36-39 / 32-36 s, the agent's host peaked at 105-107 / 111-117 / 131-137 / 202-216 MiB,
# the largest stall was 353-454 / 386-448 / 350-424 / 663-710 ms (a DDB write after it 0.6-0.8 s at 64). 16 MiB is
# the knee: nearly the throughput of 64 at a third of its memory, four maximum-size messages in flight per hop.
#: bytes one host link may hold (not yet written, or not yet acknowledged) before agent messages wait for it
LINK_QUEUE_BYTES = 16 * MiB
#: bytes this host's agents may have unread in their channels before messages to them wait and its acks are held
DELIVERY_BYTES = 16 * MiB
#: payload bytes the router may hold for pushes into frozen, new or crashed agents' queues (two queues' worth,
#: `MAX_QUEUE_BYTES`: what is pushed beyond a queue's bound is dropped on apply anyway)
PUSH_BYTES = 2 * at.MAX_QUEUE_BYTES
#: operator messages of one client (address) waiting for room on one host, and of all clients. A waiting request is
#: held whole by gRPC and decoded (about twice its size); a refused one is sent again by its client, so a lower
#: bound saves no memory while the client keeps its calls in flight (8 MiB: a peak of 357-487 MiB on the client's
#: host, 2,300-4,200 refusals; 32 MiB: 355-364 MiB, 1,800-2,600; unbounded: 391-411 MiB) but costs refusals and
#: stalls. 32 MiB is eight maximum-size messages per client, 64 MiB two such clients per host.
CLIENT_WAITING_BYTES = 32 * MiB
HOST_WAITING_BYTES = 64 * MiB
#: what one waiting operator message counts on top of its payload (its request, its task)
MESSAGE_OVERHEAD = 1024
#: the longest an operator message waits for room, s (a call's shorter deadline cuts it)
OPERATOR_WAIT = 5.0
#: how often waiting messages look again, s
POLL = 0.005


def _mib(n: int) -> str:
    return f"{n / MiB:.1f} MiB"


class MessageBudget:
    """The budgets of one host (module docstring). `node()` is the runtime's current node, `link_bytes(peer)` what
    the link to `peer` holds, `backlog()` what this host's agents have not read yet."""

    def __init__(self, name: str, counters: Counter[str], node: Callable[[], object],
                 link_bytes: Callable[[str], int], backlog: Callable[[], int]) -> None:
        self.name = name
        self.counters = counters
        self._node = node
        self._link_bytes = link_bytes
        self._backlog = backlog
        self.client_waiting: Counter[str] = Counter()
        self.host_waiting = 0
        self._tick_ev: asyncio.Event | None = None
        self._limiter = RateLimiter(1.0)

    # ------------------------------------------------------------------ the routes

    def blocked(self, dst: str, size: int) -> str:
        """"" if a message of `size` bytes to agent `dst` (an id, a name, or "@host" for the reply to an operator
        request made through that host) has room on its way from this host now; else what holds it."""
        node = self._node()
        if not isinstance(node, AgentNode):
            return ""
        if dst.startswith("@"):
            host = dst[1:]
            return "" if host == node.name else self._link(host, size)
        t = node.table
        r = t.get(dst) or t.resolve(dst)
        if r is None:
            return ""  # the router counts it (routed_to_unknown, unknown_destination)
        loc = node.local.get(r.id)
        if loc is not None:
            return self._delivery(size) if loc.phase == "active" else ""
        if r.status == at.ACTIVE and r.owner and r.owner != node.name:
            return self._link(r.owner, size)
        if r.status == at.ACTIVE:
            return ""  # ours, its instance gone: held by the recovery until the table says where it is
        held = node.router.held_bytes
        if held and held + size > PUSH_BYTES:
            return f"{_mib(held)} of messages for frozen or new agents wait to be queued (at most PUSH_BYTES = " \
                   f"{_mib(PUSH_BYTES)})"
        return ""

    def _link(self, host: str, size: int) -> str:
        q = self._link_bytes(host)
        if q and q + size > LINK_QUEUE_BYTES:
            return f"the host link to {host} holds {_mib(q)} (at most LINK_QUEUE_BYTES = {_mib(LINK_QUEUE_BYTES)})"
        return ""

    def _delivery(self, size: int) -> str:
        b = self._backlog()
        if b and b + size > DELIVERY_BYTES:
            return f"the agents of {self.name} have {_mib(b)} unread (at most DELIVERY_BYTES = " \
                   f"{_mib(DELIVERY_BYTES)})"
        return ""

    def may_ack(self) -> bool:
        """This host may acknowledge what its links received: its agents have read what it delivered to them."""
        return self._backlog() <= DELIVERY_BYTES

    # ------------------------------------------------------------------ waiting

    async def _tick(self) -> None:
        ev = self._tick_ev
        if ev is None:
            ev = self._tick_ev = asyncio.Event()
            asyncio.get_running_loop().call_later(POLL, self._fire)
        await ev.wait()

    def _fire(self) -> None:
        ev, self._tick_ev = self._tick_ev, None
        if ev is not None:
            ev.set()

    async def _wait(self, dst: str, size: int, deadline: float | None, gone: Callable[[], bool] | None) -> str:
        """Wait until the message has room ("") or `deadline` (loop time) passes (what holds it then)."""
        loop = asyncio.get_running_loop()
        while True:
            await self._tick()
            why = self.blocked(dst, size)
            if not why or (gone is not None and gone()):
                return ""
            if deadline is not None and loop.time() >= deadline:
                return why

    async def operator(self, dst: str, size: int, client: str, time_left: float | None) -> str:
        """Admit an operator message of `size` bytes to `dst` from `client` (an address): "" once it may go, else
        why it is refused (the caller answers `RESOURCE_EXHAUSTED` with it). `time_left`: the call's remaining
        deadline, s (None: none)."""
        c = self.counters
        why = self.blocked(dst, size)
        if not why:
            return ""
        cost = size + MESSAGE_OVERHEAD
        mine = self.client_waiting[client]
        if mine + cost > CLIENT_WAITING_BYTES:
            c["budget.operator_refused"] += 1
            return f"{why}, and {_mib(mine)} of this client's messages already wait on {self.name} (at most " \
                   f"CLIENT_WAITING_BYTES = {_mib(CLIENT_WAITING_BYTES)}): nothing sent, try again later"
        if self.host_waiting + cost > HOST_WAITING_BYTES:
            c["budget.operator_refused"] += 1
            return f"{why}, and {_mib(self.host_waiting)} of operator messages already wait on {self.name} (at " \
                   f"most HOST_WAITING_BYTES = {_mib(HOST_WAITING_BYTES)}): nothing sent, try again later"
        wait = OPERATOR_WAIT if time_left is None else max(0.0, min(OPERATOR_WAIT, time_left - 0.2))
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        self.client_waiting[client] += cost
        self.host_waiting += cost
        c["budget.operator_waits"] += 1
        try:
            why = await self._wait(dst, size, t0 + wait, None)
        finally:
            self.host_waiting -= cost
            self.client_waiting[client] -= cost
            if self.client_waiting[client] <= 0:
                del self.client_waiting[client]
        c["budget.operator_wait_ms"] += int((loop.time() - t0) * 1000)
        if why:
            c["budget.operator_refused"] += 1
            return f"{why} still after {wait:.1f} s (OPERATOR_WAIT = {OPERATOR_WAIT:g} s): nothing sent, try again " \
                   "later"
        return ""

    def agent_room(self, dst: str, size: int, gone: Callable[[], bool]) -> Awaitable[None] | None:
        """None if an agent's message of `size` bytes to `dst` may go now; else an awaitable that ends once it may
        (or once `gone()`: the sender's process exited). The caller holds the sender's frames meanwhile."""
        why = self.blocked(dst, size)
        if not why:
            return None
        self.counters["budget.agent_holds"] += 1
        if self._limiter.allow("agent_hold"):
            log_event(log, logging.INFO, "agent_send_held", dst=dst[:64], size=size, reason=why)
        return self._hold(dst, size, gone)

    async def _hold(self, dst: str, size: int, gone: Callable[[], bool]) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        await self._wait(dst, size, None, gone)
        self.counters["budget.agent_hold_ms"] += int((loop.time() - t0) * 1000)

    def gauges(self) -> dict[str, int]:
        """What the budgets hold now, for the status counters."""
        return {"budget.agent_unread_bytes": self._backlog(), "budget.operator_waiting_bytes": self.host_waiting}
