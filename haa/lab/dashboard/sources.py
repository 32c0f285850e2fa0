"""Where the dashboard's data comes from: one thread per source, all writing into one `Hub`.

* `MirrorFollower` — the DDB, from one host's `Mirror` stream (the thesis' AgentMirror: a snapshot, then every
  applied batch and view change), applied to the hub's `DdbMirror`. When the host goes away the follower takes
  another alive member and starts again from its snapshot. This is the only stream the DDB needs: a commit
  reaches the page as soon as that host applied it.
* `AgentPoller` — the agent table, every host's local phase, CPU and message counters, by polling every alive
  host's `AgentList` (haa.cluster.agents) once a second: the hosts have no stream of these (CPU is measured
  by each host's agent supervisor and committed to the table only at allocation sessions; message counters
  are local to the host that runs the agent), and one AgentList per host per second costs them nothing
  measurable. Message rates are the counters' differences between two polls of the same instance.
  Host states (alive, killed, left ...) come from the backend and the group (members, leader) from the
  hosts' `Status`.
* `TimelineFeed` — the agent distribution timeline: first every host's persisted timeline records
  (haa.cluster.events: also hosts that were killed or left, and lives before a restart), then each alive host's
  `AgentEvents` stream (live), de-duplicated and attributed by `haa.cluster.events.Merger`.
* `TruthPoller` — for display only: the true avatar poses (4 Hz), the true obstacles and landmarks (once) from
  haa-sim's ground-truth service, when an haa-sim is known (`--sim`, the local cluster's mission, or the
  address in `mission/params`). It calls as `x-haa-caller: dashboard`, so that haa-sim counts these calls
  apart from the agents' (which must make none).

`Hub` holds everything under one lock and remembers what changed since the server last looked (`take`), so
that the server sends each page only what changed. Every source calls `hub.wake()` after a change.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from haa.cluster.agents import agent_lists, merge_agents
from haa.cluster.backend import ALIVE, Backend, ClusterError, agreed_group
from haa.cluster.events import (
    Merger,
    TimelineEvent,
    persisted_logs,
    take_persisted,
    timeline_events,
    view_events,
)
from haa.core.ddb.objects import DdbError
from haa.hostd.control import ControlClient
from haa.lab.dashboard.model import OVERLAY_PREFIXES, DdbMirror
from haa.pb import control_pb2 as cpb

log = logging.getLogger("haa.lab.dashboard")

#: how the dashboard names itself to haa-sim's ground-truth service
SIM_CALLER = "dashboard"
#: periods, seconds
AGENT_PERIOD = 1.0
STATUS_PERIOD = 2.0
TRUTH_PERIOD = 0.25
RETRY_PERIOD = 1.0
#: timeline events wait this long for late events of other hosts before they are merged in time order
TIMELINE_DELAY = 0.5
#: timeline events kept (the oldest are dropped beyond)
TIMELINE_MAX = 50_000


@dataclass
class Changes:
    """What changed since the last `Hub.take()`."""

    ddb_all: bool = False
    ddb_keys: set[str] = field(default_factory=set)
    agents: bool = False
    hosts: bool = False
    truth: bool = False
    arena: bool = False
    timeline: list[dict[str, Any]] = field(default_factory=list)

    @property
    def overlay(self) -> bool:
        return self.ddb_all or any(k.startswith(OVERLAY_PREFIXES) for k in self.ddb_keys)

    @property
    def map(self) -> bool:
        return self.ddb_all or "slam/map" in self.ddb_keys

    def __bool__(self) -> bool:
        return bool(self.ddb_all or self.ddb_keys or self.agents or self.hosts or self.truth or self.arena
                    or self.timeline)


class Hub:
    """Everything the dashboard knows, under one lock, plus what changed since the server last looked."""

    def __init__(self, cluster: str = "") -> None:
        self.lock = threading.RLock()
        self.cluster = cluster
        self.mirror = DdbMirror()
        self.mirror_host = ""
        self.agents: list[dict[str, Any]] = []
        self.agent_types: list[str] = []
        self.hosts: list[dict[str, Any]] = []
        self.group: dict[str, Any] = {}
        self.truth: dict[str, Any] = {}  # {"t", "avatars": {id: {x, y, theta, status}}}
        self.arena: dict[str, Any] = {}  # {"obstacles": map-like view, "landmarks": [...], "sim": address}
        self.timeline: list[dict[str, Any]] = []
        self.t0 = 0.0  # the first timeline event's time
        self.sources: dict[str, str] = {}  # source -> its state ("h1", "error: ...")
        self._changes = Changes()
        self._timeline_i = 0
        self._wake: Callable[[], None] = lambda: None

    def set_waker(self, fn: Callable[[], None]) -> None:
        self._wake = fn

    def wake(self) -> None:
        self._wake()

    def take(self) -> Changes:
        with self.lock:
            c, self._changes = self._changes, Changes()
            return c

    # ------------------------------------------------------------------ writers (any thread)
    def mirror_event(self, ev: cpb.MirrorEvent) -> None:
        with self.lock:
            keys = self.mirror.apply(ev)
            if keys is None:
                self._changes.ddb_all = True
            else:
                self._changes.ddb_keys |= keys
        self.wake()

    def set_agents(self, rows: list[dict[str, Any]], types: list[str]) -> None:
        with self.lock:
            self.agents, self.agent_types = rows, types
            self._changes.agents = True
        self.wake()

    def set_hosts(self, hosts: list[dict[str, Any]], group: dict[str, Any] | None = None) -> None:
        with self.lock:
            if hosts != self.hosts or (group is not None and group != self.group):
                self.hosts = hosts
                if group is not None:
                    self.group = group
                self._changes.hosts = True
        self.wake()

    def set_truth(self, truth: dict[str, Any]) -> None:
        with self.lock:
            self.truth = truth
            self._changes.truth = True
        self.wake()

    def set_arena(self, arena: dict[str, Any]) -> None:
        with self.lock:
            self.arena = arena
            self._changes.arena = True
        self.wake()

    def add_timeline(self, events: list[dict[str, Any]]) -> None:
        if not events:
            return
        with self.lock:
            if not self.t0:
                self.t0 = events[0]["t"]
            for e in events:
                self._timeline_i += 1
                e["i"] = self._timeline_i
            self.timeline += events
            self._changes.timeline += events
            if len(self.timeline) > TIMELINE_MAX:
                del self.timeline[: len(self.timeline) - TIMELINE_MAX]
        self.wake()

    def source(self, name: str, state: str) -> None:
        with self.lock:
            if self.sources.get(name) != state:
                self.sources[name] = state
                self._changes.hosts = True
        self.wake()


class Source(threading.Thread):
    """A daemon thread that runs `step()` until `stop()`."""

    def __init__(self, hub: Hub, backend: Backend, name: str) -> None:
        super().__init__(daemon=True, name=f"dashboard-{name}")
        self.hub = hub
        self.backend = backend
        self.stopped = threading.Event()

    def stop(self) -> None:
        self.stopped.set()

    def sleep(self, s: float) -> bool:
        """Sleep; False once stopped."""
        return not self.stopped.wait(s)


# ---------------------------------------------------------------------------------------------- the DDB


class MirrorFollower(Source):
    """The DDB from one host's mirror stream (another host's when that one goes away)."""

    def __init__(self, hub: Hub, backend: Backend, prefer: str | None = None) -> None:
        super().__init__(hub, backend, "mirror")
        self.prefer = prefer
        self.stream: Any = None

    def stop(self) -> None:
        super().stop()
        s = self.stream
        if s is not None:
            s.cancel()

    def run(self) -> None:
        while not self.stopped.is_set():
            try:
                host = self.backend.pick_host(self.prefer)
                c = self.backend.client(host, timeout=None)
            except ClusterError as e:
                self.hub.source("mirror", f"error: {e}")
                self.prefer = None
                self.sleep(RETRY_PERIOD)
                continue
            self.hub.mirror_host = host
            self.hub.source("mirror", host)
            try:
                self.stream = c.mirror(views=True)
                for ev in self.stream:
                    self.hub.mirror_event(ev)
                    if self.stopped.is_set():
                        break
                why = "the stream ended"
            except grpc.RpcError as e:
                why = e.code().name if hasattr(e, "code") else str(e)
            except DdbError as e:  # a gap: subscribe again for a fresh snapshot
                why = f"replica out of step ({e})"
            finally:
                self.stream = None
                c.close()
            if self.stopped.is_set():
                return
            self.hub.source("mirror", f"error: {host}: {why}; reconnecting")
            self.prefer = None
            self.sleep(RETRY_PERIOD)


# ---------------------------------------------------------------------------------------------- agents and hosts


class AgentPoller(Source):
    """Every agent (merged AgentList of every alive host) with CPU and message rates; the hosts' states."""

    def __init__(self, hub: Hub, backend: Backend, period: float = AGENT_PERIOD) -> None:
        super().__init__(hub, backend, "agents")
        self.period = period
        self.last: dict[tuple[str, str, int], tuple[float, int, int]] = {}  # (id, host, epoch) -> (t, in, out)
        self.last_status = 0.0

    def run(self) -> None:
        while not self.stopped.is_set():
            t0 = time.monotonic()
            try:
                self.poll()
            except Exception as e:  # keep polling: a host going away mid-call, a cluster not up yet
                self.hub.source("agents", f"error: {e}")
            if not self.sleep(max(0.05, self.period - (time.monotonic() - t0))):
                return

    def poll(self) -> None:
        hosts = self.backend.hosts()
        group = None
        if time.monotonic() - self.last_status >= STATUS_PERIOD:
            self.last_status = time.monotonic()
            replies = self.backend.statuses()
            ok = {n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply)}
            members, leader, view = agreed_group(ok)
            group = {"members": members, "leader": leader, "view": view}
        self.hub.set_hosts([{"name": h.name, "state": h.state, "address": h.address} for h in hosts], group)
        try:
            replies_a = agent_lists(self.backend)
        except ClusterError as e:
            self.hub.source("agents", f"error: {e}")
            return
        ok_a = {n: r for n, r in replies_a.items() if isinstance(r, cpb.AgentListReply)}
        if not ok_a:
            self.hub.source("agents", "error: no host answered AgentList")
            return
        rows = merge_agents(ok_a)
        now = time.monotonic()
        seen: dict[tuple[str, str, int], tuple[float, int, int]] = {}
        out = []
        for r in rows:
            k = (r.id, r.host, r.epoch)
            rate_in = rate_out = None
            if r.msgs_in or r.msgs_out:
                seen[k] = (now, r.msgs_in, r.msgs_out)
                prev = self.last.get(k)
                if prev is not None and now > prev[0] and r.msgs_in >= prev[1] and r.msgs_out >= prev[2]:
                    rate_in = (r.msgs_in - prev[1]) / (now - prev[0])
                    rate_out = (r.msgs_out - prev[2]) / (now - prev[0])
            out.append({"id": r.id, "name": r.name, "type": r.type, "state": r.state, "host": r.host,
                        "cpu": round(r.cpu, 4), "parent": r.parent_id, "epoch": r.epoch, "status": r.status,
                        "owner": r.owner, "alloc": r.alloc, "pid": r.pid, "backup": r.backup, "queued": r.queued,
                        "recovery": r.recovery, "fail_reason": r.fail_reason, "msgs_in": r.msgs_in,
                        "msgs_out": r.msgs_out,
                        "rate_in": None if rate_in is None else round(rate_in, 2),
                        "rate_out": None if rate_out is None else round(rate_out, 2)})
        self.last = seen
        types = sorted({t for rep in ok_a.values() for t in rep.agent_types})
        self.hub.set_agents(out, types)
        self.hub.source("agents", f"{len(ok_a)} hosts")


