"""Helpers shared by the tests: waiting for a condition, running a coroutine, `haactl` in-process, a local
cluster for a test. Imported by name (`from helpers import until, run`; tests/ is on sys.path), not through
conftest.py: tests/chaos has a conftest.py of its own, and pytest imports each under the name `conftest`, so
`from conftest import ...` would find whichever was loaded last. tests/conftest.py lists these and hands
some of them out as fixtures.

Tests wait for conditions; they never sleep a guessed time. A fixed sleep used as synchronization ("the
message has surely arrived after 0.1 s") passes on an idle laptop and fails on a loaded CI machine; a poll
waits exactly as long as needed, up to a generous timeout, and says what it was waiting for when that runs
out. A sleep stays only where the test measures time itself (a quiet period in which nothing may happen, a
delay the code under test must keep, a hang or a timeout being exercised).
"""

from __future__ import annotations

import ast
import asyncio
import contextlib
import inspect
import json
import os
import signal
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from typer.testing import CliRunner

if TYPE_CHECKING:
    from click.testing import Result

T = TypeVar("T")

#: long enough for a loaded 2-core CI machine; a passing test never waits for it
DEFAULT_TIMEOUT = 10.0


class NotYet:
    """A false answer to a poll that says why: `until`/`wait_sync` put the last one's `why` in the timeout
    message (`return st if done(st) else NotYet(f"members {st['members']}")`)."""

    def __init__(self, why: str) -> None:
        self.why = why

    def __bool__(self) -> bool:
        return False

    def __repr__(self) -> str:
        return f"NotYet({self.why!r})"


class _Poll:
    """One poll's bookkeeping: the deadline, and what the last attempt said."""

    def __init__(self, timeout: float, what: str) -> None:
        self.timeout, self.what = timeout, what
        self.deadline = time.monotonic() + timeout
        self.last = ""

    def note(self, got: object) -> None:
        self.last = got.why if isinstance(got, NotYet) else ""

    def failed(self, e: BaseException) -> None:
        self.last = f"{type(e).__name__}: {e}"[:300]

    def expired(self) -> bool:
        return time.monotonic() > self.deadline

    def error(self) -> AssertionError:
        why = f" (last: {self.last})" if self.last else ""
        return AssertionError(f"timed out after {self.timeout:g} s waiting for {self.what}{why}")


async def until(cond: Callable[[], T | Awaitable[T]], timeout: float = DEFAULT_TIMEOUT, what: str = "condition",
                interval: float = 0.005, ignore: tuple[type[BaseException], ...] = ()) -> T:
    """Return `cond()` as soon as it is true (`cond` may be a coroutine function); fail after `timeout`
    seconds with `what` in the message. Polls every `interval` seconds on the running event loop. An exception
    of a type in `ignore` counts as "not yet" (its text goes into the timeout message, as a `NotYet`'s does)."""
    p = _Poll(timeout, what)
    while True:
        try:
            got = cond()
            if inspect.isawaitable(got):
                got = await got
        except ignore as e:
            p.failed(e)
        else:
            if got:
                return got  # type: ignore[return-value]
            p.note(got)
        if p.expired():
            raise p.error()
        await asyncio.sleep(interval)


def wait_sync(cond: Callable[[], T], timeout: float = DEFAULT_TIMEOUT, what: str = "condition",
              interval: float = 0.02, ignore: tuple[type[BaseException], ...] = ()) -> T:
    """`until` for code outside an event loop (processes, threads, a cluster polled over RPCs): returns
    `cond()` once it is true."""
    p = _Poll(timeout, what)
    while True:
        try:
            got = cond()
        except ignore as e:
            p.failed(e)
        else:
            if got:
                return got
            p.note(got)
        if p.expired():
            raise p.error()
        time.sleep(interval)


def wait_value(get: Callable[[], T], pred: Callable[[T], object], timeout: float = DEFAULT_TIMEOUT,
               what: str = "condition", interval: float = 0.1, ignore: tuple[type[BaseException], ...] = (),
               show: Callable[[T], str] = repr) -> T:
    """`get()` as soon as `pred` holds for it (a falsy value may be the one waited for); the timeout message
    ends with the last value, as `show` writes it (its first 3000 characters)."""

    def check() -> tuple[T] | NotYet:
        v = get()
        return (v,) if pred(v) else NotYet(show(v)[:3000])

    return wait_sync(check, timeout, what, interval, ignore)[0]


