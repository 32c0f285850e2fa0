"""Host-to-host transport: one reliable FIFO channel per ordered host pair over gRPC (`haa.v1.HostLink`) or TCP.

The algorithms of thesis Appendix II assume reliable FIFO channels between correct processes (§4.3.1). A TCP
connection is FIFO but not reliable across reconnects, so each direction of each host pair is a *link* with
its own sequence numbers, built on one bidirectional stream `HostLink.Open(stream Frame) -> stream LinkReply`
opened by the sender (proto/haa/pb/hostlink.proto):

Sender (`OutLink`, one asyncio task per peer)
  * `Transport.send` encodes the message at once (`haa.core.wire`) and appends it to the link's `pending`
    queue; nothing blocks the caller.
  * The link task opens the stream with metadata `x-haa-token`, `x-haa-sender`, `x-haa-incarnation`, reads
    the receiver's handshake `LinkReply(receiver, receiver_incarnation, acked_seq)`, and then writes
    everything queued as one `Frame(first_seq, envelopes)` per stream write (batching is what makes a
    stream fast in Python: see docs/transport.md for the measurements).
  * Written envelopes move to `unacked` until the receiver's cumulative ack covers them. After a reconnect
    the sender resends from the handshake's `acked_seq + 1`, so a broken TCP connection loses nothing while
    both processes live.
  * If the handshake shows a *different receiver incarnation* than the last one, that process is gone: the
    link keeps only the queued messages addressed to the new incarnation or to "unknown" (dst_inc 0),
    renumbers them after the new receiver's `acked_seq`, and reports the new incarnation through
    `on_peer_incarnation` (the runtime calls `HostCore.on_peer_info`).
  * Reconnects use capped exponential backoff (20 ms .. 1 s) for as long as the peer is configured; every
    peer has its own task and channel, so a peer that is down never stalls the others. Peers are given at
    start (static mode) or added at run time with `add_peer` (membership mode, Alg. 3 "open connection").
  * Before the first handshake with a peer, at most `precontact_limit` messages addressed to "unknown"
    (heartbeats) are kept: a peer that has not started yet would otherwise receive a burst of stale
    heartbeats that skews its failure detector's delay estimate (the UFD tolerates lost heartbeats).

Receiver (the `HostLink` servicer, raw bytes)
  * The handler receives undecoded bytes (`request_deserializer=None`) so that a frame that does not parse
    is counted (`rejected_malformed`) and dropped instead of killing the stream; an envelope that fails
    `wire.decode`, or claims another sender than the stream's metadata, is counted (`rejected_invalid`) and
    dropped; a call without the right token is answered `UNAUTHENTICATED` (`rejected_unauthenticated`,
    tokens compared with `hmac.compare_digest`); an unknown sender name gets `PERMISSION_DENIED`
    (`rejected_unknown_peer`) unless the transport accepts unknown senders (`accept_unknown`, membership
    mode: an applicant is unknown until it applies; it still needs the token and a valid name); an older
    incarnation of a sender than one already seen gets `FAILED_PRECONDITION` (`rejected_stale_incarnation`).
  * Per sender it remembers the sender incarnation and the highest link sequence number delivered; frames
    at or below it are duplicates of a resend and are dropped (`link_duplicates`).
  * Replies: first the handshake, then cumulative acks at most every `ack_interval` (1 s) seconds.

Mutual TLS (`tls`, a `haa.tls.HostTls`; docs/deploy.md): the links are TLS channels with this host's
certificate as the client's, checked against the peer's name (`grpc.ssl_target_name_override`: a host at the
address that is not that peer fails the handshake), and the server (haa.hostd.runtime) requires a client
certificate of the cluster's CA. A stream whose `x-haa-sender` is not the host its certificate names is
refused with `PERMISSION_DENIED` (`rejected_name_mismatch`, before every other check but the token): a host
can speak only as itself. Heartbeat datagrams travel outside TLS, so under TLS each link has its own random
MAC key (below).

Link keys (with or without TLS): every stream of a link carries the sender process's key for this receiver
(metadata `x-haa-hb-key`, 64 hex digits, required; `Transport.link_key`: an HMAC of a random per-process secret
and the receiver's name). The receiver checks heartbeat datagrams from `src` with the key of `src`'s accepted
stream, so no other host — a token holder without TLS, a peer under TLS — can forge them; and a second stream at
a sender incarnation it hears from must carry the same key (another process under that incarnation is refused,
`rejected_other_process`, before it learns `acked_seq`). A stream that delivers only duplicates
(`LINK_SUSPECT_DUPLICATES` in a row) or invalid envelopes (`LINK_SUSPECT_INVALID`) is ended with the error event
`link_suspect`. docs/deploy.md, "What the token does not guarantee".

Carriers (`carrier`, `haa-hostd --host-link`): everything above is the link; what carries a session is a
grpc.aio stream (`GRPC`, the default) or a framed TCP connection (`TCP`, haa.hostd.tcplink: the same Frame
and LinkReply bytes, the same handshake metadata, the same refusals by status code name, several times less
CPU per frame). Only the carrier differs: the sender's `OutLink` talks to a `LinkCall` (read a reply, write a
frame, cancel) that either carrier provides (haa.hostd.grpclink, haa.hostd.tcplink), and the receiver's checks
(`Transport._admit`), frame handling (`Transport.on_frame`) and acks (`Acker`) are shared. Every host of a
cluster must use the same carrier; a link to a host with the other one is refused with a log line that says so
(`link_wrong_carrier`, `rejected_wrong_carrier`).

Every message and byte sent and received is counted per payload kind in `counters` (a `collections.Counter`
the status RPC exposes), e.g. `tx_msgs.heartbeat`, `rx_bytes.oac_decide`.

Frames are built by hand from pre-serialized envelopes (`envelope_chunk`, `encode_frame`: haa.hostd.outlink), so
a resend never re-serializes anything.

The parts: this module holds `Transport` — the links of one host, the checks of an inbound link, frame delivery
and acks; haa.hostd.outlink the sending half (`OutLink`, lazy messages, frame encoding); haa.hostd.datagrams
the heartbeat socket; haa.hostd.grpclink and haa.hostd.tcplink the carriers; haa.hostd.linkcommon what they
share. The names other modules use are re-exported here.
"""


