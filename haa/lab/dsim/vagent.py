"""Real agents on virtual time: a control-system agent of Appendix III inside the deterministic simulator.

`haa.lab.dsim.agents` checks the agent layer (allocation, transfer, backup, recovery: Alg. 4-8) with `SimAgent`,
a counter that stands in for an agent process. This module runs a *real* `AgentBase` subclass instead —
`haa.agents.executive_mission.ExecutiveMission`, the mission's top agent (App. III L3047-3051) — with its
own code, unchanged, on the simulator's clock (issue 17, item 4):

* **Its runtime.** Each instance is an `haa.sdk.context.AgentContext`, the very object the agent runner
  builds in an agent process, given a `haa.sdk.sched.VirtualScheduler` instead of the asyncio loop: its
  timers (`every`, `call_later`), the awaits of its requests and DDB calls and their timeouts, and its
  mailbox worker are events on the cluster's event heap (`SimCluster.at`), and `now()` is the simulated
  time. Virtual time is the cluster's global time: the mission clock the agent reads is synchronised
  across hosts (`haa.agents.team.MissionClock` assumes synchronised wall clocks), while the hosts' own
  clocks keep their offsets and drifts.
* **Its host.** The frames it emits (`AgentToHost`) are what an `haa.hostd.agentdriver.AgentDriver` turns
  into agent events and DDB operations, and they are turned into the same things here, on the simulated
  host that runs the instance, after a seeded latency and in order (one FIFO pipe per direction, as the
  channel between a host and an agent process): messages, backups, freezes, stops and errors become
  `haa.core.agentio` events of that host's `AgentNode`; `spawn_child` is checked against the child
  type's config model and becomes a `SpawnChild` (the child's id drawn from the schedule's seed); DDB
  reads and scans are served from the host's replica; writes are fenced by the instance's epoch (a stale
  instance writes nothing, as in the driver) and go through the group (`MembershipNode.submit`: the
  simulated OAC), answered when committed; watches are watches of the host's replica. The node's
  commands (start fresh, thaw, recover, deliver, freeze, kill, answer) are fed back as `HostToAgent`
  frames in the order the runner would get them.
* **Faults.** The instance lives on a simulated host: a host crash, an agent kill or hang (`haactl verify
  recovery` mixes) ends it (its scheduler is closed: nothing of it runs again), a move or a rebalancing
  freezes and thaws it through Alg. 5-6, a crash recovers it from its latest committed backup (Alg. 7-8).

The agents ExecutiveMission spawns (ExecutiveAvatar, SupervisorSLAM, SupervisorExplore) talk to haa-sim or
process sensor data; here they run as `SimAgent` shells that start, move and recover like any agent but send
nothing. That is fair to what is checked: ExecutiveMission never waits on its children (it spawns them,
records their ids and sends SupervisorExplore one message in the congregate scenario, which these runs do
not use), and the property is about the executive's own state. It reads `slam/map` for the explored share;
no map is published here, so the mission ends by its time limit.

`run_real(seed, hosts, mix)` runs one schedule of `haa.lab.dsim.agents.draw_agents` with the executive in place of
the counter agents (the scenario's moves, kills and hangs all aim at it) and `check_real` checks the agent
layer's properties (`haa.lab.dsim.agents.check_agents`) plus the executive's (EX-*):

* EX-Once: the mission starts once ("Mission started" at most once in the transcript `mission/events`: a
  crash between the first status and that line leaves it out), whatever the transfers and recoveries; no
  instance spawns a child type twice, nor a child the state it was thawed or recovered from records (the
  executive backs up a child's id right after its spawn commits), and the agent table never holds two
  children of one type under the executive. A crash after a spawn committed and before the backup recording
  it makes the recovered instance ask for that child again (the child's id is drawn by the host, so it
  cannot be backed up before): the spawn is idempotent (`spawn_child`'s key, docs/agents.md "Idempotent
  spawn"), so the retry gets the first child back; without the key (mutation `no-spawn-key`) it made a
  second child (14 duplicate children in 200 schedules), now a violation (`duplicate_children` counts them).
* EX-Resume: every `mission/status` the executive writes carries the start time of the mission's first
  start (a thawed or recovered instance resumes the mission, it does not begin another), and no status
  goes back from `complete`/`stopped` to `running`. Writes — puts and the executive's create-only start (a
  compare-and-set) alike — are taken as the DDB applies them, in the total order: a status write that never
  committed (OAC aborted it and its instance died, or its host was removed before it was decided) or whose
  compare-and-set failed wrote nothing — no replica holds it, no reader or recovered instance can see it
  (AC-Uniform-Validity, thesis L545; a recovered agent gets the latest committed backup, AR-Recovery L887, and
  the committed DDB) — so the mission's first start is the first one committed. (Taken at proposal, as it
  was, a first instance whose start never committed and a recovered instance that then began the mission —
  correctly: nothing recorded a start — was a violation: seeds 494, 769, 822, 1102, 1422 at 7 hosts.)
* EX-Finish: no instance fails; after healing, the final `mission/status` in the DDB says `stopped` (the
  time limit: there is no map) and names one child of each type, each held by the agent table under the
  executive with that type.
"""

