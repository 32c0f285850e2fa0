"""The operator/control API of one haa-hostd (`haa.v1.HostControl`, proto/haa/pb/control.proto).

`HostControlService` serves it on the host's gRPC server, next to the transport, through `haa.rpcguard`
(requests arrive as raw bytes): every call must carry the cluster token in metadata `x-haa-token`, checked
*before* the request is decoded (else `UNAUTHENTICATED`, counted as `rejected_unauthenticated` and
`control_rejected`); an authenticated request that does not parse gets `INVALID_ARGUMENT` (counted as
`control_malformed` and `control_rejected`); an exception escaping a handler gets a proper status, never
UNKNOWN (counted as `control_errors`): `DEADLINE_EXCEEDED` for a timeout (e.g. an `AgentSpawn` whose commit
did not come back in time), `INVALID_ARGUMENT` for bad input, `FAILED_PRECONDITION` without the membership
or agent layer, `UNAVAILABLE` for a write the group gave up, `INTERNAL` for a bug (logged with its
traceback). Limits: docs/limits.md, "Control API and agent messages".

* `Status`: who this host is, its view of every peer (incarnation, suspected, excluded, link connected,
  the heartbeat period eta it asked for and the safety margin alpha), OAC activity, the delivered count and
  hash chain, every counter (transport, runtime, and the core's as `core.*`), the RSS of this process and
  its CPU use since the previous `Status` call (psutil).
* `Propose`: start an OAC transaction (empty participant list: this host and every peer it trusts); with
  `wait`, reply after the local decision and delivery (or abort, or the call's deadline / 30 s).
* `Deliveries`: stream the delivered log from an index and keep following new deliveries until the client
  cancels.
* `Latencies`: the propose->decide and decide->deliver samples this host recorded (optionally reset).

Membership mode (`--core`) adds the group to `Status` (members in rank order, leader, view id, own rank,
suspicions, DDB size/hash/seq, global sequence and state hash) and serves the DDB:

* `DdbWrite`: a batch of ops proposed to every member by OAC; the reply comes once the batch is committed
  and applied here, with each op's result (`committed=False` and a `reason` if it was not: not a member yet,
  leaving, gave up, timeout). In membership mode `Propose` is a test payload submitted the same way.
* `DdbGet`: local reads (keys, or a prefix).
* `DdbLoad`: a benchmark write load generated inside the host (`haactl bench ddb`): concurrent writers
  awaiting single-put writes, with their latencies (a client's own RPC cost is not what is measured).
* `Mirror`: the thesis' AgentMirror — a snapshot of the replica, then every applied batch and (optionally)
  every view change; a fresh snapshot whenever the replica was replaced or the subscriber fell behind.
* `Leave`: graceful leave (Alg. 3 ll. 14-21); with `exit` the process stops once the group removed it.

Static mode answers the DDB calls with `FAILED_PRECONDITION`. The agent calls (AgentList, AgentSpawn, AgentKill,
AgentRemove, AgentMove, AgentSend, Alloc, AgentEvents) are in `haa.hostd.agentcontrol`.

Under mutual TLS (`--tls-dir`, docs/deploy.md) the server takes only clients with a certificate of the cluster's
CA (the TLS handshake refuses the others: `rejected_tls_handshake`, haa.hostd.runtime), and the control API
only *client* certificates (haactl's): a host's certificate is refused like a wrong token (counted as
`rejected_not_client` too), so a host's key cannot drive the cluster. The token is checked as well.

`ControlClient` is a small blocking client for tests, benchmarks and tools (`tls` + `server_name`: over TLS,
checking that the server holds host `server_name`'s certificate).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import grpc
from grpc import aio

from haa import rpcguard
from haa import tls as tlsmod
from haa.core.ddb.ops import put
from haa.core.oac.oac import OacError
from haa.hostd.agentcontrol import AgentClientMixin, AgentControl
from haa.hostd.logs import LOGGER_NAME, RateLimiter, log_event
from haa.hostd.mirrors import MIRROR_SEND_TIMEOUT, MirrorRefused
from haa.hostd.outcomes import (
    HostReincarnated,
    InvalidWrite,
    NotMembershipMode,
    ProposeTimeout,
    TransactionAborted,
    WriteFailed,
)
from haa.hostd.transport import MAX_MESSAGE
from haa.pb import control_pb2 as cpb
from haa.pb import control_pb2_grpc
from haa.pb import ddb_pb2 as dpb
from haa.pb import hostlink_pb2 as pb
from haa.tls import ClientTls

if TYPE_CHECKING:
    from haa.core.messages import TxId
    from haa.hostd.agentdriver import AgentDriver
    from haa.hostd.runtime import HostRuntime

log = logging.getLogger(LOGGER_NAME + ".control")

MD_TOKEN = "x-haa-token"
DEFAULT_WAIT = 30.0
#: bounds of a DdbLoad request (a benchmark load generated inside the host)
MAX_LOAD_WRITERS = 1000
MAX_LOAD_SECONDS = 300.0
MAX_LOAD_VALUE = 64 * 1024
#: the service as protobuf describes it (methods, request and reply types): what `add_to_server` registers
SERVICE = cpb.DESCRIPTOR.services_by_name["HostControl"]
#: exceptions of the runtime that escape a handler, and the status each gets (before rpcguard's defaults)
STATUSES: tuple[tuple[type[BaseException], grpc.StatusCode], ...] = (
    (NotMembershipMode, grpc.StatusCode.FAILED_PRECONDITION),
    (WriteFailed, grpc.StatusCode.UNAVAILABLE),
    (HostReincarnated, grpc.StatusCode.ABORTED),
    (TransactionAborted, grpc.StatusCode.ABORTED),
)


class _ClientGone(Exception):
    """A stream's call ended while we were writing to it (cancelled, deadline, connection closed)."""


