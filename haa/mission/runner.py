"""The mission runner (issue 15 §3): the thesis' RemoteStart and operator (§6.1.4) for one mission.

    results = run_mission(load_mission("missions/quick.yaml"), speed=4, out_dir=Path("out"))

`run_mission` brings up its own local cluster (h1..hN, real haa-hostd processes: haa.cluster.local_backend) and
haa-sim (the mission's arena and seed, `--speed`, the avatar joins and retirements as `--schedule`), tells
ExecutiveMission what the operator knows of the arena (the number of reachable cells at `map_resolution`, from
haa-sim's explorable mask — never poses), spawns the top-level agents of docs/team.md (`executive_mission`, and
one `avatar_simulation` per avatar as it joins the arena), replays the host schedule at its simulated times
(leave = graceful retirement, kill = SIGKILL, join = a new haa-hostd, restart = haa-hostd under the killed
name with empty state), polls `mission/status` and the metrics until the mission is complete or
`complete.time_limit_s` (simulated) has passed, collects the results (haa.mission.metrics), writes the map and
allocation PNGs, the transcript (haa.mission.transcript) and the results JSON, and takes everything down — also
on Ctrl-C and on errors: every process it started is gone when it returns.

`MissionRun` is the same machinery in steps (`setup`, `poll`, `collect`, `teardown`); `haactl mission start`
runs it *attached* to a cluster the operator runs (`conduct`, a detached process of its own that `haactl mission
stop` ends): it leaves the cluster alone, and stops the mission's agents and the haa-sim it started.

Simulated time. Every schedule counts from haa-sim's t = 0 (its clock starts when it starts, after the host
group has formed); the avatar schedule runs inside haa-sim, the host schedule here, on haa-sim's clock as
polled. Mission duration is ExecutiveMission's `finished_t - started_t` (`mission/status`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import platform
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import psutil

from haa.cluster import procs
from haa.mission import metrics as mm
from haa.mission import transcript as tr
from haa.mission.extensions import ExtensionMissing, extension
from haa.mission.schema import Mission, resolve
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
#: how the runner names itself to haa-sim (its ground-truth calls are counted apart from the agents')
RUNNER_CALLER = "mission-runner"
#: how long an agent fault keeps trying to find its agent live (wall seconds; `MissionRun.kill_agent`)
FAULT_RETRY_S = 5.0
#: poll periods, wall seconds
POSE_PERIOD = 0.1
POLL_PERIOD = 1.0
MAP_PERIOD = 5.0
#: the runner stops this many simulated seconds after the time limit if ExecutiveMission has not
TIME_LIMIT_GRACE = 2.0
#: results keys that must be there (issue 15 §3)
REQUIRED_KEYS = (
    "completed", "reason", "duration_s", "wall_s", "coverage", "accuracy", "position_error_m", "hosts_avg",
    "agents_avg", "readings_generated", "readings_processed", "transfers", "recoveries", "agent_failures",
)


class MissionRunError(Exception):
    """The mission could not be run (one line for the operator)."""


# ---------------------------------------------------------------------------------------------- pure helpers


def due(times: Sequence[float], done: int, now: float) -> int:
    """Entries of a time-ordered schedule are applied one after the other: given `done` applied so far, how
    many are due at `now` in total (entries at exactly `now` are due)."""
    k = done
    while k < len(times) and times[k] <= now:
        k += 1
    return k


def host_plan(mission: Mission) -> list[tuple[float, str, str]]:
    """The host schedule as (at_s, action, host), time ordered (equal times keep file order)."""
    return [(e.at_s, e.action, e.host) for e in mission.spec.hosts.events()]


#: hosts a group needs for one of them to crash and the rest to go on (more than half must stay: below)
MIN_GROUP_FOR_KILL = 3


def host_kill_problems(mission: Mission) -> list[str]:
    """The `kill` entries of the host schedule that the host group cannot survive, one line each.

    A host crash is survived only while more than half of the group stays alive: OAC (Alg. 2) decides a
    transaction only while fewer than half of its participants have failed, and during a mission there is
    always one in flight (the team writes the DDB all the time). A group of two that loses a member blocks
    for good — no removal, no recovery of the dead host's agents, no commit, and a restarted host cannot join
    (docs/membership.md, "Faults within the assumptions" and "Open problems"). So a kill needs at least
    MIN_GROUP_FOR_KILL hosts in the group at its time (the group as the schedule leaves it: earlier kills
    removed, joins and restarts in). Leaves are graceful and always fine."""
    live = set(mission.spec.hosts.initial)
    out = []
    for e in mission.spec.hosts.events():
        if e.action == "kill" and len(live) < MIN_GROUP_FOR_KILL:
            out.append(f"hosts.schedule: kill {e.host} at {e.at_s:g} s leaves {len(live) - 1} of {len(live)} hosts "
                       "running: the group needs more than half of its members alive to remove a crashed host "
                       "(with two hosts it blocks for good: docs/membership.md, Open problems); start at least "
                       f"{MIN_GROUP_FOR_KILL} hosts or let it leave")
        if e.action in ("join", "restart"):
            live.add(e.host)
        else:
            live.discard(e.host)
    return out


def avatar_plan(mission: Mission) -> list[tuple[float, str, str]]:
    """The avatar schedule as (at_s, "join" | "retire", avatar), time ordered (SimControl Join/Retire at these
    mission times when the runner attaches to an haa-sim it did not start)."""
    out = []
    for a in mission.spec.avatars:
        out.append((a.join_at_s or 0.0, "join", a.name))
        if a.leave_at_s is not None:
            out.append((a.leave_at_s, "retire", a.name))
    return sorted(out, key=lambda e: e[0])


def schedule_yaml(mission: Mission) -> str:
    """haa-sim `--schedule` file text for the mission's avatars (`Mission.sim_schedule()`)."""
    import yaml

    entries = [e.model_dump(mode="json", exclude_none=True) for e in mission.sim_schedule()]
    return yaml.safe_dump({"schedule": entries}, sort_keys=False)


def time_limit_reached(mission_t: float, limit: float, grace: float = TIME_LIMIT_GRACE) -> bool:
    return mission_t >= limit + grace


def status_outcome(status: dict[str, Any] | None) -> tuple[bool, str] | None:
    """(completed, reason) once `mission/status` says the mission ended, else None."""
    if not isinstance(status, dict):
        return None
    state = status.get("state")
    if state == "complete":
        return True, str(status.get("reason") or "complete")
    if state == "stopped":
        return False, str(status.get("reason") or "stopped")
    return None


def mission_duration(status: dict[str, Any] | None, now: float) -> float:
    """finished_t - started_t of `mission/status` (`now` while it has not finished; `now` from 0 without a
    status)."""
    if not isinstance(status, dict):
        return max(0.0, now)
    start = _num(status.get("started_t"), 0.0)
    end = _num(status.get("finished_t"), now)
    return max(0.0, end - start)


def _num(v: Any, default: float) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f if math.isfinite(f) else default