from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import re
import secrets
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

import grpc
from google.protobuf.message import DecodeError
from grpc import aio

from haa import tls as tlsmod
from haa.core import wire
from haa.core.messages import Heartbeat, Message
from haa.hostd import grpclink, tcplink
from haa.hostd.datagrams import HB_MAC_BYTES, HB_MAGIC, HB_MAX_DATAGRAM, HeartbeatDatagrams
from haa.hostd.grpclink import (
    CARRIERS,
    GRPC,
    LINK_PIECE,
    MAX_CONCURRENT_STREAMS,
    MAX_REQUEST,
    OPEN_METHOD,
    TCP,
    FramePieces,
    client_options,
    frame_pieces,
)
from haa.hostd.linkcommon import (
    MAX_MESSAGE,
    MD_HB_KEY,
    MD_INC,
    MD_NEWER,
    MD_SENDER,
    MD_TOKEN,
    Admitted,
    LinkCall,
    LinkDown,
    LinkGap,
    LinkRefused,
    Refusal,
    RxState,
    parse_incarnation,
    split_address,
)
from haa.hostd.logs import LOGGER_NAME, RateLimiter, log_event
from haa.hostd.outlink import (
    LAZY_DELAY,
    LAZY_QUIET,
    Entry,
    LazyRelease,
    OnPeerIncarnation,
    OnSuperseded,
    OutLink,
    encode_frame,
    envelope_chunk,
)
from haa.pb import hostlink_pb2 as pb

__all__ = [
    "CARRIERS",
    "GRPC",
    "HB_MAC_BYTES",
    "HB_MAGIC",
    "HB_MAX_DATAGRAM",
    "LAZY_DELAY",
    "LAZY_QUIET",
    "LINK_PIECE",
    "LIVE_WINDOW",
    "MAX_CONCURRENT_STREAMS",
    "MAX_INCARNATION_AHEAD",
    "MAX_MESSAGE",
    "MAX_REQUEST",
    "MD_HB_KEY",
    "MD_INC",
    "MD_NEWER",
    "MD_SENDER",
    "MD_TOKEN",
    "NAME_RE",
    "OPEN_METHOD",
    "TCP",
    "Acker",
    "Admitted",
    "Entry",
    "FramePieces",
    "LinkCall",
    "LinkDown",
    "LinkGap",
    "LinkRefused",
    "OnEnvelopes",
    "OnPeerIncarnation",
    "OnSuperseded",
    "OutLink",
    "Refusal",
    "RxState",
    "Transport",
    "client_options",
    "encode_frame",
    "envelope_chunk",
    "frame_pieces",
    "parse_incarnation",
    "split_address",
    "valid_name",
]

log = logging.getLogger(LOGGER_NAME + ".transport")

_HB_KEY_RE = re.compile(r"[0-9a-f]{64}")
#: a sender's streams that deliver this many duplicate envelopes in a row, or this many invalid ones, without a new
#: valid envelope are ended with an error event (`link_suspect`): a sender resends from the handshake's
#: `acked_seq + 1`, so duplicates come only from an old stream of the same process still draining (bounded by its
#: unacked envelopes) and invalid envelopes never from a correct sender. A link that delivers nothing new for this
#: long has had its numbering taken by someone else (docs/deploy.md, "What the token does not guarantee")
LINK_SUSPECT_DUPLICATES = 100_000
LINK_SUSPECT_INVALID = 1_000

