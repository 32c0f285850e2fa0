"""What the robot-team agents of Appendix III share (issue 15; docs/team.md): config models, the mission clock,
the channel to haa-sim, DDB helpers and the mission transcript.

Not an agent type itself (the registry imports it and finds no `@register`): each agent lives in the module
named after it (executive_mission.py, avatar_simulation.py, ...).

* `TeamConfig` — the part of every team agent's config the mission sets: haa-sim's address and token file,
  the speed (simulated seconds per wall second), the mission seed and the mission clock's anchor.
* `MissionClock` — the simulated time every team agent sees (issue 15: "at `--speed 4` an agent's timers,
  `now()` and random numbers follow the simulator's clock"): `sim0` simulated seconds at wall time `wall0`
  (time.time(), so that every process on every machine with a synchronised clock agrees), running `speed`
  times faster. `use_mission_clock(agent, cfg)` installs it with the mission seed.
* `SimLink` (haa.agents.simlink) — an asyncio gRPC channel to haa-sim's AvatarSim service carrying the token
  and the caller's name (metadata `x-haa-caller`, which haa-sim uses to count calls per caller: the agents must make no
  ground-truth or Detect calls, a mission test checks it).
* `transcript(agent, text)` — one line of the mission transcript (Fig. 7.1-3) in the DDB log `mission/events`.
* `get_json`, `put_json`, `counter_add` — small DDB helpers.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import json
import math
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any, ClassVar, TypeVar

import numpy as np
import pydantic

from haa.agents.simlink import SimLink as SimLink  # the channel to haa-sim (re-exported: team.SimLink)
from haa.core.ddb import ops as ddbops
from haa.sdk.base import AgentBase, Clock

T = TypeVar("T")

#: DDB keys (docs/team.md "DDB layout")
K_PARAMS = "mission/params"
K_STATUS = "mission/status"
K_EVENTS = "mission/events"
K_AVATARS = "avatars/"
K_BIDS = "bids/"
K_ASSIGN = "assign/"
K_SLAM_LOG = "slam/log"
K_SLAM_CKPT = "slam/ckpt/"
K_SLAM_MAP = "slam/map"
K_SLAM_EST = "slam/est/"
K_SLAM_ESTIMATES = "slam/estimates"
K_SLAM_RAW = "slam/raw/"
K_SLAM_LANDMARKS = "slam/landmarks"
#: Forage (docs/team.md "Forage: identified collectables in the DDB"): SupervisorSLAM writes the estimates of
#: the identified collectables in one key; each collectable's forage state is a key of its own, written by
#: the forage agents, never by SupervisorSLAM
K_FORAGE_COLLECTABLES = "forage/collectables"
K_FORAGE_STATE = "forage/state/"
K_TARGETS = "targets/"
K_STATS = "stats/"

#: bid priorities (docs/team.md "Bid scale"): SupervisorExplore's low default, SupervisorCongregate's "all
#: avatars"; SupervisorForage bids BID_FORAGE_BASE + BID_FORAGE_RANGE / (1 + d) (d: the weighted path length in
#: metres from the avatar's estimate to the collectable's, `forage_priority`) while it looks for an avatar,
#: and BID_FORAGE_HOLD on the one it holds — above every forage bid (no other SupervisorForage takes it away),
#: below SupervisorCongregate's
BID_EXPLORE = 1.0
BID_FORAGE_BASE = 2.0
BID_FORAGE_RANGE = 6.0
BID_FORAGE_HOLD = 9.0
BID_CONGREGATE = 10.0

#: AgentPathPlanner's reason when the avatar itself is boxed in (haa.agents.path_planner.enclosed): its avatar
#: agent turns in place to look around before it gives the target up (AvatarSimulation._look_around)
START_ENCLOSED = "start enclosed"

def physics_cruise(top_speed: float, map_cell: float, sonar_period: float | None, capture_period: float) -> float:
    """Cruise speed (m/s) from an avatar's own sensing (mission `cruise: physics`, docs/team.md "Cruise speed"):
    at most one map cell travelled between two readings of the sensor that maps what it passes — the sonar
    ring's scan for an avatar with sonars, else its camera image (the floor finder) — and never above its top
    speed. A sweeper (sonar every 1 s, 0.1 m cells) drives 0.1 m/s of its 1.0; a seeker or carrier (an image
    every 0.5 s) 0.2 m/s of its 2.0 / 1.5."""
    period = sonar_period if sonar_period is not None and sonar_period > 0 else capture_period
    return min(float(top_speed), float(map_cell) / float(period))


#: collectables an avatar type carries at once (Table 6.2-3), for a registry entry without `capacity`
CAPACITY = {"seeker": 0, "enhanced_seeker": 0, "sweeper": 1, "carrier": 1}


def forage_priority(d: float | None) -> float:
    """SupervisorForage's bid for an avatar `d` metres (path) from its collectable; None/inf: unknown."""
    if d is None or not math.isfinite(d):
        return BID_FORAGE_BASE
    return BID_FORAGE_BASE + BID_FORAGE_RANGE / (1.0 + max(0.0, d))


