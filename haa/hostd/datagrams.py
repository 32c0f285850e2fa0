"""Heartbeats as datagrams (docs/transport.md, "Heartbeats as datagrams"): this host's UDP heartbeat socket, and
the checks a heartbeat datagram passes before it reaches the core.

A datagram is magic + serialized Envelope + MAC, the MAC being the first HB_MAC_BYTES of HMAC-SHA256 over magic +
envelope. Every link has its own key (`Transport.link_key`), which the sender gives the receiver inside its stream
(haa.hostd.transport's docstring, "Link keys"), so the receiver checks a datagram from `src` with the key of
`src`'s accepted stream: with token or TLS alike, a heartbeat is as authentic as a link message (a key derived from
the cluster token let any token holder forge any host's heartbeats). Anything larger than
HB_MAX_DATAGRAM bytes is not a heartbeat and is dropped unread. The socket's port is announced in every link
handshake; a sender resolves it at each handshake (haa.hostd.outlink) and sends its heartbeats there.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
import socket
from collections import Counter
from collections.abc import Callable
from typing import Any

from google.protobuf.message import DecodeError

from haa.core import wire
from haa.core.messages import Heartbeat
from haa.hostd.linkcommon import RxState
from haa.hostd.logs import LOGGER_NAME, log_event
from haa.pb import hostlink_pb2 as pb

log = logging.getLogger(LOGGER_NAME + ".transport")

HB_MAGIC = b"HAAhb1"
HB_MAC_BYTES = 16
HB_MAX_DATAGRAM = 512


def _mac(key: bytes, body: bytes) -> bytes:
    return hmac.new(key, body, hashlib.sha256).digest()[:HB_MAC_BYTES]


class HeartbeatDatagrams:
    """The heartbeat socket of one host's transport.

    `rx` is the transport's receive state per sender (a datagram counts only from the sender incarnation whose
    stream was accepted, with that stream's key); `on_datagram` is what the socket calls with
    every datagram (the transport's `on_datagram`, which delivers what `accept` lets through).
    """

    def __init__(self, *, counters: Counter[str], rx: dict[str, RxState],
                 on_datagram: Callable[[bytes], None], enabled: bool = True) -> None:
        self.counters = counters
        self.rx = rx
        self.on_datagram = on_datagram
        #: heartbeats as datagrams at all (`haa-hostd --stream-heartbeats` turns them off)
        self.enabled = enabled
        #: the port announced in every handshake (0: none; heartbeats to this host then travel on the streams)
        self.port = 0
        self.udp: asyncio.DatagramTransport | None = None
        self.family = socket.AF_INET

    async def open(self, host: str, port: int) -> int:
        """Take heartbeat datagrams on UDP `host:port` (see `Transport.open_heartbeats`)."""
        if not self.enabled:
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
        self.udp = transport
        self.family = family
        self.port = port
        return port

    def close(self) -> None:
        if self.udp is not None:
            self.udp.close()
            self.udp = None

    def send(self, key: bytes, addr: tuple[Any, ...] | None, data: bytes) -> bool:
        """Send the serialized Envelope `data` of a heartbeat to `addr` with MAC key `key`; False if it did not go
        (no socket, no address, a closed socket): the caller then sends it on the stream."""
        udp = self.udp
        if udp is None or addr is None:
            return False
        body = HB_MAGIC + data
        try:
            udp.sendto(body + _mac(key, body), addr)
        except OSError:  # (asyncio reports send errors to the protocol; this is a closed transport)
            self.counters["hb_send_failed"] += 1
            return False
        self.counters["tx_datagrams"] += 1
        return True

    def accept(self, data: bytes, now: float | None = None) -> tuple[str, int, int, Heartbeat] | None:
        """One UDP datagram: (src, src_inc, dst_inc, heartbeat) if it is a heartbeat to deliver (see
        `Transport.on_datagram`), else None, counted."""
        c = self.counters
        n = len(data)
        if n > HB_MAX_DATAGRAM or n <= len(HB_MAGIC) + HB_MAC_BYTES or not data.startswith(HB_MAGIC):
            c["hb_rejected_malformed"] += 1
            return None
        body, mac = data[:-HB_MAC_BYTES], data[-HB_MAC_BYTES:]
        try:
            env = pb.Envelope.FromString(body[len(HB_MAGIC):])
            src, src_inc, dst_inc, msg = wire.decode(env)
        except (DecodeError, wire.WireError):
            c["hb_rejected_malformed"] += 1
            return None
        if type(msg) is not Heartbeat:
            c["hb_rejected_malformed"] += 1
            return None
        st = self.rx.get(src)
        if st is None:  # no stream of `src` was accepted: no key to check it with
            c["hb_rejected_unknown"] += 1
            return None
        key = st.hb_key  # the key `src` gave this host inside its stream (module docstring)
        if key is None or not hmac.compare_digest(mac, _mac(key, body)):
            c["hb_rejected_unauthenticated"] += 1
            return None
        if st is None or st.inc != src_inc:
            # no stream of this incarnation was accepted (yet), or a newer one was (a superseded process: its
            # streams were ended when the newer one connected, so it learns of it when it reconnects)
            c["hb_rejected_stale" if st is not None and src_inc < st.inc else "hb_rejected_unknown"] += 1
            return None
        c["rx_msgs.heartbeat"] += 1
        c["rx_bytes.heartbeat"] += n
        c["rx_datagrams"] += 1
        st.confirmed = True
        st.heard = asyncio.get_running_loop().time() if now is None else now
        st.period = min(msg.period, 10.0)
        return src, src_inc, dst_inc, msg


class _HeartbeatProtocol(asyncio.DatagramProtocol):
    """The heartbeat socket: every datagram goes to `Transport.on_datagram`; a failure there is counted and
    never closes the socket."""

    def __init__(self, d: HeartbeatDatagrams) -> None:
        self.d = d

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            self.d.on_datagram(data)
        except Exception:  # the core's own errors are caught by the runtime; this is a safety net
            self.d.counters["hb_receive_errors"] += 1
            log.exception("heartbeat datagram failed", extra={"event": "heartbeat_error", "fields": {}})

    def error_received(self, exc: Exception) -> None:  # e.g. ICMP port unreachable: the peer is down
        self.d.counters["hb_send_errors"] += 1
