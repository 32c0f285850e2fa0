"""Offline replay of one recorded agent instance (thesis §6.1.4 AgentPlayback; docs/playback.md).

`replay_instance(inst)` builds the agent's class from the registry with the recorded Init (same id, name,
config, epoch, host) inside a `ReplayContext` — an `AgentContext` whose three consumption points take the
recorded inputs instead of waiting for a host: the mailbox worker's next item (`_take_item`), the answer to a
host call (`_await_answer`) and the reply to a request (`_await_reply`); `now()` and the random source read
the recorded values; timers never fire by themselves (a recorded firing fires the timer of that number);
haa-sim calls are answered from the recording (`haa.sdk.external.ReplayStub`). Every frame the agent
emits, and every haa-sim request, is compared byte for byte (deterministic protobuf serialization) with the
recorded output of the same number, together with the number of inputs consumed before it; the first
difference ends the replay as a `Divergence` (input position, expected, got).

Order. Inputs are handed out strictly in the recorded order: a consumer (the worker, or a task of the agent
awaiting an answer) whose input is not next waits until the ones before it are taken; a synchronous read
(`now()`, a random number) must be next. Nothing taken for `STALL_S` while inputs remain is a divergence too
(the agent waits for something else than it did live). `break_at=N` calls `on_break` (default: pdb) just
before input N is handed out: step (`n`, `s`) from there into the agent's code.

Log frames are compared without their `traceback` field (its frames name the replay's own methods).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from google.protobuf import text_format

from haa.lab.playback.reader import Instance
from haa.pb import agent_pb2 as pb
from haa.pb import playback_pb2 as ppb
from haa.sdk import registry
from haa.sdk.context import AgentContext, AgentFatal
from haa.sdk.sched import Clock

#: no input taken for this long (wall seconds) while some remain: the replay diverged
STALL_S = 2.0
#: after the last input, how long the agent may still run (its last handler) before the replay ends
SETTLE_S = 0.3

#: the mailbox kinds (haa.sdk.context.AgentContext) among the PlaybackInput fields
ITEM_KINDS = frozenset({"begin", "message", "timer", "watch", "log_item", "resume", "freeze", "stop"})


class ReplayStopped(BaseException):
    """Raised inside the agent's code to end the replay (a divergence, or the recording ended). A
    BaseException: the agent's `except Exception` must not swallow it."""


@dataclass
class Divergence:
    input_index: int
    what: str
    expected: str
    got: str
    output_index: int | None = None

    def __str__(self) -> str:
        where = f"input {self.input_index}"
        if self.output_index is not None:
            where += f", output {self.output_index}"
        return f"replay diverged at {where}: {self.what}\n  expected: {self.expected}\n  got:      {self.got}"


@dataclass
class ReplayResult:
    inputs: int
    outputs: int
    total_inputs: int
    total_outputs: int
    divergence: Divergence | None = None
    truncated: bool = False
    exit_code: int | None = None
    #: the recording is damaged (`Instance.damage`), read up to the damage
    damage: str = ""

    @property
    def identical(self) -> bool:
        return self.divergence is None


def describe(msg: Any, limit: int = 300) -> str:
    """One line for a protobuf message: its text format, bytes shown short."""
    if msg is None:
        return "(nothing)"
    text = text_format.MessageToString(msg, as_one_line=True, as_utf8=True)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def input_kind(inp: ppb.PlaybackInput) -> str:
    return inp.WhichOneof("input") or "?"


def _normal(frame: pb.AgentToHost) -> bytes:
    if frame.WhichOneof("msg") == "log":
        try:
            fields = json.loads(frame.log.fields_json)
        except ValueError:
            fields = None
        if isinstance(fields, dict) and "traceback" in fields:
            f = pb.AgentToHost()
            f.CopyFrom(frame)
            fields.pop("traceback")
            f.log.fields_json = json.dumps(fields, separators=(",", ":"))
            frame = f
    return frame.SerializeToString(deterministic=True)


