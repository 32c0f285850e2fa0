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
* **Delivered log.** Every committed transaction this process delivered, in delivery order, as
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
import logging
import time
from collections import Counter, deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import psutil
from grpc import aio

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
from haa.hostd.logs import LOGGER_NAME, HostIdentity, log_event, setup_logging, teardown_logging
from haa.hostd.messages import Message, TxId
from haa.hostd.transport import Transport

log = logging.getLogger(LOGGER_NAME + ".runtime")

GENESIS_HASH = "0" * 64
#: core `Log` events that duplicate a typed effect (`PeerDead`) the runtime logs itself
_TYPED_EVENTS = frozenset({"peer_dead"})
#: how many latency samples are kept (oldest dropped first)
MAX_SAMPLES = 100_000


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


class HostRuntime:
    """One haa-hostd process: core + transport + timers + control service (see the module docstring)."""

    def __init__(self, config: RuntimeConfig, evaluate: Callable[[TxId, bytes], bool] | None = None) -> None:
        self.config = config
        self.name = config.name
        self.evaluate = evaluate
        self.counters: Counter[str] = Counter()
        self.ident = HostIdentity(config.name, 0)
        self.core: HostCore | None = None
        self.transport = Transport(
            config.name,
            config.token,
            config.peers,
            on_envelopes=self._on_envelopes,
            on_peer_incarnation=self._on_peer_incarnation,
            counters=self.counters,
        )
        self.server: aio.Server | None = None
        self.port = 0
        self.delivered: list[DeliveredEntry] = []
        self.delivered_hash = GENESIS_HASH
        self.propose_to_decide: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.decide_to_deliver: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.started_at = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clock_offset = 0.0
        self._timers: dict[Hashable, asyncio.TimerHandle] = {}
        self._proposed_at: dict[TxId, float] = {}
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

    # ------------------------------------------------------------------ lifecycle

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

    def _make_core(self, inc: int) -> HostCore:
        core = HostCore(self.name, inc, list(self.config.peers), self.config.core, evaluate=self.evaluate)
        self.ident.inc = inc
        return core

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
        self.core = self._make_core(inc)
        self.transport.incarnation = inc
        # imported here because haa.hostd.control imports this module
        from haa.hostd.control import HostControlService

        server = aio.server(options=Transport.server_options())
        self.transport.add_to_server(server)
        HostControlService(self).add_to_server(server)
        self.port = server.add_insecure_port(cfg.listen)
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
            qos={"td": ufd.qos.td_upper, "tmr": ufd.qos.tmr_lower, "tm": ufd.qos.tm_upper},
            exclude_after=cfg.core.exclude_after,
        )
        self.transport.start()
        self._feed(self.core.start)

    def request_stop(self) -> None:
        """Ask `run()` to return (signal handlers call this)."""
        self._stopped.set()

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
        log_event(log, logging.INFO, "shutdown", delivered=len(self.delivered), hash=self.delivered_hash)
        for h in self._timers.values():
            h.cancel()
        self._timers.clear()
        for fut in self._waiters.values():
            if not fut.done():
                fut.set_exception(RuntimeError(f"{self.name} is shutting down"))
        await self.transport.stop()
        for task in list(self.stream_tasks):
            task.cancel()
        for _ in range(3):
            await asyncio.sleep(0)
        if self.server is not None:
            await self.server.stop(0.5)
        teardown_logging(self._log_handlers)
        self._log_handlers = []
        self._stopped.set()

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
        core = self.core
        if core is None:
            return
        now = time.monotonic()
        on_message = core.on_message
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
        if self.core is not None:
            self._feed(self.core.on_peer_info, peer, inc)

    def _fire(self, key: Hashable, at: float) -> None:
        self._timers.pop(key, None)
        core = self.core
        if core is None:
            return
        now = time.monotonic()
        if now < at:  # the loop may run a timer a hair early; the core must see its deadline reached
            now = at
        try:
            core.on_timer(now, key)
        except Exception:
            self.counters["core_errors"] += 1
            log.exception("core failed on a timer", extra={"event": "core_error", "fields": {"key": repr(key)}})
        self._apply()

    # ------------------------------------------------------------------ effects

    def _apply(self) -> None:
        core = self.core
        if core is None:
            return
        effects = core.drain()
        if not effects:
            return
        send = self.transport.send
        reincarnate_by: str | None = None
        now = time.monotonic()
        for e in effects:
            t = type(e)
            if t is Send:
                send(e.dst, e.dst_inc, e.msg)  # type: ignore[union-attr]
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
                level = logging.DEBUG if e.event in _TYPED_EVENTS else logging.INFO  # type: ignore[union-attr]
                log_event(log, level, e.event, **e.fields)  # type: ignore[union-attr]
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
        self.delivered.append(DeliveredEntry(len(self.delivered), txid, e.order, e.payload, self.delivered_hash))
        self.counters["oac_delivered"] += 1
        ev = self._delivery_event
        self._delivery_event = asyncio.Event()
        ev.set()
        fut = self._waiters.get(txid)
        p2d = self._p2d.pop(txid, 0.0)
        if fut is not None and not fut.done():
            fut.set_result(ProposeResult(txid, self.participants_of(txid), p2d, d2d))

    def _reincarnate(self, by: str) -> None:
        old = self.core
        assert old is not None
        inc = self._new_incarnation(old.inc)
        log_event(log, logging.WARNING, "reincarnate", by=by, old=old.inc, new=inc)
        self._past_core_counters.update(old.counters)
        self.counters["reincarnations"] += 1
        for h in self._timers.values():
            h.cancel()
        self._timers.clear()
        for txid, fut in self._waiters.items():
            if not fut.done():
                fut.set_exception(HostReincarnated(f"{self.name} reincarnated while {txid} was open"))
        self._proposed_at.clear()
        self._decided_at.clear()
        self._p2d.clear()
        self._participants_cache.clear()
        self.core = self._make_core(inc)
        self.transport.set_incarnation(inc)
        now = time.monotonic()
        self.core.start(now)
        # the links already know the peers' incarnations; tell the new core (it arms their exclusion timers)
        for peer, link in self.transport.links.items():
            if link.receiver_inc:
                self.core.on_peer_info(now, peer, link.receiver_inc)
        self._apply()

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

    # ------------------------------------------------------------------ queries

    async def wait_delivered(self, count: int) -> None:
        """Return once at least `count` transactions are in the delivered log."""
        while len(self.delivered) < count:
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
                    "address": self.config.peers.get(q, ""),
                    "connected": self.transport.connected(q),
                    "queued": self.transport.queued(q),
                }
            )
        mem = self._proc.memory_info()
        return {
            "name": self.name,
            "incarnation": core.inc,
            "peers": peers,
            "active_transactions": core.oac.active_count,
            "decided_transactions": core.oac.decided_count,
            "delivered": len(self.delivered),
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