from __future__ import annotations

import dataclasses
import json
import random
import uuid
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, cast

from haa.agents import executive_avatar, supervisor_explore, supervisor_slam
from haa.agents.executive_mission import ExecutiveMission
from haa.agents.team import K_EVENTS, K_STATUS
from haa.core.agentio import (
    AnswerAgent,
    BackupMade,
    DeliverAgent,
    Failed,
    FreezeAgent,
    Frozen,
    KillAgent,
    Sent,
    ShellReady,
    SpawnChild,
    SpawnShell,
    StartAgent,
    Stopped,
)
from haa.core.agents.agentnode import AgentNode
from haa.core.ddb import ops as ddbmod
from haa.core.ddb.ddb import ApplyResult, Ddb, DdbEvent
from haa.core.inputs import CreateAgent
from haa.core.membership.globalstate import GroupTxError, SeqApplied, TxDdb, TxSeq, decode_tx
from haa.core.membership.membership import AppliedTx, WriteDone
from haa.hostd.agentdriver import SCAN_LIMIT, SCAN_MAX_BYTES
from haa.lab.dsim.agents import (
    _NOISE,
    CMD_DELAY,
    SPAWN_DELAY,
    AgentScenario,
    AgentSim,
    SimAgent,
    check_agents,
    draw_agents,
    seed_fields,
)
from haa.lab.dsim.cluster import ALIVE, SimHost
from haa.lab.dsim.group import GroupViolation
from haa.pb import agent_pb2 as pb
from haa.pb import ddb_pb2 as ddbpb
from haa.sdk import registry
from haa.sdk.context import AgentContext
from haa.sdk.sched import VirtualScheduler

#: the real agent type run on virtual time, and the children it spawns (run as SimAgent shells)
REAL_TYPE = ExecutiveMission.TYPE
CHILD_TYPES = ("executive_avatar", "supervisor_slam", "supervisor_explore")
#: the mission the executive runs (no haa-sim: arena facts only; it ends by its time limit)
MISSION_CHECK_S = 0.5
MISSION_TIME_LIMIT = 6.0

# the child types' classes (registered on import): their config models check the spawn requests
_CHILD_MODULES = (executive_avatar, supervisor_slam, supervisor_explore)

REAL_PROPS = frozenset({"EX-Once", "EX-Resume", "EX-Finish"})


def mission_config(seed: int) -> bytes:
    """The executive's config: the small arena, two seekers, a short time limit (seconds of virtual time)."""
    mission = {"name": f"vtime-{seed}", "scenario": "explore", "arena": "small",
               "avatars": [{"name": "S1", "type": "seeker"}, {"name": "S2", "type": "seeker"}],
               "complete": {"explored": 0.95, "time_limit_s": MISSION_TIME_LIMIT}}
    return json.dumps({"mission": mission, "expected_cells": 2420, "check_s": MISSION_CHECK_S, "seed": seed},
                      separators=(",", ":")).encode()


