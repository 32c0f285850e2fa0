"""AgentBase / AgentContext in-process (no agent processes): the mailbox, conversations, timers, freeze,
errors; and the registry's validation and naming helpers."""

from __future__ import annotations

import ast
import asyncio
import json
import subprocess
import sys

import pytest
from helpers import run, until

from haa.pb import agent_pb2 as pb
from haa.sdk import registry
from haa.sdk.base import AgentBase, AgentContext, RemoteError, child_name, new_agent_id, root_name


def make(cls, frames: list, *, epoch: int = 1, name: str = "A1") -> AgentContext:
    init = pb.HostToAgent.Init(agent_id=new_agent_id(), name=name, type_name=cls.TYPE, epoch=epoch,
                               config=b'{"x": 1}', host="h1")
    return AgentContext(init, cls, frames.append)


def msg(src: str, data: bytes, conv: int = 0, reply: bool = False, error: str = "") -> pb.HostToAgent:
    return pb.HostToAgent(deliver=pb.AgentMsg(src=src, dst="me", payload=data, conv=conv, reply=reply, error=error))


def start(ctx: AgentContext, how: str = "start") -> None:
    ctx.feed(pb.HostToAgent(start=pb.HostToAgent.Start()))
    ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how=how)))


def kinds(frames: list) -> list[str]:
    return [f.WhichOneof("msg") for f in frames]


class Slow(AgentBase):
    TYPE = "t-slow"

    def __init__(self, ctx):
        super().__init__(ctx)
        self.seen: list[bytes] = []
        self.active = 0
        self.max_active = 0
        self.ticks = 0

    async def on_start(self):
        self.every(0.01, self.tick)

    def tick(self):
        self.ticks += 1

    async def on_message(self, src, payload):
        self.active += 1
        self.max_active = max(self.max_active, self.active)
        await asyncio.sleep(0.002)  # a handler that takes a while: handlers would overlap if run concurrently
        self.seen.append(payload)
        self.send(src, b"ack:" + payload)
        self.active -= 1

    async def on_request(self, src, payload):
        if payload == b"boom":
            raise KeyError("boom")
        return payload.upper()

    def pack_state(self):
        return json.dumps([p.decode() for p in self.seen]).encode()


