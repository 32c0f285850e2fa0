"""The agent process: one asyncio loop that runs one agent instance and talks to its host over one channel.

The fork server (`haa.sdk.forkserver`) forks and calls `run_child(fd)` with the agent's end of the
channel, or, in cold-start mode, execs `python -m haa.sdk.runner --fd N`. The conversation with the host
(proto/haa/pb/agent.proto):

1. host -> `Init` (id, name, type, config, epoch, parent, heartbeat period, max frame);
2. agent: looks the type up in the registry and builds the object -> `Hello` (or `Error` and exit 2 for
   an unknown type, exit 1 if the constructor raised);
3. then three tasks until the agent ends: the *reader* feeds every host frame to the `AgentContext` in
   channel order; the *worker* (`AgentContext.run`) handles the mailbox one item at a time; the
   *heartbeat* sends `Heartbeat` every period (from the same loop, so a blocked loop stops it: that is how
   the host detects a hung agent).

Exit codes: 0 = frozen or stopped normally, 1 = a fatal agent error (reported in an `Error` frame first),
2 = bad Init (unknown type, wrong first frame), 3 = the host closed the channel, 4 = the channel broke
(malformed frame from the host; logged on stderr). The event loop is uvloop unless HAA_EVENT_LOOP=asyncio,
as in haa-hostd.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import socket
import sys
from collections.abc import Coroutine
from typing import Any, TypeVar

from haa.pb import agent_pb2 as pb
from haa.sdk import registry
from haa.sdk import tap as agent_tap
from haa.sdk.channel import DEFAULT_MAX_FRAME, Channel, ChannelError
from haa.sdk.context import AgentContext, AgentFatal
from haa.sdk.sched import AsyncioScheduler

#: how long a new process waits for its Init frame
INIT_TIMEOUT = 30.0
#: after Frozen / Stopped, how long the process waits for the host to close the channel (`_linger`)
LINGER_S = 3.0

T = TypeVar("T")

EXIT_OK = 0
EXIT_FATAL = 1
EXIT_BAD_INIT = 2
EXIT_HOST_CLOSED = 3
EXIT_CHANNEL_ERROR = 4

# the fork server imports this module before it forks: the host's tap (haa.sdk.tap; the recorder when
# haa-hostd records) is imported once there, not in every agent process
agent_tap.preload()


def run_loop(coro: Coroutine[Any, Any, T]) -> T:
    """Run the coroutine on uvloop (default) or asyncio (HAA_EVENT_LOOP=asyncio)."""
    if os.environ.get("HAA_EVENT_LOOP", "uvloop") != "asyncio":
        try:
            import uvloop
        except ImportError:  # pragma: no cover - uvloop is a dependency
            pass
        else:
            return uvloop.run(coro)
    return asyncio.run(coro)


def run_child(fd: int) -> int:
    """Run one agent on channel socket `fd` (a connected unix stream socket); returns the exit code."""
    sock = socket.socket(fileno=fd)
    return run_loop(serve(sock))


async def serve(sock: socket.socket) -> int:
    """The agent process's main coroutine (module docstring); returns the exit code."""
    chan = await Channel.open(sock, pb.HostToAgent, max_frame=DEFAULT_MAX_FRAME)
    code = EXIT_FATAL
    try:
        code = await _serve(chan)
        return code
    finally:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(chan.drain(), 5.0)
        if code not in (EXIT_HOST_CLOSED, EXIT_CHANNEL_ERROR):  # also after a failure: its Error frame must arrive
            await _linger(chan)
        chan.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(chan.wait_closed(), 1.0)


async def _linger(chan: Channel[pb.HostToAgent]) -> None:
    """Frozen / Stopped is sent: close only once the host has. Until it has read that frame the host may still
    write to us (a watch event, the answer to a call made beside the mailbox); had we closed, its write would
    fail (EPIPE) and its transport, failing, would drop what it had not read yet — the Frozen frame, turning a
    transfer into a crash (seen: SupervisorSLAM as its host left the group). So: half-close (the host reads
    our frames, then the end of the stream) and read, discarding, until the host closes or LINGER_S. The same
    after a fatal error: an agent that failed at start, its host still writing to it, lost its Error frame
    (and the frames before it) to the host's broken pipe (tests/test_agent_channel.py)."""
    with contextlib.suppress(Exception):
        chan.writer.write_eof()
    loop = asyncio.get_running_loop()
    end = loop.time() + LINGER_S
    with contextlib.suppress(Exception):
        while (left := end - loop.time()) > 0:
            if await asyncio.wait_for(chan.recv(), left) is None:
                return