def output_bytes(out: ppb.PlaybackOutput) -> bytes:
    if out.WhichOneof("output") == "frame":
        return _normal(out.frame)
    return out.external_call.SerializeToString(deterministic=True)


def same_output(exp: ppb.PlaybackOutput, got: ppb.PlaybackOutput) -> bool:
    """`got` (a replayed output) is the recorded `exp` byte for byte (by SHA-256 when only its digest was kept)."""
    if exp.WhichOneof("output") == "digest":
        if got.WhichOneof("output") != "frame":
            return False
        data = got.frame.SerializeToString(deterministic=True)
        return len(data) == exp.digest.size and hashlib.sha256(data).digest() == exp.digest.sha256
    return output_bytes(exp) == output_bytes(got)


class ReplayFeed:
    """The recorded inputs, handed out in order, and the recorded outputs, checked in order (module docstring).
    It is also the replayed context's tap (clock, random source, emit, haa-sim stub)."""

    offline = True

    def __init__(self, inst: Instance, break_at: int | None = None,
                 on_break: Callable[[int, ppb.PlaybackInput], None] | None = None) -> None:
        self.inputs = inst.inputs
        self.outputs = inst.outputs
        self.truncated = inst.truncated
        self.damage = inst.damage
        self.pos = 0
        self.out_pos = 0
        self.divergence: Divergence | None = None
        self.break_at = break_at
        self.on_break = on_break or _pdb_break
        self.external_calls = 0
        #: what the host's Freeze does on arrival (ReplayContext: stop the timers)
        self.on_freeze: Callable[[], None] | None = None
        self.progress = 0  # bumped by every input taken and output checked
        self._changed = asyncio.Event()

    # ------------------------------------------------------------------ inputs

    def _diverge(self, what: str, expected: str, got: str, output: int | None = None) -> ReplayStopped:
        if self.divergence is None:
            self.divergence = Divergence(self.pos, what, expected, got, output)
        self._bump()
        return ReplayStopped(str(self.divergence))

    def _bump(self) -> None:
        self.progress += 1
        self._changed.set()
        self._changed = asyncio.Event()

    def _consume(self) -> ppb.PlaybackInput:
        if self.break_at is not None and self.pos == self.break_at:
            self.break_at = None
            self.on_break(self.pos, self.inputs[self.pos])
        inp = self.inputs[self.pos]
        self.pos += 1
        self._bump()
        return inp

    def take_now(self, kind: str, what: str) -> ppb.PlaybackInput:
        """A synchronous read (now(), random): it must be the next input."""
        if self.divergence is not None:
            raise ReplayStopped(str(self.divergence))
        self._arrivals()
        if self.pos >= len(self.inputs):
            raise ReplayStopped("the recording ends")
        head = self.inputs[self.pos]
        if input_kind(head) != kind:
            raise self._diverge(f"the agent read {what}; live, the next input was {input_kind(head)}",
                                describe(head), what)
        return self._consume()

    async def take(self, match: Callable[[ppb.PlaybackInput], bool], what: str) -> ppb.PlaybackInput:
        """Wait until the next input is one `match` accepts (the inputs before it taken by other consumers) and
        no output the live agent made before it is still to come; then take it at once. (Giving the agent's
        other ready tasks a few loop iterations first, before or after a wake-up, made more replays diverge
        than it saved, measured over three recorded missions: docs/playback.md.)"""
        while True:
            if self.divergence is not None:
                raise ReplayStopped(str(self.divergence))
            self._arrivals()
            if self.pos < len(self.inputs) and match(self.inputs[self.pos]) and not self.output_due():
                return self._consume()
            await self._changed.wait()

    def output_due(self) -> bool:
        """Live, the next recorded output was made before the next input was taken: hold the input until the
        replayed agent has made it (another of its tasks may be about to; else the replay stalls)."""
        return self.out_pos < len(self.outputs) and self.outputs[self.out_pos].after_input <= self.pos

    # ------------------------------------------------------------------ outputs

    def check_output(self, out: ppb.PlaybackOutput) -> None:
        if self.divergence is not None:
            raise ReplayStopped(str(self.divergence))
        k = self.out_pos
        if k >= len(self.outputs):
            if self.truncated:  # the live writer died before this output was on disk
                self.out_pos += 1
                return
            raise self._diverge("an output the live agent did not make", "(no more outputs)", describe(out), k)
        exp = self.outputs[k]
        if not same_output(exp, out):
            raise self._diverge("a different output", describe(exp), describe(out), k)
        if exp.after_input != self.pos:
            raise self._diverge(f"output {k} made after a different number of inputs",
                                f"after input {exp.after_input}", f"after input {self.pos}", k)
        self.out_pos += 1
        self._bump()

    # ------------------------------------------------------------------ the tap (AgentContext)

    def wrap_emit(self, _emit: Any) -> Callable[[pb.AgentToHost], None]:
        def emit(frame: pb.AgentToHost) -> None:
            self.check_output(ppb.PlaybackOutput(frame=frame))

        return emit

    def wrap_clock(self, clock: Clock) -> Clock:
        return _ReplayClock(self)

    def wrap_random(self, rnd: random.Random) -> random.Random:
        return _ReplayRandom(self)

    def perf_counter(self, v: float) -> None:  # pragma: no cover - ReplayContext reads it itself
        pass

    def thread_done(self, n: int) -> None:  # pragma: no cover - as above
        pass

    def freeze_fed(self) -> None:  # pragma: no cover - the replay feeds nothing
        pass

    def _arrivals(self) -> None:
        """Inputs that act on arrival, not when a consumer takes them (the host's Freeze stopping the timers):
        applied as soon as they are next."""
        while self.pos < len(self.inputs) and input_kind(self.inputs[self.pos]) == "freeze_fed":
            self._consume()
            if self.on_freeze is not None:
                self.on_freeze()

    def item(self, kind: str, data: Any) -> None:  # pragma: no cover - ReplayContext takes items itself
        pass

    def answer(self, req_id: int, ans: Any) -> None:  # pragma: no cover - as above
        pass

    def reply(self, conv: int, env: Any) -> None:  # pragma: no cover - as above
        pass

    def external_call(self, source: str, method: str, request: bytes) -> int:
        self.external_calls += 1
        self.check_output(ppb.PlaybackOutput(external_call=ppb.PlaybackOutput.ExternalCall(
            source=source, method=method, call=self.external_calls, request=request)))
        return self.external_calls

    async def take_external(self, call: int) -> ppb.PlaybackInput.External:
        inp = await self.take(lambda i: input_kind(i) == "external" and i.external.call == call,
                              f"haa-sim reply of call {call}")
        return inp.external

    def wrap_stub(self, source: str, service: Any, _stub: Any) -> Any:
        from haa.sdk.external import ReplayStub

        return ReplayStub(self, source, service)


