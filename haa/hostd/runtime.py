"""HostRuntime: drives the sans-I/O `HostCore` with asyncio, the gRPC transport and the wall clock.

The deterministic simulator (`haa.dsim.cluster`) and this runtime drive the *same* `HostCore`; this one does
it for real:

* **Inputs.** Every input is fed to the core with the current local time `time.monotonic()`: frames from
  the transport (`on_message` for each envelope, then one drain), timers (`on_timer`), handshakes that
  reveal a peer incarnation (`on_peer_info`), and local proposals (`propose`). After each input the
  runtime drains the core's effects and carries them out (`_apply`).
* **Effects.** `Send` -> the transport's per-peer queue (never blocks); `SetTimer`/`CancelTimer` -> a timer
  wheel of `loop.call_at` handles keyed like the core's timers (setting a key again replaces it); the
  core's clock (`time.monotonic()`) is converted to the loop's clock by a fixed offset measured at start
  (zero for the default loop, which also uses the monotonic clock), and a timer is never reported to the
  core before its deadline. `Decided`/`Deliver` -> the delivered log and the latency records, and wake any
  `propose()` waiting for them. `Suspicion`, `PeerDead`, `Log` -> the JSON-lines log. `Reincarnate` -> the
  core is replaced by a new incarnation (the transport stays; its links restart numbering for the new
  incarnation).
* **Delivered log.** Every committed transaction this process delivered (the latest `MAX_DELIVERED` kept in
  memory), in delivery order, as
  `(index, txid, order, payload, chain_hash)` with a running hash chain
  `chain_i = sha256(chain_{i-1} + "\\n" + "host.inc.seq" + "\\n" + payload)` (hex; `chain_{-1}` is 64
  zeros), so two hosts have delivered the same sequence iff their last hashes are equal.
* **Latencies.** For transactions this host proposed: propose -> local `Decided`; for every delivered one:
  local `Decided` -> `Deliver`. Both on the local monotonic clock.
* **Incarnations** are `time.time_ns()` at start (bumped above the last one recorded in `--data-dir`, and
  above the previous one on reincarnation), so they increase strictly across restarts.

One grpc.aio server on `listen` serves both `haa.v1.HostLink` (the transport) and `haa.v1.HostControl`
(`haa.hostd.control`). `haa.hostd.daemon` builds a `RuntimeConfig` from the command line and runs it.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import os
import socket
import time
from collections import Counter, deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from dataclasses import replace as dataclass_replace
from pathlib import Path
from typing import Any, NamedTuple

import psutil
from grpc import aio

from haa import files
from haa.hostd import agentio
from haa.hostd import ddb as ddbmod
from haa.hostd.agentnode import AgentConfig, AgentNode
from haa.hostd.core import CoreConfig, HostCore
from haa.hostd.effects import (
    CancelTimer,
    Closed,
    Decided,
    Deliver,
    Log,
    PeerDead,
    Reincarnate,
    Send,
    SetTimer,
    Suspicion,
)
from haa.hostd.globalstate import decode_tx
from haa.hostd.logs import LOGGER_NAME, HostIdentity, log_event, setup_logging, teardown_logging
from haa.hostd.membership import AppliedTx, Connect, Left, MembershipNode, NodeConfig, ViewChange, WriteDone
from haa.hostd.messages import Message, TxId
from haa.hostd.resources import LoopWatch, tune_malloc
from haa.hostd.transport import Transport, split_address
from haa.tls import HandshakeTap, HostTls

log = logging.getLogger(LOGGER_NAME + ".runtime")

GENESIS_HASH = "0" * 64
#: core `Log` events that duplicate a typed effect (`PeerDead`) the runtime logs itself
_TYPED_EVENTS = frozenset({"peer_dead"})
#: core Log events that report a bug caught by a safety net (logged at error level)
_ERROR_EVENTS = frozenset({"agent_layer_error"})
#: hosts taken from a previous incarnation's known_hosts.json (as many as --core accepts)
MAX_KNOWN_HOSTS = 1000
#: how many latency samples are kept (oldest dropped first)
MAX_SAMPLES = 100_000
#: group commit of DDB writes (`HostRuntime.ddb_write`): at most this many of this host's DDB batches are in
#: OAC at a time; writes requested meanwhile wait and go out together as one batch of at most
#: DDB_GROUP_MAX_OPS ops / DDB_GROUP_MAX_BYTES bytes (atomic writes always go alone)
DDB_MAX_INFLIGHT = 2
DDB_GROUP_MAX_OPS = 2000
DDB_GROUP_MAX_BYTES = ddbmod.MAX_BATCH_BYTES // 2
#: the delivered log keeps at most this many entries in memory (the older half is dropped when it is full;
#: the hash chain and the count go on)
MAX_DELIVERED = 200_000
#: ... and at most this many payload bytes (a few maximum-size DDB batches; the older entries are dropped
#: until half of it is left): part of the host's memory bound (docs/limits.md, "Sizes and memory")
MAX_DELIVERED_BYTES = 16 << 20
#: a mirror subscriber whose queue holds more payload bytes than this is cut back to a resync (a snapshot)
MIRROR_SUB_MAX_BYTES = 16 << 20


def chain_hash(prev: str, txid: TxId, payload: bytes) -> str:
    """One step of the delivered-log hash chain (see the module docstring)."""
    h = hashlib.sha256(f"{prev}\n{txid.host}.{txid.inc}.{txid.seq}\n".encode())
    h.update(payload)
    return h.hexdigest()


class DeliveredEntry(NamedTuple):
    index: int
    txid: TxId
    order: int
    payload: bytes
    chain_hash: str


@dataclass(frozen=True)
class ProposeResult:
    """A transaction this host proposed, committed and delivered locally."""

    txid: TxId
    participants: tuple[str, ...]
    propose_to_decide: float
    decide_to_deliver: float


class TransactionAborted(Exception):
    """The transaction was decided abort."""

    def __init__(self, txid: TxId, participants: tuple[str, ...], propose_to_decide: float) -> None:
        super().__init__(f"transaction {txid} aborted")
        self.txid = txid
        self.participants = participants
        self.propose_to_decide = propose_to_decide


class ProposeTimeout(TimeoutError):
    """No local decision and delivery within the timeout (the transaction may still finish later)."""

    def __init__(self, txid: TxId, participants: tuple[str, ...]) -> None:
        super().__init__(f"transaction {txid} not delivered in time")
        self.txid = txid
        self.participants = participants


class HostReincarnated(Exception):
    """This host restarted as a new incarnation while the transaction was open; its outcome is unknown here."""


class WriteFailed(Exception):
    """A global-state change (DDB batch, test payload) was not committed: `reason` says why. A timeout does
    not mean it will never commit."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class NotMembershipMode(Exception):
    """The operation needs group membership (`--core`); this host runs a static peer list (`--peers`)."""