def run(coro: Coroutine[Any, Any, T], timeout: float = 30.0, loop: asyncio.AbstractEventLoop | None = None) -> T:
    """Run `coro` on a fresh event loop (or on `loop`, kept by the caller), failing it after `timeout` seconds:
    a hung test fails, it does not hang."""
    if loop is not None:
        return loop.run_until_complete(asyncio.wait_for(coro, timeout))
    return asyncio.run(asyncio.wait_for(coro, timeout))


def parse_source(source: str | Path) -> ast.Module:
    """The AST of a Python file (a Path) or of source text. CPython 3.11.7 sometimes raises a spurious
    "AST constructor recursion depth mismatch" SystemError (python/cpython#106905, fixed in 3.11.8): a failed
    parse elsewhere in the process leaves the depth counter off and the next parse raises; a second parse of the
    same source is exact (seen in loaded CI runs)."""
    text = source.read_text() if isinstance(source, Path) else source
    name = str(source) if isinstance(source, Path) else "<source>"
    try:
        return ast.parse(text, filename=name)
    except SystemError:
        return ast.parse(text, filename=name)


# ---------------------------------------------------------------------------------------- haactl in-process

runner = CliRunner()


def haactl(args: Sequence[str], env: Mapping[str, str] | None = None) -> Result:
    """`haactl ARGS` in-process, whatever its exit code (haactl's modules are imported at the first call)."""
    from haactl.main import app

    return runner.invoke(app, list(args), env=env)


class Cli:
    """`haactl` run in-process (typer's CliRunner) against one cluster: a local one under `root` (every
    command gets `--root ROOT`), or one that `env` and `extra` name (`extra` goes after every command's
    arguments: `--compose`, `--swarm`)."""

    def __init__(self, root: Path | None = None, *, extra: Sequence[str] = (),
                 env: Mapping[str, str] | None = None) -> None:
        self.root = root
        self.extra = (*extra, *(("--root", str(root)) if root is not None else ()))
        self.env = dict(env) if env else None

    def __call__(self, *args: str, ok: bool = True) -> Result:
        """The command's result; with `ok`, it must have exited 0."""
        r = haactl([*args, *self.extra], env=self.env)
        if ok:
            assert r.exit_code == 0, (f"haactl {' '.join([*args, *self.extra])} -> {r.exit_code}\n{r.output}\n"
                                      f"{r.exception!r}")
        return r

    def out(self, *args: str) -> str:
        """The standard output of a command that must succeed."""
        return self(*args).stdout

    def json(self, *args: str) -> Any:
        """`haactl ARGS --json`, parsed."""
        return json.loads(self(*args, "--json").stdout)

    def fails(self, *args: str) -> str:
        """The output of a command that must fail with exit code 1, on one line (rich may wrap it)."""
        r = self(*args, ok=False)
        assert r.exit_code == 1, f"haactl {' '.join(args)} -> {r.exit_code}\n{r.output}"
        return " ".join(r.output.split())

    def status(self) -> dict[str, Any]:
        """`cluster status` without the CPU sample."""
        return self.json("cluster", "status", "--sample", "0")

    def hosts(self) -> dict[str, dict[str, Any]]:
        """The rows of `cluster status` by host name."""
        return {h["name"]: h for h in self.status()["hosts"]}

    def agents(self) -> dict[str, dict[str, Any]]:
        """`agent list` by agent name."""
        return {a["name"]: a for a in self.json("agent", "list")["agents"]}

    def events(self) -> list[dict[str, Any]]:
        """`agent events --json`, one dict per event."""
        return [json.loads(ln) for ln in self.out("agent", "events", "--json").splitlines()]


def kill_leftovers(root: Path) -> None:
    """SIGKILL every host process the local cluster under `root` still lists (after a `cluster down` that
    failed, which leaves its state file): a test leaves no process behind."""
    state = root / "cluster.json"
    if state.exists():
        for rec in json.loads(state.read_text())["hosts"].values():
            with contextlib.suppress(ProcessLookupError, TypeError):
                os.kill(rec["pid"], signal.SIGKILL)


@contextlib.contextmanager
def local_cluster(root: Path, *up: str, down: Sequence[str] = ("--grace", "1")) -> Iterator[Cli]:
    """A `Cli` for a local cluster under `root`, started with `haactl cluster up UP...` (no `up`: the test
    starts it) and, at the end, stopped with `cluster down DOWN...`, and its processes killed if that failed."""
    cli = Cli(root)
    try:
        if up:
            cli("cluster", "up", *up)
        yield cli
    finally:
        haactl(["cluster", "down", *down, "--root", str(root)])
        kill_leftovers(root)
