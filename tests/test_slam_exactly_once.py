"""Each sensor processing is applied exactly once, also across restarts and recoveries (docs/team.md "Failures").

A sensor agent commits the processing's marker `slam/done/<avatar>/<n>/<proc>` in the atomic batch of its
Observe events, with a cas "must not exist"; SupervisorSLAM skips marked processings when it (re)loads the
reading list and deletes the markers with the raw entry; a restarted sensor agent is asked what it still has
(a sync) instead of getting everything again. The agents run on a stand-in context over a real DDB replica
(haa.core.ddb.ddb.Ddb: the batches, the cas and the atomic abort are the DDB's own), with messages routed FIFO
per receiver and held while the receiver is down, as the hosts do.
"""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from types import SimpleNamespace
from typing import Any

import pytest

from haa.agents import team
from haa.agents.sensor_cooccupancy import AgentSensorCooccupancy
from haa.agents.sensor_sonar import AgentSensorSonar
from haa.agents.supervisor_slam import SupervisorSLAM
from haa.core.ddb import ops as ddbops
from haa.core.ddb.ddb import Ddb
from haa.sdk import registry
from haa.slam import events as sev

COOC = "sensor_cooccupancy"


class Bus:
    """The hosts, as far as these agents see them: one DDB replica, message routing (FIFO per receiver; a
    message for an agent that is down waits for its next life), one-shot timers, spawns."""

    def __init__(self) -> None:
        self.ddb = Ddb()
        self.t = 100.0
        self.agents: dict[str, Any] = {}
        self.queue: list[tuple[str, str, dict[str, Any]]] = []  # (src, dst, message), in sending order
        self.sent: list[tuple[str, str, dict[str, Any]]] = []  # everything ever sent
        self.soon: list[Any] = []  # one-shot timers (call_later)
        self.logs: list[tuple[str, str, dict[str, Any]]] = []
        self.backups: dict[str, bytes] = {}
        self.hold: asyncio.Event | None = None  # DDB writes wait for it when set

    def ctx(self, agent_id: str, config: dict[str, Any]) -> Ctx:
        return Ctx(self, agent_id, config)

    def start(self, cls: type, agent_id: str, config: dict[str, Any]) -> Any:
        agent = cls(self.ctx(agent_id, config))
        self.agents[agent_id] = agent
        return agent

    def put_raw(self, avatar: str, n: int, kind: str = "cooccupancy") -> tuple[str, bytes]:
        key = f"{team.K_SLAM_RAW}{avatar}/{n:08d}"
        rec: dict[str, Any] = {"avatar": avatar, "agent": "av-" + avatar, "kind": kind, "t": float(n), "n": n}
        if kind == "cooccupancy":
            rec["radius"] = 0.12
        elif kind == "sonar":
            rec.update(echoes=[[0.0, 1.0], [1.57, None]], max_range=2.0)
        else:
            rec["frame"] = n
        self.ddb.apply(ddbops.encode_batch([ddbops.put(key, "json", rec)]))
        return key, json.dumps(rec).encode()

    def keys(self, prefix: str) -> list[str]:
        return self.ddb.ls(prefix)

    def counter(self, name: str) -> int:
        o = self.ddb.get(team.K_STATS + name)
        return 0 if o is None else int(o.value)

    def log_items(self) -> list[Any]:
        o = self.ddb.get(team.K_SLAM_LOG)
        return [] if o is None else [sev.decode(i) for i in o.value["items"]]

    def processes(self, key: str) -> list[str]:
        """The agents a processing of `key` was handed to, in order."""
        return [dst for _, dst, m in self.sent if m.get("op") == "process" and m.get("key") == key]

    async def settle(self) -> None:
        """Deliver messages and run timers and tasks until nothing is left to do."""
        for _ in range(1000):
            await asyncio.sleep(0)
            if self.soon:
                fn = self.soon.pop(0)
                res = fn()
                if asyncio.iscoroutine(res):
                    await res
                continue
            i = next((i for i, (_, dst, _) in enumerate(self.queue) if dst in self.agents), None)
            if i is not None:
                src, dst, msg = self.queue.pop(i)
                await self.agents[dst].on_message(src, team.dumps(msg))
                continue
            tasks = [t for a in self.agents.values() for t in (*getattr(a, "jobs", ()), *getattr(a, "tasks", ()))
                     if not t.done()]
            if not tasks:
                return
            await asyncio.wait(tasks, timeout=1.0)
        raise AssertionError("the bus does not settle")


