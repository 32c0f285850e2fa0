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

**Exactly once** (docs/team.md "Failures"). The sensor agent commits a marker `slam/done/<avatar>/<n>/<proc>`
(haa.agents.team.done_key) in the atomic batch of its Observe events, with a cas that aborts the batch if the
marker exists: a processing handed out twice is applied once. This agent reads the markers with the reading
list when it starts, recovers or is moved (a marked processing is not handed out again; a reading whose
processings are all marked is finished at once; a marker whose reading is gone is deleted) and deletes a
reading's markers after its raw entry, which goes in an atomic batch with the reading's count (counted once
if two lives of this agent finish it). A sensor agent that says hello while it had processings, and every
sensor agent after this agent's recovery or move, is asked {"op": "sync"} before it gets more: its answer
lists the processings it has in flight (kept as its jobs), and what it had and neither reported nor has in
flight was lost with its previous life (handed out again). A sync unanswered after `sync_timeout_s`: what
it had is handed out again, and it gets nothing until it answers or says hello (after a move, an agent that
never started — one the allocation could not place — was taken for a started one and fed processings that
all timed out, again and again).

**Modes** (Table 7.2-4, the mission's `slam`):

* `jc-slam` — one LIFO stack per processing type; a sensor agent gets up to `jobs_per_agent` processings at
  once (it runs them side by side: a processing is 2-3 ms of CPU and 0.2-0.6 s of waiting for the frame and
  the DDB commit at --speed 4), the newest first, and the next when it reports. When processings pile up
  (more than `grow_backlog` waiting for `grow_wait_s`) another agent of that type is requested, "limited by
  the available processing power of the hosts and up to a maximum of one sensor processing agent of each
  type ... per host": the sensor types declare MAX_PER_HOST = 1, so the allocation never places two on one
  host; a new agent is requested only when every agent of the type has started (said hello), so one the
  allocation cannot place (every host has one) stops the growth of that type (`max_per_type` bounds it as
  well). Processings go to started agents only.
* `discard` — a processing goes to an agent of its type with room at once, or is discarded;
  `discard_agents` agents of each type are spawned at start (the thesis: one of each type on every host).
* `delay` — "each Avatar agent handles its own readings with a dedicated agent of each type": when an
  avatar's first reading of a type arrives, an agent of the type `<type>_dedicated` (haa.agents.team.
  dedicated_type: config `avatar`, no per-host limit — the limit is the type's, and one per avatar and type
  must be placeable whatever the number of hosts) is spawned for it, and that avatar's readings go to it
  only, oldest first. When the avatar's RemoveAvatar is applied, its agents are told to stop. The avatar
  halts until its readings are processed: it can wait for its own `slam/raw/<avatar>/` entries, which this
  agent deletes when every processing of a reading is done (the avatar agent's part, docs/slam.md).

**SLAM state.** The particle filters, the occupancy grid and the landmark map are the replica
(haa.slam.replica) of the event log `slam/log` plus the checkpoint `slam/ckpt/*`: this agent applies every
event in index order, appends a Request event (JC-SLAM events (d)+(e)) for every avatar every `request_s`,
publishes the map (`slam/map`), the estimates (`slam/estimates`, `slam/est/<avatar>`) and the landmarks
(`slam/landmarks`) every `publish_s` — and, when they changed, the identified collectables' estimates
(`forage/collectables`, docs/team.md "Forage: identified collectables in the DDB"; with `collectables` set
the landmark agents also report the collectables they see, haa.agents.sensor_landmark) — and every
`checkpoint_events` events writes a checkpoint and trims the log in one atomic batch. A crash of this agent
or its host loses nothing committed: its successor restores the checkpoint and replays the log (recovery:
"Restore configuration and retrieve AgentSensor* statuses, reassign readings if appropriate. Confirm that
reading list is up to date" — the reading list is `slam/raw/` less the marked processings, read again; the
sensor agents' statuses are their answers to a sync: what they have in flight stays with them, the rest is
handed out again).

Periodic DDB writes (requests, publication, checkpoints) and the bookkeeping of finished readings run beside
the mailbox (`_upkeep`, `_background`): awaiting their commits in it held up the log events and the sensor
agents' reports. Every 10 s a `slam_status` log line says what the replica applied and skipped
(SlamReplica.counts: too_old, not_yet_predicted, unknown_avatar, ...), how far each filter's newest
prediction lags the mission clock, the stacks, the agents per type and what they made of their processings
(readings, sightings / vertices, wall ms, delay). HAA_SLAM_RECORD=DIR in the hosts' environment records every
applied log item to DIR (offline replays against the simulator's true poses, docs/slam.md).
"""

from __future__ import annotations

import asyncio
import json
import os
import struct
from typing import Any, Literal

import pydantic

from haa.agents import team
from haa.core.ddb import ops as ddbops
from haa.sdk.registry import register
from haa.slam import events as sev
from haa.slam.grid import GridSpec
from haa.slam.replica import LogGap, SlamReplica
from haa.slam.sensors import CooccupancyModel, FloorModel
from haa.slam.system import SlamConfig

#: the type name of a sensor agent dedicated to one avatar (delay mode) is its processing type's + this
DEDICATED = "_dedicated"
#: replaying the log at a recovery yields to the event loop after this much work (s): a long log replayed in
#: one go kept the loop from heartbeating its host, which killed the recovered supervisor as hung
LOAD_SLICE_S = 0.05

#: reading kind → the processing types it needs (sensor agent type names)
PROCESSINGS: dict[str, tuple[str, ...]] = {
    "camera": ("sensor_landmark", "sensor_floorfinder"),
    "cooccupancy": ("sensor_cooccupancy",),
    "sonar": ("sensor_sonar",),
}


class SlamAgentConfig(team.TeamConfig):
    mode: Literal["jc-slam", "discard", "delay"] = "jc-slam"
    particles: int = pydantic.Field(100, ge=1, le=10000)
    #: p(C) of the floor finder's obstacle marks (haa.slam.sensors.FloorModel.p_occ; None: free floor only).
    #: Seekers have no other way to map an obstacle: without the marks the path planner led them into thin
    #: panels and along walls (14-27 bumps per AF-1 run, each a push their odometry never saw; docs/team.md)
    floor_p_occ: float | None = pydantic.Field(0.7, gt=0.5, lt=1.0)
    #: whether floor and co-occupancy readings weigh the particles (haa.slam.sensors FloorModel.density,
    #: CooccupancyModel.density) or only build the map: replaying an AF-1 log (docs/slam.md "In the team, the
    #: obstacle marks"), landmarks alone localize to 0.084 m, the map-based densities on top to 0.14-0.29 m
    floor_density: Literal["free", "two-sided", "none"] = "none"
    cooccupancy_density: Literal["free", "none"] = "none"
    grid: tuple[float, float, float, float, float] = (0.0, 0.0, 3.4, 7.2, 0.1)  # x0, y0, width, height, res
    landmark_ids: list[int] = []
    marker_dictionary: str = ""
    marker_size: float = 0.0
    #: Forage: the landmark agents also report collectables (haa.agents.sensor_landmark); off: their configs
    #: and readings are those of explore and congregate
    collectables: bool = False
    request_s: float = pydantic.Field(1.0, gt=0, le=60)
    publish_s: float = pydantic.Field(0.5, gt=0, le=60)
    checkpoint_events: int = pydantic.Field(600, ge=10, le=1_000_000)
    grow_backlog: int = pydantic.Field(3, ge=1, le=1000)
    grow_wait_s: float = pydantic.Field(2.0, ge=0, le=600)
    max_per_type: int = pydantic.Field(8, ge=1, le=64)
    discard_agents: int = pydantic.Field(1, ge=1, le=64)
    job_timeout_s: float = pydantic.Field(15.0, gt=0, le=600)
    #: processings a sensor agent has at once (it runs them side by side: most of a processing's time is
    #: waiting for the frame and the DDB commit)
    jobs_per_agent: int = pydantic.Field(4, ge=1, le=64)
    #: a sensor agent asked {"op": "sync"} that has not answered by then gets its processings handed out again
    sync_timeout_s: float = pydantic.Field(10.0, gt=0, le=600)


@register
class SupervisorSLAM(team.TeamAgent):
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
        #: the reading list (`slam/raw/` and the markers) is loaded: before that, a "done" for a reading this
        #: agent does not know says nothing (a recovered agent handles the messages queued for it first)
        self.listed = False
        self.syncs = 0
        #: readings whose finish (the delete of the raw entry and the markers) is being committed
        self.finishing: set[str] = set()
        self.dirty = True
        # readings: raw key → {"rec": record, "todo": set of processing types left, "discarded": int}
        self.readings: dict[str, dict[str, Any]] = {}
        self.stacks: dict[str, list[str]] = {p: [] for ps in PROCESSINGS.values() for p in ps}
        # sensor agents: processing type → {agent id: {"jobs": {raw key: since}, "ready": bool, "avatar": str}}
        # ("avatar": the avatar a dedicated agent of the delay mode serves, "" for a shared one; while a sync
        # is out: "sync": its id, "sync_t": when, None once it timed out)
        self.sensors: dict[str, dict[str, dict[str, Any]]] = {p: {} for p in self.stacks}
        self.spawning: set[str] = set()
        #: delay mode: (processing type, avatar) pairs whose dedicated agent is being spawned or exists
        self.dedicated: set[tuple[str, str]] = set()
        #: background DDB writes of the periodic upkeep still in flight (one of each at a time)
        self.inflight: set[str] = set()
        #: avatars whose RemoveAvatar the replica applied (their dedicated sensor agents can stop)
        self.removed: set[str] = set()
        self.capped: dict[str, int] = {}
        self.last_grow: dict[str, float] = {}
        self.backlog_since: dict[str, float] = {}
        self.tasks: set[asyncio.Task[Any]] = set()
        #: what the sensor agents reported per processing type: processings, readings made, sightings, ms
        self.proc_stats: dict[str, dict[str, float]] = {}
        #: the `forage/collectables` value this life last wrote (written again only when it changes)
        self.collectables_written: dict[str, Any] | None = None
        #: HAA_SLAM_RECORD=DIR: every log item applied is appended to DIR/slam-log-<agent id>.bin (u32 index,
        #: u32 length, bytes), for offline replays against the simulator's true poses (diagnosis only)
        self.record = None
        rec_dir = os.environ.get("HAA_SLAM_RECORD", "")
        if rec_dir:
            os.makedirs(rec_dir, exist_ok=True)
            self.record = open(os.path.join(rec_dir, f"slam-log-{self.id}.bin"), "ab")  # noqa: SIM115

    # ------------------------------------------------------------------ life cycle

    def pack_state(self) -> bytes:
        return team.dumps({"sensors": {p: {a: s.get("avatar", "") for a, s in sorted(ag.items())}
                                       for p, ag in self.sensors.items()}})

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        for p, ids in st.get("sensors", {}).items():
            if p in self.sensors:
                # they said hello to the instance that backed them up: ready
                av = ids if isinstance(ids, dict) else dict.fromkeys(ids, "")
                self.sensors[p] = {i: {"jobs": {}, "ready": True, "avatar": a} for i, a in av.items()}
                self.dedicated |= {(p, a) for a in av.values() if a}

    def recover(self, backup: bytes | None) -> None:
        if backup:
            self.unpack_state(backup)

    async def begin(self, how: str) -> None:
        fresh = how == "start"
        self.watch_log(team.K_SLAM_LOG, self._on_event)
        await self._load()
        self.watch(team.K_SLAM_RAW, self._on_raw)
        await self._list_readings()
        if not fresh:  # recovered or moved: what each sensor agent still has in flight is asked, not handed out again
            for p, agents in self.sensors.items():
                for a, s in agents.items():
                    self._sync(p, a, s)
        if self.cfg.mode == "discard" and fresh:
            for p in self.stacks:
                for _ in range(self.cfg.discard_agents):
                    self._spawn(p)
        self.every(self.cfg.request_s, self._requests)
        self.every(self.cfg.publish_s, self._publish, first=0.1)
        self.every(1.0, self._watchdog)
        self.every(10.0, self._status_log, first=10.0)
        self._dispatch()

    async def _list_readings(self) -> None:
        """The reading list: `slam/raw/`, less the processings whose marker exists (applied by a sensor agent
        whose report this agent never got); a marker whose reading is gone (a processing committed after its
        reading was finished, or a finish whose delete of it failed) is deleted."""
        # the markers before the readings: a marker whose reading is not in the later scan belongs to one that
        # was finished (a reading is written before any of its markers); the other order took the marker of a
        # reading written between the two scans, and processed meanwhile, for an orphan and deleted it
        marks = await self.ddb_scan(team.K_SLAM_DONE)
        raw = await self.ddb_scan(team.K_SLAM_RAW)
        cut = bool(getattr(self._ctx, "scan_truncated", False))  # (then a marker's reading may just be unlisted)
        marked: dict[str, set[str]] = {}
        for m in marks:
            key, p = team.done_parts(m)
            marked.setdefault(key, set()).add(p)
        for key, data in raw.items():
            self._add_reading(key, data, marked.get(key, set()))
        orphans = [] if cut else [m for m in marks if team.done_parts(m)[0] not in raw]
        if orphans:
            self.log("orphan_markers", level="warning", n=len(orphans))
            self._background(self.ddb_write([ddbops.delete(m) for m in orphans]))
        skipped = sum(len(marked.get(k, ())) for k in raw)
        if skipped:
            self.log("marked_processings", n=skipped)
        self.listed = True

    async def _load(self) -> None:
        """The replica from the checkpoint and the log (recovery: nothing committed is lost)."""
        blobs = {k[len(team.K_SLAM_CKPT):]: v for k, v in (await self.ddb_scan(team.K_SLAM_CKPT)).items()}
        if blobs:
            self.replica = SlamReplica.restore(blobs)
        else:
            config = SlamConfig(n_particles=self.cfg.particles,
                                floor=FloorModel(p_occ=self.cfg.floor_p_occ, density=self.cfg.floor_density),
                                cooccupancy=CooccupancyModel(density=self.cfg.cooccupancy_density))
            self.replica = SlamReplica(self.spec, config, seed=self.cfg.seed)
        data = await self.ddb_get(team.K_SLAM_LOG)
        if data is not None:
            first, items = ddbops.decode_log(data)
            t = self.perf_counter()
            for k, item in enumerate(items):
                self._apply(first + k, item)
                if self.perf_counter() - t > LOAD_SLICE_S:  # let the loop heartbeat (events wait in `buffer`)
                    await asyncio.sleep(0)
                    t = self.perf_counter()
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
            res = self.replica.apply(index, item)
            if res.kind == "remove_avatar" and res.outcome == "applied":
                self.removed.add(res.avatar)
            if self.record is not None:
                self.record.write(struct.pack("<II", index, len(item)) + item)
        except LogGap:  # items we never saw were trimmed away: start again from the checkpoint
            self.log("slam_log_gap", level="warning", index=index, expected=self.replica.next_index)
            self.loading = True
            self.call_later(0, self._load)
            return
        self.since_ckpt += 1
        self.dirty = True

    # ------------------------------------------------------------------ SLAM state upkeep

    def _upkeep(self, what: str, coro: Any) -> None:
        """Run a periodic DDB write beside the mailbox (one of each kind at a time): awaiting its commit in
        the mailbox held up the log events, the sensors' reports and the dispatch behind it."""
        if what in self.inflight:
            coro.close()
            return
        self.inflight.add(what)

        async def go() -> None:
            try:
                await coro
            except Exception as e:
                self.log("upkeep_failed", level="warning", what=what, error=f"{type(e).__name__}: {e}")
            finally:
                self.inflight.discard(what)

        self._background(go())

    async def _requests(self) -> None:
        if self.replica is None:
            return
        evs = [sev.encode(sev.Request(a)) for a in self.replica.names]
        if evs:
            self._upkeep("requests", self.ddb_write([ddbops.log_append(team.K_SLAM_LOG, evs)]))
        if self.since_ckpt >= self.cfg.checkpoint_events and "checkpoint" not in self.inflight:
            self._upkeep("checkpoint", self._checkpoint(self.replica.checkpoint(), self.perf_counter()))

    async def _checkpoint(self, blobs: dict[str, bytes], t0: float) -> None:
        assert self.replica is not None
        old = set((await self.ddb_scan(team.K_SLAM_CKPT)).keys())
        ops = [ddbops.put(team.K_SLAM_CKPT + name, "blob", data) for name, data in blobs.items()]
        ops += [ddbops.delete(k) for k in old - {team.K_SLAM_CKPT + n for n in blobs}]
        upto = json.loads(blobs["meta"])["next_index"]  # the state the blobs hold (items applied since follow)
        ops.append(ddbops.log_trim(team.K_SLAM_LOG, upto))
        errs = await self.ddb_write(ops, atomic=True)
        if any(errs):
            self.log("checkpoint_failed", level="warning", errors=[e for e in errs if e])
            return
        self.since_ckpt = self.replica.next_index - upto
        self.log("checkpoint", index=upto, bytes=sum(map(len, blobs.values())),
                 ms=round(1000 * (self.perf_counter() - t0), 1))

    async def _status_log(self) -> None:
        """What the replica applied and skipped (SlamReplica.counts), what the sensor agents made of their
        processings, the stacks' depths and how far each filter's newest prediction lags the mission clock."""
        if self.replica is None:
            return
        now = self.now()
        lag = {a: round(now - pf.time, 2) for a, pf in self.replica.system.filters.items()}
        self.log("slam_status", counts=dict(sorted(self.replica.counts.items())), lag_s=lag,
                 stacks={p: len(s) for p, s in self.stacks.items()},
                 sensors={p: len(a) for p, a in self.sensors.items()},
                 procs={p: {k: round(v, 2) for k, v in st.items()} for p, st in self.proc_stats.items()},
                 gated=self.replica.system.landmarks.gated, landmarks=len(self.replica.system.landmarks),
                 collectables=len(self.replica.system.collectables))
        if self.record is not None:
            self.record.flush()

    async def _publish(self) -> None:
        if self.replica is None or not self.dirty or "publish" in self.inflight:
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
        # the estimates part only: each collectable's forage state is a key of its own (`forage/state/<id>`),
        # written by the forage agents, so this write never overwrites it
        cols = self.replica.system.collectables.published()
        if cols and cols != self.collectables_written:
            ops.append(team.op_put_json(team.K_FORAGE_COLLECTABLES, cols))
            self._upkeep("publish", self._write_publication(ops, cols))
        else:
            self._upkeep("publish", self.ddb_write(ops))

    async def _write_publication(self, ops: list[Any], cols: dict[str, Any]) -> None:
        errs = await self.ddb_write(ops)
        if not any(errs):
            self.collectables_written = cols
        else:  # (written again at the next publication)
            self.dirty = True

    # ------------------------------------------------------------------ readings

    def _on_raw(self, kind: str, key: str, value: bytes | None) -> None:
        if kind == "add" and value is not None:
            self._add_reading(key, value)
            self._dispatch()
        elif kind == "remove":
            self.readings.pop(key, None)

    def _add_reading(self, key: str, data: bytes, marked: set[str] | None = None) -> None:
        """A reading to process; `marked`: its processings already applied (their markers exist)."""
        if key in self.readings:
            return
        try:
            rec = json.loads(data)
            procs = PROCESSINGS[rec["kind"]]
        except (ValueError, KeyError, TypeError):
            self.log("bad_reading", level="warning", key=key)
            return
        r = {"rec": rec, "todo": set(procs) - (marked or set()), "discarded": 0, "n": len(procs), "procs": procs,
             "avatar": str(rec.get("avatar", ""))}
        self.readings[key] = r
        for p in procs:
            if p in r["todo"]:
                self.stacks[p].append(key)
        if not r["todo"]:  # every processing applied: only the finish was missing
            self._background(self._finish(key, r))

    def _free(self, s: dict[str, Any]) -> int:
        return self.cfg.jobs_per_agent - len(s["jobs"]) if s.get("ready") else 0

    def _dispatch(self) -> None:
        now = self.now()
        delay = self.cfg.mode == "delay"
        for p, stack in self.stacks.items():
            # drop what is no longer waiting (processed, discarded or gone)
            stack[:] = [k for k in stack if k in self.readings and p in self.readings[k]["todo"]]
            if delay:
                self._dispatch_dedicated(p, stack, now)
                continue
            free = [(a, s) for a, s in self.sensors[p].items() if self._free(s) > 0]
            while stack and free:
                a, s = free[-1]
                key = stack.pop()  # LIFO (Table 7.2-4): the newest reading first
                self._hand_out(p, a, s, key, now)
                if self._free(s) <= 0:
                    free.pop()
            if self.cfg.mode == "discard":
                # (not while an agent of the type is syncing: it may have some of them in flight)
                while stack and not any(s.get("sync_t") is not None for s in self.sensors[p].values()):
                    self._discard(stack.pop(), p)
            elif stack:
                self.backlog_since.setdefault(p, now)
                self._maybe_grow(p, len(stack), now)
            else:
                self.backlog_since.pop(p, None)
            if not self.sensors[p] and stack and p not in self.spawning and self.cfg.mode != "discard":
                self._spawn(p)

    def _dispatch_dedicated(self, p: str, stack: list[str], now: float) -> None:
        """Delay mode (Table 7.2-4): each avatar's readings go to the agents dedicated to that avatar, oldest
        first (the avatar waits for them, so they are processed in order); an avatar without its agent of
        this type gets one."""
        mine: dict[str, list[tuple[str, dict[str, Any]]]] = {}
        for a, s in self.sensors[p].items():
            mine.setdefault(s.get("avatar", ""), []).append((a, s))
        waiting: dict[str, list[str]] = {}
        for key in stack:
            waiting.setdefault(self.readings[key]["avatar"], []).append(key)
        for avatar, keys in waiting.items():
            if (p, avatar) not in self.dedicated:
                self._spawn(p, avatar)
            for a, s in mine.get(avatar, []):
                while keys and self._free(s) > 0:
                    key = keys.pop(0)
                    stack.remove(key)
                    self._hand_out(p, a, s, key, now)

    def _hand_out(self, p: str, a: str, s: dict[str, Any], key: str, now: float) -> None:
        s["jobs"][key] = now
        self.send(a, team.dumps({"op": "process", "key": key, "proc": p, "reading": self.readings[key]["rec"]}))

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

    def _spawn(self, p: str, avatar: str = "") -> None:
        """Request a sensor agent of processing type `p`: a shared one (growth, discard), or in delay mode one
        dedicated to `avatar` — a type of its own (`<p>_dedicated`, no per-host limit: one per avatar and
        type must be placeable whatever the number of hosts)."""
        if avatar:
            self.dedicated.add((p, avatar))
        else:
            self.spawning.add(p)
            self.last_grow[p] = self.now()
        cfg = team.team_config(self, supervisor=self.id)
        if avatar:
            cfg["avatar"] = avatar
        if p == "sensor_landmark":
            cfg.update(landmark_ids=self.cfg.landmark_ids, marker_dictionary=self.cfg.marker_dictionary,
                       marker_size=self.cfg.marker_size)
            if self.cfg.collectables:
                cfg["collectables"] = True
        type_name = p + DEDICATED if avatar else p

        async def go() -> None:
            # in the background: the mailbox goes on while the allocation places it (or cannot)
            aid: str | None = None
            why = ""
            try:
                # a shared agent is one more of identical ones (growth): always a new child (key ""); a
                # dedicated one is keyed by its type and config (the avatar) by default: asked again after a
                # recovery, it is the one already running (docs/agents.md, "Idempotent spawn")
                aid = await self.spawn_child(type_name, cfg, timeout=20.0, key=None if avatar else "")
            except Exception as e:
                why = f"{type(e).__name__}: {e}"
            self.call_later(0, lambda: self._spawned(p, aid, why, avatar))

        self._background(go())

    def _background(self, coro: Any) -> None:
        """Run `coro` beside the mailbox, keeping a reference until it ends (asyncio keeps only weak ones)."""
        task = asyncio.ensure_future(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _spawned(self, p: str, aid: str | None, why: str, avatar: str = "") -> None:
        if not avatar:
            self.spawning.discard(p)
        if aid is None:
            if avatar:
                self.dedicated.discard((p, avatar))  # asked again when its next reading comes
            else:
                self.capped[p] = len(self.sensors[p])
            self.log("sensor_spawn_failed", level="warning", type=p, avatar=avatar, reason=why)
            return
        self.sensors[p].setdefault(aid, {"jobs": {}, "ready": False, "avatar": avatar})
        self.backup()
        await team.transcript(self, f"{p} agent {len(self.sensors[p])} requested"
                              + (f" for avatar {avatar}" if avatar else ""))
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
        """Delete the raw entry and count the reading, in one atomic batch: the delete fails on an absent key, so
        a reading finished twice — by this agent and by its predecessor, whose finish was still in flight when
        it was frozen or crashed, or twice by a successor that listed it before that finish committed — is
        counted once (CI saw `readings_processed` 237 of 234 generated after a graceful leave). Then its
        processings' markers (those of discarded processings too: a write reported failed may have committed;
        deleting an absent one fails alone, that batch is not atomic). Raw entry first: a crash between the two
        leaves markers without a reading, which the next load deletes; the other order would leave a reading
        without markers, processed again."""
        self.readings.pop(key, None)
        stat = "readings_discarded" if r["discarded"] >= r["n"] else "readings_processed"
        self.finishing.add(key)
        try:
            why = (await self.ddb_write([ddbops.delete(key), ddbops.add(team.K_STATS + stat, 1)], atomic=True))[0]
            if why:
                self.log("finished_already", key=key, reason=why)
            marks = [ddbops.delete(team.done_key(key, p)) for p in r.get("procs", ())]
            if marks:
                await self.ddb_write(marks)
        finally:
            self.finishing.discard(key)

    async def _stray(self, key: str, p: str, sensor: str) -> None:
        """A report of a commit for a reading already finished: if its marker exists now (the finish's delete
        has committed), the commit came after the finish — the processing was out twice and applied twice —
        and the marker would stay for good. (A report of a commit the finish accounted for finds none: e.g. a
        moved or recovered agent that found every marker of the reading and finished it at once.)"""
        marker = team.done_key(key, p)
        if await self.ddb_get(marker) is None:
            return
        self.log("late_processing", level="warning", key=key, proc=p, sensor=sensor)
        await self.ddb_write([ddbops.delete(marker)])

    def _requeue(self, p: str, s: dict[str, Any], keep: set[str] | frozenset[str] = frozenset()) -> int:
        """Processings out with a sensor agent that restarted or went silent go back on their stack, but those
        in `keep` (it has them in flight); returns how many went back."""
        back = 0
        for key in [k for k in s["jobs"] if k not in keep]:
            del s["jobs"][key]
            r = self.readings.get(key)
            if r is not None and p in r["todo"] and key not in self.stacks[p]:
                self.stacks[p].append(key)
                back += 1
        self.stacks[p].sort(key=lambda k: self.readings[k]["rec"].get("t", 0.0) if k in self.readings else 0.0)
        return back

    def _sync(self, p: str, a: str, s: dict[str, Any]) -> None:
        """Ask sensor agent `a` what it has in flight ({"op": "sync"}); it gets nothing more until it answers.
        Messages are FIFO per sender: by the time it reads this, it has seen every processing sent before."""
        self.syncs += 1
        s["sync"] = f"{self.epoch}.{self.syncs}"
        s["sync_t"] = self.now()
        s["ready"] = False
        self.send(a, team.dumps({"op": "sync", "sync": s["sync"]}))

    def _synced(self, p: str, s: dict[str, Any], busy: set[str]) -> None:
        """The agent has `busy` in flight: they are its jobs (not on a stack); anything else it had was lost
        (its "done" would have come before the answer) and goes back on its stack."""
        now = self.now()
        kept = 0
        for key in busy:
            r = self.readings.get(key)
            if r is not None and p in r["todo"]:
                s["jobs"].setdefault(key, now)
                if key in self.stacks[p]:
                    self.stacks[p].remove(key)
                kept += 1
        back = self._requeue(p, s, keep=busy)
        s.pop("sync", None)
        s.pop("sync_t", None)
        s["ready"] = True
        if kept or back:
            self.log("sensor_synced", proc=p, in_flight=kept, requeued=back)

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        if msg.get("op") == "hello":  # a (re)started sensor agent: known, and idle
            p = msg.get("proc", "")
            if p in self.sensors:
                s = self.sensors[p].setdefault(src, {"jobs": {}, "avatar": str(msg.get("avatar", ""))})
                if msg.get("avatar"):
                    s["avatar"] = str(msg["avatar"])
                    self.dedicated.add((p, s["avatar"]))
                if s["jobs"]:
                    # restarted while it had some: those sent while it was down are still to come (its host
                    # kept them), those it had received are lost — its answer to the sync tells which
                    self._sync(p, src, s)
                else:
                    s.pop("sync", None)
                    s.pop("sync_t", None)
                    s["ready"] = True
                self._dispatch()
            return
        if msg.get("op") == "synced":
            p = msg.get("proc", "")
            s = self.sensors.get(p, {}).get(src)
            if s is not None and s.get("sync") is not None and msg.get("sync") == s["sync"]:
                self._synced(p, s, {str(k) for k in msg.get("busy", [])})
                self._dispatch()
            return
        if msg.get("op") != "done":
            return
        p, key = msg.get("proc", ""), msg.get("key", "")
        s = self.sensors.get(p, {}).get(src)
        if s is not None:
            s["jobs"].pop(key, None)
        r = self.readings.get(key)
        if r is None and msg.get("wrote") and self.listed and p in self.stacks and key not in self.finishing:
            # (not before the list is read: a recovered agent handles the messages queued for it first, and
            # then the marker tells that the processing was applied)
            self._background(self._stray(key, p, src))
        st = self.proc_stats.setdefault(p, {"done": 0, "failed": 0, "skipped": 0, "readings": 0, "items": 0,
                                            "ms": 0.0, "delay_s": 0.0})
        st["skipped" if msg.get("skipped") else "done" if msg.get("ok") else "failed"] += 1
        st["readings"] += int(msg.get("n", 0))
        st["items"] += int(msg.get("items", 0))
        st["ms"] += float(msg.get("ms", 0.0))
        if r is not None:
            st["delay_s"] += self.now() - float(r["rec"].get("t", self.now()))
        if r is not None and p in r["todo"]:
            r["todo"].discard(p)
            if not msg.get("ok"):
                r["discarded"] += 1
            if not r["todo"]:
                self._background(self._finish(key, r))
        self._dispatch()

    async def _watchdog(self) -> None:
        """Status monitoring (App. III, by analogy with the other supervisors: "if failure occurs reassign
        reading"): a processing out for longer than `job_timeout_s` goes back on its stack; in delay mode the
        dedicated agents of avatars that left are stopped."""
        now = self.now()
        for p, agents in self.sensors.items():
            for a, s in agents.items():
                if s.get("sync_t") is not None and now - s["sync_t"] > self.cfg.sync_timeout_s:
                    # what it had goes to others; it stays asked (a late answer or a hello makes it ready)
                    self.log("sync_timeout", level="warning", sensor=a, jobs=self._requeue(p, s))
                    s["sync_t"] = None
                late = [k for k, since in s["jobs"].items() if now - since > self.cfg.job_timeout_s]
                for key in late:
                    del s["jobs"][key]
                    r = self.readings.get(key)
                    if r is not None and p in r["todo"]:
                        self.stacks[p].append(key)
                    self.log("processing_timeout", level="warning", sensor=a, key=key)
        if self.cfg.mode == "delay" and self.replica is not None and not self.loading:
            gone = {a for _, a in self.dedicated} & self.removed
            gone -= {r["avatar"] for r in self.readings.values()} | set(self.replica.names)
            for avatar in gone:
                for p, agents in self.sensors.items():
                    for a in [a for a, s in agents.items() if s.get("avatar") == avatar]:
                        self.send(a, team.dumps({"op": "stop"}))
                        del agents[a]
                    self.dedicated.discard((p, avatar))
                await team.transcript(self, f"avatar {avatar} left: its dedicated sensor agents stop")
                self.backup()
        self._dispatch()
