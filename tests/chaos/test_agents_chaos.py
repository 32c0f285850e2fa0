"""Agent-layer chaos in containers: counter pairs stay correct while host containers are killed,
paused and stopped and agent processes are SIGKILLed.

A compose cluster of `HAA_AGENT_CHAOS_HOSTS` (default 6; 10 collapsed at the host layer on the loaded 2-core
machine, docs/containers.md) `haa-hostd` containers runs three `counter` pairs (haa/lab/demoagents.py: numbered
pings both ways, loss / order / duplicate accounting, stats in the DDB under `demo/<name>`). For
`HAA_AGENT_CHAOS_SECONDS` (default 40) a seeded schedule then, in a random order and with random extras:

* `docker kill`s a host container that runs agents (its agents crash with it: Alg. 7-8 recovers them
  elsewhere from their backups) and restarts it a few seconds later (a new incarnation joins);
* `docker pause`s a host that runs agents for 0.4 s (below the failure detector's T_D^U = 1 s: nothing
  should happen) and for 3-6 s (suspected and removed; its agents are recovered elsewhere; unpaused, it comes
  back as a new incarnation);
* SIGKILLs an agent process inside its container (`docker exec <c> kill -9 <pid>`, the pid from AgentList);
* moves an agent to another host through the operator API (AgentMove: a transfer, Alg. 5-6);
* stops a host that runs agents gracefully (`docker stop` = SIGTERM: the daemon hands its agents over
  before it leaves, thesis AF-1) and starts it again later.

At most two hosts are down at a time (killed, paused, stopping, stopped, or restarted and not yet a member
again), of those at most one killed or paused with 6 hosts (two with 8 or more: the group must keep fewer
than half of its view in trouble, docs/membership.md "the fault gate"), and at most one of the three core
hosts. Meanwhile every running host's AgentList is sampled every 0.5 s and every host's AgentEvents
timeline is followed. Then everything is healed and the test asserts:

* all hosts are back in one view; the agent table holds exactly the six counters (duplicate agents: 0),
  each active (table status) with a member owner, run by that owner (local phase active, a pid) and by no
  other host;
* for every counter, read twice from the DDB until stable and progressing: lost == 0 (messages lost) and
  out_of_order + duplicate == 0 (order violations); `lost_after_recovery` is allowed (Alg. 8 recovers the
  latest backup, no newer state: by design);
* no two hosts ever reported the same agent active at the same time: a host that reported an agent active
  (same pid) in two consecutive samples ran it throughout the time between them, and no other host may
  report it active within that time;
* the chaos did what it says: every kind of action ran, and the counters saw at least one thaw and one
  recovery.

Isolation: the cluster is its own compose project (`haaagentchaos<pid>`), made from compose/compose.yaml
with the host services only (never `sim`), its own published ports (free ones) and its own subnet (a free
`10.77.x.0/24`), so it never touches the project `haa` (tests/chaos/test_chaos.py, `haactl cluster up
--compose`) or anyone else's containers. The seed (HAA_CHAOS_SEED, else the time) is printed first; the
readable timeline (Fig. 7.1-3 style: "00:51.2 A1 freezing on h4") is printed on failure and saved, with
the containers' logs, under .haa/agent-chaos/ (five newest runs). Skipped without docker or the image
(`make docker-setup image`), failed instead when HAA_REQUIRE_DOCKER=1. The overlap check itself has a unit
test that needs no docker.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
import re
import secrets
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml
from chaoslib import docker_problem
from helpers import NotYet, wait_sync

from haa.cluster.backend import ClusterError, natural_key, wait_until
from haa.cluster.compose_backend import ComposeBackend, host_service
from haa.cluster.hostprocs import free_port
from haa.core.ddb import objects as ddb
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "compose" / "compose.yaml"
KEEP = REPO / ".haa" / "agent-chaos"

N_HOSTS = int(os.environ.get("HAA_AGENT_CHAOS_HOSTS", "6"))
SECONDS = float(os.environ.get("HAA_AGENT_CHAOS_SECONDS", "40"))
PAIRS = 3
#: a backup every 20 messages (~0.5 s at 2 x 20 pings/s): a recovery loses little, and no pair is ever
#: without a backup once the chaos starts
COUNTER_CONFIG = {"spawn_peer": True, "period": 0.05, "backup_every": 20}
#: the cluster's failure detector promises detection within T_D^U = 1 s (docs/ufd.md, cluster default)
SHORT_PAUSE = 0.4
LONG_PAUSE = (3.0, 6.0)
#: hosts down at once (killed, paused, stopping or stopped), and of those how many may be killed or paused
#: (still in the view, "in trouble"): the group must keep fewer than half of its members in trouble (Alg. 2
#: decides only then, docs/membership.md "the fault gate"), with room left for a false suspicion under load
MAX_DOWN = 2
MAX_TROUBLE = 2 if N_HOSTS >= 8 else 1
CORE = ("h1", "h2", "h3")
KINDS = ("kill", "pause_short", "pause_long", "agent_kill", "move", "stop")
SAMPLE_EVERY = 0.5
#: two samples of one host further apart than this prove nothing about the time between them
MAX_GAP = 1.2
COUNTER_KEYS = ("sent", "received", "lost", "out_of_order", "duplicate", "lost_after_recovery",
                "resent_after_recovery", "stale", "thaws", "recoveries")


# ---------------------------------------------------------------------------------------------- the cluster


def used_subnets() -> set[str]:
    import docker

    client = docker.from_env(version="auto", timeout=30)
    try:
        out = set()
        for net in client.networks.list():
            for cfg in (net.attrs.get("IPAM") or {}).get("Config") or []:
                if cfg.get("Subnet"):
                    out.add(cfg["Subnet"])
        return out
    finally:
        client.close()


def free_prefix(rng: random.Random) -> str:
    """A /24 prefix `10.77.x` that no docker network uses (x in 100..249)."""
    used = used_subnets()
    free = [f"10.77.{x}" for x in range(100, 250) if f"10.77.{x}.0/24" not in used]
    if not free:
        raise AssertionError("no free 10.77.x.0/24 subnet for the test network")
    return rng.choice(free)


def derive_compose(dst: Path, n: int, prefix: str) -> Path:
    """compose/compose.yaml with its first `n` host services only, free published ports, subnet `prefix`,
    and a fresh token next to it (the services mount ./token)."""
    spec = yaml.safe_load(SOURCE.read_text())
    hosts = sorted((s for s, svc in spec["services"].items() if host_service(s, svc)), key=natural_key)[:n]
    assert len(hosts) == n, f"compose/compose.yaml defines {len(hosts)} hosts, the test wants {n}"
    ports: set[int] = set()
    while len(ports) < n:
        ports.add(free_port())
    services = {}
    for name, port in zip(hosts, sorted(ports), strict=True):
        svc = dict(spec["services"][name])
        svc["ports"] = [f"127.0.0.1:{port}:7000"]
        svc["labels"] = {"io.haa.test": "agent-chaos"}
        services[name] = svc
    out = {"version": spec["version"], "services": services, "networks": spec["networks"]}
    text = re.sub(r"\$\{HAA_SUBNET_PREFIX:-[0-9.]+\}", prefix, yaml.safe_dump(out, sort_keys=False))
    dst.mkdir(parents=True, exist_ok=True)
    f = dst / "compose.yaml"
    f.write_text(text)
    token = dst / "token"
    token.write_text(secrets.token_hex(32) + "\n")
    token.chmod(0o644)  # read by the daemon inside the container (bind mount, read-only)
    return f


def up_on_free_subnet(make_dir: Callable[[], Path], n: int, project: str, rng: random.Random,
                      prepare: Callable[[Path, str], None] | None = None) -> tuple[ComposeBackend, list[str], str]:
    """`compose up` of a derived compose file (`derive_compose` in a fresh `make_dir()`, then `prepare(file,
    prefix)`) as `project`: a subnet taken between our look and compose's network create is tried again with
    another, up to 3 times; any other failure fails the test. (backend, host names, subnet prefix)."""
    for _attempt in range(3):
        prefix = free_prefix(rng)
        f = derive_compose(make_dir(), n, prefix)
        if prepare is not None:
            prepare(f, prefix)
        backend = ComposeBackend(f, project=project)
        try:
            return backend, backend.up(n), prefix
        except ClusterError as e:
            with contextlib.suppress(ClusterError):
                backend.down(grace=1)
            if "overlap" not in str(e) and "Pool" not in str(e):
                pytest.fail(f"compose up of project {project} failed: {e}")
    pytest.fail(f"compose up of project {project}: no free subnet after 3 attempts")


def clock(t: float) -> str:
    """Seconds since the run started as mm:ss.s (the thesis transcript's style, Fig. 7.1-3)."""
    return f"{'-' if t < 0 else ''}{int(abs(t) // 60):02d}:{abs(t) % 60:04.1f}"


class Cluster:
    """The compose cluster under test, what the chaos did to it, and the merged timeline."""

    def __init__(self, backend: ComposeBackend, names: list[str], seed: int, keep: Path) -> None:
        self.backend = backend
        self.names = names
        self.seed = seed
        self.keep = keep
        self.addr = {h.name: h.address for h in backend.hosts()}
        self.t0 = time.monotonic()
        self.unix0 = time.time()
        self.lock = threading.Lock()
        #: name -> "killed" | "paused" | "stopping" | "stopped" | "joining" (restarted or resumed, not yet a member)
        self.down: dict[str, str] = {}
        self.lines: list[tuple[float, str]] = []
        self.host_events_added = False

    def now(self) -> float:
        return time.monotonic() - self.t0

    def client(self, name: str, timeout: float = 3.0) -> ControlClient:
        return ControlClient(self.addr[name], self.backend.token, timeout=timeout)

    def up(self) -> list[str]:
        """Hosts that are members as far as the chaos knows (not down, not rejoining)."""
        with self.lock:
            return [n for n in self.names if n not in self.down]

    def running(self) -> list[str]:
        """Hosts whose daemon runs: the up ones plus those stopping (draining) or rejoining."""
        with self.lock:
            return [n for n in self.names if self.down.get(n, "joining") in ("joining", "stopping")]

    def note(self, text: str, at: float | None = None) -> None:
        with self.lock:
            self.lines.append((self.now() if at is None else at, text))

    def timeline(self) -> str:
        with self.lock:
            lines = sorted(self.lines, key=lambda x: x[0])
        return "\n".join(f"{clock(t)} {text}" for t, text in lines)

    def add_host_events(self) -> None:
        """Merge the host layer's story from the containers' logs into the timeline (once): views, exclusions
        and reincarnations, removals waiting for a quorum, drains, leaves, starts and shutdowns."""
        if self.host_events_added:
            return
        self.host_events_added = True
        views: set[tuple[Any, ...]] = set()
        for name, ctr in self.backend.containers().items():
            try:
                raw = ctr.logs(stdout=True, stderr=True).decode("utf-8", "replace")
            except Exception:  # a container gone: its story is lost, the rest still helps
                continue
            waits: tuple[str, ...] = ()
            for line in raw.splitlines():
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                ev, f = rec.get("event"), rec.get("fields") or {}
                at = float(rec.get("ts", 0.0)) - self.unix0
                if ev == "view":
                    key = (f.get("view"), tuple(f.get("members") or ()))
                    if key in views:
                        continue
                    views.add(key)
                    text = f"view {f.get('view')}: {' '.join(m.split('.')[0] for m in f.get('members') or ())}"
                    for what in ("removed", "added"):
                        if f.get(what):
                            text += f" ({what} {' '.join(str(m).split('.')[0] for m in f[what])})"
                elif ev == "reincarnate":
                    text = f"{name} restarts as a new incarnation (excluded by {f.get('by')})"
                elif ev == "removal_waits_for_quorum":
                    if tuple(f.get("suspected") or ()) == waits:
                        continue
                    waits = tuple(f.get("suspected") or ())
                    text = f"{name}: removing {' '.join(waits)} waits for a quorum"
                elif ev == "draining":
                    text = f"{name} drains ({f.get('agents')} agents)"
                elif ev == "leave_requested":
                    text = f"{name} leaves the group"
                elif ev in ("startup", "shutdown"):
                    text = f"{name} {'starts' if ev == 'startup' else 'shuts down'}"
                else:
                    continue
                self.note(f"-- {text}", at)

    def agent_list(self, name: str, timeout: float = 2.0) -> cpb.AgentListReply:
        c = self.client(name, timeout)
        try:
            return c.agent_list()
        finally:
            c.close()

    def lists(self, names: list[str], timeout: float = 2.0) -> dict[str, cpb.AgentListReply]:
        """AgentList of the named hosts in parallel; hosts that do not answer are left out."""

        def one(n: str) -> tuple[str, cpb.AgentListReply | None]:
            try:
                return n, self.agent_list(n, timeout)
            except grpc.RpcError:
                return n, None

        with ThreadPoolExecutor(max_workers=max(1, len(names))) as pool:
            return {n: r for n, r in pool.map(one, names) if r is not None}

    def table(self) -> tuple[str, list[cpb.AgentInfo]] | None:
        """The agent table as the first answering up host holds it."""
        for n in self.up():
            with contextlib.suppress(grpc.RpcError):
                return n, list(self.agent_list(n).agents)
        return None

    def counters(self, name: str) -> dict[str, dict[str, Any]]:
        """The counters' stats as published in the DDB (`demo/<agent name>`), read on host `name`."""
        c = self.client(name, 5.0)
        try:
            objs = c.ddb_get(prefix="demo/").objects
        finally:
            c.close()
        t = ddb.TYPES["json"]
        return {o.key.removeprefix("demo/"): t.public(t.decode(o.value)[0]) for o in objs if o.type == "json"}


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    seed = int(os.environ.get("HAA_CHAOS_SEED") or time.time_ns() % 1_000_000)
    print(f"\nagent chaos seed {seed} (HAA_CHAOS_SEED={seed} reproduces the choices)")
    project = f"haaagentchaos{os.getpid()}"
    rng = random.Random(seed)
    keep = KEEP / f"{time.strftime('%Y%m%d-%H%M%S')}-seed{seed}"
    t0 = time.monotonic()
    backend, names, prefix = up_on_free_subnet(lambda: tmp_path_factory.mktemp("agentchaos"), N_HOSTS, project, rng)
    try:
        formed, _ = wait_until(lambda: backend.formation(names), 180, what=f"{N_HOSTS} hosts in one group")
        print(f"project {project}: {N_HOSTS} containers (subnet {prefix}.0/24) formed one group in "
              f"{time.monotonic() - t0:.1f} s (leader {formed.leader})")
        yield Cluster(backend, names, seed, keep)
    finally:
        with contextlib.suppress(Exception):
            for c in backend.containers().values():
                c.reload()
                if c.status == "paused":
                    c.unpause()
        keep.mkdir(parents=True, exist_ok=True)
        for n, c in backend.containers().items():
            with contextlib.suppress(Exception):
                (keep / f"{n}.jsonl").write_bytes(c.logs(stdout=True, stderr=True))
        for old in sorted(p for p in KEEP.iterdir() if p.is_dir())[:-5]:
            shutil.rmtree(old, ignore_errors=True)
        print(f"\ncontainer logs: {keep}/ (agent chaos seed {seed})")
        backend.down(grace=2)


# ---------------------------------------------------------------------------------------------- observers


class Events:
    """Follows every host's AgentEvents stream (reconnecting after kills and restarts) into the timeline."""

    WORDS = {"freezing": "freezing on", "frozen": "frozen on", "thawing": "thawing on", "thawed": "thawed by",
             "spawning": "spawning on", "active": "spawned by", "crashed": "crashed on",
             "recovering": "recovering on", "recovered": "recovered by", "removed": "removed by"}

    def __init__(self, cluster: Cluster) -> None:
        self.cluster = cluster
        self.stop = threading.Event()
        self.seen: set[tuple[str, float, str, str]] = set()
        self.created: set[str] = set()
        self.table_crash: dict[str, float] = {}
        self.calls: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self.threads = [threading.Thread(target=self.run, args=(n,), daemon=True) for n in cluster.names]

    def run(self, host: str) -> None:
        while not self.stop.is_set():
            c = self.cluster.client(host)
            try:
                call = c.agent_events(history=True)
                self.calls[host] = call
                for ev in call:
                    self.take(host, ev)
            except grpc.RpcError:
                pass
            finally:
                c.close()
            self.stop.wait(0.5)

    def take(self, host: str, ev: cpb.AgentEvent) -> None:
        key = (host, round(ev.time, 6), ev.agent, ev.event)
        at = ev.time - self.cluster.unix0
        with self.cluster.lock:
            if key in self.seen:
                return
            self.seen.add(key)
            self.counts[ev.event] = self.counts.get(ev.event, 0) + 1
            if ev.event == "created":
                if ev.agent in self.created:
                    return
                self.created.add(ev.agent)
            if ev.event == "crashed" and not ev.detail:  # every member marks it: keep the first
                last = self.table_crash.get(ev.agent)
                self.table_crash[ev.agent] = at
                if last is not None and abs(at - last) < 3.0:
                    return
        word = self.WORDS.get(ev.event, ev.event)
        if ev.event == "created":
            text = f"{ev.name} created ({ev.detail})"
        elif ev.event == "crashed" and not ev.detail:
            text = f"{ev.name} crashed (agent table, first seen by {ev.host})"
        else:
            text = f"{ev.name} {word} {ev.host}" + (f" ({ev.detail})" if ev.detail else "")
        self.cluster.note(text, at)

    def __enter__(self) -> Events:
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for call in list(self.calls.values()):
            with contextlib.suppress(Exception):
                call.cancel()
        for t in self.threads:
            t.join(5)


@dataclass(frozen=True)
class Obs:
    """One AgentList answer: host, call start / end (s since the run started), agent id -> what it said."""

    host: str
    t0: float
    t1: float
    rows: dict[str, tuple[str, str, str, str, int, int]]  # name, local_phase, status, owner, epoch, pid


class Sampler:
    """AgentList of every host that is not down, every 0.5 s."""

    def __init__(self, cluster: Cluster) -> None:
        self.cluster = cluster
        self.stop = threading.Event()
        self.obs: list[Obs] = []
        self.failed = 0
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.pool = ThreadPoolExecutor(max_workers=len(cluster.names))

    def one(self, host: str) -> Obs | None:
        t0 = self.cluster.now()
        try:
            r = self.cluster.agent_list(host, timeout=1.5)
        except grpc.RpcError:
            self.failed += 1
            return None
        rows = {a.id: (a.name, a.local_phase, a.status, a.owner, a.epoch, a.pid) for a in r.agents}
        return Obs(host, t0, self.cluster.now(), rows)

    def run(self) -> None:
        while not self.stop.is_set():
            start = time.monotonic()
            for o in self.pool.map(self.one, self.cluster.running()):
                if o is not None:
                    self.obs.append(o)
            self.stop.wait(max(0.05, SAMPLE_EVERY - (time.monotonic() - start)))

    def __enter__(self) -> Sampler:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(10)
        self.pool.shutdown(wait=False, cancel_futures=True)


@dataclass
class Overlaps:
    """What the AgentList samples say about agents running twice (see `double_active`)."""

    proven: list[str]  # two instances proven to run at the same time: a failure
    foreign: list[str]  # a host runs an agent that its own table gives to another host: a failure
    same_round: list[str]  # two hosts reported it active in one sampling round, no overlap proven: reported


def double_active(obs: list[Obs]) -> Overlaps:
    """Proven overlaps of two instances of one agent: host A reported it active with the same pid in two
    samples of consecutive rounds (at most MAX_GAP apart: a paused host is not sampled, and a frozen process
    does not run), so it ran it throughout [end of the first call, start of the second], and host B reported
    it active in a call that lies entirely inside that interval. Also every report of an agent active on a
    host whose own table names another owner, and (not failures: a transfer or a zombie's last moment can
    fall between two calls of one round) the rounds in which two hosts reported one agent active."""
    by_host: dict[str, list[Obs]] = {}
    for o in obs:
        by_host.setdefault(o.host, []).append(o)
    sure: dict[str, list[tuple[float, float, str, int, int]]] = {}  # agent -> (from, to, host, epoch, pid)
    for host, lst in by_host.items():
        lst.sort(key=lambda o: o.t0)
        for a, b in itertools.pairwise(lst):
            if b.t0 - a.t1 > MAX_GAP:
                continue
            for aid, row in a.rows.items():
                other = b.rows.get(aid)
                if row[1] == "active" and other and other[1] == "active" and row[5] and row[5] == other[5]:
                    sure.setdefault(aid, []).append((a.t1, b.t0, host, row[4], row[5]))
    proven, foreign = [], []
    for o in obs:
        for aid, row in o.rows.items():
            if row[1] != "active":
                continue
            if row[3] != o.host:
                foreign.append(f"{row[0]} active on {o.host} (pid {row[5]}) at {o.t0:.2f} s, whose table says: "
                               f"{row[2]}, owner {row[3] or '-'}, epoch {row[4]}")
            for lo, hi, host, epoch, pid in sure.get(aid, []):
                if host != o.host and lo <= o.t0 and o.t1 <= hi:
                    proven.append(f"{row[0]} ran on {host} (epoch {epoch}, pid {pid}) throughout {lo:.2f}-{hi:.2f} s "
                                  f"while {o.host} reported it active (epoch {row[4]}, pid {row[5]}) at "
                                  f"{o.t0:.2f}-{o.t1:.2f} s")
    rounds: dict[int, dict[str, list[tuple[str, str, int, float]]]] = {}  # round -> agent -> reports
    for o in obs:
        r = rounds.setdefault(int(o.t0 / SAMPLE_EVERY), {})
        for aid, row in o.rows.items():
            if row[1] == "active":
                r.setdefault(aid, []).append((row[0], o.host, row[4], o.t0))
    same_round = [
        f"{reports[0][0]} active on " + ", ".join(f"{h} (its table: epoch {e}) at {t:.2f} s" for _, h, e, t in reports)
        for r in rounds.values() for reports in r.values() if len({h for _, h, _, _ in reports}) > 1
    ]
    return Overlaps(proven, foreign, same_round)


# ---------------------------------------------------------------------------------------------- the chaos


class ChaosMonkey:
    """The seeded schedule of failures (module docstring), with the heals it owes."""

    def __init__(self, cluster: Cluster, rng: random.Random) -> None:
        self.c = cluster
        self.rng = rng
        self.done: dict[str, int] = dict.fromkeys(KINDS, 0)
        self.heals: list[tuple[float, str, str]] = []  # (due, kind, host)
        self.stoppers: list[threading.Thread] = []
        self.errors: list[str] = []

    def log(self, text: str, at: float | None = None) -> None:
        at = self.c.now() if at is None else at
        self.c.note(f"** {text}", at)
        print(f"{at:6.1f}s  {text}")

    def agents_by_owner(self) -> dict[str, list[cpb.AgentInfo]]:
        t = self.c.table()
        out: dict[str, list[cpb.AgentInfo]] = {}
        for a in t[1] if t else []:
            if a.status == "active" and a.owner:
                out.setdefault(a.owner, []).append(a)
        return out

    def victims(self, kind: str) -> list[str]:
        """Up hosts that run agents and may go down now (MAX_DOWN, one core host at most)."""
        with self.c.lock:
            down = dict(self.c.down)
        if len(down) >= MAX_DOWN:
            return []
        if kind != "stop" and sum(1 for k in down.values() if k in ("killed", "paused")) >= MAX_TROUBLE:
            return []
        core_down = any(n in CORE for n in down)
        owners = self.agents_by_owner()
        return sorted((n for n in owners if n in self.c.names and n not in down and not (core_down and n in CORE)),
                      key=natural_key)

    def container(self, name: str) -> Any:
        return self.c.backend.container(name)

    def act(self, kind: str) -> bool:
        owners = self.agents_by_owner()
        at = self.c.now()
        if kind in ("kill", "pause_long", "stop", "pause_short"):
            cands = self.victims(kind)
            if not cands:
                return False
            host = self.rng.choice(cands)
            runs = ", ".join(sorted(a.name for a in owners.get(host, [])))
            if kind == "kill":
                with self.c.lock:
                    self.c.down[host] = "killed"
                self.c.backend.kill(host)
                self.heals.append((self.c.now() + self.rng.uniform(4.0, 10.0), "restart", host))
                self.log(f"docker kill {host} (runs {runs})", at)
            elif kind == "pause_short":
                with self.c.lock:
                    self.c.down[host] = "paused"
                self.c.backend.pause(host)
                self.log(f"docker pause {host} for {SHORT_PAUSE} s (runs {runs})", at)
                time.sleep(SHORT_PAUSE)
                self.c.backend.resume(host)
                with self.c.lock:
                    self.c.down.pop(host, None)
                self.log(f"docker unpause {host}")
            elif kind == "pause_long":
                with self.c.lock:
                    self.c.down[host] = "paused"
                self.c.backend.pause(host)
                length = self.rng.uniform(*LONG_PAUSE)
                self.heals.append((self.c.now() + length, "resume", host))
                self.log(f"docker pause {host} for {length:.1f} s (runs {runs})", at)
            else:
                with self.c.lock:
                    self.c.down[host] = "stopping"
                t = threading.Thread(target=self.stop_host, args=(host, self.rng.uniform(3.0, 8.0)), daemon=True)
                self.stoppers.append(t)
                self.log(f"docker stop {host} (SIGTERM: graceful leave; runs {runs})", at)
                t.start()
            self.done[kind] += 1
            return True
        up = [n for n in self.c.up() if n in owners]
        agents = [a for n in up for a in owners[n]]
        if not agents:
            return False
        a = self.rng.choice(sorted(agents, key=lambda x: x.name))
        if kind == "agent_kill":
            try:
                rows = {r.id: r for r in self.c.agent_list(a.owner).agents}
            except grpc.RpcError:
                return False
            r = rows.get(a.id)
            if r is None or r.local_phase != "active" or not r.pid:
                return False
            at = self.c.now()
            code, out = self.container(a.owner).exec_run(["kill", "-9", str(r.pid)])
            self.log(f"docker exec {a.owner} kill -9 {r.pid} ({a.name}): exit {code} {out.decode().strip()}", at)
            if code != 0:
                return False
        else:  # move
            targets = [n for n in self.c.up() if n != a.owner]
            if not targets:
                return False
            target = self.rng.choice(targets)
            via = self.rng.choice(self.c.up())
            c = self.c.client(via, 10.0)
            try:
                at = self.c.now()
                rep = c.agent_move(a.name, target, timeout=10.0)
                self.log(f"operator (via {via}): move {a.name} from {a.owner} to {target}: "
                         f"{'ok' if rep.ok else 'refused: ' + rep.reason}", at)
            except grpc.RpcError as e:
                self.log(f"operator (via {via}): move {a.name} to {target}: {e.code().name}")
                return False
            finally:
                c.close()
            if not rep.ok:
                return False
        self.done[kind] += 1
        return True

    def stop_host(self, host: str, then: float) -> None:
        t = time.monotonic()
        try:
            self.c.backend.terminate(host, 20)
            code = self.container(host).attrs.get("State", {}).get("ExitCode")
            self.log(f"{host} stopped after {time.monotonic() - t:.1f} s (exit {code})")
        except Exception as e:  # recorded; the heal restarts it anyway
            self.errors.append(f"stop {host}: {type(e).__name__}: {e}")
        with self.c.lock:
            self.c.down[host] = "stopped"
        self.heals.append((self.c.now() + then, "restart", host))

    def heal(self, host: str, kind: str) -> None:
        at = self.c.now()
        if kind == "resume":
            self.c.backend.resume(host)
            self.log(f"docker unpause {host}", at)
        else:
            self.c.backend.restart(host)
            self.log(f"docker start {host} (a new incarnation joins)", at)
        with self.c.lock:
            self.c.down[host] = "joining"

    def check_joining(self) -> None:
        """A rejoining host counts as down until it says it is a member again."""
        with self.c.lock:
            joining = [n for n, k in self.c.down.items() if k == "joining"]
        for n in joining:
            cl = self.c.client(n, 1.0)
            try:
                member = cl.status().member
            except grpc.RpcError:
                member = False
            finally:
                cl.close()
            if member:
                with self.c.lock:
                    self.c.down.pop(n, None)

    def heal_due(self, everything: bool = False) -> None:
        now = self.c.now()
        due = [h for h in self.heals if everything or h[0] <= now]
        for h in sorted(due):
            self.heals.remove(h)
            self.heal(h[2], h[1])

    def sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.heal_due()
            self.check_joining()
            time.sleep(min(0.2, max(0.0, end - time.monotonic())))

    def run(self, seconds: float) -> None:
        plan = list(KINDS)
        self.rng.shuffle(plan)
        end = self.c.now() + seconds
        while self.c.now() < end or plan:
            if self.c.now() > end + 30:
                break  # mandatory kinds that found no victim for 30 s: reported by the test
            kind = plan[0] if plan else self.rng.choice(KINDS)
            try:
                ok = self.act(kind)
            except (ClusterError, grpc.RpcError) as e:
                self.errors.append(f"{kind}: {e}")
                ok = False
            if plan and ok:
                plan.pop(0)
            elif plan and not ok and len(plan) > 1:
                plan.append(plan.pop(0))  # try the others first
            self.sleep(self.rng.uniform(1.5, 3.5) if ok else 0.5)

    def heal_all(self) -> None:
        for t in self.stoppers:
            t.join(30)
        self.heal_due(everything=True)
        with self.c.lock:
            self.c.down.clear()


# ---------------------------------------------------------------------------------------------- checks


#: a poll of the cluster retries after an RPC error
RPC = (grpc.RpcError,)


def settled(c: Cluster) -> dict[str, str] | NotYet:
    """{agent name: host running it} when every host holds the same table of exactly the six counters, each
    active with a member owner that runs it and no other host running it; else why not."""
    lists = c.lists(c.names, timeout=3.0)
    if len(lists) != len(c.names):
        return NotYet(f"no AgentList from {sorted(set(c.names) - set(lists))}")
    tables = {n: sorted((a.id, a.name, a.status, a.owner, a.epoch) for a in r.agents) for n, r in lists.items()}
    if len({tuple(t) for t in tables.values()}) != 1:
        return NotYet("the hosts' agent tables differ")
    rows = next(iter(lists.values())).agents
    names = sorted(a.name for a in rows)
    want = sorted([f"A{i}" for i in range(1, PAIRS + 1)] + [f"A{i}.1" for i in range(1, PAIRS + 1)])
    if names != want:
        return NotYet(f"the table holds {names}, not {want}")
    out = {}
    for a in rows:
        if a.status != "active" or a.owner not in c.names:
            return NotYet(f"{a.name} is {a.status} (owner {a.owner or '-'})")
        running = [n for n, r in lists.items() for x in r.agents if x.id == a.id and x.local_phase]
        mine = next(x for x in lists[a.owner].agents if x.id == a.id)
        if running != [a.owner] or mine.local_phase != "active" or not mine.pid:
            return NotYet(f"{a.name}: owner {a.owner} (phase {mine.local_phase or '-'}, pid {mine.pid}), on {running}")
        out[a.name] = a.owner
    return out


def warmed_up(c: Cluster) -> dict[str, dict[str, Any]] | NotYet:
    """The counters' stats once each of them has published that it receives pings and has made a backup."""
    stats = c.counters(c.names[0])
    if len(stats) != 2 * PAIRS:
        return NotYet(f"stats of {sorted(stats)}")
    cold = sorted(n for n, s in stats.items() if s["received"] == 0 or s["backups"] == 0)
    return NotYet(f"no pings or no backup yet: {cold}") if cold else stats


def stable_counters(c: Cluster, rng: random.Random) -> dict[str, dict[str, Any]] | NotYet:
    """Two reads of the counters 2.5 s apart (through two hosts): every counter published in between, its
    peer's pings kept arriving, and lost / out_of_order / duplicate did not change."""
    a, b = rng.choice(c.names), rng.choice(c.names)
    first = c.counters(a)
    time.sleep(2.5)  # the period over which the counters must progress
    second = c.counters(b)
    if sorted(second) != sorted(first) or len(second) != 2 * PAIRS:
        return NotYet(f"stats of {sorted(second)}")
    for name, s in second.items():
        f = first[name]
        if s["time"] <= f["time"]:
            return NotYet(f"{name} did not publish for 2.5 s")
        if s["received"] <= f["received"]:
            return NotYet(f"{name} received nothing for 2.5 s ({s['received']})")
        if any(s[k] != f[k] for k in ("lost", "out_of_order", "duplicate")):
            return NotYet(f"{name}: lost / out_of_order / duplicate still changing")
    return second


def counter_table(stats: dict[str, dict[str, Any]]) -> str:
    head = "| agent | " + " | ".join(COUNTER_KEYS) + " |"
    rows = [head, "|" + "---|" * (len(COUNTER_KEYS) + 1)]
    for name in sorted(stats, key=natural_key):
        rows.append(f"| {name} | " + " | ".join(str(stats[name].get(k, "?")) for k in COUNTER_KEYS) + " |")
    return "\n".join(rows)


# ---------------------------------------------------------------------------------------------- the test


@pytest.mark.docker
@pytest.mark.slow
def test_counter_pairs_survive_container_chaos(cluster: Cluster) -> None:
    c = cluster
    rng = random.Random(c.seed)
    t_test = time.monotonic()
    report: list[str] = []
    try:
        with Events(c) as events, Sampler(c) as sampler:
            for _ in range(PAIRS):
                via = rng.choice(c.names)
                cl = c.client(via, 20.0)
                try:
                    rep = cl.agent_spawn("counter", json.dumps(COUNTER_CONFIG).encode(), timeout=20.0)
                finally:
                    cl.close()
                assert rep.ok, f"spawn through {via}: {rep.reason}"
                c.note(f"** operator (via {via}): spawn counter {rep.name} (it spawns its peer {rep.name}.1)")
            placed = wait_sync(lambda: settled(c), 60, "the six counters to run", interval=0.5, ignore=RPC)
            print(f"{c.now():6.1f}s  counters placed: {placed}")
            wait_sync(lambda: warmed_up(c), 30, "pings flowing, first backups made", interval=0.5, ignore=RPC)
            monkey = ChaosMonkey(c, rng)
            t_chaos = time.monotonic()
            monkey.run(SECONDS)
            monkey.heal_all()
            chaos_s = time.monotonic() - t_chaos
            print(f"{c.now():6.1f}s  chaos over after {chaos_s:.1f} s: {monkey.done}")
            t_heal = time.monotonic()
            wait_until(lambda: c.backend.formation(c.names), 120, what=f"all {len(c.names)} hosts in one group")
            placed = wait_sync(lambda: settled(c), 90, "every counter active on exactly one member host", interval=0.5,
                               ignore=RPC)
            healed_s = time.monotonic() - t_heal
            print(f"{c.now():6.1f}s  healed in {healed_s:.1f} s: {placed}")
            stats = wait_sync(lambda: stable_counters(c, rng), 40, "stable, progressing counters", interval=0.5,
                              ignore=RPC)
            n = len(sampler.obs)
            wait_sync(lambda: len(sampler.obs) >= n + len(c.names), 10, "a last sample round on the healed cluster",
                      interval=0.1)
        ov = double_active(sampler.obs)
        report += [
            f"seed {c.seed}; {len(c.names)} hosts; chaos {chaos_s:.1f} s, healed in {healed_s:.1f} s; "
            f"test {time.monotonic() - t_test:.1f} s",
            f"actions: {monkey.done}; errors: {monkey.errors or 'none'}",
            f"AgentList samples: {len(sampler.obs)} answered, {sampler.failed} not; proven overlaps: "
            f"{len(ov.proven)}; active on a host that is not the owner in its own table: {len(ov.foreign)}; "
            f"two hosts active in one round (no overlap proven): {len(ov.same_round)}",
            *[f"  same round: {x}" for x in ov.same_round[:10]],
            f"timeline events: {dict(sorted(events.counts.items()))}",
            counter_table(stats),
        ]
        print("\n".join(report))
        missing = [k for k, v in monkey.done.items() if not v]
        assert not missing, f"the chaos never managed to {missing} (seed {c.seed})"
        assert not ov.proven, "two hosts ran one agent at the same time:\n" + "\n".join(ov.proven[:20])
        assert not ov.foreign, "a host ran an agent it does not own:\n" + "\n".join(ov.foreign[:20])
        bad = {n: {k: s[k] for k in ("lost", "out_of_order", "duplicate")} for n, s in stats.items()
               if s["lost"] or s["out_of_order"] or s["duplicate"]}
        assert not bad, f"messages lost / out of order / duplicated: {bad}"
        assert sum(s["thaws"] for s in stats.values()) > 0, "no counter was ever thawed: no transfer happened"
        assert sum(s["recoveries"] for s in stats.values()) > 0, "no counter was ever recovered"
    except BaseException:
        with contextlib.suppress(Exception):
            c.add_host_events()
        print(f"\n--- timeline (seed {c.seed}; ** chaos, -- host layer, the rest from AgentEvents) ---\n"
              f"{c.timeline()}")
        raise
    finally:
        with contextlib.suppress(Exception):
            c.add_host_events()
        c.keep.mkdir(parents=True, exist_ok=True)
        (c.keep / "timeline.txt").write_text(c.timeline() + "\n\n" + "\n".join(report) + "\n")


def test_double_active_finds_proven_overlaps_only() -> None:
    """The overlap check itself (no docker): a report inside another host's proven run is a violation; a
    handover between two samples, a gap in one host's samples (paused) or a new process are not."""
    a = "agent-a"

    def obs(host: str, t0: float, phase: str = "active", pid: int = 10, epoch: int = 1, owner: str = "") -> Obs:
        return Obs(host, t0, t0 + 0.05, {a: ("A1", phase, "active", owner or host, epoch, pid)})

    # h1 runs A1 (pid 10) in samples at 0.0 and 0.5; h2 reports it active at 0.2: two instances at once
    ov = double_active([obs("h1", 0.0), obs("h2", 0.2, pid=20, epoch=2), obs("h1", 0.5)])
    assert len(ov.proven) == 1 and "A1 ran on h1" in ov.proven[0] and "while h2 reported it active" in ov.proven[0]
    # a handover: h1 active at 0.0, frozen at 0.5; h2 active from 0.6 on
    ov = double_active([obs("h1", 0.0), obs("h2", 0.1, phase="thawing", pid=20),
                        obs("h1", 0.5, phase=""), obs("h2", 0.6, pid=20), obs("h2", 1.1, pid=20)])
    assert ov.proven == [] and ov.same_round == [] and ov.foreign == []
    # a new process on h1 between two samples (a local recovery) proves nothing about the time between
    assert double_active([obs("h1", 0.0), obs("h2", 0.2, pid=20), obs("h1", 0.5, pid=11)]).proven == []
    # h1 paused from 0.1 to 5.0 (not sampled): its process did not run meanwhile, h2 recovered the agent
    ov = double_active([obs("h1", 0.0), obs("h2", 2.0, pid=20, epoch=2), obs("h1", 5.1), obs("h2", 5.1, pid=20)])
    assert ov.proven == [] and len(ov.same_round) == 1 and "h1 (its table: epoch 1)" in ov.same_round[0]
    # a host that runs an agent its own table gives to another host
    ov = double_active([obs("h1", 0.0, owner="h2")])
    assert len(ov.foreign) == 1 and "owner h2" in ov.foreign[0]