class Ctx:
    """What AgentBase asks of its context, on the bus."""

    def __init__(self, bus: Bus, agent_id: str, config: dict[str, Any]) -> None:
        self.bus, self.agent_id, self.name, self.parent, self.epoch, self.host = bus, agent_id, agent_id, None, 1, "h1"
        self.config = json.dumps(config).encode()
        self.clock = SimpleNamespace(now=lambda: bus.t)
        self.random = None
        self.writes: list[tuple[list[Any], bool]] = []
        self.stopped = False
        self.scan_truncated = False
        self.truncate = False  # scans say they were cut (the host's bounds)

    def send(self, to: str, payload: bytes) -> None:
        m = (self.agent_id, to, json.loads(payload))
        self.bus.queue.append(m)
        self.bus.sent.append(m)

    def log(self, event: str, level: str, fields: dict[str, Any]) -> None:
        self.bus.logs.append((self.agent_id, event, fields))

    def set_clock(self, clock: Any, seed: Any = None) -> None:
        pass  # the bus's time

    def timer(self, fn: Any, delay: float, period: float | None) -> Any:
        if period is None:
            self.bus.soon.append(fn)
        return SimpleNamespace(cancel=lambda: None)

    def watch(self, prefix: str, callback: Any) -> int:
        return 1  # the tests call SupervisorSLAM._on_raw themselves

    def watch_log(self, key: str, callback: Any) -> int:
        return 2

    def backup(self, data: bytes) -> None:
        self.bus.backups[self.agent_id] = data

    def request_stop(self) -> None:
        self.stopped = True

    async def ddb_write(self, ops: Any, atomic: bool, timeout: float) -> list[str]:
        ops = list(ops)
        self.writes.append((ops, atomic))
        if self.bus.hold is not None:
            await self.bus.hold.wait()
        res = self.bus.ddb.apply(ddbops.encode_batch(ops, atomic=atomic))
        return ["" if r.ok else r.reason for r in res.results]

    async def ddb_get(self, key: str, timeout: float) -> bytes | None:
        o = self.bus.ddb.get(key)
        return None if o is None else o.data

    async def ddb_scan(self, prefix: str, limit: int, timeout: float) -> dict[str, bytes]:
        self.scan_truncated = self.truncate
        return {o.key: o.data for o in self.bus.ddb.items(prefix)}

    async def spawn_child(self, type_name: str, config: bytes, timeout: float, key: str | None = None) -> str:
        aid = f"{type_name}-{len(self.bus.agents)}"
        agent = self.bus.start(registry.get(type_name), aid, json.loads(config))
        await agent.on_start()
        return aid


def process_msg(key: str, raw: bytes, proc: str = COOC) -> dict[str, Any]:
    return {"op": "process", "key": key, "proc": proc, "reading": json.loads(raw)}


def answers(bus: Bus, op: str = "done") -> list[dict[str, Any]]:
    return [m for _, _, m in bus.sent if m.get("op") == op]


# ---------------------------------------------------------------------------------------------- sensor agents