def _error(chan: Channel[pb.HostToAgent], message: str) -> None:
    with contextlib.suppress(Exception):
        chan.send(pb.AgentToHost(error=pb.AgentToHost.Error(message=message)))


async def _serve(chan: Channel[pb.HostToAgent]) -> int:
    try:
        first = await asyncio.wait_for(chan.recv(), INIT_TIMEOUT)
    except (ChannelError, TimeoutError) as e:
        print(f"agent pid {os.getpid()}: no Init frame: {e}", file=sys.stderr)
        return EXIT_BAD_INIT
    if first is None:
        return EXIT_HOST_CLOSED
    if first.WhichOneof("msg") != "init":
        _error(chan, f"the first frame must be init, got {first.WhichOneof('msg')}")
        return EXIT_BAD_INIT
    init = first.init
    if init.max_frame:
        chan.max_frame = init.max_frame
    try:
        cls = registry.get(init.type_name)
    except (LookupError, TypeError, ValueError) as e:
        _error(chan, str(e))
        return EXIT_BAD_INIT
    # AgentPlayback (docs/playback.md): the tap the host injects (HAA_AGENT_TAP, haa.sdk.tap) records every
    # input and output here
    tap = agent_tap.open_tap(init)
    try:
        # the process's asyncio loop and wall clock (haa.sdk.sched; the simulator injects a VirtualScheduler)
        ctx = AgentContext(init, cls, chan.send, drain=chan.drain, send_raw=chan.send_raw, tap=tap,
                           scheduler=AsyncioScheduler())
    except Exception as e:
        if tap is not None:
            tap.close()
        _error(chan, f"{cls.__name__}.__init__ raised {type(e).__name__}: {e}")
        return EXIT_FATAL
    chan.send(pb.AgentToHost(hello=pb.AgentToHost.Hello(pid=os.getpid(), type_name=init.type_name)))
    period = init.heartbeat_period if init.heartbeat_period > 0 else 0.5

    async def heartbeat() -> None:
        while True:
            await asyncio.sleep(period)
            chan.send(pb.AgentToHost(heartbeat=pb.AgentToHost.Heartbeat(queued=ctx.queued, handled=ctx.handled)))

    async def read() -> int:
        while True:
            try:
                msg = await chan.recv()
            except ChannelError as e:
                print(f"agent {init.name} ({init.agent_id}): channel error: {e}", file=sys.stderr)
                return EXIT_CHANNEL_ERROR
            if msg is None:
                return EXIT_HOST_CLOSED
            try:
                ctx.feed(msg)
            except AgentFatal as e:
                ctx._fatal(str(e))
                return EXIT_FATAL

    worker = asyncio.create_task(ctx.run(), name="agent-worker")
    reader = asyncio.create_task(read(), name="agent-reader")
    beat = asyncio.create_task(heartbeat(), name="agent-heartbeat")
    try:
        done, _ = await asyncio.wait({worker, reader}, return_when=asyncio.FIRST_COMPLETED)
        if worker in done:
            try:
                code = worker.result()
            except Exception as e:
                _error(chan, f"agent runtime error: {type(e).__name__}: {e}")
                code = EXIT_FATAL
        else:
            code = reader.result()
    finally:
        for t in (worker, reader, beat):
            t.cancel()
        await asyncio.gather(worker, reader, beat, return_exceptions=True)
        if tap is not None:
            tap.close()
    return code


def main(argv: list[str] | None = None) -> int:
    """Cold start: `python -m haa.sdk.runner --fd N` (the fork server's exec mode)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fd", type=int, required=True, help="inherited channel socket")
    args = ap.parse_args(argv)
    errors = registry.load_all()
    for e in errors:
        print(f"agent registry: {e}", file=sys.stderr)
    return run_child(args.fd)


if __name__ == "__main__":
    sys.exit(main())
