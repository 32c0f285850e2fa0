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
import math
import time
from collections.abc import Awaitable, Callable
from typing import Any

import grpc
import pytest
from grpc import aio
from waits import until

from haa.hostd import wire
from haa.hostd.messages import Excluded, Heartbeat, Message
from haa.hostd.transport import MD_INC, MD_SENDER, MD_TOKEN, OPEN_METHOD, Transport, encode_frame, envelope_chunk
from haa.pb import hostlink_pb2 as pb
from haactl.local import free_port

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


def run(coro_fn: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(coro_fn(), 30))


def hb(i: int) -> Heartbeat:
    return Heartbeat(i, 0.1, float(i))


# ------------------------------------------------------------------------------------------------ (f)


def test_fifo_and_no_loss_across_receiver_server_restarts(carrier: str) -> None:
    """The receiver's gRPC server is closed and reopened twice while the sender keeps queueing messages:
    every message arrives exactly once and in order."""

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        a.t.start()
        await until(lambda: a.t.connected("b"), what="first connection")
        sent = 0
        stop = asyncio.Event()
        queued_while_down: list[int] = []

        async def produce() -> None:
            nonlocal sent
            while not stop.is_set():
                sent += 1
                a.t.send("b", 22, hb(sent))
                if sent % 20 == 0:
                    await asyncio.sleep(0.001)

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
        await asyncio.sleep(0.05)
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

    run(main)


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

    run(main)


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

    run(main)


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

    run(main)


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
        await asyncio.sleep(0.05)
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

        task = asyncio.create_task(chatter())
        await asyncio.sleep(0.1)
        t2 = time.monotonic()
        a.t.send("b", 22, hb(5), lazy=True)
        await until(lambda: len(b.got) == 5, timeout=2.0, what="the lazy message on a busy host")
        assert 0.5 <= time.monotonic() - t2 < 1.0
        stop.set()
        await task
        await a.close()
        await b.close()

    run(main)


def test_before_first_contact_only_recent_unaddressed_messages_are_kept(carrier: str) -> None:
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier, precontact_limit=16)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        a.t.start()
        for i in range(1, 101):
            a.t.send("b", 0, hb(i))  # heartbeats to a peer that has not started yet
        await asyncio.sleep(0.05)
        await b.serve()
        await until(lambda: len(b.got) == 16)
        await asyncio.sleep(0.05)
        assert b.seqs() == list(range(85, 101))
        assert a.t.counters["dropped_precontact"] == 84
        await a.close()
        await b.close()

    run(main)


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


def md(token: str = TOKEN, sender: str = "a", inc: str = "11") -> tuple[tuple[str, str], ...]:
    return ((MD_TOKEN, token), (MD_SENDER, sender), (MD_INC, inc))


def frame(first: int, msgs: list[Message], sender: str = "a", inc: int = 11) -> bytes:
    return encode_frame(first, [envelope_chunk(wire.encode(sender, inc, 22, x).SerializeToString()) for x in msgs])


@pytest.mark.parametrize(
    ("metadata", "code", "counter"),
    [
        (md(token="wrong"), grpc.StatusCode.UNAUTHENTICATED, "rejected_unauthenticated"),
        (((MD_SENDER, "a"), (MD_INC, "11")), grpc.StatusCode.UNAUTHENTICATED, "rejected_unauthenticated"),
        (md(sender="mallory"), grpc.StatusCode.PERMISSION_DENIED, "rejected_unknown_peer"),
        (md(inc="x"), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
        (md(inc="0"), grpc.StatusCode.INVALID_ARGUMENT, "rejected_bad_metadata"),
    ],
    ids=["wrong-token", "no-token", "unknown-sender", "bad-inc", "zero-inc"],
)
def test_refused_calls(metadata: tuple[tuple[str, str], ...], code: grpc.StatusCode, counter: str) -> None:
    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port()})
        await b.serve()
        raw = RawLink(pb_, metadata)
        with pytest.raises(aio.AioRpcError) as exc:
            await raw.reply()
        assert exc.value.code() == code
        assert b.t.counters[counter] == 1
        await raw.close()
        # the server still serves a correct peer
        ok = RawLink(pb_, md())
        assert (await ok.reply()).receiver == "b"
        await ok.close()
        await b.close()

    run(main)


def test_garbage_invalid_spoofed_and_duplicate_frames_are_dropped_and_the_stream_survives() -> None:
    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port(), "c": free_port()}, ack_interval=0.001)
        await b.serve()
        raw = RawLink(pb_, md())
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

    run(main)