def decode_value(type_name: str, value: bytes) -> Any:
    """A DDB record's canonical value -> Python: json -> parsed, counter -> int, log/list -> [bytes], blob ->
    bytes."""
    if type_name == "json":
        return json.loads(value)
    if type_name == "counter":
        return int.from_bytes(value, "big", signed=True)
    if type_name == "log":
        from haa.pb import ddb_pb2

        cls = getattr(ddb_pb2, "DdbLogValue", None)
        if cls is None:
            return []
        return list(cls.FromString(value).items)
    if type_name == "list":
        from haa.pb import ddb_pb2

        return list(ddb_pb2.DdbListValue.FromString(value).items)
    return bytes(value)


def provenance(mission: Mission) -> dict[str, Any]:
    """Where the numbers come from: commit, mission file hash, seed, machine."""
    repo = Path(__file__).resolve().parents[2]
    commit = dirty = None
    try:
        commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip() or None
        dirty = bool(subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                                    capture_output=True, text=True, timeout=5, check=True).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        pass
    if mission.path is not None and Path(mission.path).is_file():
        digest = hashlib.sha256(Path(mission.path).read_bytes()).hexdigest()
    else:
        digest = hashlib.sha256(mission.spec.model_dump_json().encode()).hexdigest()
    return {
        "commit": commit,
        "dirty": dirty,
        "mission_file": str(mission.path) if mission.path else None,
        "mission_sha256": digest,
        "seed": mission.spec.seed,
        "machine": {
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
    }


# ---------------------------------------------------------------------------------------------- haa-sim


@dataclass
class SimHandle:
    """An haa-sim this machine can reach: its address, token file, and — if we started it — its process."""

    address: str
    token_file: str = ""
    pid: int | None = None
    create_time: float | None = None
    log: str = ""
    started_here: bool = False
    proc: subprocess.Popen[bytes] | None = field(default=None, repr=False)
    #: where the agents reach it, when not at `address` (compose: sim:7100 and the token in the containers)
    agent_address: str = ""
    agent_token_file: str = ""
    #: its Prometheus endpoint (docs/metrics.md), "" when it serves none
    metrics_url: str = ""

    def client(self, timeout: float = 5.0) -> Any:
        from haa import files
        from haa.sim.service import SimClient

        token = files.read_token(self.token_file) if self.token_file else None
        return SimClient(self.address, token=token, timeout=timeout, caller=RUNNER_CALLER)

    def alive(self) -> bool:
        if self.proc is not None:
            return self.proc.poll() is None
        if not self.pid:
            return False
        try:
            p = psutil.Process(self.pid)
            if self.create_time is not None and abs(p.create_time() - self.create_time) > 0.5:
                return False
            return p.status() != psutil.STATUS_ZOMBIE
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            return False

    def stop(self, grace: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after `grace` s (only a process we started; reaps it)."""
        if not self.started_here or not self.pid:
            return
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
            deadline = time.monotonic() + grace
            while self.alive() and time.monotonic() < deadline:
                time.sleep(0.05)
            if self.alive():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
        if self.proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(5)
        else:
            with contextlib.suppress(ChildProcessError, OSError):
                os.waitpid(self.pid, os.WNOHANG)

    def to_json(self) -> dict[str, Any]:
        return {"address": self.address, "token_file": self.token_file, "pid": self.pid,
                "create_time": self.create_time, "log": self.log, "started_here": self.started_here,
                "agent_address": self.agent_address, "agent_token_file": self.agent_token_file,
                "metrics_url": self.metrics_url}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SimHandle:
        return cls(str(d["address"]), str(d.get("token_file") or ""), d.get("pid"), d.get("create_time"),
                   str(d.get("log") or ""), bool(d.get("started_here")),
                   agent_address=str(d.get("agent_address") or ""),
                   agent_token_file=str(d.get("agent_token_file") or ""),
                   metrics_url=str(d.get("metrics_url") or ""))


def sim_command() -> list[str]:
    script = Path(sys.executable).parent / "haa-sim"
    return [str(script)] if script.exists() else [sys.executable, "-m", "haa.sim.service"]


def arena_argument(mission: Mission) -> str:
    from haa.sim.arena import BUILTIN

    a = mission.spec.arena
    if a in BUILTIN:
        return a
    base = Path(mission.path).parent if mission.path is not None else None
    return str(resolve(base, a).absolute())


def start_sim(mission: Mission, speed: float, workdir: Path, schedule: bool = True, detached: bool = False,
              timeout: float = 30.0) -> SimHandle:
    """Start haa-sim for the mission (arena, seed, speed; the avatar schedule unless `schedule` is False) on a
    free loopback port with a fresh token, its Prometheus /metrics on another (`SimHandle.metrics_url`); wait
    until it listens. `detached`: it outlives this process."""
    workdir.mkdir(parents=True, exist_ok=True)
    token_file = workdir / "sim.token"
    token_file.write_text(secrets.token_hex(24) + "\n")
    token_file.chmod(0o600)
    cmd = [*sim_command(), "--arena", arena_argument(mission), "--listen", "127.0.0.1:0",
           "--seed", str(mission.spec.seed), "--speed", repr(float(speed)), "--token-file", str(token_file),
           "--drift", mission.spec.drift, "--metrics-port", str(procs.free_port())]
    if schedule:
        sched = workdir / "sim-schedule.yaml"
        sched.write_text(schedule_yaml(mission))
        cmd += ["--schedule", str(sched)]
    log_path = workdir / "sim.log"
    with open(log_path, "wb") as err:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True)
    try:
        ct = psutil.Process(p.pid).create_time()
    except psutil.NoSuchProcess:
        ct = None
    h = SimHandle("", str(token_file), p.pid, ct, str(log_path), True, None if detached else p)
    deadline = time.monotonic() + timeout
    while True:
        for line in log_path.read_text(errors="replace").splitlines():
            with contextlib.suppress(ValueError):
                rec = json.loads(line)
                if isinstance(rec, dict) and rec.get("event") == "listening":
                    h.address = str(rec["address"])
                    h.metrics_url = str(rec.get("metrics") or "")
                    return h
        code = p.poll()
        if code is not None:
            lines = [ln for ln in log_path.read_text(errors="replace").splitlines() if ln.strip()]
            raise MissionRunError(f"haa-sim exited at start with code {code}: {lines[-1] if lines else '(no output)'}")
        if time.monotonic() > deadline:
            h.stop(1.0)
            raise MissionRunError(f"haa-sim did not start listening within {timeout:.0f} s (log: {log_path})")
        time.sleep(0.05)


def check_sim_matches(info: Any, mission: Mission) -> None:
    """Refuse an haa-sim that runs another arena or seed than the mission's (one clear line)."""
    from haa.sim.arena import load_arena

    want_seed = mission.spec.seed
    want_arena = mission.arena.name if mission.arena is not None else load_arena(arena_argument(mission)).name
    problems = []
    if info.arena != want_arena:
        problems.append(f"arena {info.arena!r} (the mission wants {want_arena!r})")
    if int(info.seed) != int(want_seed):
        problems.append(f"seed {info.seed} (the mission wants {want_seed})")
    if problems:
        raise MissionRunError("the running haa-sim has " + " and ".join(problems) +
                              ": stop it first (haactl mission stop) or change the mission file")


# ---------------------------------------------------------------------------------------------- cluster access


def _client(backend: Any, name: str, timeout: float = 3.0) -> Any:
    return backend.connect(backend.host(name), timeout)


def alive_hosts(backend: Any) -> list[str]:
    from haa.cluster.backend import ALIVE

    return [h.name for h in backend.hosts() if h.state == ALIVE]


def ddb_read(backend: Any, keys: Sequence[str] = (), prefix: str = "", prefer: str | None = None,
             timeout: float = 3.0) -> tuple[str, dict[str, Any]] | None:
    """{key: decoded value} from the replica of one alive host (`prefer` first); None if no host answers."""
    names = alive_hosts(backend)
    if prefer in names:
        names.remove(prefer)
        names.insert(0, prefer)
    for n in names:
        c = _client(backend, n, timeout)
        try:
            reply = c.ddb_get(keys=list(keys), prefix=prefix)
        except grpc.RpcError:
            continue
        finally:
            c.close()
        out: dict[str, Any] = {}
        for o in reply.objects:
            with contextlib.suppress(Exception):
                out[o.key] = decode_value(o.type, o.value)
        return n, out
    return None


def ddb_bytes(backend: Any) -> int | None:
    """Total size of the DDB's values (one replica), for "DDB Size [MB]"."""
    names = alive_hosts(backend)
    for n in names:
        c = _client(backend, n, 30.0)
        try:
            reply = c.ddb_get(prefix="")
        except grpc.RpcError:
            continue
        finally:
            c.close()
        return sum(len(o.key) + len(o.value) for o in reply.objects)
    return None


def cluster_view(backend: Any) -> tuple[list[str], dict[str, list[Any]], dict[str, Any]]:
    """(members of the agreed group, {host: its active agents (AgentInfo)}, {agent id: AgentInfo} — the most
    advanced table row of every agent)."""
    from haa.cluster.backend import agreed_group
    from haa.pb import control_pb2 as cpb

    names = alive_hosts(backend)

    def one(n: str) -> tuple[str, Any, Any]:
        c = _client(backend, n)
        try:
            st = c.status()
        except grpc.RpcError:
            st = None
        try:
            al = c.agent_list() if st is not None else None
        except grpc.RpcError:
            al = None
        finally:
            c.close()
        return n, st, al

    if not names:
        return [], {}, {}
    with ThreadPoolExecutor(max_workers=min(16, len(names))) as pool:
        got = list(pool.map(one, names))
    statuses = {n: st for n, st, _ in got if isinstance(st, cpb.StatusReply)}
    members, _, _ = agreed_group(statuses)
    per_host: dict[str, list[Any]] = {}
    rows: dict[str, Any] = {}
    for n, _, al in got:
        if al is None:
            continue
        for a in al.agents:
            prev = rows.get(a.id)
            if prev is None or a.epoch > prev.epoch:
                rows[a.id] = a
            if a.local_phase == "active":
                per_host.setdefault(n, []).append(a)
    return members, per_host, rows


def spawn_agent(backend: Any, type_name: str, config: dict[str, Any], timeout: float = 15.0) -> tuple[str, str]:
    """Spawn a top-level agent through the first alive host that accepts; (id, display name)."""
    payload = json.dumps(config).encode()
    last = "no host is alive"
    for n in alive_hosts(backend):
        c = _client(backend, n, timeout)
        try:
            r = c.agent_spawn(type_name, payload, timeout=timeout)
        except grpc.RpcError as e:
            last = f"{n}: {e.code().name}"
            continue
        finally:
            c.close()
        if r.ok:
            return r.id, r.name
        raise MissionRunError(f"spawn {type_name}: {r.reason}")
    raise MissionRunError(f"spawn {type_name}: {last}")


#: DDB prefixes of the robot team's state (docs/team.md "DDB layout")
TEAM_PREFIXES = ("mission/", "avatars/", "bids/", "assign/", "slam/", "targets/")


def clear_team_state(backend: Any, timeout: float = 15.0) -> int:
    """Delete every key of TEAM_PREFIXES from the cluster's DDB (a committed write), so that a mission started
    on a cluster that ran another one has a status, map and filters of its own (`haactl mission start` twice:
    the second must not read the first's `mission/status = complete`). The number of keys deleted."""
    from haa.core.ddb import ops as ddbmod

    names = alive_hosts(backend)
    if not names:
        raise MissionRunError("no host is alive: cannot clear the previous mission's DDB keys")
    host = names[0]
    c = _client(backend, host, timeout)
    try:
        keys = sorted(o.key for p in TEAM_PREFIXES for o in c.ddb_get(prefix=p, keys_only=True).objects)
    except grpc.RpcError as e:
        raise MissionRunError(f"reading the previous mission's DDB keys on {host}: {e.code().name}") from None
    finally:
        c.close()
    for i in range(0, len(keys), 200):
        ops = [ddbmod.delete(k) for k in keys[i:i + 200]]
        c = _client(backend, host, timeout)
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


def registered_types(backend: Any) -> list[str] | None:
    for n in alive_hosts(backend):
        c = _client(backend, n)
        try:
            return list(c.agent_list().agent_types)
        except grpc.RpcError:
            continue
        finally:
            c.close()
    return None


def remove_agents(backend: Any, top: Iterable[str], timeout: float = 15.0) -> list[str]:
    """Remove the agents `top` (ids) and all their descendants, deepest first (AgentRemove leaves children
    alone); returns the display names removed."""
    _, _, rows = cluster_view(backend)
    children: dict[str, list[str]] = {}
    for a in rows.values():
        children.setdefault(a.parent, []).append(a.id)
    order: list[str] = []

    def walk(i: str, seen: set[str]) -> None:
        for ch in children.get(i, []):
            if ch not in seen:
                seen.add(ch)
                walk(ch, seen)
        order.append(i)

    seen: set[str] = set()
    for t in top:
        if t in rows and t not in seen:
            seen.add(t)
            walk(t, seen)
    removed = []
    for i in order:
        for n in alive_hosts(backend):
            c = _client(backend, n, timeout)
            try:
                r = c.agent_remove(i, timeout=timeout)
            except grpc.RpcError:
                continue
            finally:
                c.close()
            if r.ok:
                removed.append(rows[i].name)
            break
    return removed


def team_modules_present() -> None:
    """Before starting anything: the modules of the two top-level agent types (docs/team.md) must exist (the
    hosts' registry is checked once the cluster is up)."""
    import importlib.util

    missing = [t for t in (EXECUTIVE, AVATAR) if importlib.util.find_spec(f"haa.agents.{t}") is None]
    if missing:
        raise MissionRunError(f"no agent module {', '.join(f'haa/agents/{t}.py' for t in missing)}: the robot-team "
                              "agents (docs/team.md) are not installed")


# ---------------------------------------------------------------------------------------------- the run


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


@dataclass
class Samples:
    """What polling collected (simulated mission times)."""

    hosts: list[tuple[float, float]] = field(default_factory=list)
    agents: list[tuple[float, float]] = field(default_factory=list)
    cpu: list[tuple[float, float]] = field(default_factory=list)
    per_host: list[tuple[float, dict[str, int]]] = field(default_factory=list)
    explored: list[tuple[float, float]] = field(default_factory=list)


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
        self.histories: dict[str, mm.PoseHistory] = {}
        #: avatar -> (t, distance between its odometry (dead reckoning) and its true pose), every 0.5 s
        self.uncorrected: dict[str, list[tuple[float, float]]] = {}
        #: avatar -> contacts begun with walls, obstacles or avatars (haa-sim "bump"s: pushes odometry misses)
        self.bumps: dict[str, int] = {}
        self.loc = mm.LocalizationLog()
        self.clock = tr.ClockMap(self.speed)
        self.samples = Samples()
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
        self.occ: np.ndarray | None = None  # the ideal map (surface rule)
        self.occ_half: np.ndarray | None = None  # cells at least half inside a solid
        self.map_scores_half: mm.MapScores | None = None
        self.explorable: np.ndarray | None = None
        self.grid_res = self.spec.map_resolution
        self.expected = 0
        self.map_scores: mm.MapScores | None = None
        self.map_prob: np.ndarray | None = None
        self.reader = ""  # the host we read the DDB from last
        self.outcome: tuple[bool, str] | None = None
        self.exec_failed = ""
        self.files: dict[str, str] = {}
        #: the chaos plan the mission file names (`chaos: FILE`, checked by the schema), run by `start_chaos`
        self.chaos_plan: Any = None
        self.chaos: Any = None  # the lab's chaos extension (haa.mission.extensions), loaded for a plan only
        if self.spec.chaos is not None:
            self.chaos = extension("chaos")
            self.chaos_plan = self.chaos.load(resolve(mission.path.parent if mission.path else None, self.spec.chaos))
        #: AgentPlayback (docs/playback.md): every agent of our own cluster records into this folder
        self.record_dir = record_folder(self.spec.record, self.out_dir, record)
        self.chaos_thread: threading.Thread | None = None
        self.chaos_done = threading.Event()
        self.injector: Any = None

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
        self.check_agent_types(registered_types(self.backend))
        if self.sim is None:
            self.say(f"starting haa-sim ({self.spec.arena}, seed {self.spec.seed}, speed {self.speed:g})")
            self.sim = start_sim(self.mission, self.speed, self.out_dir)
            self.owns_sim = True
        with self.sim.client() as c:
            info = c.wait_ready(10.0)
            check_sim_matches(info, self.mission)
            occ, ex, reply = c.grid(self.grid_res)
            # the ideal map of eq. 7.1-1/7.1-2: every cell a surface passes through (docs/team.md, "Map
            # metrics"); the half-cell rule's map is scored too (`accuracy_half_cells`)
            self.occ_half, self.explorable = occ.copy(), ex.copy()
            surface = np.frombuffer(reply.surface, dtype=np.uint8)
            self.occ = surface.reshape(occ.shape).copy() if surface.size == occ.size else occ.copy()
            self.expected = mm.expected_cells(ex)
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
        cfg = {"mission": self.spec.model_dump(mode="json"), "expected_cells": self.expected, **self.team_config()}
        cfg["mission"]["speed"] = self.speed
        self.exec_id, self.exec_name = spawn_agent(self.backend, self.exec_type, cfg)
        self.say(f"spawned {self.exec_name} ({self.exec_type}); {self.expected} reachable cells")

    def spawn_avatar(self, name: str) -> None:
        a = next(x for x in self.spec.avatars if x.name == name)
        cfg = {"avatar": a.name, "type": a.type, "pose": list(a.pose), **self.team_config()}
        if self.avatar_type == AVATAR:  # the team's avatar agent: SLAM mode (it halts in "delay"), speed
            cfg["slam"] = self.spec.slam
            cfg["cruise"] = self.spec.cruise
        for attempt in range(3):
            try:
                self.avatar_agents[name] = spawn_agent(self.backend, self.avatar_type, cfg)
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
                self.histories.setdefault(a.avatar_id, mm.PoseHistory()).add(r.time, a.pose.x, a.pose.y,
                                                                              a.pose.theta)
                if a.bumps > self.bumps.get(a.avatar_id, 0):
                    self.line(f"avatar {a.avatar_id} bumped into something ({a.bumps} so far)", "avatar")
                    self.bumps[a.avatar_id] = a.bumps
                unc = self.uncorrected.setdefault(a.avatar_id, [])
                # haa-sim's odometry starts at the start pose: the same frame as the truth
                if a.HasField("odometry") and (not unc or r.time >= unc[-1][0] + 0.5):
                    unc.append((round(r.time, 3), round(math.hypot(a.odometry.x - a.pose.x,
                                                                   a.odometry.y - a.pose.y), 4)))
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
        if t >= 0.0:
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
                _, per_host, _ = cluster_view(self.backend)
                live = sorted(((a, h) for h, agents in per_host.items() for a in agents), key=lambda x: x[0].name)
                hit = next(((a, h) for a, h in live if a.name == target), None) or next(
                    ((a, h) for a, h in live if a.type == target), None)
                if hit is None:
                    raise MissionRunError(f"no live agent {target!r}")
                a, host = hit
                c = _client(self.backend, host)
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
        if self.chaos_plan is None or self.chaos_thread is not None:
            return
        backend = self.backend
        if self.owns_cluster:
            from haa.cluster.local_backend import LocalBackend

            backend = LocalBackend(self.root)  # a backend object of its own for its thread
        plan = self.chaos_plan
        self.injector = self.chaos.injector(plan, backend, on_fault=self.chaos_line, clock=self.mission_time,
                                            sleep=lambda s: self.chaos_done.wait(max(0.0, s) / self.speed),
                                            duration=plan.duration_s or self.spec.complete.time_limit_s,
                                            wall_per_s=1.0 / self.speed)
        self.line(f"chaos plan {plan.name}: {len(plan.faults)} fault lines (seed {plan.seed})", "fault")

        def chaos() -> None:
            try:
                self.injector.run(stop=self.chaos_done.is_set, t0=0.0)
            except Exception as e:  # the mission goes on without its chaos; said in the results
                msg = f"chaos plan {plan.name} stopped: {e}"
                self.errors.append(msg)
                self.line(msg, "error")

        self.chaos_thread = threading.Thread(target=chaos, name="mission-chaos", daemon=True)
        self.chaos_thread.start()

    def stop_chaos(self) -> None:
        """End the chaos (pauses it holds are ended) before the results are read."""
        self.chaos_done.set()
        if self.chaos_thread is not None:
            self.chaos_thread.join(30.0)

    def chaos_line(self, rec: Any) -> None:
        """One injected (or skipped) fault on the transcript."""
        what = {"hang": "hangs", "kill": "killed", "pause": "paused", "resume": "resumed",
                "restart": "restarted"}.get(rec.action, rec.action)
        text = (f"{rec.target} {what} by chaos: {rec.detail}" if rec.ok
                else f"chaos {rec.action} {rec.target} not done: {rec.detail}")
        self.line(text, "fault", rec.target if rec.target.startswith("h") and rec.target[1:].isdigit() else "",
                  t=rec.t)

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
        if self.owns_cluster:
            with contextlib.suppress(Exception):
                self.backend.reload()
        got = ddb_read(self.backend, keys=[K_STATUS], prefer=self.reader)
        if got is not None:
            self.reader, vals = got
            st = vals.get(K_STATUS)
            if isinstance(st, dict):
                self.status = st
        got = ddb_read(self.backend, prefix="slam/est/", prefer=self.reader)
        if got is not None:
            for key, est in got[1].items():
                avatar = key[len(K_EST):]
                if isinstance(est, dict) and avatar in self.histories:
                    self.loc.add(avatar, est, self.histories[avatar])
        got = ddb_read(self.backend, prefix=K_STATS, prefer=self.reader)
        if got is not None:
            self.stats = {k[len(K_STATS):]: v for k, v in got[1].items()}
        if read_map:
            self.read_map()
        if self.detail:
            for prefix, into in ((K_ASSIGN, self.assign), (K_TARGETS, self.targets)):
                got = ddb_read(self.backend, prefix=prefix, prefer=self.reader)
                if got is not None:
                    into.clear()
                    into.update({k[len(prefix):]: v for k, v in got[1].items()})
        members, per_host, rows = cluster_view(self.backend)
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
            self.samples.hosts.append((t, float(len(members))))
        counts = {h: len(v) for h, v in per_host.items()}
        self.samples.agents.append((t, float(sum(counts.values()))))
        self.samples.per_host.append((t, counts))
        self.samples.cpu.append((t, psutil.cpu_percent(None)))
        ex = rows.get(self.exec_id)
        if ex is not None and ex.status == "failed":
            self.exec_failed = f"{self.exec_name} ({self.exec_type}) failed: {ex.fail_reason}"
        if isinstance(self.status, dict) and isinstance(self.status.get("explored"), int | float):
            self.samples.explored.append((t, float(self.status["explored"])))

    def read_map(self) -> None:
        got = ddb_read(self.backend, keys=[K_MAP], prefer=self.reader, timeout=10.0)
        if got is None or not isinstance(got[1].get(K_MAP), bytes | bytearray):
            return
        assert self.occ is not None and self.explorable is not None
        try:
            spec, prob = mm.decode_published_map(bytes(got[1][K_MAP]))
        except Exception as e:
            self.errors.append(f"slam/map: {e}")
            return
        self.map_prob = mm.align_to_grid(spec, prob, self.occ.shape, self.grid_res)
        self.map_scores = mm.map_scores(self.map_prob, self.occ, self.explorable)
        if self.occ_half is not None:
            self.map_scores_half = mm.map_scores(self.map_prob, self.occ_half, self.explorable)

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
        if self.owns_cluster and not alive_hosts(self.backend):
            return False, "every host is gone"
        return None

    def report(self, note: str = "") -> None:
        if self.progress is None:
            return
        st = self.status if isinstance(self.status, dict) else {}
        explored = st.get("explored") if isinstance(st.get("explored"), int | float) else None
        agents = int(self.samples.agents[-1][1]) if self.samples.agents else 0
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
        """The merged transcript and the agent timeline events it was made from."""
        if records is None:
            records = self.host_records()
        agent_events = tr.host_agent_events(records)
        if self.owns_cluster is False and self.wall_start:
            agent_events = [e for e in agent_events if e["time"] >= self.wall_start - 1.0]
        host_lines = tr.host_agent_lines(agent_events, self.clock, self.t0) if self.clock else []
        team = tr.mission_lines(events or [])
        own = list(self.lines)
        texts = " ".join(ln.text.lower() for ln in team)
        st = self.status if isinstance(self.status, dict) else {}
        if "mission started" not in texts and isinstance(st.get("started_t"), int | float):
            own.append(tr.Line(float(st["started_t"]) - self.t0, "Mission started", "runner", "mission"))
        if "mission finished" not in texts and isinstance(st.get("finished_t"), int | float):
            reason = f": {st['reason']}" if st.get("reason") else ""
            own.append(tr.Line(float(st["finished_t"]) - self.t0, f"Mission finished{reason}", "runner", "mission"))
        return tr.merge(own, team, host_lines), agent_events

    def collect(self, completed: bool, reason: str) -> dict[str, Any]:
        """Final reads, metrics, PNGs, transcript and the results dict (also written as results.json)."""
        with contextlib.suppress(Exception):
            self.poll_cluster(read_map=True)
        events: list[Any] = []
        got = ddb_read(self.backend, keys=[K_EVENTS], prefer=self.reader)
        if got is not None and isinstance(got[1].get(K_EVENTS), list):
            events = got[1][K_EVENTS]
        lines, agent_events = self.transcript(events=events)
        counts = mm.agent_event_counts(agent_events)
        st = self.status if isinstance(self.status, dict) else {}
        end_t = self.mission_time()
        start_t = _num(st.get("started_t"), self.t0) - self.t0
        hosts_avg = mm.time_average(self.samples.hosts, start_t, end_t)
        agents_avg = mm.time_average(self.samples.agents, start_t, end_t)
        cpu = mm.time_average(self.samples.cpu, start_t, end_t)
        size = ddb_bytes(self.backend)
        truth_calls = self.truth_calls()
        lm_err, lm_std = self.landmark_scores()
        sc = self.map_scores
        stats = mm.stats_counters(self.stats)
        results: dict[str, Any] = {
            "mission": self.spec.name,
            "scenario": self.spec.scenario,
            "completed": bool(completed),
            "reason": reason,
            "duration_s": round(mission_duration(st or None, self.now), 3),
            "wall_s": round(time.time() - self.wall_start, 3),
            "speed": self.speed,
            "seed": self.spec.seed,
            "coverage": _r(sc.coverage if sc else None),
            "accuracy": _r(sc.accuracy if sc else None),
            "accuracy_half_cells": _r(self.map_scores_half.accuracy if self.map_scores_half else None),
            "explored": _r(sc.explored if sc else st.get("explored")),
            "explored_reported": st.get("explored"),
            "position_error_m": _r(self.loc.position_error()),
            "rotation_error_rad": _r(self.loc.rotation_error()),
            "bumps": sum(self.bumps.values()),
            "uncorrected_error_m": _r(mm.mean_of_means({a: [e[1] for e in v] for a, v in self.uncorrected.items()})),
            "landmark_error_m": _r(lm_err),
            "landmark_covariance_m": _r(lm_std),
            "hosts_avg": _r(hosts_avg),
            "hosts_avg_thesis": _r(hosts_avg + 1 if hosts_avg is not None else None),
            "agents_avg": _r(agents_avg),
            "cpu_percent": _r(cpu),
            **stats,
            **counts,
            "ddb_mb": _r(size / 1e6 if size is not None else None),
            "sim_truth_calls": truth_calls,
            "chaos": self.chaos_summary(),
            "expected_cells": self.expected,
            "region_cells": sc.region_cells if sc else None,
            "estimates": sum(len(v) for v in self.loc.errors.values()),
            "status": st or None,
            "errors": self.errors,
            "provenance": provenance(self.mission),
            "cpu_count": os.cpu_count(),
        }
        self.write_outputs(results, lines)
        return results

    def chaos_summary(self) -> dict[str, Any] | None:
        """The chaos plan's name and what it did (every record is in chaos.json of the run folder)."""
        if self.injector is None:
            return None
        recs = list(self.injector.injected)
        by: dict[str, int] = {}
        for r in recs:
            if r.ok:
                by[r.action] = by.get(r.action, 0) + 1
        return {"plan": self.chaos_plan.name, "seed": self.chaos_plan.seed, "injected": sum(by.values()),
                "skipped": sum(1 for r in recs if not r.ok), "by_action": by}

    def landmark_scores(self) -> tuple[float | None, float | None]:
        """(mean distance of the team's landmark estimates `slam/landmarks` from the true landmarks, mean of
        their published standard deviations): the thesis' "Landmark Err" and "Landmark Covariance" rows of
        Table 7.1-1, over the landmarks the team has estimated. (None, None) when there are none."""
        got = ddb_read(self.backend, keys=[K_LANDMARKS], prefer=self.reader, timeout=10.0)
        est = got[1].get(K_LANDMARKS) if got is not None else None
        if not isinstance(est, dict) or not est or self.sim is None:
            return None, None
        try:
            with self.sim.client() as c:
                truth = {lm.id: (lm.position.x, lm.position.y) for lm in c.landmarks().landmarks}
        except grpc.RpcError:
            return None, None
        errs, stds = [], []
        for lid, v in est.items():
            try:
                x, y, sd = (float(a) for a in v[:3])
                true = truth[int(lid)]
            except (ValueError, TypeError, KeyError, IndexError):
                continue
            errs.append(math.dist((x, y), true))
            stds.append(sd)
        if not errs:
            return None, None
        return sum(errs) / len(errs), sum(stds) / len(stds)

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

    def write_outputs(self, results: dict[str, Any], lines: list[tr.Line]) -> None:
        out = self.out_dir
        (out / "transcript.txt").write_text("".join(ln.format() + "\n" for ln in lines))
        if self.injector is not None:
            (out / "chaos.json").write_text(json.dumps(
                {"plan": self.chaos_plan.model_dump(mode="json"),
                 "faults": [r.to_json() for r in self.injector.injected]}, indent=1) + "\n")
        with open(out / "transcript.jsonl", "w") as f:
            for ln in lines:
                f.write(json.dumps(ln.to_json()) + "\n")
        self.files = {"transcript": str(out / "transcript.txt")}
        try:
            self.files["map_png"] = str(plot_maps(self, out / "map.png"))
            self.files["timeline_png"] = str(plot_timeline(self, out / "allocation.png"))
        except ImportError as e:  # matplotlib missing
            self.errors.append(f"no PNGs: {e}")
        # the final map beside the ideal one, for offline scoring and plots (a map implies the ideal one)
        if self.map_prob is not None and self.occ is not None and self.explorable is not None:
            np.savez_compressed(out / "map.npz", prob=self.map_prob, ideal=self.occ, explorable=self.explorable,
                                ideal_half_cells=self.occ_half if self.occ_half is not None else self.occ,
                                resolution=self.grid_res)
            self.files["map_npz"] = str(out / "map.npz")
        results["files"] = dict(self.files)
        samples = dataclasses.asdict(self.samples)
        # per avatar over mission time: the SLAM estimate's position error and the odometry's (for plots)
        loc = {a: [[round(t, 3), round(pos, 4)] for t, pos, _rot in v] for a, v in self.loc.errors.items()}
        unc = {a: [list(e) for e in v] for a, v in self.uncorrected.items()}
        truth: dict[str, list[list[float]]] = {}  # true poses, one per 0.25 s of haa-sim time
        for a, h in self.histories.items():
            rows = truth.setdefault(a, [])
            for t, (x, y, th) in zip(h.t, h.poses, strict=True):
                if not rows or t >= rows[-1][0] + 0.25:
                    rows.append([round(t, 3), round(x, 4), round(y, 4), round(th, 4)])
        (out / "samples.json").write_text(json.dumps({"samples": samples, "clock": self.clock.to_json(),
                                                      "position_error": loc, "uncorrected_error": unc,
                                                      "truth": truth}))
        (out / "results.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
        results["files"]["results"] = str(out / "results.json")

    # ------------------------------------------------------------------ teardown
    def teardown(self) -> None:
        """Take down what this run started (the cluster and haa-sim if they are ours, else the mission's
        agents). Never raises."""
        self.stop_flag.set()
        self.chaos_done.set()
        for f in self.pending:
            f.cancel()
        self.host_pool.shutdown(wait=False, cancel_futures=True)
        self.agent_pool.shutdown(wait=False, cancel_futures=True)
        if not self.owns_cluster and self.backend is not None:
            with contextlib.suppress(Exception):
                remove_agents(self.backend, [self.exec_id, *(i for i, _ in self.avatar_agents.values())])
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
            self.stop_chaos()
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


def _r(v: Any, digits: int = 6) -> Any:
    if isinstance(v, float):
        return round(v, digits) if math.isfinite(v) else None
    return v


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


# ---------------------------------------------------------------------------------------------- pictures


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_maps(run: MissionRun, path: Path) -> Path:
    """The estimated map beside the ideal one (north up), true paths on the ideal map, estimates on the map."""
    plt = _plt()
    occ = run.occ if run.occ is not None else np.zeros((1, 1))
    ex = run.explorable if run.explorable is not None else np.zeros_like(occ)
    est = run.map_prob if run.map_prob is not None else np.full(occ.shape, 0.5, dtype=np.float32)
    res = run.grid_res
    extent = (0.0, occ.shape[1] * res, 0.0, occ.shape[0] * res)
    fig, axes = plt.subplots(1, 2, figsize=(10, 10 * occ.shape[0] / max(1, 2 * occ.shape[1]) + 1.2), dpi=110)
    sc = run.map_scores
    title = "estimated map (slam/map)" if run.map_prob is not None else "estimated map (none published)"
    if sc is not None:
        title += (f"\ncoverage {100 * sc.coverage:.1f} %, accuracy {100 * sc.accuracy:.1f} %, "
                  f"explored {100 * sc.explored:.1f} %")
    axes[0].imshow(1.0 - est, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent)
    axes[0].set_title(title, fontsize=9)
    ideal = np.where(occ > 0, 0.0, np.where(ex > 0, 1.0, 0.75))
    axes[1].imshow(ideal, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent)
    axes[1].set_title(f"ideal map (haa-sim, {int(ex.sum())} reachable cells) and true paths", fontsize=9)
    for i, (name, h) in enumerate(sorted(run.histories.items())):
        if not h.t:
            continue
        xy = np.array([(p[0], p[1]) for p in h.poses])
        color = f"C{i % 10}"
        axes[1].plot(xy[:, 0], xy[:, 1], lw=0.8, color=color, label=name)
        errs = run.loc.errors.get(name)
        if errs:
            axes[0].plot([], [], color=color, label=f"{name}: {np.mean([e[1] for e in errs]):.3f} m")
    for ax in axes:
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
    if run.histories:
        axes[1].legend(fontsize=7, loc="upper right")
    if run.loc.errors:
        axes[0].legend(fontsize=7, loc="upper right", title="mean position error", title_fontsize=7)
    fig.suptitle(f"mission {run.spec.name} (seed {run.spec.seed})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_timeline(run: MissionRun, path: Path) -> Path:
    """Agents per host over simulated mission time (from polling), with the group size."""
    plt = _plt()
    s = run.samples
    hosts = sorted({h for _, c in s.per_host for h in c} | set(run.members),
                   key=lambda n: (len(n), n))
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6), dpi=110, sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    ts = [t for t, _ in s.per_host]
    for i, h in enumerate(hosts):
        ax.step(ts, [c.get(h, 0) for _, c in s.per_host], where="post", lw=1.2, color=f"C{i % 10}", label=h)
    if s.agents:
        ax.step([t for t, _ in s.agents], [v for _, v in s.agents], where="post", color="k", lw=1.5, ls="--",
                label="all agents")
    ax.set_ylabel("active agents")
    ax.set_title(f"mission {run.spec.name}: agent allocation (agents per host)", fontsize=10)
    if hosts:
        ax.legend(fontsize=7, ncol=min(6, len(hosts) + 1), loc="upper left")
    if s.hosts:
        ax2.step([t for t, _ in s.hosts], [v for _, v in s.hosts], where="post", color="C3", label="hosts")
    ax2.set_ylabel("hosts")
    ax2.set_xlabel("simulated mission time [s]")
    for ln in run.lines:
        if ln.event == "host":
            ax2.axvline(ln.t, color="0.7", lw=0.6)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------- attached missions
# `haactl mission start|status|logs|stop`: a mission on a cluster the operator runs. `start_attached` checks (or
# starts) haa-sim and launches `conduct` as a detached process (python -m haa.mission.runner conduct ...) that
# runs a MissionRun against the cluster and keeps <root>/mission/state.json (the live status) and
# transcript.jsonl up to date; `stop_attached` ends it (SIGTERM: it stops the loop, collects the results,
# removes the mission's agents) and stops the haa-sim `start` started.

STATE_FILE = "state.json"
SIM_FILE = "sim.json"
TRANSCRIPT_FILE = "transcript.jsonl"
TRANSCRIPT_PERIOD = 3.0


def mission_dir(root: Path) -> Path:
    return Path(root).absolute() / "mission"


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str) + "\n")
    tmp.replace(path)


def process_alive(pid: Any, create_time: Any = None) -> bool:
    if not pid:
        return False
    try:
        p = psutil.Process(int(pid))
        if create_time is not None and abs(p.create_time() - float(create_time)) > 0.5:
            return False
        return p.status() != psutil.STATUS_ZOMBIE
    except (psutil.NoSuchProcess, psutil.AccessDenied, ValueError):
        return False


def conductor_alive(state: dict[str, Any] | None) -> bool:
    return bool(state) and process_alive(state.get("pid"), state.get("create_time"))  # type: ignore[union-attr]


def snapshot(run: MissionRun) -> dict[str, Any]:
    """The live status of a mission (`haactl mission status`): explored share, coverage, accuracy, each
    avatar's supervisor and target, agents per host."""
    st = run.status if isinstance(run.status, dict) else {}
    sc = run.map_scores
    names = {i: (a.name, a.type) for i, a in run.rows.items()}
    avatars = []
    for a in run.spec.avatars:
        agent = run.avatar_agents.get(a.name)
        asg = run.assign.get(a.name)
        if not isinstance(asg, dict):
            asg = {}
        sup = str(asg.get("supervisor", "")) if asg else ""
        sup_name = f"{names[sup][0]} ({tr.class_name(names[sup][1])})" if sup in names else sup[:8]
        tgt = run.targets.get(a.name)
        if isinstance(tgt, dict) and "x" in tgt and "y" in tgt:
            target = f"({_num(tgt['x'], math.nan):.2f}, {_num(tgt['y'], math.nan):.2f})"
        else:
            target = json.dumps(tgt) if tgt is not None else ""
        avatars.append({"avatar": a.name, "type": a.type, "in_arena": run.avatar_status.get(a.name, "not yet"),
                        "agent": agent[1] if agent else "", "supervisor": sup_name, "task": asg.get("task", ""),
                        "target": target})
    return {
        "pid": os.getpid(),
        "create_time": psutil.Process().create_time(),
        "updated": time.time(),
        "mission": run.spec.name,
        "state": st.get("state", "starting"),
        "t": round(run.mission_time(), 2),
        "limit": run.spec.complete.time_limit_s,
        "explored": st.get("explored"),
        "target_explored": run.spec.complete.explored,
        "coverage": _r(sc.coverage) if sc else None,
        "accuracy": _r(sc.accuracy) if sc else None,
        "position_error_m": _r(run.loc.position_error()),
        "hosts": run.members,
        "agents_per_host": run.per_host,
        "avatars": avatars,
        "exec": [run.exec_id, run.exec_name],
        "agent_ids": [run.exec_id, *(i for i, _ in run.avatar_agents.values())],
        "sim": run.sim.address if run.sim else "",
        "out_dir": str(run.out_dir),
        "errors": run.errors[-5:],
    }


def start_attached(root: Path | None, mission: Mission, speed: float | None = None, sim_address: str | None = None,
                   sim_token_file: str = "", wait: float = 60.0,
                   agent_types: tuple[str, str] = (EXECUTIVE, AVATAR), backend: Any = None,
                   md: Path | None = None, conductor: Sequence[str] = (),
                   agent_sim: tuple[str, str] = ("", "")) -> dict[str, Any]:
    """`haactl mission start`: check the cluster, check or start haa-sim, launch the conductor; returns its
    first status snapshot. MissionRunError when anything is wrong (nothing is left running then).

    The local cluster at `root` by default; another cluster (compose) comes as `backend` with its state
    directory `md`, `conductor` (the command that runs `conduct` with that backend, haa.mission.compose)
    and `agent_sim` (haa-sim's address and token file as the agents see them)."""
    from haa.cluster.backend import ClusterError
    from haa.cluster.local_backend import LocalBackend

    if mission.path is None:
        raise MissionRunError("mission start needs a mission file")
    try:
        backend = backend if backend is not None else LocalBackend(Path(root or "."))
        backend.require_hosts()
    except ClusterError as e:
        raise MissionRunError(str(e)) from None
    if not alive_hosts(backend):
        raise MissionRunError(f"no host is alive in the {backend.describe()}")
    md = md or mission_dir(backend.root)
    md.mkdir(parents=True, exist_ok=True)
    state = read_json(md / STATE_FILE)
    if conductor_alive(state):
        raise MissionRunError(f"mission {state.get('mission')} is running on this cluster (pid {state.get('pid')}): "  # type: ignore[union-attr]
                              "haactl mission stop first")
    speed = float(speed if speed is not None else mission.spec.speed)
    rec = read_json(md / SIM_FILE)
    handle = SimHandle.from_json(rec) if rec else None
    if handle is not None and handle.started_here and not handle.alive():
        handle = None
    if sim_address:
        handle = SimHandle(sim_address, sim_token_file, agent_address=agent_sim[0], agent_token_file=agent_sim[1])
    fresh = False
    if handle is not None:
        try:
            with handle.client(3.0) as c:
                info = c.info()
                ids = {a.avatar_id for a in c.poses().avatars}
        except grpc.RpcError as e:
            raise MissionRunError(f"haa-sim at {handle.address} does not answer: {e.code().name}") from None
        check_sim_matches(info, mission)
        clash = sorted(ids & {a.name for a in mission.spec.avatars})
        if clash:
            raise MissionRunError(f"the running haa-sim already has avatar{'s' if len(clash) > 1 else ''} "
                                  f"{', '.join(clash)}: stop it first (haactl mission stop)")
        if info.mode == "realtime" and info.speed and abs(info.speed - speed) > 1e-9:
            speed = float(info.speed)  # the agents' clocks must follow the haa-sim that runs
        if sim_address:  # the conductor finds it there
            write_json(md / SIM_FILE, handle.to_json())
    else:
        handle = start_sim(mission, speed, md, schedule=True, detached=True)
        fresh = True
        write_json(md / SIM_FILE, handle.to_json())
    (md / TRANSCRIPT_FILE).unlink(missing_ok=True)
    where = ["--state-dir", str(md)] if conductor else ["--root", str(backend.root)]
    cmd = [*(conductor or [sys.executable, "-m", "haa.mission.runner", "conduct"]), *where, "--mission",
           str(Path(mission.path).absolute()), "--speed", repr(speed), "--out", str(md / "run")]
    if fresh:
        cmd.append("--fresh-sim")
    if agent_types != (EXECUTIVE, AVATAR):
        cmd += ["--agent-types", ",".join(agent_types)]
    write_json(md / STATE_FILE, {"state": "launching", "mission": mission.spec.name})
    with open(md / "conductor.log", "wb") as logf:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT,
                             start_new_session=True)
    deadline = time.monotonic() + wait
    while True:
        st = read_json(md / STATE_FILE) or {}
        if st.get("state") == "failed" or p.poll() is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(10)
            if fresh:
                handle.stop()
                (md / SIM_FILE).unlink(missing_ok=True)
            raise MissionRunError(str(st.get("error") or f"the mission conductor exited (log: {md / 'conductor.log'})"))
        if st.get("pid") and st.get("state") not in ("launching", "starting"):
            return st
        if st.get("pid") and st.get("exec", ["", ""])[0]:
            return st
        if time.monotonic() > deadline:
            return st
        time.sleep(0.2)