class RealInstance:
    """One instance of a real agent on one simulated host: its `AgentContext` on a `VirtualScheduler`, and the
    fields `AgentSim` keeps for every instance (`agent`, `epoch`, `host`, `running`, `started`, `hung`)."""

    def __init__(self, sim: RealAgentSim, h: SimHost, c: SpawnShell) -> None:
        self.agent = c.agent
        self.epoch = c.epoch
        self.host = (h.name, h.inc)
        self.running = True
        self.started = False
        self.hung = False
        cl = sim.cl
        self.sched = VirtualScheduler(lambda: cl.now, cl.at)
        init = pb.HostToAgent.Init(agent_id=c.agent, name=c.name, type_name=c.type, config=c.config,
                                   epoch=c.epoch, parent=c.parent, host=h.name)
        self.ctx = AgentContext(init, registry.get(c.type), lambda f: sim._emitted(h, self, f),
                                scheduler=self.sched)
        #: watch id -> key prefix, and the replica watched for them (a new replica object: watched again)
        self.watches: dict[int, str] = {}
        self.replica: Any = None
        self.replica_watch = 0
        self.worker = self.sched.spawn(self.ctx.run())
        self.worker.result.add_done_callback(lambda f: sim._exited(h, self, f))

    def close(self) -> None:
        self.running = False
        self.sched.close()
        if self.replica is not None:
            self.replica.unwatch(self.replica_watch)
            self.replica = None


@dataclass
class RealHistory:
    """What the EX-* checks read."""

    #: (time, instance epoch, value) of every mission/status write applied, in the total order (the first host
    #: to apply it; a write that aborted, was dropped with its host or failed its compare-and-set is not here)
    statuses: list[tuple[float, int, dict[str, Any]]] = field(default_factory=list)
    #: the encoded value of every mission/status write the executive's host accepted to propose -> (time,
    #: instance epoch) of its first proposal: the epoch of an applied one
    proposed: dict[bytes, tuple[float, int]] = field(default_factory=dict)
    #: (global seq, txid) of the transactions already looked at for status writes (every host applies each)
    applied_seen: set[tuple[int, str]] = field(default_factory=set)
    #: (time, epoch, type) of every spawn_child the executive asked for
    spawns: list[tuple[float, int, str]] = field(default_factory=list)
    #: per instance epoch of the executive: how it started and the state it was given (thaw or recover)
    starts: dict[int, tuple[str, bytes | None]] = field(default_factory=dict)
    #: (time, host, agent epoch, event, fields) of the agents' log lines
    logs: list[tuple[float, str, int, str, str]] = field(default_factory=list)
    #: instances that ended with an error (their reason)
    failures: list[str] = field(default_factory=list)
    frames: dict[str, int] = field(default_factory=lambda: defaultdict(int))


