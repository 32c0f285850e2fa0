"""The host-to-host transport (haa.hostd.transport), in-process on loopback, over both carriers of the links
(a grpc.aio stream, or a framed TCP connection: haa.hostd.tcplink) — the tests of link semantics run once per
carrier (`carrier` fixture).

FIFO and no loss across broken connections, receiver and sender reincarnations, a down peer not stalling the
others, and the receiver's handling of hostile input (bad token, unknown sender, garbage, invalid envelopes,
duplicates); the TCP carrier's own hostile input (bytes that are not frames, oversized lengths, a peer that
stops mid-frame) and a cluster whose hosts use different carriers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import ssl
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import grpc
import pytest
from grpc import aio
from helpers import run, until

from haa.cluster.hostprocs import free_port
from haa.core import wire
from haa.core.messages import Excluded, Heartbeat, Message
from haa.hostd import tcplink
from haa.hostd.transport import (
    MAX_MESSAGE,
    MD_HB_KEY,
    MD_INC,
    MD_SENDER,
    MD_TOKEN,
    OPEN_METHOD,
    Transport,
    encode_frame,
    envelope_chunk,
)
from haa.pb import hostlink_pb2 as pb

TOKEN = "test-token"
FAST = {"min_backoff": 0.01, "max_backoff": 0.1, "handshake_timeout": 1.0}


@pytest.fixture(params=["grpc", "tcp"])
def carrier(request: pytest.FixtureRequest) -> str:
    return str(request.param)


class Node:
    """A Transport with its own grpc.aio server (and, on the TCP carrier, its TCP link server: a new port at every
    `serve`, which the senders learn from the gRPC server), recording what it receives."""

    def __init__(self, name: str, inc: int, port: int, peers: dict[str, int], **kw: Any) -> None:
        self.name = name
        self.port = port
        self.got: list[tuple[str, int, int, Message]] = []
        self.peer_incs: list[tuple[str, int]] = []
        self.t = Transport(
            name,
            TOKEN,
            {p: f"127.0.0.1:{pp}" for p, pp in peers.items()},
            on_envelopes=self._on_envelopes,
            on_peer_incarnation=lambda p, i: self.peer_incs.append((p, i)),
            **{**FAST, **kw},
        )
        self.t.incarnation = inc
        self.server: aio.Server | None = None

    def _on_envelopes(self, src: str, src_inc: int, items: list[tuple[int, Message]]) -> None:
        for dst_inc, msg in items:
            self.got.append((src, src_inc, dst_inc, msg))

    def seqs(self) -> list[int]:
        return [msg.seq for _s, _i, _d, msg in self.got if isinstance(msg, Heartbeat)]

    async def serve(self) -> None:
        server = aio.server(options=Transport.server_options())
        self.t.add_to_server(server)
        assert server.add_insecure_port(f"127.0.0.1:{self.port}") == self.port
        await server.start()
        self.server = server
        if self.t.carrier == "tcp":
            await self.t.open_tcp("127.0.0.1", 0)

    async def stop_server(self) -> None:
        assert self.server is not None
        self.t.close_tcp()
        await self.server.stop(0)
        self.server = None

    async def close(self) -> None:
        await self.t.stop()
        if self.server is not None:
            await self.stop_server()


async def connected_pair(carrier: str) -> tuple[Node, Node]:
    """Sender a#11 linked to a serving receiver b#22, the link up."""
    pa, pb_ = free_port(), free_port()
    a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
    b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
    await b.serve()
    a.t.start()
    await until(lambda: a.t.connected("b"), what="first connection")
    return a, b


def hb(i: int) -> Heartbeat:
    return Heartbeat(i, 0.1, float(i))


