"""haa.sdk.channel: length-prefixed protobuf frames over a unix socketpair, and its errors."""

from __future__ import annotations

import asyncio
import fcntl
import socket
import struct
import termios

import pytest
from helpers import run, until

from haa.pb import agent_pb2 as pb
from haa.sdk.channel import Channel, ChannelError, FrameTooLarge


async def pair(max_frame: int = 1 << 20) -> tuple[Channel, Channel]:
    a, b = socket.socketpair()
    host = await Channel.open(a, pb.AgentToHost, max_frame=max_frame)
    agent = await Channel.open(b, pb.HostToAgent, max_frame=max_frame)
    return host, agent


def sent_all(chan: Channel) -> bool:
    """The peer has half-closed (the agent's `runner._linger`): all it sent is in `chan`'s buffer, unread."""
    return chan.reader._eof  # asyncio.StreamReader has no public "EOF received" while data is still buffered


def unread(chan: Channel) -> int:
    """Bytes waiting in `chan`'s socket, not yet taken by its transport (FIONREAD)."""
    sock = chan.writer.transport.get_extra_info("socket")
    return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]


def test_frames_both_ways_in_order():
    async def main():
        host, agent = await pair()
        for i in range(200):
            host.send(pb.HostToAgent(deliver=pb.AgentMsg(src="x", dst="y", payload=bytes(i) * 50, conv=i)))
            agent.send(pb.AgentToHost(heartbeat=pb.AgentToHost.Heartbeat(handled=i)))
        for i in range(200):
            m = await agent.recv()
            assert m.WhichOneof("msg") == "deliver" and m.deliver.conv == i and len(m.deliver.payload) == 50 * i
            h = await host.recv()
            assert h.heartbeat.handled == i
        host.close()
        assert await agent.recv() is None  # clean end of stream between frames
        agent.close()

    run(main())


def test_send_refuses_oversized_frame_before_writing():
    async def main():
        host, agent = await pair(max_frame=1000)
        with pytest.raises(FrameTooLarge, match=r"frame of \d+ bytes \(deliver\) exceeds the limit of 1000 bytes"):
            host.send(pb.HostToAgent(deliver=pb.AgentMsg(payload=b"x" * 2000)))
        assert host.frames_out == 0
        host.send(pb.HostToAgent(start=pb.HostToAgent.Start()))
        m = await agent.recv()
        assert m.WhichOneof("msg") == "start"
        host.close()
        agent.close()

    run(main())


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (struct.pack(">I", 0x7FFFFFFF), r"frame of 2147483647 bytes exceeds the limit of 4096 bytes"),
        (struct.pack(">I", 3) + b"\xff\xff\xff", r"malformed frame \(3 bytes\)"),
        (struct.pack(">I", 0), r"malformed frame \(0 bytes\): no known message in it"),
        (struct.pack(">I", 2) + b"\x78\x01", r"no known message in it"),  # field 15 varint: unknown field only
        (b"\x00\x00", r"closed in the middle of a frame \(got 2 of 4 header bytes\)"),
        (struct.pack(">I", 10) + b"abc", r"closed in the middle of a frame \(got 3 of 10 body bytes\)"),
    ],
)
def test_bad_frames_are_clear_errors(raw, message):
    async def main():
        a, b = socket.socketpair()
        host = await Channel.open(a, pb.AgentToHost, max_frame=4096)
        b.sendall(raw)
        b.close()
        with pytest.raises(ChannelError, match=message):
            await host.recv()
        host.close()

    run(main())


def test_send_after_close_is_a_channel_error():
    async def main():
        host, agent = await pair()
        host.close()
        with pytest.raises(ChannelError, match="closed"):
            host.send(pb.HostToAgent(start=pb.HostToAgent.Start()))
        agent.close()

    run(main())


def test_max_frame_is_validated():
    async def main():
        a, b = socket.socketpair()
        with pytest.raises(ValueError, match="max_frame"):
            await Channel.open(a, pb.AgentToHost, max_frame=0)
        a.close()
        b.close()

    run(main())