class RealAgentSim(AgentSim):
    """`AgentSim` with ExecutiveMission running for real on virtual time (module docstring)."""

    def __init__(self, sc: AgentScenario, trace: bool = False) -> None:
        # every move, kill and hang of the scenario aims at the executive (agent #0)
        sc = dataclasses.replace(sc, n_agents=1, moves=[(t, 0, hi) for t, _a, hi in sc.moves],
                                 kills=[(t, 0) for t, _a in sc.kills], hangs=[(t, 0) for t, _a in sc.hangs])
        super().__init__(sc, trace)
        self.rh = RealHistory()
        self.rrng = random.Random(sc.group.seed * 8191 + 11)  # child ids: the core draws no random numbers
        self.config = mission_config(sc.group.seed)
        self._agent_writes: dict[int, tuple[RealInstance, int, SimHost]] = {}
        self._write_n = 0

    # ------------------------------------------------------------------ the scenario

    def _create_agent(self, node: AgentNode, now: float, i: int, agent: str) -> None:
        """The executive (the scenario's one agent, #0)."""
        cls = ExecutiveMission
        node.step(now, CreateAgent(agent, REAL_TYPE, self.config, cost=cls.COST, transfer_penalty=cls.TRANSFER_PENALTY,
                                   recovery=cls.RECOVERY, req=("create", i)))

    def _schedule_send(self, h: SimHost, a: SimAgent) -> None:
        """The children are shells: they send nothing (module docstring)."""

    def _end(self, a: Any) -> None:
        super()._end(a)
        if isinstance(a, RealInstance):
            a.close()

    def _on_effect(self, h: SimHost, e: Any) -> None:
        if type(e) is WriteDone and isinstance(e.req, tuple) and e.req[:1] == ("vagent",):
            self._agent_write_done(e)
            return
        if type(e) is AppliedTx:
            self._note_statuses(e)
            for a in self.inst.get((h.name, h.inc), {}).values():
                if isinstance(a, RealInstance) and a.watches:
                    self._watch_replica(h, a)
        super()._on_effect(h, e)

    # ------------------------------------------------------------------ commands of the node

    def _command(self, h: SimHost, c: Any) -> None:
        proc = (h.name, h.inc)
        insts = self.inst[proc]
        t = type(c)
        if t is SpawnShell:
            if c.type != REAL_TYPE:
                super()._command(h, c)
                return

            def spawn() -> None:
                old = insts.get(c.agent)
                if old is not None:
                    self._end(old)
                insts[c.agent] = RealInstance(self, h, c)  # type: ignore[assignment]
                self._event(h, ShellReady(c.agent, c.epoch))
            self._later(h, SPAWN_DELAY, spawn, "c:" + c.agent)
            return
        cur = insts.get(c.agent)
        if t is KillAgent or not isinstance(cur, RealInstance):
            super()._command(h, c)
            return
        if t is StartAgent:
            def start() -> None:
                a = insts.get(c.agent)
                if not isinstance(a, RealInstance) or a.epoch != c.epoch or not a.running:
                    return
                self._started(proc, a, c)
                how = {"fresh": "start", "thaw": "thaw"}.get(c.mode, "recover")
                if how == "start":
                    first = pb.HostToAgent(start=pb.HostToAgent.Start())
                elif how == "thaw":
                    first = pb.HostToAgent(thaw=pb.HostToAgent.Thaw(state=c.state or b""))
                else:
                    first = pb.HostToAgent(recover=pb.HostToAgent.Recover(has_backup=c.state is not None,
                                                                          backup=c.state or b""))
                a.ctx.feed(first)
                for m in c.messages:
                    a.ctx.feed(pb.HostToAgent(deliver=_agent_msg(m)))
                a.ctx.feed(pb.HostToAgent(resume=pb.HostToAgent.Resume(how=how)))
            self._later(h, CMD_DELAY, start, "c:" + c.agent)
        elif t is DeliverAgent:
            self._to_agent(h, c.agent, c.epoch, pb.HostToAgent(deliver=_agent_msg(c.msg)))
        elif t is FreezeAgent:
            self._to_agent(h, c.agent, c.epoch, pb.HostToAgent(freeze=pb.HostToAgent.Freeze()))
        elif t is AnswerAgent:
            ans = pb.HostToAgent.Answer(req_id=c.req, ok=c.ok, value=c.value.encode(), error=c.error)
            self._to_agent(h, c.agent, c.epoch, pb.HostToAgent(answer=ans))

    def _started(self, proc: tuple[str, int], a: RealInstance, c: StartAgent) -> None:
        """The bookkeeping `AgentSim` keeps of every start (AG-Single-Active, AR-Recovery)."""
        ah = self.ah
        a.started = True
        if c.agent == ah.ids[0]:
            self.rh.starts[c.epoch] = (c.mode, c.state)
        key = (c.agent, c.epoch)
        prev = ah.epochs_seen.get(key)
        if prev is not None and prev != proc:
            ah.double_epoch.append(f"{c.agent} epoch {c.epoch} on {prev} and {proc}")
        ah.epochs_seen[key] = proc
        if c.mode != "thaw":
            ah.gens += 1
            ah.recovered_starts.append((c.agent, c.epoch, c.mode, c.state))
            ah.gen_of_start.append((c.agent, ah.gens))
        ah.intervals[c.agent].append([proc, c.epoch, self.cl.now, None])

    def _to_agent(self, h: SimHost, agent: str, epoch: int, frame: pb.HostToAgent) -> None:
        """A frame down the host-to-agent pipe of the instance (after a command latency, in order)."""
        proc = (h.name, h.inc)

        def feed() -> None:
            a = self.inst[proc].get(agent)
            if isinstance(a, RealInstance) and a.epoch == epoch and a.running and not a.hung:
                a.ctx.feed(frame)
        self._later(h, CMD_DELAY, feed, "c:" + agent)

    # ------------------------------------------------------------------ frames of the agent

    def _emitted(self, h: SimHost, a: RealInstance, frame: pb.AgentToHost) -> None:
        """The agent emitted `frame`: it reaches its host after a latency, in emission order."""
        if a.running and not a.hung:
            self._later(h, CMD_DELAY, lambda: self._frame(h, a, frame), "e:" + a.agent)

    def _exited(self, h: SimHost, a: RealInstance, result: Any) -> None:
        """The instance's mailbox worker returned (frozen, stopped, failed) or raised (a bug: a failure)."""
        exc = result.exception()
        if exc is not None and not result.cancelled() and a.running:
            self.rh.failures.append(f"{a.agent} epoch {a.epoch}: {type(exc).__name__}: {exc}")
            self._emitted(h, a, pb.AgentToHost(error=pb.AgentToHost.Error(message=f"{type(exc).__name__}: {exc}")))

    def _frame(self, h: SimHost, a: RealInstance, f: pb.AgentToHost) -> None:
        proc = (h.name, h.inc)
        if self.inst[proc].get(a.agent) is not a:
            return  # the instance was replaced or killed meanwhile: its process is gone
        kind = f.WhichOneof("msg")
        self.rh.frames[kind] += 1
        self.cl._note(f"vagent {a.agent[:8]}#{a.epoch} on {h.name}#{h.inc}: {kind}")
        agent, epoch = a.agent, a.epoch
        if kind == "sent":
            m = f.sent
            self._event(h, Sent(agent, epoch, m.dst, bytes(m.payload), m.conv, m.reply, m.error))
        elif kind == "backup":
            self._event(h, BackupMade(agent, epoch, bytes(f.backup.data)))
        elif kind == "frozen":
            self._end(a)
            self.inst[proc].pop(agent, None)
            self._event(h, Frozen(agent, epoch, bytes(f.frozen.state)))
        elif kind == "stopped":
            self._end(a)
            self.inst[proc].pop(agent, None)
            self._event(h, Stopped(agent, epoch))
        elif kind == "error":
            self.rh.failures.append(f"{agent} epoch {epoch}: {f.error.message}")
            self._end(a)
            self.inst[proc].pop(agent, None)
            self._event(h, Failed(agent, epoch, f.error.message))
        elif kind == "spawn_child":
            self._spawn_child(h, a, f.spawn_child)
        elif kind == "ddb_get":
            obj = self._replica(h).get(f.ddb_get.key)
            ans = pb.HostToAgent.Answer(req_id=f.ddb_get.req_id, ok=True, missing=obj is None,
                                        value=obj.data if obj is not None else b"")
            self._to_agent(h, agent, epoch, pb.HostToAgent(answer=ans))
        elif kind == "ddb_scan":
            self._scan(h, a, f.ddb_scan)
        elif kind == "ddb_put":
            p = f.ddb_put
            value = json.loads(p.value) if p.type_name == "json" else bytes(p.value)
            self._agent_write(h, a, p.req_id, [ddbmod.put(p.key, p.type_name, value)], False)
        elif kind == "ddb_write":
            self._agent_write(h, a, f.ddb_write.req_id, list(f.ddb_write.ops), f.ddb_write.atomic)
        elif kind == "ddb_watch":
            a.watches[f.ddb_watch.watch_id] = f.ddb_watch.prefix
            self._watch_replica(h, a)
        elif kind == "ddb_unwatch":
            a.watches.pop(f.ddb_unwatch.watch_id, None)
        elif kind == "log":
            self.rh.logs.append((self.cl.now, h.name, epoch, f.log.event, f.log.fields_json))
        # hello, ready, heartbeat: nothing for the node (the driver only logs them)

    def _replica(self, h: SimHost) -> Ddb:
        return _node(h).m.state.ddb

    def _spawn_child(self, h: SimHost, a: RealInstance, s: pb.AgentToHost.SpawnChild) -> None:
        """As `AgentDriver._spawn_child`: an unknown type or a config its model refuses is answered at once."""
        try:
            cls = registry.get(s.type_name)
            why = cls.check_config(bytes(s.config))
        except LookupError as e:
            cls, why = None, str(e)
        self.rh.spawns.append((self.cl.now, a.epoch, s.type_name))
        if cls is None or why:
            ans = pb.HostToAgent.Answer(req_id=s.req_id, ok=False, error=f"{s.type_name}: {why}")
            self._to_agent(h, a.agent, a.epoch, pb.HostToAgent(answer=ans))
            return
        child = str(uuid.UUID(int=self.rrng.getrandbits(128), version=4))
        self._event(h, SpawnChild(a.agent, a.epoch, s.req_id, s.type_name, bytes(s.config), child,
                                  int(cls.MAX_PER_HOST), s.key))

    def _scan(self, h: SimHost, a: RealInstance, s: pb.AgentToHost.DdbScan) -> None:
        """As `AgentDriver._ddb_scan`: key order, at most SCAN_LIMIT keys and SCAN_MAX_BYTES of values."""
        limit = min(s.limit or SCAN_LIMIT, SCAN_LIMIT)
        keys: list[str] = []
        values: list[bytes] = []
        size, truncated = 0, False
        for obj in self._replica(h).items(s.prefix):
            if len(keys) >= limit or size + len(obj.data) + len(obj.key) > SCAN_MAX_BYTES:
                truncated = True
                break
            keys.append(obj.key)
            values.append(obj.data)
            size += len(obj.data) + len(obj.key)
        ans = pb.HostToAgent.Answer(req_id=s.req_id, ok=True, keys=keys, values=values, truncated=truncated)
        self._to_agent(h, a.agent, a.epoch, pb.HostToAgent(answer=ans))

    def _agent_write(self, h: SimHost, a: RealInstance, req_id: int, ops: list[Any], atomic: bool) -> None:
        """As `AgentDriver._ddb_write`: every op checked, the instance fenced by its epoch, then one batch
        through the group; the answer (one reason per op) once it is committed and applied here."""
        why = "" if ops else "empty batch"
        for i, op in enumerate(ops):
            bad = ddbmod.check_op(op)
            if bad:
                why = f"op {i}: {bad}"
                break
        node = _node(h)
        r = node.table.get(a.agent)
        if not why and (r is None or r.owner != h.name or r.epoch != a.epoch):
            where = f"epoch {r.epoch} on {r.owner or 'nobody'}" if r is not None else "nothing"
            why = f"stale instance (epoch {a.epoch}): the table gives {a.agent[:8]} {where}"
        if why:
            ans = pb.HostToAgent.Answer(req_id=req_id, ok=False, error=why)
            self._to_agent(h, a.agent, a.epoch, pb.HostToAgent(answer=ans))
            return
        for op in ops:
            kind = op.WhichOneof("op")
            if kind in ("put", "cas") and getattr(op, kind).key == K_STATUS:
                self.rh.proposed.setdefault(bytes(getattr(op, kind).value), (self.cl.now, a.epoch))
        self._write_n += 1
        self._agent_writes[self._write_n] = (a, req_id, h)
        payload = ddbmod.encode_batch(ops, origin=h.name, atomic=atomic)
        node.m.submit(h.local(self.cl.now), payload, ("vagent", self._write_n), kind="ddb")
        self.cl._apply(h)

    def _agent_write_done(self, e: WriteDone) -> None:
        entry = self._agent_writes.pop(e.req[1], None)  # type: ignore[index]  # ("vagent", n): _agent_write
        if entry is None:
            return
        a, req_id, h = entry
        res = e.result
        if e.ok and isinstance(res, ApplyResult):
            errors = ["" if r.ok else (r.reason or "failed") for r in res.results]
            ans = pb.HostToAgent.Answer(req_id=req_id, ok=True, op_errors=errors)
        else:
            ans = pb.HostToAgent.Answer(req_id=req_id, ok=False, error=e.reason or "not committed")
        self._to_agent(h, a.agent, a.epoch, pb.HostToAgent(answer=ans))

    def _note_statuses(self, e: AppliedTx) -> None:
        """The mission/status writes transaction `e` applied (once per transaction, at the first host to apply
        it), in order, into `rh.statuses`."""
        key = (e.seq, str(e.txid))
        if e.kind not in ("ddb", "seq") or key in self.rh.applied_seen:
            return
        self.rh.applied_seen.add(key)
        for op in _applied_ops(e.payload, e.result):
            kind = op.WhichOneof("op")
            if kind in ("put", "cas") and getattr(op, kind).key == K_STATUS:
                value = bytes(getattr(op, kind).value)
                _t, epoch = self.rh.proposed.get(value, (0.0, 0))
                self.rh.statuses.append((self.cl.now, epoch, json.loads(value)))

    def _watch_replica(self, h: SimHost, a: RealInstance) -> None:
        """Watch the host's current replica for `a`'s prefixes (again when the replica object changed)."""
        if h.core is None:
            return
        ddb = self._replica(h)
        if ddb is a.replica:
            return
        if a.replica is not None:
            a.replica.unwatch(a.replica_watch)
        a.replica = ddb

        def on_event(ev: DdbEvent) -> None:
            for wid, prefix in list(a.watches.items()):
                if not ev.key.startswith(prefix):
                    continue
                value: bytes | None = None
                if ev.kind in ("add", "write") and ev.value is not None:
                    value = ddbmod.encode_value(ev.type_name, ev.value)
                elif ev.kind == "append" and ev.type_name == "log":
                    value = ev.value
                w = pb.HostToAgent.WatchEvent(watch_id=wid, event=ev.kind, key=ev.key, has_value=value is not None,
                                              value=value or b"", index=ev.index)
                self._to_agent(h, a.agent, a.epoch, pb.HostToAgent(watch_event=w))

        a.replica_watch = ddb.watch(on_event)