def test_a_frame_larger_than_what_a_server_accepts_arrives_in_pieces(carrier: str) -> None:
    """A joiner's state snapshot of 20 MB (above the server's MAX_REQUEST, below MAX_MESSAGE) arrives whole and
    in order with small messages around it; on the gRPC carrier it went as pieces of at most LINK_PIECE."""
    from haa.core.messages import StateSnapshot
    from haa.hostd.transport import LINK_PIECE, MAX_REQUEST

    big = bytes(range(256)) * (20_000_000 // 256)
    assert MAX_REQUEST < len(big) < MAX_MESSAGE

    async def main() -> None:
        a, b = await connected_pair(carrier)
        a.t.send("b", 22, hb(1))
        a.t.send("b", 22, StateSnapshot(7, big, None, 0))
        a.t.send("b", 22, hb(2))
        await until(lambda: len(b.got) == 3, timeout=20, what="the snapshot and the heartbeats around it")
        kinds = [type(m).__name__ for _s, _i, _d, m in b.got]
        assert kinds == ["Heartbeat", "StateSnapshot", "Heartbeat"], kinds
        snap = b.got[1][3]
        assert isinstance(snap, StateSnapshot) and snap.seq == 7 and snap.data == big
        assert b.t.counters["link_receive_errors"] == 0 and b.t.counters["rejected_malformed"] == 0
        if carrier == "grpc":
            assert b.t.counters["rx_frames"] <= 3 and len(big) // LINK_PIECE >= 4
        await a.close()
        await b.close()

    run(main())


def test_frame_pieces_join_to_the_frame_and_nothing_else_is_taken_for_a_piece() -> None:
    from haa.hostd.transport import FramePieces, frame_pieces

    frame = encode_frame(5, [envelope_chunk(b"e" * 1000) for _ in range(10)])
    pieces = frame_pieces(frame, piece=3000)
    assert len(pieces) == 4 and all(len(p) <= 3000 + 8 for p in pieces)
    assert [pb.Frame.FromString(p).more for p in pieces] == [True, True, True, False]
    rx = FramePieces()
    assert [rx.add(p) for p in pieces] == [None, None, None, frame]
    assert rx.add(frame) is frame  # a whole frame passes untouched
    assert rx.add(b"\xff\xff garbage") == b"\xff\xff garbage"  # not a piece: on_frame rejects it
    bounded = FramePieces(limit=5000)
    assert bounded.add(pieces[0]) is None
    with pytest.raises(ValueError, match="more than 5000 bytes"):
        bounded.add(pieces[1])


def test_the_server_refuses_a_message_above_max_request_unread() -> None:
    """What got a host expelled: gRPC read a 50 MB control request whole on the event loop (1-5 s). The server
    now takes at most MAX_REQUEST; above it gRPC answers RESOURCE_EXHAUSTED and the loop barely notices."""
    from haa.hostd.transport import MAX_REQUEST
    from haa.pb import control_pb2 as cpb
    from haa.pb import control_pb2_grpc

    class Ctl(control_pb2_grpc.HostControlServicer):
        async def AgentSpawn(self, request: Any, context: Any) -> Any:
            return cpb.AgentOpReply(ok=True, reason=str(len(request.config)))

    async def main() -> None:
        server = aio.server(options=Transport.server_options())
        control_pb2_grpc.add_HostControlServicer_to_server(Ctl(), server)
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        lags: list[float] = []

        async def probe() -> None:
            while True:
                t0 = time.perf_counter()
                await asyncio.sleep(0.01)
                lags.append(time.perf_counter() - t0 - 0.01)

        watch = asyncio.create_task(probe())

        def call(n: int) -> Any:
            with grpc.insecure_channel(f"127.0.0.1:{port}", options=[("grpc.max_send_message_length", -1)]) as ch:
                stub = control_pb2_grpc.HostControlStub(ch)
                try:
                    return stub.AgentSpawn(cpb.AgentSpawnRequest(type="x", config=b"x" * n), timeout=20)
                except grpc.RpcError as e:
                    return e.code()

        ok = await asyncio.to_thread(call, MAX_REQUEST - 1000)
        assert ok.ok and ok.reason == str(MAX_REQUEST - 1000)
        lags.clear()
        assert await asyncio.to_thread(call, 50_000_000) == grpc.StatusCode.RESOURCE_EXHAUSTED
        watch.cancel()
        await server.stop(0)
        assert max(lags, default=0.0) < 0.5, max(lags)

    run(main())


# ------------------------------------------------------------------------------------------------ (f)


def test_fifo_and_no_loss_across_receiver_server_restarts(carrier: str) -> None:
    """The receiver's gRPC server is closed and reopened twice while the sender keeps queueing messages:
    every message arrives exactly once and in order."""

    async def main() -> None:
        a, b = await connected_pair(carrier)
        sent = 0
        stop = asyncio.Event()
        queued_while_down: list[int] = []

        async def produce() -> None:
            nonlocal sent
            while not stop.is_set():
                sent += 1
                a.t.send("b", 22, hb(sent))
                if sent % 20 == 0:
                    await asyncio.sleep(0.001)  # a producer's pace: the links run between bursts

        producer = asyncio.create_task(produce())
        for _ in range(2):
            mark = len(b.got)
            await until(lambda m=mark: len(b.got) > m + 500, what="progress")
            await b.stop_server()  # the connection breaks with frames in flight
            await until(lambda: not a.t.connected("b"), what="disconnect")
            await until(lambda: a.t.queued("b") > 0, what="messages queued while b is down")
            queued_while_down.append(a.t.queued("b"))
            await b.serve()  # same Transport object: it remembers what it already has
        mark = len(b.got)
        await until(lambda: len(b.got) > mark + 500, what="progress after the last restart")
        stop.set()
        await producer
        n = sent
        await until(lambda: len(b.got) >= n, timeout=10, what="all messages")
        await asyncio.sleep(0.05)  # a quiet period: a duplicate would arrive now
        assert b.seqs() == list(range(1, n + 1))
        assert all(src == "a" and inc == 11 and dst == 22 for src, inc, dst, _m in b.got)
        assert a.t.counters["link_disconnects"] >= 2
        assert a.t.counters["link_connects"] >= 3
        assert all(q > 0 for q in queued_while_down)  # messages really were queued while it was down
        assert b.t.counters["rx_frames"] < n  # batching: fewer frames than messages
        assert b.t.counters["link_gap"] == 0
        await until(lambda: a.t.queued("b") == 0, what="everything acknowledged")
        await a.close()
        await b.close()

    run(main())


def test_a_link_counts_its_bytes_until_acked_bulk_is_acked_early_and_acks_wait_for_the_gate(carrier: str) -> None:
    """What a link holds is counted in bytes until the receiver acknowledges it (haa.hostd.budget admits agent
    messages by it); the receiver acknowledges after ACK_BYTES at once, not an ack interval later; and while its
    ack gate is closed (its agents have not read what it delivered to them) it delivers frames but acknowledges
    nothing, so the sender keeps counting them."""
    from haa.core.messages import StateSnapshot
    from haa.hostd.transport import ACK_BYTES

    mib = 1 << 20

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier, ack_interval=30.0)  # no ack by the clock in this test
        await b.serve()
        a.t.start()
        await until(lambda: a.t.connected("b"), what="first connection")
        a.t.send("b", 22, hb(1))  # the first frame of a stream is acknowledged at once
        await until(lambda: a.t.queued_bytes("b") == 0, what="the first frame acknowledged")
        n = 2 * ACK_BYTES // mib + 1
        for i in range(n):
            a.t.send("b", 22, StateSnapshot(i, bytes(mib), None, 0))
        assert a.t.queued_bytes("b") > n * mib
        await until(lambda: len(b.got) == n + 1, what="the snapshots delivered")
        # acknowledged after every ACK_BYTES received: all but the last one's at most, long before ack_interval
        await until(lambda: a.t.queued_bytes("b") <= ACK_BYTES, what="early acks")
        assert b.t.counters["acks_early"] >= 1
        gate = [False]
        b.t.ack_gate = lambda: gate[0]
        for i in range(n):
            a.t.send("b", 22, StateSnapshot(i, bytes(mib), None, 0))
        await until(lambda: len(b.got) == 2 * n + 1, what="delivered with the gate closed")
        held = a.t.queued_bytes("b")
        assert held > ACK_BYTES
        await asyncio.sleep(0.2)  # a quiet period: no ack may come while the gate is closed
        assert a.t.queued_bytes("b") == held and b.t.counters["acks_held"] >= 1
        gate[0] = True
        await until(lambda: a.t.queued_bytes("b") == 0, what="everything acknowledged once the gate opened")
        await a.close()
        await b.close()

    run(main())


