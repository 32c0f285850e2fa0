"""The TCP host link: the carrier of `haa.hostd.transport`'s links as framed messages on a plain (or TLS) TCP
connection instead of a grpc.aio stream (issue 14; `haa-hostd --host-link tcp`, docs/transport.md "The TCP host
link").

Why: a grpc.aio stream write plus the read at the peer costs ~0.25 ms of CPU whatever the frame carries, 4-5x an
asyncio TCP write (haa/lab/bench/transport_grpc_vs_tcp.py), and a 10-host OAC needs ~80-90 frames. This module is only
the carrier: the link semantics — per-link sequence numbers, cumulative acks, resend from `acked_seq + 1` after a
reconnect, duplicate drop, receiver and sender incarnation changes, the incarnation-claim rules, lazy messages,
the counters — are `outlink.OutLink` and `Transport._admit` / `Transport.on_frame`, shared by both carriers.
gRPC stays the carrier of every service (control API, agents, DDB clients) and the default of the host link.

Wire format. Every message in either direction is a 5-byte header — kind (1 byte), payload length (4 bytes,
big-endian) — and the payload:

  * `HELLO` (1), sender -> receiver, first and once: `HAAlink1\\n` + a JSON object of the metadata the gRPC
    carrier sends (`x-haa-token`, `x-haa-sender`, `x-haa-incarnation`, `x-haa-hb-key`), at most
    `MAX_HELLO` bytes;
  * `FRAME` (2), sender -> receiver: a serialized `haa.v1.Frame` (the very bytes a gRPC stream write carries);
  * `REPLY` (3), receiver -> sender: a serialized `haa.v1.LinkReply` — first the handshake, then the acks;
  * `REFUSE` (4), receiver -> sender, instead of the handshake, then the connection closes: a JSON object
    `{"code": <grpc.StatusCode name>, "details": str, "newer": <incarnation> or null}` — the status the gRPC
    carrier's receiver would abort the call with (and the `x-haa-newer-incarnation` it would add).

Handshake and auth: the receiver runs the same checks as on a gRPC stream (`Transport._admit`): the token with
`hmac.compare_digest`, the sender's name, the incarnation claim; the same refusals, counted the same
(`rejected_unauthenticated`, `rejected_unknown_peer`, `rejected_bad_metadata`, `rejected_future_incarnation`,
`rejected_live_incarnation`, `rejected_stale_incarnation`, `rejected_name_mismatch`), and the sender treats a
refusal as it treats a gRPC status (`OutLink._refused`: superseded, logged, retried with backoff).

Where the TCP link listens: on a port of its own (`haa-hostd --link-port`, default 0 = any free port) on the
`--listen` host. Peers know only a host's gRPC address (the configuration, the core list, the membership
information), so before each connection the sender asks the peer's gRPC server where its TCP link listens
(`HostLink/LinkPort`, a raw-bytes unary call with the token: `b"tcp PORT"`); the peer may have restarted on
another port. Every host of a cluster must use the same carrier: a TCP sender whose peer answers `grpc` (or is
a daemon without this method) counts `link_wrong_carrier` and logs `link_wrong_carrier` at ERROR; a gRPC sender
that opens `HostLink.Open` on a TCP host is refused with FAILED_PRECONDITION "h2 uses the tcp host link"
(counted `rejected_wrong_carrier` there, logged as `link_refused` by the sender).

Mutual TLS (a `haa.tls.HostTls`, the same material as the gRPC server's): the server requires a client
certificate of the cluster's CA; the client checks that the server's certificate is the peer's (its DNS name,
`server_hostname=peer`); a HELLO whose sender is not the host the client certificate names is refused
(`rejected_name_mismatch`). The link key travels inside the TLS connection (`x-haa-hb-key`).

Hostile or broken input costs one counter and the connection, never the process or unbounded memory: an unknown
kind byte, a HELLO that is not `HAAlink1` JSON of strings, a second HELLO, a length above `MAX_FRAME` (the gRPC
carrier's `MAX_MESSAGE`) or above `MAX_HELLO` before the handshake -> `rejected_malformed`; no complete HELLO
within `stall_timeout`, or a frame left unfinished for longer than `stall_timeout` + its length at `MIN_RATE`
(a slowloris peer) -> `rejected_stalled`; a frame that is not a `Frame`, or envelopes that are invalid or
spoofed, are dropped by `Transport.on_frame` as on a gRPC stream (`rejected_malformed`, `rejected_invalid`) and
the connection stays. At most one unfinished frame is buffered per connection. Dead connections are noticed by
TCP keepalive (5 s idle, 5 s interval, 2 probes) and `TCP_USER_TIMEOUT` (10 s of unacknowledged data), as the
gRPC carrier notices them by HTTP/2 pings.

I/O is `asyncio.Protocol`-based (no reader task, no `await` per frame): the receiver parses and delivers frames
inside `data_received`; the sender writes a frame with one `transport.write` and waits only when the kernel
buffer is full (`pause_writing`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import os
import socket
import ssl
import struct
import tempfile
from collections import deque
from typing import Any, Protocol

import grpc
from grpc import aio

from haa import tls as tlsmod
from haa.hostd.linkcommon import (
    MAX_MESSAGE,
    MD_TOKEN,
    Acks,
    LinkDown,
    LinkGap,
    LinkHost,
    LinkRefused,
    Refusal,
    RxState,
    parse_incarnation,
    split_address,
)
from haa.hostd.logs import LOGGER_NAME, log_event

log = logging.getLogger(LOGGER_NAME + ".tcplink")


class OutLink(Protocol):
    """What this carrier uses of a `haa.hostd.outlink.OutLink`: whom it links to, and its gRPC channel."""

    peer: str
    address: str
    _channel: aio.Channel | None

    @property
    def t(self) -> LinkHost: ...

#: kind byte + payload length
HEADER = struct.Struct(">BI")
HELLO = 1
FRAME = 2
REPLY = 3
REFUSE = 4
HELLO_MAGIC = b"HAAlink1\n"
#: the largest hello (before the handshake nothing larger is buffered) and reply/refusal a sender accepts
MAX_HELLO = 4096
#: the largest frame, as the gRPC carrier's (`linkcommon.MAX_MESSAGE`: a joiner's whole state is one message)
MAX_FRAME = MAX_MESSAGE
#: a connection that leaves its hello, or a frame, unfinished this long (plus the frame's length at MIN_RATE)
#: is closed (`rejected_stalled`)
STALL_TIMEOUT = 10.0
MIN_RATE = 1 << 20
#: the gRPC method that tells a sender where this host's TCP link listens
PORT_METHOD = "/haa.v1.HostLink/LinkPort"


def _tune(transport: asyncio.BaseTransport) -> None:
    """No Nagle delay; keepalive and a user timeout so that a dead peer ends the connection within ~15 s."""
    sock = transport.get_extra_info("socket")
    if sock is None:
        return
    opts = [
        (socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),
        (socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1),
        (socket.IPPROTO_TCP, getattr(socket, "TCP_KEEPIDLE", 0), 5),
        (socket.IPPROTO_TCP, getattr(socket, "TCP_KEEPINTVL", 0), 5),
        (socket.IPPROTO_TCP, getattr(socket, "TCP_KEEPCNT", 0), 2),
        (socket.IPPROTO_TCP, getattr(socket, "TCP_USER_TIMEOUT", 0), 10_000),
    ]
    for level, opt, value in opts:
        if opt:
            with contextlib.suppress(OSError, AttributeError):
                sock.setsockopt(level, opt, value)


# ------------------------------------------------------------------------------------------------ TLS


def _load_chain(ctx: ssl.SSLContext, tls: tlsmod.HostTls) -> None:
    """The host's certificate and key into `ctx` (the ssl module reads them from files only: a private
    temporary directory, removed at once)."""
    with tempfile.TemporaryDirectory(prefix="haa-tls-") as d:
        cert, key = os.path.join(d, "host.pem"), os.path.join(d, "host.key")
        for path, data in ((cert, tls.cert), (key, tls.key)):
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
        ctx.load_cert_chain(cert, key)


@functools.lru_cache(maxsize=8)
def server_context(tls: tlsmod.HostTls) -> ssl.SSLContext:
    """The link server's TLS: this host's certificate; clients must present one of the cluster's CA."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.verify_mode = ssl.CERT_REQUIRED
    ctx.load_verify_locations(cadata=tls.ca.decode())
    _load_chain(ctx, tls)
    return ctx