def capacity(reg: dict[str, Any]) -> int:
    """How many collectables the avatar of registry entry `reg` carries at once: what it registered
    (`capacity`, from its hardware: haa-sim's AvatarInfo), else its type's (CAPACITY; unknown type: 0)."""
    c = reg.get("capacity")
    if isinstance(c, int | float) and not isinstance(c, bool):
        return int(c)
    return CAPACITY.get(str(reg.get("type", "")), 0)

#: transcript lines kept in `mission/events` (older ones are trimmed by ExecutiveMission)
EVENTS_KEEP = 2000


class TeamConfig(pydantic.BaseModel):
    """Config fields every team agent takes from the mission (docs/team.md "Starting a mission")."""

    model_config = pydantic.ConfigDict(extra="forbid")

    sim: str = pydantic.Field("", description="haa-sim address HOST:PORT")
    sim_token_file: str = ""
    speed: float = pydantic.Field(1.0, gt=0, le=1000)
    seed: int = 0
    #: the mission clock's anchor: `sim0` simulated seconds at wall time `wall0` (time.time()); 0/0 = the
    #: simulated clock starts at 0 when the agent starts (tests)
    sim0: float = 0.0
    wall0: float = 0.0


class MissionClock(Clock):
    """Simulated mission time: `sim0` at wall time `wall0`, `speed` simulated seconds per wall second."""

    def __init__(self, speed: float, sim0: float, wall0: float) -> None:
        self.speed = float(speed)
        self.sim0 = float(sim0)
        self.wall0 = float(wall0) if wall0 > 0 else time.time()

    def now(self) -> float:
        return self.sim0 + (time.time() - self.wall0) * self.speed

    def wall_delay(self, delay: float) -> float:
        return max(0.0, delay) / self.speed


def use_mission_clock(agent: AgentBase, cfg: TeamConfig) -> None:
    """Give `agent` the mission clock and the mission's seeded random source."""
    agent._ctx.set_clock(MissionClock(cfg.speed, cfg.sim0, cfg.wall0), seed=cfg.seed)


def team_config(agent: AgentBase, **extra: Any) -> dict[str, Any]:
    """The TeamConfig part of `agent.cfg` as a dict (to pass on to a child), updated with `extra`."""
    base = {k: getattr(agent.cfg, k) for k in TeamConfig.model_fields}
    base.update(extra)
    return base


# ---------------------------------------------------------------------------------------------- haa-sim


def frame_from_pb(m: Any, avatar: str) -> SimpleNamespace:
    """A haa-sim CameraFrame message as the object haa.control's detectors read (image, K, mount, max_range,
    time, avatar); the true pose is not in the message and is not made up."""
    from haa.sim.convert import decode_frame

    return SimpleNamespace(
        image=decode_frame(m),
        K=np.asarray(m.K, dtype=float).reshape(3, 3),
        mount=(m.mount.x, m.mount.y, m.mount.z, m.mount.pitch),
        max_range=float(m.max_range),
        fov=float(m.fov),
        time=float(m.time),
        avatar=avatar,
        camera=m.camera,
    )


