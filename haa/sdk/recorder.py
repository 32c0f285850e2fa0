"""The AgentPlayback recorder (thesis §6.1.4; docs/playback.md): runs inside the agent process.

`from_env(init)` gives a `Recorder` when `HAA_RECORD_DIR` is set (haa-hostd `--record DIR` sets it for the
host's agent processes), else None; it is the tap factory haa-hostd names for them (HAA_AGENT_TAP, loaded by
name: haa.sdk.tap), so `haa.sdk.runner` installs the recorder as the tap of the agent's `AgentContext`
(haa.sdk.base) without importing haa.lab.playback. The context reports every input where the agent consumes
it, in that order — mailbox items (messages and requests with their sender, timer firings, DDB watch
notifications and log items, the start/thaw/recover, resume, freeze and stop steps with their blobs), the
host's answers to DDB reads, writes and spawn requests, replies to the agent's requests and timeouts of either,
every `now()` and every random number — and every frame the agent sends its host (the outputs the replay
compares). `wrap_stub` records an agent's calls to haa-sim and their replies (haa.sdk.external).

Files: `<dir>/<agent name>/<instance>-<segment>.mcap`, instance = "e<epoch>-<host>-<start ns>" (a transferred
or recovered agent goes on in a new instance on its new host, in the same folder). Each segment starts with a
`PlaybackInstance` message (the Init frame); a segment is closed and the next one begun once it holds
`HAA_RECORD_SEGMENT_BYTES` (default 64 MiB) of messages. Chunks (zstd) are closed and written at least every
`FLUSH_S` (1 s: what the agent did up to a second before a crash of its process or host is readable) and
when the agent ends. A write error stops the recording (one line on stderr), never the agent.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import random
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.well_known import MessageEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from haa.pb import agent_pb2 as pb
from haa.pb import playback_pb2 as ppb
from haa.sdk.base import Clock

#: the recording format (haa.lab.playback.reader reads it): its name and the MCAP topics of a segment
FORMAT = "haa-playback/1"
TOPIC_INSTANCE = "/playback/instance"
TOPIC_INPUT = "/playback/input"
TOPIC_OUTPUT = "/playback/output"
#: a recording segment's file name ends so
SUFFIX = ".mcap"

#: the environment variable that turns recording on in an agent process (haa-hostd --record sets it)
RECORD_ENV = "HAA_RECORD_DIR"
#: rotate segments at this many bytes of messages (environment HAA_RECORD_SEGMENT_BYTES)
SEGMENT_ENV = "HAA_RECORD_SEGMENT_BYTES"
DEFAULT_SEGMENT_BYTES = 64 * 1024 * 1024
MIN_SEGMENT_BYTES = 4096
#: the largest segment size one may ask for: a reader keeps a segment's messages in memory, and refuses a
#: segment of more than this plus `SEGMENT_SLACK` bytes of messages (haa.lab.playback.reader)
MAX_SEGMENT_BYTES = 256 * 1024 * 1024
#: what the last message of a segment may add past its rotation size (an agent message, 4 MiB, with its
#: envelope; a state, 2 MiB)
SEGMENT_SLACK = 16 * 1024 * 1024
#: close the open chunk and write it out at least this often, seconds
FLUSH_S = 1.0
#: a chunk is closed at this many bytes anyway
CHUNK_BYTES = 256 * 1024
#: an output frame larger than this (bytes) is kept as its SHA-256 and size (camera frames sent to sensor agents)
DIGEST_OVER = 64 * 1024

_SAFE = re.compile(r"[^A-Za-z0-9._-]")


def safe_name(text: str) -> str:
    """`text` usable as one path component."""
    out = _SAFE.sub("_", text)[:100]
    return out if out not in ("", ".", "..") else "_"


def from_env(init: pb.HostToAgent.Init) -> Recorder | None:
    """A recorder for this agent instance when HAA_RECORD_DIR is set, else None."""
    root = os.environ.get(RECORD_ENV, "")
    if not root:
        return None
    size = DEFAULT_SEGMENT_BYTES
    if os.environ.get(SEGMENT_ENV):
        try:
            size = min(MAX_SEGMENT_BYTES, max(MIN_SEGMENT_BYTES, int(os.environ[SEGMENT_ENV])))
        except ValueError:
            print(f"agent {init.name}: {SEGMENT_ENV}={os.environ[SEGMENT_ENV]!r} is not a number; "
                  f"using {DEFAULT_SEGMENT_BYTES}", file=sys.stderr)
    try:
        return Recorder(Path(root), init, segment_bytes=size)
    except OSError as e:
        print(f"agent {init.name}: cannot record into {root}: {e.strerror or e}", file=sys.stderr)
        return None


class _TapClock(Clock):
    """The agent's clock, each `now()` recorded."""

    def __init__(self, inner: Clock, rec: Recorder) -> None:
        self.inner = inner
        self._rec = rec

    def now(self) -> float:
        v = self.inner.now()
        self._rec.input(ppb.PlaybackInput(clock=v))
        return v

    def wall_delay(self, delay: float) -> float:
        return self.inner.wall_delay(delay)


