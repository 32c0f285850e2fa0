"""The parts HostRuntime owns, each alone — no server, no sockets.

The effect dispatcher (every effect reaches its part; an effect outside the closed union is an error, not a
silent drop), the timer wheel, the delivered log, propose waiters and latencies, the host's writes (driven by a
fake node that commits on the next loop turn), mirror subscribers, the agent operations, the data directory,
and the composition root (`build_host`).
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import pytest
from helpers import until

from haa.core import agentio as io
from haa.core.ddb import ops as ddb
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import MAX_JSON_VALUE_BYTES, MAX_VALUE_BYTES
from haa.core.effects import CancelTimer, Closed, Decided, Deliver, Log, Reincarnate, Send, SetTimer
from haa.core.membership.globalstate import TxDdb, encode_tx
from haa.core.membership.membership import AppliedTx, Connect, Left, WriteDone
from haa.core.messages import Heartbeat, TxId
from haa.hostd.agentops import AgentOps
from haa.hostd.datadir import HostDataDir
from haa.hostd.delivered import GENESIS_HASH, DeliveredLog, chain_hash
from haa.hostd.dispatch import EffectDispatcher
from haa.hostd.mirrors import Mirrors
from haa.hostd.outcomes import InvalidWrite, NotMembershipMode, TransactionAborted, WriteFailed
from haa.hostd.proposals import Proposals
from haa.hostd.timers import TimerWheel
from haa.hostd.writes import Writes
from haa.pb import control_pb2 as cpb

# ----------------------------------------------------------------------------------------------- fakes


class FakeTransport:
    def __init__(self) -> None:
        self.sent: list[tuple[str, int, Any, bool]] = []
        self.peers: dict[str, str] = {}

    def send(self, dst: str, dst_inc: int, msg: Any, lazy: bool = False) -> None:
        self.sent.append((dst, dst_inc, msg, lazy))

    def add_peer(self, name: str, addr: str) -> None:
        self.peers[name] = addr


class FakeTimers:
    def __init__(self) -> None:
        self.armed: dict[Hashable, float] = {}

    def set(self, key: Hashable, at: float) -> None:
        self.armed[key] = at

    def cancel(self, key: Hashable) -> None:
        self.armed.pop(key, None)


class FakeBackend:
    def __init__(self) -> None:
        self.commands: list[Any] = []
        self.timeline: list[io.AgentTimeline] = []

    async def start(self, host: AgentOps) -> None: ...

    async def close(self) -> None: ...

    def command(self, c: Any) -> None:
        self.commands.append(c)

    def on_timeline(self, e: io.AgentTimeline) -> None:
        self.timeline.append(e)

    def check_replica(self) -> None: ...

    def kill_all(self, reason: str) -> None: ...

    def backlog(self) -> int:
        return 0


def _no_writes() -> Writes:
    def propose(payload: bytes, req: int, kind: str, cost: int = 1) -> None:
        raise AssertionError("no write expected")

    return Writes("h1", Counter(), propose, lambda: None, lambda: False, iter(range(1, 10**6)).__next__)


def _dispatcher(tmp_path: Path, agents: FakeBackend | None = None) -> tuple[EffectDispatcher, dict[str, Any]]:
    parts: dict[str, Any] = {
        "transport": FakeTransport(),
        "timers": FakeTimers(),
        "proposals": Proposals("h1"),
        "delivered": DeliveredLog(),
        "writes": _no_writes(),
        "mirrors": Mirrors(),
        "data": HostDataDir("h1", tmp_path),
        "counters": Counter(),
        "left": [],
    }
    parts["agent_ops"] = AgentOps("h1", parts["counters"], lambda: None, lambda fn, *a: None,
                                  lambda ops, atomic: _never(), iter(range(1, 100)).__next__)
    d = EffectDispatcher(
        transport=parts["transport"], timers=parts["timers"], proposals=parts["proposals"],
        delivered=parts["delivered"], writes=parts["writes"], mirrors=parts["mirrors"],
        agent_ops=parts["agent_ops"], agents=agents, data=parts["data"], counters=parts["counters"],
        on_left=lambda: parts["left"].append(True),
    )
    return d, parts


async def _never() -> Any:
    raise AssertionError("no DDB write expected")


# ----------------------------------------------------------------------------------------------- dispatcher


def test_each_effect_reaches_its_part(tmp_path: Path) -> None:
    backend = FakeBackend()
    d, p = _dispatcher(tmp_path, backend)
    t1, t2 = TxId("h1", 1, 1), TxId("h2", 1, 1)
    hb = Heartbeat(1, 0.1, 0.0)
    spawn = io.SpawnShell("a", 1, "counter", "A1", b"", "")
    timeline = io.AgentTimeline("a", "A1", "active", "h1", "")
    by = d.run([
        Send("h2", 7, hb, True),
        SetTimer(("hb", "h2"), 5.0),
        SetTimer(("fd", "h2"), 6.0),
        CancelTimer(("fd", "h2")),
        Decided(t1, True),
        Deliver(t1, 1, b"x"),
        Decided(t2, False),
        Closed(t1),
        Log("something", {"k": 1}),
        Connect("h3", "127.0.0.1:3"),
        spawn,
        timeline,
        Reincarnate("h2"),
        Left(),
    ])
    assert by == "h2"  # returned, not carried out: the runtime reincarnates after the whole list
    assert p["transport"].sent == [("h2", 7, hb, True)]
    assert p["transport"].peers == {"h3": "127.0.0.1:3"}
    assert p["timers"].armed == {("hb", "h2"): 5.0}
    log_: DeliveredLog = p["delivered"]
    assert [e.txid for e in log_.entries] == [t1] and log_.hash == chain_hash(GENESIS_HASH, t1, b"x")
    c = p["counters"]
    assert (c["oac_committed"], c["oac_aborted"], c["oac_delivered"], c["oac_closed"]) == (1, 1, 1, 1)
    assert backend.commands == [spawn] and backend.timeline == [timeline]
    assert p["left"] == [True]


def test_agent_effects_without_a_backend_are_dropped_and_operator_answers_wake_their_callers(tmp_path: Path) -> None:
    d, p = _dispatcher(tmp_path, None)
    ops: AgentOps = p["agent_ops"]
    assert d.run([io.KillAgent("a", 1, "test"), io.AgentOpDone(("op", 9), True), io.OperatorReply(3, b"r", "")]) is None
    # nobody waited for those answers: nothing to wake, nothing kept
    assert not ops._ops and not ops._requests


def test_an_effect_outside_the_union_is_an_error_not_a_silent_drop(tmp_path: Path) -> None:
    d, _p = _dispatcher(tmp_path)
    with pytest.raises(AssertionError):
        d.run(["not an effect"])  # type: ignore[list-item]


def test_view_changes_and_applied_batches_feed_counters_mirrors_and_known_hosts(tmp_path: Path) -> None:
    async def main() -> None:
        d, p = _dispatcher(tmp_path)
        mirrors: Mirrors = p["mirrors"]
        replica = Ddb()
        sub = mirrors.subscribe(views=True, replica=replica)
        batch = ddb.encode_batch([ddb.put("k", "counter", 1)], origin="h1")
        res = replica.apply(batch)
        tx = encode_tx(TxDdb(batch))
        d.run([AppliedTx(4, TxId("h1", 1, 1), "ddb", tx, "", res)])
        assert p["counters"]["global_applied"] == 1
        assert await sub.get() == ("batch", res.seq, batch, 4)
        # a new replica object (a joiner installed its sponsor's state): the subscriber resyncs
        mirrors.check_replica(replica)
        assert not sub.queue
        mirrors.check_replica(Ddb())
        assert await sub.get() == ("resync",)
        mirrors.close()
        assert await sub.get() is None

    asyncio.run(main())


# ----------------------------------------------------------------------------------------------- timers


def test_timer_wheel_replaces_cancels_and_reports_the_deadline() -> None:
    async def main() -> None:
        fired: list[tuple[Hashable, float]] = []
        wheel = TimerWheel(lambda key, at: fired.append((key, at)))
        wheel.start(asyncio.get_running_loop())
        t = time.monotonic()
        wheel.set("x", t + 0.02)
        wheel.set("x", t + 0.04)  # replaces the first
        wheel.set("y", t + 0.01)
        wheel.set("z", t + 0.01)
        wheel.cancel("z")
        assert len(wheel) == 2
        await until(lambda: len(fired) == 2, what="two timers")
        assert fired == [("y", t + 0.01), ("x", t + 0.04)] and len(wheel) == 0
        wheel.set("w", t + 10)
        wheel.clear()
        assert len(wheel) == 0

    asyncio.run(main())


# ----------------------------------------------------------------------------------------------- proposals


def test_proposals_time_both_latencies_and_answer_their_waiters() -> None:
    async def main() -> None:
        pr = Proposals("h1")
        a, b, own = TxId("h1", 1, 1), TxId("h1", 1, 2), TxId("h1", 1, 3)

        class Oac:
            _seq = 2
            inc = 1

        pr._proposed_at[a] = 10.0  # proposed through the runtime: dated at once
        pr._proposed_at[b] = 10.0
        pr.catch_up(Oac(), lambda: 10.2)  # type: ignore[arg-type]  # already dated: kept
        assert pr._proposed_at == {a: 10.0, b: 10.0}
        fut_a, fut_b = pr.expect(a), pr.expect(b)
        pr.decided(10.5, Decided(a, True))
        pr.decided(10.7, Decided(b, False))
        d2d = pr.delivering(11.0, Deliver(a, 1, b""))
        pr.delivered(a, d2d)
        res = await pr.wait(a, fut_a, 1.0)
        assert (res.propose_to_decide, res.decide_to_deliver) == (0.5, 0.5)
        with pytest.raises(TransactionAborted):
            await pr.wait(b, fut_b, 1.0)
        assert pr.take_latencies(reset=True) == ([0.5], [0.5, pytest.approx(0.7)])
        assert pr.take_latencies(reset=False) == ([], [])

        # a transaction the machines proposed themselves is dated at the next input (OAC numbers them)
        Oac._seq = 3
        pr.catch_up(Oac(), lambda: 20.0)  # type: ignore[arg-type]
        assert pr._proposed_at == {own: 20.0}
        pr.catch_up(Oac(), lambda: pytest.fail("the clock is read only when there is something to date"))  # type: ignore[arg-type]

    asyncio.run(main())


# ----------------------------------------------------------------------------------------------- writes


class FakeNode:
    """Commits each submitted batch on the next loop turn by applying it to one replica (as OAC would)."""

    def __init__(self, writes: Callable[[], Writes]) -> None:
        self.writes = writes
        self.replica = Ddb()
        self.batches: list[tuple[int, bool]] = []  # (ops, atomic)

    def propose(self, payload: bytes, req: int, kind: str, cost: int = 1) -> None:
        assert kind == "ddb"
        res = self.replica.apply(payload)
        self.batches.append((len(res.results), res.atomic))
        done = WriteDone(req, True, TxId("h1", 1, req), len(self.batches), "", res)
        asyncio.get_running_loop().call_soon(self.writes().done, done)


def _writes(closed: Callable[[], bool] = lambda: False) -> tuple[Writes, FakeNode]:
    w: list[Writes] = []
    node = FakeNode(lambda: w[0])
    w.append(Writes("h1", Counter(), node.propose, lambda: None, closed, iter(range(1, 10**6)).__next__))
    return w[0], node


def test_each_ddb_write_is_one_batch_with_its_own_results() -> None:
    async def main() -> None:
        wr, node = _writes()
        writes = [wr.ddb_write([ddb.put(f"k{i}", "counter", i), ddb.add(f"k{i}", 10)]) for i in range(20)]
        writes.append(wr.ddb_write([ddb.cas("k0", 999, "counter", 1), ddb.put("k99", "counter", 1)], atomic=True))
        res = await asyncio.gather(*writes)
        for i, r in enumerate(res[:20]):
            assert [(o.key, o.ok) for o in r.results] == [(f"k{i}", True), (f"k{i}", True)]
        # all or none covers exactly the atomic request's ops: the stale cas fails, so k99 is not written
        assert [o.ok for o in res[20].results] == [False, False] and node.replica.get("k99") is None
        assert node.replica.get("k7").value == 17
        # one batch per request, in request order (the sequencer is the one batching layer, in the core)
        assert node.batches == [(2, False)] * 20 + [(2, True)]
        assert [r.ddb_seq for r in res] == list(range(1, 22))
        assert wr.counters["ddb_writes"] == 21

    asyncio.run(main())


def test_a_bad_write_is_refused_where_it_enters_and_nothing_is_proposed() -> None:
    async def main() -> None:
        closed = [False]
        wr, node = _writes(lambda: closed[0])
        with pytest.raises(InvalidWrite, match="empty batch"):
            await wr.ddb_write([])
        big = [ddb.put(f"k{i}", "blob", b"x" * MAX_VALUE_BYTES) for i in range(3)]
        with pytest.raises(InvalidWrite, match="MAX_BATCH_BYTES"):
            await wr.ddb_write(big)
        js = [ddb._op(put=ddb.pb.DdbPut(key=f"j{i}", type="json", value=b"1" * (MAX_JSON_VALUE_BYTES // 2)))
              for i in range(3)]
        with pytest.raises(InvalidWrite, match="MAX_BATCH_JSON_BYTES"):
            await wr.ddb_write(js)
        assert node.batches == [] and wr.counters["ddb_writes"] == 0
        closed[0] = True
        with pytest.raises(WriteFailed, match="stopping or left"):
            await wr.ddb_write([ddb.put("k", "counter", 1)])
        assert node.batches == []

    asyncio.run(main())


def test_open_writes_end_on_a_new_incarnation() -> None:
    async def main() -> None:
        def propose(payload: bytes, req: int, kind: str, cost: int = 1) -> None:
            pass  # never committed

        gc = Writes("h1", Counter(), propose, lambda: None, lambda: False, iter(range(1, 100)).__next__)
        w = asyncio.ensure_future(gc.submit(b"t", "test", timeout=5))
        x = asyncio.ensure_future(gc.ddb_write([ddb.put("k", "counter", 1)], timeout=5))
        await until(lambda: len(gc._writes) == 2, what="both writes proposed")
        gc.fail_all(lambda: WriteFailed("restarted"))
        gc.forget()
        for f in (w, x):
            with pytest.raises(WriteFailed, match="restarted"):
                await f

    asyncio.run(main())


# ----------------------------------------------------------------------------------------------- agent ops, data dir


def test_agent_operations_need_the_agent_layer() -> None:
    async def main() -> None:
        ops = AgentOps("h1", Counter(), lambda: None, lambda fn, *a: None, lambda o, a: _never(),
                       iter(range(1, 10)).__next__)
        with pytest.raises(NotMembershipMode):
            await ops.agent_request("A1", b"")
        with pytest.raises(NotMembershipMode):
            await ops.agent_op(lambda now, **kw: None)
        assert ops.local_replica() is None and ops.agent_table() is None
        ops.on_agent_event(io.ShellReady("a", 1))  # no agent layer: nothing to feed

    asyncio.run(main())


def test_incarnations_increase_strictly_and_known_hosts_round_trip(tmp_path: Path) -> None:
    class M:
        def __init__(self, name: str, addr: str) -> None:
            self.name, self.addr = name, addr

    data = HostDataDir("h1", tmp_path)
    first = data.new_incarnation(0)
    assert HostDataDir("h1", tmp_path).new_incarnation(0) > first  # above the recorded one, whatever the clock
    assert data.new_incarnation(10**30) == 10**30 + 1
    assert data.load_known_hosts() == []
    data.save_known_hosts([M("h1", "a:1"), M("h2", "b:2")])
    assert HostDataDir("h1", tmp_path).load_known_hosts() == [("h2", "b:2")]
    data.forget_known_hosts()
    assert data.load_known_hosts() == []
    nowhere = HostDataDir("h1", None)  # no data dir: nothing read or written
    nowhere.save_known_hosts([M("h2", "b:2")])
    assert nowhere.load_known_hosts() == [] and nowhere.new_incarnation(5) > 5


# ----------------------------------------------------------------------------------------------- composition


def test_build_host_gives_the_runtime_its_driver_and_serves_the_control_api(tmp_path: Path) -> None:
    from haa.hostd.agentdriver import AgentDriver
    from haa.hostd.daemon import build_host
    from haa.hostd.runtime import RuntimeConfig

    cfg = RuntimeConfig(name="h1", listen="127.0.0.1:0", peers={}, token="t", data_dir=tmp_path,
                        core_processes=[("h1", "127.0.0.1:1")])
    host = build_host(cfg)
    assert isinstance(host.agents, AgentDriver)
    assert host.runtime.agents is host.agents and host.control.agents is host.agents
    assert host.control.rt is host.runtime and host.runtime._services == [host.control]
    static = build_host(RuntimeConfig(name="h1", listen="127.0.0.1:0", peers={"h2": "127.0.0.1:2"}, token="t"))
    assert static.agents is None and static.runtime.agents is None


# ----------------------------------------------------------------------------------------------- mirror bounds


def test_mirror_streams_are_bounded_per_host_and_per_client() -> None:
    from haa.hostd.mirrors import MirrorRefused

    async def main() -> None:
        m, db = Mirrors(max_subs=5, max_per_client=3), Ddb()
        subs = [m.subscribe(True, db, "10.0.0.1") for _ in range(3)]
        with pytest.raises(MirrorRefused, match=r"10\.0\.0\.1 has 3 mirror streams here.*MAX_MIRRORS_PER_CLIENT"):
            m.subscribe(True, db, "10.0.0.1")
        subs += [m.subscribe(True, db, "10.0.0.2") for _ in range(2)]
        with pytest.raises(MirrorRefused, match=r"serves 5 mirror streams.*MAX_MIRRORS"):
            m.subscribe(True, db, "10.0.0.3")
        m.unsubscribe(subs[0])
        assert m.subscribe(True, db, "10.0.0.1").client == "10.0.0.1"  # a freed place is taken again

    asyncio.run(main())


def test_a_mirror_snapshot_is_built_once_and_later_subscribers_catch_up_from_the_ring() -> None:
    from haa.hostd.mirrors import snapshot_event

    async def main() -> None:
        db, m = Ddb(), Mirrors()
        db.apply(ddb.encode_batch([ddb.put(f"k{i}", "blob", bytes(300)) for i in range(500)]), 7)
        ev = cpb.MirrorEvent.FromString(snapshot_event(db))  # serialized without decoding the snapshot
        assert ev.WhichOneof("event") == "snapshot" and ev.ddb_hash == db.content_hash()
        assert Ddb.restore(ev.snapshot.SerializeToString()).content_hash() == db.content_hash()
        m.subscribe(True, db)
        first, since = m.snapshot(db)
        assert first.seq == 1 and since == []
        db.apply(ddb.encode_batch([ddb.put("late", "counter", 1)]), 8)  # meta: the global seq
        again, since = m.snapshot(db)
        assert again is first and [(e.seq, e.meta) for e in since] == [(2, 8)]  # shared, plus the catch-up
        replica = Ddb.restore(cpb.MirrorEvent.FromString(again.event).snapshot.SerializeToString())
        for e in since:
            replica.apply(e.payload)
        assert replica.content_hash() == db.content_hash()
        other = Ddb()
        assert m.snapshot(other)[0].replica is other  # another replica object: a new snapshot

    asyncio.run(main())