#: an inbound link acknowledges at once (not `ack_interval` later) once it has received this many bytes since its
#: last ack: a sender frees what it keeps for resending, and takes new agent messages (haa.hostd.budget), only
#: on an ack, so with acks once a second a link could carry at most its byte budget per second
ACK_BYTES = 4 * 1024 * 1024
#: while the ack gate is closed (`Transport.ack_gate`), an ack that is due is tried again this often, s
ACK_GATE_POLL = 0.005

#: called with (sender, sender_inc, [(dst_inc, msg), ...]) for every frame's valid, new envelopes
OnEnvelopes = Callable[[str, int, list[tuple[int, Message]]], None]

#: an incarnation is `time.time_ns()` when the daemon (re)started (haa.hostd.runtime): a claim more than this
#: many seconds ahead of the receiver's clock is refused (`rejected_future_incarnation`, OUT_OF_RANGE)
MAX_INCARNATION_AHEAD = 60.0
#: a sender incarnation counts as live on this host while one of its streams is open and it sent a valid
#: message within this many seconds plus twice the heartbeat period it announced last
LIVE_WINDOW = 1.0

#: a host name (`haa-hostd --name`); haa.hostd.daemon validates names with the same pattern
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")


def valid_name(name: str) -> bool:
    """A host name as haa-hostd accepts it (`--name`): 1-63 of [A-Za-z0-9_.-], not starting with [_.-]."""
    return bool(NAME_RE.match(name))


class Cancellable(Protocol):
    """An inbound stream as the transport ends it: a handler task (gRPC) or a connection (TCP)."""

    def cancel(self) -> Any: ...