def _txid(t: TxId) -> pb.TxId:
    return pb.TxId(host=t.host, incarnation=t.inc, seq=t.seq)


#: membership fields of `HostRuntime.status()` that map one to one onto `StatusReply`
_GROUP_KEYS = (
    "member",
    "members",
    "leader",
    "view",
    "rank",
    "suspicions",
    "ddb_size",
    "ddb_hash",
    "ddb_seq",
    "global_seq",
    "state_hash",
    "group_id",
    "group_correct",
    "locked",
    "applicants",
    "leaving",
)


def _group_fields(st: dict[str, Any]) -> dict[str, Any]:
    if st["mode"] != "membership":
        return {}
    return {k: st[k] for k in _GROUP_KEYS} | {"member_info": [cpb.MemberInfo(**m) for m in st["member_info"]]}


class HostControlService(AgentControl, control_pb2_grpc.HostControlServicer):
    """`haa.v1.HostControl` backed by a `HostRuntime` and, for the agent calls, its agent driver (both given by
    the composition root, haa.hostd.daemon.build_host; `agents` None without the agent layer)."""

    def __init__(self, runtime: HostRuntime, agents: AgentDriver | None = None) -> None:
        self.rt = runtime
        self.agents = agents
        self._limiter = RateLimiter(1.0)

    def add_to_server(self, server: aio.Server) -> None:
        """Register every method with raw requests: the token is checked before decoding (haa.rpcguard)."""
        guard = rpcguard.Guard(
            authenticate=self._authenticate,
            on_event=self._guard_event,
            statuses=STATUSES,
            log=log,
        )
        server.add_generic_rpc_handlers((rpcguard.guarded_handler(SERVICE, self, guard),))

    def _authenticate(self, ctx: aio.ServicerContext) -> bool:
        """The cluster token, and under TLS a client (operator) certificate."""
        if not self.rt.transport.check_token(ctx.invocation_metadata()):
            return False
        if self.rt.config.tls is None:
            return True
        ident = tlsmod.peer_identity(ctx)
        if ident is not None and ident[0] == tlsmod.CLIENT:
            return True
        self.rt.counters["rejected_not_client"] += 1
        if self._limiter.allow("not_client"):
            log_event(log, logging.WARNING, "control_reject_not_client",
                      certificate=f"{ident[0]} {ident[1]}" if ident else "none", peer=ctx.peer())
        return False

    def _guard_event(self, kind: str, method: str, detail: str, exc: BaseException | None) -> None:
        """Count (and log, rate-limited) a call refused before its handler or a handler's exception."""
        c = self.rt.counters
        if kind == "unauthenticated":
            c["rejected_unauthenticated"] += 1
            c["control_rejected"] += 1
            event, level = "control_reject_unauthenticated", logging.WARNING
        elif kind == "malformed":
            c["control_malformed"] += 1
            c["control_rejected"] += 1
            event, level = "control_reject_malformed", logging.WARNING
        else:
            c["control_errors"] += 1
            internal = detail.startswith("INTERNAL")
            event, level = ("control_internal_error", logging.ERROR) if internal else ("control_error", logging.INFO)
            if internal and exc is not None and self._limiter.allow("internal_trace"):
                log.error("control_internal_error in %s", method, exc_info=exc)
        if self._limiter.allow(event):
            log_event(log, level, event, method=method, detail=detail[:300])

    async def Status(self, request: cpb.StatusRequest, context: aio.ServicerContext) -> cpb.StatusReply:
        st = self.rt.status()
        peers = [
            cpb.PeerStatus(
                name=p["name"],
                address=p["address"],
                incarnation=p["incarnation"],
                suspected=p["suspected"],
                excluded=p["excluded"],
                connected=p["connected"],
                heartbeat_period=p["eta"],
                alpha=p["alpha"],
            )
            for p in st["peers"]
        ]
        return cpb.StatusReply(
            name=st["name"],
            incarnation=st["incarnation"],
            peers=peers,
            active_transactions=st["active_transactions"],
            decided_transactions=st["decided_transactions"],
            delivered=st["delivered"],
            delivered_hash=st["delivered_hash"],
            counters=cpb.Counters(values={k: v for k, v in st["counters"].items() if v >= 0}),
            cpu_percent=st["cpu_percent"],
            rss_bytes=st["rss_bytes"],
            uptime=st["uptime"],
            mode=st["mode"],
            load_cpu_seconds=st["cpu_seconds"],
            **_group_fields(st),
        )

    def _deadline(self, context: aio.ServicerContext) -> float:
        remaining = context.time_remaining()
        return DEFAULT_WAIT if remaining is None else max(0.0, remaining - 0.05)

    async def _membership_propose(self, request: cpb.ProposeRequest, context: aio.ServicerContext) -> cpb.ProposeReply:
        if request.participants:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "membership mode: a transaction goes to every member")
        rt = self.rt
        try:
            res = await rt.writes.submit(request.payload, "test", timeout=self._deadline(context))
        except WriteFailed as e:
            await context.abort(grpc.StatusCode.UNAVAILABLE, e.reason)
            raise
        return cpb.ProposeReply(id=_txid(res.txid), decided=True, committed=True)

    async def DdbWrite(self, request: cpb.DdbWriteRequest, context: aio.ServicerContext) -> cpb.DdbWriteReply:
        rt = self.rt
        if not rt.membership:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, "static mode (--peers): this host has no DDB")
        rt.counters["control_ddb_writes"] += 1
        try:
            res = await rt.writes.ddb_write(list(request.ops), request.atomic, timeout=self._deadline(context))
        except InvalidWrite as e:  # (empty, too large, JSON bounds: haa.core.ddb.ops.check_batch)
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, e.reason)
            raise
        except WriteFailed as e:
            return cpb.DdbWriteReply(committed=False, reason=e.reason)
        except NotMembershipMode as e:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
            raise
        return cpb.DdbWriteReply(
            committed=True,
            id=_txid(res.txid),
            global_seq=res.global_seq,
            ddb_seq=res.ddb_seq,
            results=[
                cpb.DdbOpResult(op=o.op, key=o.key, ok=o.ok, reason=o.reason, version=o.version) for o in res.results
            ],
        )

    async def DdbLoad(self, request: cpb.DdbLoadRequest, context: aio.ServicerContext) -> cpb.DdbLoadReply:
        """A DDB write load from inside this host (a benchmark: a mission's agents write through their host,
        not through this API, so a client's RPC cost must not be what is measured). The keys it writes stay in
        the DDB (under `prefix`, default load/<host>)."""
        rt = self.rt
        if not rt.membership:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, "static mode (--peers): this host has no DDB")
        r = request
        if not (1 <= r.writers <= MAX_LOAD_WRITERS and 0 < r.seconds <= MAX_LOAD_SECONDS
                and r.value_bytes <= MAX_LOAD_VALUE and len(r.prefix) <= 64):
            await context.abort(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"writers 1..{MAX_LOAD_WRITERS}, seconds in (0, {MAX_LOAD_SECONDS}], value_bytes <= "
                f"{MAX_LOAD_VALUE}, prefix <= 64 characters",
            )
        wait = r.start_at - time.time() if r.start_at else 0.0
        if wait > 30.0:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "start_at more than 30 s ahead")
        if wait > 0:
            await asyncio.sleep(wait)
        value = bytes(r.value_bytes)
        prefix = r.prefix or f"load/{rt.name}"
        lat: list[float] = []
        failed = committed = 0
        applied0 = rt.counters["global_applied"]
        t0 = time.perf_counter()
        stop = t0 + r.seconds

        async def writer(i: int) -> None:
            nonlocal failed, committed
            k = 0
            while time.perf_counter() < stop:
                t = time.perf_counter()
                try:
                    res = await rt.writes.ddb_write([put(f"{prefix}/{i}/{k}", "blob", value)], timeout=30.0)
                except WriteFailed:
                    failed += 1
                else:
                    if not res.results[0].ok:  # committed, the put refused (a full DDB: MAX_DDB_KEYS / BYTES)
                        failed += 1
                    else:
                        committed += 1
                        if len(lat) < 200_000:
                            lat.append(time.perf_counter() - t)
                k += 1

        await asyncio.gather(*(writer(i) for i in range(r.writers)))
        return cpb.DdbLoadReply(
            committed=committed,
            failed=failed,
            latencies=lat,
            elapsed=time.perf_counter() - t0,
            global_applied=rt.counters["global_applied"] - applied0,
        )

    async def DdbGet(self, request: cpb.DdbGetRequest, context: aio.ServicerContext) -> cpb.DdbGetReply:
        try:
            node = self.rt.member_node()
        except NotMembershipMode as e:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
            raise
        db = node.state.ddb
        if request.keys:
            objs = [o for o in (db.get(k) for k in request.keys) if o is not None]
        else:
            objs = list(db.items(request.prefix))
        truncated = bool(request.limit) and len(objs) > request.limit
        if truncated:
            objs = objs[: request.limit]
        return cpb.DdbGetReply(
            objects=[
                dpb.DdbObjectRecord(
                    key=o.key,
                    type=o.type_name,
                    value=b"" if request.keys_only else o.data,
                    version=o.version,
                    created=o.created,
                )
                for o in objs
            ],
            ddb_seq=db.seq,
            ddb_hash=db.content_hash(),
            truncated=truncated,
        )

    async def Mirror(self, request: cpb.MirrorRequest, context: aio.ServicerContext) -> None:
        """A snapshot, then every applied DDB batch (and view changes if asked). Sent with `context.write`, each
        within `MIRROR_SEND_TIMEOUT`: a client that stops reading is cut off (RESOURCE_EXHAUSTED), and what gRPC
        held for it is freed. Bounded in number (haa.hostd.mirrors)."""
        rt = self.rt
        try:
            node = rt.member_node()
        except NotMembershipMode as e:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
            raise
        try:
            sub = rt.mirrors.subscribe(request.views, node.state.ddb, rpcguard.client_address(context.peer()))
        except MirrorRefused as e:
            rt.counters["mirror_refused"] += 1
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(e))
            raise
        task = asyncio.current_task()
        if task is not None:
            rt.stream_tasks.add(task)
        rt.counters["mirror_subscribers"] += 1

        async def send(event: cpb.MirrorEvent | bytes) -> None:
            try:
                await asyncio.wait_for(context.write(event), MIRROR_SEND_TIMEOUT)
            except aio.AbortError:
                raise
            except TimeoutError:
                rt.counters["mirror_cut_off"] += 1
                await context.abort(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"the client took no mirror event for {MIRROR_SEND_TIMEOUT:g} s (MIRROR_SEND_TIMEOUT)",
                )
            except Exception:  # (grpc's ExecuteBatchError: a write fails only once the call has ended under us)
                raise _ClientGone from None

        async def send_snapshot(db: Any) -> int:
            snap, since = rt.mirrors.snapshot(db)
            await send(snap.event)
            last = snap.seq
            for entry in since:  # (a shared snapshot: catch up from the replica's mirror ring)
                if entry.seq == last + 1:
                    last = entry.seq
                    h = db.content_hash() if db.seq == last else ""
                    batch = cpb.MirrorBatch(ddb_seq=last, payload=entry.payload, global_seq=entry.meta or 0)
                    await send(cpb.MirrorEvent(batch=batch, ddb_hash=h))
            return last

        try:
            last = await send_snapshot(node.state.ddb)
            while True:
                item = await sub.get()
                if item is None:
                    return
                kind = item[0]
                node = rt.member_node()
                db = node.state.ddb
                if kind == "batch":
                    _, seq, payload, gseq = item
                    if seq <= last:
                        continue  # already in the snapshot sent
                    if seq != last + 1:
                        kind = "resync"  # a gap: cannot happen unless the replica changed; resend
                    else:
                        last = seq
                        h = db.content_hash() if db.seq == seq else ""
                        await send(cpb.MirrorEvent(
                            batch=cpb.MirrorBatch(ddb_seq=seq, payload=payload, global_seq=gseq), ddb_hash=h
                        ))
                        continue
                if kind == "resync":
                    rt.counters["mirror_resyncs"] += 1
                    last = await send_snapshot(db)
                elif kind == "view":
                    v = item[1]
                    lead = v.members[0].name if v.members else ""
                    await send(cpb.MirrorEvent(
                        view=cpb.ViewEvent(
                            view=v.view,
                            global_seq=v.seq,
                            members=[cpb.MemberInfo(name=m.name, incarnation=m.inc, address=m.addr) for m in v.members],
                            removed=[m.name for m in v.removed],
                            added=[m.name for m in v.added],
                            leader=lead,
                        )
                    ))
        except _ClientGone:
            return
        except asyncio.CancelledError:
            if not rt.stopping:
                raise
        finally:
            rt.mirrors.unsubscribe(sub)
            if task is not None:
                rt.stream_tasks.discard(task)

    async def Leave(self, request: cpb.LeaveRequest, context: aio.ServicerContext) -> cpb.LeaveReply:
        rt = self.rt
        try:
            await rt.leave(timeout=self._deadline(context))
        except NotMembershipMode as e:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
            raise
        except (TimeoutError, WriteFailed) as e:
            return cpb.LeaveReply(left=False, reason=str(e) or "the group did not commit the leave in time")
        if request.exit:
            asyncio.get_running_loop().call_later(0.2, rt.request_stop)
        return cpb.LeaveReply(left=True)

    async def Propose(self, request: cpb.ProposeRequest, context: aio.ServicerContext) -> cpb.ProposeReply:
        if self.rt.membership:
            return await self._membership_propose(request, context)
        parts = list(request.participants) or None
        rt = self.rt
        rt.counters["control_proposals"] += 1
        try:
            if not request.wait:
                txid = rt.propose_nowait(request.payload, parts)
                return cpb.ProposeReply(id=_txid(txid), participants=rt.proposals.participants_of(txid))
            remaining = context.time_remaining()
            timeout = DEFAULT_WAIT if remaining is None else max(0.0, remaining - 0.05)
            res = await rt.propose(request.payload, parts, timeout=timeout)
        except OacError as e:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
            raise  # not reached: abort raises
        except TransactionAborted as e:
            return cpb.ProposeReply(
                id=_txid(e.txid),
                decided=True,
                committed=False,
                propose_to_decide=e.propose_to_decide,
                participants=e.participants,
            )
        except ProposeTimeout as e:
            return cpb.ProposeReply(id=_txid(e.txid), decided=False, participants=e.participants)
        except HostReincarnated as e:
            await context.abort(grpc.StatusCode.ABORTED, str(e))
            raise
        return cpb.ProposeReply(
            id=_txid(res.txid),
            decided=True,
            committed=True,
            propose_to_decide=res.propose_to_decide,
            decide_to_deliver=res.decide_to_deliver,
            participants=res.participants,
        )

    async def Deliveries(
        self, request: cpb.DeliveriesRequest, context: aio.ServicerContext
    ) -> AsyncIterator[cpb.Delivery]:
        rt = self.rt
        i = request.from_index
        task = asyncio.current_task()
        if task is not None:
            rt.stream_tasks.add(task)
        try:
            while True:
                log_ = rt.delivered
                if i < log_.base:
                    await context.abort(
                        grpc.StatusCode.OUT_OF_RANGE,
                        f"entries before {log_.base} are no longer kept (MAX_DELIVERED)",
                    )
                while i < log_.count:
                    e = log_.get(i)
                    yield cpb.Delivery(
                        index=e.index, id=_txid(e.txid), order=e.order, payload=e.payload, chain_hash=e.chain_hash
                    )
                    i += 1
                await log_.wait(i + 1)
        except asyncio.CancelledError:
            if not rt.stopping:
                raise
            # the host is shutting down: end the stream normally
        finally:
            if task is not None:
                rt.stream_tasks.discard(task)

    async def Latencies(self, request: cpb.LatencyRequest, context: aio.ServicerContext) -> cpb.LatencyReply:
        d2d, p2d = self.rt.proposals.take_latencies(request.reset)
        return cpb.LatencyReply(decide_to_deliver=d2d, propose_to_decide=p2d)