def _node(h: SimHost) -> AgentNode:
    """The agent node a live simulated host runs (`AgentSim` builds one per incarnation)."""
    node: Any = h.core
    assert isinstance(node, AgentNode)
    return node


def _member_nodes(sim: AgentSim) -> list[AgentNode]:
    return [_node(h) for h in sim.cl.by_idx if h.state == ALIVE and h.core is not None and _node(h).m.is_member()]


def _applied_ops(payload: bytes, result: Any) -> list[Any]:
    """The DDB ops an applied group transaction (a DDB batch, or a sequencer batch of them) wrote: those of its
    batches that were applied, each op that succeeded."""
    try:
        tx = decode_tx(payload)
    except GroupTxError:
        return []
    if isinstance(tx, TxDdb):
        pairs = [(tx.data, result)]
    elif isinstance(tx, TxSeq) and isinstance(result, tuple):
        pairs = []
        for entry, sa in zip(tx.entries, result, strict=False):
            if isinstance(sa, SeqApplied) and sa.applied and sa.kind == "ddb":
                pairs.append((cast(TxDdb, decode_tx(entry.tx)).data, sa.result))
    else:
        return []
    out = []
    for data, res in pairs:
        if not isinstance(res, ApplyResult):
            continue
        batch = ddbpb.DdbBatch.FromString(data)  # (it applied: it decodes)
        out += [op for op, r in zip(batch.ops, res.results, strict=False) if r.ok]
    return out


