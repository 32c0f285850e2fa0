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
MAC key, sent to the receiver inside the TLS stream (metadata `x-haa-hb-key`, 64 hex digits, required):
the receiver checks a datagram from `src` with the key of `src`'s accepted stream, so one host's key cannot
forge another's heartbeats. Without TLS the key is derived from the cluster token, as before.

Carriers (`carrier`, `haa-hostd --host-link`): everything above is the link; what carries a session is a
grpc.aio stream (`GRPC`, the default) or a framed TCP connection (`TCP`, haa.hostd.tcplink: the same Frame
and LinkReply bytes, the same handshake metadata, the same refusals by status code name, several times less
CPU per frame). Only the carrier differs: the sender's `OutLink` talks to a `LinkCall` (read a reply, write a
frame, cancel) that either carrier provides, and the receiver's checks (`Transport._admit`), frame handling
(`Transport.on_frame`) and acks (`_Acker`) are shared. Every host of a cluster must use the same carrier; a
link to a host with the other one is refused with a log line that says so (`link_wrong_carrier`,
`rejected_wrong_carrier`).

Every message and byte sent and received is counted per payload kind in `counters` (a `collections.Counter`
the status RPC exposes), e.g. `tx_msgs.heartbeat`, `rx_bytes.oac_decide`.

Frames are built by hand from pre-serialized envelopes (`envelope_chunk`, `encode_frame`): a Frame is
field 1 (varint `first_seq`) followed by one length-delimited field 2 per envelope, so concatenating the
envelope chunks is a valid protobuf encoding and a resend never re-serializes anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import re
import secrets
import socket
import time
from collections import Counter, deque
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, Protocol

import grpc
from google.protobuf.message import DecodeError
from grpc import aio

from haa import tls as tlsmod
from haa.core import wire
from haa.core.messages import Heartbeat, Message
from haa.hostd import tcplink
from haa.hostd.linkcommon import (
    MD_INC,
    MD_NEWER,
    MD_SENDER,
    MD_TOKEN,
    LinkDown,
    LinkGap,
    LinkRefused,
    Refusal,
    parse_incarnation,
    split_address,
)
from haa.hostd.logs import LOGGER_NAME, RateLimiter, log_event
from haa.pb import hostlink_pb2 as pb

log = logging.getLogger(LOGGER_NAME + ".transport")

OPEN_METHOD = "/haa.v1.HostLink/Open"
#: the carriers of a host link (`Transport(carrier=...)`, `haa-hostd --host-link`): every host of a cluster uses one
GRPC = "grpc"
TCP = "tcp"
CARRIERS = (GRPC, TCP)
#: under TLS: the link's heartbeat MAC key, hex (see the module docstring)
MD_HB_KEY = "x-haa-hb-key"
_HB_KEY_RE = re.compile(r"[0-9a-f]{64}")

#: (dst_inc, envelope chunk) — what a link queues
Entry = tuple[int, bytes]
#: called with (sender, sender_inc, [(dst_inc, msg), ...]) for every frame's valid, new envelopes
OnEnvelopes = Callable[[str, int, list[tuple[int, Message]]], None]
#: called with (peer, incarnation) when a handshake shows a receiver incarnation this link did not know
OnPeerIncarnation = Callable[[str, int], None]
#: called with (peer, newer) when `peer` refused this host's incarnation because it knows a newer one of this
#: host's name (`newer`): this process has been superseded (docs/membership.md, "incarnation claims")
OnSuperseded = Callable[[str, int], None]

#: an incarnation is `time.time_ns()` when the daemon (re)started (haa.hostd.runtime): a claim more than this
#: many seconds ahead of the receiver's clock is refused (`rejected_future_incarnation`, OUT_OF_RANGE)
MAX_INCARNATION_AHEAD = 60.0
#: a sender incarnation counts as live on this host while one of its streams is open and it sent a valid
#: message within this many seconds plus twice the heartbeat period it announced last
LIVE_WINDOW = 1.0


#: the largest host-link message, a frame (one carries a joiner's whole state, `StateSnapshot`: the DDB and the
#: agent table with every backup), and the largest gRPC message a host sends or a client of it receives
MAX_MESSAGE = 64 << 20
#: the largest gRPC message a host's server accepts, control requests and host-link stream messages alike (one
#: server serves both, and gRPC's limits are per server): a larger one is refused by gRPC itself, unread
#: (RESOURCE_EXHAUSTED). gRPC reads a message whole, on the event loop: 50 MB took 1-5 s on this 2-core machine
#: and got the host suspected and removed (T_D^U = 1 s), 8 MiB takes 15-40 ms. The control API's largest legal
#: request is an agent message of 4 MiB (`MAX_AGENT_MESSAGE`); the handlers bound the others much lower, before
#: any work (docs/limits.md, "Sizes and memory"). A larger host-link frame goes in pieces (`LINK_PIECE`).
MAX_REQUEST = 8 << 20
#: on the gRPC carrier a serialized `Frame` larger than this goes as several stream messages, `Frame(part, more)`
#: each, joined by the receiver before decoding (docs/transport.md, "Large frames")
LINK_PIECE = 4 << 20
#: concurrent streams (RPCs) per client connection: a host link is one stream on a connection of its own, a
#: control client needs a few (a watch, an event stream, a request); more are queued by the client's gRPC
MAX_CONCURRENT_STREAMS = 64

