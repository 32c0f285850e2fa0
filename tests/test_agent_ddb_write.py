"""Agents' batched DDB writes and log watches: `AgentBase.ddb_write`, `ddb_log_append` and `watch_log`.

Three levels: the agent's side in-process (AgentContext and its frames); the host's side (AgentDriver's checks
before anything is proposed, fencing, the per-op results, log events with their indexes) with a fake runtime;
and end to end, a real one-host group (haa-hostd) running the `probe` demo agent in its own process, which
writes an atomic batch and sees the log's events with their indexes."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import run, until

from haa.cluster.hostprocs import MemberGroup, MemberHost
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import ops as ddb
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import MAX_LOG_ITEM_BYTES
from haa.hostd import agentproc as ap
from haa.hostd.agentdriver import AgentDriver
from haa.pb import agent_pb2 as pb
from haa.pb import ddb_pb2
from haa.sdk.base import AgentBase, AgentContext, HostError, new_agent_id

# ============================================================================ the agent's side (in-process)


class Writer(AgentBase):
    TYPE = "t-ddb-writer"

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        self.out: list[Any] = []
        self.seen: list[tuple[int, bytes]] = []

    async def on_message(self, src: str, payload: bytes) -> None:
        if payload == b"write":
            self.out.append(
                await self.ddb_write([ddb.log_append("ev", [b"a", b"b"]), ddb.put("k", "json", 1)], atomic=True)
            )
        elif payload == b"append":
            try:
                await self.ddb_log_append("ev", [b"c"])
                self.out.append("appended")
            except HostError as e:
                self.out.append(f"HostError: {e}")
        elif payload == b"watch":
            self.out.append(self.watch_log("ev", lambda index, item: self.seen.append((index, item))))


def test_the_agent_side_frames_results_and_log_callbacks() -> None:
    async def main() -> None:
        frames: list[pb.AgentToHost] = []
        init = pb.HostToAgent.Init(agent_id=new_agent_id(), name="A1", type_name=Writer.TYPE, epoch=1, host="h1")
        ctx = AgentContext(init, Writer, frames.append)
        worker = asyncio.create_task(ctx.run())
        ctx.feed(pb.HostToAgent(start=pb.HostToAgent.Start()))
        ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="start")))

        async def answer(**kw: Any) -> pb.AgentToHost.DdbWrite:
            await until(lambda: any(f.WhichOneof("msg") == "ddb_write" for f in frames))
            f = next(f for f in frames if f.WhichOneof("msg") == "ddb_write")
            frames.remove(f)
            ctx.feed(pb.HostToAgent(answer=pb.HostToAgent.Answer(req_id=f.ddb_write.req_id, **kw)))
            return f.ddb_write

        def deliver(data: bytes) -> None:
            ctx.feed(pb.HostToAgent(deliver=pb.AgentMsg(src="p", dst=ctx.agent_id, payload=data)))

        deliver(b"write")
        w = await answer(ok=True, op_errors=["", ""])
        assert w.atomic and [op.WhichOneof("op") for op in w.ops] == ["log_append", "put"]
        assert list(w.ops[0].log_append.items) == [b"a", b"b"]
        deliver(b"append")
        w = await answer(ok=True, op_errors=["log full: 'ev' would hold ..."])
        assert not w.atomic and w.ops[0].log_append.key == "ev"
        deliver(b"append")
        await answer(ok=False, error="op 0: invalid key: empty")
        await until(lambda: len(ctx.agent.out) == 3)
        assert ctx.agent.out == [
            ["", ""],
            "HostError: ddb_log_append 'ev': log full: 'ev' would hold ...",
            "HostError: ddb_write of 1 op(s): op 0: invalid key: empty",
        ]

        deliver(b"watch")
        await until(lambda: any(f.WhichOneof("msg") == "ddb_watch" for f in frames))
        watch = next(f.ddb_watch for f in frames if f.WhichOneof("msg") == "ddb_watch")
        assert watch.prefix == "ev"

        def event(kind: str, key: str, index: int, value: bytes | None = None) -> None:
            ev = pb.HostToAgent.WatchEvent(
                watch_id=watch.watch_id,
                event=kind,
                key=key,
                index=index,
                has_value=value is not None,
                value=value or b"",
            )
            ctx.feed(pb.HostToAgent(watch_event=ev))

        event("add", "ev", 0, b"")
        event("append", "ev", 0, b"a")
        event("append", "events", 7, b"other key under the prefix")
        event("append", "ev", 1, b"b")
        event("trim", "ev", 1)
        event("append", "ev", 2, b"c")
        await until(lambda: len(ctx.agent.seen) == 3)
        assert ctx.agent.seen == [(0, b"a"), (1, b"b"), (2, b"c")]
        ctx.agent.unwatch(watch.watch_id)
        assert frames[-1].WhichOneof("msg") == "ddb_unwatch"
        event("append", "ev", 3, b"d")  # after unwatch: dropped
        with pytest.raises(TypeError, match="DdbOp messages"):
            await ctx.ddb_write([b"not an op"], False, 1.0)
        with pytest.raises(ValueError, match="no ops"):
            await ctx.ddb_write([], False, 1.0)
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await worker == 0
        assert ctx.agent.seen == [(0, b"a"), (1, b"b"), (2, b"c")]

    run(main())


# ============================================================================ the host's side (AgentDriver)


class FakeSup:
    def __init__(self) -> None:
        self.answers: list[dict[str, Any]] = []
        self.notified: list[tuple[Any, ...]] = []

    def answer(
        self,
        agent: str,
        req: int,
        ok: bool,
        value: bytes,
        error: str = "",
        *,
        missing: bool = False,
        op_errors: Any = (),
    ) -> bool:
        self.answers.append({"req": req, "ok": ok, "error": error, "op_errors": list(op_errors)})
        return True

    def notify_watch(self, agent: str, wid: int, event: str, key: str, value: bytes | None, index: int = 0) -> bool:
        self.notified.append((wid, event, key, value, index))
        return True


class FakeRuntime:
    """The driver's host (`AgentHost`): commits a write by applying it to one replica, as the runtime's group
    commit does once OAC delivers it."""

    def __init__(self, fenced: bool = False) -> None:
        self.name = "h1"
        self.replica = Ddb()
        self.writes: list[tuple[list[Any], bool]] = []
        self.counters: Counter[str] = Counter()
        self.fenced = fenced

    def local_replica(self) -> Ddb:
        return self.replica

    def agent_table(self) -> None:
        return None

    async def ddb_write(self, ops: list[Any], atomic: bool = False) -> Any:
        self.writes.append((ops, atomic))
        return self.replica.apply(ddb.encode_batch(ops, "h1", len(self.writes), atomic))


def driver(rt: FakeRuntime) -> tuple[AgentDriver, FakeSup]:
    drv = AgentDriver.__new__(AgentDriver)
    drv.host = rt  # type: ignore[assignment]
    drv.sup = FakeSup()  # type: ignore[assignment]
    drv.epochs = {"a": 1}
    drv._tasks = set()
    drv._watches = {}
    drv._ddb_ref = None
    drv._ddb_watch = 0
    drv._fenced = lambda agent: "stale instance (epoch 1)" if rt.fenced else ""  # type: ignore[method-assign]
    rt.counters = Counter()
    return drv, drv.sup  # type: ignore[return-value]


def test_the_driver_checks_every_op_before_proposing_and_answers_per_op() -> None:
    async def main() -> None:
        rt = FakeRuntime()
        drv, sup = driver(rt)
        big = b"x" * (MAX_LOG_ITEM_BYTES + 1)
        refused = {
            1: [ddb.log_append("ok", [b"a"]), ddb.log_append("", [b"a"])],
            2: [ddb.put("k", "blob", b""), ddb_pb2.DdbOp(put=ddb_pb2.DdbPut(key="k", type="nope"))],
            3: [ddb_pb2.DdbOp(log_append=ddb_pb2.DdbLogAppend(key="ev", items=[big]))],
            4: [ddb_pb2.DdbOp(put=ddb_pb2.DdbPut(key="ev", type="log"))],
            5: [],
        }
        for req, ops in refused.items():
            drv._ddb_write(ap.DdbWrite("a", req, tuple(ops), True))
        assert rt.writes == [] and rt.counters["agent_ddb_write_refused"] == 5  # nothing was proposed
        assert [(a["req"], a["ok"], a["error"][:40]) for a in sup.answers] == [
            (1, False, "op 1: invalid key: empty"),
            (2, False, "op 1: unknown type 'nope'"),
            (3, False, "op 0: log item 0 too large: 262145 bytes"),
            (4, False, "op 0: a log is written only by its own o"),
            (5, False, "empty batch"),
        ]
        sup.answers.clear()

        events: list[Any] = []
        drv._watches[("a", 7)] = "ev"
        drv._ensure_ddb_watch()
        rt.replica.watch(events.append)
        ops = (ddb.log_append("ev", [b"a", b"b", b"c"]), ddb.log_trim("ev", 9), ddb.log_trim("ev", 1))
        drv._ddb_write(ap.DdbWrite("a", 10, ops, False))
        drv._ddb_write(ap.DdbWrite("a", 11, (ddb.log_append("ev", [b"d"]), ddb.delete("nope")), True))
        await until(lambda: len(sup.answers) == 2)
        aborted = "atomic batch aborted: op 1 failed: not found: 'nope'"
        assert sup.answers == [
            {
                "req": 10,
                "ok": True,
                "error": "",
                "op_errors": ["", "trim beyond the end: upto 9 > next index 3 of 'ev'", ""],
            },
            {"req": 11, "ok": True, "error": "", "op_errors": [aborted, aborted]},
        ]
        assert [atomic for _ops, atomic in rt.writes] == [False, True]
        # the agent's watch gets each item with its index, and the trim with the new first index
        assert sup.notified == [
            (7, "add", "ev", b"", 0),
            (7, "append", "ev", b"a", 0),
            (7, "append", "ev", b"b", 1),
            (7, "append", "ev", b"c", 2),
            (7, "trim", "ev", None, 1),
        ]

        # an instance the table no longer gives this host writes nothing (as for DdbPut)
        rt.fenced = True
        drv._ddb_write(ap.DdbWrite("a", 12, (ddb.log_append("ev", [b"e"]),), False))
        await until(lambda: len(sup.answers) == 3)
        assert sup.answers[-1]["ok"] is False and "stale instance" in sup.answers[-1]["error"]
        assert len(rt.writes) == 2 and rt.counters["agent_ddb_write_fenced"] == 1

    run(main())


def test_the_driver_answers_a_ddb_get_with_the_stored_bytes() -> None:
    rt = FakeRuntime()
    drv, sup = driver(rt)
    rt.replica.apply(ddb.encode_batch([ddb.log_append("ev", [b"a", b"b"]), ddb.log_trim("ev", 1)]))
    got: list[bytes] = []
    sup.answer = lambda agent, req, ok, value, error="", missing=False, op_errors=(): got.append(value)  # type: ignore[method-assign]
    drv._ddb_get(ap.DdbGet("a", 1, "ev"))
    assert len(got) == 1 and ddb.decode_log(got[0]) == (1, (b"b",))


# ============================================================================ end to end: haa-hostd + probe

TOKEN = "ddb-write-test-token"


@pytest.fixture(scope="module")
def host(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MemberHost]:
    root: Path = tmp_path_factory.mktemp("ddbwrite")
    group = MemberGroup(root, ["h1"], core=1, token=TOKEN, args=["--rebalance-period", "0"])
    h = group["h1"]
    try:
        h.start()
        wait(lambda: len(h.status().members) == 1, 40, "a group of 1")
        wait(lambda: "probe" in h.client.agent_list().agent_types, 20, "the agent types")
        yield h
    finally:
        group.close()


def ask(h: MemberHost, agent: str, cmd: dict[str, Any]) -> Any:
    rep = h.client.agent_request(agent, json.dumps(cmd).encode(), timeout=10)
    if not rep.ok:
        return {"error": rep.error}
    return json.loads(rep.payload)


def test_a_probe_agent_writes_an_atomic_batch_and_sees_log_events_with_indexes(host: MemberHost) -> None:
    r = host.client.agent_spawn("probe", b'{"record": false}')
    assert r.ok, r
    a = r.id
    wait(lambda: {x.id: x for x in host.client.agent_list().agents}[a].status == "active", 20, "the probe active")
    assert ask(host, a, {"op": "watch_log", "key": "mission/events"}) >= 1
    # an atomic batch: two log appends and a json put, committed together
    ops = [
        ["log_append", "mission/events", ["e0", "e1"]],
        ["put", "mission/status", "json", {"state": "running"}],
        ["log_append", "mission/events", ["e2"]],
    ]
    assert ask(host, a, {"op": "ddb_write", "ops": ops, "atomic": True}) == ["", "", ""]
    # an atomic batch with a failing op: nothing of it is written, every op says why
    bad = [["log_append", "mission/events", ["lost"]], ["log_trim", "mission/events", 99]]
    why = "atomic batch aborted: op 1 failed: trim beyond the end: upto 99 > next index 4 of 'mission/events'"
    assert ask(host, a, {"op": "ddb_write", "ops": bad, "atomic": True}) == [why, why]
    # the same ops without atomic: the append is taken, the trim fails alone
    got = ask(host, a, {"op": "ddb_write", "ops": bad})
    assert got == ["", "trim beyond the end: upto 99 > next index 4 of 'mission/events'"]
    assert ask(host, a, {"op": "ddb_write", "ops": [["log_trim", "mission/events", 2]]}) == [""]
    assert ask(host, a, {"op": "ddb_write", "ops": [["log_append", "mission/events", ["e4"]]]}) == [""]
    # refused before anything is proposed: an invalid key
    err = ask(host, a, {"op": "ddb_write", "ops": [["log_append", "mission/events", ["x"]], ["put", "", "blob", "v"]]})
    assert "HostError: ddb_write of 2 op(s): op 1: invalid key: empty" in err["error"]

    assert ask(host, a, {"op": "ddb_log", "key": "mission/events"}) == {"first": 2, "items": ["e2", "lost", "e4"]}
    # a prefix scan from the local replica: key order, values as stored, the limit honoured
    puts = [["put", "avatars/s2", "json", {"n": 2}], ["put", "avatars/s1", "json", {"n": 1}],
            ["put", "avatarsX", "blob", "no"]]
    ask(host, a, {"op": "ddb_write", "ops": puts})
    got = ask(host, a, {"op": "ddb_scan", "prefix": "avatars/"})
    assert got == {"objects": {"avatars/s1": '{"n":1}', "avatars/s2": '{"n":2}'}, "truncated": False}
    assert ask(host, a, {"op": "ddb_scan", "prefix": "avatars/", "limit": 1}) == {
        "objects": {"avatars/s1": '{"n":1}'}, "truncated": True}
    assert ask(host, a, {"op": "ddb_scan", "prefix": "nothing/"}) == {"objects": {}, "truncated": False}
    state = ask(host, a, {"op": "state"})
    logs = [e for e in state["events"] if e[0] == "log"]
    assert logs == [
        ["log", "mission/events", 0, "e0"],
        ["log", "mission/events", 1, "e1"],
        ["log", "mission/events", 2, "e2"],
        ["log", "mission/events", 3, "lost"],
        ["log", "mission/events", 4, "e4"],
    ]
    # what the replica holds, as any reader sees it
    rec = {o.key: o for o in host.client.ddb_get(keys=["mission/events", "mission/status"]).objects}
    assert ddb.decode_log(rec["mission/events"].value) == (2, (b"e2", b"lost", b"e4"))
    assert json.loads(rec["mission/status"].value) == {"state": "running"}
    assert host.client.agent_remove(a).ok
