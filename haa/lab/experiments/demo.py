"""The demo scenario (`haactl demo`, `make demo`): agents live on a local cluster while hosts join, retire and crash.

A local cluster of real `haa-hostd` processes (haa.cluster.local_backend: three core hosts, a fourth joins
later) runs three pairs of `counter` agents (haa.lab.demoagents: each agent pings its peer with numbered
messages every 50 ms and checks what it receives: lost, out of order, duplicate). Then a scripted scenario,
each step waiting for its effect:

1. a host joins the group (the allocation rebalances onto it: agents freeze on their host, thaw on h4);
2. an operator move of one agent (`haactl agent move`);
3. a graceful leave of a host running agents (SIGTERM: its agents are frozen and handed over, thesis AF-1);
4. an agent process killed with SIGKILL on its host (`haactl agent kill`: recovered from its last backup);
5. a host crash (SIGKILL of a haa-hostd running agents: its agents are recovered elsewhere, Alg. 7-8);
6. quiet.

While it runs, the allocation timeline of every host is merged and printed as it happens in the style of
the thesis' transcript (Fig. 7.1-3): "00:51 A1 (counter) freezing on h4 (to h3)", "00:53 A1 (counter) thawed
by h3" (haa.cluster.feed.EventFeed), with hosts joining and being removed and the operator's actions.

Checks. Every counter publishes its counters to DDB key `demo/<name>`. At the end the demo takes a first
snapshot, then waits until every receiver has taken every message its peer had sent by that snapshot
(the operator API has no request path to agents, so the pingers cannot be paused from here: this catch-up
is the "everything sent has arrived" condition), and prints

    messages lost: N, order violations: N, duplicate agents: N

where lost counts numbers skipped and never filled (`lost`, plus messages that never arrived by the end),
order violations = out_of_order + duplicate, and duplicate agents counts moments where two hosts ran the
same agent: (a) a sampler asks every host's AgentList every 0.5 s and flags an agent whose instance is
active on two hosts in the same round, (b) the merged timeline is replayed as per-host activity intervals
(active/thawed/recovered .. freezing/crashed/host gone) and any overlap is flagged. Messages a recovered
agent lost since its last backup are lost by design (Alg. 8 restores the latest backup, no more) and are
printed separately as "lost to recovery (by design)". The exit code is 0 only if all three numbers are 0.

`Demo.run()` returns a `DemoResult` (the counters, the checks' findings, `ok`); the timeline goes to the
`show` callback as it happens (each `TimelineEvent`: the hosts' events and the operator's lines) and a
duplicate agent seen by the sampler to `alert`, so that haactl/demo.py prints them (moved here from there:
haactl parses and prints).
"""

from __future__ import annotations

import contextlib
import json
import random
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from haa.cluster.agents import AgentRow, merge_agents
from haa.cluster.backend import ALIVE, ClusterError, Formation, agreed_group
from haa.cluster.events import TimelineEvent, host_event
from haa.cluster.feed import EventFeed, operator_event
from haa.cluster.local_backend import LocalBackend
from haa.cluster.values import plain_value
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb

COUNTER_CONFIG = {"spawn_peer": True, "period": 0.05, "backup_every": 20}
#: counters of `haa.lab.demoagents.CounterAgent.stats()` summed in the report
COUNTS = ("sent", "received", "lost", "out_of_order", "duplicate", "lost_after_recovery", "resent_after_recovery",
          "stale", "thaws", "recoveries")
#: their column headers
HEADERS = ("sent", "received", "lost", "out of order", "duplicate", "lost (recovery)", "resent (recovery)", "stale",
           "thaws", "recoveries")


@dataclass(frozen=True)
class Pace:
    """Seconds between the scenario's steps (`--quick` compresses them)."""

    settle: float = 3.0  # after the pairs are active
    after_join: float = 4.0
    after_move: float = 3.0
    after_leave: float = 3.0
    after_kill: float = 3.0
    quiet: float = 8.0


FULL = Pace()
QUICK = Pace(settle=1.0, after_join=1.5, after_move=1.0, after_leave=1.0, after_kill=1.0, quiet=2.0)