def test_the_marker_is_committed_in_the_batch_of_the_observe() -> None:
    """One atomic batch: the marker's cas ("must not exist"), `stats/processings` and the Observe event."""
    bus = Bus()

    async def go() -> None:
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        key, raw = bus.put_raw("s1", 1)
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        await bus.settle()
        ((ops, atomic),) = c1._ctx.writes
        assert atomic
        kinds = {op.WhichOneof("op"): op for op in ops}
        assert set(kinds) == {"cas", "add", "log_append"}
        assert kinds["cas"].cas.key == team.done_key(key, COOC) == "slam/done/s1/00000001/sensor_cooccupancy"
        assert kinds["cas"].cas.expected_version == 0
        assert team.done_parts(kinds["cas"].cas.key) == (key, COOC)
        (done,) = answers(bus)
        assert done["ok"] and done["wrote"] and not done["skipped"] and done["n"] == 1

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_DONE) == [team.done_key("slam/raw/s1/00000001", COOC)]
    assert len(bus.log_items()) == 1 and bus.counter("processings") == 1


def test_a_processing_handed_out_to_two_agents_is_applied_once() -> None:
    """Both agents find no marker and process; the second commit's cas fails and aborts its whole batch."""
    bus = Bus()

    async def go() -> None:
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        c2 = bus.start(AgentSensorCooccupancy, "c2", {"supervisor": "sup"})
        key, raw = bus.put_raw("s1", 1)
        bus.hold = asyncio.Event()
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        await c2.on_message("sup", team.dumps(process_msg(key, raw)))
        for _ in range(10):
            await asyncio.sleep(0)
        assert len(c1._ctx.writes) == 1 and len(c2._ctx.writes) == 1  # both got as far as writing
        bus.hold.set()
        await bus.settle()

    asyncio.run(go())
    assert len(bus.log_items()) == 1 and bus.counter("processings") == 1
    done = sorted(answers(bus), key=lambda m: m["wrote"])
    assert [(m["ok"], m["wrote"], m["skipped"]) for m in done] == [(True, False, "marked"), (True, True, "")]
    assert done[0]["n"] == 0


def test_a_replayed_processing_writes_nothing() -> None:
    """The same processing again — to the same agent, or to its next life after a restart (its queued copy):
    the marker is found before anything is processed or written."""
    bus = Bus()

    async def go() -> None:
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        key, raw = bus.put_raw("s1", 1)
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        await bus.settle()
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        await bus.settle()
        assert len(c1._ctx.writes) == 1
        again = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})  # restarted (same id, no state)
        await again.on_message("sup", team.dumps(process_msg(key, raw)))
        await bus.settle()
        assert again._ctx.writes == []

    asyncio.run(go())
    assert [m["skipped"] for m in answers(bus)] == ["", "marked", "marked"]
    assert len(bus.log_items()) == 1 and bus.counter("processings") == 1


def test_a_copy_of_a_processing_in_flight_waits_for_it() -> None:
    bus = Bus()
    calls = Counter()

    async def go() -> None:
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        real = c1.process

        async def counted(reading: dict[str, Any]) -> list[Any]:
            calls[reading["n"]] += 1
            return await real(reading)

        c1.process = counted
        key, raw = bus.put_raw("s1", 1)
        bus.hold = asyncio.Event()
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        await c1.on_message("sup", team.dumps(process_msg(key, raw)))
        for _ in range(10):
            await asyncio.sleep(0)
        assert sorted(c1.inflight) == [key]
        bus.hold.set()
        await bus.settle()
        assert len(c1._ctx.writes) == 1 and not c1.inflight

    asyncio.run(go())
    assert calls == {1: 1}
    assert [m["skipped"] for m in answers(bus)] == ["", "marked"]


def test_dedicated_agents_write_the_marker_of_their_base_type() -> None:
    """Delay mode: `sensor_sonar_dedicated` serves `sensor_sonar` processings, and its markers are the ones
    SupervisorSLAM deletes (keyed by the processing type, not the agent type)."""
    bus = Bus()
    cls = registry.get("sensor_sonar_dedicated")
    assert issubclass(cls, AgentSensorSonar)

    async def go() -> None:
        d = bus.start(cls, "d1", {"supervisor": "sup", "avatar": "s1"})
        key, raw = bus.put_raw("s1", 1, "sonar")
        for _ in range(2):
            await d.on_message("sup", team.dumps(process_msg(key, raw, "sensor_sonar")))
            await bus.settle()

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_DONE) == ["slam/done/s1/00000001/sensor_sonar"]
    assert [m["skipped"] for m in answers(bus)] == ["", "marked"] and len(bus.log_items()) == 1