# ---------------------------------------------------------------------------------------------- DDB


async def get_json(agent: AgentBase, key: str, default: Any = None) -> Any:
    """The JSON value at `key`, or `default` when it is missing or not JSON."""
    data = await agent.ddb_get(key)
    if data is None:
        return default
    try:
        return json.loads(data)
    except ValueError:
        return default


async def put_json(agent: AgentBase, key: str, value: Any) -> None:
    await agent.ddb_put_json(key, value)


def op_put_json(key: str, value: Any) -> Any:
    return ddbops.put(key, "json", value)


def dumps(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":")).encode()


async def counter_add(agent: AgentBase, name: str, delta: int = 1) -> None:
    await agent.ddb_write([ddbops.add(K_STATS + name, delta)])


async def transcript(agent: AgentBase, text: str) -> None:
    """Append one line to the mission transcript (Fig. 7.1-3): time, agent name and type, text."""
    line = {"t": round(agent.now(), 3), "agent": agent.name, "type": agent.TYPE, "text": text}
    try:
        await agent.ddb_log_append(K_EVENTS, [dumps(line)])
    except Exception as e:  # the transcript must never take an agent down
        agent.log("transcript_failed", level="warning", error=str(e))


# ---------------------------------------------------------------------------------------------- team agents


class TeamAgent(AgentBase):
    """Base of the control-system agents (App. III): each runs on the mission clock and the mission's seeded
    random source (`use_mission_clock`), and a start, a thaw after a transfer and a recovery from a backup all
    go through one `begin(how)` — `how` is "start", "thaw" or "recover" (AgentBase.on_resume's values) — so
    what an agent sets up on each of them (watches, timers, bidding) is written once.

    A subclass reads `how` where the three differ: only a new agent announces itself, a recovered one may
    drop what its backup cannot vouch for, a thawed one keeps everything it had."""

    cfg: TeamConfig

    async def on_start(self) -> None:
        use_mission_clock(self, self.cfg)
        await self.begin("start")

    async def on_resume(self, how: str) -> None:
        use_mission_clock(self, self.cfg)
        await self.begin(how)

    async def begin(self, how: str) -> None:
        """Set the agent up after a start, a thaw or a recovery (the clock is the mission's already)."""


# ---------------------------------------------------------------------------------------------- supervisors


