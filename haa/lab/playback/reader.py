"""Reading AgentPlayback recordings (docs/playback.md): MCAP segments written by `haa.sdk.recorder`.

A recording folder holds one folder per agent (its display name), and in it one or more segments per agent
instance: `<instance>-<segment>.mcap`, where an instance is one life of the agent on one host ("e<epoch>-
<host>-<start ns>"; a transfer or a recovery starts a new one, on the new host). A segment whose writer was
killed is read up to its last complete chunk (at most the last second before the crash): `Segment.truncated`.
"""

from __future__ import annotations

import contextlib
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from haa.files import FileError, check_regular
from haa.pb import playback_pb2 as ppb
from haa.sdk.recorder import FORMAT as FORMAT
from haa.sdk.recorder import MAX_SEGMENT_BYTES, SEGMENT_SLACK
from haa.sdk.recorder import SUFFIX as SUFFIX
from haa.sdk.recorder import TOPIC_INPUT as TOPIC_INPUT
from haa.sdk.recorder import TOPIC_INSTANCE as TOPIC_INSTANCE
from haa.sdk.recorder import TOPIC_OUTPUT as TOPIC_OUTPUT


class RecordingError(Exception):
    """A recording cannot be read (not a recording, no such agent, ...); the message is one line."""


class EmptySegment(RecordingError):
    """A segment whose writer died before its first message reached the disk (an instance killed as it
    started): nothing to read; `load` skips it."""


@dataclass
class Segment:
    path: Path
    header: ppb.PlaybackInstance
    inputs: list[ppb.PlaybackInput] = field(default_factory=list)
    outputs: list[ppb.PlaybackOutput] = field(default_factory=list)
    truncated: bool = False
    size: int = 0
    #: why reading stopped before the end when it was not the file ending (a writer that died leaves a file that
    #: ends early; a record that fails its CRC or does not parse is damage): "" for a whole or a cut segment
    damage: str = ""


@dataclass
class Instance:
    """One life of an agent (its Init: id, name, epoch, host), possibly split into several segments."""

    key: str
    segments: list[Segment] = field(default_factory=list)

    @property
    def init(self) -> ppb.PlaybackInstance:
        return self.segments[0].header

    @property
    def inputs(self) -> list[ppb.PlaybackInput]:
        return [i for s in self.segments for i in s.inputs]

    @property
    def outputs(self) -> list[ppb.PlaybackOutput]:
        return [o for s in self.segments for o in s.outputs]

    @property
    def truncated(self) -> bool:
        return any(s.truncated for s in self.segments)

    @property
    def damage(self) -> str:
        """The first damaged segment's damage (`Segment.damage`), "" if none."""
        return next((f"{s.path.name}: {s.damage}" for s in self.segments if s.damage), "")


def read_segment(path: Path, headers_only: bool = False) -> Segment:
    """Read one segment; RecordingError if it is not an AgentPlayback MCAP file, or holds more than
    `MAX_SEGMENT_BYTES` + `SEGMENT_SLACK` bytes of messages (the most a recorder writes in one)."""
    path = Path(path)
    try:
        check_regular(path)
    except FileError as e:
        raise RecordingError(str(e)) from None
    most = MAX_SEGMENT_BYTES + SEGMENT_SLACK
    taken = 0
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as e:
        raise RecordingError(f"{path}: {e.strerror or e}") from None
    topics: dict[int, str] = {}
    header: ppb.PlaybackInstance | None = None
    inputs: list[ppb.PlaybackInput] = []
    outputs: list[ppb.PlaybackOutput] = []
    truncated = False
    damage = ""
    with f:
        size = os.fstat(f.fileno()).st_size
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    taken += len(rec.data)
                    if taken > most:
                        raise RecordingError(f"{path}: more than {most >> 20} MiB of messages in one segment "
                                             "(MAX_SEGMENT_BYTES + SEGMENT_SLACK): not one a recorder wrote")
                    topic = topics.get(rec.channel_id)
                    if topic == TOPIC_INSTANCE:
                        header = ppb.PlaybackInstance.FromString(rec.data)
                        if headers_only:
                            break
                    elif topic == TOPIC_INPUT:
                        inputs.append(ppb.PlaybackInput.FromString(rec.data))
                    elif topic == TOPIC_OUTPUT:
                        outputs.append(ppb.PlaybackOutput.FromString(rec.data))
        except RecordingError:
            raise
        except (McapError, EOFError, ValueError, OSError) as e:
            if header is None and isinstance(e, EndOfFile | EOFError):
                raise EmptySegment(f"{path}: cut before its first message") from None
            if header is None:
                raise RecordingError(f"{path}: not a readable AgentPlayback recording ({type(e).__name__}: {e})") \
                    from None
            truncated = True  # the writer died: everything up to its last complete chunk is here
            if not isinstance(e, EndOfFile | EOFError):
                damage = f"{type(e).__name__}: {e}"[:200]
        except Exception as e:  # a decode error inside a damaged chunk (zstd, protobuf)
            if header is None and isinstance(e, struct.error):  # the mcap reader's short read of a cut file
                raise EmptySegment(f"{path}: cut before its first message") from None
            if header is None:
                raise RecordingError(f"{path}: not a readable AgentPlayback recording ({type(e).__name__}: {e})") \
                    from None
            truncated = True
            damage = f"{type(e).__name__}: {e}"[:200]
    if header is None:
        raise RecordingError(f"{path}: no {TOPIC_INSTANCE} message (not an AgentPlayback recording)")
    if header.format != FORMAT:
        raise RecordingError(f"{path}: format {header.format!r}, this haactl reads {FORMAT!r}")
    return Segment(path, header, inputs, outputs, truncated, size, damage)