# ---------------------------------------------------------------------------------------------- SupervisorSLAM


def test_a_recovered_supervisor_skips_marked_processings() -> None:
    """Its predecessor handed out both processings of camera reading A and landmark's committed; B's both
    committed (the finish was lost); D is in flight at C1; a marker of a reading that is gone is left.
    The recovered agent hands out A's floor processing only, finishes B, keeps D with C1, deletes the stray
    marker."""
    bus = Bus()
    ka, _ = bus.put_raw("s1", 1, "camera")
    kb, _ = bus.put_raw("s1", 2, "camera")
    kd, _ = bus.put_raw("s2", 3)
    marks = [team.done_key(ka, "sensor_landmark"), team.done_key(kb, "sensor_landmark"),
             team.done_key(kb, "sensor_floorfinder"), team.done_key("slam/raw/s1/00000000", "sensor_floorfinder")]
    bus.ddb.apply(ddbops.encode_batch([ddbops.put(m, "json", {"n": 1}) for m in marks]))
    sup = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5})
    backup = team.dumps({"sensors": {"sensor_landmark": {"L": ""}, "sensor_floorfinder": {"F": ""}, COOC: {"C1": ""}}})

    async def go() -> None:
        sup.recover(backup)
        await sup.on_resume("recover")
        await asyncio.gather(*sup.tasks)
        # every known sensor agent is asked what it has; nothing is handed out before it answers
        syncs = {dst: m for _, dst, m in bus.queue if m["op"] == "sync"}
        assert sorted(syncs) == ["C1", "F", "L"] and not answers(bus, "process")
        bus.queue.clear()
        for aid, proc, busy in (("L", "sensor_landmark", []), ("F", "sensor_floorfinder", []), ("C1", COOC, [kd])):
            await sup.on_message(aid, team.dumps({"op": "synced", "proc": proc, "sync": syncs[aid]["sync"],
                                                  "busy": busy}))
        await asyncio.gather(*sup.tasks)
        # the report of B's floor processing comes now: B was finished from its markers, this is no late commit
        await sup.on_message("F", team.dumps({"op": "done", "key": kb, "proc": "sensor_floorfinder", "ok": True,
                                              "wrote": True}))
        await asyncio.gather(*sup.tasks)

    asyncio.run(go())
    assert bus.processes(ka) == ["F"]  # not "L": its landmark processing is marked
    assert bus.processes(kd) == [] and kd in sup.sensors[COOC]["C1"]["jobs"]  # in flight at C1: kept
    assert bus.processes(kb) == [] and kb not in bus.keys(team.K_SLAM_RAW)  # all marked: finished
    assert bus.counter("readings_processed") == 1
    assert bus.keys(team.K_SLAM_DONE) == [team.done_key(ka, "sensor_landmark")]  # B's deleted with it, stray gone
    assert "late_processing" not in {e for _, e, _ in bus.logs}


def test_markers_of_unlisted_readings_stay_when_the_scan_was_cut() -> None:
    """A reading list cut at the host's scan bounds does not show every reading: a marker whose reading is not
    in it may belong to one that was cut off, and is not taken for a stray one."""
    bus = Bus()
    stray = team.done_key("slam/raw/s1/00000000", COOC)
    bus.ddb.apply(ddbops.encode_batch([ddbops.put(stray, "json", {"n": 1})]))
    sup = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5})
    sup._ctx.truncate = True

    async def go() -> None:
        await sup.on_start()
        await asyncio.gather(*sup.tasks)

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_DONE) == [stray]