@dataclass
class Checks:
    """What the sampler and the timeline found (the "duplicate agents" evidence)."""

    samples: int = 0
    sampled_dups: list[tuple[float, str, tuple[str, ...]]] = field(default_factory=list)
    overlap_dups: list[tuple[float, str, str, str]] = field(default_factory=list)
    events: list[TimelineEvent] = field(default_factory=list)


@dataclass
class DemoResult:
    """The end of a run: every counter's last published counters, the streams still behind and the messages
    they miss, the checks' findings, the agents' hosts at the end; `ok` when nothing was lost, reordered or
    run twice."""

    counters: dict[str, dict[str, Any]]
    hosts: dict[str, str]  # agent -> host at the end
    expected: int  # counters expected (2 per pair)
    behind: list[str]
    missing: int
    overlaps: list[tuple[float, str, str, str]]  # (time, agent, host, other host) from the timeline
    checks: Checks

    def total(self) -> dict[str, int]:
        """Every counter of `COUNTS` summed over the agents."""
        total = dict.fromkeys(COUNTS, 0)
        for s in self.counters.values():
            for k in COUNTS:
                total[k] += int(s.get(k, 0))
        return total

    @property
    def lost(self) -> int:
        return self.total()["lost"] + self.missing

    @property
    def order_violations(self) -> int:
        t = self.total()
        return t["out_of_order"] + t["duplicate"]

    @property
    def duplicates(self) -> int:
        return len(self.checks.sampled_dups) + len(self.overlaps)

    @property
    def ok(self) -> bool:
        clean = self.lost == 0 and self.order_violations == 0 and self.duplicates == 0
        return clean and len(self.counters) == self.expected