class SupervisorBase(TeamAgent):
    """What the task supervisors share (the thesis' SupervisorTask parent class, Fig. 6.2-3): bidding for
    avatars with ExecutiveAvatar (App. III L3043: bids and assignments in the DDB), knowing which avatars it
    controls, and sending them targets.

    A subclass sets `TASK` and `priority()`, and implements `on_avatars_changed()` (called, in the mailbox,
    when the set of controlled avatars changes). State kept here: `controlled` (avatar → agent id), `bid_on`
    (avatars bid on), `targets` (avatar → the last target sent), `next_tid`.
    """

    TASK: str = ""

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.controlled: dict[str, str] = {}
        self.registry: dict[str, dict[str, Any]] = {}
        self.targets: dict[str, dict[str, Any]] = {}
        self.next_tid = 1
        self.bidding = True

    def priority(self, avatar: str) -> float:
        raise NotImplementedError

    def wants(self, avatar: str) -> bool:
        """Whether to bid on `avatar` (active, and bidding at all, are checked besides). Default: every one."""
        return True

    def _bid_op(self, a: str) -> Any:
        return op_put_json(f"{K_BIDS}{a}/{self.id}", {"priority": self.priority(a), "task": self.TASK,
                                                      "t": round(self.now(), 3)})

    def _unbid_op(self, a: str) -> Any:
        """The deletion of this supervisor's bid on avatar `a`."""
        return ddbops.delete(f"{K_BIDS}{a}/{self.id}")

    async def _my_bids(self) -> set[str]:
        """The avatars this supervisor has a bid on, as `bids/` holds them (not as its registry says)."""
        out = set()
        for k in await self.ddb_scan(K_BIDS):
            avatar, _, sup = k[len(K_BIDS):].partition("/")
            if sup == self.id:
                out.add(avatar)
        return out

    async def _withdraw_mine(self) -> None:
        """Delete every bid of this supervisor in `bids/` — those on avatars no longer in its registry too, which
        `withdraw_bids` (the registry's avatars) leaves."""
        mine = await self._my_bids()
        if mine:
            await self.ddb_write([self._unbid_op(b) for b in sorted(mine)])

    async def on_avatars_changed(self) -> None:
        """The controlled set changed."""

    async def start_bidding(self) -> None:
        """Watch the avatar registry and the assignments; bid on every active avatar."""
        self.watch(K_AVATARS, self._on_registry)
        self.watch(K_ASSIGN, self._on_assign)
        for key, data in (await self.ddb_scan(K_AVATARS)).items():
            self.registry[key[len(K_AVATARS):]] = json.loads(data)
        await self._bid_all()
        await self._load_assignments()

    async def _bid_all(self) -> None:
        ops = []
        for a, reg in self.registry.items():
            if reg.get("status") == "active" and self.bidding and self.wants(a):
                ops.append(self._bid_op(a))
        if ops:
            await self.ddb_write(ops)

    async def withdraw_bids(self) -> None:
        self.bidding = False
        ops = [self._unbid_op(a) for a in self.registry]
        if ops:
            await self.ddb_write(ops)

    async def _load_assignments(self) -> None:
        mine: dict[str, str] = {}
        for key, data in (await self.ddb_scan(K_ASSIGN)).items():
            a = key[len(K_ASSIGN):]
            v = json.loads(data)
            if v.get("supervisor") == self.id and self.registry.get(a, {}).get("status") == "active":
                mine[a] = self.registry[a]["agent"]
        await self._set_controlled(mine)

    async def _set_controlled(self, mine: dict[str, str]) -> None:
        if mine != self.controlled:
            gained = sorted(set(mine) - set(self.controlled))
            lost = sorted(set(self.controlled) - set(mine))
            self.controlled = mine
            for a in lost:
                self.targets.pop(a, None)
            if gained or lost:
                await transcript(self, f"controls {', '.join(sorted(mine)) or 'no avatar'}"
                                 + (f" (gained {', '.join(gained)})" if gained else "")
                                 + (f" (lost {', '.join(lost)})" if lost else ""))
            await self.on_avatars_changed()

    async def _on_registry(self, kind: str, key: str, value: bytes | None) -> None:
        a = key[len(K_AVATARS):]
        if kind == "remove" or value is None:
            self.registry.pop(a, None)
        else:
            self.registry[a] = json.loads(value)
        reg = self.registry.get(a)
        if reg and reg.get("status") == "active" and self.bidding and self.wants(a):
            await self.ddb_write([self._bid_op(a)])
        elif reg is not None or kind == "remove":
            await self.ddb_write([self._unbid_op(a)])
        await self._load_assignments()

    async def _on_assign(self, kind: str, key: str, value: bytes | None) -> None:
        await self._load_assignments()

    def send_target(self, avatar: str, x: float, y: float) -> None:
        agent = self.controlled.get(avatar)
        if not agent:
            return
        tid = self.next_tid
        self.next_tid += 1
        t = {"x": round(x, 3), "y": round(y, 3), "tid": tid, "sup": self.id}
        self.targets[avatar] = {**t, "state": "driving", "since": self.now()}
        self.send(agent, dumps({"op": "target", **t}))

    def pack_state(self) -> bytes:
        """The whole state (a transfer): targets, next target id, bidding, and the controlled set — a thawed
        supervisor that took its avatars for new ones would send them all new targets after every move."""
        return dumps({"targets": self.targets, "tid": self.next_tid, "bidding": self.bidding,
                      "controlled": self.controlled})

    def pack_backup(self) -> bytes:
        """The backup without the controlled set: a recovered supervisor reads it again from `assign/` and gives
        every avatar a target afresh (App. III: "retrieve Avatar* statuses, reassign targets if appropriate")."""
        return dumps({"targets": self.targets, "tid": self.next_tid, "bidding": self.bidding})

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        self.targets = st.get("targets", {})
        self.next_tid = int(st.get("tid", 1))
        self.bidding = bool(st.get("bidding", True))
        self.controlled = dict(st.get("controlled", {}))

    def recover(self, backup: bytes | None) -> None:
        if backup:
            self.unpack_state(backup)