def test_a_reading_written_and_processed_between_the_scans_keeps_its_marker() -> None:
    """The reading list is two scans. A reading written and processed (its marker committed) between them is
    not an orphan's: its marker must stay, or the processing would be applied again when handed out."""
    bus = Bus()
    sup = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5})
    scan = sup._ctx.ddb_scan
    late: list[str] = []

    async def scan_then_write(prefix: str, limit: int, timeout: float) -> dict[str, bytes]:
        got = await scan(prefix, limit, timeout)
        if not late:
            key, _ = bus.put_raw("s1", 7)
            bus.ddb.apply(ddbops.encode_batch([ddbops.put(team.done_key(key, COOC), "json", {"n": 1})]))
            late.append(key)
        return got

    sup._ctx.ddb_scan = scan_then_write

    async def go() -> None:
        sup.recover(None)
        await sup._list_readings()
        await asyncio.gather(*sup.tasks)

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_DONE) == [team.done_key(late[0], COOC)]
    assert "orphan_markers" not in {e for _, e, _ in bus.logs}


@pytest.mark.parametrize("mode", ["jc-slam", "discard", "delay"])
def test_markers_are_deleted_with_the_raw_entry(mode: str) -> None:
    """The whole round, in each mode (delay: the avatars' dedicated agents): readings in, each processing
    handed out once, and the DDB left with neither raw entries nor markers; a late commit (a processing that
    was out twice, committed after its reading was finished) has its marker deleted when its report comes."""
    bus = Bus()
    sup = bus.start(SupervisorSLAM, "sup", {"mode": mode, "particles": 5, "jobs_per_agent": 2})
    keys: list[str] = []

    async def go() -> None:
        await sup.on_start()
        await bus.settle()
        for n in range(1, 9):
            key, raw = bus.put_raw(f"s{n % 2}", n, "sonar" if n % 3 == 0 else "cooccupancy")
            keys.append(key)
            sup._on_raw("add", key, raw)
            await bus.settle()
        raw = json.dumps({"avatar": "s1", "kind": "cooccupancy", "t": 1.0, "radius": 0.12}).encode()
        late = bus.start(AgentSensorCooccupancy, "late", {"supervisor": "sup"})
        await late.on_message("sup", team.dumps(process_msg(keys[0], raw)))
        await bus.settle()

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_RAW) == [] and bus.keys(team.K_SLAM_DONE) == []
    assert bus.counter("readings_processed") + bus.counter("readings_discarded") == 8
    if mode != "discard":
        assert bus.counter("readings_processed") == 8
    assert all(len(bus.processes(k)) <= 1 for k in keys)
    assert ("sup", "late_processing") in {(a, e) for a, e, _ in bus.logs}
    # (the late one is the one duplicate: committed after its reading was finished, see docs/team.md)
    assert len(bus.log_items()) == bus.counter("processings") == 8 - bus.counter("readings_discarded") + 1


def test_a_reading_finished_by_two_lives_of_the_supervisor_is_counted_once() -> None:
    """A moved (or recovered) SupervisorSLAM lists a reading whose processings are all marked and finishes it,
    while its predecessor's finish of the same reading is still uncommitted (frozen with the write in flight).
    Both batches commit; the reading is counted once — the count is in the atomic batch whose delete of the
    raw entry fails if it is gone (CI: `readings_processed` 237 of 234 generated after a graceful leave)."""
    bus = Bus()
    key, raw = bus.put_raw("s1", 1, "camera")
    procs = {"sensor_landmark", "sensor_floorfinder"}
    bus.ddb.apply(ddbops.encode_batch([ddbops.put(team.done_key(key, p), "json", {"n": 1}) for p in procs]))
    old = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5})
    new = bus.start(SupervisorSLAM, "sup2", {"mode": "jc-slam", "particles": 5})

    async def go() -> None:
        bus.hold = asyncio.Event()
        old._add_reading(key, raw, procs)  # both processings applied: it finishes the reading
        await asyncio.sleep(0)  # its write is out, not committed
        assert key in old.finishing
        new.recover(None)
        await new._list_readings()  # sees the raw entry and both markers: finishes it at once
        await asyncio.sleep(0)
        assert key in new.finishing
        bus.hold.set()
        await asyncio.gather(*old.tasks, *new.tasks)

    asyncio.run(go())
    assert bus.counter("readings_processed") == 1
    assert bus.keys(team.K_SLAM_RAW) == [] and bus.keys(team.K_SLAM_DONE) == []
    assert ("sup2", "finished_already") in {(a, e) for a, e, _ in bus.logs}


