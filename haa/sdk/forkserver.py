"""The fork server ("zygote"): a small process that preloads the agent runtime and every agent type, then
forks one child per agent on request, so that starting an agent costs a fork instead of an interpreter
start and its imports (AP-4: spawn <= 0.5 s end to end; the fork + ready part here is a few ms).

Why a separate process: haa-hostd runs grpc's threads and an event loop, and forking a threaded process is
unsafe (a child can inherit a lock some other thread held). The zygote is single-threaded and never runs an
event loop, so its children start clean; each builds its own loop (`haa.sdk.runner`).

Protocol (proto/haa/pb/agent.proto, one message per packet on a SOCK_SEQPACKET socketpair):

* zygote -> host, once: `ForkServerEvent.ready` with the registered types (cost, hardware, transfer
  penalty, recovery: what the host needs for allocation without importing agent code) and load errors;
* host -> zygote: `ForkServerRequest` (req_id, type_name, agent_id, log_path, exec) with the agent's end of
  its channel attached as SCM_RIGHTS; the zygote checks the type, forks, closes its copy of the fd and
  answers `ForkServerEvent.reply` (pid, or an error such as an unknown type — then nothing was forked);
* host -> zygote: `ForkServerRequest` with `validate` set: check a config against the type's model
  (`AgentBase.check_config`) without forking, answered `Reply.config_error` ("" = valid). The config
  travels in a memfd attached as SCM_RIGHTS (a packet is bounded by the socket buffer; a config may be
  1 MiB, `haa.core.ddb.agenttable.MAX_CONFIG`), `config_size` bytes of it; at most MAX_VALIDATE_BYTES are read;
* zygote -> host: `ForkServerEvent.exit` (pid, exit code or signal) for every child it reaps. The agents
  are the zygote's children, so it is the one that learns how each ended ("exited code 1", "killed by
  signal 9"); the host turns that into the agent's Failed event.

Lifetime: the zygote exits when the host's end of the socket closes (it SIGKILLs and reaps its children
first), and it asks the kernel to SIGKILL it if haa-hostd dies (PR_SET_PDEATHSIG); every child asks the
same about the zygote. So no agent outlives its host. The zygote runs in its own session, so a Ctrl-C in
the host's terminal reaches only haa-hostd, which then closes its agents in order.

Preloading: the registry (`haa.sdk.registry.load_all`: the names of the entry points' types, the modules of
HAA_AGENT_MODULES and --preload), the runtime, protobuf, uvloop; then `gc.freeze()` so the children share the
preloaded objects' pages instead of copying them when the collector touches them. Math libraries are limited to one
thread (OMP/OPENBLAS/MKL_NUM_THREADS=1 unless set): an agent is one process whose CPU the host measures, and
forking after a thread pool started is unsafe. A type registered by name only (an entry point) is imported by the
zygote at the first request for it (`describe`, a fork or a config check), before it forks: its children share it.

`ForkServer` is the host's side (asyncio); `serve()` is the zygote's main (`python -m haa.sdk.forkserver`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import gc
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from haa.pb import agent_pb2 as pb

if TYPE_CHECKING:
    from haa.sdk.base import AgentBase

PR_SET_PDEATHSIG = 1
#: largest packet on the control socket (the ready message with the type table is the big one)
MAX_PACKET = 1 << 20
#: the largest config a validate request may carry (the memfd is not read beyond it); the agent table's own
#: limit (haa.core.ddb.agenttable.MAX_CONFIG) is smaller and checked by the host first
MAX_VALIDATE_BYTES = 16 * 1024 * 1024
#: environment defaults for the zygote (one math thread per agent process)
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class SpawnError(RuntimeError):
    """An agent process could not be started (unknown type, fork failure, no Hello, fork server gone)."""


def set_pdeathsig(sig: int = signal.SIGKILL) -> bool:
    """Ask Linux to send `sig` to this process when its parent dies; False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


# ====================================================================================== zygote side


def _send(sock: socket.socket, ev: pb.ForkServerEvent) -> None:
    sock.sendall(ev.SerializeToString())