def test_a_gap_ends_the_stream_and_the_sender_resends_from_the_last_delivered() -> None:
    """The receiver never skips a link sequence number: a frame that does ends the stream, and the next
    stream's handshake tells the sender where to resend from. Two streams of one sender incarnation open
    at once (a reconnect while the old stream still delivers) interleave without loss or duplicates."""

    async def main() -> None:
        pb_ = free_port()
        b = Node("b", 22, pb_, {"a": free_port()}, ack_interval=0.001)
        await b.serve()
        c = b.t.counters
        old = RawLink(pb_, md())
        await old.reply()
        await old.call.write(frame(1, [hb(1), hb(2)]))
        await until(lambda: b.seqs() == [1, 2])
        new = RawLink(pb_, md())
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
        again = RawLink(pb_, md())
        assert (await again.reply()).acked_seq == 4  # resend from 5
        await again.call.write(frame(5, [hb(5), hb(6), hb(7)]))
        await until(lambda: b.seqs() == [1, 2, 3, 4, 5, 6, 7])
        for link in (old, new, again):
            await link.close()
        await b.close()

    run(main)


def test_restarts_and_kicks_during_traffic_never_run_two_sessions(carrier: str) -> None:
    """Regression: a link restarted (a kick, a reincarnation) while its session waited for the handshake
    could keep running next to its replacement (asyncio.wait_for in 3.11 swallows a cancellation that
    coincides with the read completing); both sessions then wrote from one queue on two streams and the
    receiver saw gaps — lost messages, stalled OAC. Restart the link hundreds of times under traffic: every
    message arrives once, in order, and the receiver never sees a gap."""

    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        a = Node("a", 11, pa, {"b": pb_}, carrier=carrier)
        b = Node("b", 22, pb_, {"a": pa}, carrier=carrier)
        await b.serve()
        a.t.start()
        await until(lambda: a.t.connected("b"), what="first connection")
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
            await asyncio.sleep(0.001 if i % 2 else 0)
        await until(lambda: len(b.got) >= sent, timeout=20, what="all messages")
        await asyncio.sleep(0.05)
        assert b.seqs() == list(range(1, sent + 1))
        assert b.t.counters["link_gap"] == 0 and a.t.counters["link_sender_gap"] == 0
        tasks = [t for t in asyncio.all_tasks() if t.get_name() == "link-b" and not t.done()]
        assert tasks == [link.task]
        await a.close()
        await b.close()

    run(main)


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

        from haa.hostd.transport import heartbeat_key

        def mac(key: bytes, data: bytes) -> bytes:
            return hm.new(key, data, hashlib.sha256).digest()[:16]

        good = body + mac(heartbeat_key(TOKEN), body)
        b.t.on_datagram(body + mac(heartbeat_key("wrong token"), body))
        b.t.on_datagram(good[:-1] + bytes([good[-1] ^ 1]))
        assert b.t.counters["hb_rejected_unauthenticated"] == 2
        b.t.on_datagram(b"garbage" * 10)
        b.t.on_datagram(b"HAAhb1" + b"\xff" * 40)  # the MAC is checked before anything is decoded
        b.t.on_datagram(good + b"x" * 600)  # too large
        assert b.t.counters["hb_rejected_malformed"] == 2 and b.t.counters["hb_rejected_unauthenticated"] == 3
        junk = b"HAAhb1" + b"\xff" * 40
        b.t.on_datagram(junk + mac(heartbeat_key(TOKEN), junk))  # authentic, but no envelope
        assert b.t.counters["hb_rejected_malformed"] == 3
        other = wire.encode("a", 10, 22, hb(100)).SerializeToString()  # an older incarnation of a
        b.t.on_datagram(b"HAAhb1" + other + mac(heartbeat_key(TOKEN), b"HAAhb1" + other))
        stranger = wire.encode("z", 5, 22, hb(1)).SerializeToString()  # never opened a stream
        b.t.on_datagram(b"HAAhb1" + stranger + mac(heartbeat_key(TOKEN), b"HAAhb1" + stranger))
        assert b.t.counters["hb_rejected_stale"] == 1 and b.t.counters["hb_rejected_unknown"] == 1
        notbeat = wire.encode("a", 11, 22, Excluded(22)).SerializeToString()
        b.t.on_datagram(b"HAAhb1" + notbeat + mac(heartbeat_key(TOKEN), b"HAAhb1" + notbeat))
        assert b.t.counters["hb_rejected_malformed"] == 4
        n = len(b.seqs())
        b.t.on_datagram(good)  # a valid one is delivered (the failure detector ignores replays, Alg. 1 l. 20)
        assert len(b.seqs()) == n + 1
        for x in (a, b, c):
            await x.close()

    run(main)


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

    run(main)