# ---------------------------------------------------------------------------------------------- sensor agents

#: processing markers (docs/team.md "DDB layout"): `slam/done/<avatar>/<n>/<proc>` exists once processing
#: `<proc>` of the reading `slam/raw/<avatar>/<n>` is applied — written by the sensor agent in the atomic batch
#: of its Observe events (a cas "must not exist": a second application of the same processing aborts),
#: deleted by SupervisorSLAM with the raw entry
K_SLAM_DONE = "slam/done/"


def done_key(raw_key: str, proc: str) -> str:
    """The marker key of processing `proc` of the reading at `raw_key`."""
    tail = raw_key[len(K_SLAM_RAW):] if raw_key.startswith(K_SLAM_RAW) else raw_key
    return f"{K_SLAM_DONE}{tail}/{proc}"


def done_parts(marker: str) -> tuple[str, str]:
    """(raw key, processing type) of a marker key (`done_key`'s inverse for raw keys under `slam/raw/`)."""
    tail, _, proc = marker[len(K_SLAM_DONE):].rpartition("/")
    return K_SLAM_RAW + tail, proc


class SensorConfig(TeamConfig):
    supervisor: str = pydantic.Field(min_length=1)
    #: the avatar this agent is dedicated to (SupervisorSLAM's delay mode, Table 7.2-4: "each Avatar agent
    #: handles its own readings with a dedicated agent of each type"); "" = shared by the team
    avatar: str = pydantic.Field("", max_length=64)


