"""The mission runner (issue 15 §3): the thesis' RemoteStart and operator (§6.1.4) for one mission.

    results = run_mission(load_mission("missions/quick.yaml"), speed=4, out_dir=Path("out"))

`run_mission` brings up its own local cluster (h1..hN, real haa-hostd processes: haa.cluster.local_backend) and
haa-sim (the mission's arena and seed, `--speed`, the avatar joins and retirements as `--schedule`), tells
ExecutiveMission what the operator knows of the arena (the number of reachable cells at `map_resolution`, from
haa-sim's explorable mask — never poses), spawns the top-level agents of docs/team.md (`executive_mission`, and
one `avatar_simulation` per avatar as it joins the arena), replays the host schedule at its simulated times
(leave = graceful retirement, kill = SIGKILL, join = a new haa-hostd, restart = haa-hostd under the killed
name with empty state), polls `mission/status` and the metrics until the mission is complete or
`complete.time_limit_s` (simulated) has passed, collects the results (haa.mission.results), writes the map and
allocation PNGs, the transcript (haa.mission.transcript) and the results JSON, and takes everything down — also
on Ctrl-C and on errors: every process it started is gone when it returns.

`MissionRun` is the same machinery in steps (`setup`, `poll`, `collect`, `teardown`); `haactl mission start`
runs it *attached* to a cluster the operator runs (haa.mission.attached: `conduct`, a detached process of its
own that `haactl mission stop` ends): it leaves the cluster alone, and stops the mission's agents and the
haa-sim it started.

Its parts: the schedules and end conditions as pure functions (haa.mission.plan), haa-sim's process
(haa.mission.simproc), the cluster queries it polls with (haa.cluster.queries), what it measures and the
results and files it makes of it (haa.mission.results: `Tally`; the PNGs: haa.mission.plots), the mission's
chaos plan (haa.mission.chaosrun).

Simulated time. Every schedule counts from haa-sim's t = 0 (its clock starts when it starts, after the host
group has formed); the avatar schedule runs inside haa-sim, the host schedule here, on haa-sim's clock as
polled. Mission duration is ExecutiveMission's `finished_t - started_t` (`mission/status`).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import psutil

from haa.cluster import queries
from haa.cluster.backend import Backend, ClusterError
from haa.mission import forage
from haa.mission import transcript as tr
from haa.mission.chaosrun import ChaosRun
from haa.mission.extensions import ExtensionMissing, extension
from haa.mission.plan import (
    MissionRunError,
    as_float,
    avatar_plan,
    due,
    host_kill_problems,
    host_plan,
    status_outcome,
    time_limit_reached,
)
from haa.mission.results import Tally, landmark_scores
from haa.mission.schema import Mission
from haa.mission.simproc import RUNNER_CALLER, SimHandle, arena_argument, check_sim_matches, start_sim
from haa.sdk import registry

#: top-level agent types the runner spawns (docs/team.md "Starting a mission")
EXECUTIVE = "executive_mission"
AVATAR = "avatar_simulation"
#: DDB keys the runner reads (docs/team.md "DDB layout")
K_STATUS = "mission/status"
K_EVENTS = "mission/events"
K_MAP = "slam/map"
K_EST = "slam/est/"
K_STATS = "stats/"
K_ASSIGN = "assign/"
K_TARGETS = "targets/"
K_LANDMARKS = "slam/landmarks"
#: how long an agent fault keeps trying to find its agent live (wall seconds; `MissionRun.kill_agent`)
FAULT_RETRY_S = 5.0
#: poll periods, wall seconds
POSE_PERIOD = 0.1
POLL_PERIOD = 1.0
MAP_PERIOD = 5.0


#: DDB prefixes of the robot team's state (docs/team.md "DDB layout")
TEAM_PREFIXES = ("mission/", "avatars/", "bids/", "assign/", "slam/", "targets/", "forage/")


def clear_team_state(backend: Backend, timeout: float = 15.0) -> int:
    """Delete every key of TEAM_PREFIXES from the cluster's DDB (a committed write), so that a mission started
    on a cluster that ran another one has a status, map and filters of its own (`haactl mission start` twice:
    the second must not read the first's `mission/status = complete`). The number of keys deleted."""
    from haa.core.ddb import ops as ddbmod

    names = queries.alive_hosts(backend)
    if not names:
        raise MissionRunError("no host is alive: cannot clear the previous mission's DDB keys")
    host = names[0]
    c = queries.host_client(backend, host, timeout)
    try:
        keys = sorted(o.key for p in TEAM_PREFIXES for o in c.ddb_get(prefix=p, keys_only=True).objects)
    except grpc.RpcError as e:
        raise MissionRunError(f"reading the previous mission's DDB keys on {host}: {e.code().name}") from None
    finally:
        c.close()
    for i in range(0, len(keys), 200):
        ops = [ddbmod.delete(k) for k in keys[i:i + 200]]
        c = queries.host_client(backend, host, timeout)
        try:
            rep = c.ddb_write(ops, timeout=timeout)
        except grpc.RpcError as e:
            raise MissionRunError(f"clearing the previous mission's DDB keys on {host}: {e.code().name}") from None
        finally:
            c.close()
        if not rep.committed:
            why = rep.reason or "not committed"
            raise MissionRunError(f"clearing the previous mission's DDB keys on {host}: {why}")
    return len(keys)


def team_modules_present() -> None:
    """Before starting anything: the modules of the two top-level agent types (docs/team.md) must exist (the
    hosts' registry is checked once the cluster is up)."""
    import importlib.util

    missing = [t for t in (EXECUTIVE, AVATAR) if importlib.util.find_spec(f"haa.agents.{t}") is None]
    if missing:
        raise MissionRunError(f"no agent module {', '.join(f'haa/agents/{t}.py' for t in missing)}: the robot-team "
                              "agents (docs/team.md) are not installed")


@dataclass
class ProgressInfo:
    """What a progress display needs, after each poll."""

    t: float  # simulated mission time
    limit: float
    explored: float | None
    target: float
    state: str
    hosts: int
    agents: int
    note: str = ""


class MissionRun:
    """One mission, step by step (module docstring). `run()` does it all and returns the results dict."""

    def __init__(
        self,
        mission: Mission,
        speed: float | None = None,
        out_dir: Path | None = None,
        root: Path | None = None,
        progress: Callable[[ProgressInfo], None] | None = None,
        backend: Any = None,
        sim: SimHandle | None = None,
        log: Callable[[str], None] | None = None,
        fresh_sim: bool | None = None,
        on_poll: Callable[[MissionRun], None] | None = None,
        agent_types: tuple[str, str] = (EXECUTIVE, AVATAR),
        record: Path | None = None,
    ) -> None:
        self.mission = mission
        self.spec = mission.spec
        self.speed = float(speed if speed is not None else self.spec.speed)
        self.progress = progress
        self.say = log or (lambda _text: None)
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if out_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="haa-mission-")
            out_dir = Path(self._tmp.name)
        self.out_dir = out_dir.absolute()
        self.root = (root or self.out_dir / "cluster").absolute()
        self.owns_cluster = backend is None
        self.backend = backend
        self.actions_backend: Any = None  # a second LocalBackend object for the host-action thread
        self.sim = sim
        self.owns_sim = sim is None  # started (and stopped) by this run
        #: haa-sim was started for this mission (its clock's 0 is mission time 0, it applies the avatar
        #: schedule itself); else the mission starts at its current time and avatars join through SimControl
        self.fresh_sim = sim is None if fresh_sim is None else fresh_sim
        self.on_poll = on_poll
        #: the types of the two top-level agents (tests run the runner with stand-ins)
        self.exec_type, self.avatar_type = agent_types
        self.rows: dict[str, Any] = {}  # agent id -> AgentInfo (last poll)
        self.per_host: dict[str, list[str]] = {}  # host -> display names of its active agents (last poll)
        self.assign: dict[str, Any] = {}  # avatar -> assign/<avatar>
        self.targets: dict[str, Any] = {}  # avatar -> targets/<avatar> (when the team publishes it)
        self.detail = on_poll is not None  # read assignments and targets too (haactl mission status)
        self.t0 = 0.0  # simulated time of mission time 0
        self.wall_start = 0.0
        self.lock = threading.Lock()
        self.stop_flag = threading.Event()
        self.host_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mission-hosts")
        self.agent_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mission-agents")
        self.pending: list[Future[Any]] = []
        #: what the run measures for its results (samples, true paths, estimates, maps)
        self.tally = Tally(mission, self.spec.map_resolution)
        self.clock = tr.ClockMap(self.speed)
        self.lines: list[tr.Line] = []  # the runner's own transcript lines
        self.errors: list[str] = []
        self.status: dict[str, Any] | None = None
        self.stats: dict[str, Any] = {}
        self.members: list[str] = []
        self.now = 0.0  # simulated time (haa-sim's clock)
        self.exec_id = ""
        self.exec_name = ""
        self.avatar_agents: dict[str, tuple[str, str]] = {}  # avatar -> (agent id, display name)
        self.spawning: set[str] = set()
        self.avatar_status: dict[str, str] = {}
        self.host_steps = host_plan(mission)
        self.hosts_done = 0
        self.avatar_steps = avatar_plan(mission)
        #: operator kills of agents (mission file `agent_faults`), in time order
        self.fault_steps = sorted(((f.at_s, f.kill) for f in mission.spec.agent_faults), key=lambda x: x[0])
        self.faults_done = 0
        self.avatars_done = 0
        self.sim_schedule = self.fresh_sim  # haa-sim applies the avatar schedule (started with --schedule)
        self.reader = ""  # the host we read the DDB from last
        self.outcome: tuple[bool, str] | None = None
        self.exec_failed = ""
        #: the chaos plan the mission file names (`chaos: FILE`, checked by the schema), run by `start_chaos`
        self.chaos = ChaosRun.of(mission, self.line, self.errors)
        #: AgentPlayback (docs/playback.md): every agent of our own cluster records into this folder
        self.record_dir = record_folder(self.spec.record, self.out_dir, record)

    # ------------------------------------------------------------------ lines
    def line(self, text: str, event: str = "runner", host: str = "", t: float | None = None) -> None:
        with self.lock:
            self.lines.append(tr.Line(self.mission_time() if t is None else t, text, "runner", event, host=host))
        self.say(text)

    def mission_time(self, sim_t: float | None = None) -> float:
        return (self.now if sim_t is None else sim_t) - self.t0

    # ------------------------------------------------------------------ setup
    def check_agent_types(self, types: Iterable[str] | None) -> None:
        have = set(types or [])
        missing = [t for t in (self.exec_type, self.avatar_type) if t not in have]
        if missing:
            raise MissionRunError(
                f"agent type{'s' if len(missing) > 1 else ''} {', '.join(missing)} not registered on the hosts: "
                "the robot-team agents (haa/agents/, docs/team.md) are not installed")

    def setup(self) -> None:
        from haa.cluster.backend import StartError, wait_until
        from haa.cluster.local_backend import LocalBackend

        if self.owns_cluster:  # the host schedule is replayed on our own cluster only
            problems = host_kill_problems(self.mission)
            if problems:
                raise MissionRunError(problems[0])
        self.wall_start = time.time()
        if (self.exec_type, self.avatar_type) == (EXECUTIVE, AVATAR):
            team_modules_present()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        psutil.cpu_percent(None)
        if self.owns_cluster:
            n = self.spec.hosts.start
            self.backend = LocalBackend(self.root)
            self.say(f"starting {n} hosts (local cluster in {self.root})")
            names = self.backend.up(n, min(3, n), hostd_args=[*self.spec.hostd_args, *self.record_args(),
                                                              *self.preload_args()])
            self.actions_backend = LocalBackend(self.root)

            def formed() -> Any:
                self.backend.check_started()
                return self.backend.formation(names)

            try:
                f, _ = wait_until(formed, 90.0, what=f"the group to form with {n} members")
            except StartError as e:
                raise MissionRunError(str(e)) from None
            self.members = list(f.members)
            for m in f.members:
                self.lines.append(tr.Line(0.0, f"{m} joined", "runner", "host", host=m))
        else:
            self.actions_backend = self.backend
        self.check_agent_types(queries.registered_types(self.backend))
        if self.sim is None:
            self.say(f"starting haa-sim ({self.spec.arena}, seed {self.spec.seed}, speed {self.speed:g})")
            self.sim = start_sim(self.mission, self.speed, self.out_dir)
            self.owns_sim = True
        with self.sim.client() as c:
            info = c.wait_ready(10.0)
            check_sim_matches(info, self.mission)
            occ, ex, reply = c.grid(self.tally.grid_res)
            self.tally.ideal_map(occ, ex, reply.surface)
            now = c.info().time
        if not self.fresh_sim:  # an haa-sim that was running: the mission starts now, avatars join by SimControl
            self.t0 = now
        self.now = now
        if not self.owns_cluster:  # an operator's cluster may hold an earlier mission's status, map and filters
            n = clear_team_state(self.backend)
            if n:
                self.say(f"cleared {n} DDB keys of an earlier mission ({', '.join(TEAM_PREFIXES)})")
        self.poll_sim()
        self.spawn_executive()

    def team_config(self) -> dict[str, Any]:
        """The TeamConfig part of every top-level agent's config (haa.agents.team): haa-sim, the speed, the
        mission seed and the mission clock's anchor (simulated `sim0` at wall time `wall0`)."""
        assert self.sim is not None
        with self.sim.client() as c:
            w0 = time.time()
            t = c.info().time
            w1 = time.time()
        return {"sim": self.sim.agent_address or self.sim.address,
                "sim_token_file": self.sim.agent_token_file if self.sim.agent_address else self.sim.token_file,
                "speed": self.speed,
                "seed": self.spec.seed, "sim0": t, "wall0": (w0 + w1) / 2}

    def spawn_executive(self) -> None:
        expected = self.tally.expected
        cfg = {"mission": self.spec.model_dump(mode="json"), "expected_cells": expected, **self.team_config()}
        cfg["mission"]["speed"] = self.speed
        cfg["mission"]["arena"] = arena_argument(self.mission)  # an arena file: its absolute path, for the agents
        self.exec_id, self.exec_name = self.spawn(self.exec_type, cfg)
        self.say(f"spawned {self.exec_name} ({self.exec_type}); {expected} reachable cells")

    def spawn(self, type_name: str, config: dict[str, Any]) -> tuple[str, str]:
        """A top-level agent spawned through the first alive host that answers; (id, display name)."""
        try:
            return queries.spawn_agent(self.backend, type_name, config)
        except ClusterError as e:
            raise MissionRunError(str(e)) from None

    def spawn_avatar(self, name: str) -> None:
        a = next(x for x in self.spec.avatars if x.name == name)
        cfg = {"avatar": a.name, "type": a.type, "pose": list(a.pose), **self.team_config()}
        if self.avatar_type == AVATAR:  # the team's avatar agent: SLAM mode (it halts in "delay"), speed
            cfg["slam"] = self.spec.slam
            cfg["cruise"] = self.spec.cruise
            if self.spec.cruise == "physics":
                cfg["map_cell"] = self.spec.map_resolution
        for attempt in range(3):
            try:
                self.avatar_agents[name] = self.spawn(self.avatar_type, cfg)
                self.say(f"spawned {self.avatar_agents[name][1]} ({self.avatar_type}) for {name}")
                return
            except MissionRunError as e:
                if attempt == 2:
                    self.errors.append(str(e))
                    self.line(f"could not spawn the agent of avatar {name}: {e}", "error")
                    return
                time.sleep(1.0)

    # ------------------------------------------------------------------ polling
    def poll_sim(self) -> None:
        """True poses, haa-sim's clock, avatars joining and leaving the arena."""
        assert self.sim is not None
        with self.sim.client(3.0) as c:
            w0 = time.time()
            r = c.poses()
            w1 = time.time()
        self.now = r.time
        self.clock.add((w0 + w1) / 2, r.time)
        names = {a.name for a in self.spec.avatars}
        for a in r.avatars:
            if a.status == "active":
                bumps = self.tally.avatar_pose(r.time, a)
                if bumps:
                    self.line(f"avatar {a.avatar_id} bumped into something ({bumps} so far)", "avatar")
            prev = self.avatar_status.get(a.avatar_id)
            if prev != a.status:
                self.avatar_status[a.avatar_id] = a.status
                if a.status == "active" and prev is None:
                    self.line(f"avatar {a.avatar_id} ({a.type}) joined the arena", "avatar",
                              t=self.mission_time(a.joined))
                elif a.status in ("retired", "crashed"):
                    how = "left the arena (retired)" if a.status == "retired" else "crashed"
                    self.line(f"avatar {a.avatar_id} {how}", "avatar", t=self.mission_time(a.left or r.time))
            if (a.status == "active" and a.avatar_id in names and a.avatar_id not in self.avatar_agents
                    and a.avatar_id not in self.spawning):
                self.spawning.add(a.avatar_id)
                self.pending.append(self.agent_pool.submit(self.spawn_avatar, a.avatar_id))

    def apply_schedules(self) -> None:
        t = self.mission_time()
        if t >= 0.0 and self.chaos is not None and not self.chaos.started:
            self.start_chaos()
        k = due([s[0] for s in self.fault_steps], self.faults_done, t)
        for at, target in self.fault_steps[self.faults_done:k]:
            self.pending.append(self.host_pool.submit(self.kill_agent, at, target))
        self.faults_done = k
        if self.owns_cluster:  # a cluster the operator runs is theirs to change (haactl host ...)
            k = due([s[0] for s in self.host_steps], self.hosts_done, t)
            for at, action, host in self.host_steps[self.hosts_done:k]:
                self.pending.append(self.host_pool.submit(self.host_action, at, action, host))
            self.hosts_done = k
        if not self.sim_schedule:
            k = due([s[0] for s in self.avatar_steps], self.avatars_done, t)
            for _, action, avatar in self.avatar_steps[self.avatars_done:k]:
                self.pending.append(self.agent_pool.submit(self.avatar_action, action, avatar))
            self.avatars_done = k

    def host_action(self, at: float, action: str, host: str) -> None:
        b = self.actions_backend
        try:
            if action == "leave":
                self.line(f"{host} retires (graceful leave)", "host", host)
                how = b.leave(host, timeout=30.0)
                self.line(f"{host} has left ({how})", "host", host)
            elif action == "kill":
                self.line(f"{host} crashes (SIGKILL of its haa-hostd)", "host", host)
                b.kill(host)
            elif action in ("join", "restart"):
                known = {h.name for h in b.hosts()}
                if host in known:
                    # a host that left or was killed comes back under its name with empty state (no known hosts;
                    # its log goes on in the same file)
                    data_dir = Path(b.state["hosts"][host]["data_dir"])
                    (data_dir / "known_hosts.json").unlink(missing_ok=True)
                    self.line(f"{host} {'restarts' if action == 'restart' else 'starts again'} and joins "
                              "(empty state)", "host", host)
                    b.restart(host)
                else:
                    self.line(f"{host} starts and joins", "host", host)
                    b.add(host)
        except Exception as e:
            msg = f"host schedule at {at:g} s ({action} {host}) failed: {e}"
            self.errors.append(msg)
            self.line(msg, "error", host)

    def kill_agent(self, at: float, target: str) -> None:
        """SIGKILL an agent (mission file `agent_faults`): the first live agent of type `target`, or the agent
        with display name `target`, on the host running it (as `haactl agent kill`). An agent being moved or
        recovered is live on no host for a moment, and one may move between the look-up and the kill ("not
        running here"): tried again every 0.2 s for up to FAULT_RETRY_S wall seconds."""
        deadline = time.monotonic() + FAULT_RETRY_S
        while True:
            try:
                _, per_host, _ = queries.cluster_view(self.backend)
                live = sorted(((a, h) for h, agents in per_host.items() for a in agents), key=lambda x: x[0].name)
                hit = next(((a, h) for a, h in live if a.name == target), None) or next(
                    ((a, h) for a, h in live if a.type == target), None)
                if hit is None:
                    raise MissionRunError(f"no live agent {target!r}")
                a, host = hit
                c = queries.host_client(self.backend, host)
                try:
                    reply = c.agent_kill(a.id)
                finally:
                    c.close()
                if not reply.ok:
                    raise MissionRunError(reply.reason)
                self.line(f"{a.name} ({a.type}) killed on {host} (SIGKILL, agent_faults)", "fault", host)
                return
            except Exception as e:
                if time.monotonic() < deadline and not self.stop_flag.is_set():
                    time.sleep(0.2)
                    continue
                msg = f"agent fault at {at:g} s (kill {target}) failed: {e}"
                self.errors.append(msg)
                self.line(msg, "error")
                return

    def start_chaos(self) -> None:
        """The mission's chaos plan, on a thread of its own from mission time 0 until the mission ends (or the
        plan's `duration_s`): its times and `hang_s` are simulated seconds (docs/chaos.md, "Inside a mission")."""
        assert self.chaos is not None
        backend = self.backend
        if self.owns_cluster:
            from haa.cluster.local_backend import LocalBackend

            backend = LocalBackend(self.root)  # a backend object of its own for its thread
        self.chaos.start(backend, self.mission_time, self.speed, self.spec.complete.time_limit_s)

    def avatar_action(self, action: str, avatar: str) -> None:
        assert self.sim is not None
        a = next(x for x in self.spec.avatars if x.name == avatar)
        try:
            with self.sim.client() as c:
                if action == "join":
                    c.join(a.type, a.name, tuple(a.pose))
                else:
                    c.retire(a.name)
        except grpc.RpcError as e:
            msg = f"haa-sim {action} {avatar}: {e.code().name}: {e.details()}"
            self.errors.append(msg)
            self.line(msg, "error")

    def poll_cluster(self, read_map: bool = False) -> None:
        """mission/status, the estimates, the counters; members and agents per host; the machine's CPU."""
        t = self.mission_time()
        samples = self.tally.samples
        if self.owns_cluster:
            with contextlib.suppress(Exception):
                self.backend.reload()
        got = queries.ddb_read(self.backend, keys=[K_STATUS], prefer=self.reader)
        if got is not None:
            self.reader, vals = got
            st = vals.get(K_STATUS)
            if isinstance(st, dict):
                self.status = st
        got = queries.ddb_read(self.backend, prefix=K_EST, prefer=self.reader)
        if got is not None:
            self.tally.estimates({key[len(K_EST):]: est for key, est in got[1].items()})
        got = queries.ddb_read(self.backend, prefix=K_STATS, prefer=self.reader)
        if got is not None:
            self.stats = {k[len(K_STATS):]: v for k, v in got[1].items()}
        if read_map:
            self.read_map()
        if self.detail:
            for prefix, into in ((K_ASSIGN, self.assign), (K_TARGETS, self.targets)):
                got = queries.ddb_read(self.backend, prefix=prefix, prefer=self.reader)
                if got is not None:
                    into.clear()
                    into.update({k[len(prefix):]: v for k, v in got[1].items()})
        members, per_host, rows = queries.cluster_view(self.backend)
        self.rows = rows
        self.per_host = {h: sorted(a.name for a in v) for h, v in per_host.items()}
        if members:
            if self.members:
                for m in members:
                    if m not in self.members:
                        self.line(f"{m} joined", "host", m)
                for m in self.members:
                    if m not in members:
                        self.line(f"{m} removed", "host", m)
            self.members = members
            samples.hosts.append((t, float(len(members))))
        counts = {h: len(v) for h, v in per_host.items()}
        samples.agents.append((t, float(sum(counts.values()))))
        samples.per_host.append((t, counts))
        samples.cpu.append((t, psutil.cpu_percent(None)))
        ex = rows.get(self.exec_id)
        if ex is not None and ex.status == "failed":
            self.exec_failed = f"{self.exec_name} ({self.exec_type}) failed: {ex.fail_reason}"
        if isinstance(self.status, dict) and isinstance(self.status.get("explored"), int | float):
            samples.explored.append((t, float(self.status["explored"])))

    def read_map(self) -> None:
        got = queries.ddb_read(self.backend, keys=[K_MAP], prefer=self.reader, timeout=10.0)
        if got is None or not isinstance(got[1].get(K_MAP), bytes | bytearray):
            return
        why = self.tally.score_map(bytes(got[1][K_MAP]))
        if why:
            self.errors.append(f"slam/map: {why}")

    def read_events(self) -> list[Any]:
        """The team's transcript entries (`mission/events`, a log: its items; [] if none can be read)."""
        got = queries.ddb_read(self.backend, keys=[K_EVENTS], prefer=self.reader)
        events = got[1].get(K_EVENTS) if got is not None else None
        return list(events["items"]) if isinstance(events, dict) else []

    def finished(self) -> tuple[bool, str] | None:
        if self.stop_flag.is_set():
            return False, "stopped by the operator"
        if self.exec_failed:
            return False, self.exec_failed
        out = status_outcome(self.status)
        if out is not None:
            return out
        limit = self.spec.complete.time_limit_s
        if time_limit_reached(self.mission_time(), limit):
            return False, f"time limit ({limit:g} s simulated)"
        if self.owns_cluster and not queries.alive_hosts(self.backend):
            return False, "every host is gone"
        return None

    def report(self, note: str = "") -> None:
        if self.progress is None:
            return
        st = self.status if isinstance(self.status, dict) else {}
        explored = st.get("explored") if isinstance(st.get("explored"), int | float) else None
        samples = self.tally.samples
        agents = int(samples.agents[-1][1]) if samples.agents else 0
        self.progress(ProgressInfo(self.mission_time(), self.spec.complete.time_limit_s, explored,
                                   self.spec.complete.explored, str(st.get("state", "starting")),
                                   len(self.members), agents, note))

    def loop(self) -> tuple[bool, str]:
        next_poll = next_map = 0.0
        while True:
            tick = time.monotonic()
            try:
                self.poll_sim()
            except grpc.RpcError as e:
                if self.sim is not None and not self.sim.alive():
                    return False, "haa-sim is gone"
                self.say(f"haa-sim: {e.code().name}")
            self.apply_schedules()
            if tick >= next_poll:
                read_map = tick >= next_map
                self.poll_cluster(read_map)
                next_poll = tick + POLL_PERIOD
                if read_map:
                    next_map = tick + MAP_PERIOD
                self.report()
                if self.on_poll is not None:
                    self.on_poll(self)
                out = self.finished()
                if out is not None:
                    return out
            self.stop_flag.wait(max(0.0, POSE_PERIOD - (time.monotonic() - tick)))

    # ------------------------------------------------------------------ results
    def host_records(self) -> list[dict[str, Any]]:
        names = [h.name for h in self.backend.hosts()]
        recs = []
        for host, raw in self.backend.log_records(names, follow=False):
            with contextlib.suppress(ValueError):
                r = json.loads(raw)
                if isinstance(r, dict):
                    r.setdefault("host", host)
                    recs.append(r)
        return recs

    def transcript(self, records: list[dict[str, Any]] | None = None, events: list[Any] | None = None,
                   ) -> tuple[list[tr.Line], list[dict[str, Any]]]:
        """The merged transcript and the agent timeline events it was made from (transcript.mission_transcript;
        the hosts' agent events of an operator's cluster from this run's start on)."""
        since = self.wall_start - 1.0 if self.owns_cluster is False and self.wall_start else None
        return tr.mission_transcript(self.lines, events or [], self.host_records() if records is None else records,
                                     self.clock, self.t0, self.status, since)

    def collect(self, completed: bool, reason: str) -> dict[str, Any]:
        """Final reads, metrics, PNGs, transcript and the results dict (also written as results.json)."""
        with contextlib.suppress(Exception):
            self.poll_cluster(read_map=True)
        lines, agent_events = self.transcript(events=self.read_events())
        st = self.status if isinstance(self.status, dict) else {}
        results = self.tally.results(
            completed, reason, status=st, start_t=as_float(st.get("started_t"), self.t0) - self.t0,
            end_t=self.mission_time(), now=self.now, speed=self.speed, stats=self.stats, agent_events=agent_events,
            ddb_size=queries.ddb_bytes(self.backend), truth_calls=self.truth_calls(),
            landmarks=self.landmark_scores(), chaos=self.chaos.summary() if self.chaos else None,
            errors=self.errors, wall_start=self.wall_start)
        if self.spec.scenario == "forage":  # haa.mission.forage: counts, haa-sim's view, SupervisorForage lives
            more, retired = forage.collect(self.mission, self.backend, self.reader, self.sim, agent_events,
                                           self.clock, self.t0)
            results.update(more)
            lines = tr.merge(lines, retired)
        self.tally.write(self.out_dir, results, lines, chaos=self.chaos.to_json() if self.chaos else None,
                         clock=self.clock, members=self.members, runner_lines=self.lines)
        return results

    def landmark_scores(self) -> tuple[float | None, float | None]:
        """The team's landmark estimates `slam/landmarks` against haa-sim's landmarks (results.landmark_scores);
        (None, None) when there are none."""
        got = queries.ddb_read(self.backend, keys=[K_LANDMARKS], prefer=self.reader, timeout=10.0)
        est = got[1].get(K_LANDMARKS) if got is not None else None
        if not isinstance(est, dict) or not est or self.sim is None:
            return None, None
        try:
            with self.sim.client() as c:
                truth = {lm.id: (lm.position.x, lm.position.y) for lm in c.landmarks().landmarks}
        except grpc.RpcError:
            return None, None
        return landmark_scores(est, truth)

    def truth_calls(self) -> dict[str, int] | None:
        """haa-sim's ground-truth and Detect calls per "<caller>/<method>", the runner's own left out: the
        agents must have made none (issue 15). None if haa-sim does not say."""
        if self.sim is None:
            return None
        try:
            with self.sim.client() as c:
                calls = dict(getattr(c.info(), "truth_calls", {}) or {})
        except grpc.RpcError:
            return None
        return {k: int(v) for k, v in sorted(calls.items()) if not k.startswith(RUNNER_CALLER + "/")}

    # ------------------------------------------------------------------ teardown
    def teardown(self) -> None:
        """Take down what this run started (the cluster and haa-sim if they are ours, else the mission's
        agents). Never raises."""
        self.stop_flag.set()
        if self.chaos is not None:
            self.chaos.stop(wait=0)
        for f in self.pending:
            f.cancel()
        self.host_pool.shutdown(wait=False, cancel_futures=True)
        self.agent_pool.shutdown(wait=False, cancel_futures=True)
        if not self.owns_cluster and self.backend is not None:
            with contextlib.suppress(Exception):
                queries.remove_agents(self.backend, [self.exec_id, *(i for i, _ in self.avatar_agents.values())])
        if self.owns_sim and self.sim is not None:
            with contextlib.suppress(Exception):
                self.sim.stop()
        if self.owns_cluster and self.backend is not None:
            with contextlib.suppress(Exception):
                self.backend.down(grace=2.0)
            with contextlib.suppress(Exception):
                if self.actions_backend is not None:
                    for p in self.actions_backend._procs.values():
                        with contextlib.suppress(subprocess.TimeoutExpired):
                            p.wait(2)
        self.host_pool.shutdown(wait=True)
        self.agent_pool.shutdown(wait=True)

    # ------------------------------------------------------------------ AgentPlayback recording
    def preload_args(self) -> list[str]:
        """The thesis' team is imported when each host starts, not at the first spawn of a type during the mission
        (an import of the SLAM and vision stack would cost the mission simulated seconds)."""
        if (self.exec_type, self.avatar_type) != (EXECUTIVE, AVATAR) or any(
                a.startswith("--preload-agents") for a in self.spec.hostd_args):
            return []
        return ["--preload-agents", ",".join(registry.types_of("haa.agents"))]

    def record_args(self) -> list[str]:
        """haa-hostd's `--record-dir` for our hosts (the ones restarted later too): their agent processes
        record (haa.sdk.recorder)."""
        if self.record_dir is None:
            return []
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.say(f"recording every agent's inputs into {self.record_dir} (haactl record ls / haactl replay)")
        return ["--record-dir", str(self.record_dir)]

    def run(self, json_out: Path | None = None) -> dict[str, Any]:
        try:
            self.setup()
            completed, reason = self.loop()
            if self.chaos is not None:
                self.chaos.stop()  # pauses it holds are ended before the results are read
            self.outcome = (completed, reason)
            self.say(f"mission {'complete' if completed else 'not complete'}: {reason}; collecting results")
            results = self.collect(completed, reason)
        finally:
            self.teardown()
        if self._tmp is None and self.owns_cluster and self.backend is not None:  # -o DIR: the hosts' stats
            with contextlib.suppress(ExtensionMissing):  # bundles beside the results (haactl report DIR)
                extension("bundles")(self.backend, self.out_dir)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(results, indent=2, default=str) + "\n")
        return results


