"""The sending half of a host link (haa.hostd.transport's docstring, "Sender"): `OutLink`, one per peer — its
queue of encoded envelopes, its link task (connect through the carrier, handshake, resend from the receiver's
`acked_seq + 1`, write the queue as frames, read the acks), and `LazyRelease`, which holds lazy messages while the
host is busy (docs/transport.md, "Lazy messages").

Frames are built by hand from pre-serialized envelopes (`envelope_chunk`, `encode_frame`): a Frame is field 1
(varint `first_seq`) followed by one length-delimited field 2 per envelope, so concatenating the envelope chunks
is a valid protobuf encoding and a resend never re-serializes anything.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import grpc
from google.protobuf.message import DecodeError
from grpc import aio

from haa import tls as tlsmod
from haa.hostd import tcplink
from haa.hostd.datagrams import HeartbeatDatagrams
from haa.hostd.grpclink import OPEN_METHOD, TCP, GrpcCall, client_options
from haa.hostd.linkcommon import (
    MD_HB_KEY,
    MD_INC,
    MD_NEWER,
    MD_SENDER,
    MD_TOKEN,
    LinkCall,
    LinkDown,
    LinkHost,
    LinkRefused,
    parse_incarnation,
    split_address,
)
from haa.hostd.logs import LOGGER_NAME, log_event
from haa.pb import hostlink_pb2 as pb

log = logging.getLogger(LOGGER_NAME + ".transport")

#: (dst_inc, envelope chunk) — what a link queues
Entry = tuple[int, bytes]
#: called with (peer, incarnation) when a handshake shows a receiver incarnation this link did not know
OnPeerIncarnation = Callable[[str, int], None]
#: called with (peer, newer) when `peer` refused this host's incarnation because it knows a newer one of this
#: host's name (`newer`): this process has been superseded (docs/membership.md, "incarnation claims")
OnSuperseded = Callable[[str, int], None]

#: lazy messages (an OAC decision rebroadcast, a round estimate nobody waits for) wait for other traffic on their
#: link while this host is busy — it received a frame within the last LAZY_QUIET seconds — but never longer than
#: LAZY_DELAY; once the host is quiet they are written at once (docs/transport.md, "Lazy messages")
LAZY_DELAY = 0.02
LAZY_QUIET = 0.003
#: a quiet check that runs this much later than it was due counts as busy
LAZY_LATE = 0.001


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def length_delimited(field: int, data: bytes) -> bytes:
    """Already serialized bytes as protobuf field `field` (wire type 2), to be joined with a message's other
    fields without decoding them (a field may come in any order in a serialized message)."""
    return _varint(field << 3 | 2) + _varint(len(data)) + data


def envelope_chunk(env_bytes: bytes) -> bytes:
    """A serialized Envelope as one element of `Frame.envelopes` (field 2)."""
    return length_delimited(2, env_bytes)


def encode_frame(first_seq: int, chunks: list[bytes]) -> bytes:
    """Serialized `Frame(first_seq, envelopes)` from envelope chunks (tag 1 varint + the chunks)."""
    return b"\x08" + _varint(first_seq) + b"".join(chunks)


class LinkOwner(LinkHost, Protocol):
    """What an `OutLink` uses of its `haa.hostd.transport.Transport` (which imports this module)."""

    incarnation: int
    precontact_limit: int
    max_queue: int
    min_backoff: float
    max_backoff: float
    handshake_timeout: float
    max_batch: int
    max_batch_bytes: int
    lazy: LazyRelease
    datagrams: HeartbeatDatagrams
    on_peer_incarnation: OnPeerIncarnation
    on_superseded: OnSuperseded
    on_live_elsewhere: Callable[[str], None]

    def track(self, task: asyncio.Task[Any]) -> None: ...

    def link_key(self, peer: str) -> bytes: ...


class LazyRelease:
    """The lazy messages of every link of one host: a link that holds lazy messages only (`OutLink.enqueue`) is
    registered here, and one timer releases them all once the host is quiet — no frame received (`last_rx`, set by
    the receiver) within `quiet` seconds — or the oldest has waited `delay` seconds."""

    def __init__(self, delay: float = LAZY_DELAY, quiet: float = LAZY_QUIET) -> None:
        self.delay = delay
        self.quiet = quiet
        self.links: set[OutLink] = set()  # links holding lazy messages only
        self.since = 0.0  # when the first of them was held
        self.timer: asyncio.TimerHandle | None = None
        self.at = 0.0  # when `timer` is due
        #: loop time of the last frame received on any link
        self.last_rx = 0.0

    def hold(self, link: OutLink) -> None:
        """`link` holds lazy messages only: release them once this host is quiet (one timer for all links)."""
        links = self.links
        if not links:
            self.since = asyncio.get_running_loop().time()
        links.add(link)
        if self.timer is None:
            loop = asyncio.get_running_loop()
            self.at = loop.time() + self.quiet
            self.timer = loop.call_at(self.at, self.check)

    def check(self) -> None:
        """While frames keep arriving (other traffic is about to leave on the links) and the oldest held message
        is younger than `delay`, hold on; otherwise write every link's held messages."""
        self.timer = None
        loop = asyncio.get_running_loop()
        now = loop.time()
        # busy: a frame arrived lately, or this check itself ran late (the process waited for a CPU, and frames
        # may be waiting to be read)
        busy = now - self.last_rx < self.quiet or now - self.at > LAZY_LATE
        if busy and now - self.since < self.delay:
            self.at = now + self.quiet
            self.timer = loop.call_at(self.at, self.check)
            return
        links, self.links = self.links, set()
        for link in links:
            if link.pending and not link._due:
                link._due = True
                link.wake.set()

    def cancel(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


class OutLink:
    """The sending half of the link to one peer (see haa.hostd.transport's docstring, "Sender")."""

    def __init__(self, transport: LinkOwner, peer: str, address: str) -> None:
        self.t = transport
        self.peer = peer
        self.address = address
        self.pending: deque[Entry] = deque()  # not yet written on the current stream
        self.unacked: deque[Entry] = deque()  # written, not yet acknowledged; seqs base, base+1, ...
        #: bytes of the envelopes in `pending` and `unacked`: what this link holds of this host's memory. Agent
        #: messages wait for it to drop below `haa.hostd.budget.LINK_QUEUE_BYTES` before they enter it
        self.queued_bytes = 0
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
        #: the key of this process's link to the peer (`Transport.link_key`): sent in every stream's metadata, it
        #: MACs this link's heartbeat datagrams and shows the receiver that a new stream comes from the same process
        self.hb_key = transport.link_key(peer)
        #: something queued must go now: an ordinary (not lazy) message, lazy ones the transport released
        #: (`LazyRelease`), or a resend after a handshake. Lazy messages alone only register the link
        #: with the transport (docs/transport.md, "Lazy messages")
        self._due = True

    # ------------------------------------------------------------------ queueing (synchronous)

    def enqueue(self, dst_inc: int, chunk: bytes, lazy: bool = False) -> None:
        pending = self.pending
        pending.append((dst_inc, chunk))
        self.queued_bytes += len(chunk)
        t = self.t
        if not self.receiver_inc and len(pending) > t.precontact_limit and pending[0][0] == 0:
            self.queued_bytes -= len(pending.popleft()[1])
            t.counters["dropped_precontact"] += 1
        elif len(pending) + len(self.unacked) > t.max_queue:
            self.queued_bytes -= len(pending.popleft()[1])
            t.counters["dropped_overflow"] += 1
            if t.limiter.allow("overflow." + self.peer):
                log_event(log, logging.WARNING, "link_overflow", peer=self.peer, queued=len(pending))
        if not lazy or t.lazy.delay <= 0:
            self._due = True
            self.wake.set()
        elif not self._due:
            t.lazy.hold(self)

    @property
    def next_seq(self) -> int:
        return self.base + len(self.unacked) + len(self.pending)

    def reset(self) -> None:
        """This host became a new incarnation: the old incarnation's messages are void, numbering restarts."""
        self._gen += 1  # acks still arriving on the old stream count the old numbering
        self._next_write = 1
        self.pending.clear()
        self.unacked.clear()
        self.queued_bytes = 0
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
            self.t.track(asyncio.get_running_loop().create_task(old.close()))
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
        if code == "UNAVAILABLE":  # another process under this host's name is live at the peer
            asyncio.get_running_loop().call_soon(t.on_live_elsewhere, self.peer)
        if code != "FAILED_PRECONDITION":
            return
        if newer is not None and newer > t.incarnation:
            t.counters["link_superseded"] += 1
            # not from inside this task: the callback reincarnates, which restarts (cancels) every link task
            asyncio.get_running_loop().call_soon(t.on_superseded, self.peer, newer)

    async def _session(self) -> None:
        t = self.t
        md: tuple[tuple[str, str], ...] = ((MD_TOKEN, t.token), (MD_SENDER, t.name), (MD_INC, str(t.incarnation)))
        md += ((MD_HB_KEY, self.hb_key.hex()),)
        call: LinkCall | None = None
        try:
            try:
                async with asyncio.timeout(t.handshake_timeout):
                    if t.carrier == TCP:
                        call = await tcplink.connect(self, md)
                    else:
                        call = GrpcCall(self._open(metadata=md, wait_for_ready=True))
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
        if not port or t.datagrams.udp is None or hp is None:
            self.hb_addr = None
            return
        try:
            infos = await asyncio.get_running_loop().getaddrinfo(hp[0], port, family=t.datagrams.family,
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
            self.queued_bytes = sum(len(e[1]) for e in keep)
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
            self.queued_bytes -= len(unacked.popleft()[1])
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
        freed = 0
        for _ in range(n):
            freed += len(unacked.popleft()[1])
        self.queued_bytes -= freed
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
