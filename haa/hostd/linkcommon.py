"""What the host link and its carriers share without importing each other: the handshake metadata names, the
largest frame, the incarnation parser, host:port splitting, the exceptions of a link session, the receiver's
state per sender incarnation (`RxState`), and what a carrier is to the link — a sender-side session (`LinkCall`)
— and the link to a carrier (`LinkHost`: the checks, frame handling and acks of `haa.hostd.transport.Transport`
that both carriers' receivers share). haa.hostd.transport is the link (haa.hostd.outlink its sending half,
haa.hostd.datagrams its heartbeat datagrams); haa.hostd.grpclink and haa.hostd.tcplink are its carriers. All of
them import this module, which imports none of them."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from haa import tls as tlsmod
from haa.hostd.logs import RateLimiter

MD_TOKEN = "x-haa-token"
MD_SENDER = "x-haa-sender"
MD_INC = "x-haa-incarnation"
#: the sender process's link key for this receiver, hex (haa.hostd.transport's docstring, "Link keys")
MD_HB_KEY = "x-haa-hb-key"
#: trailing metadata of a stale-incarnation refusal: the newer incarnation of the sender the receiver knows
MD_NEWER = "x-haa-newer-incarnation"
#: incarnations are unsigned 64-bit numbers (the wire's `uint64`); 0 means "unknown" and is never valid
MAX_INCARNATION = (1 << 64) - 1
_INC_RE = re.compile(r"[1-9][0-9]{0,19}")
#: the largest host-link message, a frame (one carries a joiner's whole state, `StateSnapshot`: the DDB and the
#: agent table with every backup), and the largest gRPC message a host sends or a client of it receives
MAX_MESSAGE = 64 << 20


def parse_incarnation(text: str) -> int | None:
    """The `x-haa-incarnation` metadata value as an incarnation, or None: plain decimal digits only (no sign,
    spaces, underscores or non-ASCII digits, which `int()` would accept), 1 .. `MAX_INCARNATION`."""
    if not isinstance(text, str) or not _INC_RE.fullmatch(text):
        return None
    inc = int(text)
    return inc if inc <= MAX_INCARNATION else None


def split_address(address: str) -> tuple[str, int] | None:
    """("host", port) of "host:port" or "[v6]:port"; None if it has no numeric port."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return None
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host, int(port)


class LinkDown(Exception):
    """The current stream of a link ended (the link task reconnects)."""


class LinkRefused(Exception):
    """The receiver refused the link: `code` is a `grpc.StatusCode` name (both carriers use gRPC's codes),
    `newer` the newer incarnation of this host's name it knows (a stale-incarnation refusal), if any."""

    def __init__(self, code: str, details: str, newer: int | None = None) -> None:
        super().__init__(f"{code}: {details}")
        self.code = code
        self.details = details
        self.newer = newer


class LinkGap(Exception):
    """A frame skips link sequence numbers: end the stream, the sender resends from our last + 1."""


class Refusal(Exception):
    """`Transport._admit` refuses an inbound link: a `grpc.StatusCode` name, the details, and for a stale
    incarnation the newer one the receiver knows (both carriers send all three to the sender)."""

    def __init__(self, code: str, details: str, newer: int | None = None) -> None:
        super().__init__(f"{code}: {details}")
        self.code = code
        self.details = details
        self.newer = newer


class RxState:
    """What a receiver knows of one sender incarnation (per sender name, the latest it accepted)."""

    __slots__ = ("bad_run", "confirmed", "dup_run", "gaps", "hb_key", "heard", "inc", "last", "period", "streams")

    def __init__(self, inc: int) -> None:
        self.inc = inc
        self.last = 0  # highest link sequence number delivered from this sender incarnation
        self.gaps = 0  # streams ended in a row because of a gap in the numbering
        self.streams = 0  # open inbound streams of this incarnation
        self.confirmed = False  # it delivered a valid envelope (more than a claim in metadata)
        self.heard = float("-inf")  # loop time of its last valid envelope
        self.period = 0.0  # the heartbeat period it announced last, s
        self.hb_key: bytes | None = None  # its link key (MACs its heartbeat datagrams to this host)
        self.dup_run = 0  # envelopes in a row that were duplicates (no new one since)
        self.bad_run = 0  # envelopes in a row that were refused as invalid


#: what `Transport._admit` returns: (sender, sender incarnation, its receive state, its link key)
Admitted = tuple[str, int, RxState, bytes | None]


class LinkCall(Protocol):
    """One sender-side session of a link, whatever carries it (a grpc.aio stream call,
    `haa.hostd.grpclink.GrpcCall`, or a TCP connection, `haa.hostd.tcplink.ClientConn`): the receiver's replies,
    serialized `LinkReply`s (None once the stream ended), and the serialized `Frame`s this side writes."""

    async def read(self) -> bytes | None: ...

    async def write(self, data: bytes) -> None: ...

    def cancel(self) -> bool | None: ...


class Acks(Protocol):
    """The acks of one inbound link (`haa.hostd.transport.Acker`): `frame(size)` after every frame taken."""

    def frame(self, size: int = 0) -> None: ...

    def stop(self) -> None: ...


class LinkHost(Protocol):
    """What a carrier's receiver uses of `haa.hostd.transport.Transport` (which imports the carriers, so they do
    not import it): its settings, counters, and the checks, frame handling and acks both carriers share."""

    name: str
    token: str
    carrier: str
    tls: tlsmod.HostTls | None
    stall_timeout: float
    tcp_port: int
    counters: Counter[str]
    limiter: RateLimiter

    def check_token(self, metadata: Any) -> bool: ...

    def _admit(self, md: dict[str, str], token_ok: bool, peer: str, ident: tuple[str, str] | None) -> Admitted: ...

    def _reject(self, counter: str, event: str, **fields: Any) -> None: ...

    def _opened_stream(self, handle: Any, sender: str, inc: int) -> None: ...

    def _closed_stream(self, handle: Any, sender: str, st: RxState) -> None: ...

    def ending(self, handle: Any) -> bool: ...

    def handshake_reply(self, st: RxState) -> bytes: ...

    def acker(self, write: Callable[[bytes], Awaitable[None]], st: RxState) -> Acks: ...

    def wrong_carrier(self, peer: str, theirs: str) -> str: ...

    def on_frame(self, data: bytes, sender: str, inc: int, st: RxState) -> bool: ...
