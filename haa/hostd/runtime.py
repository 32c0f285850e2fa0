"""HostRuntime: drives the host's sans-I/O state machines with asyncio, the gRPC transport and the wall clock.

The deterministic simulator (`haa.lab.dsim.cluster`) and this runtime drive the *same* machines — an `AgentNode`
over a `MembershipNode` over a `HostCore` (membership mode), or a bare `HostCore` (static mode); this one does
it for real (docs/architecture.md, "How an input travels"):

* **Inputs.** Every input is fed to the node with the current local time `time.monotonic()`: frames from
  the transport (`on_message` for each envelope, then one drain), timers (`on_timer`), handshakes that
  reveal a peer incarnation (`on_peer_info`), local proposals and writes, operator requests and the agent
  processes' events. After each input the runtime drains the node's effects and hands them to its
  `EffectDispatcher` (haa.hostd.dispatch: one `match` over the closed `HostEffect` union).
* **Parts.** Each concern is a class of its own that the runtime owns: the timer wheel (haa.hostd.timers),
  the delivered log with its hash chain (haa.hostd.delivered), propose waiters and latency samples
  (haa.hostd.proposals), the global-state writes (haa.hostd.writes), operator and agent-driver calls
  (haa.hostd.agentops), mirror subscribers (haa.hostd.mirrors) and the data directory's incarnation and
  known-hosts files (haa.hostd.datadir). What they return and raise is in haa.hostd.outcomes.
* **Reincarnation.** A `Reincarnate` effect (this host was excluded) or a peer that knows a newer incarnation
  of our name replaces the node by a new incarnation: timers, waiters and open writes end, the agents of the
  old incarnation are killed, the transport stays (its links restart numbering for the new incarnation).
  Incarnations are `time.time_ns()` at start, bumped above the last one recorded in `--data-dir`, so they
  increase strictly across restarts.

One grpc.aio server on `listen` serves `haa.v1.HostLink` (the transport) and the services the composition
root adds (`add_service`: the control API, haa.hostd.control). The runtime imports neither the control
service nor the agent driver: `haa.hostd.daemon.build_host` builds them and gives each what it needs — the
driver comes in as an `AgentBackend` (haa.hostd.agentops) and gets the runtime's `AgentOps` at start.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import socket
import time
from collections import Counter
from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass, field
from dataclasses import replace as dataclass_replace
from pathlib import Path
from typing import Any, Protocol, cast

import psutil
from grpc import aio

from haa.core.agents.agentnode import AgentConfig, AgentNode
from haa.core.host.hostcore import CoreConfig, HostCore
from haa.core.inputs import LeaveGroup, PeerInfo, Receive, Start, Submit, TimerFired
from haa.core.membership.membership import MembershipNode, NodeConfig
from haa.core.messages import Message, TxId
from haa.hostd.agentops import AgentBackend, AgentOps
from haa.hostd.budget import MessageBudget
from haa.hostd.datadir import HostDataDir
from haa.hostd.delivered import DeliveredLog
from haa.hostd.dispatch import EffectDispatcher, HostEffect
from haa.hostd.logs import LOGGER_NAME, HostIdentity, log_event, setup_logging, teardown_logging
from haa.hostd.mirrors import Mirrors
from haa.hostd.outcomes import (
    HostReincarnated,
    NotMembershipMode,
    ProposeResult,
    WriteFailed,
)
from haa.hostd.proposals import Proposals
from haa.hostd.resources import LoopWatch, tune_malloc
from haa.hostd.status import host_status
from haa.hostd.timers import TimerWheel
from haa.hostd.transport import Transport, split_address
from haa.hostd.writes import Writes
from haa.tls import HandshakeTap, HostTls

log = logging.getLogger(LOGGER_NAME + ".runtime")


class HostService(Protocol):
    """A gRPC service served next to the transport (`HostRuntime.add_service`)."""

    def add_to_server(self, server: aio.Server) -> None: ...


@dataclass
class RuntimeConfig:
    name: str
    listen: str
    peers: dict[str, str]
    token: str
    core: CoreConfig = field(default_factory=CoreConfig)
    data_dir: Path | None = None
    log_level: int = logging.INFO
    log_stderr: bool = False
    #: membership mode (Alg. 3): the ordered core process list; empty = static mode over `peers`
    core_processes: list[tuple[str, str]] = field(default_factory=list)
    #: the address other hosts connect to (membership mode); default: `listen`
    advertise: str = ""
    node: NodeConfig | None = None
    #: ignore the hosts a previous incarnation knew (`<data-dir>/known_hosts.json`)
    forget_group: bool = False
    #: failure-detector heartbeats as UDP datagrams on the listen port (docs/transport.md, "Heartbeats as
    #: datagrams"); False: on the host-link streams like every other message
    datagram_heartbeats: bool = True
    #: the carrier of the host links, "grpc" or "tcp" (haa.hostd.tcplink), and the TCP one's port (0: any free)
    host_link: str = "grpc"
    link_port: int = 0
    #: how long SIGTERM waits for the graceful leave to commit before stopping anyway, s (with agents: after
    #: handing them over, which takes at most `agent.drain_timeout`)
    leave_timeout: float = 3.0
    #: membership mode runs the agent layer (haa.core.agents.agentnode) and supervises agent processes
    agents: bool = True
    agent: AgentConfig = field(default_factory=AgentConfig)
    #: hang detection of agent processes (no heartbeat for this long), s
    agent_hang_timeout: float = 3.0
    preload_agents: list[str] = field(default_factory=list)
    #: mutual TLS (haa.tls, `--tls-dir`): links and control API over TLS with this host's certificate
    tls: HostTls | None = None

    @property
    def membership(self) -> bool:
        return bool(self.core_processes)


class HostRuntime:
    """One haa-hostd process: node + transport + the parts it owns (see the module docstring)."""

    def __init__(
        self,
        config: RuntimeConfig,
        no_votes: Iterable[bytes] = (),
        agents: AgentBackend | None = None,
    ) -> None:
        if agents is not None and not (config.membership and config.agents):
            raise ValueError("agent processes need the agent layer (membership mode with agents on)")
        self.config = config
        self.name = config.name
        #: static mode: the payloads this host votes no on (OAC's unilateral abort, Alg. 2 l. 27; tests)
        self.no_votes = tuple(no_votes)
        self.counters: Counter[str] = Counter()
        self.ident = HostIdentity(config.name, 0)
        self.membership = config.membership
        #: the state machine this runtime drives: an `AgentNode` over a `MembershipNode` (membership mode; a bare
        #: `MembershipNode` with agents off) or a bare `HostCore` (static mode)
        self.node: AgentNode | MembershipNode | HostCore | None = None
        #: the failure detector + OAC core (the node's own in membership mode)
        self.core: HostCore | None = None
        #: whatever runs this host's agent processes (the composition root's `AgentDriver`), None without agents
        self.agents = agents
        self.transport = self._make_transport()
        self._tap: HandshakeTap | None = None
        self._services: list[HostService] = []
        self.advertise = config.advertise
        self.server: aio.Server | None = None
        self.port = 0
        self.started_at = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped = asyncio.Event()
        self.stopping = False  # stop() began
        self.left = False
        self._left_waiters: list[asyncio.Future[None]] = []
        #: tasks serving long-lived control streams (Deliveries, Mirror, AgentEvents), ended cleanly on shutdown
        self.stream_tasks: set[asyncio.Task[Any]] = set()
        self._log_handlers: list[logging.Handler] = []
        self._past_core_counters: Counter[str] = Counter()
        self._proc = psutil.Process()
        next_req = itertools.count(1).__next__  # request numbers of writes and operator calls
        self.data = HostDataDir(config.name, config.data_dir)
        self.timers = TimerWheel(self._fire)
        self.delivered = DeliveredLog()
        self.proposals = Proposals(config.name)
        self.writes = Writes(config.name, self.counters, self._submit_input, self._check_writable,
                                  lambda: self.stopping or self.left, next_req)
        self.agent_ops = AgentOps(config.name, self.counters, lambda: self.node, self.feed,
                                  lambda ops, atomic: self.writes.ddb_write(ops, atomic), next_req)
        #: the byte budgets of agent messages in flight through this host (haa.hostd.budget): a message waits for
        #: room on its way; this host's acks wait for its agents to read what it delivered to them
        self.budget = MessageBudget(config.name, self.counters, lambda: self.node, self.transport.queued_bytes,
                                    self._agent_backlog)
        self.agent_ops.budget = self.budget
        self.transport.ack_gate = self.budget.may_ack
        #: mirror stream subscribers, fed from applied transactions and view changes
        self.mirrors = Mirrors()
        self.dispatcher = EffectDispatcher(
            transport=self.transport, timers=self.timers, proposals=self.proposals, delivered=self.delivered,
            writes=self.writes, mirrors=self.mirrors, agent_ops=self.agent_ops, agents=agents, data=self.data,
            counters=self.counters, on_left=self._on_left,
        )
        #: event-loop stall watchdog and heap trimming (haa.hostd.resources)
        self.loopwatch = LoopWatch(self.counters, self._moved_bytes)

    def _agent_backlog(self) -> int:
        return self.agents.backlog() if self.agents is not None else 0

    def _make_transport(self) -> Transport:
        """The host-to-host links (haa.hostd.transport), feeding this runtime's inputs."""
        cfg = self.config
        return Transport(cfg.name, cfg.token, {} if cfg.membership else cfg.peers,
                         on_envelopes=self._on_envelopes, on_peer_incarnation=self._on_peer_incarnation,
                         counters=self.counters, accept_unknown=cfg.membership, on_superseded=self._on_superseded,
                         on_live_elsewhere=self._on_live_elsewhere,
                         datagram_heartbeats=cfg.datagram_heartbeats, tls=cfg.tls, carrier=cfg.host_link)

    def add_service(self, service: HostService) -> None:
        """Serve `service` (e.g. the control API) on this host's gRPC server; before `start`."""
        if self.server is not None:
            raise RuntimeError("add_service after start")
        self._services.append(service)

    # ------------------------------------------------------------------ lifecycle

    @property
    def mnode(self) -> MembershipNode | None:
        """The membership node (inside the agent layer when agents run), None in static mode."""
        node = self.node.m if isinstance(self.node, AgentNode) else self.node
        return node if isinstance(node, MembershipNode) else None

    @property
    def incarnation(self) -> int:
        return self.core.inc if self.core is not None else 0

    def _make_node(self, inc: int) -> None:
        cfg = self.config
        self.ident.inc = inc
        self.proposals.reset()
        known = [] if cfg.forget_group or not self.membership else self.data.load_known_hosts()
        if self.mnode is not None:
            # a reincarnation: apply to the hosts the previous incarnation knew as members
            known = [(m.name, m.addr) for m in self.mnode.state.members if m.name != self.name] or known
        self.node, self.core = build_node(cfg, inc, self.advertise, known, self.no_votes)

    async def start(self) -> None:
        """Bind the server, start the links, the agent backend and the node."""
        cfg = self.config
        if cfg.data_dir is not None:
            cfg.data_dir.mkdir(parents=True, exist_ok=True)
        self._log_handlers = setup_logging(
            self.ident, cfg.data_dir / f"{cfg.name}.jsonl" if cfg.data_dir else None, cfg.log_level, cfg.log_stderr
        )
        loop = asyncio.get_running_loop()
        self._loop = loop
        self.timers.start(loop)
        self._proc.cpu_percent(None)
        inc = self.data.new_incarnation(0)
        self.transport.incarnation = inc
        tune_malloc()  # before the gRPC server starts its threads (their arenas)
        server = aio.server(options=Transport.server_options())
        self.transport.add_to_server(server)
        for service in self._services:
            service.add_to_server(server)
        if cfg.tls is None:
            self.port = server.add_insecure_port(cfg.listen)
        else:  # mutual TLS: a client without a certificate of the cluster's CA never gets past the handshake
            self.port = server.add_secure_port(cfg.listen, cfg.tls.server_credentials())
        hp = split_address(cfg.listen)
        await self.transport.open_heartbeats(hp[0] if hp else "", self.port)
        if cfg.host_link == "tcp":
            try:
                await self.transport.open_tcp(hp[0] if hp else "", cfg.link_port)
            except OSError as e:
                raise RuntimeError(f"--link-port {cfg.link_port}: cannot bind the tcp host link: {e}") from None
        if not self.advertise:
            self.advertise = advertised_address(cfg.listen, self.port)
        self._make_node(inc)
        await server.start()
        self.server = server
        self.started_at = time.monotonic()
        _log_startup(cfg, self.port, self.advertise if self.membership else "", self.transport.tcp_port)
        if self.agents is not None:
            await self.agents.start(self.agent_ops)
        if cfg.tls is not None:
            # after the agents' fork server started (it keeps the real stderr); see haa.tls.HandshakeTap
            def refused(reason: str) -> None:  # called on the tap's thread
                loop.call_soon_threadsafe(self._tls_refused, reason)

            self._tap = HandshakeTap(refused)
            self._tap.start()
        self.transport.start()
        self.loopwatch.start()
        node = self.node
        assert node is not None
        self.feed(node.step, Start())

    def _tls_refused(self, reason: str) -> None:
        """gRPC refused a TLS handshake (no client certificate, another CA's, expired): count and log it."""
        self.counters["rejected_tls_handshake"] += 1
        self.counters["rejected_tls_handshake." + reason.lower()[:60]] += 1
        if self.transport.limiter.allow("tls_handshake"):
            log_event(log, logging.WARNING, "reject_tls_handshake", reason=reason)

    def request_stop(self) -> None:
        """Ask `run()` to return."""
        self._stopped.set()

    async def run(self) -> None:
        """Start, serve until `request_stop()`, then shut down gracefully."""
        await self.start()
        try:
            await self._stopped.wait()
        finally:
            await self.stop()

    async def stop(self) -> None:
        if self.stopping:
            return
        self.stopping = True
        log_event(log, logging.INFO, "shutdown", delivered=self.delivered.count, hash=self.delivered.hash)
        self.loopwatch.stop()
        self.timers.clear()
        self.proposals.fail_all(lambda _txid: RuntimeError(f"{self.name} is shutting down"))
        self.writes.fail_all(lambda: RuntimeError(f"{self.name} is shutting down"))
        self._end_leave_waiters(RuntimeError(f"{self.name} is shutting down"))
        self.mirrors.close()
        if self.agents is not None:
            await self.agents.close()
        await self.transport.stop()
        for task in list(self.stream_tasks):
            task.cancel()
        for _ in range(3):
            await asyncio.sleep(0)
        if self.server is not None:
            await self.server.stop(0.5)
        if self._tap is not None:
            self._tap.stop()
            self._tap = None
        teardown_logging(self._log_handlers)
        self._log_handlers = []
        self._stopped.set()

    def _moved_bytes(self) -> int:
        """Bytes this host's links sent and received so far (the heap-trim trigger of `LoopWatch`)."""
        return sum(v for k, v in self.counters.items() if k.startswith(("rx_bytes.", "tx_bytes.")))

    # ------------------------------------------------------------------ inputs

    def feed(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Call a node input with the current time, then carry out its effects; the input's return value
        (None if it raised: a bug in the node is counted and logged, never passed to the caller)."""
        try:
            res = fn(time.monotonic(), *args)
        except Exception:
            what = type(args[0]).__name__ if fn.__name__ == "step" and args else fn.__name__
            self._core_error("core input failed", input=what)
            self._apply()
            return None
        self._apply()
        return res

    def _on_envelopes(self, sender: str, sender_inc: int, items: list[tuple[int, Message]]) -> None:
        node = self.node
        if node is None:
            return
        now = time.monotonic()
        step = node.step
        for dst_inc, msg in items:
            try:
                if step(now, Receive(sender, sender_inc, dst_inc, msg)) is not None:  # for an agent layer not run here
                    node.counters["rejected_unknown_message"] += 1
            except Exception:
                self._core_error("core failed on a message", src=sender, msg=type(msg).__name__)
        self._apply()

    def _core_error(self, what: str, **fields: str) -> None:
        """A bug in the node: counted and logged with its traceback, never raised into the caller (a link's
        receive loop, a timer, an RPC) — a link that stops reading wedges the whole group (issue 13, defect 1)."""
        self.counters["core_errors"] += 1
        log.exception(what, extra={"event": "core_error", "fields": fields})

    def _on_peer_incarnation(self, peer: str, inc: int) -> None:
        if self.node is not None:
            self.feed(self.node.step, PeerInfo(peer, inc))

    def _fire(self, key: Hashable, at: float) -> None:
        node = self.node
        if node is None:
            return
        now = time.monotonic()
        if now < at:  # the loop may run a timer a hair early; the core must see its deadline reached
            now = at
        try:
            node.step(now, TimerFired(key))
        except Exception:
            self._core_error("core failed on a timer", key=repr(key))
        self._apply()

    def _submit_input(self, payload: bytes, req: int, kind: str, cost: int) -> None:
        """The writes' way into the node (`MembershipNode.submit`, through the agent layer if any)."""
        node = self.node
        assert isinstance(node, (AgentNode, MembershipNode))
        self.feed(node.step, Submit(payload, req, kind, cost))

    # ------------------------------------------------------------------ effects

    def _apply(self) -> None:
        node = self.node
        if node is None:
            return
        try:
            # AgentNode.drain is typed list[Any]: it returns the HostEffect union (haa.hostd.dispatch)
            effects = cast("list[HostEffect]", node.drain())
        except Exception:
            self._core_error("core drain failed", input="drain")
            return
        core = self.core
        if core is not None:
            self.proposals.catch_up(core.oac, time.monotonic)
        if not effects:
            return
        reincarnate_by = self.dispatcher.run(effects)
        if self.mirrors:
            mnode = self.mnode
            self.mirrors.check_replica(mnode.state.ddb if mnode is not None else None)
        if self.agents is not None:
            self.agents.check_replica()
        if reincarnate_by is not None:
            self._reincarnate(reincarnate_by)

    def _on_superseded(self, peer: str, newer: int) -> None:
        """`peer` knows a newer incarnation of this host's name: this process was displaced (a second daemon
        under our name, or a claim, was accepted while we were silent). Rejoin as a new incarnation above it,
        dropping our agent instances (docs/membership.md, "incarnation claims")."""
        if self.node is None or self.stopping or self.left or newer <= self.incarnation:
            return
        self._reincarnate(f"superseded at {peer} by incarnation {newer}", above=newer)

    def _on_live_elsewhere(self, peer: str) -> None:
        """`peer` refused this process: another one under this host's name is live there (a second daemon, a
        copied certificate). This one never forms a group of its own then (it used to, after the formation
        timeout: a one-host group beside the real one); it keeps applying, and joins once the other is gone."""
        node = self.node.m if isinstance(self.node, AgentNode) else self.node
        if isinstance(node, MembershipNode) and node.note_live_elsewhere(peer):
            log_event(log, logging.ERROR, "name_in_use", peer=peer,
                      reason=f"another process runs as {self.name} (live on {peer}): this one will not form a "
                             "group of its own; it joins once the other is gone")

    def _reincarnate(self, by: str, above: int = 0) -> None:
        old = self.core
        assert old is not None
        inc = self.data.new_incarnation(max(old.inc, above))
        log_event(log, logging.WARNING, "reincarnate", by=by, old=old.inc, new=inc)
        self._past_core_counters.update(old.counters)
        self.counters["reincarnations"] += 1
        self.timers.clear()
        self.proposals.fail_all(lambda txid: HostReincarnated(f"{self.name} reincarnated while {txid} was open"))
        restarted = f"{self.name} restarted as a new incarnation (outcome unknown)"
        self.writes.fail_all(lambda: WriteFailed(restarted))
        self._end_leave_waiters(WriteFailed(restarted))
        self.writes.forget()
        if self.agents is not None:
            self.agents.kill_all("this host restarted as a new incarnation")
        self._make_node(inc)
        self.transport.set_incarnation(inc)
        now = time.monotonic()
        node = self.node
        assert node is not None
        node.step(now, Start())
        # the links already know the peers' incarnations; tell the new core (it arms their exclusion timers)
        for peer, link in self.transport.links.items():
            if link.receiver_inc:
                node.step(now, PeerInfo(peer, link.receiver_inc))
        self._apply()

    def _on_left(self) -> None:
        self.left = True
        self.data.forget_known_hosts()
        self._end_leave_waiters(None)

    def _end_leave_waiters(self, error: Exception | None) -> None:
        for fut in self._left_waiters:
            if not fut.done():
                if error is None:
                    fut.set_result(None)
                else:
                    fut.set_exception(error)
        self._left_waiters.clear()

    # ------------------------------------------------------------------ proposals (static mode: bare OAC)

    def _propose(self, payload: bytes, participants: list[str] | None) -> TxId:
        if self.core is None:
            raise RuntimeError("host not started")
        return self.proposals.start(time.monotonic(), self.core, payload, participants)

    def propose_nowait(self, payload: bytes, participants: list[str] | None = None) -> TxId:
        """Propose a transaction and return its id at once (None participants: this host and every peer
        it trusts)."""
        txid = self._propose(payload, participants)
        self._apply()
        return txid

    async def propose(
        self, payload: bytes, participants: list[str] | None = None, timeout: float = 30.0
    ) -> ProposeResult:
        """Propose a transaction and wait until this host decided it and delivered it.

        Raises `OacError` (bad participants), `TransactionAborted`, `ProposeTimeout` or `HostReincarnated`."""
        txid = self._propose(payload, participants)
        fut = self.proposals.expect(txid)
        self._apply()
        return await self.proposals.wait(txid, fut, timeout)

    # ------------------------------------------------------------------ global-state changes (membership mode)

    def member_node(self) -> MembershipNode:
        """The membership node; `NotMembershipMode` in static mode."""
        node = self.mnode
        if node is None:
            raise NotMembershipMode(f"{self.name} runs a static peer list (--peers): no group, no DDB")
        return node

    def _check_writable(self) -> None:
        node = self.member_node()
        if self.left or node.lv.leaving:
            raise WriteFailed("this host is leaving the group")

    async def leave(self, timeout: float = 10.0) -> None:
        """Leave the group (Alg. 3 ll. 14-21) and wait until the group has removed this host. The process
        keeps running (stop it with `request_stop`); `TimeoutError` if the removal did not commit in time."""
        self.member_node()
        if self.left:
            return
        node = self.node
        assert isinstance(node, (AgentNode, MembershipNode))
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._left_waiters.append(fut)
        self.feed(node.step, LeaveGroup())  # the agent layer hands its agents over first
        await asyncio.wait_for(fut, timeout)

    # ------------------------------------------------------------------ queries

    def all_counters(self) -> Counter[str]:
        c = Counter(self.counters)
        core = self.core
        for k, v in (self._past_core_counters + (core.counters if core else Counter())).items():
            c["core." + k] += v
        c.update(self.budget.gauges())
        c["budget.link_queued_bytes"] = self.transport.queued_bytes_total()
        return c

    def status(self) -> dict[str, Any]:
        """This host as `haactl status` shows it (haa.hostd.status)."""
        core = self.core
        assert core is not None
        return host_status(name=self.name, core=core, node=self.mnode, transport=self.transport,
                           delivered=self.delivered, counters=self.all_counters(), proc=self._proc,
                           uptime=time.monotonic() - self.started_at)


def build_node(
    cfg: RuntimeConfig,
    inc: int,
    advertise: str,
    known: list[tuple[str, str]],
    no_votes: Iterable[bytes] = (),
) -> tuple[AgentNode | MembershipNode | HostCore, HostCore]:
    """The state machines of one incarnation and its core: a bare `HostCore` over the static peer list, or a
    `MembershipNode` (Alg. 3) applying to the core processes and `known` hosts, wrapped in an `AgentNode` when
    agents run."""
    if not cfg.membership:
        core = HostCore(cfg.name, inc, list(cfg.peers), cfg.core, no_votes=no_votes)
        return core, core
    ncfg = dataclass_replace(cfg.node, core=cfg.core) if cfg.node is not None else NodeConfig(core=cfg.core)
    node = MembershipNode(cfg.name, inc, advertise, cfg.core_processes, ncfg, known_hosts=known)
    return (AgentNode(node, cfg.agent) if cfg.agents else node), node.core


def _log_startup(cfg: RuntimeConfig, port: int, advertise: str, link_port: int) -> None:
    ufd = cfg.core.ufd
    log_event(
        log,
        logging.INFO,
        "startup",
        listen=cfg.listen,
        port=port,
        peers=cfg.peers,
        core_processes=cfg.core_processes,
        advertise=advertise,
        qos={"td": ufd.qos.td_upper, "tmr": ufd.qos.tmr_lower, "tm": ufd.qos.tm_upper},
        exclude_after=cfg.core.exclude_after,
        host_link=cfg.host_link,
        link_port=link_port,
    )


def advertised_address(listen: str, port: int) -> str:
    """The address other hosts reach this one at: `listen` with the bound port; a wildcard listen address
    (0.0.0.0, [::]) is replaced by this machine's host name (a compose service's name)."""
    host = listen.rpartition(":")[0]
    if host in ("", "0.0.0.0", "[::]", "::"):
        host = socket.gethostname()
    return f"{host}:{port}"
