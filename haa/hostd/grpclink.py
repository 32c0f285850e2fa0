"""The gRPC host link: the default carrier of `haa.hostd.transport`'s links, one `HostLink.Open` grpc.aio stream
per session (proto/haa/pb/hostlink.proto), as haa.hostd.tcplink is the TCP one. Only the carrier lives here: the
link semantics (numbering, acks, resends, incarnations, lazy messages, the counters) are haa.hostd.outlink's and
`Transport`'s, shared by both carriers.

Sender: `GrpcCall`, a stream call as a `LinkCall`, on the link's gRPC channel (`client_options`). Receiver: the
`HostLink` servicer (`rpc_handler`) — `Open` takes undecoded bytes (`request_deserializer=None`) so that a frame
that does not parse is counted and dropped by `Transport.on_frame` instead of killing the stream; `LinkPort`
tells a TCP sender where this host's TCP link listens (haa.hostd.tcplink, "Where the TCP link listens").

Large frames: a serialized `Frame` above `LINK_PIECE` goes as several stream messages, `Frame(part, more)` each
(`frame_pieces`), joined by the receiver before decoding (`FramePieces`; docs/transport.md, "Large frames").
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from typing import Any

import grpc
from google.protobuf.message import DecodeError
from grpc import aio

from haa import tls as tlsmod
from haa.hostd.linkcommon import MAX_MESSAGE, MD_NEWER, Acks, LinkHost, Refusal, RxState
from haa.hostd.logs import LOGGER_NAME, log_event
from haa.pb import hostlink_pb2 as pb

log = logging.getLogger(LOGGER_NAME + ".transport")

OPEN_METHOD = "/haa.v1.HostLink/Open"
#: the carriers of a host link (`Transport(carrier=...)`, `haa-hostd --host-link`): every host of a cluster uses one
GRPC = "grpc"
TCP = "tcp"
CARRIERS = (GRPC, TCP)

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


# ------------------------------------------------------------------------------------------------ large frames


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


# ------------------------------------------------------------------------------------------------ sender


class GrpcCall:
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


# ------------------------------------------------------------------------------------------------ receiver


def rpc_handler(t: LinkHost) -> grpc.GenericRpcHandler:
    """The `HostLink` servicer of transport `t`."""

    async def open_(request_iterator: AsyncIterator[bytes], context: aio.ServicerContext) -> None:
        await serve_open(t, request_iterator, context)

    async def link_port(request: bytes, context: aio.ServicerContext) -> bytes:
        return await serve_link_port(t, request, context)

    return grpc.method_handlers_generic_handler(
        "haa.v1.HostLink",
        {
            "Open": grpc.stream_stream_rpc_method_handler(
                open_, request_deserializer=None, response_serializer=None
            ),
            # (a raw-bytes method outside hostlink.proto's service: `b"tcp PORT"` or the carrier's name)
            "LinkPort": grpc.unary_unary_rpc_method_handler(
                link_port, request_deserializer=None, response_serializer=None
            ),
        },
    )


async def serve_link_port(t: LinkHost, _request: bytes, context: aio.ServicerContext) -> bytes:
    """`HostLink/LinkPort`: where this host takes TCP links (`b"tcp PORT"`), or `b"grpc"` if it does not
    (the TCP carrier's sender asks before it connects: haa.hostd.tcplink, "Where the TCP link listens")."""
    if not t.check_token(context.invocation_metadata() or ()):
        t._reject("rejected_unauthenticated", "reject_unauthenticated", peer=context.peer())
        await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong cluster token")
    if t.carrier == TCP and t.tcp_port:
        return b"tcp %d" % t.tcp_port
    return t.carrier.encode()


async def serve_open(t: LinkHost, request_iterator: AsyncIterator[bytes], context: aio.ServicerContext) -> None:
    """`HostLink/Open`: the checks of `Transport._admit`, the handshake reply, then frames until the stream ends."""
    if t.carrier != GRPC:
        await context.abort(grpc.StatusCode.FAILED_PRECONDITION, t.wrong_carrier(context.peer(), GRPC))
    md = context.invocation_metadata() or ()
    mdd = {k: v for k, v in md if isinstance(v, str)}
    try:
        sender, inc, st, _hb = t._admit(
            mdd, t.check_token(md), context.peer(),
            tlsmod.peer_identity(context) if t.tls is not None else None,
        )
    except Refusal as r:
        await context.abort(
            getattr(grpc.StatusCode, r.code), r.details,
            trailing_metadata=((MD_NEWER, str(r.newer)),) if r.newer is not None else (),
        )
        return
    acker: Acks | None = None
    task = asyncio.current_task()
    if task is not None:
        t._opened_stream(task, sender, inc)
    try:
        await context.write(t.handshake_reply(st))
        acker = t.acker(context.write, st)
        await receive(t, request_iterator, sender, inc, st, acker)
    except asyncio.CancelledError:
        if not t.ending(task):
            raise
        # shutting down, or a newer incarnation of the sender connected: end the RPC normally rather than
        # leave grpc a cancelled task to report
    except Exception as e:  # a broken stream must never take the host down
        t.counters["link_receive_errors"] += 1
        log_event(log, logging.DEBUG, "link_receive_ended", sender=sender, reason=f"{type(e).__name__}: {e}")
    finally:
        if acker is not None:
            acker.stop()
        t._closed_stream(task, sender, st)


async def receive(
    t: LinkHost,
    request_iterator: AsyncIterator[bytes],
    sender: str,
    inc: int,
    st: RxState,
    acker: Acks,
) -> None:
    """The frames of one accepted stream, joined from their pieces, to `Transport.on_frame`; an ack after each."""
    on_frame = t.on_frame
    pieces = FramePieces()
    async for data in request_iterator:
        frame = pieces.add(data)
        if frame is None:
            continue
        if not on_frame(frame, sender, inc, st):
            return
        acker.frame(len(frame))
