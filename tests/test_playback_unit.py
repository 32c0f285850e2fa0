"""AgentPlayback's recorder and reader without a cluster (docs/playback.md): segments rotate by size and
join up again, an idle recorder's inputs reach the disk within about a second (a crash loses at most that),
a cut file reads up to its last chunk, random draws and clock reads replay to the same values, the schemas
are the protobuf FileDescriptorSets Foxglove reads, and bad input gets one clear line."""

from __future__ import annotations

import asyncio
import random
import shutil
import time
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from typer.testing import CliRunner

from haa.lab.playback import reader
from haa.lab.playback.replay import ReplayFeed, ReplayStopped
from haa.pb import agent_pb2 as pb
from haa.pb import playback_pb2 as ppb
from haa.sdk.base import WALL_CLOCK
from haa.sdk.recorder import Recorder
from haactl.main import app

INIT = pb.HostToAgent.Init(agent_id="0f0e0d0c-aaaa-bbbb-cccc-000000000001", name="A7.2", type_name="probe",
                           config=b"{}", epoch=3, host="h2")


def _draws(rnd: random.Random) -> list:
    xs = list(range(20))
    rnd.shuffle(xs)
    return [rnd.random(), rnd.uniform(-1, 1), rnd.randint(0, 10**12), rnd.choice("abcdefgh"), xs,
            rnd.gauss(0, 1), rnd.randbytes(5), rnd.sample(range(1000), 3)]


def test_segments_rotate_by_size_and_read_back_in_order(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, INIT, segment_bytes=4096)
    for k in range(600):
        rec.input(ppb.PlaybackInput(clock=float(k)))
        if k % 7 == 0:
            rec.output(ppb.PlaybackOutput(frame=pb.AgentToHost(sent=pb.AgentMsg(dst="x", payload=b"p" * 40))))
    rec.close()
    files = sorted((tmp_path / "A7.2").iterdir())
    assert len(files) >= 3 and all(f.name.startswith("e3-h2-") for f in files), files
    (inst,) = reader.load(tmp_path)["A7.2"]
    assert [i.seq for i in inst.inputs] == list(range(600))
    assert [i.clock for i in inst.inputs] == [float(k) for k in range(600)]
    assert [o.after_input for o in inst.outputs] == [k + 1 for k in range(0, 600, 7)]
    assert not inst.truncated and inst.init.init == INIT
    assert all(s.header.first_input == s.inputs[0].seq for s in inst.segments if s.inputs)
    (row,) = reader.summarize(tmp_path)
    assert (row.name, row.instances, row.segments, row.inputs) == ("A7.2", 1, len(files), 600)


def test_an_idle_recorder_flushes_within_a_second_and_a_cut_file_reads_to_its_last_chunk(tmp_path: Path) -> None:
    async def go() -> tuple[float, int]:
        rec = Recorder(tmp_path, INIT)
        for k in range(50):
            rec.input(ppb.PlaybackInput(clock=float(k)))
        t0 = time.monotonic()
        path = next((tmp_path / "A7.2").iterdir())
        while time.monotonic() - t0 < 10:  # the agent records nothing more; its file is still open
            seg = reader.read_segment(path)
            if len(seg.inputs) == 50:
                break
            await asyncio.sleep(0.05)
        took = time.monotonic() - t0
        n = len(reader.read_segment(path).inputs)
        rec.close()
        return took, n

    took, n = asyncio.run(go())
    assert n == 50 and took < 3.0, (n, took)  # FLUSH_S = 1 s (+ a loaded machine's slack)
    path = next((tmp_path / "A7.2").iterdir())
    whole = path.read_bytes()
    seg = reader.read_segment(path)
    assert not seg.truncated and len(seg.inputs) == 50
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole[: len(whole) - 40])  # the summary and footer lost, as if the writer had died
    seg = reader.read_segment(cut)
    assert seg.truncated and [i.clock for i in seg.inputs] == [float(k) for k in range(50)]


def test_random_draws_and_clock_reads_replay_to_the_same_values(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, INIT)
    rnd = rec.wrap_random(random.Random("seed/A7.2/3"))
    clock = rec.wrap_clock(WALL_CLOCK)
    live = _draws(rnd)
    t = clock.now()
    rec.close()
    assert live == _draws(random.Random("seed/A7.2/3"))  # recording does not change what the agent draws
    (inst,) = reader.load(tmp_path)["A7.2"]

    async def again() -> tuple[list, float, ReplayFeed]:
        feed = ReplayFeed(inst)
        return _draws(feed.wrap_random(random.Random(0))), feed.wrap_clock(WALL_CLOCK).now(), feed

    got, t2, feed = asyncio.run(again())
    assert got == live and t2 == t and feed.pos == len(inst.inputs)

    async def diverge() -> None:
        ReplayFeed(inst).wrap_clock(WALL_CLOCK).now()  # live, the first input was a random draw

    with pytest.raises(ReplayStopped):
        asyncio.run(diverge())