@dataclass(frozen=True)
class WriteResult:
    """A committed global-state change, applied on this host."""

    txid: TxId
    global_seq: int
    result: object | None  # haa.hostd.ddb.ApplyResult for DDB batches
    reason: str  # non-empty if the payload was committed but could not be applied (malformed)


@dataclass(frozen=True)
class DdbWriteResult:
    """One `ddb_write` request, committed and applied on this host: its ops' results (in request order),
    the DDB seq of the batch that carried it and how many requests shared that batch (group commit)."""

    txid: TxId
    global_seq: int
    ddb_seq: int
    results: tuple[Any, ...]  # haa.hostd.ddb.OpResult
    merged: int


@dataclass(eq=False)
class _QueuedWrite:
    ops: list[Any]
    atomic: bool
    size: int
    fut: asyncio.Future[DdbWriteResult]
    json: int = 0  # JSON value bytes (a group stays within ddb.MAX_BATCH_JSON_BYTES)
    abandoned: bool = False


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
    #: membership mode runs the agent layer (haa.hostd.agentnode) and supervises agent processes
    agents: bool = True
    agent: AgentConfig = field(default_factory=AgentConfig)
    #: hang detection of agent processes (no heartbeat for this long), s
    agent_hang_timeout: float = 3.0
    #: mutual TLS (haa.tls, `--tls-dir`): links and control API over TLS with this host's certificate
    tls: HostTls | None = None

    @property
    def membership(self) -> bool:
        return bool(self.core_processes)


_AGENT_COMMANDS = agentio.AGENT_COMMANDS