def stop_attached(root: Path | None, timeout: float = 90.0, md: Path | None = None,
                  backend: Any = None) -> dict[str, Any]:
    """`haactl mission stop`: end the conductor (it collects the results and removes the mission's agents),
    or remove the agents itself if the conductor is gone; stop the haa-sim `start` started. Returns
    {"results": ... or None, "removed": [...], "sim": "stopped" | "left running" | ""}. The local cluster at
    `root`, or `backend` with its state directory `md` (compose)."""
    from haa.cluster.local_backend import LocalBackend

    md = md or mission_dir(Path(root or "."))
    state = read_json(md / STATE_FILE)
    out: dict[str, Any] = {"results": None, "removed": [], "sim": "", "was_running": False}
    if conductor_alive(state):
        out["was_running"] = True
        assert state is not None
        os.kill(int(state["pid"]), signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while conductor_alive(state) and time.monotonic() < deadline:
            time.sleep(0.2)
        if conductor_alive(state):
            os.kill(int(state["pid"]), signal.SIGKILL)
    elif state and state.get("agent_ids") and state.get("state") not in ("finished", "failed"):
        with contextlib.suppress(Exception):
            backend = backend if backend is not None else LocalBackend(Path(root or "."))
            out["removed"] = remove_agents(backend, [i for i in state["agent_ids"] if i])
    rec = read_json(md / SIM_FILE)
    if rec:
        h = SimHandle.from_json(rec)
        if h.started_here and h.alive():
            h.stop()
            out["sim"] = "stopped"
        (md / SIM_FILE).unlink(missing_ok=True)
    out["results"] = read_json(md / "run" / "results.json")
    return out


def live_transcript(root: Path | None, md: Path | None = None) -> list[dict[str, Any]]:
    path = (md or mission_dir(Path(root or "."))) / TRANSCRIPT_FILE
    out = []
    with contextlib.suppress(OSError):
        for line in path.read_text().splitlines():
            with contextlib.suppress(ValueError):
                out.append(json.loads(line))
    return out


def conduct(argv: Sequence[str] | None = None, backend: Any = None) -> int:
    """The detached process behind `haactl mission start` (see above): on the local cluster `--root`, or on
    `backend` with its state directory `--state-dir` (haa.mission.compose for the compose cluster)."""
    import argparse

    from haa.cluster.local_backend import LocalBackend
    from haa.mission.schema import MissionError, load_mission

    p = argparse.ArgumentParser(prog="python -m haa.mission.runner conduct")
    p.add_argument("--root", type=Path)
    p.add_argument("--state-dir", type=Path, help="the mission state directory (default <root>/mission)")
    p.add_argument("--mission", type=Path, required=True)
    p.add_argument("--speed", type=float, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--fresh-sim", action="store_true")
    p.add_argument("--agent-types", default=f"{EXECUTIVE},{AVATAR}", help="stand-ins of the two top-level types")
    a = p.parse_args(argv)
    exec_type, _, avatar_type = a.agent_types.partition(",")
    if a.root is None and (backend is None or a.state_dir is None):
        p.error("--root, or a backend and --state-dir")
    md = a.state_dir.absolute() if a.state_dir is not None else mission_dir(a.root)
    me = psutil.Process()
    base = {"pid": me.pid, "create_time": me.create_time()}
    try:
        mission = load_mission(a.mission)
        rec = read_json(md / SIM_FILE)
        if rec is None:
            raise MissionRunError(f"no haa-sim recorded in {md / SIM_FILE}")
        sim = SimHandle.from_json(rec)
        sim.started_here = False  # `haactl mission stop` stops it, not the conductor
        last_tr = [0.0]

        def on_poll(run: MissionRun) -> None:
            write_json(md / STATE_FILE, snapshot(run))
            if time.monotonic() - last_tr[0] > TRANSCRIPT_PERIOD:
                last_tr[0] = time.monotonic()
                with contextlib.suppress(Exception):
                    got = ddb_read(run.backend, keys=[K_EVENTS], prefer=run.reader)
                    events = got[1].get(K_EVENTS, []) if got else []
                    lines, _ = run.transcript(events=events if isinstance(events, list) else [])
                    tmp = md / (TRANSCRIPT_FILE + ".tmp")
                    tmp.write_text("".join(json.dumps(ln.to_json()) + "\n" for ln in lines))
                    tmp.replace(md / TRANSCRIPT_FILE)

        write_json(md / STATE_FILE, {**base, "state": "starting", "mission": mission.spec.name})
        run = MissionRun(mission, a.speed, a.out, backend=backend if backend is not None else LocalBackend(a.root),
                         sim=sim, fresh_sim=a.fresh_sim,
                         on_poll=on_poll, log=lambda text: print(text, flush=True),
                         agent_types=(exec_type, avatar_type))
        signal.signal(signal.SIGTERM, lambda *_: run.stop_flag.set())
        signal.signal(signal.SIGINT, lambda *_: run.stop_flag.set())
        results = run.run()
        lines = [json.loads(x) for x in (a.out / "transcript.jsonl").read_text().splitlines() if x.strip()]
        (md / TRANSCRIPT_FILE).write_text("".join(json.dumps(x) + "\n" for x in lines))
        write_json(md / STATE_FILE, {**snapshot(run), "state": "finished", "results": results})
        return 0 if results.get("completed") else 1
    except (MissionRunError, MissionError) as e:
        write_json(md / STATE_FILE, {**base, "state": "failed", "error": str(e)})
        print(f"error: {e}", flush=True)
        return 2
    except Exception as e:
        write_json(md / STATE_FILE, {**base, "state": "failed", "error": f"{type(e).__name__}: {e}"})
        raise


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "conduct":
        sys.exit(conduct(sys.argv[2:]))
    print("usage: python -m haa.mission.runner conduct --root DIR --mission FILE --speed X --out DIR", file=sys.stderr)
    sys.exit(2)