# ---------------------------------------------------------------------------------------------- timeline


def event_json(e: TimelineEvent) -> dict[str, Any]:
    return {"t": round(e.time, 3), "agent": e.agent, "name": e.name, "event": e.event, "host": e.host,
            "detail": e.detail, "type": e.type, "reporter": e.reporter}


class TimelineFeed(Source):
    """The merged agent timeline: the hosts' persisted records, then their live `AgentEvents` streams."""

    def __init__(self, hub: Hub, backend: Backend) -> None:
        super().__init__(hub, backend, "timeline")
        self.q: queue.Queue[tuple[str, cpb.AgentEvent | None]] = queue.Queue()
        self.streams: dict[str, Any] = {}
        self.threads: dict[str, threading.Thread] = {}
        self.persisted: dict[tuple[str, str, str, str], list[float]] = {}
        self.seen: set[tuple[str, float, str, str]] = set()
        self.buffer: list[TimelineEvent] = []
        self.merger = Merger()

    def stop(self) -> None:
        super().stop()
        for s in list(self.streams.values()):
            s.cancel()

    def run(self) -> None:
        self.connect()  # streams first, so that nothing falls between the persisted records and the streams
        try:
            logs = persisted_logs(self.backend)
        except Exception as e:
            logs = {}
            self.hub.source("timeline", f"error reading the hosts' logs: {e}")
        evs = timeline_events(logs)
        for e in evs:
            self.persisted.setdefault((e.host, e.agent, e.event, e.detail), []).append(e.time)
        self.buffer += evs + view_events(logs)
        last_connect = time.monotonic()
        while not self.stopped.is_set():
            self.take(0.1)
            if time.monotonic() - last_connect > RETRY_PERIOD:
                self.connect()
                last_connect = time.monotonic()
            cut = time.time() - TIMELINE_DELAY
            self.buffer.sort(key=lambda e: e.time)
            ready = [e for e in self.buffer if e.time <= cut]
            if ready:
                self.buffer = self.buffer[len(ready):]
                kept = [e for e in ready if self.merger.take(e, ready)]
                self.hub.add_timeline([event_json(e) for e in kept])

    def connect(self) -> None:
        try:
            hosts = self.backend.hosts()
        except ClusterError:
            return
        for h in hosts:
            t = self.threads.get(h.name)
            if h.state != ALIVE or (t is not None and t.is_alive()):
                continue
            c = self.backend.connect(h)
            stream = c.agent_events(history=True)
            self.streams[h.name] = stream
            th = threading.Thread(target=self._pump, args=(h.name, c, stream), daemon=True,
                                  name=f"dashboard-events-{h.name}")
            self.threads[h.name] = th
            th.start()
        self.hub.source("timeline", f"{sum(t.is_alive() for t in self.threads.values())} streams")

    def _pump(self, host: str, c: ControlClient, stream: Any) -> None:
        try:
            for ev in stream:
                self.q.put((host, ev))
        except grpc.RpcError:
            pass
        finally:
            c.close()

    def take(self, timeout: float) -> None:
        try:
            item = self.q.get(timeout=timeout)
        except queue.Empty:
            return
        while True:
            host, ev = item
            if ev is not None:
                key = (host, ev.time, ev.agent, ev.event)
                if key not in self.seen:  # a reconnect replays the host's kept history
                    self.seen.add(key)
                    if not self._persisted_already(host, ev):
                        self.buffer.append(TimelineEvent(ev.time, ev.agent, ev.name, ev.event, ev.host, ev.detail))
            try:
                item = self.q.get_nowait()
            except queue.Empty:
                return

    def _persisted_already(self, host: str, ev: cpb.AgentEvent) -> bool:
        """A stream replays the host's kept history, which its persisted log already holds (same host, agent,
        event and detail within a second)."""
        return take_persisted(self.persisted, host, ev.agent, ev.event, ev.detail, ev.time)