def _agent_msg(m: Any) -> pb.AgentMsg:
    return pb.AgentMsg(src=m.src, dst=m.dst, payload=m.payload, conv=m.conv, reply=m.reply, error=m.error)


# ------------------------------------------------------------------------------------------------ checks


def check_real(sim: RealAgentSim) -> list[GroupViolation]:
    """The agent layer's properties (`check_agents`) and the executive's (EX-*, module docstring)."""
    rh = sim.rh
    exec_id = sim.ah.ids[0]
    out: list[GroupViolation] = []

    def bad(prop: str, detail: str) -> None:
        out.append(GroupViolation(prop, detail, []))

    members = _member_nodes(sim)
    table = members[0].table if members else None
    children = [r for r in table if r.parent == exec_id] if table is not None else []
    for v in check_agents(sim):
        # the table holds the executive and its children, not only the scenario's agents
        if v.prop == "AG-Liveness" and "agents were created" in v.detail and len(children) + 1 == len(table or ()):
            continue
        out.append(v)
    for f in rh.failures:
        bad("EX-Finish", f"the executive failed: {f[:300]}")
    # EX-Once: no instance spawns a child the state it started from records, nor one type twice; a type the
    # table holds twice is then the window the executive documents (a crash after the spawn committed and
    # before the backup that records it: `duplicates`, not a violation)
    per_epoch: dict[tuple[int, str], int] = defaultdict(int)
    for t, epoch, typ in rh.spawns:
        per_epoch[(epoch, typ)] += 1
        if per_epoch[(epoch, typ)] == 2:
            bad("EX-Once", f"t={t:.3f} epoch {epoch} asked for a second {typ}")
        mode, state = rh.starts.get(epoch, ("fresh", None))
        recorded = json.loads(state).get("children", {}) if state else {}
        if typ in recorded:
            bad("EX-Once", f"t={t:.3f} epoch {epoch} ({mode}) spawned a {typ} again, its state records "
                f"{recorded[typ][:8]}")
    dups = duplicate_children(sim)
    if dups:
        kinds = sorted(r.type for r in children)
        bad("EX-Once", f"the agent table holds {dups} duplicate child(ren) under the executive: {kinds}")
    ddb = members[0].m.state.ddb if members else None
    started = 0
    events = ddb.get(K_EVENTS) if ddb is not None else None
    if events is not None:
        _first, items = ddbmod.decode_log(events.data)
        started = sum(1 for it in items if json.loads(it)["text"].startswith("Mission started"))
        if started > 1:
            bad("EX-Once", f"the transcript says 'Mission started' {started} times")
    # EX-Resume
    first_t = rh.statuses[0][2].get("started_t") if rh.statuses else None
    finished = False
    for t, epoch, st in rh.statuses:
        if st.get("started_t") != first_t or first_t is None:
            bad("EX-Resume", f"t={t:.3f} a status of epoch {epoch} with started_t {st.get('started_t')} was applied, "
                f"the mission started at {first_t}")
            break
        if finished and st.get("state") == "running":
            bad("EX-Resume", f"t={t:.3f} a status of epoch {epoch} with state running was applied after the "
                "mission ended")
            break
        finished = finished or st.get("state") in ("complete", "stopped")
    # EX-Finish (after healing)
    if sim.quiescent and ddb is not None:
        obj = ddb.get(K_STATUS)
        st = json.loads(obj.data) if obj is not None else {}
        if st.get("state") != "stopped":
            bad("EX-Finish", f"final mission/status is {st.get('state')!r}, expected 'stopped' (time limit)")
        named = dict(st.get("children", {}))
        held = {r.id: r.type for r in children}
        if set(named) != set(CHILD_TYPES) or any(held.get(cid) != typ for typ, cid in named.items()):
            bad("EX-Finish", f"mission/status names children {sorted(named)}, the table holds "
                f"{sorted(held.values())} under the executive")
    return out