#: heartbeat datagrams (docs/transport.md, "Heartbeats as datagrams"): magic + serialized Envelope + MAC, the
#: MAC being the first HB_MAC_BYTES of HMAC-SHA256 over magic + envelope, keyed by a key derived from the
#: cluster token; anything larger than HB_MAX_DATAGRAM bytes is not a heartbeat and is dropped unread
HB_MAGIC = b"HAAhb1"
HB_MAC_BYTES = 16
HB_MAX_DATAGRAM = 512
#: lazy messages (an OAC decision rebroadcast, a round estimate nobody waits for) wait for other traffic on their
#: link while this host is busy — it received a frame within the last LAZY_QUIET seconds — but never longer than
#: LAZY_DELAY; once the host is quiet they are written at once (docs/transport.md, "Lazy messages")
LAZY_DELAY = 0.02
LAZY_QUIET = 0.003
#: a quiet check that runs this much later than it was due counts as busy
LAZY_LATE = 0.001


def heartbeat_key(token: str) -> bytes:
    """The MAC key of heartbeat datagrams (a hash of the token: the token itself never keys two things)."""
    return hashlib.sha256(b"haa-heartbeat\0" + token.encode()).digest()


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def envelope_chunk(env_bytes: bytes) -> bytes:
    """A serialized Envelope as one element of `Frame.envelopes` (tag 2, length-delimited)."""
    return b"\x12" + _varint(len(env_bytes)) + env_bytes


def encode_frame(first_seq: int, chunks: list[bytes]) -> bytes:
    """Serialized `Frame(first_seq, envelopes)` from envelope chunks (tag 1 varint + the chunks)."""
    return b"\x08" + _varint(first_seq) + b"".join(chunks)


def client_options() -> list[tuple[str, Any]]:
    """Channel options for links: fast reconnects, keepalive to notice dead connections, large frames."""
    return [
        ("grpc.initial_reconnect_backoff_ms", 20),
        ("grpc.min_reconnect_backoff_ms", 20),
        ("grpc.max_reconnect_backoff_ms", 1000),
        ("grpc.keepalive_time_ms", 5000),
        ("grpc.keepalive_timeout_ms", 5000),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.max_pings_without_data", 0),
        ("grpc.max_send_message_length", MAX_MESSAGE),
        ("grpc.max_receive_message_length", MAX_MESSAGE),
        ("grpc.enable_retries", 0),
        # a channel of its own subchannels: otherwise a fresh channel (OutLink.kick) shares the old one's
        # subchannel from gRPC's global pool, still waiting out its reconnect backoff
        ("grpc.use_local_subchannel_pool", 1),
    ]


#: a host name (`haa-hostd --name`); haa.hostd.daemon validates names with the same pattern
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")


def valid_name(name: str) -> bool:
    """A host name as haa-hostd accepts it (`--name`): 1-63 of [A-Za-z0-9_.-], not starting with [_.-]."""
    return bool(NAME_RE.match(name))


class LinkCall(Protocol):
    """One sender-side session of a link, whatever carries it (a grpc.aio stream call, `_GrpcCall`, or a TCP
    connection, `haa.hostd.tcplink.ClientConn`): the receiver's replies, serialized `LinkReply`s (None once
    the stream ended), and the serialized `Frame`s this side writes."""

    async def read(self) -> bytes | None: ...

    async def write(self, data: bytes) -> None: ...

    def cancel(self) -> bool | None: ...


def frame_pieces(data: bytes, piece: int = LINK_PIECE) -> list[bytes]:
    """A serialized `Frame` larger than `piece` as the gRPC carrier sends it: serialized `Frame(part, more)`s of
    at most `piece` bytes of it each, `more` on all but the last (`FramePieces` joins them)."""
    view = memoryview(data)
    return [pb.Frame(part=bytes(view[i:i + piece]), more=i + piece < len(data)).SerializeToString()
            for i in range(0, len(data), piece)]


class FramePieces:
    """The receiving end of `frame_pieces` on one stream: `add` takes each stream message and returns the
    serialized `Frame` to decode, or None while pieces are still coming. A frame (first byte 0x08: `first_seq`,
    always set) passes through untouched; a piece is decoded and kept, at most `limit` bytes in all. Whatever is
    neither is passed on for `Transport.on_frame` to reject."""

    __slots__ = ("limit", "parts", "size")

    def __init__(self, limit: int = MAX_MESSAGE) -> None:
        self.limit = limit
        self.parts: list[bytes] = []
        self.size = 0

    def add(self, data: bytes) -> bytes | None:
        if data[:1] == b"\x08" or not data:
            return data
        try:
            msg = pb.Frame.FromString(data)
        except DecodeError:
            return data
        if msg.first_seq or msg.envelopes or not msg.part:
            return data  # no piece: on_frame rejects it
        self.size += len(msg.part)
        if self.size > self.limit:
            raise ValueError(f"a frame in pieces of more than {self.limit} bytes")
        self.parts.append(msg.part)
        if msg.more:
            return None
        out = b"".join(self.parts)
        self.parts, self.size = [], 0
        return out


class _GrpcCall:
    """A `HostLink.Open` stream call as a `LinkCall` (a frame above `LINK_PIECE` goes in pieces)."""

    __slots__ = ("call", "cancel")

    def __init__(self, call: aio.StreamStreamCall) -> None:
        self.call = call
        self.cancel = call.cancel

    async def write(self, data: bytes) -> None:
        if len(data) <= LINK_PIECE:
            await self.call.write(data)
            return
        for piece in frame_pieces(data):
            await self.call.write(piece)

    async def read(self) -> bytes | None:
        data = await self.call.read()
        return None if data is aio.EOF else data


