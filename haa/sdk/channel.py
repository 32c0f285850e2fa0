"""The local host <-> agent channel: length-prefixed protobuf frames over a unix stream socket, asyncio.

Each agent process has exactly one channel, to its host (thesis §6.1.2: "all inter-agent communication is
routed through the hosts"). The host makes a `socket.socketpair()`, keeps one end and hands the other to the
agent process (through the fork server, see `haa.sdk.forkserver`). Both ends use this module:

    frame = 4-byte big-endian unsigned length N, then N bytes = one serialized protobuf message

The host sends `haa.v1.HostToAgent` messages and receives `haa.v1.AgentToHost`; the agent the reverse
(proto/haa/pb/agent.proto). A unix stream socket is reliable and FIFO, which is all the ordering the agent
runtime relies on: an agent's frames reach the host in the order the agent wrote them.

Errors are `ChannelError` with a one-line reason, e.g.

    frame of 1073741824 bytes exceeds the limit of 16777216 bytes
    malformed frame (2 bytes): Error parsing message ...
    malformed frame (5 bytes): no known message in it
    connection closed in the middle of a frame (got 2 of 4 header bytes)

A frame larger than `max_frame` is refused on both sides: `send` raises `FrameTooLarge` (a `ValueError`, the
caller's bug) before writing anything, `recv` raises `ChannelError` without reading the body (the peer is
broken or hostile; the caller drops the channel). An empty protobuf message (no field of the `oneof msg`
set) is malformed too: protobuf parses almost any byte string as a message of unknown fields, so "parses"
alone proves nothing.

`send` never blocks: it hands the bytes to the asyncio transport, which buffers them; `drain()` waits until
the buffer is below the transport's high-water mark (use it for backpressure where you can await).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from typing import Generic, TypeVar

from google.protobuf.message import DecodeError, Message

#: default largest frame, in bytes (agent state travels in one frame, so this bounds pack_state())
DEFAULT_MAX_FRAME = 16 * 1024 * 1024
#: a frame's length prefix
HEADER = struct.Struct(">I")
#: bytes a frame adds around a message payload (header + protobuf field tags); used for size checks
FRAME_OVERHEAD = 64
#: the largest payload of one agent message, in bytes: an operator's `AgentSend` / `AgentRequest` (refused by
#: the control API with ok=false and a reason) and an agent's `send` / `request` (ValueError in the agent).
#: A message travels wrapped - in an AgentMsg with two agent ids inside a channel frame, in a host-link
#: envelope, batched with others into a queue2 push transaction while its receiver is frozen - so it is kept
#: well below `DEFAULT_MAX_FRAME - FRAME_OVERHEAD`: what passes this check always fits every hop's frame.
#: docs/limits.md, "Control API and agent messages".
MAX_AGENT_MESSAGE = 4 * 1024 * 1024
assert MAX_AGENT_MESSAGE <= DEFAULT_MAX_FRAME - FRAME_OVERHEAD


def message_too_large(size: int) -> str:
    """The reason an agent message payload of `size` bytes is refused, or "" if it is small enough."""
    if size > MAX_AGENT_MESSAGE:
        return f"message of {size} bytes exceeds the limit of {MAX_AGENT_MESSAGE} bytes (MAX_AGENT_MESSAGE)"
    return ""

M = TypeVar("M", bound=Message)


class ChannelError(Exception):
    """The channel is unusable: a malformed or oversized frame arrived, or the peer closed mid-frame."""


class FrameTooLarge(ValueError):
    """A frame we were asked to send exceeds the channel's limit (nothing was written)."""