def test_messages_are_handled_one_at_a_time_in_order_and_freeze_packs_after_them():
    async def main():
        frames: list = []
        ctx = make(Slow, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        await until(lambda: ctx.agent.ticks >= 3)
        for i in range(30):
            ctx.feed(msg("peer", b"m%d" % i))
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        ticks_at_freeze = ctx.agent.ticks
        code = await worker
        a = ctx.agent
        assert code == 0
        assert a.max_active == 1
        assert a.seen == [b"m%d" % i for i in range(30)]
        assert a.ticks == ticks_at_freeze  # timers stop at the freeze, while the mailbox drains (>= 60 ms)
        ks = kinds(frames)
        assert ks[0] == "ready" and ks[-1] == "frozen"
        sent = [f.sent.payload for f in frames if f.WhichOneof("msg") == "sent"]
        assert sent == [b"ack:m%d" % i for i in range(30)]  # every Sent before the Frozen frame
        assert json.loads(frames[-1].frozen.state) == [f"m{i}" for i in range(30)]

    run(main())


def test_requests_are_answered_and_errors_become_error_replies():
    async def main():
        frames: list = []
        ctx = make(Slow, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        ctx.feed(msg("peer", b"hi", conv=5))
        ctx.feed(msg("peer", b"boom", conv=6))
        await until(lambda: len([f for f in frames if f.WhichOneof("msg") == "sent"]) == 2)
        r1, r2 = [f.sent for f in frames if f.WhichOneof("msg") == "sent"]
        assert (r1.dst, r1.conv, r1.reply, r1.payload, r1.error) == ("peer", 5, True, b"HI", "")
        assert (r2.conv, r2.reply, r2.payload) == (6, True, b"")
        assert r2.error == "KeyError: 'boom'"
        ctx.feed(pb.HostToAgent(stop=pb.HostToAgent.Stop()))
        assert await worker == 0
        assert kinds(frames)[-1] == "stopped"

    run(main())


class Asker(AgentBase):
    TYPE = "t-asker"

    async def on_request(self, src, payload):
        cmd = json.loads(payload)
        try:
            return await self.request(cmd["to"], b"q", timeout=cmd["timeout"])
        except TimeoutError as e:
            return b"timeout: " + str(e).encode()
        except RemoteError as e:
            return b"remote: " + str(e).encode()


def test_request_timeout_late_reply_dropped_and_remote_error():
    async def main():
        frames: list = []
        ctx = make(Asker, frames, epoch=7)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        ctx.feed(msg("op", json.dumps({"to": "b", "timeout": 0.05}).encode(), conv=1))
        await until(lambda: any(f.WhichOneof("msg") == "sent" and f.sent.reply for f in frames))
        out = [f.sent for f in frames if f.WhichOneof("msg") == "sent"]
        req, reply = out[0], out[1]
        assert req.dst == "b" and not req.reply and req.conv >> 32 == 7  # conversation ids carry the epoch
        assert reply.payload == b"timeout: request to b timed out after 0.05 s"
        ctx.feed(msg("b", b"late", conv=req.conv, reply=True))  # the late reply is dropped
        await until(lambda: ctx.late_replies == 1)
        # an error reply (e.g. from a host: no such agent) raises RemoteError in the requester
        n = len(frames)
        ctx.feed(msg("op", json.dumps({"to": "c", "timeout": 5}).encode(), conv=2))
        await until(lambda: len(frames) > n)
        req2 = frames[n].sent
        ctx.feed(msg("", b"", conv=req2.conv, reply=True, error="no agent c"))
        await until(lambda: any(f.WhichOneof("msg") == "sent" and f.sent.conv == 2 for f in frames))
        assert [f.sent.payload for f in frames if f.WhichOneof("msg") == "sent" and f.sent.conv == 2] == [
            b"remote: no agent c"
        ]
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0

    run(main())


class Timers(AgentBase):
    TYPE = "t-timers"

    def __init__(self, ctx):
        super().__init__(ctx)
        self.log_: list[str] = []

    async def on_start(self):
        self.call_later(0.01, lambda: self.log_.append("once"))
        t = self.call_later(0.01, lambda: self.log_.append("cancelled"))
        t.cancel()
        self.every(0.005, self.tick)

    async def tick(self):
        self.log_.append("tick")
        await asyncio.sleep(0)


def test_timers_run_in_the_mailbox_and_cancel():
    async def main():
        frames: list = []
        ctx = make(Timers, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        await until(lambda: ctx.agent.log_.count("tick") >= 5 and "once" in ctx.agent.log_)
        assert "cancelled" not in ctx.agent.log_
        assert ctx.agent.log_.count("once") == 1
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0

    run(main())


class Fragile(AgentBase):
    TYPE = "t-fragile"

    async def on_message(self, src, payload):
        raise RuntimeError("bad message")

    def unpack_state(self, data):
        raise ValueError("corrupt state")


class Brittle(Fragile):
    TYPE = "t-brittle"
    CRASH_ON_ERROR = True


def test_handler_error_is_logged_and_the_agent_goes_on():
    async def main():
        frames: list = []
        ctx = make(Fragile, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        ctx.feed(msg("p", b"x"))
        ctx.feed(msg("p", b"y"))
        await until(lambda: ctx.handler_errors == 2)
        logs = [f.log for f in frames if f.WhichOneof("msg") == "log"]
        assert [lg.event for lg in logs] == ["handler_error", "handler_error"]
        assert json.loads(logs[0].fields_json)["error"] == "RuntimeError: bad message"
        ctx.feed(pb.HostToAgent(stop=pb.HostToAgent.Stop()))
        assert await worker == 0

    run(main())


def test_crash_on_error_and_fatal_hooks_exit_with_code_1():
    async def main():
        frames: list = []
        ctx = make(Brittle, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        ctx.feed(msg("p", b"x"))
        assert await worker == 1
        assert frames[-1].error.message == "on_message raised RuntimeError: bad message"

        frames2: list = []
        ctx2 = make(Fragile, frames2)
        worker2 = asyncio.create_task(ctx2.run())
        ctx2.feed(pb.HostToAgent(thaw=pb.HostToAgent.Thaw(state=b"??")))
        ctx2.feed(msg("p", b"queued"))
        ctx2.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="thaw")))
        assert await worker2 == 1
        assert kinds(frames2) == ["error"]  # no Ready, the queued message was not handled
        assert frames2[0].error.message == "unpack_state raised ValueError: corrupt state"

    run(main())


class Lister(AgentBase):
    TYPE = "t-lister"

    def __init__(self, ctx):
        super().__init__(ctx)
        self.got: list[tuple[str, bytes]] = []
        self.how: list[str] = []

    async def on_message(self, src, payload):
        self.got.append((src, payload))

    def unpack_state(self, data):
        self.got.append(("state", data))

    def recover(self, backup):
        self.got.append(("backup", backup))

    async def on_resume(self, how):
        self.how.append(how)


def test_thaw_and_recover_order_state_messages_resume():
    async def main():
        for how, first in (
            ("thaw", pb.HostToAgent(thaw=pb.HostToAgent.Thaw(state=b"S"))),
            ("recover", pb.HostToAgent(recover=pb.HostToAgent.Recover(has_backup=False))),
        ):
            frames: list = []
            ctx = make(Lister, frames)
            worker = asyncio.create_task(ctx.run())
            ctx.feed(first)
            ctx.feed(msg("a", b"1"))
            ctx.feed(msg("b", b"2"))
            ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how=how)))
            ctx.feed(msg("a", b"3"))
            await until(lambda ctx=ctx: len(ctx.agent.got) == 4)
            head = ("state", b"S") if how == "thaw" else ("backup", None)
            assert ctx.agent.got == [head, ("a", b"1"), ("b", b"2"), ("a", b"3")]
            assert ctx.agent.how == [how]
            assert [f.ready.how for f in frames if f.WhichOneof("msg") == "ready"] == [how]
            ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
            assert await worker == 0

    run(main())