class HostRuntime:
    """One haa-hostd process: core + transport + timers + control service (see the module docstring)."""

    def __init__(self, config: RuntimeConfig, evaluate: Callable[[TxId, bytes], bool] | None = None) -> None:
        self.config = config
        self.name = config.name
        self.evaluate = evaluate
        self.counters: Counter[str] = Counter()
        self.ident = HostIdentity(config.name, 0)
        self.membership = config.membership
        #: the state machine this runtime drives: an `AgentNode` over a `MembershipNode` (membership mode; a bare
        #: `MembershipNode` with agents off) or a bare `HostCore` (static mode)
        self.node: AgentNode | MembershipNode | HostCore | None = None
        #: the agent processes of this host (membership mode with agents)
        self.agents: Any = None
        #: the failure detector + OAC core (the node's own in membership mode)
        self.core: HostCore | None = None
        self.transport = Transport(
            config.name,
            config.token,
            {} if config.membership else config.peers,
            on_envelopes=self._on_envelopes,
            on_peer_incarnation=self._on_peer_incarnation,
            counters=self.counters,
            accept_unknown=config.membership,
            on_superseded=self._on_superseded,
            datagram_heartbeats=config.datagram_heartbeats,
            tls=config.tls,
            carrier=config.host_link,
        )
        self._tap: HandshakeTap | None = None
        self.advertise = config.advertise
        self.server: aio.Server | None = None
        self.port = 0
        self.delivered: list[DeliveredEntry] = []
        self.delivered_base = 0  # index of delivered[0]: entries before it were dropped (MAX_DELIVERED)
        self.delivered_bytes = 0  # payload bytes in `delivered` (MAX_DELIVERED_BYTES)
        self.delivered_hash = GENESIS_HASH
        self.propose_to_decide: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.decide_to_deliver: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.started_at = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clock_offset = 0.0
        self._timers: dict[Hashable, asyncio.TimerHandle] = {}
        self._proposed_at: dict[TxId, float] = {}
        #: the highest OAC transaction number of this incarnation whose proposal time is known: transactions the
        #: cores propose themselves (membership, sequencer batches, agent table) get theirs in `_apply`, so
        #: that propose -> decide covers every transaction this host proposes
        self._oac_seq_seen = 0
        self._decided_at: dict[TxId, float] = {}
        self._p2d: dict[TxId, float] = {}
        self._participants_cache: dict[TxId, tuple[str, ...]] = {}
        self._waiters: dict[TxId, asyncio.Future[ProposeResult]] = {}
        self._delivery_event = asyncio.Event()
        self._stopped = asyncio.Event()
        self._stopping = False
        #: tasks serving long-lived control streams (Deliveries), ended cleanly on shutdown
        self.stream_tasks: set[asyncio.Task[Any]] = set()
        self._log_handlers: list[logging.Handler] = []
        self._past_core_counters: Counter[str] = Counter()
        self._proc = psutil.Process()
        # membership mode
        self._writes: dict[int, asyncio.Future[WriteResult]] = {}
        self._ddb_queue: deque[_QueuedWrite] = deque()
        self._ddb_inflight = 0
        self._write_seq = 0
        self._left_waiters: list[asyncio.Future[None]] = []
        self._agent_ops: dict[Any, asyncio.Future[agentio.AgentOpDone]] = {}
        self._agent_requests: dict[int, asyncio.Future[agentio.OperatorReply]] = {}
        self.left = False
        self._exit_after_leave = False
        #: mirror stream subscribers (`MirrorSub`), fed from applied transactions and view changes
        self.mirrors: set[MirrorSub] = set()
        self._ddb_ref: object | None = None
        #: event-loop stall watchdog and heap trimming (haa.hostd.resources)
        self.loopwatch = LoopWatch(self.counters, self._moved_bytes)

    # ------------------------------------------------------------------ lifecycle

    @property
    def mnode(self) -> MembershipNode | None:
        """The membership node (inside the agent layer when agents run), None in static mode."""
        node = getattr(self.node, "m", self.node)
        return node if isinstance(node, MembershipNode) else None

    @property
    def incarnation(self) -> int:
        return self.core.inc if self.core is not None else 0

    def _new_incarnation(self, above: int) -> int:
        inc = max(time.time_ns(), above + 1)
        d = self.config.data_dir
        if d is not None:
            f = d / "incarnation"
            with contextlib.suppress(OSError, ValueError):
                inc = max(inc, int(f.read_text().strip()) + 1)
            try:
                f.write_text(f"{inc}\n")
            except OSError as e:
                log_event(log, logging.WARNING, "incarnation_not_saved", error=str(e))
        return inc

    def _make_node(self, inc: int) -> None:
        cfg = self.config
        self.ident.inc = inc
        self._oac_seq_seen = 0
        if not self.membership:
            self.node = self.core = HostCore(self.name, inc, list(cfg.peers), cfg.core, evaluate=self.evaluate)
            return
        known = [] if cfg.forget_group else self._load_known_hosts()
        if self.mnode is not None:
            # a reincarnation: apply to the hosts the previous incarnation knew as members
            known = [(m.name, m.addr) for m in self.mnode.state.members if m.name != self.name] or known
        ncfg = dataclass_replace(cfg.node, core=cfg.core) if cfg.node is not None else NodeConfig(core=cfg.core)
        node = MembershipNode(self.name, inc, self.advertise, cfg.core_processes, ncfg, known_hosts=known)
        self.node = AgentNode(node, cfg.agent) if cfg.agents else node
        self.core = node.core
        self._oac_seq_seen = 0

    def _known_hosts_file(self) -> Path | None:
        d = self.config.data_dir
        return d / "known_hosts.json" if d is not None else None

    def _load_known_hosts(self) -> list[tuple[str, str]]:
        """Hosts a previous incarnation had as fellow members (docs/membership.md, "restarts")."""
        f = self._known_hosts_file()
        if f is None or not f.exists():
            return []
        try:
            # a file of our own, read with the limits of every file HAA reads (a corrupt or huge one is ignored)
            data = files.load_json(f, what="known hosts file", max_bytes=1 << 20)
            out = [(str(n), str(a)) for n, a in data["members"] if n != self.name][:MAX_KNOWN_HOSTS]
        except (OSError, ValueError, KeyError, TypeError) as e:
            log_event(log, logging.WARNING, "known_hosts_unreadable", file=str(f), error=str(e))
            return []
        log_event(log, logging.INFO, "known_hosts", hosts=[n for n, _ in out])
        return out

    def _save_known_hosts(self, members: Any) -> None:
        f = self._known_hosts_file()
        if f is None:
            return
        data = {"members": [[m.name, m.addr] for m in members if m.name != self.name]}
        tmp = f.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(data))
            os.replace(tmp, f)
        except OSError as e:
            log_event(log, logging.WARNING, "known_hosts_not_saved", error=str(e))

    def _forget_known_hosts(self) -> None:
        f = self._known_hosts_file()
        if f is not None:
            with contextlib.suppress(OSError):
                f.unlink()

    async def start(self) -> None:
        """Bind the server, start the links and the core."""
        cfg = self.config
        if cfg.data_dir is not None:
            cfg.data_dir.mkdir(parents=True, exist_ok=True)
        self._log_handlers = setup_logging(
            self.ident, cfg.data_dir / f"{cfg.name}.jsonl" if cfg.data_dir else None, cfg.log_level, cfg.log_stderr
        )
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._clock_offset = loop.time() - time.monotonic()
        self._proc.cpu_percent(None)
        inc = self._new_incarnation(0)
        self.transport.incarnation = inc
        # imported here because haa.hostd.control imports this module
        from haa.hostd.control import HostControlService

        tune_malloc()  # before the gRPC server starts its threads (their arenas)
        server = aio.server(options=Transport.server_options())
        self.transport.add_to_server(server)
        HostControlService(self).add_to_server(server)
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
        ufd = cfg.core.ufd
        log_event(
            log,
            logging.INFO,
            "startup",
            listen=cfg.listen,
            port=self.port,
            peers=cfg.peers,
            core_processes=cfg.core_processes,
            advertise=self.advertise if self.membership else "",
            qos={"td": ufd.qos.td_upper, "tmr": ufd.qos.tmr_lower, "tm": ufd.qos.tm_upper},
            exclude_after=cfg.core.exclude_after,
            host_link=cfg.host_link,
            link_port=self.transport.tcp_port,
        )
        if self.membership and cfg.agents:
            from haa.hostd.agentdriver import AgentDriver

            self.agents = AgentDriver(self, cfg.data_dir, hang_timeout=cfg.agent_hang_timeout)
            await self.agents.start()
        if cfg.tls is not None:
            # after the agents' fork server started (it keeps the real stderr); see haa.tls.HandshakeTap
            self._tap = HandshakeTap(lambda reason: loop.call_soon_threadsafe(self._tls_refused, reason))
            self._tap.start()
        self.transport.start()
        self.loopwatch.start()
        self._feed(self.node.start)

    def _tls_refused(self, reason: str) -> None:
        """gRPC refused a TLS handshake (no client certificate, another CA's, expired): count and log it."""
        self.counters["rejected_tls_handshake"] += 1
        self.counters["rejected_tls_handshake." + reason.lower()[:60]] += 1
        if self.transport.limiter.allow("tls_handshake"):
            log_event(log, logging.WARNING, "reject_tls_handshake", reason=reason)

    def request_stop(self) -> None:
        """Ask `run()` to return."""
        self._stopped.set()

    def request_shutdown(self) -> None:
        """SIGTERM/SIGINT: in membership mode leave the group gracefully first (at most `leave_timeout`
        seconds), then stop; a second signal stops at once."""
        if not self.membership or self.left or self._exit_after_leave or self.node is None:
            self.request_stop()
            return
        self._exit_after_leave = True
        loop = self._loop
        assert loop is not None
        task = loop.create_task(self._leave_then_stop())
        self.stream_tasks.add(task)
        task.add_done_callback(self.stream_tasks.discard)

    async def _leave_then_stop(self) -> None:
        try:
            drain = self.config.agent.drain_timeout if self.agents is not None else 0.0
            await self.leave(timeout=self.config.leave_timeout + drain)
        except (TimeoutError, WriteFailed) as e:
            log_event(log, logging.WARNING, "leave_incomplete", reason=str(e) or "timeout")
        finally:
            self.request_stop()

    async def run(self) -> None:
        """Start, serve until `request_stop()`, then shut down gracefully."""
        await self.start()
        try:
            await self._stopped.wait()
        finally:
            await self.stop()

    @property
    def stopping(self) -> bool:
        return self._stopping

    async def stop(self) -> None:
        if self._stopping:
            return
        self._stopping = True
        log_event(log, logging.INFO, "shutdown", delivered=self.delivered_count, hash=self.delivered_hash)
        self.loopwatch.stop()
        for h in self._timers.values():
            h.cancel()
        self._timers.clear()
        for fut in [*self._waiters.values(), *self._writes.values(), *self._left_waiters]:
            if not fut.done():
                fut.set_exception(RuntimeError(f"{self.name} is shutting down"))
        for sub in list(self.mirrors):
            sub.close()
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

    def _feed(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Call a core input with the current time, then carry out its effects."""
        try:
            res = fn(time.monotonic(), *args)
        except Exception:
            self.counters["core_errors"] += 1
            log.exception("core input failed", extra={"event": "core_error", "fields": {"input": fn.__name__}})
            self._apply()
            return None
        self._apply()
        return res

    def _on_envelopes(self, sender: str, sender_inc: int, items: list[tuple[int, Message]]) -> None:
        node = self.node
        if node is None:
            return
        now = time.monotonic()
        on_message = node.on_message
        for dst_inc, msg in items:
            try:
                on_message(now, sender, sender_inc, dst_inc, msg)
            except Exception:
                self.counters["core_errors"] += 1
                log.exception(
                    "core failed on a message",
                    extra={"event": "core_error", "fields": {"src": sender, "msg": type(msg).__name__}},
                )
        self._apply()

    def _on_peer_incarnation(self, peer: str, inc: int) -> None:
        if self.node is not None:
            self._feed(self.node.on_peer_info, peer, inc)

    def _fire(self, key: Hashable, at: float) -> None:
        self._timers.pop(key, None)
        node = self.node
        if node is None:
            return
        now = time.monotonic()
        if now < at:  # the loop may run a timer a hair early; the core must see its deadline reached
            now = at
        try:
            node.on_timer(now, key)
        except Exception:
            self.counters["core_errors"] += 1
            log.exception("core failed on a timer", extra={"event": "core_error", "fields": {"key": repr(key)}})
        self._apply()

    # ------------------------------------------------------------------ effects

    def _apply(self) -> None:
        node = self.node
        if node is None:
            return
        try:
            effects = node.drain()
        except Exception:
            # a bug in the core: never let it end the caller (a link's receive loop, a timer, an RPC) — a link
            # that stops reading wedges the whole group (issue 13, defect 1)
            self.counters["core_errors"] += 1
            log.exception("core drain failed", extra={"event": "core_error", "fields": {"input": "drain"}})
            return
        core = self.core
        if core is not None and core.oac._seq != self._oac_seq_seen:
            t_prop = time.monotonic()
            inc = core.oac.inc
            for s in range(self._oac_seq_seen + 1, core.oac._seq + 1):
                self._proposed_at.setdefault(TxId(self.name, inc, s), t_prop)
            self._oac_seq_seen = core.oac._seq
        if not effects:
            return
        send = self.transport.send
        reincarnate_by: str | None = None
        now = time.monotonic()
        for e in effects:
            t = type(e)
            if t is Send:
                send(e.dst, e.dst_inc, e.msg, e.lazy)  # type: ignore[union-attr]
            elif t is SetTimer:
                self._set_timer(e.key, e.at)  # type: ignore[union-attr]
            elif t is CancelTimer:
                h = self._timers.pop(e.key, None)  # type: ignore[union-attr]
                if h is not None:
                    h.cancel()
            elif t is Decided:
                self._on_decided(now, e)  # type: ignore[arg-type]
            elif t is Deliver:
                self._on_deliver(now, e)  # type: ignore[arg-type]
            elif t is Closed:
                self.counters["oac_closed"] += 1
            elif t is Suspicion:
                log_event(
                    log,
                    logging.INFO,
                    "suspicion",
                    peer=e.peer,
                    inc=e.inc,
                    suspected=e.suspected,  # type: ignore[union-attr]
                )
            elif t is PeerDead:
                log_event(log, logging.WARNING, "peer_dead", peer=e.peer, inc=e.inc, reason=e.reason)  # type: ignore[union-attr]
            elif t is Reincarnate:
                reincarnate_by = e.by  # type: ignore[union-attr]
            elif t is Log:
                # the core also logs what a typed effect above already carries: keep those at debug level
                ev = e.event  # type: ignore[union-attr]
                level = logging.DEBUG if ev in _TYPED_EVENTS else logging.ERROR if ev in _ERROR_EVENTS else logging.INFO
                log_event(log, level, e.event, **e.fields)  # type: ignore[union-attr]
            elif t is Connect:
                self.transport.add_peer(e.name, e.addr)  # type: ignore[union-attr]
            elif t is AppliedTx:
                self._on_applied(e)  # type: ignore[arg-type]
            elif t is ViewChange:
                self._on_view(e)  # type: ignore[arg-type]
            elif t is WriteDone:
                self._on_write_done(e)  # type: ignore[arg-type]
            elif t is Left:
                self._on_left()
            elif t in _AGENT_COMMANDS:
                if self.agents is not None:
                    self.agents.command(e)
            elif t is agentio.AgentTimeline:
                if self.agents is not None:
                    self.agents.on_timeline(e)
            elif t is agentio.AgentOpDone:
                self._on_agent_op(e)  # type: ignore[arg-type]
            elif t is agentio.OperatorReply:
                fut = self._agent_requests.pop(e.conv, None)  # type: ignore[union-attr]
                if fut is not None and not fut.done():
                    fut.set_result(e)
        if self.mirrors:
            self._check_replica()
        if self.agents is not None:
            self.agents.check_replica()
        if reincarnate_by is not None:
            self._reincarnate(reincarnate_by)

    def _set_timer(self, key: Hashable, at: float) -> None:
        old = self._timers.get(key)
        if old is not None:
            old.cancel()
        loop = self._loop
        assert loop is not None
        self._timers[key] = loop.call_at(at + self._clock_offset, self._fire, key, at)

    def _on_decided(self, now: float, e: Decided) -> None:
        txid = e.txid
        t0 = self._proposed_at.pop(txid, None)
        p2d = now - t0 if t0 is not None else 0.0
        if t0 is not None:
            self.propose_to_decide.append(p2d)
        if e.commit:
            self._decided_at[txid] = now
            if t0 is not None:
                self._p2d[txid] = p2d
            self.counters["oac_committed"] += 1
        else:
            self.counters["oac_aborted"] += 1
            fut = self._waiters.get(txid)
            if fut is not None and not fut.done():
                fut.set_exception(TransactionAborted(txid, self.participants_of(txid), p2d))

    def _on_deliver(self, now: float, e: Deliver) -> None:
        txid = e.txid
        t1 = self._decided_at.pop(txid, None)
        d2d = now - t1 if t1 is not None else 0.0
        self.decide_to_deliver.append(d2d)
        self.delivered_hash = chain_hash(self.delivered_hash, txid, e.payload)
        log_ = self.delivered
        log_.append(DeliveredEntry(self.delivered_count, txid, e.order, e.payload, self.delivered_hash))
        self.delivered_bytes += len(e.payload)
        if len(log_) > MAX_DELIVERED or self.delivered_bytes > MAX_DELIVERED_BYTES:
            self._trim_delivered()
        self.counters["oac_delivered"] += 1
        ev = self._delivery_event
        self._delivery_event = asyncio.Event()
        ev.set()
        fut = self._waiters.get(txid)
        p2d = self._p2d.pop(txid, 0.0)
        if fut is not None and not fut.done():
            fut.set_result(ProposeResult(txid, self.participants_of(txid), p2d, d2d))

    def _on_superseded(self, peer: str, newer: int) -> None:
        """`peer` knows a newer incarnation of this host's name: this process was displaced (a second daemon
        under our name, or a claim, was accepted while we were silent). Rejoin as a new incarnation above it,
        dropping our agent instances (docs/membership.md, "incarnation claims")."""
        if self.node is None or self._stopping or self.left or newer <= self.incarnation:
            return
        self._reincarnate(f"superseded at {peer} by incarnation {newer}", above=newer)

    def _trim_delivered(self) -> None:
        """Drop the oldest entries of the delivered log until at most half of MAX_DELIVERED entries and half of
        MAX_DELIVERED_BYTES payload bytes are left (the newest entry always stays)."""
        log_ = self.delivered
        left = self.delivered_bytes
        drop = max(0, len(log_) - MAX_DELIVERED // 2)
        for entry in log_[:drop]:
            left -= len(entry.payload)
        while drop < len(log_) - 1 and left > MAX_DELIVERED_BYTES // 2:
            left -= len(log_[drop].payload)
            drop += 1
        del log_[:drop]
        self.delivered_base += drop
        self.delivered_bytes = left

    def _reincarnate(self, by: str, above: int = 0) -> None:
        old = self.core
        assert old is not None
        inc = self._new_incarnation(max(old.inc, above))
        log_event(log, logging.WARNING, "reincarnate", by=by, old=old.inc, new=inc)
        self._past_core_counters.update(old.counters)
        self.counters["reincarnations"] += 1
        for h in self._timers.values():
            h.cancel()
        self._timers.clear()
        for txid, fut in self._waiters.items():
            if not fut.done():
                fut.set_exception(HostReincarnated(f"{self.name} reincarnated while {txid} was open"))
        for fut in [*self._writes.values(), *self._left_waiters]:
            if not fut.done():
                fut.set_exception(WriteFailed(f"{self.name} restarted as a new incarnation (outcome unknown)"))
        self._writes.clear()
        self._left_waiters.clear()
        self._proposed_at.clear()
        self._decided_at.clear()
        self._p2d.clear()
        self._participants_cache.clear()
        if self.agents is not None:
            self.agents.kill_all("this host restarted as a new incarnation")
        self._make_node(inc)
        self.transport.set_incarnation(inc)
        now = time.monotonic()
        node = self.node
        assert node is not None
        node.start(now)
        # the links already know the peers' incarnations; tell the new core (it arms their exclusion timers)
        for peer, link in self.transport.links.items():
            if link.receiver_inc:
                node.on_peer_info(now, peer, link.receiver_inc)
        self._apply()

    # ------------------------------------------------------------------ membership effects

    def _on_applied(self, e: AppliedTx) -> None:
        self.counters["global_applied"] += 1
        if e.result is None or not self.mirrors:
            return
        if e.kind == "ddb":
            data = decode_tx(e.payload).data  # type: ignore[union-attr]  # the DdbBatch inside the TxDdb
            ddb_seq = e.result.seq  # type: ignore[attr-defined]
            for sub in list(self.mirrors):
                sub.push(("batch", ddb_seq, data, e.seq))
        elif e.kind == "seq":  # a sequencer batch: every DDB batch in it that was applied, in order
            entries = decode_tx(e.payload).entries  # type: ignore[union-attr]
            for entry, r in zip(entries, e.result, strict=True):  # type: ignore[call-overload]
                if r.applied and r.kind == "ddb" and r.result is not None:
                    data = decode_tx(entry.tx).data  # type: ignore[union-attr]
                    for sub in list(self.mirrors):
                        sub.push(("batch", r.result.seq, data, e.seq))

    def _on_view(self, e: ViewChange) -> None:
        self.counters["view_changes"] += 1
        self._save_known_hosts(e.members)
        for sub in list(self.mirrors):
            if sub.views:
                sub.push(("view", e))

    def _on_write_done(self, e: WriteDone) -> None:
        fut = self._writes.pop(e.req, None)  # type: ignore[arg-type]
        if fut is None or fut.done():
            return
        if e.ok:
            fut.set_result(WriteResult(e.txid, e.seq, e.result, e.reason))  # type: ignore[arg-type]
        else:
            fut.set_exception(WriteFailed(e.reason))

    def _on_agent_op(self, e: agentio.AgentOpDone) -> None:
        fut = self._agent_ops.pop(e.req, None)  # type: ignore[arg-type]
        if fut is not None and not fut.done():
            fut.set_result(e)

    async def agent_op(self, call: Callable[..., Any], *args: Any, timeout: float = 10.0, **kw: Any) -> Any:
        """Run an operator request of the agent layer (`AgentNode.create_agent`, `remove_agent`, `move_agent`,
        `set_paused`) and wait for its `AgentOpDone`."""
        if not isinstance(self.node, AgentNode):
            raise NotMembershipMode(f"{self.name} does not run the agent layer")
        self._write_seq += 1
        req = ("op", self._write_seq)
        fut: asyncio.Future[agentio.AgentOpDone] = asyncio.get_running_loop().create_future()
        self._agent_ops[req] = fut
        def operator_request(now: float, *a: Any) -> Any:
            return call(now, *a, req=req, **kw)

        try:
            self._feed(operator_request, *args)
            return await asyncio.wait_for(fut, timeout)
        finally:
            self._agent_ops.pop(req, None)

    async def agent_request(self, ref: str, payload: bytes, timeout: float = 5.0) -> agentio.OperatorReply:
        """Send an operator request to an agent and wait for its reply (TimeoutError; LookupError for an
        unknown agent)."""
        node = self.node
        if not isinstance(node, AgentNode):
            raise NotMembershipMode(f"{self.name} does not run the agent layer")
        self._write_seq += 1
        conv = self._write_seq
        fut: asyncio.Future[agentio.OperatorReply] = asyncio.get_running_loop().create_future()
        self._agent_requests[conv] = fut
        try:
            if not self._feed(node.operator_request, ref, payload, conv):
                raise LookupError(f"unknown agent {ref!r}")
            return await asyncio.wait_for(fut, timeout)
        finally:
            self._agent_requests.pop(conv, None)

    def _on_left(self) -> None:
        self.left = True
        self._forget_known_hosts()
        for fut in self._left_waiters:
            if not fut.done():
                fut.set_result(None)
        self._left_waiters.clear()

    def _check_replica(self) -> None:
        """A joiner that installed its sponsor's state, or a new incarnation, has a new replica object:
        mirror subscribers need a fresh snapshot."""
        node = self.mnode
        if node is None:
            return
        ddb = node.state.ddb
        if ddb is not self._ddb_ref:
            self._ddb_ref = ddb
            for sub in list(self.mirrors):
                sub.push(("resync",))

    # ------------------------------------------------------------------ proposals

    def participants_of(self, txid: TxId) -> tuple[str, ...]:
        return self._participants_cache.get(txid, (self.name,))

    def _propose(self, payload: bytes, participants: list[str] | None) -> TxId:
        core = self.core
        if core is None:
            raise RuntimeError("host not started")
        now = time.monotonic()
        txid = core.propose(now, payload, participants)  # OacError (ValueError) on bad participants
        self._proposed_at[txid] = now
        tx = core.oac.txs.get(txid)
        parts = tuple(q for q, _ in tx.parts) if tx is not None and tx.parts else (self.name,)
        if len(self._participants_cache) > 10_000:
            self._participants_cache.clear()
        self._participants_cache[txid] = parts
        return txid

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
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[ProposeResult] = loop.create_future()
        self._waiters[txid] = fut
        try:
            self._apply()
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise ProposeTimeout(txid, self.participants_of(txid)) from None
        finally:
            self._waiters.pop(txid, None)

    # ------------------------------------------------------------------ global-state changes (membership mode)

    def _member_node(self) -> MembershipNode:
        node = self.mnode
        if node is None:
            raise NotMembershipMode(f"{self.name} runs a static peer list (--peers): no group, no DDB")
        return node

    async def submit(self, payload: bytes, kind: str = "ddb", timeout: float = 30.0) -> WriteResult:
        """Propose a global-state change to every member (a `DdbBatch` for `kind="ddb"`, any bytes for
        `kind="test"`) and wait until it is committed and applied here.

        Raises `WriteFailed` (not a member, leaving, gave up after aborts, this host restarted, timeout —
        after a timeout the change may still commit) or `NotMembershipMode`."""
        node = self._member_node()
        if self.left or node.leaving:
            raise WriteFailed("this host is leaving the group")
        self._write_seq += 1
        req = self._write_seq
        fut: asyncio.Future[WriteResult] = asyncio.get_running_loop().create_future()
        self._writes[req] = fut
        self.counters["writes_submitted"] += 1
        try:
            self._feed(self.node.submit, payload, req, kind)  # type: ignore[union-attr]
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise WriteFailed(f"not committed within {timeout:g} s (it may still commit)") from None
        finally:
            self._writes.pop(req, None)

    async def ddb_write(self, ops: list[Any], atomic: bool = False, timeout: float = 30.0) -> DdbWriteResult:
        """Write DDB ops (`haa.hostd.ddb.put/...`) to the group and wait until they are committed and applied
        here. Group commit: while `DDB_MAX_INFLIGHT` batches of this host are in OAC, further requests queue
        and then go out merged into one batch, in arrival order (an op sees the effects of the ops before
        it, as if the requests had been committed one after the other; they share one version number).
        `atomic` requests always travel alone, so "all or none" covers exactly their ops.

        Raises `WriteFailed` (see `submit`) or `NotMembershipMode`."""
        node = self._member_node()
        if self.left or node.leaving:
            raise WriteFailed("this host is leaving the group")
        if not ops:
            raise WriteFailed("empty batch")
        size = sum(op.ByteSize() for op in ops)
        if size > ddbmod.MAX_BATCH_BYTES:  # checked before anything is queued (docs/limits.md)
            raise WriteFailed(f"batch of {size} bytes > {ddbmod.MAX_BATCH_BYTES} (MAX_BATCH_BYTES)")
        why = ddbmod.check_json_sizes(ops)
        if why:
            raise WriteFailed(why)
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[DdbWriteResult] = loop.create_future()
        fut.add_done_callback(_retrieve)
        q = _QueuedWrite(list(ops), atomic, size, fut, sum(ddbmod.json_bytes(op) for op in ops))
        self._ddb_queue.append(q)
        self.counters["ddb_writes"] += 1
        self._flush_ddb()
        try:
            return await asyncio.wait_for(asyncio.shield(fut), timeout)
        except TimeoutError:
            q.abandoned = True  # not proposed yet: it never will be
            raise WriteFailed(f"not committed within {timeout:g} s (it may still commit)") from None

    def _flush_ddb(self) -> None:
        queue = self._ddb_queue
        if self._stopping or self.left:
            while queue:
                q = queue.popleft()
                if not q.fut.done():
                    q.fut.set_exception(WriteFailed("this host is stopping or left the group"))
            return
        loop = asyncio.get_running_loop()
        while queue and self._ddb_inflight < DDB_MAX_INFLIGHT:
            group: list[_QueuedWrite] = []
            ops: list[Any] = []
            size = 0
            json_size = 0
            while queue:
                q = queue[0]
                if q.abandoned or q.fut.done():
                    queue.popleft()
                    continue
                if group and (
                    q.atomic
                    or len(ops) + len(q.ops) > DDB_GROUP_MAX_OPS
                    or size + q.size > DDB_GROUP_MAX_BYTES
                    or json_size + q.json > ddbmod.MAX_BATCH_JSON_BYTES
                ):
                    break
                queue.popleft()
                group.append(q)
                ops.extend(q.ops)
                size += q.size
                json_size += q.json
                if q.atomic:
                    break
            if not group:
                return
            try:
                payload = ddbmod.encode_batch(ops, origin=self.name, atomic=group[0].atomic)
            except ddbmod.DdbError as e:  # (ddb_write checked each request; a group of them stays in bounds)
                for q in group:
                    if not q.fut.done():
                        q.fut.set_exception(WriteFailed(str(e)))
                continue
            self._write_seq += 1
            req = self._write_seq
            gfut: asyncio.Future[WriteResult] = loop.create_future()
            self._writes[req] = gfut
            self._ddb_inflight += 1
            self.counters["ddb_batches"] += 1
            self.counters["ddb_merged_writes"] += len(group) - 1
            gfut.add_done_callback(lambda f, g=group: self._ddb_group_done(g, f))
            assert self.mnode is not None
            self._feed(self.node.submit, payload, req, "ddb")  # type: ignore[union-attr]

    def _ddb_group_done(self, group: list[_QueuedWrite], gfut: asyncio.Future[WriteResult]) -> None:
        self._ddb_inflight -= 1
        exc = gfut.exception() if not gfut.cancelled() else WriteFailed("cancelled")
        res = None if exc is not None else gfut.result()
        r = res.result if res is not None else None
        if exc is None and r is None:
            exc = WriteFailed(res.reason if res is not None and res.reason else "committed but not applied")
        if exc is not None:
            reason = getattr(exc, "reason", None) or str(exc)
            for q in group:
                if not q.fut.done():
                    q.fut.set_exception(WriteFailed(reason))
        else:
            assert res is not None
            i = 0
            for q in group:
                n = len(q.ops)
                if not q.fut.done():
                    q.fut.set_result(
                        DdbWriteResult(res.txid, res.global_seq, r.seq, tuple(r.results[i : i + n]), len(group))  # type: ignore[union-attr]
                    )
                i += n
        self._flush_ddb()

    async def leave(self, timeout: float = 10.0) -> None:
        """Leave the group (Alg. 3 ll. 14-21) and wait until the group has removed this host. The process
        keeps running (stop it with `request_stop`); `TimeoutError` if the removal did not commit in time."""
        self._member_node()
        if self.left:
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._left_waiters.append(fut)
        self._feed(self.node.leave)  # type: ignore[union-attr]  # the agent layer hands its agents over first
        await asyncio.wait_for(fut, timeout)

    # ------------------------------------------------------------------ queries

    @property
    def delivered_count(self) -> int:
        """Transactions delivered since this process started (the log keeps the latest MAX_DELIVERED)."""
        return self.delivered_base + len(self.delivered)

    async def wait_delivered(self, count: int) -> None:
        """Return once at least `count` transactions are in the delivered log."""
        while self.delivered_count < count:
            await self._delivery_event.wait()

    def all_counters(self) -> Counter[str]:
        c = Counter(self.counters)
        core = self.core
        for k, v in (self._past_core_counters + (core.counters if core else Counter())).items():
            c["core." + k] += v
        return c

    def status(self) -> dict[str, Any]:
        core = self.core
        assert core is not None
        peers = []
        for row in core.peer_view():
            q = row["name"]
            peers.append(
                {
                    **row,
                    "address": self.transport.peers.get(q, ""),
                    "connected": self.transport.connected(q),
                    "queued": self.transport.queued(q),
                }
            )
        mem = self._proc.memory_info()
        cpu = self._proc.cpu_times()
        group: dict[str, Any] = {"mode": "static"}
        node = self.mnode
        if node is not None:
            st = node.state
            ns = node.status()
            group = {
                "mode": "membership",
                "member": ns["member"],
                "members": ns["members"],
                "member_info": [
                    {"name": m.name, "incarnation": m.inc, "address": m.addr, "suspected": node._suspected(m.proc)}
                    for m in st.members
                ],
                "leader": ns["leader"],
                "view": ns["view"],
                "rank": ns["rank"],
                "suspicions": ns["suspected"],
                "ddb_size": st.ddb.size,
                "ddb_hash": st.ddb.content_hash(),
                "ddb_seq": st.ddb.seq,
                "global_seq": st.seq,
                "state_hash": ns["state_hash"],
                "group_id": st.genesis,
                "group_correct": st.group_correct,
                "locked": ns["locked"],
                "applicants": ns["applicants"],
                "leaving": node.leaving,
            }
        return {
            **group,
            "cpu_seconds": cpu.user + cpu.system,
            "name": self.name,
            "incarnation": core.inc,
            "peers": peers,
            "active_transactions": core.oac.active_count,
            "decided_transactions": core.oac.decided_count,
            "delivered": self.delivered_count,
            "delivered_hash": self.delivered_hash,
            "counters": self.all_counters(),
            "cpu_percent": self._proc.cpu_percent(None),
            "rss_bytes": mem.rss,
            "uptime": time.monotonic() - self.started_at,
        }

    def take_latencies(self, reset: bool) -> tuple[list[float], list[float]]:
        """(decide->deliver, propose->decide) samples; cleared if `reset`."""
        d2d, p2d = list(self.decide_to_deliver), list(self.propose_to_decide)
        if reset:
            self.decide_to_deliver.clear()
            self.propose_to_decide.clear()
        return d2d, p2d


class MirrorSub:
    """One mirror-stream subscriber: a queue of ("batch", ddb_seq, payload, global_seq), ("view", ViewChange)
    and ("resync",) items the control service turns into `MirrorEvent`s. A subscriber more than `limit`
    items behind is cut back to one ("resync",): it gets a fresh snapshot instead of the batches."""

    def __init__(self, views: bool, limit: int = 10_000, limit_bytes: int = MIRROR_SUB_MAX_BYTES) -> None:
        self.views = views
        self.limit = limit
        self.limit_bytes = limit_bytes
        self.queue: deque[tuple[Any, ...]] = deque()
        self.bytes = 0  # payload bytes of the queued batches
        self.closed = False
        self._event = asyncio.Event()

    def push(self, item: tuple[Any, ...]) -> None:
        size = len(item[2]) if item[0] == "batch" else 0
        if len(self.queue) >= self.limit or (self.queue and self.bytes + size > self.limit_bytes):
            self.queue.clear()
            self.bytes = 0
            item, size = ("resync",), 0
        self.queue.append(item)
        self.bytes += size
        self._event.set()

    def close(self) -> None:
        self.closed = True
        self._event.set()

    async def get(self) -> tuple[Any, ...] | None:
        """The next item, or None once closed."""
        while not self.queue:
            if self.closed:
                return None
            self._event.clear()
            await self._event.wait()
        item = self.queue.popleft()
        if item[0] == "batch":
            self.bytes -= len(item[2])
        return item


def advertised_address(listen: str, port: int) -> str:
    """The address other hosts reach this one at: `listen` with the bound port; a wildcard listen address
    (0.0.0.0, [::]) is replaced by this machine's host name (a compose service's name)."""
    host = listen.rpartition(":")[0]
    if host in ("", "0.0.0.0", "[::]", "::"):
        host = socket.gethostname()
    return f"{host}:{port}"


def _retrieve(fut: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (its waiter may have timed out and gone)."""
    if not fut.cancelled():
        fut.exception()