class Channel(Generic[M]):
    """One end of a host<->agent channel: sends `Message`s, receives messages of type `in_type`."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        in_type: type[M],
        *,
        max_frame: int = DEFAULT_MAX_FRAME,
    ) -> None:
        if max_frame <= 0 or max_frame > 0xFFFFFFFF:
            raise ValueError(f"max_frame: must be in 1..{0xFFFFFFFF}, got {max_frame}")
        self.reader = reader
        self.writer = writer
        self.in_type = in_type
        self.max_frame = max_frame
        self.frames_in = 0
        self.frames_out = 0
        self.bytes_in = 0
        self.bytes_out = 0
        self._closed = False

    @classmethod
    async def open(cls, sock: socket.socket, in_type: type[M], *, max_frame: int = DEFAULT_MAX_FRAME) -> Channel[M]:
        """Wrap a connected unix stream socket (it becomes non-blocking and owned by the channel)."""
        sock.setblocking(False)
        # the default 64 KiB StreamReader limit only matters for readline(); readexactly() is unbounded
        reader, writer = await asyncio.open_unix_connection(sock=sock)
        return cls(reader, writer, in_type, max_frame=max_frame)

    # ------------------------------------------------------------------ sending

    def encode(self, msg: Message) -> bytes:
        """Serialize `msg` as one frame; raises `FrameTooLarge` if it exceeds `max_frame`."""
        body = msg.SerializeToString()
        if len(body) > self.max_frame:
            which = _which(msg)
            raise FrameTooLarge(
                f"frame of {len(body)} bytes ({which}) exceeds the limit of {self.max_frame} bytes"
            )
        return HEADER.pack(len(body)) + body

    def send(self, msg: Message) -> None:
        """Queue one frame for sending (never blocks); raises `FrameTooLarge`, or `ChannelError` if closed."""
        data = self.encode(msg)
        self.send_raw(data)

    def send_raw(self, data: bytes) -> None:
        """Queue already framed bytes (tests use it to send garbage)."""
        if self._closed or self.writer.is_closing():
            raise ChannelError("channel is closed")
        self.writer.write(data)
        self.frames_out += 1
        self.bytes_out += len(data)

    async def drain(self) -> None:
        """Wait until the transport's write buffer is below its high-water mark; ChannelError if broken."""
        try:
            await self.writer.drain()
        except (ConnectionError, OSError) as e:
            raise ChannelError(f"write failed: {e}") from e

    # ------------------------------------------------------------------ receiving

    async def recv(self) -> M | None:
        """The next message, or None at a clean end of stream (the peer closed between frames).

        A peer that closes with unread input in its socket (a process that exits, or fails at start, while its
        host still writes to it) resets the connection. The frames it had sent before are in our reader's
        buffer already, but the stream reader raises the reset before it hands them out: they are returned
        from the buffer first, then the end of stream (`_after_reset`). Without that, an agent's last frames
        (its Error, the message before it) were lost."""
        try:
            header = await self.reader.readexactly(HEADER.size)
        except asyncio.IncompleteReadError as e:
            if not e.partial:
                return None
            raise ChannelError(
                f"connection closed in the middle of a frame (got {len(e.partial)} of {HEADER.size} header bytes)"
            ) from None
        except ConnectionResetError:
            return self._after_reset()
        except (ConnectionError, OSError) as e:
            raise ChannelError(f"read failed: {e}") from e
        (n,) = HEADER.unpack(header)
        if n > self.max_frame:
            raise ChannelError(f"frame of {n} bytes exceeds the limit of {self.max_frame} bytes")
        try:
            body = await self.reader.readexactly(n)
        except asyncio.IncompleteReadError as e:
            raise ChannelError(
                f"connection closed in the middle of a frame (got {len(e.partial)} of {n} body bytes)"
            ) from None
        except ConnectionResetError:
            return self._after_reset(n)
        except (ConnectionError, OSError) as e:
            raise ChannelError(f"read failed: {e}") from e
        self.frames_in += 1
        self.bytes_in += HEADER.size + n
        return self.decode(body)

    def _after_reset(self, body_size: int | None = None) -> M | None:
        """The connection was reset (`recv`): the next frame still in the reader's buffer, or None when it
        holds nothing more (an end of stream); ChannelError if it ends inside a frame. `body_size`: the header
        was read already and announced that many bytes."""
        buf = getattr(self.reader, "_buffer", None)
        if buf is None:
            buf = bytearray()
        if body_size is None:
            if not buf:
                return None
            if len(buf) < HEADER.size:
                raise ChannelError("connection reset in the middle of a frame")
            (body_size,) = HEADER.unpack(bytes(buf[: HEADER.size]))
            if body_size > self.max_frame:
                raise ChannelError(f"frame of {body_size} bytes exceeds the limit of {self.max_frame} bytes")
            if len(buf) < HEADER.size + body_size:
                raise ChannelError("connection reset in the middle of a frame")
            del buf[: HEADER.size]
        if len(buf) < body_size:
            raise ChannelError("connection reset in the middle of a frame")
        body = bytes(buf[:body_size])
        del buf[:body_size]
        self.frames_in += 1
        self.bytes_in += HEADER.size + body_size
        return self.decode(body)

    def decode(self, body: bytes) -> M:
        """Parse one frame body; raises `ChannelError` if it is not a message of `in_type` with a known kind."""
        msg = self.in_type()
        try:
            msg.ParseFromString(body)
        except DecodeError as e:
            raise ChannelError(f"malformed frame ({len(body)} bytes): {e}") from None
        except Exception as e:  # the upb backend raises other types for some garbage
            raise ChannelError(f"malformed frame ({len(body)} bytes): {type(e).__name__}: {e}") from None
        if _which(msg) is None:
            raise ChannelError(f"malformed frame ({len(body)} bytes): no known message in it")
        return msg

    # ------------------------------------------------------------------ closing

    def close(self) -> None:
        """Close the socket (idempotent); frames already queued are flushed by the transport if it can."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self.writer.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def buffered(self) -> int:
        """Bytes queued by `send` that the socket has not taken yet (the peer has not read them); 0 once closed."""
        try:
            return self.writer.transport.get_write_buffer_size()
        except Exception:  # a transport already gone
            return 0

    async def wait_closed(self) -> None:
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()


def _which(msg: Message) -> str | None:
    """The name of the `msg` oneof field set in a HostToAgent / AgentToHost, or None."""
    try:
        return msg.WhichOneof("msg")
    except ValueError:  # a message without a `msg` oneof: report its type
        return type(msg).__name__