def test_new_receiver_incarnation_discards_messages_for_the_old_one(carrier: str) -> None:
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        a.t.start()
        await until(lambda: a.t.connected("b"))
        for i in range(1, 11):
            a.t.send("b", 22, hb(i))
        await until(lambda: len(b.got) == 10)
        assert a.peer_incs == [("b", 22)]
        await b.close()  # process b is gone
        await until(lambda: not a.t.connected("b"))
        for i in range(11, 16):
            a.t.send("b", 22, hb(i))  # addressed to the dead incarnation
        for i in range(16, 19):
            a.t.send("b", 0, hb(i))  # addressed to "whoever b is"
        b2 = Node("b", 33, pb_, {"a": pa}, carrier=carrier)
        await b2.serve()
        await until(lambda: a.t.connected("b"))
        await until(lambda: len(b2.got) == 3)
        assert b2.seqs() == [16, 17, 18]
        assert a.peer_incs == [("b", 22), ("b", 33)]
        assert a.t.counters["link_discarded"] == 5
        a.t.send("b", 33, hb(19))
        await until(lambda: len(b2.got) == 4)
        assert b2.seqs() == [16, 17, 18, 19]
        assert b2.t.counters["link_gap"] == 0  # renumbered after the new receiver's acked_seq
        await a.close()
        await b2.close()

    run(main())


def test_sender_reincarnation_restarts_numbering_and_stale_sender_is_refused(carrier: str) -> None:
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        a.t.start()
        await until(lambda: a.t.connected("b"))
        for i in range(1, 6):
            a.t.send("b", 22, hb(i))
        await until(lambda: len(b.got) == 5)
        a.t.set_incarnation(12)
        for i in range(6, 9):
            a.t.send("b", 22, hb(i))
        await until(lambda: len(b.got) == 8)
        assert [(inc, msg.seq) for _s, inc, _d, msg in b.got] == [(11, i) for i in range(1, 6)] + [
            (12, i) for i in range(6, 9)
        ]
        assert b.t.counters["link_gap"] == 0
        with pytest.raises(ValueError):
            a.t.set_incarnation(12)
        # a leftover process of incarnation 11 is refused
        old = Node("a", 11, free_port(), {"b": pb_}, carrier=carrier)
        old.t.start()
        await until(lambda: b.t.counters["rejected_stale_incarnation"] >= 1)
        assert not old.t.connected("b")
        await old.close()
        await a.close()
        await b.close()

    run(main())


def test_a_down_peer_does_not_stall_the_others(carrier: str) -> None:
    async def main() -> None:
        pa, pb_, pc = free_port(), free_port(), free_port()  # nothing listens on pc
        a = Node("a", 11, pa, {"b": pb_, "c": pc}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        a.t.start()
        t0 = time.monotonic()
        await until(lambda: a.t.connected("b"))
        for i in range(1, 201):
            a.t.send("c", 7, hb(i))
            a.t.send("b", 22, hb(i))
        await until(lambda: len(b.got) == 200, timeout=2.0)
        assert time.monotonic() - t0 < 2.0
        assert not a.t.connected("c")
        assert a.t.queued("c") == 200  # kept for when c comes up (addressed to a known incarnation)
        await a.close()
        await b.close()

    run(main())


def test_lazy_messages_wait_for_other_traffic_and_keep_their_order(carrier: str) -> None:
    """A lazy message is written once the host is quiet (no frame received for `lazy_quiet`), or with the next
    ordinary message on its link, in order; while frames keep arriving it waits, but at most `lazy_delay`
    (docs/transport.md, "Lazy messages")."""

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier, lazy_delay=0.6, lazy_quiet=0.15)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        await a.serve()
        a.t.start()
        b.t.start()
        await until(lambda: a.t.connected("b") and b.t.connected("a"), what="connections")
        frames0 = b.t.counters["rx_frames"]
        # quiet host: held for lazy_quiet, then written
        t0 = time.monotonic()
        a.t.send("b", 22, hb(1), lazy=True)
        await asyncio.sleep(0.05)  # within lazy_quiet: the message must still be held
        assert b.got == []
        await until(lambda: len(b.got) == 1, timeout=2.0, what="the lazy message alone")
        assert 0.12 <= time.monotonic() - t0 < 0.5
        # lazy, lazy, ordinary: one frame, at once, in order
        t1 = time.monotonic()
        a.t.send("b", 22, hb(2), lazy=True)
        a.t.send("b", 22, hb(3), lazy=True)
        a.t.send("b", 22, hb(4))
        await until(lambda: len(b.got) == 4, timeout=2.0, what="the ordinary message")
        assert time.monotonic() - t1 < 0.1
        assert b.seqs() == [1, 2, 3, 4]
        assert b.t.counters["rx_frames"] - frames0 == 2
        await asyncio.sleep(0.3)
        assert b.t.counters["rx_frames"] - frames0 == 2  # nothing left over to write
        # a busy host (b keeps sending to a) holds a lazy message up to lazy_delay
        stop = asyncio.Event()

        async def chatter() -> None:
            i = 100
            while not stop.is_set():
                i += 1
                b.t.send("a", 11, hb(i))
                await asyncio.sleep(0.02)

        chat0 = a.t.counters["rx_frames"]
        task = asyncio.create_task(chatter())
        await until(lambda: a.t.counters["rx_frames"] >= chat0 + 3, what="b's chatter arriving at a")
        t2 = time.monotonic()
        a.t.send("b", 22, hb(5), lazy=True)
        await until(lambda: len(b.got) == 5, timeout=2.0, what="the lazy message on a busy host")
        assert 0.5 <= time.monotonic() - t2 < 1.0
        stop.set()
        await task
        await a.close()
        await b.close()

    run(main())