class SensorBase(TeamAgent):
    """What the sensor processing agents share (the thesis' AgentSensorProcessing parent class, Fig. 6.2-3).

    Protocol with SupervisorSLAM ("Assign processing requests" / "Report success or failure of processing",
    App. III L2971-3015): {"op": "process", "key", "proc", "reading"} in; the agent turns the raw reading
    into haa.slam readings (`process`, implemented by each type), appends their Observe events to
    `slam/log` with `stats/processings` and the processing's marker (`done_key`) in one atomic batch, and
    answers {"op": "done", "key", "proc", "ok", "wrote", "skipped", "ms", "n", "items"}; several processings
    run side by side (each in a task beside the mailbox: most of their time is waiting for the frame and the
    commit). A (re)started agent says {"op": "hello", "proc", "avatar"} to its supervisor; {"op": "stop"} from
    it ends the agent (a dedicated agent whose avatar left, `dedicated_type`). Recovery: "Restore
    configuration and wait for instructions" (RECOVERY = "restart": the supervisor hands out again what
    was in flight). At most one agent of each sensor type per host (MAX_PER_HOST = 1, App. III L3103).

    **Exactly once.** A processing may be handed out twice (SupervisorSLAM recovered, or its job timed out, or
    the agent restarted): the marker makes the second one a no-op. The agent looks for the marker first (a
    local read: present → answers done with `skipped` "marked", writes nothing), and the batch's first op is
    a cas of the marker with expected version 0 ("must not exist"): if another agent or copy committed it
    meanwhile the whole batch aborts ("op 0 failed: version mismatch") and the answer is the same. A copy of
    a processing this agent has in flight waits for it and then takes the same path (no second frame fetch
    or detection). {"op": "sync", "sync"} from the supervisor (after a hello from an agent it had given
    processings to, and after its own recovery or move) is answered {"op": "synced", "proc", "sync", "busy":
    keys in flight}: the messages are FIFO per sender, so every processing the supervisor sent before it
    has been seen by then, and those neither done nor busy were lost with the agent's previous life."""

    cfg: SensorConfig

    CONFIG: ClassVar[type[pydantic.BaseModel] | None] = SensorConfig
    #: the processing type it serves (the supervisor's name for it); "" = its TYPE. A dedicated agent
    #: (`dedicated_type`) is a type of its own that serves its base type's processings
    PROC: ClassVar[str] = ""
    RECOVERY = "restart"
    MAX_PER_HOST = 1
    COST = 0.2
    CPU_LIMIT = 1.5

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.done = 0
        self.failed = 0
        self.skipped = 0
        self.jobs: set[asyncio.Task[Any]] = set()  # processings in flight (kept referenced: asyncio holds weak ones)
        #: raw key → the task of the first copy of that processing in flight here
        self.inflight: dict[str, asyncio.Task[Any]] = {}
        self._compute_pool: concurrent.futures.ThreadPoolExecutor | None = None

    async def compute(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on this agent's one compute thread: image decoding and scanning (OpenCV and numpy
        release the GIL) stay off the event loop, which keeps answering messages and heartbeating its host — a
        loop blocked for the host's hang timeout (`haa-hostd --agent-hang-timeout`) is killed as hung, and under
        load a few frames scanned in a row on the loop took over a second. One thread: the processings in
        flight share the detector objects, which are not made for concurrent use."""
        if self._compute_pool is None:
            self._compute_pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="compute")
        return await self.run_in_thread(self._compute_pool, fn, *args)  # its return recorded (docs/playback.md)

    async def process(self, reading: dict[str, Any]) -> list[Any]:
        """The haa.slam readings (SonarReading, LandmarkReading, ...) of one raw reading; [] if it gives none."""
        raise NotImplementedError

    @property
    def proc(self) -> str:
        return self.PROC or self.TYPE

    def _hello(self) -> None:
        self.send(self.cfg.supervisor, dumps({"op": "hello", "proc": self.proc, "avatar": self.cfg.avatar}))

    async def begin(self, how: str) -> None:
        self._hello()  # a new, moved or recovered sensor agent tells its supervisor it is (again) there

    async def on_message(self, src: str, payload: bytes) -> None:
        msg = json.loads(payload)
        op = msg.get("op")
        if op == "stop" and src == self.cfg.supervisor:  # its avatar left (delay mode)
            self.stop()
            return
        if op == "sync":
            self.send(src, dumps({"op": "synced", "proc": self.proc, "sync": msg.get("sync"),
                                  "busy": sorted(self.inflight)}))
            return
        if op != "process":
            return
        # each processing runs beside the mailbox: most of its time is waiting (the frame from the avatar agent,
        # the DDB commit), so several in flight share one process instead of needing one agent each (the
        # supervisor bounds how many it hands out at once: SlamAgentConfig.jobs_per_agent)
        key = str(msg.get("key", ""))
        first = self.inflight.get(key)
        if first is None:
            task = asyncio.ensure_future(self._process_one(src, msg))
            self.inflight[key] = task
            task.add_done_callback(functools.partial(self._done, key))
        else:  # handed out again while this agent has it: after the first copy, the marker answers
            task = asyncio.ensure_future(self._after(first, src, msg))
        self.jobs.add(task)
        task.add_done_callback(self.jobs.discard)

    async def _after(self, first: asyncio.Task[Any], src: str, msg: dict[str, Any]) -> None:
        await asyncio.wait([first])
        await self._process_one(src, msg)

    def _done(self, key: str, task: asyncio.Task[Any]) -> None:
        if self.inflight.get(key) is task:
            self.inflight.pop(key)

    async def _process_one(self, src: str, msg: dict[str, Any]) -> None:
        from haa.slam import events as sev

        t0 = self.perf_counter()  # recorded (AgentPlayback, docs/playback.md)
        ok, why, wrote, skipped = True, "", False, ""
        readings: list[Any] = []
        marker = done_key(str(msg.get("key", "")), self.proc)
        try:
            if await self.ddb_get(marker) is not None:
                skipped = "marked"  # applied already (by this agent's previous life, another agent, a copy)
            else:
                readings = await self.process(msg["reading"])
                evs = [sev.encode(sev.Observe(r, self.name)) for r in readings]
                ops = [ddbops.cas(marker, 0, "json", {"agent": self.name, "n": len(evs), "t": round(self.now(), 3)}),
                       ddbops.add(K_STATS + "processings", 1)]
                if evs:
                    ops.append(ddbops.log_append(K_SLAM_LOG, evs))
                errs = await self.ddb_write(ops, atomic=True)
                if not any(errs):
                    wrote = True
                elif "op 0 failed: version mismatch" in errs[0]:
                    skipped = "marked"  # committed meanwhile: the batch aborted, nothing written twice
                else:
                    ok, why = False, "; ".join(e for e in errs if e)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # a reading that cannot be processed is reported, not fatal
            ok, why = False, f"{type(e).__name__}: {e}"
        if skipped:
            self.skipped += 1
            readings = []
        elif ok:
            self.done += 1
        else:
            self.failed += 1
            self.log("processing_failed", level="warning", key=msg.get("key"), reason=why)
        # n: haa.slam readings made (Observe events), items: their parts (landmark sightings, floor vertices,
        # sonar echoes) — what SupervisorSLAM reports per processing type (its `slam_status` log)
        items = sum(len(getattr(r, "sightings", getattr(r, "polygon", getattr(r, "echoes", ())))) for r in readings)
        # (the agent may have ended meanwhile — moved, stopped: then it cannot send, and the marker tells)
        try:  # noqa: SIM105 (one import fewer in the shared module)
            self.send(src, dumps({"op": "done", "key": msg.get("key"), "proc": self.proc, "ok": ok, "why": why,
                                  "wrote": wrote, "skipped": skipped,
                                  "ms": round(1000 * (self.perf_counter() - t0), 2), "n": len(readings) if ok else 0,
                                  "items": items if ok else 0}))
        except RuntimeError:
            pass

    def on_stop(self) -> None:
        for t in list(self.jobs):
            t.cancel()

    async def fetch_frame(self, reading: dict[str, Any]) -> SimpleNamespace:
        """The camera frame of a reading, from the avatar agent that keeps it (no frames in the DDB)."""
        from haa.pb import sim_pb2 as spb

        data = await self.request(reading["agent"], dumps({"op": "frame", "n": reading["frame"]}), timeout=10.0)

        def decode() -> SimpleNamespace:
            m = spb.CameraFrame()
            m.ParseFromString(data)
            return frame_from_pb(m, reading["avatar"])

        return await self.compute(decode)


def dedicated_type(cls: type[SensorBase]) -> type[SensorBase]:
    """The type of `cls`'s agents dedicated to one avatar (SupervisorSLAM's delay mode): TYPE `<type>_dedicated`,
    serving `<type>` processings, with no per-host limit. The per-host limit is a property of the agent type
    (the allocation reads MAX_PER_HOST from the type, not from a config): with one agent of each type per
    avatar, five avatars on three hosts could not all be placed under `<type>`'s limit of one; and the
    dedicated agents should not take the shared type's places. Register the result in the sensor's module."""
    return type(f"{cls.__name__}Dedicated", (cls,), {
        "TYPE": cls.TYPE + "_dedicated", "PROC": cls.TYPE, "MAX_PER_HOST": 0, "__module__": cls.__module__,
        "__doc__": f"{cls.__name__} dedicated to one avatar (delay mode; haa.agents.team.dedicated_type)."})