class _ReplayClock(Clock):
    def __init__(self, feed: ReplayFeed) -> None:
        self._feed = feed

    def now(self) -> float:
        return self._feed.take_now("clock", "now()").clock

    def wall_delay(self, delay: float) -> float:
        return 0.0  # nothing waits for the wall clock offline


class _ReplayRandom(random.Random):
    def __init__(self, feed: ReplayFeed) -> None:
        super().__init__(0)
        self._feed = feed

    def random(self) -> float:
        return self._feed.take_now("random", "random()").random

    def getrandbits(self, k: int) -> int:
        inp = self._feed.take_now("random_bits", f"getrandbits({k})")
        if inp.random_bits.k != k:
            raise self._feed._diverge("a different random draw", f"getrandbits({inp.random_bits.k})",
                                      f"getrandbits({k})")
        return int.from_bytes(inp.random_bits.value, "little")


class ReplayContext(AgentContext):
    """An AgentContext fed from a recording (module docstring)."""

    replay: ReplayFeed

    def __init__(self, init: pb.HostToAgent.Init, cls: Any, feed: ReplayFeed) -> None:
        self.replay = feed
        self._timer_by_id: dict[int, Any] = {}
        super().__init__(init, cls, lambda _f: None, tap=feed)
        feed.on_freeze = self._freeze_arrived

    def _freeze_arrived(self) -> None:
        self.state = "freezing"  # as AgentContext.feed does when the host's Freeze arrives (Alg. 5 l. 17)
        self._cancel_timers()

    async def _take_item(self) -> tuple[str, Any]:
        inp = await self.replay.take(lambda i: input_kind(i) in ITEM_KINDS, "a mailbox item")
        kind = input_kind(inp)
        if kind == "message":
            return "msg", inp.message
        if kind == "timer":
            t = self._timer_by_id.get(inp.timer.timer_id)
            if t is None:
                raise self.replay._diverge("a timer fired that the agent did not arm",
                                         f"timer {inp.timer.timer_id} fires",
                                         f"{len(self._timer_by_id)} timers armed")
            return "timer", t
        if kind == "watch":
            w = inp.watch
            return "watch", (w.watch_id, w.event, w.key, bytes(w.value) if w.has_value else None)
        if kind == "log_item":
            w = inp.log_item
            return "log_item", (w.watch_id, w.index, bytes(w.value))
        if kind == "begin":
            b = inp.begin
            return "begin", (b.how, bytes(b.blob) if b.has_blob else None)
        if kind == "resume":
            return "resume", inp.resume
        if kind == "freeze":
            self.state = "freezing"
            self._cancel_timers()
            return "freeze", None
        return "stop", None

    async def _await_answer(self, fut: Any, req_id: int, timeout: float) -> pb.HostToAgent.Answer:
        inp = await self.replay.take(
            lambda i: (input_kind(i) == "answer" and i.answer.req_id == req_id)
            or (input_kind(i) == "call_timeout" and i.call_timeout.req_id == req_id), f"the answer to call {req_id}")
        if input_kind(inp) == "call_timeout":
            raise TimeoutError
        return inp.answer

    async def _await_reply(self, fut: Any, conv: int, timeout: float) -> pb.AgentMsg:
        inp = await self.replay.take(
            lambda i: (input_kind(i) == "reply" and i.reply.conv == conv)
            or (input_kind(i) == "request_timeout" and i.request_timeout.conv == conv), f"the reply to {conv}")
        if input_kind(inp) == "request_timeout":
            raise TimeoutError
        return inp.reply

    def perf_counter(self) -> float:
        return self.replay.take_now("perf_counter", "perf_counter()").perf_counter

    async def run_in_thread(self, executor: Any, call: Callable[[], Any]) -> Any:
        """Run it here and now (its result depends on its arguments only), hand it back where it came back live."""
        self._thread_calls += 1
        n = self._thread_calls
        try:
            return call()
        finally:
            try:
                await self.replay.take(lambda i: input_kind(i) == "thread_done" and i.thread_done == n,
                                     f"the result of thread call {n}")
            except asyncio.CancelledError:  # live, its task was cancelled while it ran: recorded right then
                self.replay.take_now("thread_done", f"the cancelled thread call {n}")
                raise

    def timer(self, fn: Any, delay: float, period: float | None) -> Any:
        t = super().timer(fn, delay, period)
        if t._handle is not None:  # offline a timer fires only when the recording says it did
            t._handle.cancel()
            t._handle = None
        self._timer_by_id[t.id] = t
        return t