def test_before_first_contact_only_recent_unaddressed_messages_are_kept(carrier: str) -> None:
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier, precontact_limit=16)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        a.t.start()
        for i in range(1, 101):
            a.t.send("b", 0, hb(i))  # heartbeats to a peer that has not started yet
        await asyncio.sleep(0.05)  # ... and stays down a while: a's link tries and fails
        await b.serve()
        await until(lambda: len(b.got) == 16)
        await asyncio.sleep(0.05)  # a quiet period: no 17th may follow
        assert b.seqs() == list(range(85, 101))
        assert a.t.counters["dropped_precontact"] == 84
        await a.close()
        await b.close()

    run(main())


# ------------------------------------------------------------------------------------------ hostile input


class RawLink:
    """A hand-driven HostLink.Open call (bytes in, bytes out)."""

    def __init__(self, port: int, md: tuple[tuple[str, str], ...]) -> None:
        self.channel = aio.insecure_channel(f"127.0.0.1:{port}")
        self.call = self.channel.stream_stream(OPEN_METHOD)(metadata=md)

    async def reply(self) -> pb.LinkReply:
        data = await asyncio.wait_for(self.call.read(), 5)
        assert data is not aio.EOF
        return pb.LinkReply.FromString(data)

    async def close(self) -> None:
        self.call.cancel()
        await self.channel.close()


class TcpRefused(Exception):
    def __init__(self, code: str, newer: int | None) -> None:
        super().__init__(code)
        self.code = code
        self.newer = newer


class RawTcp:
    """A hand-driven TCP host link (haa.hostd.tcplink's framing): the hello, then frames; replies one by one.
    `call` is itself, so that tests drive it like `RawLink` (`call.write`, `call.read` returning `aio.EOF`)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer
        self.call = self

    @classmethod
    async def open(cls, port: int, md: tuple[tuple[str, str], ...] | None, raw: bytes = b"") -> RawTcp:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        conn = cls(reader, writer)
        if md is not None:
            conn.send(tcplink.HELLO, tcplink.HELLO_MAGIC + json.dumps(dict(md)).encode())
        if raw:
            writer.write(raw)
        return conn

    def send(self, kind: int, payload: bytes) -> None:
        self.writer.write(tcplink.HEADER.pack(kind, len(payload)) + payload)

    async def write(self, data: bytes) -> None:
        self.send(tcplink.FRAME, data)
        await self.writer.drain()

    async def read(self) -> Any:
        try:
            kind, n = tcplink.HEADER.unpack(await asyncio.wait_for(self.reader.readexactly(5), 5))
            payload = await asyncio.wait_for(self.reader.readexactly(n), 5)
        except (asyncio.IncompleteReadError, ConnectionError):
            return aio.EOF
        if kind == tcplink.REFUSE:
            r = json.loads(payload)
            raise TcpRefused(r["code"], r["newer"])
        assert kind == tcplink.REPLY
        return payload

    async def reply(self) -> pb.LinkReply:
        data = await self.read()
        assert data is not aio.EOF
        return pb.LinkReply.FromString(data)

    async def closed(self) -> bool:
        """The receiver closed the connection (everything it sent before is read and dropped)."""
        try:
            while await asyncio.wait_for(self.reader.read(1 << 16), 5):
                pass
        except ConnectionError:
            pass
        return True

    async def close(self) -> None:
        self.writer.close()


async def raw_link(node: Node, metadata: tuple[tuple[str, str], ...]) -> RawLink | RawTcp:
    """A hand-driven link to `node` over its carrier."""
    if node.t.carrier == "tcp":
        return await RawTcp.open(node.t.tcp_port, metadata)
    return RawLink(node.port, metadata)


def md(token: str = TOKEN, sender: str = "a", inc: str = "11", key: str = "ab" * 32) -> tuple[tuple[str, str], ...]:
    """A sender's stream metadata; `key` is its link key (the same for every stream of one process)."""
    return ((MD_TOKEN, token), (MD_SENDER, sender), (MD_INC, inc), (MD_HB_KEY, key))


def frame(first: int, msgs: list[Message], sender: str = "a", inc: int = 11) -> bytes:
    return encode_frame(first, [envelope_chunk(wire.encode(sender, inc, 22, x).SerializeToString()) for x in msgs])


