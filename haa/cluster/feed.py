"""The allocation timeline of every host of a cluster, merged and live: `EventFeed` (moved here from
haactl.agentcli, which prints it: `haactl agent events`; `haactl demo` prints it as the demo runs).

What the hosts persisted comes first (their JSON-lines logs, read through the backend: also hosts that were
killed, left or are stopped, and the lives before a restart — haa.cluster.events), then the `AgentEvents`
streams of every alive host (haa.hostd.agentcontrol: each host's kept history, then live). Each event is
kept once (a persisted record and the same event on a stream are one), attributed by
`haa.cluster.events.Merger` (events every member reports for one table change are shown once) and given its
text (`describe`: "A1 (counter) freezing on h4 (to h3)", thesis Fig. 7.1-3); the caller styles and prints it.
`operator_event` makes a line of the caller's own that sorts in with the hosts' events.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

import grpc

from haa.cluster.backend import ALIVE, Backend, agreed_group
from haa.cluster.events import (
    Merger,
    TimelineEvent,
    host_event,
    persisted_logs,
    take_persisted,
    timeline_events,
    view_events,
)
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb


def operator_event(t: float, text: str, kind: str = "operator") -> TimelineEvent:
    """A line of the operator's own, ordered with the hosts' events: a step ("operator": the demo's "▶ h4
    retires: SIGTERM") or a remark on it ("note": an indented line without a clock)."""
    return TimelineEvent(t, "", "", kind, "", text=text)


class EventFeed:
    """The allocation timeline of every host, merged: what the hosts persisted (`load_persisted`), then the
    `AgentEvents` streams of every alive host (each host's kept history first, then live).

    `load_persisted()` reads every host's log — also of hosts that were killed, left or are stopped, and the
    lives before a restart, which no stream can replay (haa.cluster.events). One thread per alive host pushes
    what its stream yields into a queue; an event that a persisted record already holds (the same host, agent,
    event and detail within a second) is dropped. `poll()` returns the events that are at least `delay` seconds
    old in time order, each kept once and attributed by `haa.cluster.events.Merger`, then described. With
    `views`, `poll()` also reports hosts joining and leaving the group (from the members' status, checked every
    second). New hosts are picked up by `connect()` (called by `poll()` every second).
    """

    def __init__(self, backend: Backend, delay: float = 0.6, views: bool = False) -> None:
        self.backend = backend
        self.delay = delay
        self.views = views
        self.q: queue.Queue[tuple[str, cpb.AgentEvent | None]] = queue.Queue()
        self.streams: dict[str, Any] = {}
        self.threads: dict[str, threading.Thread] = {}
        self.ended: dict[str, str] = {}  # host -> why its stream ended
        self.buffer: list[TimelineEvent] = []
        self.seen: set[tuple[str, float, str, str]] = set()
        self.merger = Merger()
        #: (host, agent, event, detail) -> times of the persisted records not matched by a stream event yet
        self.persisted: dict[tuple[str, str, str, str], list[float]] = {}
        self.unreadable: dict[str, str] = {}  # host -> why its persisted log could not be read
        self.members: list[str] | None = None
        self.last_connect = 0.0
        self.last_view = 0.0
        self.received = 0
        self.closed = False
        self.live = False  # streams are opened (`start`) and reopened by `poll`
        self.extra: queue.Queue[TimelineEvent] = queue.Queue()  # lines added by `add()`, from any thread

    def load_persisted(self) -> int:
        """Every host's persisted timeline records (and, with `views`, its view changes) into the buffer;
        returns how many events. Hosts whose logs cannot be read are in `unreadable`."""
        logs = persisted_logs(self.backend, errors=self.unreadable)
        evs = timeline_events(logs)
        for e in evs:
            self.persisted.setdefault((e.host, e.agent, e.event, e.detail), []).append(e.time)
        if self.views:
            evs += view_events(logs)
        self.buffer += evs
        return len(evs)

    def _persisted_already(self, host: str, ev: cpb.AgentEvent) -> bool:
        """Whether a persisted record holds this stream event (a stream replays the host's kept history)."""
        return take_persisted(self.persisted, host, ev.agent, ev.event, ev.detail, ev.time)

    def start(self, settle: float = 0.4, limit: float = 5.0) -> list[str]:
        """Connect to every alive host and take their kept histories (until no event came for `settle` s),
        so that the first `poll()` returns them all in time order. Returns the hosts connected."""
        self.live = True
        hosts = self.connect()
        t = time.monotonic()
        deadline, quiet = t + limit, t
        while hosts and time.monotonic() < deadline:
            n = self.received
            self._take(0.05)
            if self.received != n:
                quiet = time.monotonic()
            elif time.monotonic() - quiet > settle:
                break
        return hosts

    def connect(self) -> list[str]:
        """Open a stream to every alive host that has none; returns the hosts newly connected."""
        self.last_connect = time.monotonic()
        new = []
        for h in self.backend.hosts():
            t = self.threads.get(h.name)
            if h.state != ALIVE or (t is not None and t.is_alive()):
                continue
            c = self.backend.connect(h)
            stream = c.agent_events(history=True)
            self.streams[h.name] = stream
            th = threading.Thread(target=self._pump, args=(h.name, c, stream), daemon=True, name=f"events-{h.name}")
            self.threads[h.name] = th
            th.start()
            new.append(h.name)
        return new

    def _pump(self, host: str, c: ControlClient, stream: Any) -> None:
        try:
            for ev in stream:
                self.q.put((host, ev))
            self.ended[host] = "stream ended"
        except grpc.RpcError as e:
            self.ended[host] = e.code().name if hasattr(e, "code") else str(e)
        finally:
            c.close()
            self.q.put((host, None))

    def close(self) -> None:
        self.closed = True
        for s in self.streams.values():
            s.cancel()
        for t in self.threads.values():
            t.join(2)

    def _take(self, timeout: float) -> None:
        try:
            item: tuple[str, cpb.AgentEvent | None] | None = self.q.get(timeout=timeout)
        except queue.Empty:
            return
        while item is not None:
            host, ev = item
            if ev is not None:
                key = (host, ev.time, ev.agent, ev.event)
                if key not in self.seen:  # a reconnect replays the history
                    self.seen.add(key)
                    self.received += 1
                    if not self._persisted_already(host, ev):
                        self.buffer.append(TimelineEvent(ev.time, ev.agent, ev.name, ev.event, ev.host, ev.detail))
            try:
                item = self.q.get_nowait()
            except queue.Empty:
                item = None

    def _views(self) -> list[TimelineEvent]:
        self.last_view = time.monotonic()
        replies = self.backend.statuses()
        ok = {n: r for n, r in replies.items() if isinstance(r, cpb.StatusReply)}
        members, _, _ = agreed_group(ok)
        if not members:
            return []
        now = time.time()
        evs: list[TimelineEvent] = []
        if self.members is not None:
            evs += [host_event(now, m, "joined") for m in members if m not in self.members]
            evs += [host_event(now, m, "removed") for m in self.members if m not in members]
        self.members = members
        return evs

    def add(self, e: TimelineEvent) -> None:
        """Show a line of the caller's (already described: `e.text`) in time order with the hosts' events, which
        reach us up to `delay` s late; callable from any thread."""
        self.extra.put(e)

    def poll(self, timeout: float = 0.2, flush: bool = False) -> list[TimelineEvent]:
        """Events ready to show (all of them with `flush`), in time order."""
        self._take(timeout)
        while True:
            try:
                self.buffer.append(self.extra.get_nowait())
            except queue.Empty:
                break
        if self.live and time.monotonic() - self.last_connect > 1.0:
            self.connect()
        if self.views and self.live and time.monotonic() - self.last_view > 1.0:
            self.buffer += self._views()
        cut = time.time() - self.delay
        self.buffer.sort(key=lambda e: e.time)
        ready = [e for e in self.buffer if flush or e.time <= cut]
        self.buffer = [e for e in self.buffer if not (flush or e.time <= cut)]
        shown = []
        for e in ready:
            if self.describe(e, ready):
                shown.append(e)
        return shown

    def describe(self, e: TimelineEvent, batch: list[TimelineEvent]) -> bool:
        """Fill `e.text`; False if the event repeats one already shown (a table event of another member).
        Who did what where is `Merger`'s (haa.cluster.events): a table-level crash is shown on the host that
        ran the agent, "reported by" the member whose log has it."""
        if not e.agent:
            return True  # a host line, already described
        if not self.merger.take(e, (*batch, *self.buffer)):
            return False
        kind = e.event
        who = f"{e.name} ({e.type})" if e.type else e.name
        d = e.detail
        if kind == "created":
            parent = e.name.rsplit(".", 1)[0] if "." in e.name else ""
            text = f"{who} requested by {parent if parent else 'the operator'}"
        elif kind == "spawning":
            text = f"{who} spawning on {e.host}"
        elif kind == "active":
            text = f"{who} spawned by {e.host}"
        elif kind == "freezing":
            text = f"{who} freezing on {e.host}" + (f" ({d})" if d and d != f"to {e.host}" else "")
        elif kind == "frozen":
            text = f"{who} frozen on {e.host}"
        elif kind == "thawing":
            text = f"{who} thawing on {e.host}"
        elif kind == "thawed":
            if d.startswith("1 queued messages"):
                d = "1 queued message"
            text = f"{who} thawed by {e.host}" + (f" ({d})" if d and not d.startswith("0 ") else "")
        elif kind == "crashed":
            if d:
                text = f"{who} crashed on {e.host}: {d}"
            else:
                text = f"{who} crashed" + (f" on {e.host}" if e.host else "")
                text += f" (reported by {e.reporter})" if e.reporter else ""
        elif kind == "recovering":
            text = f"{who} recovering on {e.host}"
        elif kind == "recovered":
            text = f"{who} recovered by {e.host}" + (f" ({d})" if d else "")
        elif kind == "removed":
            text = f"{who} removed"
        elif kind == "backoff":
            text = f"{who} could not start: {d}"
        elif kind == "failed":
            text = f"{who} failed, not recovered any more: {d}"
        else:
            text = f"{who} {kind} on {e.host}" + (f" ({d})" if d else "")
        e.text = text
        return True