class Demo:
    """The scenario (module docstring) on one local cluster."""

    def __init__(self, root: Path, quick: bool, seed: int, pairs: int,
                 show: Callable[[TimelineEvent], None] = lambda e: None,
                 alert: Callable[[str], None] = lambda text: None) -> None:
        """`show`: each line of the timeline as it happens (in time order, one at a time); `alert`: a
        duplicate agent seen by the sampler (a line with its clock)."""
        self.root = root
        self.show = show
        self.alert = alert
        self.pace = QUICK if quick else FULL
        self.rng = random.Random(seed)
        self.pairs = pairs
        self.backend = LocalBackend(root)
        self.t0 = 0.0
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.checks = Checks()
        self.host_gone: dict[str, float] = {}  # host -> time it was killed / left (ends its agents' intervals)
        self.feed: EventFeed | None = None
        self.threads: list[threading.Thread] = []

    # ------------------------------------------------------------------ output

    def clock(self, t: float | None = None) -> str:
        s = max(0, int((t if t is not None else time.time()) - self.t0))
        return f"{s // 60:02d}:{s % 60:02d}"

    def say(self, text: str, kind: str = "operator") -> None:
        """An operator line. Once the timeline runs it goes through it: the hosts' events reach us up to the
        feed's delay late, and printed at once the line could come before an event stamped earlier."""
        e = operator_event(time.time(), text, kind)
        if self.feed is not None and not self.stop.is_set():
            self.feed.add(e)
            return
        with self.lock:
            self.show(e)

    def note(self, text: str) -> None:
        """A remark on the last step (indented, no clock), in order with it (`say`)."""
        self.say(text, "note")

    # ------------------------------------------------------------------ cluster access

    def client(self, name: str, timeout: float = 5.0) -> ControlClient:
        return self.backend.connect(self.backend.host(name), timeout)

    def alive(self) -> list[str]:
        return [h.name for h in self.backend.hosts() if h.state == ALIVE]

    def lists(self, timeout: float = 3.0) -> dict[str, cpb.AgentListReply]:
        names = self.alive()

        def one(n: str) -> tuple[str, cpb.AgentListReply | None]:
            c = self.client(n, timeout)
            try:
                return n, c.agent_list()
            except grpc.RpcError:
                return n, None
            finally:
                c.close()

        with ThreadPoolExecutor(max_workers=max(1, len(names))) as pool:
            return {n: r for n, r in pool.map(one, names) if r is not None}

    def rows(self) -> list[AgentRow]:
        return merge_agents(self.lists())

    def session(self, full: bool = False) -> Any:
        """The last allocation session the leader committed (and, with `full`, the last finished one)."""
        c = self.client(self.leader())
        try:
            r = c.alloc("status", timeout=5)
        finally:
            c.close()
        return (r.session, r.finished_session) if full else r.session

    def leader(self) -> str:
        replies = {n: r for n, r in self.backend.statuses().items() if isinstance(r, cpb.StatusReply)}
        return agreed_group(replies)[1]

    def wait(self, pred: Callable[[], Any], timeout: float, what: str) -> Any:
        deadline = time.monotonic() + timeout
        while True:
            try:
                v = pred()
                if v:
                    return v
            except grpc.RpcError:
                pass
            if time.monotonic() > deadline:
                raise ClusterError(f"timed out after {timeout:g} s waiting for {what}")
            time.sleep(0.1)

    def all_active(self, n: int | None = None) -> list[AgentRow] | None:
        rows = self.rows()
        if n is not None and len(rows) != n:
            return None
        return rows if rows and all(r.state == "active" for r in rows) else None

    def members(self) -> list[str]:
        replies = {n: r for n, r in self.backend.statuses().items() if isinstance(r, cpb.StatusReply)}
        return agreed_group(replies)[0]

    def by_host(self, rows: list[AgentRow]) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {h: [] for h in self.members()}
        for r in rows:
            out.setdefault(r.host, []).append(r.name)
        return out

    # ------------------------------------------------------------------ background: timeline and sampler

    def _printer(self) -> None:
        assert self.feed is not None
        while not self.stop.is_set():
            self._show(self.feed.poll(0.2))
        self._show(self.feed.poll(0.3, flush=True))

    def _show(self, evs: list[TimelineEvent]) -> None:
        if not evs:
            return
        with self.lock:
            for e in evs:
                if e.event not in ("operator", "note"):
                    self.checks.events.append(e)
                self.show(e)

    def _sampler(self) -> None:
        while not self.stop.wait(0.5):
            try:
                lists = self.lists(timeout=2.0)
            except Exception:  # a host going away mid-call: next round
                continue
            self.checks.samples += 1
            running: dict[str, list[str]] = {}
            names: dict[str, str] = {}
            for host, reply in lists.items():
                for a in reply.agents:
                    names[a.id] = a.name
                    if a.local_phase == "active":
                        running.setdefault(a.id, []).append(host)
            for agent, hosts in running.items():
                if len(hosts) > 1:
                    self.checks.sampled_dups.append((time.time(), names[agent], tuple(sorted(hosts))))
                    with self.lock:
                        self.alert(f"{self.clock()} DUPLICATE: {names[agent]} active on {', '.join(sorted(hosts))}")

    # ------------------------------------------------------------------ the scenario

    def run(self) -> DemoResult:
        b = self.backend
        self.t0 = time.time()
        self.say("h1, h2, h3 start (core hosts)")
        b.up(3, 3)

        def formed() -> Formation | None:
            b.check_started()
            f = b.formation(["h1", "h2", "h3"])
            return f if f.done else None

        f = self.wait(formed, 90, "the group to form")
        with self.lock:
            for m in f.members:
                self.show(host_event(time.time(), m, "joined"))
        self.feed = EventFeed(b, views=True)
        self.feed.members = list(f.members)
        self.feed.start()
        self.threads = [threading.Thread(target=self._printer, daemon=True, name="demo-timeline"),
                        threading.Thread(target=self._sampler, daemon=True, name="demo-sampler")]
        for t in self.threads:
            t.start()
        try:
            self.scenario()
            return self.finish()
        finally:
            self.stop.set()
            for t in self.threads:
                t.join(5)
            if self.feed is not None:
                self.feed.close()

    def scenario(self) -> None:
        b, p = self.backend, self.pace
        # spawn the pairs
        self.say(f"operator: spawn {self.pairs} counter pairs {json.dumps(COUNTER_CONFIG)}")
        c = self.client("h1", 15)
        for _ in range(self.pairs):
            r = c.agent_spawn("counter", json.dumps(COUNTER_CONFIG).encode(), timeout=15)
            if not r.ok:
                raise ClusterError(f"spawn counter: {r.reason}")
        c.close()
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 60, "every counter agent to be active")
        self.note("agents per host: " + self.placement(rows))
        time.sleep(p.settle)

        # 1. a host joins
        self.say("h4 starts and joins the group (the allocation rebalances)")
        session = self.session()
        b.add("h4")
        def h4_joined() -> bool:
            b.check_started()
            return b.rejoined("h4").done

        self.wait(h4_joined, 60, "h4 to join")
        # the membership change starts an allocation session (Alg. 4 l. 17); wait until it has finished
        with contextlib.suppress(ClusterError):
            self.wait(lambda: (s := self.session(full=True))[0] > session and s[1] >= s[0], 10, "a session")
        time.sleep(p.after_join)
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active")
        self.note("agents per host: " + self.placement(rows))

        # 2. an operator move
        load = self.by_host(rows)
        agent = rows[0]
        to = min((h for h in load if h != agent.host), key=lambda h: (len(load[h]), h))
        self.say(f"operator: haactl agent move {agent.name} {to}")
        c = self.client(self.alive()[0], 15)
        r = c.agent_move(agent.name, to, timeout=15)
        c.close()
        if not r.ok:
            raise ClusterError(f"move {agent.name} {to}: {r.reason}")
        self.wait(lambda: any(x.id == agent.id and x.host == to and x.state == "active" for x in self.rows()), 30,
                  f"{agent.name} active on {to}")
        time.sleep(p.after_move)

        # 3. a graceful leave of a host running agents (not the leader)
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active")
        leader = self.leader()
        load = self.by_host(rows)
        leaver = max((h for h in load if h != leader), key=lambda h: (len(load[h]), h))
        self.say(f"{leaver} retires: SIGTERM (graceful leave; its agents {', '.join(load[leaver]) or 'none'} "
                 "are handed over)")
        t = time.monotonic()
        b.terminate(leaver, 30)
        self.host_gone[leaver] = time.time()
        if b.host(leaver).up:
            raise ClusterError(f"{leaver} is still running 30 s after SIGTERM")
        b.mark_left(leaver)
        self.note(f"{leaver} exited {time.monotonic() - t:.1f} s after SIGTERM")
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active after the leave")
        time.sleep(p.after_leave)

        # 4. an agent process killed
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active")
        victim = self.rng.choice(rows)
        self.say(f"operator: haactl agent kill {victim.name} (SIGKILL of its process on {victim.host})")
        c = self.client(victim.host, 10)
        r = c.agent_kill(victim.id)
        c.close()
        if not r.ok:
            raise ClusterError(f"kill {victim.name}: {r.reason}")
        self.wait(lambda: any(x.id == victim.id and x.state == "active" and x.epoch > victim.epoch
                              for x in self.rows()), 30, f"{victim.name} to be recovered")
        time.sleep(p.after_kill)

        # 5. a host crash (not the leader)
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active")
        leader = self.leader()
        load = self.by_host(rows)
        crash = max((h for h in load if h != leader), key=lambda h: (len(load[h]), h))
        self.say(f"{crash} crashes: SIGKILL of its haa-hostd (agents {', '.join(load[crash]) or 'none'})")
        b.kill(crash)
        self.host_gone[crash] = time.time()
        self.wait(lambda: (rows := self.all_active(2 * self.pairs)) and all(r.host != crash for r in rows), 60,
                  f"the agents of {crash} to be recovered elsewhere")

        # 6. quiet
        time.sleep(1.0)  # the timeline shows an event 0.6 s after it happened
        self.say(f"quiet for {p.quiet:g} s")
        time.sleep(p.quiet)

    @staticmethod
    def placement(rows: list[AgentRow]) -> str:
        hosts: dict[str, list[str]] = {}
        for r in rows:
            hosts.setdefault(r.host, []).append(r.name)
        return "; ".join(f"{h}: {' '.join(v)}" for h, v in sorted(hosts.items()))

    # ------------------------------------------------------------------ the end: accounting

    def stats(self) -> dict[str, dict[str, Any]]:
        """Every counter's latest published counters (DDB `demo/<name>`), read from one alive member."""
        for n in self.alive():
            c = self.client(n)
            try:
                reply = c.ddb_get(prefix="demo/")
            except grpc.RpcError:
                continue
            finally:
                c.close()
            out = {}
            for o in reply.objects:
                v = plain_value(o.type, o.value)
                if isinstance(v, dict):
                    out[o.key.removeprefix("demo/")] = v
            return out
        raise ClusterError("no alive host answers DdbGet")

    def catch_up(self, timeout: float = 30.0) -> tuple[dict[str, dict[str, Any]], list[str], int]:
        """Wait until every receiver has taken what its peer had sent at a first snapshot. Returns the last
        snapshot, the streams still behind at the timeout and how many messages they miss."""
        first = self.stats()
        deadline = time.monotonic() + timeout
        while True:
            time.sleep(1.0)
            last = self.stats()
            behind, missing = [], 0
            for name, s in first.items():
                peer = next((p for p in last.values() if p.get("id") == s.get("peer")), None)
                if peer is None:
                    behind.append(f"{name}: peer {str(s.get('peer'))[:8]} publishes nothing")
                    continue
                st = peer.get("streams", {}).get(s["id"])
                now = last.get(name, s)
                if now.get("gen") != s.get("gen"):  # the sender was recovered meanwhile: a new baseline
                    first[name] = now
                    behind.append(f"{name}: recovered meanwhile")
                    continue
                if st is None or st["gen"] < s["gen"] or st["expected"] < s["next_seq"]:
                    got = 0 if st is None or st["gen"] < s["gen"] else st["expected"]
                    behind.append(f"{name} -> {peer['name']}: {got}/{s['next_seq']}")
                    missing += s["next_seq"] - max(got, 1)
            if not behind:
                return last, [], 0
            if time.monotonic() > deadline:
                return last, behind, missing

    def overlaps(self) -> list[tuple[float, str, str, str]]:
        """Replay the timeline as per-host activity intervals; any two that overlap are a duplicate agent."""
        open_on: dict[str, dict[str, float]] = {}  # agent -> host -> since
        names: dict[str, str] = {}
        dups: list[tuple[float, str, str, str]] = []
        events = sorted(self.checks.events, key=lambda e: e.time)
        gone = sorted(self.host_gone.items(), key=lambda kv: kv[1])
        gi = 0
        for e in events:
            while gi < len(gone) and gone[gi][1] <= e.time:
                for hosts in open_on.values():
                    hosts.pop(gone[gi][0], None)
                gi += 1
            if not e.agent:
                continue
            names[e.agent] = e.name
            hosts = open_on.setdefault(e.agent, {})
            if e.event in ("active", "thawed", "recovered"):
                for h in hosts:
                    if h != e.host:
                        dups.append((e.time, e.name, h, e.host))
                hosts[e.host] = e.time
            elif e.event in ("freezing", "frozen") or (e.event == "crashed" and e.detail):
                hosts.pop(e.host, None)
            elif e.event in ("crashed", "removed"):  # the table says so: no instance is valid any more
                hosts.clear()
        return dups

    def finish(self) -> DemoResult:
        self.say("checking: every message sent has arrived (catch-up of every stream), then the counters")
        rows = self.wait(lambda: self.all_active(2 * self.pairs), 30, "every agent active")
        last, behind, missing = self.catch_up()
        self.stop.set()
        for t in self.threads:
            t.join(5)
        overlap = self.overlaps()
        self.checks.overlap_dups = overlap
        return DemoResult(counters=last, hosts={r.name: r.host for r in rows}, expected=2 * self.pairs,
                          behind=behind, missing=missing, overlaps=overlap, checks=self.checks)