def test_a_restarted_sensor_agent_does_not_get_its_queued_processings_twice() -> None:
    """c1 has k3, k2, k1; it dies having received k3 (lost with it); k2 and k1 wait at its host. Its next life
    says hello, which reaches SupervisorSLAM before k2 and k1 are handled: the supervisor asks (sync), c1
    answers after handling them (FIFO), and only k3 is handed out again."""
    bus = Bus()
    sup = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5, "jobs_per_agent": 4})

    async def go() -> None:
        await sup.on_start()
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        await c1.on_start()
        await bus.settle()
        keys = []
        for n in (1, 2, 3):
            key, raw = bus.put_raw("s1", n)
            keys.append(key)
            sup._add_reading(key, raw)
        sup._dispatch()
        assert [m["key"] for _, dst, m in bus.queue if dst == "c1"] == keys[::-1]
        del bus.agents["c1"]  # killed: k3 was delivered to it and is lost, k2 and k1 are held by its host
        first = next(i for i, (_, dst, _) in enumerate(bus.queue) if dst == "c1")
        bus.queue.pop(first)
        c1 = bus.start(AgentSensorCooccupancy, "c1", {"supervisor": "sup"})
        await c1.on_start()  # hello — to the supervisor first
        hello = next(i for i, (_, dst, m) in enumerate(bus.queue) if dst == "sup" and m["op"] == "hello")
        src, _, msg = bus.queue.pop(hello)
        await sup.on_message(src, team.dumps(msg))
        assert [m["op"] for _, d, m in bus.queue if d == "c1"] == ["process", "process", "sync"]
        await bus.settle()
        assert [bus.processes(k) for k in keys] == [["c1"], ["c1"], ["c1", "c1"]]

    asyncio.run(go())
    assert bus.keys(team.K_SLAM_RAW) == [] and bus.keys(team.K_SLAM_DONE) == []
    assert len(bus.log_items()) == bus.counter("processings") == bus.counter("readings_processed") == 3


def test_a_sync_unanswered_hands_the_processings_out_again() -> None:
    """A restarted agent that dies again before it answers: after `sync_timeout_s` what it had goes back on
    the stack (to any agent; if it still had one, the marker makes the second a no-op), and it gets nothing
    more until it answers — an agent that never answers (one that never started) must not be fed processings
    that all time out."""
    bus = Bus()
    sup = bus.start(SupervisorSLAM, "sup", {"mode": "jc-slam", "particles": 5, "sync_timeout_s": 3.0})

    async def go() -> None:
        await sup.on_message("c1", team.dumps({"op": "hello", "proc": COOC}))
        key, raw = bus.put_raw("s1", 1)
        sup._add_reading(key, raw)
        sup._dispatch()
        await sup.on_message("c1", team.dumps({"op": "hello", "proc": COOC}))  # restarted, then silent
        await sup.on_message("c2", team.dumps({"op": "hello", "proc": COOC}))
        assert bus.processes(key) == ["c1"]
        bus.t += 2.0
        await sup._watchdog()
        assert bus.processes(key) == ["c1"]
        bus.t += 2.0
        await sup._watchdog()
        assert bus.processes(key) == ["c1", "c2"]
        c1 = sup.sensors[COOC]["c1"]
        assert not c1["ready"] and not c1["jobs"]
        (sync,) = [m for _, dst, m in bus.sent if dst == "c1" and m["op"] == "sync"]
        await sup.on_message("c1", team.dumps({"op": "synced", "proc": COOC, "sync": sync["sync"], "busy": []}))
        assert c1["ready"]  # a late answer: alive after all

    asyncio.run(go())
