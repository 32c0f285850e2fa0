"""Benchmark: one bidirectional gRPC stream per link vs unary calls, for the host-to-host transport.

The gRPC Python performance guide warns that streaming RPCs can be slower than unary ones in Python. Before
building `haa.hostd.transport` on a bidirectional stream (`HostLink.Open`), this benchmark measures, between
two processes on loopback (grpc.aio on both sides, raw-bytes handlers, the real `haa.v1.Frame` framing):

  (a) one-way latency of small messages sent one at a time (2 ms apart, so none waits behind another), and
  (b) throughput for bursts of 1,000 small messages queued at once,

for these ways of carrying a FIFO link:

  stream-batched     one bidi stream; a writer task packs everything queued into one Frame per write
  stream-per-msg     one bidi stream; one Frame (one envelope) per write
  unary-seq          one unary call per message, each awaited before the next (FIFO by construction)
  unary-pipelined    one unary call per message, up to 64 in flight, receiver re-orders by sequence number
  unary-batched      unary calls carrying everything queued (one call in flight at a time)
  transport          the real `haa.hostd.transport.Transport` (batched stream + acks + resend buffer)

One-way latency uses CLOCK_MONOTONIC, which is the same clock in both processes on Linux: the sender stamps
`Heartbeat.sent_at`, the receiver subtracts it from its arrival time. Burst throughput is measured from the
first enqueue to the arrival of the last message at the receiver.

Prints a table and writes `bench-results/transport.json`. Run:
`.venv/bin/python -m haa.lab.bench.transport_stream_vs_unary` (`--quick` for a short run). It never fails on a timing.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import grpc
from grpc import aio

from haa.core import wire
from haa.core.messages import Heartbeat
from haa.hostd.transport import Transport, encode_frame, envelope_chunk
from haa.pb import hostlink_pb2 as pb

ROOT = Path(__file__).resolve().parents[3]
STREAM = "/bench.Link/Stream"
UNARY = "/bench.Link/Unary"
STATS = "/bench.Link/Stats"
WINDOW = 64
GAP = 0.002  # seconds between messages in the latency phase
TOKEN = "bench-token"


def _msg(seq: int) -> bytes:
    """One small envelope (a heartbeat stamped with the send time), as a Frame chunk."""
    env = wire.encode("sender", 1, 1, Heartbeat(seq, 0.1, time.monotonic()))
    return envelope_chunk(env.SerializeToString())


def _pct(xs: list[float], q: float) -> float:
    if not xs:
        return float("nan")
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


# ------------------------------------------------------------------------------------------ receiver


class Receiver:
    """Receiver side: records one-way latency of every envelope, acks, re-orders pipelined unary calls."""

    def __init__(self) -> None:
        self.lat: list[float] = []
        self.last = 0  # highest in-order seq delivered
        self.held: dict[int, list[pb.Envelope]] = {}  # out-of-order unary frames, by first_seq

    def _deliver(self, frame: pb.Frame) -> None:
        now = time.monotonic()
        lat = self.lat
        for env in frame.envelopes:
            lat.append(now - env.heartbeat.sent_at)
        self.last = frame.first_seq + len(frame.envelopes) - 1

    def _accept(self, frame: pb.Frame) -> None:
        if frame.first_seq == 1:  # a new run
            self.last = 0
            self.held.clear()
        if frame.first_seq != self.last + 1:
            self.held[frame.first_seq] = frame
            return
        self._deliver(frame)
        while self.last + 1 in self.held:
            self._deliver(self.held.pop(self.last + 1))  # type: ignore[arg-type]

    async def stream(self, request_iterator: object, context: aio.ServicerContext) -> None:
        while True:
            data = await context.read()
            if data is aio.EOF:
                return
            self._accept(pb.Frame.FromString(data))
            await context.write(pb.LinkReply(acked_seq=self.last).SerializeToString())

    async def unary(self, data: bytes, context: aio.ServicerContext) -> bytes:
        self._accept(pb.Frame.FromString(data))
        return pb.LinkReply(acked_seq=self.last).SerializeToString()

    async def stats(self, data: bytes, context: aio.ServicerContext) -> bytes:
        out = json.dumps(self.lat).encode()
        self.lat = []
        return out


async def serve(port: int, transport_port: int) -> None:
    rec = Receiver()
    server = aio.server(options=[("grpc.max_receive_message_length", 64 << 20)])
    handler = grpc.method_handlers_generic_handler(
        "bench.Link",
        {
            "Stream": grpc.stream_stream_rpc_method_handler(rec.stream),
            "Unary": grpc.unary_unary_rpc_method_handler(rec.unary),
            "Stats": grpc.unary_unary_rpc_method_handler(rec.stats),
        },
    )
    server.add_generic_rpc_handlers((handler,))
    server.add_insecure_port(f"127.0.0.1:{port}")
    # the real transport, receiving side: records latency in the same list
    tlat: list[float] = []

    def on_envelopes(src: str, src_inc: int, items: list) -> None:
        now = time.monotonic()
        for _dst_inc, msg in items:
            tlat.append(now - msg.sent_at)

    receiver = Transport("receiver", TOKEN, {"sender": "127.0.0.1:1"}, on_envelopes=on_envelopes)
    receiver.incarnation = 1
    tserver = aio.server(options=receiver.server_options())
    receiver.add_to_server(tserver)
    tserver.add_insecure_port(f"127.0.0.1:{transport_port}")

    async def tstats(data: bytes, context: aio.ServicerContext) -> bytes:
        out = json.dumps(tlat).encode()
        tlat.clear()
        return out

    server.add_generic_rpc_handlers(
        (grpc.method_handlers_generic_handler("bench.T", {"Stats": grpc.unary_unary_rpc_method_handler(tstats)}),)
    )
    await server.start()
    await tserver.start()
    await server.wait_for_termination()


# ------------------------------------------------------------------------------------------ sender


class StreamSender:
    def __init__(self, channel: aio.Channel, batched: bool) -> None:
        self.call = channel.stream_stream(STREAM)()
        self.batched = batched
        self.queue: collections.deque[bytes] = collections.deque()
        self.next_seq = 1
        self.wake = asyncio.Event()
        self.acked = 0
        self.ack_event = asyncio.Event()
        self.tasks = [asyncio.create_task(self._writer()), asyncio.create_task(self._reader())]

    def send(self, chunk: bytes) -> None:
        self.queue.append(chunk)
        self.wake.set()

    async def _writer(self) -> None:
        q = self.queue
        while True:
            if not q:
                self.wake.clear()
                await self.wake.wait()
            if self.batched:
                chunks = list(q)
                q.clear()
            else:
                chunks = [q.popleft()]
            await self.call.write(encode_frame(self.next_seq, chunks))
            self.next_seq += len(chunks)

    async def _reader(self) -> None:
        while True:
            data = await self.call.read()
            if data is aio.EOF:
                return
            self.acked = pb.LinkReply.FromString(data).acked_seq
            self.ack_event.set()

    async def wait_acked(self, seq: int) -> None:
        while self.acked < seq:
            self.ack_event.clear()
            await self.ack_event.wait()

    async def close(self) -> None:
        for t in self.tasks:
            t.cancel()
        self.call.cancel()


class UnarySender:
    def __init__(self, channel: aio.Channel, mode: str) -> None:
        self.call = channel.unary_unary(UNARY)
        self.mode = mode  # "seq", "pipelined", "batched"
        self.queue: collections.deque[tuple[int, bytes]] = collections.deque()
        self.next_seq = 1
        self.acked = 0
        self.ack_event = asyncio.Event()
        self.wake = asyncio.Event()
        self.sem = asyncio.Semaphore(WINDOW)
        self.inflight: set[asyncio.Task[None]] = set()
        self.task = asyncio.create_task(self._writer())

    def send(self, chunk: bytes) -> None:
        self.queue.append((self.next_seq, chunk))
        self.next_seq += 1
        self.wake.set()

    def _ack(self, data: bytes) -> None:
        a = pb.LinkReply.FromString(data).acked_seq
        if a > self.acked:
            self.acked = a
            self.ack_event.set()

    async def _one(self, seq: int, chunks: list[bytes]) -> None:
        try:
            self._ack(await self.call(encode_frame(seq, chunks)))
        finally:
            self.sem.release()

    async def _writer(self) -> None:
        q = self.queue
        while True:
            if not q:
                self.wake.clear()
                await self.wake.wait()
            if self.mode == "seq":
                seq, chunk = q.popleft()
                self._ack(await self.call(encode_frame(seq, [chunk])))
            elif self.mode == "batched":
                seq = q[0][0]
                chunks = [c for _s, c in q]
                q.clear()
                self._ack(await self.call(encode_frame(seq, chunks)))
            else:
                await self.sem.acquire()
                seq, chunk = q.popleft()
                t = asyncio.create_task(self._one(seq, [chunk]))
                self.inflight.add(t)
                t.add_done_callback(self.inflight.discard)

    async def wait_acked(self, seq: int) -> None:
        while self.acked < seq:
            self.ack_event.clear()
            await self.ack_event.wait()

    async def close(self) -> None:
        self.task.cancel()
        for t in list(self.inflight):
            t.cancel()


class TransportSender:
    """The real transport: acks are cumulative and delayed, so completion is polled from its link state."""

    def __init__(self, port: int) -> None:
        self.t = Transport("sender", TOKEN, {"receiver": f"127.0.0.1:{port}"}, on_envelopes=lambda *a: None)
        self.t.incarnation = 1
        self.t.start()
        self.seq = 0

    def send_msg(self, seq: int) -> None:
        self.t.send("receiver", 1, Heartbeat(seq, 0.1, time.monotonic()))
        self.seq += 1

    async def wait_acked(self, seq: int) -> None:
        link = self.t.links["receiver"]
        while link.acked < seq:
            await asyncio.sleep(0.0002)

    async def close(self) -> None:
        await self.t.stop()


async def _stats(channel: aio.Channel, method: str = STATS) -> list[float]:
    return json.loads(await channel.unary_unary(method)(b""))


async def run_variant(
    channel: aio.Channel, name: str, n_lat: int, bursts: int, burst: int, tport: int
) -> dict[str, object]:
    if name.startswith("stream"):
        s: StreamSender | UnarySender | TransportSender = StreamSender(channel, batched=name == "stream-batched")
    elif name == "transport":
        s = TransportSender(tport)
    else:
        s = UnarySender(channel, name.split("-")[1])
    stats_method = "/bench.T/Stats" if name == "transport" else STATS

    def send(seq: int) -> None:
        if isinstance(s, TransportSender):
            s.send_msg(seq)
        else:
            s.send(_msg(seq))

    seq = 0
    # warm-up (connection set-up, first-call costs)
    for _ in range(50):
        seq += 1
        send(seq)
        await s.wait_acked(seq)
    await asyncio.sleep(0.05)
    await _stats(channel, stats_method)
    # (a) latency, one message at a time: paced GAP apart, so every message finds both processes idle
    # (like heartbeats and OAC steps), and no message waits behind another
    for _ in range(n_lat):
        seq += 1
        send(seq)
        await asyncio.sleep(GAP)
    await s.wait_acked(seq)
    await asyncio.sleep(0.05)
    one_way = await _stats(channel, stats_method)
    # (b) bursts
    rates = []
    for _ in range(bursts):
        t0 = time.monotonic()
        for _ in range(burst):
            seq += 1
            send(seq)
        await s.wait_acked(seq)
        rates.append(burst / (time.monotonic() - t0))
        await asyncio.sleep(0.02)
    await asyncio.sleep(0.05)
    burst_lat = await _stats(channel, stats_method)
    await s.close()
    ms = 1e3
    return {
        "variant": name,
        "one_way_p50_ms": _pct(one_way, 0.5) * ms,
        "one_way_p99_ms": _pct(one_way, 0.99) * ms,
        "burst_msgs_per_s_median": statistics.median(rates),
        "burst_msgs_per_s_min": min(rates),
        "burst_one_way_p50_ms": _pct(burst_lat, 0.5) * ms,
        "burst_one_way_p99_ms": _pct(burst_lat, 0.99) * ms,
        "latency_samples": len(one_way),
        "bursts": bursts,
    }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def client(port: int, tport: int, variants: list[str], n_lat: int, bursts: int, burst: int) -> list[dict]:
    results = []
    for name in variants:
        channel = aio.insecure_channel(f"127.0.0.1:{port}")
        await asyncio.wait_for(channel.channel_ready(), 10)
        results.append(await run_variant(channel, name, n_lat, bursts, burst, tport))
        await channel.close()
        r = results[-1]
        print(
            f"{name:16s} one-way p50 {r['one_way_p50_ms']:7.3f} ms  p99 {r['one_way_p99_ms']:7.3f} ms  "
            f"burst {r['burst_msgs_per_s_median']:9.0f} msg/s",
            file=sys.stderr,
        )
    return results


VARIANTS = ["stream-batched", "stream-per-msg", "unary-seq", "unary-pipelined", "unary-batched", "transport"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serve", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--tport", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="short run")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default=str(ROOT / "bench-results" / "transport.json"))
    args = ap.parse_args()
    if args.serve:
        asyncio.run(serve(args.serve, args.tport))
        return
    n_lat, bursts = (300, 5) if args.quick else (2000, 20)
    port, tport = _free_port(), _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "haa.lab.bench.transport_stream_vs_unary", "--serve", str(port),
                             "--tport", str(tport)])
    try:
        time.sleep(0.5)
        results = asyncio.run(client(port, tport, args.variants.split(","), n_lat, bursts, 1000))
    finally:
        proc.terminate()
        proc.wait(5)
    cols = [
        ("variant", "{:16s}"),
        ("one_way_p50_ms", "{:9.3f}"),
        ("one_way_p99_ms", "{:9.3f}"),
        ("burst_msgs_per_s_median", "{:12.0f}"),
        ("burst_one_way_p50_ms", "{:9.2f}"),
        ("burst_one_way_p99_ms", "{:9.2f}"),
    ]
    heads = ["variant", "1way p50", "1way p99", "burst msg/s", "b p50 ms", "b p99 ms"]
    widths = [16, 9, 9, 12, 9, 9]
    print("  ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(zip(heads, widths, strict=True))))
    for r in results:
        print("  ".join(fmt.format(r[k]) for k, fmt in cols))
    out = {
        "benchmark": "transport_stream_vs_unary",
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "grpc": grpc.__version__},
        "latency_samples": n_lat,
        "latency_gap_s": GAP,
        "burst_size": 1000,
        "bursts": bursts,
        "results": results,
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        main()