class _TapRandom(random.Random):
    """The agent's random source, each draw recorded. Every method of random.Random is built on `random()` and
    `getrandbits()` (this subclass defines both, so `_randbelow` uses getrandbits): recording those two records
    every random number the agent takes."""

    def __init__(self, inner: random.Random, rec: Recorder) -> None:
        super().__init__()
        self.inner = inner
        self._rec = rec

    def random(self) -> float:
        v = self.inner.random()
        self._rec.input(ppb.PlaybackInput(random=v))
        return v

    def getrandbits(self, k: int) -> int:
        v = self.inner.getrandbits(k)
        self._rec.input(ppb.PlaybackInput(random_bits=ppb.PlaybackInput.RandomBits(
            k=k, value=v.to_bytes((k + 7) // 8, "little"))))
        return v


class Recorder:
    """Records one agent instance (module docstring)."""

    def __init__(self, root: Path, init: pb.HostToAgent.Init, segment_bytes: int = DEFAULT_SEGMENT_BYTES,
                 flush_s: float = FLUSH_S) -> None:
        self.init = pb.HostToAgent.Init()
        self.init.CopyFrom(init)
        self.dir = Path(root) / safe_name(init.name or init.agent_id)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.start_ns = time.time_ns()
        self.instance = f"e{init.epoch}-{safe_name(init.host or 'nohost')}-{self.start_ns}"
        self.segment_bytes = int(segment_bytes)
        self.flush_s = float(flush_s)
        self.inputs = 0
        self.outputs = 0
        self.external_calls = 0
        self.segment = -1
        self.bytes_total = 0
        self.closed = False
        self._writer: Writer | None = None
        self._file: Any = None
        self._seg_bytes = 0
        self._dirty = False
        self._last_flush = time.monotonic()
        self._flush_handle: asyncio.TimerHandle | None = None
        self._open()

    # ------------------------------------------------------------------ files

    def _open(self) -> None:
        self.segment += 1
        path = self.dir / f"{self.instance}-{self.segment:04d}{SUFFIX}"
        self._file = open(path, "wb")  # noqa: SIM115 - closed in _finish
        w = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="", library=f"haa-playback {FORMAT}")
        self._channels = {}
        for topic, cls in ((TOPIC_INSTANCE, ppb.PlaybackInstance), (TOPIC_INPUT, ppb.PlaybackInput),
                           (TOPIC_OUTPUT, ppb.PlaybackOutput)):
            sid = register_schema(w, cls)
            self._channels[topic] = w.register_channel(topic=topic, message_encoding=MessageEncoding.Protobuf,
                                                       schema_id=sid)
        self._writer = w
        self._seg_bytes = 0
        head = ppb.PlaybackInstance(init=self.init, instance=self.instance, segment=self.segment,
                                    first_input=self.inputs, first_output=self.outputs,
                                    wall_start_ns=self.start_ns, format=FORMAT)
        self._write(TOPIC_INSTANCE, head.SerializeToString(), 0, time.time_ns())
        self.flush()  # the header is on disk at once: `haactl record ls` sees the instance

    def _finish(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def _write(self, topic: str, data: bytes, seq: int, ns: int) -> None:
        if self._writer is None:
            return
        try:
            self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns,
                                     sequence=seq & 0xFFFFFFFF)
            self._seg_bytes += len(data)
            self.bytes_total += len(data)
            self._dirty = True
            if self._seg_bytes >= self.segment_bytes:
                self._finish()
                self._open()
            elif time.monotonic() - self._last_flush >= self.flush_s:
                self.flush()
            else:
                self._arm_flush()
        except OSError as e:
            self._failed(e)

    def _failed(self, e: OSError) -> None:
        print(f"agent {self.init.name}: recording stopped: {e.strerror or e}", file=sys.stderr)
        self._writer = None
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None

    def _arm_flush(self) -> None:
        """Flush within `flush_s` even if the agent records nothing more (an idle agent)."""
        if self._flush_handle is not None:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._flush_handle = loop.call_later(self.flush_s, self._timed_flush)

    def _timed_flush(self) -> None:
        self._flush_handle = None
        if self._dirty:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and write everything out (not fsync: a host crash keeps what the kernel has)."""
        self._last_flush = time.monotonic()
        self._dirty = False
        if self._writer is None:
            return
        try:
            self._writer.flush()
        except OSError as e:
            self._failed(e)

    def close(self) -> None:
        """The instance ended (frozen, stopped, failed or its host went away): finish the segment."""
        if self.closed:
            return
        self.closed = True
        if self._flush_handle is not None:
            self._flush_handle.cancel()
            self._flush_handle = None
        try:
            self._finish()
        except OSError as e:
            self._failed(e)

    # ------------------------------------------------------------------ inputs and outputs

    def input(self, msg: ppb.PlaybackInput) -> None:
        if self.closed:
            return
        ns = time.time_ns()
        msg.seq = self.inputs
        msg.wall_ns = ns
        self.inputs += 1
        self._write(TOPIC_INPUT, msg.SerializeToString(), msg.seq, ns)

    def output(self, msg: ppb.PlaybackOutput) -> None:
        if self.closed:
            return
        ns = time.time_ns()
        msg.seq = self.outputs
        msg.after_input = self.inputs
        msg.wall_ns = ns
        self.outputs += 1
        self._write(TOPIC_OUTPUT, msg.SerializeToString(), msg.seq, ns)

    # ------------------------------------------------------------------ the tap (haa.sdk.context.AgentContext)

    def wrap_emit(self, emit: Callable[[pb.AgentToHost], None]) -> Callable[[pb.AgentToHost], None]:
        def recorded(frame: pb.AgentToHost) -> None:
            emit(frame)  # may raise (a frame too large): then it was not sent, and is not an output
            self.output(output_of(frame))

        return recorded

    def wrap_clock(self, clock: Clock) -> Clock:
        return _TapClock(clock, self)

    def wrap_random(self, rnd: random.Random) -> random.Random:
        return _TapRandom(rnd, self)

    def perf_counter(self, v: float) -> None:
        self.input(ppb.PlaybackInput(perf_counter=v))

    def thread_done(self, n: int) -> None:
        self.input(ppb.PlaybackInput(thread_done=n))

    def freeze_fed(self) -> None:
        self.input(ppb.PlaybackInput(freeze_fed=True))

    def item(self, kind: str, data: Any) -> None:
        """The mailbox worker took this item (haa.sdk.context.AgentContext._take_item)."""
        self.input(item_input(kind, data))

    def answer(self, req_id: int, ans: pb.HostToAgent.Answer | None) -> None:
        if ans is None:
            self.input(ppb.PlaybackInput(call_timeout=ppb.PlaybackInput.CallTimeout(req_id=req_id)))
        else:
            self.input(ppb.PlaybackInput(answer=ans))

    def reply(self, conv: int, env: pb.AgentMsg | None) -> None:
        if env is None:
            self.input(ppb.PlaybackInput(request_timeout=ppb.PlaybackInput.RequestTimeout(conv=conv)))
        else:
            self.input(ppb.PlaybackInput(reply=env))

    def external_call(self, source: str, method: str, request: bytes) -> int:
        self.external_calls += 1
        self.output(ppb.PlaybackOutput(external_call=ppb.PlaybackOutput.ExternalCall(
            source=source, method=method, call=self.external_calls, request=request)))
        return self.external_calls

    def external(self, ext: ppb.PlaybackInput.External) -> None:
        self.input(ppb.PlaybackInput(external=ext))

    def wrap_stub(self, source: str, service: Any, stub: Any) -> Any:
        from haa.sdk.external import RecordingStub

        return RecordingStub(self, source, service, stub)


def output_of(frame: pb.AgentToHost) -> ppb.PlaybackOutput:
    """The PlaybackOutput of a frame: the frame, or its digest when it is larger than DIGEST_OVER (not a log)."""
    kind = frame.WhichOneof("msg") or ""
    if kind == "log" or frame.ByteSize() <= DIGEST_OVER:
        return ppb.PlaybackOutput(frame=frame)
    data = frame.SerializeToString(deterministic=True)
    return ppb.PlaybackOutput(digest=ppb.PlaybackOutput.Digest(
        sha256=hashlib.sha256(data).digest(), size=len(data), kind=kind, dst=frame.sent.dst if kind == "sent" else ""))


def item_input(kind: str, data: Any) -> ppb.PlaybackInput:
    """The PlaybackInput of a mailbox item (haa.sdk.context.AgentContext's mailbox kinds)."""
    if kind == "msg":
        return ppb.PlaybackInput(message=data)
    if kind == "timer":
        return ppb.PlaybackInput(timer=ppb.PlaybackInput.TimerFired(timer_id=data.id))
    if kind == "watch":
        wid, event, key, value = data
        return ppb.PlaybackInput(watch=pb.HostToAgent.WatchEvent(watch_id=wid, event=event, key=key,
                                                                 has_value=value is not None, value=value or b""))
    if kind == "log_item":
        wid, index, item = data
        return ppb.PlaybackInput(log_item=pb.HostToAgent.WatchEvent(watch_id=wid, event="append", index=index,
                                                                    has_value=True, value=item))
    if kind == "begin":
        how, blob = data
        return ppb.PlaybackInput(begin=ppb.PlaybackInput.Begin(how=how, has_blob=blob is not None, blob=blob or b""))
    if kind == "resume":
        return ppb.PlaybackInput(resume=data)
    if kind == "freeze":
        return ppb.PlaybackInput(freeze=True)
    if kind == "stop":
        return ppb.PlaybackInput(stop=True)
    raise ValueError(f"unknown mailbox item {kind!r}")  # pragma: no cover - base.py's kinds are all above
