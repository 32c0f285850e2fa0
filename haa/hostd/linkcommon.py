"""What both carriers of a host link share without importing each other: the handshake metadata names, the
incarnation parser, host:port splitting and the exceptions of a link session (haa.hostd.transport is the link,
haa.hostd.tcplink the TCP carrier; both import this module, which imports neither)."""

from __future__ import annotations

import re

MD_TOKEN = "x-haa-token"
MD_SENDER = "x-haa-sender"
MD_INC = "x-haa-incarnation"
#: trailing metadata of a stale-incarnation refusal: the newer incarnation of the sender the receiver knows
MD_NEWER = "x-haa-newer-incarnation"
#: incarnations are unsigned 64-bit numbers (the wire's `uint64`); 0 means "unknown" and is never valid
MAX_INCARNATION = (1 << 64) - 1
_INC_RE = re.compile(r"[1-9][0-9]{0,19}")


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
