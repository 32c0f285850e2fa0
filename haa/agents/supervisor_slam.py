"""SupervisorSLAM (thesis App. III L3089-3104; Table 7.2-4 L1749-1754; §5.2.3): sensor readings to sensor agents,
and the keeper of the team's SLAM state.

"Monitors the DDB for new sensor readings and assigns them to sensor processing agents ... also maintains the
active set of sensor processing agents and spawns new agents as required."

**Readings.** Avatar agents write each reading as `slam/raw/<avatar>/<n>` (docs/team.md); a camera image is
one reading and two processings (AgentSensorLandmark and AgentSensorFloorFinder), a co-occupancy reading
one (AgentSensorCooccupancy), a sonar scan one (AgentSensorSonar). The supervisor watches `slam/raw/` and
hands each processing to a sensor agent of its type with the message {"op": "process", "key", "reading"};
the sensor agent appends the resulting Observe event to `slam/log` and answers {"op": "done", "key", "proc",
"ok"}. When every processing of a reading is done the raw entry is deleted and `stats/readings_processed`
counts it (`stats/processings` is counted by the sensor agents, `stats/readings_discarded` here).

**Modes** (Table 7.2-4, the mission's `slam`):

* `jc-slam` — one LIFO stack per processing type; a sensor agent gets one processing at a time, the newest
  first, and the next when it reports. When processings pile up (more than `grow_backlog` waiting for
  `grow_wait_s`) another agent of that type is requested, "limited by the available processing power of
  the hosts and up to a maximum of one sensor processing agent of each type ... per host": the sensor types
  declare MAX_PER_HOST = 1, so the allocation never places two on one host; a new agent is requested only
  when every agent of the type has started (said hello), so one the allocation cannot place (every host has
  one) stops the growth of that type (`max_per_type` bounds it as well). Processings go to started agents
  only.
* `discard` — a processing goes to an idle agent of its type at once, or is discarded; `discard_agents`
  agents of each type are spawned at start (the thesis: one of each type on every host).
* `delay` — each avatar's readings are handled by agents of each type dedicated to it and the avatar waits
  for them: not built yet; the mission runs as `jc-slam` and the transcript says so.

**SLAM state.** The particle filters, the occupancy grid and the landmark map are the replica
(haa.slam.replica) of the event log `slam/log` plus the checkpoint `slam/ckpt/*`: this agent applies every
event in index order, appends a Request event (JC-SLAM events (d)+(e)) for every avatar every `request_s`,
publishes the map (`slam/map`), the estimates (`slam/estimates`, `slam/est/<avatar>`) and the landmarks
(`slam/landmarks`) every `publish_s`, and every `checkpoint_events` events writes a checkpoint and trims the
log in one atomic batch. A crash of this agent or its host loses nothing committed: its successor restores
the checkpoint and replays the log (recovery: "Restore configuration and retrieve AgentSensor* statuses,
reassign readings if appropriate. Confirm that reading list is up to date" — the reading list is
`slam/raw/`, read again; processings in flight are handed out again after `job_timeout_s`).
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any, Literal

import pydantic

from haa.agents import team
from haa.agents.base import AgentBase
from haa.agents.registry import register
from haa.hostd import ddb as ddbops
from haa.slam import events as sev
from haa.slam.grid import GridSpec
from haa.slam.replica import LogGap, SlamReplica
from haa.slam.system import SlamConfig

#: reading kind → the processing types it needs (sensor agent type names)
PROCESSINGS: dict[str, tuple[str, ...]] = {
    "camera": ("sensor_landmark", "sensor_floorfinder"),
    "cooccupancy": ("sensor_cooccupancy",),
    "sonar": ("sensor_sonar",),
}


class SlamAgentConfig(team.TeamConfig):
    mode: Literal["jc-slam", "discard", "delay"] = "jc-slam"
    particles: int = pydantic.Field(100, ge=1, le=10000)
    grid: tuple[float, float, float, float, float] = (0.0, 0.0, 3.4, 7.2, 0.1)  # x0, y0, width, height, res
    landmark_ids: list[int] = []
    marker_dictionary: str = ""
    marker_size: float = 0.0
    request_s: float = pydantic.Field(1.0, gt=0, le=60)
    publish_s: float = pydantic.Field(0.5, gt=0, le=60)
    checkpoint_events: int = pydantic.Field(600, ge=10, le=1_000_000)
    grow_backlog: int = pydantic.Field(3, ge=1, le=1000)
    grow_wait_s: float = pydantic.Field(2.0, ge=0, le=600)
    max_per_type: int = pydantic.Field(8, ge=1, le=64)
    discard_agents: int = pydantic.Field(1, ge=1, le=64)
    job_timeout_s: float = pydantic.Field(15.0, gt=0, le=600)


@register
class SupervisorSLAM(AgentBase):
    TYPE = "supervisor_slam"
    CONFIG = SlamAgentConfig
    COST = 0.15
    RECOVERY = "backup"
    #: its streams to haa-sim (or its replica) are rebuilt on every move: the allocation should rather not
    TRANSFER_PENALTY = 0.5
    CPU_LIMIT = 1.5
    MEMORY_LIMIT_MB = 1024

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: SlamAgentConfig
        x0, y0, w, h, res = self.cfg.grid
        self.spec = GridSpec(w, h, res, x0, y0)
        self.replica: SlamReplica | None = None
        self.since_ckpt = 0
        self.buffer: list[tuple[int, bytes]] = []
        self.loading = True
        self.dirty = True
        # readings: raw key → {"rec": record, "todo": set of processing types left, "discarded": int}
        self.readings: dict[str, dict[str, Any]] = {}
        self.stacks: dict[str, list[str]] = {p: [] for ps in PROCESSINGS.values() for p in ps}
        # sensor agents: type → {agent id: {"job": raw key or None, "since": t}}
        self.sensors: dict[str, dict[str, dict[str, Any]]] = {p: {} for p in self.stacks}
        self.spawning: set[str] = set()
        self.capped: dict[str, int] = {}
        self.last_grow: dict[str, float] = {}
        self.backlog_since: dict[str, float] = {}
        self.tasks: set[asyncio.Task[Any]] = set()

    # ------------------------------------------------------------------ life cycle

    def pack_state(self) -> bytes:
        return team.dumps({"sensors": {p: sorted(a) for p, a in self.sensors.items()}})

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        for p, ids in st.get("sensors", {}).items():
            if p in self.sensors:
                # they said hello to the instance that backed them up: ready
                self.sensors[p] = {i: {"job": None, "since": 0.0, "ready": True} for i in ids}

    def recover(self, backup: bytes | None) -> None:
        if backup:
            self.unpack_state(backup)

    async def on_start(self) -> None:
        await self._begin(fresh=True)

    async def on_resume(self, how: str) -> None:
        await self._begin(fresh=False)

    async def _begin(self, fresh: bool) -> None:
        team.use_mission_clock(self, self.cfg)
        if self.cfg.mode == "delay" and fresh:
            await team.transcript(self, "SLAM mode 'delay' is not built yet: running 'jc-slam'")
        self.watch_log(team.K_SLAM_LOG, self._on_event)
        await self._load()
        self.watch(team.K_SLAM_RAW, self._on_raw)
        for key, data in (await self.ddb_scan(team.K_SLAM_RAW)).items():
            self._add_reading(key, data)
        if self.cfg.mode == "discard" and fresh:
            for p in self.stacks:
                for _ in range(self.cfg.discard_agents):
                    self._spawn(p)
        self.every(self.cfg.request_s, self._requests)
        self.every(self.cfg.publish_s, self._publish, first=0.1)
        self.every(1.0, self._watchdog)
        self._dispatch()

    async def _load(self) -> None:
        """The replica from the checkpoint and the log (recovery: nothing committed is lost)."""
        blobs = {k[len(team.K_SLAM_CKPT):]: v for k, v in (await self.ddb_scan(team.K_SLAM_CKPT)).items()}
        if blobs:
            self.replica = SlamReplica.restore(blobs)
        else:
            self.replica = SlamReplica(self.spec, SlamConfig(n_particles=self.cfg.particles), seed=self.cfg.seed)
        data = await self.ddb_get(team.K_SLAM_LOG)
        if data is not None:
            first, items = ddbops.decode_log(data)
            for k, item in enumerate(items):
                self._apply(first + k, item)
        self.loading = False
        for index, item in sorted(self.buffer):
            self._apply(index, item)
        self.buffer.clear()

    def _on_event(self, index: int, item: bytes) -> None:
        if self.loading:
            self.buffer.append((index, item))
        else:
            self._apply(index, item)

    def _apply(self, index: int, item: bytes) -> None:
        assert self.replica is not None
        if index < self.replica.next_index:
            return
        try:
            self.replica.apply(index, item)
        except LogGap:  # items we never saw were trimmed away: start again from the checkpoint
            self.log("slam_log_gap", level="warning", index=index, expected=self.replica.next_index)
            self.loading = True
            self.call_later(0, self._load)
            return
        self.since_ckpt += 1
        self.dirty = True

    # ------------------------------------------------------------------ SLAM state upkeep

    async def _requests(self) -> None:
        if self.replica is None:
            return
        evs = [sev.encode(sev.Request(a)) for a in self.replica.names]
        if evs:
            await self.ddb_write([ddbops.log_append(team.K_SLAM_LOG, evs)])
        if self.since_ckpt >= self.cfg.checkpoint_events:
            await self._checkpoint()

    async def _checkpoint(self) -> None:
        assert self.replica is not None
        t0 = time.perf_counter()
        blobs = self.replica.checkpoint()
        old = set((await self.ddb_scan(team.K_SLAM_CKPT)).keys())
        ops = [ddbops.put(team.K_SLAM_CKPT + name, "blob", data) for name, data in blobs.items()]
        ops += [ddbops.delete(k) for k in old - {team.K_SLAM_CKPT + n for n in blobs}]
        ops.append(ddbops.log_trim(team.K_SLAM_LOG, self.replica.next_index))
        errs = await self.ddb_write(ops, atomic=True)
        if any(errs):
            self.log("checkpoint_failed", level="warning", errors=[e for e in errs if e])
            return
        self.since_ckpt = 0
        self.log("checkpoint", index=self.replica.next_index, bytes=sum(map(len, blobs.values())),
                 ms=round(1000 * (time.perf_counter() - t0), 1))

    async def _publish(self) -> None:
        if self.replica is None or not self.dirty:
            return
        self.dirty = False
        ests = {}
        for a in self.replica.names:
            t, x, y, th, std = self.replica.estimate(a)
            ests[a] = {"t": round(t, 4), "x": round(x, 4), "y": round(y, 4), "theta": round(th, 5),
                       "std": [round(float(s), 4) for s in std]}
        ops = [ddbops.put(team.K_SLAM_MAP, "blob", self.replica.encode_map()),
               team.op_put_json(team.K_SLAM_ESTIMATES, ests)]
        ops += [team.op_put_json(team.K_SLAM_EST + a, e) for a, e in ests.items()]
        lms = {str(i): [round(float(lm.mean[0]), 4), round(float(lm.mean[1]), 4),
                        round(float(max(lm.cov[0, 0], lm.cov[1, 1])) ** 0.5, 4)]
               for i, lm in self.replica.system.landmarks.landmarks.items()}
        if lms:
            ops.append(team.op_put_json(team.K_SLAM_LANDMARKS, lms))
        await self.ddb_write(ops)

    # ------------------------------------------------------------------ readings

    def _on_raw(self, kind: str, key: str, value: bytes | None) -> None:
        if kind == "add" and value is not None:
            self._add_reading(key, value)
            self._dispatch()
        elif kind == "remove":
            self.readings.pop(key, None)

    def _add_reading(self, key: str, data: bytes) -> None:
        if key in self.readings:
            return
        try:
            rec = json.loads(data)
            procs = PROCESSINGS[rec["kind"]]
        except (ValueError, KeyError, TypeError):
            self.log("bad_reading", level="warning", key=key)
            return
        self.readings[key] = {"rec": rec, "todo": set(procs), "discarded": 0, "n": len(procs)}
        for p in procs:
            self.stacks[p].append(key)

    def _dispatch(self) -> None:
        now = self.now()
        for p, stack in self.stacks.items():
            idle = [a for a, s in self.sensors[p].items() if s["job"] is None and s.get("ready")]
            while stack and idle:
                key = stack.pop()  # LIFO (Table 7.2-4): the newest reading first
                r = self.readings.get(key)
                if r is None or p not in r["todo"]:
                    continue
                a = idle.pop()
                self.sensors[p][a].update(job=key, since=now)
                self.send(a, team.dumps({"op": "process", "key": key, "proc": p, "reading": r["rec"]}))
            if self.cfg.mode == "discard":
                while stack:
                    self._discard(stack.pop(), p)
            elif stack:
                self.backlog_since.setdefault(p, now)
                self._maybe_grow(p, len(stack), now)
            else:
                self.backlog_since.pop(p, None)
            if not self.sensors[p] and not stack:
                continue
            if not self.sensors[p] and p not in self.spawning and self.cfg.mode != "discard":
                self._spawn(p)

    def _maybe_grow(self, p: str, backlog: int, now: float) -> None:
        n = len(self.sensors[p]) + (p in self.spawning)
        if n == 0:
            self._spawn(p)
            return
        if not all(s.get("ready") for s in self.sensors[p].values()):
            return  # one is still starting, or the allocation cannot place it (one per host): not yet
        cap = min(self.cfg.max_per_type, self.capped.get(p, self.cfg.max_per_type))
        if (backlog > self.cfg.grow_backlog and n < cap and p not in self.spawning
                and now - self.backlog_since.get(p, now) >= self.cfg.grow_wait_s
                and now - self.last_grow.get(p, -1e9) >= self.cfg.grow_wait_s):
            self._spawn(p)

    def _spawn(self, p: str) -> None:
        self.spawning.add(p)
        self.last_grow[p] = self.now()
        cfg = team.team_config(self, supervisor=self.id)
        if p == "sensor_landmark":
            cfg.update(landmark_ids=self.cfg.landmark_ids, marker_dictionary=self.cfg.marker_dictionary,
                       marker_size=self.cfg.marker_size)

        async def go() -> None:
            # in the background: the mailbox goes on while the allocation places it (or cannot)
            aid: str | None = None
            why = ""
            try:
                aid = await self.spawn_child(p, cfg, timeout=20.0)
            except Exception as e:
                why = f"{type(e).__name__}: {e}"
            self.call_later(0, lambda: self._spawned(p, aid, why))

        self._background(go())

    def _background(self, coro: Any) -> None:
        """Run `coro` beside the mailbox, keeping a reference until it ends (asyncio keeps only weak ones)."""
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _spawned(self, p: str, aid: str | None, why: str) -> None:
        self.spawning.discard(p)
        if aid is None:
            self.capped[p] = len(self.sensors[p])
            self.log("sensor_spawn_failed", level="warning", type=p, reason=why)
            return
        self.sensors[p].setdefault(aid, {"job": None, "since": self.now(), "ready": False})
        self.backup()
        await team.transcript(self, f"{p} agent {len(self.sensors[p])} requested")
        self._dispatch()

    def _discard(self, key: str, p: str) -> None:
        r = self.readings.get(key)
        if r is None or p not in r["todo"]:
            return
        r["todo"].discard(p)
        r["discarded"] += 1
        if not r["todo"]:
            self._background(self._finish(key, r))

    async def _finish(self, key: str, r: dict[str, Any]) -> None:
        self.readings.pop(key, None)
        ops = [ddbops.delete(key)]
        if r["discarded"] >= r["n"]:
            ops.append(ddbops.add(team.K_STATS + "readings_discarded", 1))
        else:
            ops.append(ddbops.add(team.K_STATS + "readings_processed", 1))
        await self.ddb_write(ops)

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        if msg.get("op") == "hello":  # a (re)started sensor agent: known, and idle
            p = msg.get("proc", "")
            if p in self.sensors:
                s = self.sensors[p].setdefault(src, {"job": None, "since": self.now()})
                if s["job"] is not None:  # restarted while it had one: hand it out again
                    r = self.readings.get(s["job"])
                    if r is not None and p in r["todo"]:
                        self.stacks[p].append(s["job"])
                s["job"] = None
                s["ready"] = True
                self._dispatch()
            return
        if msg.get("op") != "done":
            return
        p, key = msg.get("proc", ""), msg.get("key", "")
        s = self.sensors.get(p, {}).get(src)
        if s is not None and s["job"] == key:
            s["job"] = None
        r = self.readings.get(key)
        if r is not None and p in r["todo"]:
            r["todo"].discard(p)
            if not msg.get("ok"):
                r["discarded"] += 1
            if not r["todo"]:
                await self._finish(key, r)
        self._dispatch()

    async def _watchdog(self) -> None:
        """Status monitoring (App. III, by analogy with the other supervisors: "if failure occurs reassign
        reading"): a processing out for longer than `job_timeout_s` goes back on its stack."""
        now = self.now()
        for p, agents in self.sensors.items():
            for a, s in agents.items():
                if s["job"] is not None and now - s["since"] > self.cfg.job_timeout_s:
                    key = s["job"]
                    s["job"] = None
                    r = self.readings.get(key)
                    if r is not None and p in r["todo"]:
                        self.stacks[p].append(key)
                    self.log("processing_timeout", level="warning", agent=a, key=key)
        self._dispatch()