class OutLink:
    """The sending half of the link to one peer (see the module docstring)."""

    def __init__(self, transport: Transport, peer: str, address: str) -> None:
        self.t = transport
        self.peer = peer
        self.address = address
        self.pending: deque[Entry] = deque()  # not yet written on the current stream
        self.unacked: deque[Entry] = deque()  # written, not yet acknowledged; seqs base, base+1, ...
        self.base = 1  # link sequence number of unacked[0] (or of pending[0] if unacked is empty)
        self.acked = 0  # highest sequence number the receiver acknowledged
        self.receiver_inc = 0  # receiver incarnation of the last handshake (0: never connected)
        self.connected = False
        self.wake = asyncio.Event()
        self.task: asyncio.Task[None] | None = None
        self._broken = False
        self._gen = 0  # session number: a finished session's reader must not touch the current one
        self._next_write = 1  # seq of the next envelope this session writes (a check: numbering never skips)
        self._channel: aio.Channel | None = None
        self._open: Any = None
        self._kicked = 0.0
        #: where heartbeats go as datagrams (resolved at each handshake that announced a heartbeat port);
        #: None: heartbeats travel on the stream
        self.hb_addr: tuple[Any, ...] | None = None
        #: the MAC key of this link's heartbeat datagrams: the token's under token mode, a random one under TLS
        self.hb_key = secrets.token_bytes(32) if transport.tls is not None else transport._hb_key
        #: something queued must go now: an ordinary (not lazy) message, lazy ones the transport released
        #: (`Transport._lazy_check`), or a resend after a handshake. Lazy messages alone only register the link
        #: with the transport (docs/transport.md, "Lazy messages")
        self._due = True

    # ------------------------------------------------------------------ queueing (synchronous)

    def enqueue(self, dst_inc: int, chunk: bytes, lazy: bool = False) -> None:
        pending = self.pending
        pending.append((dst_inc, chunk))
        t = self.t
        if not self.receiver_inc and len(pending) > t.precontact_limit and pending[0][0] == 0:
            pending.popleft()
            t.counters["dropped_precontact"] += 1
        elif len(pending) + len(self.unacked) > t.max_queue:
            pending.popleft()
            t.counters["dropped_overflow"] += 1
            if t.limiter.allow("overflow." + self.peer):
                log_event(log, logging.WARNING, "link_overflow", peer=self.peer, queued=len(pending))
        if not lazy or t.lazy_delay <= 0:
            self._due = True
            self.wake.set()
        elif not self._due:
            t._lazy_hold(self)

    @property
    def next_seq(self) -> int:
        return self.base + len(self.unacked) + len(self.pending)

    def reset(self) -> None:
        """This host became a new incarnation: the old incarnation's messages are void, numbering restarts."""
        self._gen += 1  # acks still arriving on the old stream count the old numbering
        self._next_write = 1
        self.pending.clear()
        self.unacked.clear()
        self.base = 1
        self.acked = 0

    # ------------------------------------------------------------------ the link task

    def start(self) -> None:
        """Start the link task. A previous task is cancelled, and the new one waits until it has ended:
        two sessions of one link must never run at once — they would take messages from the same queue
        and write them, numbered from the same counters, on two streams (the receiver then sees gaps)."""
        if self._channel is None:
            tls = self.t.tls
            if tls is None:
                self._channel = aio.insecure_channel(self.address, options=client_options())
            else:  # the peer must hold a certificate for its name (docs/deploy.md, "Mutual TLS")
                self._channel = aio.secure_channel(self.address, tls.channel_credentials(),
                                                   options=client_options() + tlsmod.channel_options(self.peer))
            self._open = self._channel.stream_stream(OPEN_METHOD)
        prev = self.task
        if prev is not None and not prev.done():
            prev.cancel()
        else:
            prev = None
        self.task = asyncio.get_running_loop().create_task(self._run(prev), name=f"link-{self.peer}")

    def restart(self) -> None:
        """Drop the current stream and connect again at once (used after this host reincarnates)."""
        self.start()

    def _current(self) -> bool:
        """This code runs in the link's current task (not in one that was replaced)."""
        return asyncio.current_task() is self.task

    def retarget(self, address: str) -> None:
        """The peer is now reached at `address`: drop the channel and reconnect there. The queues and the
        numbering stay (the receiver process, if it is the same, resends nothing twice)."""
        self.address = address
        self.hb_addr = None
        old = self._channel
        self._channel = None
        if old is not None:
            task = asyncio.get_running_loop().create_task(old.close())
            self.t._handlers.add(task)
            task.add_done_callback(self.t._handlers.discard)
        if self.task is not None:
            self.restart()

    def kick(self) -> None:
        """The peer just opened a link to us, so it is up: if ours to it is down, reconnect at once on a
        fresh channel rather than at the end of the backoff (up to `max_backoff`, and gRPC's own channel
        backoff): a host that starts after its peers would otherwise wait up to a second for their links."""
        if self.connected or self.task is None:
            return
        now = asyncio.get_running_loop().time()
        if now - self._kicked < 0.05:
            return
        self._kicked = now
        self.t.counters["link_kicks"] += 1
        self.retarget(self.address)

    async def close(self) -> None:
        task, self.task = self.task, None  # (a task that is no longer current stops at its next check)
        while task is not None and not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=0.05)
        if self._channel is not None:
            await self._channel.close()
            self._channel = None

    async def _run(self, prev: asyncio.Task[None] | None = None) -> None:
        t = self.t
        if prev is not None:
            # asyncio.wait_for in Python 3.11 can swallow a cancellation that arrives as its awaitable
            # completes: cancel again until the previous task is really gone
            while not prev.done():
                prev.cancel()
                await asyncio.wait({prev}, timeout=0.05)
        backoff = t.min_backoff
        while True:
            try:
                await self._session()
            except asyncio.CancelledError:
                raise
            except LinkDown as e:
                reason = str(e)
            except grpc.RpcError as e:
                code = e.code() if isinstance(e, aio.AioRpcError) else None
                reason = f"{code.name if code else 'rpc error'}: {e.details() if code else e}"
                if code is not None:
                    newer = None
                    for key, value in e.trailing_metadata() or ():
                        if key == MD_NEWER and isinstance(value, str):
                            newer = parse_incarnation(value)
                    self._refused(code.name, reason, newer)
            except LinkRefused as e:  # the TCP carrier's refusal (haa.hostd.tcplink)
                reason = f"{e.code}: {e.details}"
                self._refused(e.code, reason, e.newer)
            except asyncio.InvalidStateError as e:  # grpc.aio: a write on a call that has just finished
                reason = f"stream finished: {e}"
            except OSError as e:  # the TCP carrier: connection refused or reset, a TLS handshake that failed
                reason = f"{type(e).__name__}: {e}"
            except Exception as e:  # a link must survive anything and reconnect
                reason = f"{type(e).__name__}: {e}"
                log.exception("link %s failed", self.peer, extra={"event": "link_error", "fields": {}})
            was_connected = self.connected
            self.connected = False
            if was_connected:
                t.counters["link_disconnects"] += 1
                log_event(log, logging.INFO, "link_down", peer=self.peer, reason=reason)
                backoff = t.min_backoff
            else:
                t.counters["link_connect_failures"] += 1
                if t.limiter.allow("connect." + self.peer):
                    log_event(log, logging.DEBUG, "link_connect_failed", peer=self.peer, reason=reason)
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2.0, t.max_backoff)

    def _refused(self, code: str, reason: str, newer: int | None) -> None:
        """The receiver refused this host's stream with status `code` (a `grpc.StatusCode` name, whichever the
        carrier): say why (rate-limited), and if it knows a newer incarnation of this host's name (`newer`), this
        process has been superseded (`Transport.on_superseded`)."""
        t = self.t
        if code not in ("FAILED_PRECONDITION", "OUT_OF_RANGE") and not (
            code == "UNAVAILABLE" and " is live on " in reason
        ):
            return
        t.counters["link_refused"] += 1
        if t.limiter.allow("refused." + self.peer):
            log_event(log, logging.WARNING, "link_refused", peer=self.peer, reason=reason[:300])
        if code != "FAILED_PRECONDITION":
            return
        if newer is not None and newer > t.incarnation:
            t.counters["link_superseded"] += 1
            # not from inside this task: the callback reincarnates, which restarts (cancels) every link task
            asyncio.get_running_loop().call_soon(t.on_superseded, self.peer, newer)

    async def _session(self) -> None:
        t = self.t
        md: tuple[tuple[str, str], ...] = ((MD_TOKEN, t.token), (MD_SENDER, t.name), (MD_INC, str(t.incarnation)))
        if t.tls is not None:
            md += ((MD_HB_KEY, self.hb_key.hex()),)
        call: LinkCall | None = None
        try:
            try:
                async with asyncio.timeout(t.handshake_timeout):
                    if t.carrier == TCP:
                        call = await tcplink.connect(self, md)
                    else:
                        call = _GrpcCall(self._open(metadata=md, wait_for_ready=True))
                    data = await call.read()
            except TimeoutError:
                raise LinkDown("no handshake") from None
            if not self._current():
                raise asyncio.CancelledError
            if data is None:
                raise LinkDown("stream closed before the handshake")
            try:
                reply = pb.LinkReply.FromString(data)
            except DecodeError:
                raise LinkDown("malformed handshake") from None
            if reply.receiver != self.peer:
                t.counters["link_wrong_receiver"] += 1
                if t.limiter.allow("wrong." + self.peer):
                    log_event(
                        log,
                        logging.ERROR,
                        "link_wrong_receiver",
                        peer=self.peer,
                        answered=reply.receiver,
                        address=self.address,
                    )
                raise LinkDown(f"{self.address} is {reply.receiver!r}, not {self.peer!r}")
            if reply.receiver_incarnation == 0:
                raise LinkDown("handshake without receiver incarnation")
            await self._resolve_heartbeats(reply.heartbeat_port)
            if not self._current():
                raise asyncio.CancelledError
            self._handshake(reply.receiver_incarnation, reply.acked_seq)
            self._next_write = self.base + len(self.unacked)
            self._gen += 1
            self._broken = False
            self.connected = True
            t.counters["link_connects"] += 1
            log_event(
                log,
                logging.INFO,
                "link_up",
                peer=self.peer,
                receiver_inc=reply.receiver_incarnation,
                acked=reply.acked_seq,
                queued=len(self.pending),
            )
            reader = asyncio.get_running_loop().create_task(self._read_acks(call, self._gen))
            try:
                await self._write_loop(call)
            finally:
                reader.cancel()
        finally:
            if call is not None:
                call.cancel()

    async def _resolve_heartbeats(self, port: int) -> None:
        """Send heartbeats as datagrams to the receiver's announced `port` at the address of this link
        (looked up again at every handshake: a restarted container may have a new address), if both sides
        have a heartbeat socket; on the stream otherwise."""
        t = self.t
        hp = split_address(self.address)
        if not port or t._udp is None or hp is None:
            self.hb_addr = None
            return
        try:
            infos = await asyncio.get_running_loop().getaddrinfo(hp[0], port, family=t._udp_family,
                                                                 type=socket.SOCK_DGRAM)
        except OSError as e:
            t.counters["hb_resolve_failed"] += 1
            if t.limiter.allow("hbres." + self.peer):
                log_event(log, logging.WARNING, "heartbeat_resolve_failed", peer=self.peer, address=self.address,
                          reason=str(e))
            self.hb_addr = None
            return
        self.hb_addr = infos[0][4] if infos else None

    def _handshake(self, inc: int, acked: int) -> None:
        t = self.t
        if inc != self.receiver_inc:
            # A receiver process we have not talked to: whatever it had of ours is gone with its predecessor.
            # Keep what is addressed to it (or to "unknown"), numbered after what it says it has.
            old = self.receiver_inc
            entries = list(self.unacked) + list(self.pending)
            keep = [e for e in entries if e[0] == 0 or e[0] == inc]
            t.counters["link_discarded"] += len(entries) - len(keep)
            self.unacked.clear()
            self.pending = deque(keep)
            self.base = acked + 1
            self.acked = acked
            self.receiver_inc = inc
            if old:
                log_event(
                    log,
                    logging.INFO,
                    "link_new_receiver",
                    peer=self.peer,
                    old=old,
                    new=inc,
                    discarded=len(entries) - len(keep),
                )
            t.on_peer_incarnation(self.peer, inc)
            return
        # The same receiver process: resend everything it does not have, in order.
        unacked = self.unacked
        while unacked and self.base <= acked:
            unacked.popleft()
            self.base += 1
        if acked >= self.base:  # it has more than we ever wrote: impossible unless the numbering broke
            t.counters["link_ack_beyond_sent"] += 1
            acked = self.base - 1
        if acked > self.acked:
            self.acked = acked
        if unacked:
            t.counters["link_resent"] += len(unacked)
            self.pending.extendleft(reversed(unacked))
            unacked.clear()

    async def _read_acks(self, call: LinkCall, gen: int) -> None:
        try:
            while True:
                data = await call.read()
                if data is None or gen != self._gen:
                    return
                try:
                    a = pb.LinkReply.FromString(data).acked_seq
                except DecodeError:
                    self.t.counters["link_bad_ack"] += 1
                    return
                self._on_ack(a)
        except asyncio.CancelledError:
            raise
        except Exception:  # any failure of the stream ends this session
            return
        finally:
            if gen == self._gen:
                self._broken = True
                self.wake.set()

    def _on_ack(self, a: int) -> None:
        unacked = self.unacked
        if a < self.base - 1 or a >= self.base + len(unacked):
            if a >= self.base + len(unacked):
                self.t.counters["link_ack_beyond_sent"] += 1
            return
        n = a - self.base + 1
        for _ in range(n):
            unacked.popleft()
        self.base += n
        self.acked = a

    async def _write_loop(self, call: LinkCall) -> None:
        t = self.t
        pending = self.pending
        unacked = self.unacked
        max_n = t.max_batch
        max_bytes = t.max_batch_bytes
        counters = t.counters
        self._due = True  # a new stream: whatever is queued (a resend, held lazy messages) goes at once
        while True:
            if self._broken:
                raise LinkDown("stream closed by the receiver")
            if not self._current():  # replaced (see `start`): never touch the queues again
                raise asyncio.CancelledError
            pending = self.pending  # `_handshake` may have replaced it
            if not pending or not self._due:
                if not pending:
                    self._due = False
                self.wake.clear()
                await self.wake.wait()
                continue
            first = self.base + len(unacked)
            if first != self._next_write:
                counters["link_sender_gap"] += 1
                log_event(
                    log,
                    logging.ERROR,
                    "link_sender_gap",
                    peer=self.peer,
                    expected=self._next_write,
                    first=first,
                    base=self.base,
                    unacked=len(unacked),
                )
            chunks: list[bytes] = []
            size = 0
            while pending and len(chunks) < max_n and size < max_bytes:
                e = pending.popleft()
                unacked.append(e)
                chunks.append(e[1])
                size += len(e[1])
            self._next_write = first + len(chunks)
            if not pending:
                self._due = False
            await call.write(encode_frame(first, chunks))
            counters["tx_frames"] += 1


