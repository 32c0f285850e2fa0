"""Fuzz targets, so that what was fixed stays fixed: every decoder that reads bytes from outside, fed with random
bytes, random protobuf messages generated from the message descriptors (extreme numbers, NaN and infinities,
odd strings, nested and repeated fields) and mutations of valid encodings (flipped and overwritten bytes,
truncations, insertions, splices, huge and overlong varints, length prefixes that claim more than follows).

Targets, and what may come out of them:

(a) host links: `pb.Envelope` bytes through `haa.core.wire.decode` (only `DecodeError` / `WireError`);
    `Frame`s through the transport's receive loop (only `LinkGap`); whole `HostLink.Open` streams with random
    metadata against a real in-process `Transport` server (a known status; the receive loop ends on nothing
    but a `LinkGap`; the server still serves a correct peer afterwards).
(b) agent channel frames over a real socketpair (`haa.sdk.channel`): the reader yields messages and then
    ends cleanly or raises `ChannelError`, within a second, without allocating what a length prefix claims.
(c) the control API of a real haa-hostd (membership mode, agent layer on) and the simulator's API of a real
    haa-sim: every RPC, with and without the token, gets a status that is neither UNKNOWN nor INTERNAL (a
    handler crash), unauthenticated calls are always UNAUTHENTICATED and counted, and both keep serving.
(d) the agent transaction and DDB decoders: `agenttable.decode` (only `AgentTxError`),
    `AgentTable.apply` and `Ddb.apply` on two replicas (only `DdbError` from the DDB, none from the table;
    both replicas stay equal), `Ddb.restore` (only `DdbError`).

Regression tests for undecodable requests, spawn timeouts and oversized agent messages are here too.

Budget: CI runs each target with a fixed number of examples (derandomized: the same inputs every run), each
example a batch of inputs (see BATCH): 2,000-3,000 inputs per decoder target, 200-1,000 calls per gRPC
target, about 30 s for the whole file on a quiet machine. `HAA_FUZZ_EXAMPLES=N` feeds about N inputs to every
target, freshly random (`make fuzz`: 20,000). A failure names the input bytes and hypothesis prints the seed
(`@reproduce_failure`); a crash found becomes a named regression test.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import os
import random
import signal
import socket
import struct
import tempfile
import time
import tracemalloc
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from google.protobuf import message_factory
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import DecodeError, Message
from grpc import aio
from helpers import run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_sim_service import SimProcess

from haa.cluster.hostprocs import MemberGroup, MemberHost, free_port
from haa.cluster.hostprocs import wait_for as wait
from haa.core import wire
from haa.core.ddb import agenttable
from haa.core.ddb import ddb as ddbmod
from haa.core.ddb.objects import DdbError
from haa.core.ddb.ops import encode_batch, put
from haa.core.messages import Excluded
from haa.hostd.control import MD_TOKEN
from haa.hostd.grpclink import receive
from haa.hostd.linkcommon import RxState
from haa.hostd.logs import LOGGER_NAME
from haa.hostd.outlink import _varint
from haa.hostd.transport import MD_HB_KEY, MD_INC, MD_SENDER, OPEN_METHOD, LinkGap, Transport, encode_frame
from haa.hostd.transport import envelope_chunk as chunk
from haa.pb import agent_pb2 as apb
from haa.pb import agenttx_pb2 as txpb
from haa.pb import control_pb2 as cpb
from haa.pb import ddb_pb2 as dpb
from haa.pb import hostlink_pb2 as pb
from haa.pb import sim_pb2 as spb
from haa.sdk.base import AgentBase, AgentContext, new_agent_id
from haa.sdk.channel import DEFAULT_MAX_FRAME, HEADER, MAX_AGENT_MESSAGE, Channel, ChannelError

# ------------------------------------------------------------------------------------------------ budget

_ENV = os.environ.get("HAA_FUZZ_EXAMPLES", "").strip()
LONG_RUN = bool(_ENV)


def fuzz(ci_examples: int, per_example: int = 20) -> settings:
    """Hypothesis settings of one target whose examples feed `per_example` inputs each: `ci_examples`
    derandomized examples, or enough random ones for HAA_FUZZ_EXAMPLES inputs."""
    return settings(
        max_examples=-(-int(_ENV) // per_example) if LONG_RUN else ci_examples,
        derandomize=not LONG_RUN,
        deadline=None,
        suppress_health_check=list(HealthCheck),
        print_blob=True,
    )


# ------------------------------------------------------------------------------------------------ strategies

_I32, _I64 = 2**31, 2**63
_EXTREME_INTS = [0, 1, -1, 2, _I32 - 1, -_I32, 2**32 - 1, _I64 - 1, -_I64, 2**64 - 1, 2**53 + 1]
_EXTREME_FLOATS = [0.0, -0.0, math.inf, -math.inf, math.nan, 1e308, -1e308, 5e-324, 1e-9, 0.5, 3600.0, 1e12]
_ODD_TEXT = ["", " ", "A1", "h1", "x" * 300, "\x00", "../..", "é" * 40, "A1.1.1.1", "*", "%s%n", "counter"]
_ODD_BYTES = [b"", b"\x00" * 300, b"{}", b'{"period": 1}', b"\xff" * 8]
_CHARS = "abcAZ09_.-/ \x00\x7féあ😀"

_F = FieldDescriptor
#: (low, high) of each integer field type (enums: proto3 enums are open, any int32)
_INT_RANGE = {
    _F.TYPE_INT64: (-_I64, _I64 - 1), _F.TYPE_SINT64: (-_I64, _I64 - 1), _F.TYPE_SFIXED64: (-_I64, _I64 - 1),
    _F.TYPE_UINT64: (0, 2**64 - 1), _F.TYPE_FIXED64: (0, 2**64 - 1),
    _F.TYPE_INT32: (-_I32, _I32 - 1), _F.TYPE_SINT32: (-_I32, _I32 - 1), _F.TYPE_SFIXED32: (-_I32, _I32 - 1),
    _F.TYPE_ENUM: (-_I32, _I32 - 1), _F.TYPE_UINT32: (0, 2**32 - 1), _F.TYPE_FIXED32: (0, 2**32 - 1),
}
MAX_DEPTH = 3


def _scalar(f: FieldDescriptor, rng: random.Random) -> Any:
    t = f.type
    if t in _INT_RANGE:
        lo, hi = _INT_RANGE[t]
        r = rng.random()
        if r < 0.3:
            return rng.choice([v for v in _EXTREME_INTS if lo <= v <= hi])
        if r < 0.7:
            return max(lo, min(hi, rng.randint(-3, 100)))
        return rng.randint(lo, hi)
    if t == _F.TYPE_DOUBLE:
        r = rng.random()
        if r < 0.4:
            return rng.choice(_EXTREME_FLOATS)
        return rng.uniform(-10, 10) if r < 0.7 else struct.unpack("<d", rng.randbytes(8))[0]
    if t == _F.TYPE_FLOAT:
        return rng.choice([0.0, 1.0, -1.0, math.inf, -math.inf, math.nan, 3.4e38, rng.uniform(-1e3, 1e3)])
    if t == _F.TYPE_BOOL:
        return rng.random() < 0.5
    if t == _F.TYPE_STRING:
        if rng.random() < 0.4:
            return rng.choice(_ODD_TEXT)
        return "".join(rng.choice(_CHARS) for _ in range(rng.randint(0, 12)))
    if t == _F.TYPE_BYTES:
        if rng.random() < 0.3:
            return rng.choice(_ODD_BYTES)
        return rng.randbytes(rng.choice([0, 1, 4, 16, 64]))
    raise AssertionError(f"field type {t}")


def _value(f: FieldDescriptor, rng: random.Random, depth: int) -> Any:
    if f.message_type is not None:
        return random_message(f.message_type, rng, depth + 1)
    return _scalar(f, rng)


def random_message(desc: Descriptor, rng: random.Random, depth: int = 0) -> Message:
    """A random message of type `desc`: each field set or not, with random (often extreme) values; one
    member of each oneof at most."""
    m = message_factory.GetMessageClass(desc)()
    if depth > MAX_DEPTH:
        return m
    chosen = {o.name: rng.choice([None, *o.fields]) for o in desc.oneofs}
    for f in desc.fields:
        o = f.containing_oneof
        if o is not None:
            if chosen[o.name] is not f:
                continue
        elif rng.random() < 0.4:
            continue
        target = getattr(m, f.name)
        if f.message_type is not None and f.message_type.GetOptions().map_entry:
            kf, vf = f.message_type.fields_by_name["key"], f.message_type.fields_by_name["value"]
            for _ in range(rng.randint(0, 3)):
                k, v = _value(kf, rng, depth), _value(vf, rng, depth)
                if isinstance(v, Message):
                    target[k].CopyFrom(v)
                else:
                    target[k] = v
        elif f.is_repeated:
            for _ in range(rng.choice([0, 1, 1, 2, 3])):
                v = _value(f, rng, depth)
                if isinstance(v, Message):
                    target.add().CopyFrom(v)
                else:
                    target.append(v)
        else:
            v = _value(f, rng, depth)
            if isinstance(v, Message):
                target.CopyFrom(v)
            else:
                setattr(m, f.name, v)
    return m


#: byte strings that break parsers: huge, overlong and unterminated varints, lengths claiming more than follows
_NASTY = [
    _varint(2**64 - 1),
    _varint(2**63),
    _varint(2**32),
    b"\xff" * 10 + b"\x01",  # an overlong (11-byte) varint
    b"\x80" * 10 + b"\x00",
    b"\xff" * 5,  # unterminated
    b"\x0a" + _varint(2**31),  # field 1, length-delimited, claims 2 GiB
    b"\x12" + _varint(2**64 - 1),
    b"\x0b\x0c",  # start/end group
    b"\x00",  # field number 0
    b"\xfa\xff\xff\xff\x0f\x00",  # field number 2^29 - 1
]
_MUTATIONS = ("flip", "set", "truncate", "insert", "delete", "splice", "nasty", "dup")


def mutate(data: bytes, rng: random.Random, others: list[bytes] | None = None) -> bytes:
    """`data` mutated one to four times: flipped or overwritten bytes, truncation, random insertions and
    deletions, a splice with another input, a nasty varint or length prefix, a duplicated chunk."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.choice(_MUTATIONS)
        pos = rng.randint(0, len(b))
        if op == "flip" and b:
            b[min(pos, len(b) - 1)] ^= 1 << rng.randint(0, 7)
        elif op == "set" and b:
            b[min(pos, len(b) - 1)] = rng.choice([0x00, 0x7F, 0x80, 0xFF, rng.randint(0, 255)])
        elif op == "truncate":
            del b[pos:]
        elif op == "insert":
            b[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif op == "delete":
            del b[pos : pos + rng.randint(1, 8)]
        elif op == "splice" and others:
            other = rng.choice(others)
            b = b[:pos] + other[rng.randint(0, len(other)) :]
        elif op == "nasty":
            b[pos:pos] = rng.choice(_NASTY)
        elif op == "dup" and b:
            end = rng.randint(pos, len(b))
            b[pos:pos] = b[pos:end]
    return bytes(b)


def make_inputs(
    desc: Descriptor, rng: random.Random, n: int, max_random: int = 200, mix: tuple[float, float] = (0.25, 0.5)
) -> list[bytes]:
    """`n` inputs for a decoder of `desc` messages: random bytes (a share of `mix[0]`), random messages (up to
    `mix[1]`), the rest mutated encodings of random messages."""
    valid = [random_message(desc, rng).SerializeToString() for _ in range(max(2, n // 2))]
    out = []
    for _ in range(n):
        r = rng.random()
        if r < mix[0]:
            out.append(rng.randbytes(rng.randint(0, max_random)))
        elif r < mix[1]:
            out.append(rng.choice(valid))
        else:
            out.append(mutate(rng.choice(valid), rng, valid))
    return out


# Hypothesis costs about 1 ms of CPU per example whatever the test does, more than most decoders here take for
# one input. So an example is a seed (hypothesis draws it: derandomized in CI, reproducible, printed on a
# failure) from which `make_inputs` makes a batch of inputs with Python's random; a failing assertion names
# the input bytes. BATCH inputs per example: examples x BATCH inputs per target.
BATCH = 20
seeds = st.integers(0, 2**64 - 1)


def messages(desc: Descriptor) -> st.SearchStrategy[Message]:
    """Random messages of type `desc` (one draw each)."""
    return seeds.map(lambda seed: random_message(desc, random.Random(seed)))


def inputs(desc: Descriptor, n: int = BATCH, max_random: int = 200) -> st.SearchStrategy[list[bytes]]:
    """Batches of `n` inputs for a decoder of `desc` messages (see `make_inputs`)."""
    return seeds.map(lambda seed: make_inputs(desc, random.Random(seed), n, max_random))


@functools.cache
def _loop() -> asyncio.AbstractEventLoop:
    """This module's event loop: one for all examples, cheap per example (`run(coro, loop=_loop())`)."""
    return asyncio.new_event_loop()


@pytest.fixture(scope="module", autouse=True)
def _close_loop() -> Iterator[None]:
    yield
    if _loop.cache_info().currsize:
        loop = _loop()
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()
        _loop.cache_clear()


# ============================================================================ (a) host-link frames


def _show(b: bytes) -> str:
    return repr(b if len(b) <= 200 else b[:200] + b"...")


def test_the_inputs_contain_the_nasty_cases() -> None:
    """The generator produces what the targets rely on (a guard against a generator that silently narrowed)."""
    rng = random.Random(1)
    got = make_inputs(pb.Envelope.DESCRIPTOR, rng, 2000)
    assert len(set(got)) > 1000
    assert sum(any(n in b for n in _NASTY[:7]) for b in got) > 50
    decoded = [x for x in got if _decodes(pb.Envelope, x)]
    kinds = {pb.Envelope.FromString(x).WhichOneof("payload") for x in decoded}
    assert len(kinds) >= 15, kinds  # nearly every payload kind
    msgs = [random_message(cpb.AgentSpawnRequest.DESCRIPTOR, rng) for _ in range(300)]
    assert any(math.isinf(m.cost) for m in msgs) and any(math.isnan(m.cost) for m in msgs)
    assert any(m.cost < 0 for m in msgs) and any(m.type == "" for m in msgs)


def _decodes(cls: Any, data: bytes) -> bool:
    try:
        cls.FromString(data)
    except DecodeError:
        return False
    return True


@fuzz(150)
@given(batch=inputs(pb.Envelope.DESCRIPTOR))
def test_fuzz_link_envelope_decoder(batch: list[bytes]) -> None:
    """What a peer sends as one envelope: only DecodeError (protobuf) or WireError (wire.decode) escape, and
    whatever decodes re-encodes to the same message."""
    for data in batch:
        try:
            env = pb.Envelope.FromString(data)
        except DecodeError:
            continue
        try:
            sender, inc, dst_inc, msg = wire.decode(env)
        except wire.WireError:
            continue
        except Exception as e:
            raise AssertionError(f"wire.decode raised {e!r} on {_show(data)}") from e
        again = wire.decode(pb.Envelope.FromString(wire.encode(sender, inc, dst_inc, msg).SerializeToString()))
        assert repr(again) == repr((sender, inc, dst_inc, msg)), _show(data)  # repr: NaN == NaN


class _Acks:
    """Where the receive loop reports a frame (the real one writes an ack on the stream)."""

    def __init__(self) -> None:
        self.frames = 0

    def frame(self, size: int = 0) -> None:
        self.frames += 1


def make_frames(rng: random.Random, n: int, sender: str = "a", inc: int = 11) -> list[bytes]:
    """`n` link frames: random bytes, frames of random / mutated envelopes (some from the stream's sender, so
    that they get through), and mutated frames."""
    envs = make_inputs(pb.Envelope.DESCRIPTOR, rng, 6, 60)
    for _ in range(3):
        e = random_message(pb.Envelope.DESCRIPTOR, rng)
        e.sender, e.sender_incarnation = sender, inc
        envs.append(e.SerializeToString())
    out: list[bytes] = []
    for _ in range(n):
        first = rng.choice([1, 1, 2, 3, 4, 5, 0, 2**64 - 1, rng.randint(1, 2**64 - 1)])
        frame = encode_frame(first, [chunk(e) for e in rng.sample(envs, rng.randint(0, 4))])
        r = rng.random()
        out.append(rng.randbytes(rng.randint(0, 100)) if r < 0.15 else frame if r < 0.6 else mutate(frame, rng, out))
    return out


async def _aiter(items: list[bytes]) -> AsyncIterator[bytes]:
    for x in items:
        yield x


@fuzz(150, 5 * 4)
@given(seed=seeds)
def test_fuzz_link_frames_receive_loop(seed: int) -> None:
    """The transport's receive loop on inbound streams (5 per example, up to 6 frames each): garbage frames
    are counted and dropped; only a LinkGap (a frame skipping sequence numbers: the sender resends) ends a
    stream; only well-formed envelopes of the stream's sender reach the core."""
    rng = random.Random(seed)
    for _ in range(5):
        inc = rng.choice([1, 11, 2**64 - 1])
        frames = make_frames(rng, rng.randint(1, 6), "a", inc)
        got: list[tuple[str, int, list[Any]]] = []
        t = Transport("b", "tok", {"a": "127.0.0.1:1"}, on_envelopes=lambda s, i, items, g=got: g.append((s, i, items)))
        rx = RxState(inc)
        t._rx["a"] = rx
        try:
            run(receive(t, _aiter(frames), "a", inc, rx, _Acks()), loop=_loop())  # type: ignore[arg-type]
        except LinkGap:
            pass
        except Exception as e:
            raise AssertionError(f"receive loop raised {e!r} on {[_show(f) for f in frames]}") from e
        for sender, i, items in got:
            assert (sender, i) == ("a", inc) and items
            assert all(type(msg) in wire.KIND for _dst, msg in items)


class _LinkServer:
    """A real in-process `Transport` server (no core behind it) on this module's loop."""

    def __init__(self) -> None:
        self.got = 0
        self.t = Transport("b", "tok", {"a": "127.0.0.1:1"}, on_envelopes=self._on, accept_unknown=True)
        self.t.incarnation = 7
        self.port = free_port()
        self.server: aio.Server | None = None
        self.records: list[logging.LogRecord] = []

    def _on(self, _s: str, _i: int, items: list[Any]) -> None:
        self.got += len(items)

    async def start(self) -> None:
        self.server = aio.server(options=Transport.server_options())
        self.t.add_to_server(self.server)
        self.server.add_insecure_port(f"127.0.0.1:{self.port}")
        await self.server.start()
        self.channel = aio.insecure_channel(f"127.0.0.1:{self.port}")

    async def open(self, md: tuple[tuple[str, str], ...], frames: list[bytes]) -> grpc.StatusCode:
        """Open a stream, send `frames` once the handshake came (as a real peer does), read to the end. The
        status: the server's refusal, or (accepted) OK - a write racing with the server ending the stream
        (a LinkGap) fails on the client side as INTERNAL, which says nothing about the server."""
        hello, taken, ended = asyncio.Event(), asyncio.Event(), asyncio.Event()
        accepted = False

        async def send() -> AsyncIterator[bytes]:
            await hello.wait()
            if accepted:
                for f in frames:
                    yield f
            taken.set()  # gRPC asked for what follows the last frame: it has written them all
            await ended.wait()  # half-closing at once would end the server's stream before it read the frames

        call = self.channel.stream_stream(OPEN_METHOD)(send(), metadata=md, timeout=5.0)
        try:
            with contextlib.suppress(aio.AioRpcError):
                async for _ in call:
                    accepted = True
                    hello.set()
                    # the frames go out, unless the server ends the stream first (a LinkGap)
                    waits = [asyncio.ensure_future(taken.wait()), asyncio.ensure_future(call.code())]
                    await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
                    for w in waits:
                        w.cancel()
                    break
        finally:
            hello.set()
            ended.set()
        with contextlib.suppress(aio.AioRpcError):
            async for _ in call:
                pass
        code = await call.code()
        return grpc.StatusCode.OK if accepted and code == grpc.StatusCode.INTERNAL else code

    async def stop(self) -> None:
        await self.channel.close()
        assert self.server is not None
        await self.server.stop(0)


class _Capture(logging.Handler):
    def __init__(self, into: list[logging.LogRecord]) -> None:
        super().__init__(logging.DEBUG)
        self.into = into

    def emit(self, record: logging.LogRecord) -> None:
        self.into.append(record)


@pytest.fixture(scope="module")
def link_server() -> Iterator[_LinkServer]:
    s = _LinkServer()
    run(s.start(), loop=_loop())
    logger = logging.getLogger(LOGGER_NAME + ".transport")
    handler, old = _Capture(s.records), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield s
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)
        run(s.stop(), loop=_loop())


LINK_CODES = {
    grpc.StatusCode.OUT_OF_RANGE,  # an incarnation far ahead of the clock (docs/limits.md)
    grpc.StatusCode.UNAVAILABLE,  # a newer incarnation of a live sender
    grpc.StatusCode.OK,
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.PERMISSION_DENIED,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.FAILED_PRECONDITION,
}


@fuzz(40, 5)
@given(seed=seeds)
def test_fuzz_link_streams_on_a_real_server(link_server: _LinkServer, seed: int) -> None:
    """Whole HostLink.Open calls (5 per example) with random metadata and frames: a known status, the receive
    loop ends on nothing but a LinkGap, and a correct peer is still served (next test)."""
    rng = random.Random(seed)
    for _ in range(5):
        md = tuple(
            (k, v)
            for k, v in (
                (MD_TOKEN, rng.choice(["tok", "tok", "", "wrong", None])),
                (MD_SENDER, rng.choice(["a", "a", "b", "zz", "", "-x", "x" * 70, "a b", None])),
                (MD_INC, rng.choice(["1", "11", "0", "-1", "x", " 7 ", "1_0", str(2**64), "", None])),
                (MD_HB_KEY, rng.choice(["ab" * 32, "ab" * 32, "cd" * 32, "AB" * 32, "ab" * 31, "", None])),
            )
            if v is not None
        )
        frames = make_frames(rng, rng.randint(0, 4), "a", 11)
        n = len(link_server.records)
        code = run(link_server.open(md, frames), loop=_loop())
        assert code in LINK_CODES, (code, md)
        for r in link_server.records[n:]:
            if getattr(r, "event", "") == "link_receive_ended":
                assert r.fields["reason"].startswith("LinkGap"), (r.fields, md, frames)  # type: ignore[attr-defined]


def test_link_server_still_serves_after_the_fuzzing(link_server: _LinkServer) -> None:
    before = link_server.got
    code = run(link_server.open((("x-haa-token", "tok"), (MD_SENDER, "zz"), (MD_INC, "3"), (MD_HB_KEY, "ef" * 32)), [
        encode_frame(1, [chunk(wire.encode("zz", 3, 7, Excluded(5)).SerializeToString())])]), loop=_loop())
    assert code == grpc.StatusCode.OK and link_server.got == before + 1


# ============================================================================ (b) agent channel frames


def make_channel_stream(rng: random.Random, in_type: type[Message]) -> bytes:
    """Bytes an agent channel's peer writes: framed random / mutated messages, bare length prefixes (0, the
    limit, above it, 4 GiB), random bytes."""
    bodies = make_inputs(in_type.DESCRIPTOR, rng, 6, 80)
    parts = []
    for _ in range(rng.randint(1, 5)):
        r = rng.random()
        if r < 0.5:
            parts.append(HEADER.pack(len(b := rng.choice(bodies))) + b)
        elif r < 0.7:
            parts.append(mutate(HEADER.pack(len(b := rng.choice(bodies))) + b, rng, parts))
        elif r < 0.85:
            n = rng.choice([0, 1, DEFAULT_MAX_FRAME, DEFAULT_MAX_FRAME + 1, 2**32 - 1, rng.randint(0, 2**32 - 1)])
            parts.append(HEADER.pack(n))
        else:
            parts.append(rng.randbytes(rng.randint(0, 40)))
    return b"".join(parts)


async def _read_all(in_type: type[Message], data: bytes) -> tuple[list[Message], str]:
    a, b = socket.socketpair()
    chan = await Channel.open(a, in_type)
    try:
        b.sendall(data)
        b.shutdown(socket.SHUT_WR)
        got: list[Message] = []
        while True:
            try:
                m = await asyncio.wait_for(chan.recv(), 1.0)
            except ChannelError as e:
                return got, f"error: {e}"
            if m is None:
                return got, "end"
            got.append(m)
    finally:
        chan.close()
        await chan.wait_closed()
        b.close()


@pytest.mark.parametrize("in_type", [apb.AgentToHost, apb.HostToAgent], ids=["host-reads", "agent-reads"])
def test_fuzz_agent_channel_frames(in_type: type[Message]) -> None:
    """Garbage, oversized length prefixes and truncated frames over a real socketpair (10 streams per
    example): the reader yields well-formed messages, then ends cleanly or raises ChannelError, within 1 s."""

    @fuzz(60, 10)
    @given(seed=seeds)
    def one(seed: int) -> None:
        rng = random.Random(seed)
        for _ in range(10):
            data = make_channel_stream(rng, in_type)
            try:
                got, how = run(_read_all(in_type, data), loop=_loop())
            except Exception as e:  # a hang (TimeoutError) or another exception type
                raise AssertionError(f"{e!r} reading {_show(data)}") from e
            assert all(m.WhichOneof("msg") is not None for m in got)
            assert how == "end" or how.startswith("error: ")

    one()


def test_channel_refuses_a_huge_length_prefix_at_once_and_allocates_nothing_for_a_truncated_frame() -> None:
    async def main() -> None:
        # a 4 GiB claim with the peer still connected: refused from the header alone (no waiting for a body)
        a, b = socket.socketpair()
        chan = await Channel.open(a, apb.AgentToHost)
        b.sendall(struct.pack(">I", 2**32 - 1) + b"xx")
        with pytest.raises(ChannelError, match="exceeds the limit"):
            await asyncio.wait_for(chan.recv(), 1.0)
        chan.close()
        b.close()
        # a 16 MiB claim (within the limit) followed by 10 bytes and EOF: an error, and the reader never
        # allocated anything near the claimed size
        a, b = socket.socketpair()
        chan = await Channel.open(a, apb.AgentToHost)
        b.sendall(HEADER.pack(DEFAULT_MAX_FRAME) + b"0123456789")
        b.shutdown(socket.SHUT_WR)
        tracemalloc.start()
        try:
            with pytest.raises(ChannelError, match="got 10 of 16777216 body bytes"):
                await asyncio.wait_for(chan.recv(), 1.0)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 1 << 20, peak
        chan.close()
        b.close()

    run(main(), loop=_loop())


class _Sender(AgentBase):
    TYPE = "t-sender"


def test_agent_send_over_max_agent_message_is_a_clear_error_in_the_agent() -> None:
    """Oversized agent messages, the agent side: an agent's send over MAX_AGENT_MESSAGE raises ValueError naming the
    limit before anything goes to the host (before, it passed up to the 16 MiB frame limit, and a message
    that fit the agent's frame could still be dropped further on once wrapped)."""
    frames: list[Any] = []
    init = apb.HostToAgent.Init(agent_id=new_agent_id(), name="A1", type_name=_Sender.TYPE, epoch=1, host="h1")
    ctx = AgentContext(init, _Sender, frames.append)
    ctx.send("someone", b"x" * MAX_AGENT_MESSAGE)
    assert len(frames) == 1
    with pytest.raises(ValueError, match="MAX_AGENT_MESSAGE"):
        ctx.send("someone", b"x" * (MAX_AGENT_MESSAGE + 1))
    assert len(frames) == 1


# ============================================================================ (c) the control API of a real host

TOKEN = "fuzz-token"
CONTROL = cpb.DESCRIPTOR.services_by_name["HostControl"]
#: calls that end or disturb the host on purpose: never fuzzed with the token
DISRUPTIVE = {"Leave"}


def call(channel: grpc.Channel, path: str, streaming: bool, raw: bytes, md: Any, timeout: float) -> grpc.StatusCode:
    """One call with raw request bytes; a stream counts as OK once it yielded its first item."""
    return calls(channel, [(path, streaming, raw)], md, timeout, timeout)[0]


def calls(
    channel: grpc.Channel, reqs: list[tuple[str, bool, bytes]], md: Any, unary_timeout: float, stream_timeout: float
) -> list[grpc.StatusCode]:
    """Start every call at once (path, server-streaming, raw request), then collect each one's status; a
    stream counts as OK once it yielded its first item (then it is cancelled)."""
    started: list[Any] = []
    for path, streaming, raw in reqs:
        if streaming:
            started.append(channel.unary_stream(path)(raw, metadata=md, timeout=stream_timeout))
        else:
            started.append(channel.unary_unary(path).future(raw, metadata=md, timeout=unary_timeout))
    codes = []
    for (_path, streaming, _raw), c in zip(reqs, started, strict=True):
        try:
            if streaming:
                for _ in c:
                    break
                c.cancel()
            else:
                c.result()
            codes.append(grpc.StatusCode.OK)
        except grpc.RpcError as e:
            codes.append(e.code())
    return codes


def _request(m: Any, rng: random.Random) -> bytes:
    """A request for method `m`: mostly well-formed messages with odd values (what reaches the handler)."""
    return make_inputs(m.input_type, rng, 1, mix=(0.1, 0.65))[0]


def make_calls(service: Any, methods: list[Any], rng: random.Random, n: int) -> list[tuple[str, bool, bytes]]:
    out = []
    for _ in range(n):
        m = rng.choice(methods)
        out.append((f"/{service.full_name}/{m.name}", m.server_streaming, _request(m, rng)))
    return out


def assert_statuses(reqs: list[tuple[str, bool, bytes]], codes: list[grpc.StatusCode], allowed: Any) -> None:
    for (path, _s, raw), code in zip(reqs, codes, strict=True):
        assert allowed(code), f"{path} -> {code} for {_show(raw)}"


@pytest.fixture(scope="module")
def host() -> Iterator[MemberHost]:
    """One haa-hostd: a group of one, agent layer on (no rebalancing)."""
    root = Path(tempfile.mkdtemp(prefix="haa-fuzz-"))
    group = MemberGroup(root, ["h1"], core=1, token=TOKEN, args=["--rebalance-period", "0"])
    h = group["h1"]
    h.start()
    try:
        wait(lambda: len(h.status().members) == 1, 40, "a group of one")
        yield h
    finally:
        group.close()
        err = (h.data_dir / "stderr.1.txt").read_text()
        assert "Traceback" not in err, err[-3000:]


def counters(h: MemberHost) -> dict[str, int]:
    return dict(h.status().counters.values)


def test_undecodable_requests_without_the_token_are_unauthenticated_and_counted(host: MemberHost) -> None:
    """Regression guard: garbage to every method without (or with a wrong) token was UNKNOWN "DecodeError"
    and not counted; it is UNAUTHENTICATED, counted as rejected_unauthenticated and control_rejected."""
    before = counters(host)
    ch = grpc.insecure_channel(host.address)
    n = 0
    for m in CONTROL.methods:
        for md in ((), ((MD_TOKEN, "wrong"),)):
            code = call(ch, f"/{CONTROL.full_name}/{m.name}", m.server_streaming, b"\xff\xff\xff\xff", md, 5.0)
            assert code == grpc.StatusCode.UNAUTHENTICATED, (m.name, code)
            n += 1
    after = counters(host)
    assert after.get("rejected_unauthenticated", 0) - before.get("rejected_unauthenticated", 0) == n
    assert after.get("control_rejected", 0) - before.get("control_rejected", 0) == n
    ch.close()


def test_undecodable_requests_with_the_token_are_invalid_argument_and_counted(host: MemberHost) -> None:
    before = counters(host)
    ch = grpc.insecure_channel(host.address)
    md = ((MD_TOKEN, TOKEN),)
    for m in CONTROL.methods:
        code = call(ch, f"/{CONTROL.full_name}/{m.name}", m.server_streaming, b"\x0a\xff\xff\xff", md, 5.0)
        assert code == grpc.StatusCode.INVALID_ARGUMENT, (m.name, code)
    with pytest.raises(grpc.RpcError) as e:
        ch.unary_unary(f"/{CONTROL.full_name}/Status")(b"\x0a\x05ab", metadata=md, timeout=5.0)
    assert "malformed StatusRequest (4 bytes)" in (e.value.details() or "")
    after = counters(host)
    n = len(CONTROL.methods) + 1
    assert after.get("control_malformed", 0) - before.get("control_malformed", 0) == n
    assert after.get("rejected_unauthenticated", 0) == before.get("rejected_unauthenticated", 0)
    ch.close()


def test_agent_send_and_request_over_max_agent_message_are_refused_up_front(host: MemberHost) -> None:
    """Regression guard: a 50 MB AgentSend returned ok and the owner then dropped it ("frame exceeds limit");
    a payload over MAX_AGENT_MESSAGE is refused with ok=false and the reason, and one at the limit is taken."""
    c = host.client
    r = c.agent_spawn("counter", b"{}")
    assert r.ok, r
    wait(lambda: any(a.name == r.name and a.local_phase == "active" for a in c.agent_list().agents), 20, "active")
    before = counters(host).get("control_oversized", 0)
    # (a 50 MB one is now refused by gRPC unread, above the server's MAX_REQUEST: docs/transport.md "Large frames")
    with pytest.raises(grpc.RpcError) as e:
        c._stub.AgentSend(cpb.AgentSendRequest(ref=r.name, payload=b"x" * (50 << 20)), metadata=c._md, timeout=30)
    assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    big = c._stub.AgentSend(cpb.AgentSendRequest(ref=r.name, payload=b"x" * (6 << 20)), metadata=c._md, timeout=30)
    assert not big.ok and "exceeds the limit of 4194304 bytes (MAX_AGENT_MESSAGE)" in big.reason, big
    assert not c.agent_send(r.name, b"x" * (MAX_AGENT_MESSAGE + 1)).ok
    rq = c.agent_request(r.name, b"x" * (MAX_AGENT_MESSAGE + 1))
    assert not rq.ok and "MAX_AGENT_MESSAGE" in rq.error
    assert c.agent_send(r.name, b"x" * MAX_AGENT_MESSAGE).ok
    assert counters(host).get("control_oversized", 0) == before + 3
    assert c.agent_remove(r.name).ok


def _control_methods(authenticated: bool) -> list[Any]:
    return [m for m in CONTROL.methods if not (authenticated and m.name in DISRUPTIVE)]


BAD_CODES = {grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL}


@functools.cache
def _channel(address: str) -> grpc.Channel:
    return grpc.insecure_channel(address, options=[("grpc.max_send_message_length", 64 << 20)])


@fuzz(50)
@given(seed=seeds)
def test_fuzz_control_api_with_the_token(host: MemberHost, seed: int) -> None:
    """Random and mutated requests to every control method but Leave, with the token (BATCH concurrent calls
    per example): never UNKNOWN or INTERNAL; the host keeps serving (checked by the next test)."""
    reqs = make_calls(CONTROL, _control_methods(True), random.Random(seed), BATCH)
    codes = calls(_channel(host.address), reqs, ((MD_TOKEN, TOKEN),), 5.0, 0.2)
    assert_statuses(reqs, codes, lambda c: c not in BAD_CODES)


@fuzz(15)
@given(seed=seeds)
def test_fuzz_control_api_without_the_token(host: MemberHost, seed: int) -> None:
    rng = random.Random(seed)
    reqs = make_calls(CONTROL, _control_methods(False), rng, BATCH)
    md = rng.choice([(), ((MD_TOKEN, "wrong"),), ((MD_TOKEN, ""),), (("x-haa-token-x", TOKEN),),
                     ((MD_TOKEN, TOKEN + " "),)])
    before = counters(host).get("rejected_unauthenticated", 0)
    codes = calls(_channel(host.address), reqs, md, 5.0, 5.0)
    assert_statuses(reqs, codes, lambda c: c == grpc.StatusCode.UNAUTHENTICATED)
    assert counters(host).get("rejected_unauthenticated", 0) == before + len(reqs)


def test_host_alive_and_serving_after_the_control_fuzzing(host: MemberHost) -> None:
    assert host.alive()
    st_ = host.status()
    assert st_.member and len(st_.members) == 1
    c = st_.counters.values
    assert c.get("core_errors", 0) == 0, dict(c)
    # the handlers' exceptions (control_errors) were all proper statuses: none was a bug
    assert not host.events(0, {"control_internal_error"}), host.events(0, {"control_internal_error"})[:3]
    r = host.client.ddb_write([put("fuzz/after", "blob", b"1")], timeout=10)
    assert r.committed, r


@pytest.mark.slow
def test_a_spawn_that_times_out_is_deadline_exceeded(tmp_path: Path) -> None:
    """Regression guard: a spawn whose commit does not come back (the other member is stopped) surfaced as
    UNKNOWN "TimeoutError"; it is DEADLINE_EXCEEDED with a reason. About 12 s (the runtime waits 10 s)."""
    args = ["--rebalance-period", "0", "--exclude-after", "60"]
    group = MemberGroup(tmp_path, ["h1", "h2"], core=1, token=TOKEN, args=args)
    h1, h2 = group["h1"], group["h2"]
    group.start()
    try:
        wait(lambda: len(h1.status().members) == 2, 40, "a group of two")
        assert h2.proc is not None
        h2.proc.send_signal(signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(grpc.RpcError) as e:
            h1.client.agent_spawn("counter", b"{}", timeout=30)
        assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED, (e.value.code(), e.value.details())
        assert "AgentSpawn: no answer in time" in (e.value.details() or "")
        assert time.monotonic() - t0 < 25  # the server's 10 s, not the client's 30 s
        assert h1.status().counters.values.get("control_errors", 0) == 1
    finally:
        group.close()


# ============================================================================ (c) the simulator's API

SIM_TOKEN = "sim-fuzz-token"
SIM_SERVICES = [spb.DESCRIPTOR.services_by_name[n] for n in ("AvatarSim", "GroundTruth", "SimControl")]
SIM_METHODS = [(s, m) for s in SIM_SERVICES for m in s.methods]


@pytest.fixture(scope="module")
def sim() -> Iterator[SimProcess]:
    d = Path(tempfile.mkdtemp(prefix="haa-fuzz-sim-"))
    (d / "token").write_text(SIM_TOKEN + "\n")
    s = SimProcess("--arena", "small", "--seed", "5", "--step", "--token-file", str(d / "token"))
    try:
        with s.client(token=SIM_TOKEN) as c:
            c.register("seeker", avatar_id="fz1")
        yield s
    finally:
        assert s.stop() == 0, s.lines[-5:]
        assert not any("Traceback" in line for line in s.lines), "\n".join(s.lines[-40:])


def test_sim_undecodable_requests_are_unauthenticated_or_invalid_argument(sim: SimProcess) -> None:
    """Regression guard for haa-sim: garbage was UNKNOWN "DecodeError"; it is UNAUTHENTICATED without the
    token and INVALID_ARGUMENT with it."""
    ch = grpc.insecure_channel(sim.address)
    for s, m in SIM_METHODS:
        path = f"/{s.full_name}/{m.name}"
        assert call(ch, path, m.server_streaming, b"\xff\xff", (), 5.0) == grpc.StatusCode.UNAUTHENTICATED, m.name
        code = call(ch, path, m.server_streaming, b"\xff\xff", ((MD_TOKEN, SIM_TOKEN),), 5.0)
        assert code == grpc.StatusCode.INVALID_ARGUMENT, (m.name, code)
    ch.close()


@fuzz(40)
@given(seed=seeds)
def test_fuzz_sim_api(sim: SimProcess, seed: int) -> None:
    """Random and mutated requests to every simulator method (BATCH concurrent calls per example), with the
    token (never UNKNOWN or INTERNAL) and without it (UNAUTHENTICATED)."""
    rng = random.Random(seed)
    reqs: list[tuple[str, bool, bytes]] = []
    for _ in range(BATCH):
        s, m = rng.choice(SIM_METHODS)
        reqs.append((f"/{s.full_name}/{m.name}", m.server_streaming, _request(m, rng)))
    authed = rng.random() < 0.8
    md = ((MD_TOKEN, SIM_TOKEN),) if authed else rng.choice([(), ((MD_TOKEN, "no"),)])
    codes = calls(_channel(sim.address), reqs, md, 5.0, 0.2)
    if authed:
        assert_statuses(reqs, codes, lambda c: c not in BAD_CODES)
    else:
        assert_statuses(reqs, codes, lambda c: c == grpc.StatusCode.UNAUTHENTICATED)


def test_sim_serving_after_the_fuzzing(sim: SimProcess) -> None:
    with sim.client(token=SIM_TOKEN) as c:
        assert c.info().arena == "small"
        assert c.poses().avatars


# ============================================================================ (d) agent transactions and the DDB


@fuzz(150)
@given(batch=inputs(txpb.AgentTx.DESCRIPTOR))
def test_fuzz_agent_transaction_decoder(batch: list[bytes]) -> None:
    for data in batch:
        try:
            tx = agenttable.decode(data)
        except agenttable.AgentTxError:
            continue
        except Exception as e:
            raise AssertionError(f"agenttable.decode raised {e!r} on {_show(data)}") from e
        assert tx.WhichOneof("body") is not None


@fuzz(100, 10)
@given(batch=inputs(txpb.AgentTx.DESCRIPTOR, n=10))
def test_fuzz_agent_table_apply_on_two_replicas(batch: list[bytes]) -> None:
    """Committed agent transactions are applied by every replica: no exception, the same result and hash."""
    a, b = agenttable.AgentTable(), agenttable.AgentTable()
    for p in batch:
        try:
            ra, rb = a.apply(p, ("h1", "h2")), b.apply(p, ("h1", "h2"))
        except Exception as e:
            raise AssertionError(f"AgentTable.apply raised {e!r} on {_show(p)}") from e
        assert repr(ra) == repr(rb)
    assert a.content_hash() == b.content_hash()


@fuzz(100, 10)
@given(batch=inputs(dpb.DdbBatch.DESCRIPTOR, n=10))
def test_fuzz_ddb_apply_on_two_replicas(batch: list[bytes]) -> None:
    """Committed DDB batches: only DdbError escapes apply, identically on both replicas, hashes stay equal."""
    a, b = ddbmod.Ddb(), ddbmod.Ddb()
    for p in batch:
        out = []
        for db in (a, b):
            try:
                out.append(repr(db.apply(p)))
            except DdbError as e:
                out.append(f"DdbError: {e}")
            except Exception as e:
                raise AssertionError(f"Ddb.apply raised {e!r} on {_show(p)}") from e
        assert out[0] == out[1], (out, _show(p))
    assert a.content_hash() == b.content_hash() and a.seq == b.seq


def _snapshot() -> bytes:
    db = ddbmod.Ddb()
    db.apply(encode_batch([put("k1", "blob", b"v"), put("k2", "json", {"a": 1})]))
    return db.snapshot()


@fuzz(100)
@given(seed=seeds)
def test_fuzz_ddb_restore(seed: int) -> None:
    """A snapshot from a sponsor (state transfer): only DdbError escapes restore; what restores re-snapshots."""
    rng = random.Random(seed)
    good = _snapshot()
    batch = make_inputs(dpb.DdbSnapshot.DESCRIPTOR, rng, 10) + [mutate(good, rng) for _ in range(10)]
    for data in batch:
        try:
            db = ddbmod.Ddb.restore(data)
        except DdbError:
            continue
        except Exception as e:
            raise AssertionError(f"Ddb.restore raised {e!r} on {_show(data)}") from e
        assert ddbmod.Ddb.restore(db.snapshot()).content_hash() == db.content_hash()