def segment_files(root: Path) -> list[Path]:
    """Every segment under `root` (a folder of agent folders, one agent's folder, or one file)."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise RecordingError(f"{root}: no such file or folder")
    return sorted(p for p in root.rglob("*" + SUFFIX) if p.is_file())


def load(root: Path, agent: str | None = None, headers_only: bool = False) -> dict[str, list[Instance]]:
    """Agent name -> its instances in the order they began, each with its segments in order. `agent` (a display
    name or an id, or a prefix of the id) keeps only that agent."""
    files = segment_files(root)
    if not files:
        raise RecordingError(f"{root}: no recording segments (*{SUFFIX})")
    instances: dict[tuple[str, str], Instance] = {}
    empty = 0  # segments of the agent's folder cut before their first message
    for p in files:
        if agent is not None and Path(root).is_dir() and p.parent.name != agent:
            # the folder is the display name: skip other agents' files without reading them (an id is
            # matched from the header below)
            with contextlib.suppress(RecordingError):
                seg = read_segment(p, headers_only=True)
                if not seg.header.init.agent_id.startswith(agent):
                    continue
        try:
            seg = read_segment(p, headers_only=headers_only)
        except EmptySegment:
            empty += agent is not None and Path(root).is_dir() and p.parent.name == agent
            continue
        init = seg.header.init
        if agent is not None and agent not in (init.name,) and not init.agent_id.startswith(agent):
            continue
        key = (init.name, seg.header.instance)
        instances.setdefault(key, Instance(seg.header.instance)).segments.append(seg)
    out: dict[str, list[Instance]] = {}
    for (name, _), inst in instances.items():
        inst.segments.sort(key=lambda s: s.header.segment)
        out.setdefault(name, []).append(inst)
    for lst in out.values():
        lst.sort(key=lambda i: (i.init.wall_start_ns, i.key))
    if agent is not None and not out:
        if empty:
            raise RecordingError(f"{root}: every segment of agent {agent!r} ({empty}) was cut before its first "
                                 "message (its writer died as the instance started): nothing to replay")
        raise RecordingError(f"{root}: no recording of agent {agent!r}")
    return dict(sorted(out.items(), key=lambda kv: _name_key(kv[0])))


def _name_key(name: str) -> tuple[object, ...]:
    """"A2.10" after "A2.9": numeric parts compared as numbers."""
    parts: list[object] = []
    for p in name.lstrip("A").split("."):
        parts.append((0, int(p)) if p.isdigit() else (1, p))
    return tuple(parts)


@dataclass
class AgentSummary:
    """One agent of a recording, as `haactl record ls` shows it."""

    name: str
    agent_id: str
    type_name: str
    instances: int
    segments: int
    inputs: int
    outputs: int
    first_ns: int
    last_ns: int
    bytes: int
    hosts: list[str]
    truncated: int  # segments whose writer died

    @property
    def span_s(self) -> float:
        return max(0.0, (self.last_ns - self.first_ns) / 1e9)


def summarize(root: Path, agent: str | None = None) -> list[AgentSummary]:
    """Per agent of the recording at `root`: instances, segments, inputs, outputs, time span, bytes on disk."""
    rows = []
    for name, insts in load(root, agent).items():
        segs = [s for i in insts for s in i.segments]
        stamps = [m.wall_ns for s in segs for m in s.inputs] + [m.wall_ns for s in segs for m in s.outputs]
        stamps = stamps or [insts[0].init.wall_start_ns]
        hosts: list[str] = []
        for i in insts:
            if i.init.init.host not in hosts:
                hosts.append(i.init.init.host)
        init = insts[-1].init.init
        rows.append(AgentSummary(name, init.agent_id, init.type_name, len(insts), len(segs),
                                 sum(len(s.inputs) for s in segs), sum(len(s.outputs) for s in segs),
                                 min(stamps), max(stamps), sum(s.size for s in segs), hosts,
                                 sum(1 for s in segs if s.truncated)))
    return rows