def _pdb_break(n: int, inp: ppb.PlaybackInput) -> None:
    import pdb

    print(f"replay: stopped before input {n} ({input_kind(inp)}): {describe(inp, 200)}")
    print("replay: `w` shows the agent's stack waiting for it (`up` to its frames, `p` its variables); `r` a few "
          "times returns into the agent's code as it takes the input, `n`/`s` from there; `c` replays on")
    pdb.Pdb().set_trace(__import__("sys")._getframe(2))


async def _replay(inst: Instance, break_at: int | None,
                  on_break: Callable[[int, ppb.PlaybackInput], None] | None) -> ReplayResult:
    init = inst.init.init
    cls = registry.get(init.type_name)
    feed = ReplayFeed(inst, break_at, on_break)
    loop = asyncio.get_running_loop()

    def quiet(lp: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if not isinstance(context.get("exception"), ReplayStopped | asyncio.CancelledError):
            lp.default_exception_handler(context)

    loop.set_exception_handler(quiet)  # the agent's own tasks end with ReplayStopped: not worth a traceback
    ctx = ReplayContext(init, cls, feed)
    worker = asyncio.create_task(ctx.run(), name="replay-worker")
    last, since = -1, loop.time()
    while not worker.done() and feed.divergence is None:
        await asyncio.sleep(0.005)
        feed._arrivals()
        if feed.progress != last:
            last, since = feed.progress, loop.time()
            continue
        idle = loop.time() - since
        if feed.pos >= len(feed.inputs) and idle >= SETTLE_S:
            break
        if feed.pos < len(feed.inputs) and idle >= STALL_S:
            head = feed.inputs[feed.pos]
            if feed.output_due():
                k = feed.out_pos
                feed._diverge(f"the agent did not make output {k} before input {feed.pos}, as it did live",
                              describe(feed.outputs[k]), "(nothing)", k)
            else:
                feed._diverge(f"the agent never took input {feed.pos} ({input_kind(head)}): it waits for "
                              "something else than it did live", describe(head), "(nothing taken)")
    # end every task the agent left (its own background tasks included)
    worker.cancel()
    others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for t in others:
        t.cancel()
    await asyncio.gather(worker, *others, return_exceptions=True)
    if feed.divergence is None and feed.out_pos < len(feed.outputs):
        k = feed.out_pos
        feed.divergence = Divergence(feed.pos, "an output the replay did not make", describe(feed.outputs[k]),
                                     "(nothing)", k)
    return ReplayResult(feed.pos, feed.out_pos, len(feed.inputs), len(feed.outputs), feed.divergence,
                        feed.truncated, ctx.exit_code, feed.damage)


def replay_instance(inst: Instance, break_at: int | None = None,
                    on_break: Callable[[int, ppb.PlaybackInput], None] | None = None) -> ReplayResult:
    """Re-run one recorded instance offline (module docstring); runs its own event loop."""
    registry.load_all()
    return asyncio.run(_replay(inst, break_at, on_break))


__all__ = ["AgentFatal", "Divergence", "ReplayContext", "ReplayFeed", "ReplayResult", "replay_instance"]


@dataclass
class InstanceResult:
    instance: str
    host: str
    epoch: int
    how: str  # start | thaw | recover (its first input), "" if it has none
    result: ReplayResult


def replay_agent(root: Any, agent: str, instance: int | None = None, break_at: int | None = None,
                 on_break: Callable[[int, ppb.PlaybackInput], None] | None = None) -> list[InstanceResult]:
    """Replay every recorded instance of `agent` (display name or id) in the order they ran, or only the
    `instance`-th (1-based); stops at the first one that diverges. `break_at` applies to the first replayed."""
    from haa.lab.playback.reader import RecordingError, load

    found = load(root, agent)
    if len(found) > 1:
        raise RecordingError(f"{agent!r} names {len(found)} agents: {', '.join(found)}")
    (insts,) = found.values()
    if instance is not None:
        if not 1 <= instance <= len(insts):
            raise RecordingError(f"--instance {instance}: agent {agent} has {len(insts)} recorded instance(s)")
        insts = [insts[instance - 1]]
    out: list[InstanceResult] = []
    for inst in insts:
        first = inst.inputs[0] if inst.inputs else None
        how = first.begin.how if first is not None and input_kind(first) == "begin" else ""
        r = replay_instance(inst, break_at, on_break)
        break_at = None
        out.append(InstanceResult(inst.key, inst.init.init.host, inst.init.init.epoch, how, r))
        if not r.identical:
            break
    return out