# ---------------------------------------------------------------------------------------------- haa-sim


@dataclass
class SimTarget:
    address: str
    token: str | None = None


def local_sim(backend: Backend) -> SimTarget | None:
    """The haa-sim of the mission `haactl mission start` runs on a local cluster (its `mission/sim.json`)."""
    root = getattr(backend, "root", None)
    if not isinstance(root, Path):
        return None
    try:
        rec = json.loads((root / "mission" / "sim.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or not rec.get("address"):
        return None
    token = None
    if rec.get("token_file"):
        from haa import files

        with contextlib.suppress(Exception):
            token = files.read_token(rec["token_file"])
    return SimTarget(str(rec["address"]), token)


class TruthPoller(Source):
    """True poses (and, once per haa-sim, obstacles and landmarks) for display; never fed back to the team."""

    def __init__(self, hub: Hub, backend: Backend, sim: SimTarget | None = None, period: float = TRUTH_PERIOD) -> None:
        super().__init__(hub, backend, "truth")
        self.explicit = sim
        self.period = period
        self.client: Any = None
        self.target: SimTarget | None = None
        self.arena_for = ""

    def find(self) -> SimTarget | None:
        if self.explicit is not None:
            return self.explicit
        t = local_sim(self.backend)
        if t is not None:
            return t
        with self.hub.lock:
            params = self.hub.mirror.json("mission/params")
        if isinstance(params, dict) and isinstance(params.get("sim"), str) and params["sim"]:
            return SimTarget(params["sim"], None)
        return None

    def run(self) -> None:
        from haa.sim.client import SimClient

        while not self.stopped.is_set():
            target = self.find()
            if target is None:
                self.hub.source("truth", "no haa-sim known")
                if not self.sleep(RETRY_PERIOD):
                    return
                continue
            if self.target != target:
                if self.client is not None:
                    self.client.close()
                self.client = SimClient(target.address, token=target.token, timeout=2.0, caller=SIM_CALLER)
                self.target = target
            try:
                if self.arena_for != target.address:
                    self.hub.set_arena(self.arena(self.client, target.address))
                    self.arena_for = target.address
                r = self.client.poses()
                self.hub.set_truth({"t": round(r.time, 3), "avatars": {
                    a.avatar_id: {"x": round(a.pose.x, 4), "y": round(a.pose.y, 4), "theta": round(a.pose.theta, 4),
                                  "status": a.status, "type": a.type, "radius": a.radius} for a in r.avatars}})
                self.hub.source("truth", target.address)
            except grpc.RpcError as e:
                self.hub.source("truth", f"error: haa-sim at {target.address}: {e.code().name}")
                if not self.sleep(RETRY_PERIOD):
                    return
                continue
            if not self.sleep(self.period):
                return

    def arena(self, client: Any, address: str) -> dict[str, Any]:
        import base64

        with self.hub.lock:
            params = self.hub.mirror.json("mission/params")
        res = 0.05
        if isinstance(params, dict) and isinstance(params.get("mission"), dict):
            with contextlib.suppress(TypeError, ValueError):
                res = float(params["mission"].get("map_resolution") or res)
        _, _, g = client.grid(res)
        cells = np.frombuffer(g.surface or g.cells, dtype=np.uint8)
        lm = client.landmarks()
        return {"sim": address, "obstacles": {
            "w": g.width, "h": g.height, "res": g.resolution, "x0": g.origin.x, "y0": g.origin.y,
            "cells": base64.b64encode((cells * 254).astype(np.uint8).tobytes()).decode()},
            "landmarks": [{"id": m.id, "x": round(m.position.x, 4), "y": round(m.position.y, 4),
                           "congregation": m.congregation} for m in lm.landmarks]}


def start_sources(hub: Hub, backend: Backend, host: str | None = None, sim: SimTarget | None = None,
                  truth: bool = True) -> list[Source]:
    """Start every source thread; returns them (stop each with `.stop()`)."""
    srcs: list[Source] = [MirrorFollower(hub, backend, host), AgentPoller(hub, backend), TimelineFeed(hub, backend)]
    if truth:
        srcs.append(TruthPoller(hub, backend, sim))
    for s in srcs:
        s.start()
    return srcs