class _RxState:
    __slots__ = ("confirmed", "gaps", "hb_key", "heard", "inc", "last", "period", "streams")

    def __init__(self, inc: int) -> None:
        self.inc = inc
        self.last = 0  # highest link sequence number delivered from this sender incarnation
        self.gaps = 0  # streams ended in a row because of a gap in the numbering
        self.streams = 0  # open inbound streams of this incarnation
        self.confirmed = False  # it delivered a valid envelope (more than a claim in metadata)
        self.heard = float("-inf")  # loop time of its last valid envelope
        self.period = 0.0  # the heartbeat period it announced last, s
        self.hb_key: bytes | None = None  # under TLS: the MAC key of its heartbeat datagrams to this host


class Cancellable(Protocol):
    """An inbound stream as the transport ends it: a handler task (gRPC) or a connection (TCP)."""

    def cancel(self) -> Any: ...


#: what `Transport._admit` returns: (sender, sender incarnation, its receive state, its heartbeat key under TLS)
Admitted = tuple[str, int, _RxState, bytes | None]


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
        max_batch: int = 4096,
        max_batch_bytes: int = 1 << 20,
        precontact_limit: int = 16,
        max_queue: int = 1_000_000,
        accept_unknown: bool = False,
        on_superseded: OnSuperseded | None = None,
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
        self.max_batch = max_batch
        self.max_batch_bytes = max_batch_bytes
        self.precontact_limit = precontact_limit
        self.max_queue = max_queue
        self.lazy_delay = lazy_delay
        self.lazy_quiet = lazy_quiet
        self._lazy_links: set[OutLink] = set()  # links holding lazy messages only
        self._lazy_since = 0.0  # when the first of them was held
        self._lazy_timer: asyncio.TimerHandle | None = None
        self._lazy_at = 0.0  # when `_lazy_timer` is due
        self._last_rx = 0.0  # loop time of the last frame received on any link
        self.accept_unknown = accept_unknown
        self.on_superseded: OnSuperseded = on_superseded or (lambda _p, _i: None)
        self.max_ahead = max_ahead
        self.live_window = live_window
        self.wall_ns = wall_ns
        self.limiter = RateLimiter(1.0)
        self.links: dict[str, OutLink] = {}
        self._rx: dict[str, _RxState] = {}
        self._inbound: dict[str, int] = Counter()  # open inbound streams per sender
        self._handlers: set[Cancellable] = set()  # inbound streams (tasks, TCP connections), channel closings
        self._rx_tasks: dict[str, dict[Cancellable, int]] = {}  # sender -> its inbound streams -> incarnation
        self._ended: set[Cancellable] = set()  # inbound streams ended because the sender was superseded
        self._started = False
        self._closing = False
        #: heartbeats as datagrams (`open_heartbeats`); the port is announced in every handshake
        self.datagram_heartbeats = datagram_heartbeats
        self.heartbeat_port = 0
        self._hb_key = heartbeat_key(token)
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_family = socket.AF_INET

    # ------------------------------------------------------------------ heartbeat datagrams

    async def open_heartbeats(self, host: str, port: int) -> int:
        """Take heartbeat datagrams on UDP `host:port` (the gRPC server's port number; "" or "0.0.0.0" = every
        address). Returns the port, or 0 when datagrams are off or the socket cannot be had (heartbeats then
        travel on the streams, as a peer that never announced a port also gets them)."""
        if not self.datagram_heartbeats:
            return 0
        if host in ("", "[::]", "::"):
            host = "0.0.0.0"
        host = host.strip("[]")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
                lambda: _HeartbeatProtocol(self), local_addr=(host, port), family=family
            )
        except OSError as e:
            self.counters["hb_socket_failed"] += 1
            log_event(log, logging.WARNING, "heartbeat_socket_failed", address=f"{host}:{port}", reason=str(e))
            return 0
        self._udp = transport
        self._udp_family = family
        self.heartbeat_port = port
        return port

    def _send_datagram(self, link: OutLink, data: bytes) -> bool:
        udp, addr = self._udp, link.hb_addr
        if udp is None or addr is None:
            return False
        body = HB_MAGIC + data
        try:
            udp.sendto(body + hmac.new(link.hb_key, body, hashlib.sha256).digest()[:HB_MAC_BYTES], addr)
        except OSError:  # (asyncio reports send errors to the protocol; this is a closed transport)
            self.counters["hb_send_failed"] += 1
            return False
        self.counters["tx_datagrams"] += 1
        return True

    def on_datagram(self, data: bytes, now: float | None = None) -> None:
        """One UDP datagram. It is a heartbeat only if it carries the magic, the MAC under the cluster token,
        a valid Envelope of a Heartbeat, and comes from the sender incarnation this host accepted a stream
        from (the incarnation claims of the stream handshake cover heartbeats too); anything else is counted
        and dropped. Stale and replayed heartbeats are the failure detector's to ignore (Alg. 1 l. 20)."""
        c = self.counters
        n = len(data)
        if n > HB_MAX_DATAGRAM or n <= len(HB_MAGIC) + HB_MAC_BYTES or not data.startswith(HB_MAGIC):
            c["hb_rejected_malformed"] += 1
            return
        body, mac = data[:-HB_MAC_BYTES], data[-HB_MAC_BYTES:]
        if self.tls is None and not hmac.compare_digest(
            mac, hmac.new(self._hb_key, body, hashlib.sha256).digest()[:HB_MAC_BYTES]
        ):
            c["hb_rejected_unauthenticated"] += 1
            return
        try:
            env = pb.Envelope.FromString(body[len(HB_MAGIC):])
            src, src_inc, dst_inc, msg = wire.decode(env)
        except (DecodeError, wire.WireError):
            c["hb_rejected_malformed"] += 1
            return
        if type(msg) is not Heartbeat:
            c["hb_rejected_malformed"] += 1
            return
        st = self._rx.get(src)
        if self.tls is not None:  # the key `src` gave this host inside its TLS stream (module docstring)
            key = st.hb_key if st is not None else None
            if key is None or not hmac.compare_digest(
                mac, hmac.new(key, body, hashlib.sha256).digest()[:HB_MAC_BYTES]
            ):
                c["hb_rejected_unauthenticated"] += 1
                return
        if st is None or st.inc != src_inc:
            # no stream of this incarnation was accepted (yet), or a newer one was (a superseded process: its
            # streams were ended when the newer one connected, so it learns of it when it reconnects)
            c["hb_rejected_stale" if st is not None and src_inc < st.inc else "hb_rejected_unknown"] += 1
            return
        c["rx_msgs.heartbeat"] += 1
        c["rx_bytes.heartbeat"] += n
        c["rx_datagrams"] += 1
        st.confirmed = True
        st.heard = asyncio.get_running_loop().time() if now is None else now
        st.period = min(msg.period, 10.0)
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
        if self._udp is not None:
            self._udp.close()
            self._udp = None
        if self._lazy_timer is not None:
            self._lazy_timer.cancel()
            self._lazy_timer = None
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
        if link.hb_addr is not None and type(msg) is Heartbeat and self._send_datagram(link, data):
            return
        link.enqueue(dst_inc, envelope_chunk(data), lazy)

    def _lazy_hold(self, link: OutLink) -> None:
        """`link` holds lazy messages only: release them once this host is quiet (one timer for all links)."""
        links = self._lazy_links
        if not links:
            self._lazy_since = asyncio.get_running_loop().time()
        links.add(link)
        if self._lazy_timer is None:
            loop = asyncio.get_running_loop()
            self._lazy_at = loop.time() + self.lazy_quiet
            self._lazy_timer = loop.call_at(self._lazy_at, self._lazy_check)

    def _lazy_check(self) -> None:
        """While frames keep arriving (other traffic is about to leave on the links) and the oldest held message
        is younger than `lazy_delay`, hold on; otherwise write every link's held messages."""
        self._lazy_timer = None
        loop = asyncio.get_running_loop()
        now = loop.time()
        # busy: a frame arrived lately, or this check itself ran late (the process waited for a CPU, and frames
        # may be waiting to be read)
        busy = now - self._last_rx < self.lazy_quiet or now - self._lazy_at > LAZY_LATE
        if busy and now - self._lazy_since < self.lazy_delay:
            self._lazy_at = now + self.lazy_quiet
            self._lazy_timer = loop.call_at(self._lazy_at, self._lazy_check)
            return
        links, self._lazy_links = self._lazy_links, set()
        for link in links:
            if link.pending and not link._due:
                link._due = True
                link.wake.set()

    def connected(self, peer: str) -> bool:
        link = self.links.get(peer)
        return link is not None and link.connected

    def queued(self, peer: str) -> int:
        link = self.links.get(peer)
        return 0 if link is None else len(link.pending) + len(link.unacked)

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
        return grpc.method_handlers_generic_handler(
            "haa.v1.HostLink",
            {
                "Open": grpc.stream_stream_rpc_method_handler(
                    self._serve_open, request_deserializer=None, response_serializer=None
                ),
                # (a raw-bytes method outside hostlink.proto's service: `b"tcp PORT"` or the carrier's name)
                "LinkPort": grpc.unary_unary_rpc_method_handler(
                    self._serve_link_port, request_deserializer=None, response_serializer=None
                ),
            },
        )

    def add_to_server(self, server: aio.Server) -> None:
        server.add_generic_rpc_handlers((self.rpc_handler(),))

    @staticmethod
    def server_options() -> list[tuple[str, Any]]:
        """Options for the grpc.aio server that hosts the links (accept keepalive pings, large frames)."""
        return [
            # never share the port with another server (two hosts on one port would split the links)
            ("grpc.so_reuseport", 0),
            ("grpc.max_receive_message_length", MAX_REQUEST),
            ("grpc.max_send_message_length", MAX_MESSAGE),
            ("grpc.max_concurrent_streams", MAX_CONCURRENT_STREAMS),
            ("grpc.http2.min_ping_interval_without_data_ms", 1000),
            ("grpc.http2.min_recv_ping_interval_without_data_ms", 1000),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.keepalive_time_ms", 10000),
            ("grpc.keepalive_timeout_ms", 5000),
        ]

    def check_token(self, metadata: Any) -> bool:
        """True if the call metadata carries the cluster token."""
        for key, value in metadata or ():
            if key == MD_TOKEN:
                v = value.encode() if isinstance(value, str) else bytes(value)
                return hmac.compare_digest(v, self._token_b)
        return False

    def _live(self, st: _RxState, now: float) -> bool:
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
        stale-incarnation refusal); else registers the stream (`_RxState.streams`, `link_accepts`) and returns
        (sender, incarnation, state, heartbeat key). The caller must call `_closed_stream` when it ends."""
        if not token_ok:
            self._reject("rejected_unauthenticated", "reject_unauthenticated", peer=peer)
            raise Refusal("UNAUTHENTICATED", "missing or wrong cluster token")
        sender = md.get(MD_SENDER, "")
        hb_key = None
        if self.tls is not None:
            if ident != (tlsmod.HOST, sender):
                # a certificate of this cluster's CA (the TLS handshake checked that), but not of `sender`: a host
                # speaks only as itself (docs/deploy.md, "Mutual TLS")
                cert = f"{ident[0]} {ident[1]}" if ident else "none"
                self._reject("rejected_name_mismatch", "reject_name_mismatch", sender=sender[:100], certificate=cert,
                             peer=peer)
                raise Refusal("PERMISSION_DENIED", f"the certificate is {cert}'s: it cannot speak as {sender[:100]!r}")
            text = md.get(MD_HB_KEY, "")
            if not _HB_KEY_RE.fullmatch(text):
                self._reject("rejected_bad_metadata", "reject_bad_metadata", sender=sender, why=MD_HB_KEY)
                raise Refusal("INVALID_ARGUMENT", f"bad {MD_HB_KEY}: 64 hex digits under TLS")
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
            st = _RxState(inc)
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
        if hb_key is not None:
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

    def _closed_stream(self, handle: Cancellable | None, sender: str, st: _RxState) -> None:
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

    def acker(self, write: Callable[[bytes], Awaitable[None]], st: _RxState) -> _Acker:
        """The acks of an inbound link whose replies `write` writes (see `_Acker`)."""
        return _Acker(self, write, st)

    def handshake_reply(self, st: _RxState) -> bytes:
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

    async def _serve_link_port(self, _request: bytes, context: aio.ServicerContext) -> bytes:
        """`HostLink/LinkPort`: where this host takes TCP links (`b"tcp PORT"`), or `b"grpc"` if it does not
        (the TCP carrier's sender asks before it connects: haa.hostd.tcplink, "Where the TCP link listens")."""
        if not self.check_token(context.invocation_metadata() or ()):
            self._reject("rejected_unauthenticated", "reject_unauthenticated", peer=context.peer())
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong cluster token")
        if self.carrier == TCP and self.tcp_port:
            return b"tcp %d" % self.tcp_port
        return self.carrier.encode()

    async def _serve_open(self, request_iterator: AsyncIterator[bytes], context: aio.ServicerContext) -> None:
        if self.carrier != GRPC:
            await context.abort(grpc.StatusCode.FAILED_PRECONDITION, self.wrong_carrier(context.peer(), GRPC))
        md = context.invocation_metadata() or ()
        mdd = {k: v for k, v in md if isinstance(v, str)}
        try:
            sender, inc, st, _hb = self._admit(
                mdd, self.check_token(md), context.peer(),
                tlsmod.peer_identity(context) if self.tls is not None else None,
            )
        except Refusal as r:
            await context.abort(
                getattr(grpc.StatusCode, r.code), r.details,
                trailing_metadata=((MD_NEWER, str(r.newer)),) if r.newer is not None else (),
            )
            return
        acker: _Acker | None = None
        task = asyncio.current_task()
        if task is not None:
            self._opened_stream(task, sender, inc)
        try:
            await context.write(self.handshake_reply(st))
            acker = _Acker(self, context.write, st)
            await self._receive(request_iterator, sender, inc, st, acker)
        except asyncio.CancelledError:
            if not self._closing and task not in self._ended:
                raise
            # shutting down, or a newer incarnation of the sender connected: end the RPC normally rather than
            # leave grpc a cancelled task to report
        except Exception as e:  # a broken stream must never take the host down
            self.counters["link_receive_errors"] += 1
            log_event(log, logging.DEBUG, "link_receive_ended", sender=sender, reason=f"{type(e).__name__}: {e}")
        finally:
            if acker is not None:
                acker.stop()
            self._closed_stream(task, sender, st)

    async def _receive(
        self,
        request_iterator: AsyncIterator[bytes],
        sender: str,
        inc: int,
        st: _RxState,
        acker: _Acker,
    ) -> None:
        on_frame = self.on_frame
        pieces = FramePieces()
        async for data in request_iterator:
            frame = pieces.add(data)
            if frame is None:
                continue
            if not on_frame(frame, sender, inc, st):
                return
            acker.frame()

    def on_frame(self, data: bytes, sender: str, inc: int, st: _RxState) -> bool:
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
                continue
            if src != sender or src_inc != inc:
                self._reject(
                    "rejected_invalid", "reject_invalid", sender=sender, reason=f"envelope from {src}#{src_inc}"
                )
                continue
            kind = wire.KIND[type(msg)]
            counters["rx_msgs." + kind] += 1
            counters["rx_bytes." + kind] += env.ByteSize()
            items.append((dst_inc, msg))
            if type(msg) is Heartbeat:
                st.period = min(msg.period, 10.0)  # (wire.decode checked it is finite and positive)
        if items:
            st.confirmed = True
            st.heard = self._last_rx = asyncio.get_running_loop().time()
            self.on_envelopes(sender, inc, items)
        return True


class _Acker:
    """Cumulative acks on one inbound stream, at most one per `ack_interval`. Acks only let the sender free
    its resend buffer, so they can be rare: the first frame is acknowledged at once, later ones after at
    most `ack_interval` (a profile of 10 hosts under load showed 5 ms acks costing a sixth of each host's
    CPU; at 100 ms an idle 10-host group still acked every heartbeat — 36 acks/s per host — and 1 s cut the
    idle cluster's CPU from 49 % to 37 % of one core; the price is up to 1 s of traffic kept for resending,
    memory only). All writes after the handshake happen in this task (a stream allows one write at a time);
    `write` writes one serialized `LinkReply` on the stream, whichever carrier it is."""

    def __init__(self, t: Transport, write: Callable[[bytes], Awaitable[None]], st: _RxState) -> None:
        self.t = t
        self.write = write
        self.st = st
        self.sent = -1
        self.need = asyncio.Event()
        self.task = asyncio.get_running_loop().create_task(self._run())

    def frame(self) -> None:
        self.need.set()

    def stop(self) -> None:
        self.task.cancel()

    async def _run(self) -> None:
        t = self.t
        with contextlib.suppress(Exception):
            while True:
                await self.need.wait()
                self.need.clear()
                last = self.st.last
                if last != self.sent:
                    await self.write(pb.LinkReply(acked_seq=last).SerializeToString())
                    self.sent = last
                    t.counters["acks_sent"] += 1
                await asyncio.sleep(t.ack_interval)


class _HeartbeatProtocol(asyncio.DatagramProtocol):
    """The heartbeat socket: every datagram goes to `Transport.on_datagram`; a failure there is counted and
    never closes the socket."""

    def __init__(self, t: Transport) -> None:
        self.t = t

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            self.t.on_datagram(data)
        except Exception:  # the core's own errors are caught by the runtime; this is a safety net
            self.t.counters["hb_receive_errors"] += 1
            log.exception("heartbeat datagram failed", extra={"event": "heartbeat_error", "fields": {}})

    def error_received(self, exc: Exception) -> None:  # e.g. ICMP port unreachable: the peer is down
        self.t.counters["hb_send_errors"] += 1