def duplicate_children(sim: RealAgentSim) -> int:
    """Children the agent table holds beyond one per type (the window EX-Once describes)."""
    members = _member_nodes(sim)
    if not members:
        return 0
    kids = [r.type for r in members[0].table if r.parent == sim.ah.ids[0]]
    return len(kids) - len(set(kids))


def run_real(seed: int, hosts: int = 5, mix: str = "recovery",
             trace: bool = False) -> tuple[RealAgentSim, list[GroupViolation]]:
    """One schedule with the real executive (module docstring)."""
    sim = RealAgentSim(draw_agents(seed, hosts, mix), trace=trace)
    sim.run()
    return sim, check_real(sim)


# ------------------------------------------------------------------------------------------------ the verifier

#: the fault mix of `haactl verify executive`: crashes, agent kills and hangs, moves (transfers), pauses
VERIFY_MIX = "recovery"


def seed_result(seed: int, hosts: int) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed (`haactl verify executive`)."""
    sim, vs = run_real(seed, hosts, VERIFY_MIX)
    ah = sim.ah
    exec_id = ah.ids[0]
    return seed_fields(seed, sim, vs, {
        "transfers": float(sum(1 for _t, _h, _n, ev in ah.timeline if ev == "thawed")),
        "recoveries": float(sum(1 for a, _e, m, _s in ah.recovered_starts if a == exec_id and m == "recover")),
        "duplicate_children": float(duplicate_children(sim)),
        "faults_dropped": float(len(sim.gh.dropped)),
    }, sim.asc.describe())


def full_trace(seed: int, hosts: int) -> list[str]:
    """The scenario, the trace (the executive's frames as `vagent` lines), the violations and the hash."""
    sim, vs = run_real(seed, hosts, VERIFY_MIX, trace=True)
    out = [f"# {ln}" for ln in sim.asc.describe()]
    out += [ln for ln in sim.cl.trace or [] if not any(k in ln for k in _NOISE)]
    out += [f"# {v}" for v in vs]
    out.append(f"# trace hash {sim.cl.trace_hash()}")
    return out


def trace_excerpt(seed: int, hosts: int, bad_hosts: list[str], lines: int = 40) -> list[str]:
    """Scenario, then the executive's frames, the agent timeline, views and faults."""
    sim, _vs = run_real(seed, hosts, VERIFY_MIX, trace=True)
    words = (" agent ", "vagent ", " view ", "crash", "pause")
    picked = [ln for ln in sim.cl.trace or [] if " -> " not in ln and " <- " not in ln and any(w in ln for w in words)]
    out = [f"  scenario: {ln}" for ln in sim.asc.describe()[:16]]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    return out + [f"  {ln}" for ln in picked]