def serve(fd: int, preload: Sequence[str] = (), preload_types: Sequence[str] = ()) -> int:
    """The zygote's main loop (module docstring); returns when the host closes the socket."""
    parent = os.getppid()
    set_pdeathsig()
    if os.getppid() != parent:  # the host died before prctl took effect
        return 1
    sock = socket.socket(fileno=fd)
    sock.setblocking(True)
    t0 = time.perf_counter()
    # preloaded for the children
    from haa.sdk import base as _base  # noqa: F401
    from haa.sdk import registry, runner  # noqa: F401

    with contextlib.suppress(ImportError):
        import uvloop  # noqa: F401
    errors = registry.load_all(preload)
    for name in preload_types:  # imported now rather than at the first spawn
        try:
            registry.get(name)
        except LookupError as e:
            errors.append(str(e))
    for e in errors:
        print(f"haa fork server: {e}", file=sys.stderr)
    types = [pb.AgentTypeInfo(**registry.type_info(cls)) for cls in registry.REGISTRY.values()]
    gc.collect()
    gc.freeze()
    ready = pb.ForkServerEvent(
        ready=pb.ForkServerEvent.Ready(
            pid=os.getpid(), types=types, load_errors=errors, preload_seconds=time.perf_counter() - t0,
            lazy_types=sorted(registry.LAZY),
        )
    )
    _send(sock, ready)

    rpipe, wpipe = os.pipe()
    os.set_blocking(rpipe, False)
    os.set_blocking(wpipe, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.set_wakeup_fd(wpipe)
    children: set[int] = set()
    sel = selectors.DefaultSelector()
    sel.register(sock, selectors.EVENT_READ)
    sel.register(rpipe, selectors.EVENT_READ)

    def reap() -> None:
        while children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                children.clear()
                return
            if pid == 0:
                return
            children.discard(pid)
            if os.WIFSIGNALED(status):
                ev = pb.ForkServerEvent.ChildExit(pid=pid, signal=os.WTERMSIG(status))
            else:
                ev = pb.ForkServerEvent.ChildExit(pid=pid, exit_code=os.waitstatus_to_exitcode(status))
            with contextlib.suppress(OSError):
                _send(sock, pb.ForkServerEvent(exit=ev))

    try:
        while True:
            for key, _ in sel.select():
                if key.fileobj is sock:
                    try:
                        data, fds, _flags, _addr = socket.recv_fds(sock, MAX_PACKET, 4)
                    except ConnectionError:
                        return 0
                    if not data and not fds:
                        return 0  # the host closed its end
                    pid = _fork_one(sock, data, fds, children, (rpipe, wpipe, sel))
                    if pid:
                        children.add(pid)
                else:
                    with contextlib.suppress(BlockingIOError):
                        while os.read(rpipe, 4096):
                            pass
                    reap()
            reap()  # SIGCHLDs can coalesce; reaping is cheap
    finally:
        for pid in list(children):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        while children:
            try:
                pid, _status = os.waitpid(-1, 0)
            except ChildProcessError:
                break
            children.discard(pid)


def _fork_one(sock: socket.socket, data: bytes, fds: list[int], children: set[int],
              private: tuple[int, int, selectors.DefaultSelector]) -> int:
    """Handle one request: check the type, fork, answer. Returns the child's pid (0 if none)."""
    from haa.sdk import registry

    req = pb.ForkServerRequest()
    try:
        req.ParseFromString(data)
    except Exception as e:
        for fd in fds:
            os.close(fd)
        _send(sock, pb.ForkServerEvent(reply=pb.ForkServerEvent.Reply(error=f"malformed fork request: {e}")))
        return 0

    def refuse(message: str) -> int:
        for fd in fds:
            os.close(fd)
        _send(sock, pb.ForkServerEvent(reply=pb.ForkServerEvent.Reply(req_id=req.req_id, error=message)))
        return 0

    try:
        cls = registry.get(req.type_name)  # a lazy type is imported here, once, for every child forked later
    except LookupError as e:
        return refuse(str(e))
    if req.describe:
        for fd in fds:
            os.close(fd)
        info = pb.AgentTypeInfo(**registry.type_info(cls))
        _send(sock, pb.ForkServerEvent(reply=pb.ForkServerEvent.Reply(req_id=req.req_id, info=info)))
        return 0
    if len(fds) != 1:
        return refuse(f"a fork request needs exactly one channel fd, got {len(fds)}")
    if req.validate:
        _validate_one(sock, req, fds[0], cls)
        return 0
    (fd,) = fds
    sys.stdout.flush()
    sys.stderr.flush()
    zygote = os.getpid()
    try:
        pid = os.fork()
    except OSError as e:
        return refuse(f"fork failed: {e}")
    if pid == 0:  # ---------------------------------------------------------------- the agent process
        code = 70
        try:
            signal.set_wakeup_fd(-1)
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            rpipe, wpipe, sel = private
            os.close(rpipe)
            os.close(wpipe)
            os.close(sel.fileno())  # not sel.close(): the epoll instance is shared with the zygote
            sock.close()  # the child's copy only; the zygote's stays open
            set_pdeathsig()
            if os.getppid() != zygote:
                os._exit(1)
            if req.log_path:
                out = os.open(req.log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
                os.dup2(out, 1)
                os.dup2(out, 2)
                os.close(out)
            if req.exec:
                os.set_inheritable(fd, True)
                os.execv(sys.executable, [sys.executable, "-m", "haa.sdk.runner", "--fd", str(fd)])
            from haa.sdk.runner import run_child

            code = run_child(fd)
        except BaseException:
            with contextlib.suppress(Exception):
                traceback.print_exc()
        finally:
            with contextlib.suppress(Exception):
                sys.stdout.flush()
                sys.stderr.flush()
            os._exit(code)
    os.close(fd)  # ---------------------------------------------------------------------- the zygote
    _send(sock, pb.ForkServerEvent(reply=pb.ForkServerEvent.Reply(req_id=req.req_id, pid=pid)))
    return pid


def _validate_one(sock: socket.socket, req: pb.ForkServerRequest, fd: int, cls: type[AgentBase]) -> None:
    """Answer a validate request: read the config from the memfd `fd` and check it (no fork)."""
    try:
        size = req.config_size
        if size > MAX_VALIDATE_BYTES:
            why = f"config of {size} bytes exceeds the fork server's limit of {MAX_VALIDATE_BYTES} bytes"
        else:
            data = bytearray()
            while len(data) < size:
                chunk = os.pread(fd, min(size - len(data), 1 << 20), len(data))
                if not chunk:
                    break
                data += chunk
            if len(data) != size:
                why = f"config: expected {size} bytes, the memfd holds {len(data)}"
            else:
                why = cls.check_config(bytes(data))
    except Exception as e:  # a bug in a model (a validator that raises something else) is the type's problem
        why = f"config: the check raised {type(e).__name__}: {' '.join(str(e).split())}"[:400]
    finally:
        os.close(fd)
    _send(sock, pb.ForkServerEvent(reply=pb.ForkServerEvent.Reply(req_id=req.req_id, config_error=why)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="HAA agent fork server (started by haa-hostd)")
    ap.add_argument("--fd", type=int, required=True, help="the SOCK_SEQPACKET control socket")
    ap.add_argument("--preload", default="", help="extra modules to import, comma separated")
    ap.add_argument("--preload-types", default="", help="agent types to import now, comma separated")
    args = ap.parse_args(argv)
    return serve(args.fd, [m for m in args.preload.split(",") if m], [t for t in args.preload_types.split(",") if t])


# ====================================================================================== host side

ExitCallback = Callable[[int, str], None]


def exit_reason(exit_code: int, sig: int) -> str:
    """The Failed reason of an exit status: "exited code N" or "killed by signal S"."""
    return f"killed by signal {sig}" if sig else f"exited code {exit_code}"


class ForkServer:
    """The host's handle on a zygote: start it, fork agents, learn how they exit (asyncio).

    `on_exit(pid, reason)` is called from the event loop for every reaped child; `on_dead()` once if the
    zygote itself goes away while it should be running.
    """

    def __init__(
        self,
        on_exit: ExitCallback,
        *,
        on_dead: Callable[[str], None] | None = None,
        workdir: Path | None = None,
        preload: Sequence[str] = (),
        preload_types: Sequence[str] = (),
        env: dict[str, str] | None = None,
    ) -> None:
        self.on_exit = on_exit
        self.on_dead = on_dead
        self.workdir = workdir
        self.preload = list(preload)
        self.preload_types = list(preload_types)
        self.env = env
        self.proc: subprocess.Popen[bytes] | None = None
        self.sock: socket.socket | None = None
        self.types: dict[str, pb.AgentTypeInfo] = {}  # the imported types
        self.lazy: set[str] = set()  # types known by name, imported by the zygote at their first describe
        self.load_errors: list[str] = []
        self.preload_seconds = 0.0
        self.start_seconds = 0.0
        self._pending: dict[int, asyncio.Future[pb.ForkServerEvent.Reply]] = {}
        self._next = 1
        self._reader: asyncio.Task[None] | None = None
        self._closing = False
        self.alive = False

    async def start(self, timeout: float = 60.0) -> None:
        """Start the zygote and wait until it has preloaded everything."""
        t0 = time.perf_counter()
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        env = dict(os.environ if self.env is None else self.env)
        for k, v in THREAD_ENV.items():
            env.setdefault(k, v)
        cmd = [sys.executable, "-m", "haa.sdk.forkserver", "--fd", str(theirs.fileno())]
        if self.preload:
            cmd += ["--preload", ",".join(self.preload)]
        if self.preload_types:
            cmd += ["--preload-types", ",".join(self.preload_types)]
        try:
            self.proc = subprocess.Popen(
                cmd,
                pass_fds=[theirs.fileno()],
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                cwd=self.workdir,
                env=env,
            )
        finally:
            theirs.close()
        mine.setblocking(False)
        self.sock = mine
        loop = asyncio.get_running_loop()
        try:
            data = await asyncio.wait_for(loop.sock_recv(mine, MAX_PACKET), timeout)
        except TimeoutError:
            await self.close()
            raise SpawnError(f"the agent fork server did not start within {timeout:g} s") from None
        ev = pb.ForkServerEvent()
        if not data:
            code = self.proc.wait(5)
            await self.close()
            raise SpawnError(f"the agent fork server exited during start ({exit_reason(code, 0)}; see its stderr)")
        ev.ParseFromString(data)
        if ev.WhichOneof("ev") != "ready":
            await self.close()
            raise SpawnError(f"the agent fork server sent {ev.WhichOneof('ev')} instead of ready")
        self.types = {t.type_name: t for t in ev.ready.types}
        self.lazy = set(ev.ready.lazy_types) - set(self.types)
        self.load_errors = list(ev.ready.load_errors)
        self.preload_seconds = ev.ready.preload_seconds
        self.start_seconds = time.perf_counter() - t0
        self.alive = True
        self._reader = asyncio.create_task(self._read(), name="forkserver-reader")

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    async def fork(self, type_name: str, agent_id: str, channel_fd: int, *, log_path: str = "",
                   exec_: bool = False, timeout: float = 10.0) -> int:
        """Fork an agent process with `channel_fd` as its channel; its pid. SpawnError if refused."""
        if not self.alive or self.sock is None:
            raise SpawnError("the agent fork server is not running")
        req = pb.ForkServerRequest(type_name=type_name, agent_id=agent_id, log_path=log_path, exec=exec_)
        reply = await self._ask(req, channel_fd, timeout)
        if reply.error:
            raise SpawnError(reply.error)
        return reply.pid

    def known(self) -> list[str]:
        """Every type this fork server can start, imported or not."""
        return sorted({*self.types, *self.lazy})

    async def describe(self, type_name: str, timeout: float = 30.0) -> pb.AgentTypeInfo:
        """The type's info, importing it in the zygote first if it is lazy. SpawnError if it is unknown, its
        module fails to import (the reason is added to `load_errors` once) or the fork server cannot answer."""
        info = self.types.get(type_name)
        if info is not None:
            return info
        if not self.alive or self.sock is None:
            raise SpawnError("the agent fork server is not running")
        reply = await self._ask(pb.ForkServerRequest(type_name=type_name, describe=True), None, timeout)
        if reply.error:
            if type_name in self.lazy:
                self.lazy.discard(type_name)
                self.load_errors.append(reply.error)
            raise SpawnError(reply.error)
        self.types[type_name] = reply.info
        self.lazy.discard(type_name)
        return reply.info

    async def validate(self, type_name: str, config: bytes, timeout: float = 10.0) -> str:
        """'' when `config` is valid for `type_name` (its model, `AgentBase.check_config`), else the reason.
        SpawnError if the fork server cannot answer (not running, unknown type)."""
        if not self.alive or self.sock is None:
            raise SpawnError("the agent fork server is not running")
        fd = os.memfd_create("haa-agent-config", os.MFD_CLOEXEC)
        try:
            view = memoryview(config)
            while view:
                view = view[os.write(fd, view):]
            req = pb.ForkServerRequest(type_name=type_name, validate=True, config_size=len(config))
            reply = await self._ask(req, fd, timeout)
        finally:
            os.close(fd)  # the zygote got its own copy when the request was sent
        if reply.error:
            raise SpawnError(reply.error)
        return reply.config_error

    async def _ask(self, req: pb.ForkServerRequest, fd: int | None, timeout: float) -> pb.ForkServerEvent.Reply:
        """Send one request with `fd` attached (if any) and wait for its reply."""
        assert self.sock is not None
        req_id = self._next
        self._next += 1
        req.req_id = req_id
        fut: asyncio.Future[pb.ForkServerEvent.Reply] = asyncio.get_running_loop().create_future()
        self._pending[req_id] = fut
        data = req.SerializeToString()
        try:
            deadline = time.monotonic() + timeout
            while True:
                try:
                    socket.send_fds(self.sock, [data], [] if fd is None else [fd])
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise SpawnError("the agent fork server is not reading its requests") from None
                    await asyncio.sleep(0.002)
                except OSError as e:
                    raise SpawnError(f"the agent fork server is gone: {e}") from None
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise SpawnError(f"the agent fork server did not answer within {timeout:g} s") from None
        finally:
            self._pending.pop(req_id, None)

    async def _read(self) -> None:
        assert self.sock is not None
        loop = asyncio.get_running_loop()
        reason = "closed its socket"
        try:
            while True:
                try:
                    data = await loop.sock_recv(self.sock, MAX_PACKET)
                except OSError as e:
                    reason = f"socket error: {e}"
                    break
                if not data:
                    break
                ev = pb.ForkServerEvent()
                try:
                    ev.ParseFromString(data)
                except Exception as e:
                    reason = f"sent a malformed packet: {e}"
                    break
                kind = ev.WhichOneof("ev")
                if kind == "reply":
                    fut = self._pending.get(ev.reply.req_id)
                    if fut is not None and not fut.done():
                        fut.set_result(ev.reply)
                elif kind == "exit":
                    try:
                        self.on_exit(ev.exit.pid, exit_reason(ev.exit.exit_code, ev.exit.signal))
                    except Exception:
                        traceback.print_exc()
        finally:
            self.alive = False
            for fut in self._pending.values():
                if not fut.done():
                    fut.set_exception(SpawnError(f"the agent fork server {reason}"))
            if not self._closing and self.on_dead is not None:
                self.on_dead(reason)

    async def close(self, timeout: float = 5.0) -> None:
        """Close the socket (the zygote kills its children and exits) and wait for it."""
        self._closing = True
        self.alive = False
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        if self.sock is not None:
            self.sock.close()
        if self.proc is not None:
            deadline = time.monotonic() + timeout
            while self.proc.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            if self.proc.poll() is None:
                self.proc.kill()
                with contextlib.suppress(Exception):
                    self.proc.wait(2)


if __name__ == "__main__":
    sys.exit(main())