@pytest.mark.parametrize(
    ("metadata", "code", "counter"),
    [
        (md(token="wrong"), grpc.StatusCode.UNAUTHENTICATED, "rejected_unauthenticated"),
        (((MD_SENDER, "a"), (MD_INC, "11")), grpc.StatusCode.UNAUTHENTICATED, "rejected_unauthenticated"),
        (md(key=""), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
        (md(key="AB" * 32), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
        (md(sender="mallory"), grpc.StatusCode.PERMISSION_DENIED, "rejected_unknown_peer"),
        (md(inc="x"), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
        (md(inc="0"), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
    ],
    ids=["wrong-token", "no-token", "no-key", "upper-case-key", "unknown-sender", "bad-inc", "zero-inc"],
)
def test_refused_calls(
    metadata: tuple[tuple[str, str], ...], code: grpc.StatusCode, counter: str, carrier: str
) -> None:
    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port()}, carrier=carrier)
        await b.serve()
        raw = await raw_link(b, metadata)
        with pytest.raises((aio.AioRpcError, TcpRefused)) as exc:
            await raw.reply()
        got = exc.value.code if isinstance(exc.value, TcpRefused) else exc.value.code().name
        assert got == code.name
        assert b.t.counters[counter] == 1
        await raw.close()
        # the server still serves a correct peer
        ok = await raw_link(b, md())
        assert (await ok.reply()).receiver == "b"
        await ok.close()
        await b.close()

    run(main())


def test_garbage_invalid_spoofed_and_duplicate_frames_are_dropped_and_the_stream_survives(carrier: str) -> None:
    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port(), "c": free_port()}, ack_interval=0.001, carrier=carrier)
        await b.serve()
        raw = await raw_link(b, md())
        hello = await raw.reply()
        assert (hello.receiver, hello.receiver_incarnation, hello.acked_seq) == ("b", 22, 0)
        c = b.t.counters
        await raw.call.write(b"\xff\xff\xff\xff garbage")
        await raw.call.write(b"\x08")  # truncated varint
        await until(lambda: c["rejected_malformed"] == 2)
        await raw.call.write(encode_frame(0, []))  # sequence numbers start at 1
        await until(lambda: c["rejected_malformed"] == 3)
        await raw.call.write(frame(1, [hb(1), hb(2)]))
        await until(lambda: len(b.got) == 2)
        bad = wire.encode("a", 11, 22, Heartbeat(3, 0.1, 0.0))
        bad.heartbeat.period = math.nan
        spoofed = wire.encode("c", 5, 22, Excluded(22))  # c's message on a's link
        await raw.call.write(
            encode_frame(3, [envelope_chunk(bad.SerializeToString()), envelope_chunk(spoofed.SerializeToString())])
        )
        await until(lambda: c["rejected_invalid"] == 2)
        await raw.call.write(frame(2, [hb(102), hb(103), hb(104), hb(105)]))  # seqs 2..5: 2-4 are duplicates
        await until(lambda: len(b.got) == 3)
        assert c["link_duplicates"] == 3
        assert b.seqs() == [1, 2, 105]
        # acks are cumulative and reach the last link sequence number seen
        last = 0
        while last < 5:
            last = (await raw.reply()).acked_seq
        assert last == 5
        await raw.close()
        await b.close()

    run(main())