def run_mission(
    mission: Mission,
    speed: float | None = None,
    out_dir: Path | None = None,
    json_out: Path | None = None,
    progress: Callable[[ProgressInfo], None] | None = None,
    root: Path | None = None,
    log: Callable[[str], None] | None = None,
    agent_types: tuple[str, str] = (EXECUTIVE, AVATAR),
    record: Path | None = None,
) -> dict[str, Any]:
    """Run `mission` on its own local cluster and haa-sim (module docstring); the results dict. `record`: a
    folder for the AgentPlayback recording (else the mission file's `record` key decides)."""
    return MissionRun(mission, speed, out_dir, root, progress, log=log, agent_types=agent_types,
                      record=record).run(json_out)


def record_folder(key: bool | str, out_dir: Path, override: Path | None) -> Path | None:
    """Where a mission records (docs/playback.md): `override` (haactl --record), else the mission file's
    `record` key — true: `<out>/recording`, a folder: relative to the output folder; None = no recording."""
    if override is not None:
        return Path(override).absolute()
    if key is True:
        return out_dir / "recording"
    if isinstance(key, str) and key:
        return (out_dir / Path(key).expanduser()).absolute()
    return None


if __name__ == "__main__":  # the conductor's former command line; it is haa.mission.attached's now (same process)
    os.execv(sys.executable, [sys.executable, "-m", "haa.mission.attached", *sys.argv[1:]])
