"""What one message costs on a gRPC stream and on a plain TCP stream (issue 14: the floor of the OAC latency).

One process (uvloop), loopback, both ends in it: the sender writes N 40-byte messages one at a time (each
`await call.write` on a grpc.aio bidi stream / each `write` + `drain` on an asyncio TCP stream, length-
prefixed), the receiver reads them one by one. Printed: messages per second and process CPU per message
(sender + receiver together, every thread of the process). Run:
`.venv/bin/python -m haa.lab.bench.transport_grpc_vs_tcp`
(docs/transport.md, "Where the floor is").
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections.abc import AsyncIterator

import grpc
import uvloop
from grpc import aio

N = 5000
MSG = b"x" * 40


async def main_tcp() -> None:
    loop = asyncio.get_running_loop()
    done: asyncio.Future[float] = loop.create_future()

    async def handle(r: asyncio.StreamReader, _w: asyncio.StreamWriter) -> None:
        for _ in range(N):
            (n,) = struct.unpack("!I", await r.readexactly(4))
            await r.readexactly(n)
        done.set_result(time.perf_counter())

    srv = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = srv.sockets[0].getsockname()[1]
    _r, w = await asyncio.open_connection("127.0.0.1", port)
    c0 = time.process_time()
    t0 = time.perf_counter()
    for _ in range(N):
        w.write(struct.pack("!I", len(MSG)) + MSG)
        await w.drain()
        await asyncio.sleep(0)  # one message per loop turn, as one event makes one frame
    t1 = await done
    c1 = time.process_time()
    print(f"asyncio TCP stream: {N / (t1 - t0):.0f} msgs/s, {(c1 - c0) / N * 1e6:.1f} us CPU per message")
    w.close()
    srv.close()


async def main_grpc() -> None:
    done: asyncio.Future[float] = asyncio.get_running_loop().create_future()

    async def handler(it: AsyncIterator[bytes], _ctx: object) -> AsyncIterator[bytes]:
        n = 0
        async for _ in it:
            n += 1
            if n == N:
                done.set_result(time.perf_counter())
        yield b""

    h = grpc.method_handlers_generic_handler("b.B", {"S": grpc.stream_stream_rpc_method_handler(handler)})
    server = aio.server()
    server.add_generic_rpc_handlers((h,))
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    ch = aio.insecure_channel(f"127.0.0.1:{port}")
    call = ch.stream_stream("/b.B/S")()
    c0 = time.process_time()
    t0 = time.perf_counter()
    for _ in range(N):
        await call.write(MSG)
    t1 = await done
    c1 = time.process_time()
    print(f"grpc.aio bidi stream: {N / (t1 - t0):.0f} msgs/s, {(c1 - c0) / N * 1e6:.1f} us CPU per message")
    await call.done_writing()
    await ch.close()
    await server.stop(None)


if __name__ == "__main__":
    uvloop.run(main_tcp())
    uvloop.run(main_grpc())