def test_host_calls_and_watches():
    class Caller(AgentBase):
        TYPE = "t-caller"

        def __init__(self, ctx):
            super().__init__(ctx)
            self.out: list = []

        async def on_message(self, src, payload):
            self.out.append(await self.ddb_get("k1"))
            self.out.append(await self.ddb_get("nope"))
            try:
                await self.ddb_put("k2", b"v")
            except Exception as e:
                self.out.append(f"{type(e).__name__}: {e}")
            self.out.append(await self.spawn_child("probe", {"a": 1}))
            self.watch("cfg/", lambda ev, key, val: self.out.append((ev, key, val)))

    async def main():
        frames: list = []
        ctx = make(Caller, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        ctx.feed(msg("p", b"go"))

        async def answer(kind, **kw):
            await until(lambda: any(f.WhichOneof("msg") == kind for f in frames))
            f = next(f for f in frames if f.WhichOneof("msg") == kind)
            frames.remove(f)
            ctx.feed(pb.HostToAgent(answer=pb.HostToAgent.Answer(req_id=getattr(f, kind).req_id, **kw)))
            return getattr(f, kind)

        assert (await answer("ddb_get", ok=True, value=b"V1")).key == "k1"
        assert (await answer("ddb_get", ok=True, missing=True)).key == "nope"
        put = await answer("ddb_put", ok=False, error="not committed")
        assert (put.key, put.value, put.type_name) == ("k2", b"v", "blob")
        sc = await answer("spawn_child", ok=True, value=b"child-id")
        assert (sc.type_name, json.loads(sc.config)) == ("probe", {"a": 1})
        await until(lambda: any(f.WhichOneof("msg") == "ddb_watch" for f in frames))
        w = next(f.ddb_watch for f in frames if f.WhichOneof("msg") == "ddb_watch")
        assert w.prefix == "cfg/"
        ctx.feed(pb.HostToAgent(watch_event=pb.HostToAgent.WatchEvent(watch_id=w.watch_id, event="add", key="cfg/a",
                                                                       has_value=True, value=b"1")))
        await until(lambda: len(ctx.agent.out) == 5)
        assert ctx.agent.out == [b"V1", None, "HostError: ddb_put 'k2': not committed", "child-id",
                                 ("add", "cfg/a", b"1")]
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0

    run(main())


# ------------------------------------------------------------------------------------------ registry


def test_registry_validates_types():
    class NoType(AgentBase):
        pass

    class BadRecovery(AgentBase):
        TYPE = "t-bad-recovery"
        RECOVERY = "sometimes"

    class BadPenalty(AgentBase):
        TYPE = "t-bad-penalty"
        TRANSFER_PENALTY = 2

    class BadHardware(AgentBase):
        TYPE = "t-bad-hw"
        HARDWARE = ["camera"]

    with pytest.raises(ValueError, match=r"TYPE must match"):
        registry.register(NoType)
    with pytest.raises(ValueError, match=r"RECOVERY must be one of \['backup', 'none', 'restart'\], got 'sometimes'"):
        registry.register(BadRecovery)
    with pytest.raises(ValueError, match=r"TRANSFER_PENALTY must be in \[0, 1\], got 2"):
        registry.register(BadPenalty)
    with pytest.raises(ValueError, match=r"HARDWARE must be a frozenset"):
        registry.register(BadHardware)
    with pytest.raises(TypeError, match="not a subclass"):
        registry.register(dict)  # type: ignore[arg-type]
    assert "t-bad-recovery" not in registry.REGISTRY


def test_registry_register_get_and_conflicts():
    class One(AgentBase):
        TYPE = "t-one"
        COST = 0.5
        HARDWARE = frozenset({"camera"})

    class Other(AgentBase):
        TYPE = "t-one"

    try:
        assert registry.register(One) is One
        assert registry.register(One) is One  # idempotent
        assert registry.get("t-one") is One
        with pytest.raises(ValueError, match="already registered"):
            registry.register(Other)
        with pytest.raises(LookupError, match=r"unknown agent type 'nope' \(registered: .*t-one"):
            registry.get("nope")
        info = registry.type_info(One)
        assert info["cost"] == 0.5 and info["hardware"] == ["camera"] and info["recovery"] == "backup"
    finally:
        registry.REGISTRY.pop("t-one", None)


def test_load_all_finds_demo_types_and_reports_bad_modules(monkeypatch):
    monkeypatch.setenv(registry.ENV_MODULES, "haa.agents.no_such_module")
    errors = registry.load_all()
    assert {"counter", "spawner", "busy", "probe", "executive_mission", "supervisor_slam"} <= set(registry.known())
    assert any("haa.agents.no_such_module" in e and "ModuleNotFoundError" in e for e in errors)
    assert registry.get("counter").__module__ == "haa.lab.demoagents"


_LAZY_PROBE = """
import sys
from haa.sdk import registry
import haa.hostd.daemon, haa.sdk.base, haa.sdk.runner, haa.sdk.forkserver, haa.sdk.recorder
assert registry.load_all() == []
{extra}
team = ("haa.agents.", "haa.control", "haa.slam", "haa.sim", "haa.mission", "haa.lab")
print(sorted(m for m in sys.modules if m.startswith(team)))
"""


def _imported_after(extra: str = "") -> list[str]:
    r = subprocess.run([sys.executable, "-c", _LAZY_PROBE.format(extra=extra)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    return ast.literal_eval(r.stdout.strip().splitlines()[-1])


def test_the_sdk_and_the_daemon_import_no_team_or_lab_module_until_a_type_is_asked_for():
    """Every built-in type is known by name (entry points) without importing its module; asking for one imports
    its module only (the demo agents are the lab's, the supervisor the team's)."""
    assert _imported_after() == []
    after = _imported_after("registry.get('counter')")
    assert after == ["haa.lab", "haa.lab.demoagents"]
    after = _imported_after("registry.get('supervisor_explore')")
    assert "haa.agents.supervisor_explore" in after and not any(m.startswith("haa.lab") for m in after)


def test_a_lazy_type_whose_class_does_not_match_its_entry_point_is_refused(monkeypatch):
    import importlib.metadata as md

    ep = md.EntryPoint(name="t-lazy-wrong", value="haa.lab.demoagents:CounterAgent", group=registry.ENTRY_POINT_GROUP)
    monkeypatch.setitem(registry.LAZY, "t-lazy-wrong", ep)
    with pytest.raises(registry.TypeLoadError, match="TYPE is 'counter', not the entry point's name"):
        registry.get("t-lazy-wrong")
    ep = md.EntryPoint(name="t-lazy-gone", value="haa.lab.no_such:Thing", group=registry.ENTRY_POINT_GROUP)
    monkeypatch.setitem(registry.LAZY, "t-lazy-gone", ep)
    with pytest.raises(registry.TypeLoadError, match=r"t-lazy-gone.*ModuleNotFoundError"):
        registry.get("t-lazy-gone")
    assert "t-lazy-gone" not in registry.REGISTRY


def test_names_follow_parentage():
    assert root_name(6) == "A6"
    assert child_name("A6.2", 1) == "A6.2.1"
    with pytest.raises(ValueError, match="numbered from 1"):
        child_name("A6", 0)
    a, b = new_agent_id(), new_agent_id()
    assert a != b and len(a) == 36


class Sync(AgentBase):
    TYPE = "t-sync"

    def __init__(self, ctx):
        super().__init__(ctx)
        self.n = 0

    async def on_message(self, src, payload):
        self.n += 1  # never awaits


def test_a_long_backlog_of_sync_handlers_lets_other_tasks_run():
    async def main():
        frames: list = []
        ctx = make(Sync, frames)
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        for _ in range(5000):
            ctx.feed(msg("p", b"x"))
        beats = 0

        async def other():  # stands for the heartbeat task
            nonlocal beats
            while True:
                beats += 1
                await asyncio.sleep(0)

        t = asyncio.create_task(other())
        await until(lambda: ctx.agent.n == 5000)
        t.cancel()
        assert beats > 1000  # the other task ran while the backlog was handled, not only after it
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0

    run(main())


# ------------------------------------------------------------------ the agent's clock and random source
from haa.sdk.base import Clock, ScaledClock, agent_random  # noqa: E402


class Clocked(AgentBase):
    TYPE = "t-clocked"

    def __init__(self, ctx):
        super().__init__(ctx)
        self.ticks: list[float] = []
        self.once_at: float | None = None

    async def on_start(self):
        self.every(0.4, lambda: self.ticks.append(self.now()))
        self.call_later(1.0, self._once)

    def _once(self):
        self.once_at = self.now()


def test_default_clock_is_the_wall_clock():
    import time as _time

    frames: list = []
    ctx = make(Clocked, frames)
    assert ctx.clock.wall_delay(2.5) == 2.5
    assert abs(ctx.agent.now() - _time.time()) < 1.0


def test_timers_and_now_follow_a_scaled_clock():
    async def main():
        frames: list = []
        ctx = make(Clocked, frames)
        ctx.set_clock(ScaledClock(speed=10.0, start=100.0), seed=7)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        worker = asyncio.create_task(ctx.run())
        start(ctx)
        # 1 simulated second at speed 10 is 0.1 s of wall time; a wall-clock timer would take 1 s
        await until(lambda: ctx.agent.once_at is not None, timeout=0.8)
        wall = loop.time() - t0
        assert wall < 0.6
        assert 100.9 <= ctx.agent.once_at <= 100.0 + 10 * wall + 0.2
        await until(lambda: len(ctx.agent.ticks) >= 3, timeout=1.0)
        gaps = [b - a for a, b in zip(ctx.agent.ticks, ctx.agent.ticks[1:], strict=False)]
        assert all(0.25 <= g <= 1.0 for g in gaps), gaps  # 0.4 simulated seconds apart (loaded CI: slack)
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0

    run(main())


def test_seeded_random_source():
    frames: list = []
    a, b = make(Clocked, frames, name="A3"), make(Clocked, frames, name="A3")
    # different UUIDs: by default two instances draw differently
    assert [a.agent.random.random() for _ in range(3)] != [b.agent.random.random() for _ in range(3)]
    a.set_clock(Clock(), seed=42)
    b.set_clock(Clock(), seed=42)
    assert [a.agent.random.random() for _ in range(5)] == [b.agent.random.random() for _ in range(5)]
    c = make(Clocked, frames, name="A4")
    c.set_clock(Clock(), seed=42)
    d = make(Clocked, frames, name="A3", epoch=2)
    d.set_clock(Clock(), seed=42)
    first = agent_random(42, "A3", 1).random()
    assert c.agent.random.random() != first and d.agent.random.random() != first


def test_scaled_clock():
    clk = ScaledClock(4.0, start=10.0, wall_start=0.0)
    assert clk.wall_delay(8.0) == 2.0
    import time as _time

    assert abs(clk.now() - (10.0 + 4.0 * _time.monotonic())) < 0.5
    for bad in (0, -1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="speed"):
            ScaledClock(bad)