@functools.lru_cache(maxsize=8)
def client_context(tls: tlsmod.HostTls) -> ssl.SSLContext:
    """A link's TLS: this host's certificate as the client's; the server must hold the peer's (checked by name)."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.check_hostname = True
    ctx.verify_mode = ssl.CERT_REQUIRED
    ctx.load_verify_locations(cadata=tls.ca.decode())
    _load_chain(ctx, tls)
    return ctx


def peer_identity(transport: asyncio.BaseTransport) -> tuple[str, str] | None:
    """(role, name) of the certificate the peer of a TLS connection presented (its `urn:haa:` URI), or None."""
    cert = transport.get_extra_info("peercert")
    if not cert:
        return None
    for kind, value in cert.get("subjectAltName", ()):
        if kind == "URI":
            ident = tlsmod.parse_identity(value)
            if ident is not None:
                return ident
    return None


# ------------------------------------------------------------------------------------------------ framing


class _Framed(asyncio.Protocol):
    """Length-prefixed messages on a stream connection (see the module docstring): `on_message(kind, payload)`
    for each whole one; at most one unfinished message is buffered, and it must finish in time."""

    def __init__(self, t: LinkHost) -> None:
        self.t = t
        self.tr: asyncio.Transport | None = None
        self.closed = False
        self._buf = bytearray()
        self._need = 0  # bytes the buffered, unfinished message needs in all (header included)
        self._done = 0  # whole messages received
        self._timer: asyncio.TimerHandle | None = None
        self._timer_done = -1  # `_done` when the stall timer was set
        self._paused = False
        self._drain: asyncio.Future[None] | None = None

    # subclasses
    def on_message(self, kind: int, payload: bytes) -> bool:
        """One whole message; False: the connection was closed (stop parsing)."""
        raise NotImplementedError

    def max_payload(self) -> int:
        raise NotImplementedError

    def rejected(self, counter: str, why: str) -> None:
        """Hostile or broken input: count it, log it (rate-limited), drop the connection."""
        raise NotImplementedError

    # asyncio.Protocol
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.tr = transport  # type: ignore[assignment]
        _tune(transport)

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        buf = self._buf
        if buf:
            buf += data
            if len(buf) < self._need:
                return
            data = bytes(buf)
            buf.clear()
        pos, end = 0, len(data)
        unpack = HEADER.unpack_from
        limit = self.max_payload()
        while end - pos >= 5:
            kind, n = unpack(data, pos)
            if n > limit:
                self.rejected("rejected_malformed", f"a message of {n} bytes (at most {limit})")
                return
            stop = pos + 5 + n
            if stop > end:
                break
            self._done += 1
            if not self.on_message(kind, data[pos + 5:stop]):
                return
            limit = self.max_payload()
            pos = stop
        if pos < end:
            buf += memoryview(data)[pos:]
            self._need = 5 + unpack(buf, 0)[1] if len(buf) >= 5 else 5
            if self._timer is None or self._timer_done != self._done:
                self._arm_stall()

    def _arm_stall(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer_done = self._done
        loop = asyncio.get_running_loop()
        self._timer = loop.call_later(self.t.stall_timeout + self._need / MIN_RATE, self._stall_check)

    def _stall_check(self) -> None:
        self._timer = None
        if self.closed or not self._buf:
            return
        if self._done != self._timer_done:  # that message finished; this is another one: give it its time
            self._arm_stall()
            return
        self.rejected("rejected_stalled", f"a message unfinished for {self.t.stall_timeout:g} s or more "
                      f"({len(self._buf)} of {self._need} bytes)")

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self._buf = bytearray()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._drain is not None and not self._drain.done():
            self._drain.set_result(None)

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        if self._drain is not None and not self._drain.done():
            self._drain.set_result(None)

    def send(self, kind: int, payload: bytes) -> None:
        assert self.tr is not None
        self.tr.write(HEADER.pack(kind, len(payload)) + payload)

    async def drained(self) -> None:
        """Return once the kernel takes more (the transport's buffer is below its high-water mark)."""
        while self._paused and not self.closed:
            self._drain = asyncio.get_running_loop().create_future()
            await self._drain

    def abort(self) -> None:
        self.closed = True
        if self.tr is not None:
            self.tr.abort()


# ------------------------------------------------------------------------------------------------ receiver


class ServerConn(_Framed):
    """One inbound TCP link: the hello and the checks of `Transport._admit`, then frames to `Transport.on_frame`
    and acks by the shared `Acker`."""

    def __init__(self, t: LinkHost) -> None:
        super().__init__(t)
        self.sender = ""
        self.inc = 0
        self.st: RxState | None = None  # the sender's receive state once the hello was accepted
        self.acker: Acks | None = None  # its acks (`transport.Acker`)
        self.peer = "?"
        self._hello_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        peer = transport.get_extra_info("peername")
        self.peer = f"tcp:{peer[0]}:{peer[1]}" if isinstance(peer, tuple) and len(peer) >= 2 else "tcp:?"
        self._hello_timer = asyncio.get_running_loop().call_later(self.t.stall_timeout, self._hello_check)

    def _hello_check(self) -> None:
        self._hello_timer = None
        if self.st is None and not self.closed:
            self.rejected("rejected_stalled", f"no hello within {self.t.stall_timeout:g} s")

    def max_payload(self) -> int:
        return MAX_FRAME if self.st is not None else MAX_HELLO

    def rejected(self, counter: str, why: str) -> None:
        self.t._reject(counter, "reject_" + counter.removeprefix("rejected_"), sender=self.sender[:100],
                       peer=self.peer, why=why)
        self.abort()

    def cancel(self) -> None:
        """End this link (the transport stops, or a newer incarnation of the sender connected)."""
        self.abort()

    def on_message(self, kind: int, payload: bytes) -> bool:
        st = self.st
        if st is None:
            return self._hello(kind, payload)
        if kind != FRAME:
            self.rejected("rejected_malformed", f"message kind {kind} on an open link")
            return False
        t = self.t
        try:
            ok = t.on_frame(payload, self.sender, self.inc, st)
        except Exception as e:  # a LinkGap (the sender resends), or the core's callback failed: end this link
            if not isinstance(e, LinkGap):
                t.counters["link_receive_errors"] += 1
                log_event(log, logging.DEBUG, "link_receive_ended", sender=self.sender,
                          reason=f"{type(e).__name__}: {e}")
            self.abort()
            return False
        if not ok:
            self.abort()
            return False
        assert self.acker is not None
        self.acker.frame(len(payload))
        return True

    def _hello(self, kind: int, payload: bytes) -> bool:
        t = self.t
        md: Any = None
        if kind == HELLO and payload.startswith(HELLO_MAGIC):
            with contextlib.suppress(ValueError, RecursionError):
                md = json.loads(payload[len(HELLO_MAGIC):])
        if not (isinstance(md, dict) and len(md) <= 16 and all(isinstance(v, str) for v in md.values())):
            self.rejected("rejected_malformed", "not a link hello" if kind != HELLO else "a malformed hello")
            return False
        assert self.tr is not None
        try:
            sender, inc, st, _key = t._admit(
                md, t.check_token(md.items()), self.peer, peer_identity(self.tr) if t.tls is not None else None
            )
        except Refusal as r:
            self.send(REFUSE, json.dumps({"code": r.code, "details": r.details, "newer": r.newer}).encode())
            self.closed = True
            self.tr.close()  # (after the refusal is written)
            return False
        self.sender, self.inc, self.st = sender, inc, st
        if self._hello_timer is not None:
            self._hello_timer.cancel()
            self._hello_timer = None
        t._opened_stream(self, sender, inc)
        self.send(REPLY, t.handshake_reply(st))
        self.acker = t.acker(self._write_reply, st)
        return True

    async def _write_reply(self, data: bytes) -> None:
        if self.closed:
            raise ConnectionError("link closed")
        self.send(REPLY, data)
        await self.drained()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        if self._hello_timer is not None:
            self._hello_timer.cancel()
            self._hello_timer = None
        if self.acker is not None:
            self.acker.stop()
            self.acker = None
        if self.st is not None:
            self.t._closed_stream(self, self.sender, self.st)
            self.st = None


async def serve(t: LinkHost, host: str, port: int) -> tuple[asyncio.AbstractServer, int]:
    """Listen for TCP links of transport `t` on `host:port` (see `Transport.open_tcp`)."""
    bind: str | None = host.strip("[]")
    if bind in ("", "::", "0.0.0.0"):
        bind = None
    ctx = server_context(t.tls) if t.tls is not None else None
    server = await asyncio.get_running_loop().create_server(
        lambda: ServerConn(t), bind, port, ssl=ctx, reuse_address=True, backlog=256,
        ssl_handshake_timeout=t.stall_timeout if ctx is not None else None,
    )
    return server, server.sockets[0].getsockname()[1]


# ------------------------------------------------------------------------------------------------ sender


class ClientConn(_Framed):
    """One outbound TCP link as a `linkcommon.LinkCall`: replies are read (rarely: a handshake, then acks at most
    once a `Transport.ack_interval`), frames written."""

    def __init__(self, t: LinkHost) -> None:
        super().__init__(t)
        self._replies: deque[bytes] = deque()
        self._refusal: Exception | None = None
        self._waiter: asyncio.Future[None] | None = None

    def max_payload(self) -> int:
        return MAX_HELLO

    def rejected(self, counter: str, why: str) -> None:
        self.t.counters["link_bad_reply"] += 1
        self._refusal = ConnectionError(f"the receiver sent {why}")
        self.abort()
        self._wake()

    def on_message(self, kind: int, payload: bytes) -> bool:
        if kind == REPLY:
            self._replies.append(payload)
        elif kind == REFUSE:
            try:
                r = json.loads(payload)
                code, details, newer = str(r["code"]), str(r["details"]), r.get("newer")
            except (ValueError, KeyError, TypeError):
                self.rejected("link_bad_reply", "a malformed refusal")
                return False
            self._refusal = LinkRefused(code, details[:1000],
                                        parse_incarnation(str(newer)) if newer is not None else None)
            self.abort()
        else:
            self.rejected("link_bad_reply", f"message kind {kind}")
            return False
        self._wake()
        return not self.closed

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        self._wake()

    async def read(self) -> bytes | None:
        while not self._replies:
            if self._refusal is not None:
                raise self._refusal
            if self.closed:
                return None
            self._waiter = asyncio.get_running_loop().create_future()
            await self._waiter
        return self._replies.popleft()

    async def write(self, data: bytes) -> None:
        if self.closed:
            raise ConnectionError("link closed")
        self.send(FRAME, data)
        if self._paused:
            await self.drained()

    def cancel(self) -> bool:
        if self.tr is not None and not self.closed:
            self.closed = True
            self.tr.close()
        return True


def _wrong_carrier(link: OutLink, answer: str) -> None:
    t = link.t
    t.counters["link_wrong_carrier"] += 1
    if t.limiter.allow("carrier." + link.peer):
        log_event(log, logging.ERROR, "link_wrong_carrier", peer=link.peer, address=link.address, theirs=answer,
                  ours=t.carrier, hint="every host of a cluster must use the same haa-hostd --host-link")


async def connect(link: OutLink, md: tuple[tuple[str, str], ...]) -> ClientConn:
    """Open a TCP session of `link`: ask the peer's gRPC server where its TCP link listens, connect (TLS with
    this host's certificate if it has one, the peer's checked by name), send the hello. The handshake reply is
    the caller's to read (`ClientConn.read`)."""
    t = link.t
    channel = link._channel
    assert channel is not None
    try:
        answer = await channel.unary_unary(PORT_METHOD)(b"", metadata=((MD_TOKEN, t.token),), wait_for_ready=True)
    except aio.AioRpcError as e:
        if e.code() == grpc.StatusCode.UNIMPLEMENTED:
            _wrong_carrier(link, "grpc (a daemon without the tcp host link)")
            raise LinkDown(f"{link.peer} does not offer the tcp host link") from None
        raise
    text = bytes(answer).decode("ascii", "replace")
    kind, _, port_text = text.partition(" ")
    if kind != "tcp" or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        _wrong_carrier(link, text[:40])
        raise LinkDown(f"{link.peer} uses the {text[:40]!r} host link, this host tcp")
    hp = split_address(link.address)
    if hp is None:
        raise LinkDown(f"no port in {link.address!r}")
    ctx = client_context(t.tls) if t.tls is not None else None
    _tr, conn = await asyncio.get_running_loop().create_connection(
        lambda: ClientConn(t), hp[0], int(port_text), ssl=ctx, server_hostname=link.peer if ctx is not None else None,
    )
    conn.send(HELLO, HELLO_MAGIC + json.dumps(dict(md)).encode())
    return conn
