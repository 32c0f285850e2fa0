"""Idempotent spawn (docs/agents.md, "Idempotent spawn"): `spawn_child(key=)`, the key in SpawnChild and
AgentCreate, and `AgentTable.child_by_key`, which answers a create whose (parent, key) already names a live
child with that child instead of creating a second one."""

from __future__ import annotations

import asyncio
import hashlib
import json

import pytest
from helpers import until

from haa.core.agentio import AnswerAgent
from haa.core.agents import agentrequests as ops
from haa.core.ddb import agenttable as at
from haa.pb import agent_pb2 as pb
from haa.sdk.base import MAX_SPAWN_KEY, AgentBase, AgentContext, new_agent_id


def create(t: at.AgentTable, agent: str, parent: str = "", key: str = "", type_name: str = "probe") -> at.AgentApplied:
    tx = ops.create(agent, type_name, b"{}", parent, "h1", 0.1, (), 0.1, "backup", 0, key)
    return t.apply(at.encode(tx), ("h1",))


def table_with_parent() -> at.AgentTable:
    t = at.AgentTable()
    assert create(t, "p").ok
    return t


def test_a_create_with_a_key_the_parent_used_applies_as_the_existing_child():
    t = table_with_parent()
    first = create(t, "c1", "p", "k")
    assert first.ok and not first.existing and first.agent == "c1"
    again = create(t, "c2", "p", "k")
    assert again.ok and again.existing and again.agent == "c1"
    assert "c2" not in t.records and t.records["p"].children == 1  # nothing created, no name used up
    assert t.child_by_key("p", "k") is t.records["c1"]
    # another key, another parent, or no key: a new child each time
    assert not create(t, "c3", "p", "j").existing
    assert create(t, "q", "", "").ok and not create(t, "c4", "q", "k").existing
    assert not create(t, "c5", "p", "").existing and not create(t, "c6", "p", "").existing
    assert t.child_by_key("p", "") is None
    assert [t.records[c].name for c in ("c1", "c3", "c5", "c6")] == ["A1.1", "A1.2", "A1.3", "A1.4"]


def test_a_failed_or_removed_child_is_not_returned_a_new_one_is_created():
    t = table_with_parent()
    create(t, "c1", "p", "k")
    t.records["c1"].status = at.FAILED
    assert create(t, "c2", "p", "k").agent == "c2"
    assert t.child_by_key("p", "k") is t.records["c2"]
    t.records["c2"].status = at.CRASHED  # crashed is recovered: still the child
    assert create(t, "c3", "p", "k").existing
    del t.records["c2"]
    t.records["c1"].status = at.ACTIVE
    assert create(t, "c4", "p", "k").agent == "c1"


def test_the_key_survives_a_snapshot_and_is_bounded():
    t = table_with_parent()
    create(t, "c1", "p", "k")
    r = at.AgentTable.restore(t.snapshot())
    assert r.child_by_key("p", "k") is not None and create(r, "c2", "p", "k").agent == "c1"
    assert r.content_hash() == t.content_hash()
    long = create(t, "c3", "p", "x" * (at.MAX_SPAWN_KEY + 1))
    assert not long.ok and "key must be at most" in long.reason
    orphan = create(t, "c4", "", "k")
    assert not orphan.ok and "needs a parent" in orphan.reason


def test_a_retried_spawn_is_answered_with_the_existing_child():
    t = table_with_parent()
    create(t, "c1", "p", "k")
    o = ops.Operations(lambda: t)
    (prop,) = o.create(ops.create("c2", "probe", b"", "p", "h1", 0.1, (), 0.1, "backup", 0, "k"),
                       ("child", "p", 3, 7))
    res = t.apply(at.encode(prop.tx), ("h1",))
    assert o.done(prop.epoch, "c2", True, "", res) == [AnswerAgent("p", 3, 7, True, "c1", "")]


class Spawner(AgentBase):
    TYPE = "spawn-key-test"

    def __init__(self, ctx: AgentContext) -> None:
        super().__init__(ctx)
        self.kids: list[str] = []

    async def on_message(self, src: str, payload: bytes) -> None:
        cmd = json.loads(payload)
        kw = {"key": cmd["key"]} if "key" in cmd else {}
        self.kids.append(await self.spawn_child(cmd["type"], cmd.get("config", {}), **kw))


def test_the_default_key_is_type_config_digest_and_count():
    frames: list[pb.AgentToHost] = []

    async def main() -> list[str]:
        init = pb.HostToAgent.Init(agent_id=new_agent_id(), name="A1", type_name=Spawner.TYPE, epoch=1, host="h1")
        ctx = AgentContext(init, Spawner, frames.append)
        worker = asyncio.create_task(ctx.run())
        ctx.feed(pb.HostToAgent(start=pb.HostToAgent.Start()))
        ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how="start")))
        keys = []
        for cmd in ({"type": "a"}, {"type": "a"}, {"type": "a", "config": {"x": 1}}, {"type": "b"},
                    {"type": "a", "key": "mine"}, {"type": "a", "key": ""}):
            ctx.feed(pb.HostToAgent(deliver=pb.AgentMsg(src="op", dst=init.agent_id, payload=json.dumps(cmd).encode())))
            asks = await until(lambda: [f for f in frames if f.WhichOneof("msg") == "spawn_child"],
                               what="the agent's spawn_child")
            (f,) = asks
            frames.remove(f)
            keys.append(f.spawn_child.key)
            ctx.feed(pb.HostToAgent(answer=pb.HostToAgent.Answer(req_id=f.spawn_child.req_id, ok=True, value=b"id")))
        ctx.feed(pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        assert await asyncio.wait_for(worker, 5) == 0
        return keys

    keys = asyncio.run(main())

    def digest(config: bytes) -> str:
        return hashlib.sha256(config).hexdigest()[:16]

    empty, x1 = digest(b"{}"), digest(b'{"x":1}')
    assert keys == [f"a/{empty}/1", f"a/{empty}/2", f"a/{x1}/1", f"b/{empty}/1", "mine", ""]


def test_an_overlong_key_is_refused_in_the_agent():
    class Ctx:
        async def spawn_child(self, *a: object, **kw: object) -> str:  # pragma: no cover - never reached
            raise AssertionError

    agent = AgentBase.__new__(AgentBase)
    agent._ctx = Ctx()  # type: ignore[assignment]
    with pytest.raises(ValueError, match="key: at most"):
        asyncio.run(agent.spawn_child("a", b"", key="k" * (MAX_SPAWN_KEY + 1)))