class Transport:
    """All links of one host: the sending halves (`OutLink`) and the `HostLink` servicer.

    Args:
        name: this host.
        token: the cluster token (sent on every link, required on every incoming call).
        peers: peer name -> "host:port".
        on_envelopes: receives every frame's new, valid messages (see `OnEnvelopes`).
        on_peer_incarnation: learns receiver incarnations from handshakes (see `OnPeerIncarnation`).
        counters: where to count (shared with the runtime); a new Counter if not given.
        on_superseded: told when a peer refuses this host's incarnation as stale (see `OnSuperseded`).
        max_ahead: seconds a sender's incarnation may be ahead of `wall_ns()` (`MAX_INCARNATION_AHEAD`).
        live_window: see `LIVE_WINDOW`; wall_ns: the wall clock in ns (tests move it).
        tls: this host's certificate (mutual TLS, see the module docstring); None: token only.
    The caller sets `incarnation` before `start()` and calls `set_incarnation` when the host reincarnates.
    """

    def __init__(
        self,
        name: str,
        token: str,
        peers: dict[str, str],
        on_envelopes: OnEnvelopes,
        on_peer_incarnation: OnPeerIncarnation | None = None,
        counters: Counter[str] | None = None,
        *,
        min_backoff: float = 0.02,
        max_backoff: float = 1.0,
        handshake_timeout: float = 2.0,
        ack_interval: float = 1.0,
        ack_bytes: int = ACK_BYTES,
        max_batch: int = 4096,
        max_batch_bytes: int = 1 << 20,
        precontact_limit: int = 16,
        max_queue: int = 1_000_000,
        accept_unknown: bool = False,
        on_superseded: OnSuperseded | None = None,
        on_live_elsewhere: Callable[[str], None] | None = None,
        max_ahead: float = MAX_INCARNATION_AHEAD,
        live_window: float = LIVE_WINDOW,
        wall_ns: Callable[[], int] = time.time_ns,
        datagram_heartbeats: bool = True,
        lazy_delay: float = LAZY_DELAY,
        lazy_quiet: float = LAZY_QUIET,
        tls: tlsmod.HostTls | None = None,
        carrier: str = GRPC,
        stall_timeout: float = tcplink.STALL_TIMEOUT,
    ) -> None:
        if name in peers:
            raise ValueError(f"{name!r} cannot be its own peer")
        if carrier not in CARRIERS:
            raise ValueError(f"host link carrier {carrier!r}: one of {', '.join(CARRIERS)}")
        #: what carries this host's links: gRPC streams, or framed TCP connections (haa.hostd.tcplink)
        self.carrier = carrier
        #: TCP carrier: the port the link server listens on (`open_tcp`), 0 before; its server and connections
        self.tcp_port = 0
        self._tcp_server: asyncio.AbstractServer | None = None
        #: TCP carrier: a peer that leaves a frame (or its hello) unfinished this long is cut off (tcplink)
        self.stall_timeout = stall_timeout
        self.name = name
        self.token = token
        self.tls = tls
        self._token_b = token.encode()
        self.incarnation = 0
        self.peers = dict(peers)
        self.on_envelopes = on_envelopes
        self.on_peer_incarnation: OnPeerIncarnation = on_peer_incarnation or (lambda _p, _i: None)
        self.counters: Counter[str] = counters if counters is not None else Counter()
        self.min_backoff = min_backoff
        self.max_backoff = max_backoff
        self.handshake_timeout = handshake_timeout
        self.ack_interval = ack_interval
        self.ack_bytes = ack_bytes
        #: False while this host may not acknowledge what it received (`Acker`): set by the runtime to "this host's
        #: agents have read what was delivered to them" (haa.hostd.budget.MessageBudget.may_ack)
        self.ack_gate: Callable[[], bool] = lambda: True
        self.max_batch = max_batch
        self.max_batch_bytes = max_batch_bytes
        self.precontact_limit = precontact_limit
        self.max_queue = max_queue
        #: lazy messages, held while this host is busy (haa.hostd.outlink)
        self.lazy = LazyRelease(lazy_delay, lazy_quiet)
        self.accept_unknown = accept_unknown
        self.on_superseded: OnSuperseded = on_superseded or (lambda _p, _i: None)
        #: told when a peer refuses this host because another process under its name is live there
        self.on_live_elsewhere: Callable[[str], None] = on_live_elsewhere or (lambda _p: None)
        self.max_ahead = max_ahead
        self.live_window = live_window
        self.wall_ns = wall_ns
        self.limiter = RateLimiter(1.0)
        self.links: dict[str, OutLink] = {}
        self._rx: dict[str, RxState] = {}
        self._inbound: dict[str, int] = Counter()  # open inbound streams per sender
        self._handlers: set[Cancellable] = set()  # inbound streams (tasks, TCP connections), channel closings
        self._rx_tasks: dict[str, dict[Cancellable, int]] = {}  # sender -> its inbound streams -> incarnation
        self._ended: set[Cancellable] = set()  # inbound streams ended because the sender was superseded
        self._started = False
        self._closing = False
        #: heartbeats as datagrams (`open_heartbeats`); the port is announced in every handshake
        self.datagrams = HeartbeatDatagrams(counters=self.counters, rx=self._rx, on_datagram=self.on_datagram,
                                            enabled=datagram_heartbeats)
        #: this process's secret, from which each link's key derives (`link_key`)
        self._link_secret = secrets.token_bytes(32)

    def link_key(self, peer: str) -> bytes:
        """The key of this process's link to `peer` (32 bytes): sent inside every stream of the link (metadata
        `x-haa-hb-key`), it MACs the link's heartbeat datagrams, and it is the receiver's proof that a later
        stream of the same incarnation comes from the same process (`_admit`). One per receiver, so that no
        receiver can forge this host's heartbeats to another; the same for every stream of this process, so
        that a reconnect or a re-added peer presents it again."""
        return hmac.new(self._link_secret, peer.encode(), hashlib.sha256).digest()

    @property
    def lazy_delay(self) -> float:
        return self.lazy.delay

    @property
    def lazy_quiet(self) -> float:
        return self.lazy.quiet

    @property
    def datagram_heartbeats(self) -> bool:
        return self.datagrams.enabled

    @property
    def heartbeat_port(self) -> int:
        """The UDP port of this host's heartbeat datagrams (0: none), announced in every handshake."""
        return self.datagrams.port

    # ------------------------------------------------------------------ heartbeat datagrams

    async def open_heartbeats(self, host: str, port: int) -> int:
        """Take heartbeat datagrams on UDP `host:port` (the gRPC server's port number; "" or "0.0.0.0" = every
        address). Returns the port, or 0 when datagrams are off or the socket cannot be had (heartbeats then
        travel on the streams, as a peer that never announced a port also gets them)."""
        return await self.datagrams.open(host, port)

    def on_datagram(self, data: bytes, now: float | None = None) -> None:
        """One UDP datagram. It is a heartbeat only if it carries the magic, the MAC under the cluster token,
        a valid Envelope of a Heartbeat, and comes from the sender incarnation this host accepted a stream
        from (the incarnation claims of the stream handshake cover heartbeats too); anything else is counted
        and dropped. Stale and replayed heartbeats are the failure detector's to ignore (Alg. 1 l. 20)."""
        got = self.datagrams.accept(data, now)
        if got is not None:
            src, src_inc, dst_inc, msg = got
            self.on_envelopes(src, src_inc, [(dst_inc, msg)])

    # ------------------------------------------------------------------ sending

    def start(self) -> None:
        """Start one link task per peer (needs a running event loop and `incarnation` set)."""
        if self.incarnation <= 0:
            raise ValueError("set the incarnation before starting the transport")
        self._started = True
        for peer, addr in self.peers.items():
            link = self.links.get(peer)
            if link is None:  # (add_peer may have made it already, with messages queued)
                link = OutLink(self, peer, addr)
                self.links[peer] = link
            link.start()

    async def stop(self) -> None:
        """Close every link. Inbound streams are ended cleanly (their senders see the stream finish and
        reconnect later), so that stopping the gRPC server afterwards has nothing left to cancel."""
        self._started = False
        self._closing = True
        self.datagrams.close()
        self.lazy.cancel()
        self.close_tcp()
        for task in list(self._handlers):
            task.cancel()
        for link in self.links.values():
            await link.close()
        for _ in range(3):  # let the cancelled handlers finish their RPCs
            await asyncio.sleep(0)

    def set_incarnation(self, inc: int) -> None:
        """This host restarted as incarnation `inc`: void every queued message and reconnect every link
        with the new incarnation in its metadata (receivers restart their numbering for it)."""
        if inc <= self.incarnation:
            raise ValueError("incarnations must increase")
        self.incarnation = inc
        for link in self.links.values():
            link.reset()
            if self._started:
                link.restart()

    def add_peer(self, name: str, address: str) -> None:
        """Start sending to `name` at `address` (a new link), or move its link to a new address. Used by the
        membership layer ("open connection to", Alg. 3); links are never removed while the host runs (a
        link to a host that is gone costs one connection attempt per `max_backoff`)."""
        if name == self.name:
            return
        link = self.links.get(name)
        self.peers[name] = address
        if link is None:
            link = OutLink(self, name, address)
            self.links[name] = link
            if self._started:
                link.start()
            self.counters["links_added"] += 1
        elif link.address != address:
            log_event(log, logging.INFO, "link_retarget", peer=name, old=link.address, new=address)
            link.retarget(address)

    def send(self, dst: str, dst_inc: int, msg: Message, lazy: bool = False) -> None:
        """Queue `msg` for `dst` (its incarnation `dst_inc`, 0 = unknown). Never blocks. A `lazy` message waits
        up to `lazy_delay` for other traffic to the same peer and goes in its frame (FIFO order is kept: the
        link always writes its whole queue in order)."""
        link = self.links.get(dst)
        if link is None:
            self.counters["send_unknown_peer"] += 1
            return
        data = wire.encode(self.name, self.incarnation, dst_inc, msg).SerializeToString()
        kind = wire.KIND[type(msg)]
        c = self.counters
        c["tx_msgs." + kind] += 1
        c["tx_bytes." + kind] += len(data)
        if link.hb_addr is not None and type(msg) is Heartbeat and self.datagrams.send(link.hb_key, link.hb_addr, data):
            return
        link.enqueue(dst_inc, envelope_chunk(data), lazy)

    def track(self, task: asyncio.Task[Any]) -> None:
        """Keep `task` (a link's old channel closing) until it ends; `stop` cancels it if it has not."""
        self._handlers.add(task)
        task.add_done_callback(self._handlers.discard)

    def connected(self, peer: str) -> bool:
        link = self.links.get(peer)
        return link is not None and link.connected

    def queued(self, peer: str) -> int:
        link = self.links.get(peer)
        return 0 if link is None else len(link.pending) + len(link.unacked)

    def queued_bytes(self, peer: str) -> int:
        """Bytes of the envelopes the link to `peer` holds (not yet written, or written and not yet acked)."""
        link = self.links.get(peer)
        return 0 if link is None else link.queued_bytes

    def queued_bytes_total(self) -> int:
        return sum(link.queued_bytes for link in self.links.values())

    # ------------------------------------------------------------------ receiving

    async def open_tcp(self, host: str, port: int = 0) -> int:
        """TCP carrier: listen for links on `host:port` (0: any free port; "" or "0.0.0.0": every address) with
        this host's TLS material if it has some; returns the port (peers learn it from `HostLink/LinkPort`).
        OSError if the port cannot be had."""
        self._tcp_server, self.tcp_port = await tcplink.serve(self, host, port)
        return self.tcp_port

    def close_tcp(self) -> None:
        """TCP carrier: stop listening and end every inbound TCP link (their senders reconnect and resend)."""
        if self._tcp_server is not None:
            self._tcp_server.close()
            self._tcp_server = None
        self.tcp_port = 0
        for conn in [h for h in self._handlers if isinstance(h, tcplink.ServerConn)]:
            conn.cancel()

    def rpc_handler(self) -> grpc.GenericRpcHandler:
        """The `HostLink` servicer (haa.hostd.grpclink) of this transport."""
        return grpclink.rpc_handler(self)

    def add_to_server(self, server: aio.Server) -> None:
        server.add_generic_rpc_handlers((self.rpc_handler(),))

    @staticmethod
    def server_options() -> list[tuple[str, Any]]:
        """Options for the grpc.aio server that hosts the links (accept keepalive pings, large frames)."""
        return grpclink.server_options()

    def check_token(self, metadata: Any) -> bool:
        """True if the call metadata carries the cluster token."""
        for key, value in metadata or ():
            if key == MD_TOKEN:
                v = value.encode() if isinstance(value, str) else bytes(value)
                return hmac.compare_digest(v, self._token_b)
        return False

    def _live(self, st: RxState, now: float) -> bool:
        """The sender incarnation `st` lives: a stream of it is open and it spoke recently (see `LIVE_WINDOW`)."""
        return st.streams > 0 and now - st.heard <= self.live_window + 2.0 * st.period

    def _reject(self, counter: str, event: str, **fields: Any) -> None:
        self.counters[counter] += 1
        if self.limiter.allow(counter):
            log_event(log, logging.WARNING, event, **fields)

    def _admit(self, md: dict[str, str], token_ok: bool, peer: str, ident: tuple[str, str] | None) -> Admitted:
        """The checks of a new inbound link, whichever carrier opened it: the token (`token_ok`), under TLS the
        certificate's identity `ident` against the sender's name, the sender, its incarnation claim. Counts and
        logs a refusal and raises `Refusal` (a `grpc.StatusCode` name, the details, the newer incarnation of a
        stale-incarnation refusal); else registers the stream (`RxState.streams`, `link_accepts`) and returns
        (sender, incarnation, state, heartbeat key). The caller must call `_closed_stream` when it ends."""
        if not token_ok:
            self._reject("rejected_unauthenticated", "reject_unauthenticated", peer=peer)
            raise Refusal("UNAUTHENTICATED", "missing or wrong cluster token")
        sender = md.get(MD_SENDER, "")
        if self.tls is not None and ident != (tlsmod.HOST, sender):
            # a certificate of this cluster's CA (the TLS handshake checked that), but not of `sender`: a host
            # speaks only as itself (docs/deploy.md, "Mutual TLS")
            cert = f"{ident[0]} {ident[1]}" if ident else "none"
            self._reject("rejected_name_mismatch", "reject_name_mismatch", sender=sender[:100], certificate=cert,
                         peer=peer)
            raise Refusal("PERMISSION_DENIED", f"the certificate is {cert}'s: it cannot speak as {sender[:100]!r}")
        text = md.get(MD_HB_KEY, "")
        if not _HB_KEY_RE.fullmatch(text):
            self._reject("rejected_bad_metadata", "reject_bad_metadata", sender=sender[:100], why=MD_HB_KEY)
            raise Refusal("INVALID_ARGUMENT", f"bad {MD_HB_KEY}: 64 hex digits (the sender's link key)")
        hb_key = bytes.fromhex(text)
        if sender not in self.peers and not (self.accept_unknown and valid_name(sender) and sender != self.name):
            self._reject("rejected_unknown_peer", "reject_unknown_peer", sender=sender[:100], peer=peer)
            raise Refusal("PERMISSION_DENIED", f"{sender[:100]!r} is not a configured peer")
        inc = parse_incarnation(md.get(MD_INC, ""))
        if inc is None:
            self._reject("rejected_bad_metadata", "reject_bad_metadata", sender=sender)
            raise Refusal("INVALID_ARGUMENT", f"bad {MD_INC}: a decimal in 1..2**64-1")
        ahead = (inc - self.wall_ns()) / 1e9
        if ahead > self.max_ahead:
            # incarnations are wall-clock timestamps: one far in the future is a forgery (or a broken clock);
            # believed, it would make every real incarnation of that host look stale
            self._reject("rejected_future_incarnation", "reject_future_incarnation", sender=sender, inc=inc,
                         ahead_s=round(ahead, 3))
            raise Refusal(
                "OUT_OF_RANGE",
                f"incarnation {inc} is {ahead:.0f} s ahead of {self.name}'s clock (at most {self.max_ahead:g} s)",
            )
        st = self._rx.get(sender)
        now = asyncio.get_running_loop().time()
        if st is not None and st.inc == inc and st.hb_key is not None and not hmac.compare_digest(st.hb_key, hb_key):
            if st.confirmed or self._live(st, now):
                # another process at the incarnation this host hears from (a token holder, or a copy of the
                # host's TLS key): accepted, it would be told how far the real sender's numbering got and could
                # make its messages look like duplicates. The real process always presents the same key
                self._reject("rejected_other_process", "reject_other_process", sender=sender, inc=inc, peer=peer)
                raise Refusal("PERMISSION_DENIED", f"{sender} incarnation {inc} already speaks to {self.name} with "
                                                   "another link key: one process per incarnation")
            # the key was only ever a claim (no valid message came with it, no stream of it is open): the real
            # process replaces it, so that a claim alone never locks it out
            self.counters["rx_claim_forgotten"] += 1
            st = self._rx[sender] = RxState(inc)
        if st is None or st.inc == inc:
            pass
        elif st.inc < inc:
            if self._live(st, now):
                # a second process under a live host's name (an impostor, or a claim made with the token):
                # refused while the incarnation we hear from lives; a real restart ends the old process and
                # its streams, and is accepted at the next attempt (docs/membership.md, "incarnation claims")
                self._reject("rejected_live_incarnation", "reject_live_incarnation", sender=sender, inc=inc,
                             live=st.inc)
                raise Refusal("UNAVAILABLE", f"{sender} incarnation {st.inc} is live on {self.name}")
        elif st.confirmed or self._live(st, now):
            self._reject("rejected_stale_incarnation", "reject_stale_incarnation", sender=sender, inc=inc,
                         newer=st.inc)
            raise Refusal("FAILED_PRECONDITION", "a newer incarnation of the sender exists", st.inc)
        else:
            # the newer incarnation was only ever a claim (no valid message came with it) and it is gone:
            # forget it, so that a claim alone can never lock the real host out
            self.counters["rx_claim_forgotten"] += 1
        if st is None or st.inc != inc:
            st = RxState(inc)
            self._rx[sender] = st
            # the streams of an older incarnation of the sender end now: the process behind them (if it still
            # runs) reconnects, is refused as stale and learns it was superseded. (A frame on such a stream
            # ended it too; but a silent process that only sends heartbeats, which are datagrams, would
            # otherwise never hear of it.)
            for other, other_inc in list(self._rx_tasks.get(sender, {}).items()):
                if other_inc < inc:
                    self.counters["link_superseded_streams"] += 1
                    self._ended.add(other)
                    other.cancel()
        st.hb_key = hb_key
        st.streams += 1
        self._inbound[sender] += 1
        self.counters["link_accepts"] += 1
        link = self.links.get(sender)
        if link is not None:
            link.kick()
        return sender, inc, st, hb_key

    def _opened_stream(self, handle: Cancellable, sender: str, inc: int) -> None:
        """Remember an accepted inbound stream (an asyncio task under gRPC, a connection under TCP): `stop` and a
        newer incarnation of its sender end it with `handle.cancel()`."""
        self._handlers.add(handle)
        self._rx_tasks.setdefault(sender, {})[handle] = inc

    def _closed_stream(self, handle: Cancellable | None, sender: str, st: RxState) -> None:
        """An inbound stream `_admit` accepted ended (`handle`: as given to `_opened_stream`, if it was)."""
        if handle is not None:
            self._handlers.discard(handle)
            self._ended.discard(handle)
            tasks = self._rx_tasks.get(sender)
            if tasks is not None:
                tasks.pop(handle, None)
                if not tasks:
                    del self._rx_tasks[sender]
        self._inbound[sender] -= 1
        st.streams -= 1

    def ending(self, handle: Cancellable | None) -> bool:
        """This host ends the inbound stream `handle` itself: it is stopping, or a newer incarnation of the stream's
        sender connected (the carrier then ends the stream normally)."""
        return self._closing or handle in self._ended

    def acker(self, write: Callable[[bytes], Awaitable[None]], st: RxState) -> Acker:
        """The acks of an inbound link whose replies `write` writes (see `Acker`)."""
        return Acker(self, write, st)

    def handshake_reply(self, st: RxState) -> bytes:
        """The first reply on an accepted link: who this host is and what it already has from the sender."""
        return pb.LinkReply(
            receiver=self.name,
            receiver_incarnation=self.incarnation,
            acked_seq=st.last,
            heartbeat_port=self.heartbeat_port,
        ).SerializeToString()

    def wrong_carrier(self, peer: str, theirs: str) -> str:
        """A peer tried to open a link with the carrier this host does not use: count, log, and the reason."""
        why = (f"{self.name} uses the {self.carrier} host link, the sender {theirs}: every host of a cluster must use "
               f"the same (haa-hostd --host-link)")
        self._reject("rejected_wrong_carrier", "reject_wrong_carrier", peer=peer, theirs=theirs, ours=self.carrier)
        return why

    def on_frame(self, data: bytes, sender: str, inc: int, st: RxState) -> bool:
        """One serialized `Frame` of an accepted link from `sender`#`inc` (whichever carrier brought it): deliver
        its new, valid envelopes (see the module docstring). False: this stream belongs to a dead process (a newer
        incarnation of the sender connected) and must end; raises `LinkGap` when the frame skips sequence numbers
        (the stream must end: the sender resends)."""
        counters = self.counters
        if self._rx.get(sender) is not st:
            # a newer incarnation of the sender connected: this stream belongs to a dead process
            counters["rejected_stale_incarnation"] += 1
            return False
        try:
            frame = pb.Frame.FromString(data)
        except DecodeError:
            self._reject("rejected_malformed", "reject_malformed", sender=sender, size=len(data))
            return True
        seq = frame.first_seq
        if seq == 0:
            self._reject("rejected_malformed", "reject_malformed", sender=sender, why="first_seq 0")
            return True
        counters["rx_frames"] += 1
        decode = wire.decode
        items: list[tuple[int, Message]] = []
        for env in frame.envelopes:
            last = st.last
            if seq <= last:
                counters["link_duplicates"] += 1
                st.dup_run += 1
                seq += 1
                continue
            if seq > last + 1:
                counters["link_gap"] += 1
                log_event(log, logging.WARNING, "link_gap", sender=sender, expected=last + 1, got=seq)
                if st.gaps < 3:
                    # never skip a message: end the stream; the sender reconnects and resends from
                    # last + 1. (After three such streams in a row the sender evidently no longer has
                    # the message — a bug — and the gap is accepted rather than stalling the link.)
                    st.gaps += 1
                    if items:
                        self.on_envelopes(sender, inc, items)
                    raise LinkGap(f"expected {last + 1}, got {seq}")
                log_event(log, logging.ERROR, "link_gap_accepted", sender=sender, expected=last + 1, got=seq)
            st.gaps = 0
            st.last = seq
            seq += 1
            try:
                src, src_inc, dst_inc, msg = decode(env)
            except wire.WireError as e:
                self._reject("rejected_invalid", "reject_invalid", sender=sender, reason=str(e))
                st.bad_run += 1
                continue
            if src != sender or src_inc != inc:
                self._reject(
                    "rejected_invalid", "reject_invalid", sender=sender, reason=f"envelope from {src}#{src_inc}"
                )
                st.bad_run += 1
                continue
            st.dup_run = st.bad_run = 0
            kind = wire.KIND[type(msg)]
            counters["rx_msgs." + kind] += 1
            counters["rx_bytes." + kind] += env.ByteSize()
            items.append((dst_inc, msg))
            if type(msg) is Heartbeat:
                st.period = min(msg.period, 10.0)  # (wire.decode checked it is finite and positive)
        if items:
            st.confirmed = True
            st.heard = self.lazy.last_rx = asyncio.get_running_loop().time()
            self.on_envelopes(sender, inc, items)
        if st.dup_run >= LINK_SUSPECT_DUPLICATES or st.bad_run >= LINK_SUSPECT_INVALID:
            counters["link_suspect"] += 1
            log_event(log, logging.ERROR, "link_suspect", sender=sender, inc=inc, duplicates=st.dup_run,
                      invalid=st.bad_run, last=st.last)
            st.dup_run = st.bad_run = 0
            return False  # end the stream: the sender reconnects (and the event says why)
        return True