def test_schemas_are_protobuf_file_descriptor_sets(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, INIT)
    rec.input(ppb.PlaybackInput(clock=1.0))
    rec.close()
    path = next((tmp_path / "A7.2").iterdir())
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    names = {}
    for s in summary.schemas.values():
        assert s.encoding == "protobuf"
        fds = descriptor_pb2.FileDescriptorSet.FromString(s.data)
        names[s.name] = {m.name for fd in fds.file for m in fd.message_type}
    assert set(names) == {"haa.v1.PlaybackInstance", "haa.v1.PlaybackInput", "haa.v1.PlaybackOutput"}
    assert {c.topic for c in summary.channels.values()} == {reader.TOPIC_INSTANCE, reader.TOPIC_INPUT,
                                                             reader.TOPIC_OUTPUT}


def test_bad_input_gets_one_line(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(reader.RecordingError, match="not a readable AgentPlayback recording"):
        reader.read_segment(junk)
    cli = CliRunner()
    res = cli.invoke(app, ["record", "ls", str(tmp_path / "nowhere")])
    assert res.exit_code == 1 and res.output.strip().endswith("no such file or folder"), res.output
    (tmp_path / "empty").mkdir()
    res = cli.invoke(app, ["replay", str(tmp_path / "empty"), "--agent", "A1"])
    assert res.exit_code == 2 and "no recording segments" in res.output and len(res.output.splitlines()) == 1
    rec = Recorder(tmp_path / "r", INIT)
    rec.close()
    shutil.copy(junk, tmp_path / "r" / "A7.2" / "zz.mcap")
    res = cli.invoke(app, ["record", "ls", str(tmp_path / "r")])
    assert res.exit_code == 1 and "zz.mcap: not a readable AgentPlayback recording" in res.output, res.output


def test_a_segment_beyond_what_a_recorder_writes_or_a_fifo_is_refused(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    monkeypatch.setattr(reader, "MAX_SEGMENT_BYTES", 2048)
    monkeypatch.setattr(reader, "SEGMENT_SLACK", 1024)
    rec = Recorder(tmp_path, INIT, segment_bytes=1 << 20)  # one segment, larger than the reader's bound
    for k in range(200):
        rec.input(ppb.PlaybackInput(clock=float(k)))
    rec.close()
    (seg,) = (tmp_path / "A7.2").iterdir()
    with pytest.raises(reader.RecordingError, match=r"more than 0 MiB of messages in one segment"):
        reader.read_segment(seg)
    os.mkfifo(tmp_path / "f.mcap")  # nobody writes: refused unopened, not waited on
    with pytest.raises(reader.RecordingError, match=r"f\.mcap: is a FIFO"):
        reader.read_segment(tmp_path / "f.mcap")


def test_haa_hostd_record_dir_option(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from haa.hostd.daemon import load_settings

    token = tmp_path / "token"
    token.write_text("t" * 32)
    base = ["--name", "h1", "--listen", "127.0.0.1:1", "--token-file", str(token)]
    monkeypatch.delenv("HAA_RECORD_DIR", raising=False)
    assert load_settings(base).record_dir is None
    assert load_settings([*base, "--record-dir", str(tmp_path / "rec")]).record_dir == tmp_path / "rec"
    monkeypatch.setenv("HAA_RECORD_DIR", str(tmp_path / "env"))  # the agents' variable is the option's too
    assert load_settings(base).record_dir == tmp_path / "env"


def test_the_host_injects_the_recorder_as_the_agents_tap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """An agent process that does not record never imports the recorder (or mcap): the runner opens the tap the
    host names in HAA_AGENT_TAP."""
    from haa.hostd.daemon import RECORDER_TAP
    from haa.sdk import recorder
    from haa.sdk.tap import TAP_ENV, load_factory, open_tap

    monkeypatch.delenv(TAP_ENV, raising=False)
    monkeypatch.setenv("HAA_RECORD_DIR", str(tmp_path / "rec"))
    assert open_tap(INIT) is None  # no factory named: nothing recorded, whatever HAA_RECORD_DIR says
    assert load_factory(RECORDER_TAP) is recorder.from_env
    monkeypatch.setenv(TAP_ENV, RECORDER_TAP)
    tap = open_tap(INIT)
    assert isinstance(tap, Recorder) and tap.dir == tmp_path / "rec" / "A7.2"
    tap.close()
    for bad in ("haa.sdk.recorder", "haa.sdk.recorder:nothing", "haa.no_such_module:f"):
        monkeypatch.setenv(TAP_ENV, bad)
        assert open_tap(INIT) is None  # a broken name stops the recording, never the agent
        assert "agent A7.2: no recording (HAA_AGENT_TAP=" in capsys.readouterr().err


def test_where_a_mission_records(tmp_path: Path) -> None:
    from haa.mission.runner import record_folder

    out = tmp_path / "out"
    assert record_folder(False, out, None) is None
    assert record_folder(True, out, None) == out / "recording"
    assert record_folder("rec/a", out, None) == out / "rec" / "a"
    assert record_folder("/abs/rec", out, None) == Path("/abs/rec")
    assert record_folder(False, out, Path("cli")) == Path("cli").absolute()  # haactl --record wins


def test_a_large_output_is_kept_as_its_digest_and_still_compared_byte_for_byte(tmp_path: Path) -> None:
    rec = Recorder(tmp_path, INIT)
    sent: list = []
    emit = rec.wrap_emit(sent.append)
    big = pb.AgentToHost(sent=pb.AgentMsg(src=INIT.agent_id, dst="sensor", payload=random.Random(1).randbytes(256_000)))
    small = pb.AgentToHost(sent=pb.AgentMsg(src=INIT.agent_id, dst="sensor", payload=b"hello"))
    emit(big)
    emit(small)
    rec.close()
    assert sent == [big, small]  # what the host gets is untouched
    (inst,) = reader.load(tmp_path)["A7.2"]
    assert [o.WhichOneof("output") for o in inst.outputs] == ["digest", "frame"]
    assert inst.outputs[0].digest.size == big.ByteSize() and inst.outputs[0].digest.dst == "sensor"
    assert sum(f.stat().st_size for f in (tmp_path / "A7.2").iterdir()) < 100_000  # not the 256 kB frame

    async def check(frames: list) -> ReplayFeed:
        feed = ReplayFeed(inst)
        out = feed.wrap_emit(None)
        for f in frames:
            out(f)
        return feed

    assert asyncio.run(check([big, small])).out_pos == 2
    changed = pb.AgentToHost()
    changed.CopyFrom(big)
    changed.sent.payload = big.sent.payload[:-1] + b"\xff"
    with pytest.raises(ReplayStopped, match="output 0"):
        asyncio.run(check([changed]))


def test_a_damaged_segment_says_so_and_a_folder_of_cut_segments_says_why_nothing_replays(tmp_path: Path) -> None:
    """A writer that died leaves a file that ends early: "cut". A record that fails its CRC is damage, and is
    named as such, not passed off as a cut; an agent whose every segment was cut before its first message is
    not "no recording" but an instance killed as it started."""
    rec = Recorder(tmp_path, INIT, segment_bytes=4096)
    for k in range(300):
        rec.input(ppb.PlaybackInput(clock=float(k)))
    rec.close()
    path = sorted((tmp_path / "A7.2").iterdir())[0]
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[-1]  # (the first holds the instance header: without it nothing is readable)
    mid = chunk.chunk_start_offset + chunk.chunk_length // 2  # inside the last chunk's compressed records
    data = bytearray(path.read_bytes())
    data[mid:mid + 8] = b"\xde\xad\xbe\xef" * 2
    bad = tmp_path / "bad" / "A7.2"
    bad.mkdir(parents=True)
    (bad / path.name).write_bytes(bytes(data))
    seg = reader.read_segment(bad / path.name)
    assert seg.truncated and "CRC" in seg.damage, seg.damage
    r = CliRunner().invoke(app, ["replay", str(tmp_path / "bad"), "--agent", "A7.2"])
    assert "damaged" in r.output and "writer died" not in r.output, r.output
    cut = tmp_path / "cut" / "A7.2"
    cut.mkdir(parents=True)
    (cut / path.name).write_bytes(path.read_bytes()[:20])
    r = CliRunner().invoke(app, ["replay", str(tmp_path / "cut"), "--agent", "A7.2"])
    assert r.exit_code == 2 and "cut before its first message" in r.output, r.output