_T_co = TypeVar("_T_co", covariant=True)


class Stream(Protocol[_T_co]):
    """A server stream as grpc returns it: an iterator of the messages that can be cancelled."""

    def __iter__(self) -> Iterator[_T_co]: ...
    def __next__(self) -> _T_co: ...
    def cancel(self) -> bool: ...


class ControlClient(AgentClientMixin):
    """Blocking client of one host's control API (the agent calls come from `AgentClientMixin`)."""

    def __init__(
        self, address: str, token: str, timeout: float = 5.0, tls: ClientTls | None = None, server_name: str = ""
    ) -> None:
        self.address = address
        self.timeout = timeout
        self._md = ((MD_TOKEN, token),)
        # the server's limits (64 MiB each way), not gRPC's client default of 4 MiB replies: a DdbGet or a
        # Mirror snapshot of a large DDB is bigger than that
        options: list[tuple[str, Any]] = [
            ("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)
        ]
        if tls is None:
            self._channel = grpc.insecure_channel(address, options=options)
        else:
            if not server_name:
                raise ValueError("a TLS control client needs the host's name (server_name)")
            self._channel = grpc.secure_channel(
                address, tls.channel_credentials(), options=options + tlsmod.channel_options(server_name)
            )
        self._stub = control_pb2_grpc.HostControlStub(self._channel)

    def status(self) -> cpb.StatusReply:
        return self._stub.Status(cpb.StatusRequest(), metadata=self._md, timeout=self.timeout)

    def propose(
        self, payload: bytes, participants: Sequence[str] = (), wait: bool = True, timeout: float = 20.0
    ) -> cpb.ProposeReply:
        req = cpb.ProposeRequest(payload=payload, participants=list(participants), wait=wait)
        return self._stub.Propose(req, metadata=self._md, timeout=timeout)

    def deliveries(self, from_index: int = 0, timeout: float | None = None) -> Stream[cpb.Delivery]:
        """Stream deliveries from `from_index` (the iterator follows new ones; cancel it to stop)."""
        return self._stub.Deliveries(cpb.DeliveriesRequest(from_index=from_index), metadata=self._md, timeout=timeout)

    def latencies(self, reset: bool = False) -> cpb.LatencyReply:
        return self._stub.Latencies(cpb.LatencyRequest(reset=reset), metadata=self._md, timeout=self.timeout)

    def ddb_write(self, ops: Sequence[object], atomic: bool = False, timeout: float = 30.0) -> cpb.DdbWriteReply:
        """Write a batch of DDB ops (`haa.core.ddb.ops.put/delete/append/cas/add`) through this host; returns
        once the batch is committed and applied here (`committed`), or given up (`reason`)."""
        req = cpb.DdbWriteRequest(ops=list(ops), atomic=atomic)  # type: ignore[arg-type]
        return self._stub.DdbWrite(req, metadata=self._md, timeout=timeout)

    def ddb_load(
        self, writers: int, seconds: float, value_bytes: int = 64, prefix: str = "", start_at: float = 0.0
    ) -> cpb.DdbLoadReply:
        req = cpb.DdbLoadRequest(
            writers=writers, seconds=seconds, value_bytes=value_bytes, prefix=prefix, start_at=start_at
        )
        wait = max(0.0, start_at - time.time()) if start_at else 0.0
        return self._stub.DdbLoad(req, metadata=self._md, timeout=wait + seconds + 60.0)

    def ddb_get(
        self, keys: Sequence[str] = (), prefix: str = "", keys_only: bool = False, limit: int = 0
    ) -> cpb.DdbGetReply:
        """Read this host's replica: the given keys, or every key under `prefix`."""
        req = cpb.DdbGetRequest(keys=list(keys), prefix=prefix, keys_only=keys_only, limit=limit)
        return self._stub.DdbGet(req, metadata=self._md, timeout=self.timeout)

    def mirror(self, views: bool = True, timeout: float | None = None) -> Stream[cpb.MirrorEvent]:
        """The mirror stream: a snapshot, then every applied DDB batch (and view change); cancel to stop."""
        return self._stub.Mirror(cpb.MirrorRequest(views=views), metadata=self._md, timeout=timeout)

    def leave(self, exit: bool = True, timeout: float = 30.0) -> cpb.LeaveReply:
        """Leave the group gracefully (Alg. 3 ll. 14-21); with `exit` the host process stops afterwards."""
        return self._stub.Leave(cpb.LeaveRequest(exit=exit), metadata=self._md, timeout=timeout)

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