def test_a_stream_of_nothing_but_duplicates_or_invalid_envelopes_is_ended_loudly(
    carrier: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A link whose numbering was taken by someone else delivers only duplicates: it used to stay silent (every
    message of the sender lost, one `reject_invalid` in the log). Past `LINK_SUSPECT_DUPLICATES` duplicates in a
    row (or `LINK_SUSPECT_INVALID` invalid envelopes) the stream ends with an error event `link_suspect`; a new
    envelope in between resets the count (the bounds are lowered here to keep the test short)."""
    from haa.hostd import transport as tmod

    monkeypatch.setattr(tmod, "LINK_SUSPECT_DUPLICATES", 30)
    monkeypatch.setattr(tmod, "LINK_SUSPECT_INVALID", 5)

    async def main() -> None:
        b = Node("b", 22, free_port(), {"a": free_port()}, carrier=carrier)
        await b.serve()
        c = b.t.counters
        raw = await raw_link(b, md())
        await raw.reply()
        await raw.call.write(frame(1, [hb(i) for i in range(1, 11)]))
        await until(lambda: len(b.got) == 10)
        await raw.call.write(frame(1, [hb(i) for i in range(1, 11)]))  # 10 duplicates
        await raw.call.write(frame(11, [hb(11)]))  # a new one: the run starts again
        await raw.call.write(frame(1, [hb(i) for i in range(1, 12)]))  # 11 duplicates
        await until(lambda: c["link_duplicates"] == 21)
        assert c["link_suspect"] == 0
        await raw.call.write(frame(1, [hb(i) for i in range(1, 12)]))  # 12 .. 22 in a row
        await raw.call.write(frame(1, [hb(i) for i in range(1, 12)]))  # 23 .. 33: past 30, ended
        await until(lambda: c["link_suspect"] == 1, what="the stream ended as suspect")
        await raw.close()
        raw = await raw_link(b, md())  # the same process reconnects and goes on
        assert (await raw.reply()).acked_seq == 11
        spoofed = envelope_chunk(wire.encode("z", 5, 22, Excluded(22)).SerializeToString())
        await raw.call.write(encode_frame(12, [spoofed] * 5))
        await until(lambda: c["link_suspect"] == 2, what="invalid envelopes end it too")
        await raw.close()
        await b.close()

    run(main())


def test_a_gap_ends_the_stream_and_the_sender_resends_from_the_last_delivered(carrier: str) -> None:
    """The receiver never skips a link sequence number: a frame that does ends the stream, and the next
    stream's handshake tells the sender where to resend from. Two streams of one sender incarnation open
    at once (a reconnect while the old stream still delivers) interleave without loss or duplicates."""

    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port()}, ack_interval=0.001, carrier=carrier)
        await b.serve()
        c = b.t.counters
        old = await raw_link(b, md())
        await old.reply()
        await old.call.write(frame(1, [hb(1), hb(2)]))
        await until(lambda: b.seqs() == [1, 2])
        new = await raw_link(b, md())
        hello = await new.reply()
        assert hello.acked_seq == 2
        await new.call.write(frame(3, [hb(3), hb(4)]))
        await until(lambda: b.seqs() == [1, 2, 3, 4])
        await old.call.write(frame(3, [hb(3), hb(4)]))  # the old stream's late copies: duplicates
        await until(lambda: c["link_duplicates"] == 2)
        await new.call.write(frame(7, [hb(7)]))  # 5 and 6 are missing
        await until(lambda: c["link_gap"] == 1)
        while (await asyncio.wait_for(new.call.read(), 5)) is not aio.EOF:
            pass  # the receiver ended the stream
        assert b.seqs() == [1, 2, 3, 4]
        again = await raw_link(b, md())
        assert (await again.reply()).acked_seq == 4  # resend from 5
        await again.call.write(frame(5, [hb(5), hb(6), hb(7)]))
        await until(lambda: b.seqs() == [1, 2, 3, 4, 5, 6, 7])
        for link in (old, new, again):
            await link.close()
        await b.close()

    run(main())


def test_restarts_and_kicks_during_traffic_never_run_two_sessions(carrier: str) -> None:
    """Regression: a link restarted (a kick, a reincarnation) while its session waited for the handshake
    could keep running next to its replacement (asyncio.wait_for in 3.11 swallows a cancellation that
    coincides with the read completing); both sessions then wrote from one queue on two streams and the
    receiver saw gaps — lost messages, stalled OAC. Restart the link hundreds of times under traffic: every
    message arrives once, in order, and the receiver never sees a gap."""

    async def main() -> None:
        a, b = await connected_pair(carrier)
        link = a.t.links["b"]
        sent = 0
        for i in range(300):
            for _ in range(5):
                sent += 1
                a.t.send("b", 22, hb(sent))
            if i % 3 == 0:
                link.restart()
            else:
                link.kick()
            await asyncio.sleep(0.001 if i % 2 else 0)  # restarts at varied points of the links' work
        await until(lambda: len(b.got) >= sent, timeout=20, what="all messages")
        await asyncio.sleep(0.05)  # a quiet period: a duplicate would arrive now
        assert b.seqs() == list(range(1, sent + 1))
        assert b.t.counters["link_gap"] == 0 and a.t.counters["link_sender_gap"] == 0
        tasks = [t for t in asyncio.all_tasks() if t.get_name() == "link-b" and not t.done()]
        assert tasks == [link.task]
        await a.close()
        await b.close()

    run(main())


def test_heartbeats_travel_as_authenticated_datagrams_once_a_stream_is_accepted(carrier: str) -> None:
    """Heartbeats go as UDP datagrams to the port the receiver announced in the handshake (docs/transport.md,
    "Heartbeats as datagrams"); forged, malformed, unknown-incarnation and non-heartbeat datagrams are counted
    and dropped; a receiver without a heartbeat socket gets them on the stream."""

    async def main() -> None:
        pa, pb_, pc = free_port(), free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_, "c": pc}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        c = Node("c", 33, pc, {"a": pa}, carrier=carrier, datagram_heartbeats=False)
        for n in (a, b, c):
            await n.serve()
            await n.t.open_heartbeats("127.0.0.1", n.port)
        assert (a.t.heartbeat_port, b.t.heartbeat_port, c.t.heartbeat_port) == (pa, pb_, 0)
        a.t.start()
        await until(lambda: a.t.connected("b") and a.t.connected("c"), what="links up")
        await until(lambda: a.t.links["b"].hb_addr is not None, what="datagram address resolved")
        assert a.t.links["c"].hb_addr is None  # c announced no port
        for i in range(1, 21):
            a.t.send("b", 22, hb(i))
            a.t.send("c", 33, hb(i))
        await until(lambda: len(b.seqs()) == 20 and len(c.seqs()) == 20, what="heartbeats")
        assert a.t.counters["tx_datagrams"] == 20 and b.t.counters["rx_datagrams"] == 20
        assert b.t.counters["rx_frames"] == 0  # none came on b's stream
        assert c.t.counters["rx_frames"] >= 1 and c.t.counters["rx_datagrams"] == 0
        # hostile datagrams
        env = wire.encode("a", 11, 22, hb(99)).SerializeToString()
        body = b"HAAhb1" + env
        import hashlib
        import hmac as hm

        key = a.t.link_key("b")  # a's link key to b, which a's stream gave b

        def mac(key: bytes, data: bytes) -> bytes:
            return hm.new(key, data, hashlib.sha256).digest()[:16]

        good = body + mac(key, body)
        b.t.on_datagram(body + mac(hashlib.sha256(TOKEN.encode()).digest(), body))  # e.g. a key from the token
        b.t.on_datagram(body + mac(a.t.link_key("c"), body))  # a's key to another host
        b.t.on_datagram(good[:-1] + bytes([good[-1] ^ 1]))
        assert b.t.counters["hb_rejected_unauthenticated"] == 3
        b.t.on_datagram(b"garbage" * 10)
        b.t.on_datagram(b"HAAhb1" + b"\xff" * 40)  # no envelope (decoded first: the key is the sender's)
        b.t.on_datagram(good + b"x" * 600)  # too large
        assert b.t.counters["hb_rejected_malformed"] == 3 and b.t.counters["hb_rejected_unauthenticated"] == 3
        other = wire.encode("a", 10, 22, hb(100)).SerializeToString()  # an older incarnation of a
        b.t.on_datagram(b"HAAhb1" + other + mac(key, b"HAAhb1" + other))
        stranger = wire.encode("z", 5, 22, hb(1)).SerializeToString()  # never opened a stream: no key
        b.t.on_datagram(b"HAAhb1" + stranger + mac(key, b"HAAhb1" + stranger))
        assert b.t.counters["hb_rejected_stale"] == 1 and b.t.counters["hb_rejected_unknown"] == 1
        notbeat = wire.encode("a", 11, 22, Excluded(22)).SerializeToString()
        b.t.on_datagram(b"HAAhb1" + notbeat + mac(key, b"HAAhb1" + notbeat))
        assert b.t.counters["hb_rejected_malformed"] == 4
        n = len(b.seqs())
        b.t.on_datagram(good)  # a valid one is delivered (the failure detector ignores replays, Alg. 1 l. 20)
        assert len(b.seqs()) == n + 1
        for x in (a, b, c):
            await x.close()

    run(main())


def test_a_newer_incarnation_ends_the_streams_of_the_older_one(carrier: str) -> None:
    """A superseded process that only sends heartbeats (datagrams) still learns of it: when the newer
    incarnation's stream is accepted, the older one's stream ends, and its reconnection is refused as stale."""

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        old = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        superseded: list[tuple[str, int]] = []
        old.t.on_superseded = lambda p, i: superseded.append((p, i))
        old.t.start()
        await until(lambda: old.t.connected("b"), what="old a connected")
        old.t.send("b", 22, hb(1))
        await until(lambda: len(b.seqs()) == 1, what="a message of the old incarnation")
        new = Node("a", 12, pa, {"b": pb_}, carrier=carrier)
        new.t.start()
        await until(lambda: new.t.connected("b"), timeout=10, what="new a accepted")
        new.t.send("b", 22, hb(1))  # more than a claim: it speaks (docs/transport.md, incarnation claims)
        await until(lambda: len(b.seqs()) == 2, what="a message of the new incarnation")
        await until(lambda: b.t.counters["link_superseded_streams"] >= 1, what="old stream ended")
        await until(lambda: len(superseded) >= 1, timeout=10, what="old a told")
        assert superseded[0] == ("b", 12)
        for x in (old, new, b):
            await x.close()

    run(main())


# ------------------------------------------------------------------------------------- the TCP carrier only


def test_tcp_hostile_bytes_cost_one_counter_and_the_connection() -> None:
    """Bytes that are not a hello, a length above the limit (before the handshake: `MAX_HELLO`; after it:
    `MAX_FRAME`), a peer that stops mid-frame or never says hello, a second hello, a malformed hello: each is
    counted and its connection closed, no more than one unfinished frame is ever buffered, and the receiver
    keeps serving a correct peer (haa.hostd.tcplink, "Hostile or broken input")."""

    async def main() -> None:
        b = Node("b", 22, free_port(), {"a": free_port()}, carrier="tcp", stall_timeout=0.3)
        await b.serve()
        c = b.t.counters
        port = b.t.tcp_port
        hdr = tcplink.HEADER.pack
        cases: list[tuple[str, Callable[[], Awaitable[RawTcp]], str]] = [
            ("an HTTP request", lambda: RawTcp.open(port, None, b"GET / HTTP/1.1\r\nHost: b\r\n\r\n"),
             "rejected_malformed"),
            ("a huge hello", lambda: RawTcp.open(port, None, hdr(tcplink.HELLO, tcplink.MAX_HELLO + 1)),
             "rejected_malformed"),
            ("a hello of another protocol", lambda: RawTcp.open(port, None, hdr(tcplink.HELLO, 4) + b"{}\n\n"),
             "rejected_malformed"),
            ("a frame before the hello", lambda: RawTcp.open(port, None, hdr(tcplink.FRAME, 2) + b"\x08\x01"),
             "rejected_malformed"),
            ("a hello that is not JSON of strings",
             lambda: RawTcp.open(port, None, hdr(tcplink.HELLO, 13) + tcplink.HELLO_MAGIC + b"[1]\n"),
             "rejected_malformed"),
            ("nothing at all", lambda: RawTcp.open(port, None), "rejected_stalled"),
            ("half a hello", lambda: RawTcp.open(port, None, hdr(tcplink.HELLO, 100) + b"HAA"), "rejected_stalled"),
        ]
        for what, opener, counter in cases:
            before = c[counter]
            raw = await opener()
            t0 = time.monotonic()
            assert await raw.closed(), what
            assert c[counter] == before + 1, what
            assert time.monotonic() - t0 < 3.0, what
            await raw.close()
        # after the handshake
        for what, data, counter in [
            ("an oversized length", hdr(tcplink.FRAME, tcplink.MAX_FRAME + 1), "rejected_malformed"),
            ("a second hello", hdr(tcplink.HELLO, 2) + b"{}", "rejected_malformed"),
            ("a reply from the sender", hdr(tcplink.REPLY, 0), "rejected_malformed"),
            ("half a frame, then silence (slowloris)", hdr(tcplink.FRAME, 1000) + b"\x08\x01" + b"\x00" * 100,
             "rejected_stalled"),
        ]:
            before = c[counter]
            raw = await RawTcp.open(port, md())
            await raw.reply()
            raw.writer.write(data)
            await until(lambda: len(b.t._handlers) == 1, what="the link registered")
            conn = next(iter(b.t._handlers))
            assert await raw.closed(), what
            assert c[counter] == before + 1, what
            assert len(conn._buf) <= 1000 + 5  # type: ignore[attr-defined]
            await until(lambda: not b.t._handlers, what="the link unregistered")
            await raw.close()
        # a frame that is not a Frame is dropped as on a gRPC stream: the link stays
        raw = await RawTcp.open(port, md())
        await raw.reply()
        await raw.write(b"\xff\xff garbage")
        await raw.write(frame(1, [hb(1)]))
        await until(lambda: b.seqs() == [1], what="the next frame delivered")
        assert c["rejected_malformed"] == 9
        await raw.close()
        assert c["rejected_stalled"] == 3
        await b.close()

    run(main())


def test_the_tcp_frame_limit_is_the_grpc_message_limit() -> None:
    """A frame either carrier carries, the other carries too (a joiner's whole state is one message)."""
    from haa.hostd.transport import MAX_MESSAGE

    assert tcplink.MAX_FRAME == MAX_MESSAGE


def test_a_frame_split_into_single_bytes_and_frames_in_one_segment_arrive_whole() -> None:
    """The receiver's framing: a frame written byte by byte and many frames in one write are parsed alike."""

    async def main() -> None:
        b = Node("b", 22, free_port(), {"a": free_port()}, carrier="tcp")
        await b.serve()
        raw = await RawTcp.open(b.t.tcp_port, md())
        await raw.reply()
        data = tcplink.HEADER.pack(tcplink.FRAME, len(frame(1, [hb(1), hb(2)]))) + frame(1, [hb(1), hb(2)])
        for i in range(len(data)):
            raw.writer.write(data[i:i + 1])
            await raw.writer.drain()
            await asyncio.sleep(0)
        await until(lambda: b.seqs() == [1, 2], what="the frame written byte by byte")
        many = b"".join(tcplink.HEADER.pack(tcplink.FRAME, len(f)) + f
                        for f in (frame(i, [hb(i)]) for i in range(3, 503)))
        raw.writer.write(many)
        await until(lambda: len(b.seqs()) == 502, what="500 frames in one write")
        assert b.seqs() == list(range(1, 503)) and b.t.counters["rejected_malformed"] == 0
        await raw.close()
        await b.close()

    run(main())


def test_hosts_with_different_carriers_refuse_each_other_loudly() -> None:
    """Every host of a cluster must use the same carrier: a TCP sender whose peer runs gRPC links counts
    `link_wrong_carrier` (logged at ERROR); a gRPC sender to a TCP host is refused (FAILED_PRECONDITION, counted
    `rejected_wrong_carrier` there, `link_refused` here). Nothing is delivered either way."""

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier="tcp")
        b = Node("b", 22, pb_, {"a": pa}, carrier="grpc")
        await a.serve()
        await b.serve()
        a.t.start()
        b.t.start()
        a.t.send("b", 0, hb(1))
        b.t.send("a", 0, hb(1))
        await until(lambda: a.t.counters["link_wrong_carrier"] >= 1, what="a finds b on gRPC")
        await until(lambda: b.t.counters["link_refused"] >= 1, what="b refused by a")
        assert a.t.counters["rejected_wrong_carrier"] >= 1
        assert not a.t.connected("b") and not b.t.connected("a") and not a.got and not b.got
        await a.close()
        await b.close()

    run(main())


def test_tcp_links_over_mutual_tls(tmp_path: Path) -> None:
    """Mutual TLS on the TCP carrier: links between hosts with certificates of the cluster's CA carry messages
    (heartbeats as datagrams under each link's own key); a client without a certificate never gets a hello in,
    one with another host's certificate speaking as `a` is refused (`rejected_name_mismatch`), and a link to
    an address where another host answers fails the server-name check."""
    from haa import tls as tlsmod
    from haa.cluster.tls import make_cluster_tls

    make_cluster_tls(tmp_path / "tls", ["a", "b", "c"])

    def material(n: str) -> tlsmod.HostTls:
        return tlsmod.load_host(tmp_path / "tls" / "hosts" / n, n)

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier="tcp", tls=material("a"))
        b = Node("b", 22, pb_, {"a": pa}, carrier="tcp", tls=material("b"))
        for n in (a, b):
            server = aio.server(options=Transport.server_options())
            n.t.add_to_server(server)
            assert n.t.tls is not None
            server.add_secure_port(f"127.0.0.1:{n.port}", n.t.tls.server_credentials())
            await server.start()
            n.server = server
            await n.t.open_tcp("127.0.0.1", 0)
            await n.t.open_heartbeats("127.0.0.1", n.port)
        a.t.start()
        b.t.start()
        await until(lambda: a.t.connected("b") and b.t.connected("a"), what="TLS links up")
        for i in range(1, 6):
            a.t.send("b", 22, hb(i))
            a.t.send("b", 22, Excluded(22))
        await until(lambda: len(b.got) == 10, what="messages over TLS")
        assert b.seqs() == [1, 2, 3, 4, 5] and b.t.counters["rx_datagrams"] == 5
        # no client certificate: the TLS handshake fails, nothing reaches the link
        ctx = ssl.create_default_context(cadata=material("a").ca.decode())
        ctx.check_hostname = False
        accepts = b.t.counters["link_accepts"]
        with contextlib.suppress(ssl.SSLError, ConnectionError, asyncio.IncompleteReadError, TimeoutError):
            r, w = await asyncio.open_connection("127.0.0.1", b.t.tcp_port, ssl=ctx, server_hostname="b")
            w.write(tcplink.HEADER.pack(tcplink.HELLO, 2) + b"{}")
            await asyncio.wait_for(r.read(), 5)
        # c's certificate, speaking as a
        cctx = tcplink.client_context(material("c"))
        r, w = await asyncio.open_connection("127.0.0.1", b.t.tcp_port, ssl=cctx, server_hostname="b")
        raw = RawTcp(r, w)
        raw.send(tcplink.HELLO, tcplink.HELLO_MAGIC + json.dumps(
            dict(md(sender="a")) | {"x-haa-hb-key": "0" * 64}).encode())
        with pytest.raises(TcpRefused) as exc:
            await raw.reply()
        assert exc.value.code == "PERMISSION_DENIED"
        assert b.t.counters["rejected_name_mismatch"] == 1 and b.t.counters["link_accepts"] == accepts
        await raw.close()
        # a's link to "c" at b's address: b's certificate is not c's
        with pytest.raises(ssl.SSLCertVerificationError):
            await asyncio.open_connection("127.0.0.1", b.t.tcp_port, ssl=tcplink.client_context(material("a")),
                                          server_hostname="c")
        await a.close()
        await b.close()

    run(main())