def test_the_frozen_frame_survives_host_writes_after_the_freeze():
    """An agent that has sent Frozen waits for the host to close the channel (haa.sdk.runner._linger): a
    busy host may still write to it (watch events, answers) before it reads Frozen, and a write to a closed
    socket (EPIPE) made the host's transport drop the unread Frozen frame: 'channel error: read failed: [Errno
    32] Broken pipe', a transfer turned into a crash (SupervisorSLAM as its host left the group)."""
    from haa.sdk import registry, runner

    async def main():
        registry.load_all()
        a, b = socket.socketpair()
        host = await Channel.open(a, pb.AgentToHost)
        agent = asyncio.ensure_future(runner.serve(b))
        host.send(pb.HostToAgent(init=pb.HostToAgent.Init(agent_id="x1", name="A1", type_name="counter", epoch=1)))
        assert (await host.recv()).WhichOneof("msg") == "hello"
        host.send(pb.HostToAgent(start=pb.HostToAgent.Start()))
        host.send(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="start")))
        while (await host.recv()).WhichOneof("msg") != "ready":
            pass
        host.send(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        # the agent packs its state, sends Frozen and half-closes; the host has not read it yet
        await until(lambda: sent_all(host), what="the agent's Frozen and half-close")
        for _ in range(50):
            host.send(pb.HostToAgent(watch_event=pb.HostToAgent.WatchEvent(watch_id=1, event="append", key="k")))
            await asyncio.sleep(0.005)  # writes spread over time, as a busy host's are
        kinds = []
        while (m := await host.recv()) is not None:
            kinds.append(m.WhichOneof("msg"))
            if kinds[-1] == "frozen":
                break
        host.close()
        return kinds, await asyncio.wait_for(agent, 5)

    kinds, code = run(main())
    assert kinds[-1] == "frozen" and code == 0, kinds


def test_frames_buffered_before_a_reset_are_received_before_the_end():
    """A peer that closes with unread input resets the connection; the frames it sent before are in our
    reader's buffer and come out first (the stream reader raised the reset at once: 'connection reset in the
    middle of a frame', the frames lost)."""

    async def main():
        host, agent = await pair()
        agent.writer.transport.pause_reading()  # what the host writes stays unread in the agent's socket
        for _ in range(20):
            host.send(pb.HostToAgent(watch_event=pb.HostToAgent.WatchEvent(watch_id=1, event="append", key="k")))
        await until(lambda: unread(agent) == host.bytes_out, what="the host's frames unread in the agent's socket")
        agent.send(pb.AgentToHost(log=pb.AgentToHost.Log(event="last words")))
        agent.send(pb.AgentToHost(error=pb.AgentToHost.Error(message="boom")))
        await agent.drain()
        agent.close()
        await agent.wait_closed()
        await until(lambda: host.reader.exception() is not None, what="the reset at the host")
        assert isinstance(host.reader.exception(), ConnectionResetError)
        kinds = []
        while (m := await host.recv()) is not None:
            kinds.append(m.WhichOneof("msg"))
        host.close()
        return kinds

    assert run(main()) == ["log", "error"]


def test_the_error_of_an_agent_that_fails_at_start_survives_host_writes():
    """An agent that fails at start (here: its state does not unpack) half-closes and waits for the host to close
    (haa.sdk.runner._linger) as after Frozen: had it closed at once, the host's next write broke the pipe
    and its transport dropped the unread Error frame ('read failed: [Errno 32] Broken pipe', every time here)."""
    from haa.sdk import registry, runner

    async def main():
        registry.load_all()
        a, b = socket.socketpair()
        host = await Channel.open(a, pb.AgentToHost)
        agent = asyncio.ensure_future(runner.serve(b))
        host.send(pb.HostToAgent(init=pb.HostToAgent.Init(agent_id="x1", name="A1", type_name="counter", epoch=1)))
        assert (await host.recv()).WhichOneof("msg") == "hello"
        host.send(pb.HostToAgent(thaw=pb.HostToAgent.Thaw(state=b"not json")))
        host.send(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="thaw")))
        # the agent fails, reports it and half-closes; the host has not read it yet
        await until(lambda: sent_all(host), what="the agent's Error and half-close")
        for _ in range(50):
            host.send(pb.HostToAgent(watch_event=pb.HostToAgent.WatchEvent(watch_id=1, event="append", key="k")))
            await asyncio.sleep(0.002)  # writes spread over time, as a busy host's are
        kinds = []
        while (m := await host.recv()) is not None:
            kinds.append((m.WhichOneof("msg"), m.error.message if m.WhichOneof("msg") == "error" else ""))
        host.close()
        return kinds, await asyncio.wait_for(agent, 5)

    kinds, code = run(main())
    assert code == 1 and kinds[-1][0] == "error" and "unpack_state raised" in kinds[-1][1], kinds