class Acker:
    """Cumulative acks on one inbound stream, at most one per `ack_interval` — or at once after `ack_bytes`.
    Acks only let the sender free its resend buffer, so they can be rare: the first frame is acknowledged at
    once, later ones after at most `ack_interval` (a profile of 10 hosts under load showed 5 ms acks costing a
    sixth of each host's CPU; at 100 ms an idle 10-host group still acked every heartbeat — 36 acks/s per host —
    and 1 s cut the idle cluster's CPU from 49 % to 37 % of one core; the price is up to 1 s of traffic kept for
    resending, memory only). Bulk traffic is acknowledged sooner: once `ack_bytes` (`ACK_BYTES`) arrived since
    the last ack, the next goes at once, because the sender admits agent messages only while its link holds less
    than its byte budget (haa.hostd.budget). No ack leaves while the transport's `ack_gate` is closed — while this
    host's agents have not read what it delivered to them — so that a sender's byte budget also holds what this
    host buffers for its agents (docs/limits.md, "Messages in flight"); the frames are still read and delivered.
    All writes after the handshake happen in this task (a stream allows one write at a time); `write` writes one
    serialized `LinkReply` on the stream, whichever carrier it is."""

    def __init__(self, t: Transport, write: Callable[[bytes], Awaitable[None]], st: RxState) -> None:
        self.t = t
        self.write = write
        self.st = st
        self.sent = -1
        self.need = asyncio.Event()
        #: bytes received since the last ack; `soon` is set once they reach `ack_bytes`
        self.bytes = 0
        self.soon = asyncio.Event()
        self.task = asyncio.get_running_loop().create_task(self._run())

    def frame(self, size: int = 0) -> None:
        """A frame of `size` bytes was taken."""
        self.need.set()
        self.bytes += size
        if self.bytes >= self.t.ack_bytes:
            self.soon.set()

    def stop(self) -> None:
        self.task.cancel()

    async def _run(self) -> None:
        t = self.t
        with contextlib.suppress(Exception):
            while True:
                await self.need.wait()
                self.need.clear()
                if not t.ack_gate():
                    t.counters["acks_held"] += 1
                    while not t.ack_gate():
                        await asyncio.sleep(ACK_GATE_POLL)
                last = self.st.last
                if last != self.sent:
                    self.bytes = 0
                    self.soon.clear()
                    await self.write(pb.LinkReply(acked_seq=last).SerializeToString())
                    self.sent = last
                    t.counters["acks_sent"] += 1
                if not self.soon.is_set():
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(t.ack_interval):
                            await self.soon.wait()
                if self.soon.is_set():
                    t.counters["acks_early"] += 1
