"""The simulated cluster: N `HostCore`s, one virtual clock, one seeded network.

* Virtual time is global; every host reads its own local clock `offset + (1 + drift) * t` (clocks are not
  synchronized, thesis §4.3.1), and its timers are set in local time.
* One reliable FIFO channel per ordered host pair: each message gets a delay from the `DelayModel` plus any
  active delay spike, and never arrives before a message sent earlier on the same pair.
* Faults: crash (optionally in the middle of a step, so that only a prefix of that step's sends leaves —
  a broadcast cut short), pause (the process stops; messages and timers wait and are processed late on
  resume, exactly like SIGSTOP), restart as a new incarnation, delay spikes on a channel or a host, and — in
  external failure-detector mode — suspicions injected by an adversarial model.
* Everything is recorded in a `History` that `haa.lab.dsim.checks` verifies; every processed event also
  feeds a running trace hash, so the same seed must give the same hash.
"""

from __future__ import annotations

import functools
import hashlib
import random
from collections import Counter
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from haa.core.agents.agentnode import AgentNode
from haa.core.effects import (
    CancelTimer,
    Closed,
    Decided,
    Deliver,
    Log,
    PeerDead,
    Reincarnate,
    Send,
    SetTimer,
    Suspicion,
    Voted,
)
from haa.core.host.hostcore import FD_EXTERNAL, CoreConfig, HostCore
from haa.core.inputs import FdReport, PeerInfo, Receive, Start, TimerFired
from haa.core.messages import OAC_TYPES, Heartbeat, TxId
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.scheduler import EventHeap

Proc = tuple[str, int]  # (host name, incarnation): one process life


class SimCore(Protocol):
    """What a simulated host's core must offer the cluster: a `HostCore` (the default), a `MembershipNode`
    (haa.lab.dsim.group) or an `AgentNode` (haa.lab.dsim.agents) — inputs in by `step` (`haa.core.inputs`), effects
    drained out. The cluster handles the `HostCore` effects itself and hands any other effect to
    `SimCluster.on_effect`."""

    def step(self, now: float, inp: Any) -> object: ...
    def drain(self) -> Sequence[object]: ...

    @property
    def peers(self) -> Mapping[str, Any]: ...

    @property
    def oac(self) -> Any: ...

EV_MSG = 0
EV_TIMER = 1
EV_CALL = 2

ALIVE = 0
PAUSED = 1
CRASHED = 2


#: core Log events that report a bug caught by a safety net (haa.core.agents.agentnode): violations in every sweep
ERROR_EVENTS = frozenset({"agent_layer_error"})

#: a message whose own delay draw is at least this long is recorded (`History.late`): rare with every delay
#: model the schedules use but the heavy-tailed ones, where one draw in ~10^8 holds a channel for seconds
LATE_MESSAGE = 0.25

@dataclass
class Proposal:
    proposer: Proc
    participants: tuple[Proc, ...]
    payload: bytes
    time: float


@dataclass
class History:
    """What happened, for the property checkers."""

    proposals: dict[TxId, Proposal] = field(default_factory=dict)
    votes: dict[TxId, dict[Proc, bool]] = field(default_factory=dict)
    decided: dict[Proc, dict[TxId, tuple[bool, float]]] = field(default_factory=dict)
    delivered: dict[Proc, list[tuple[TxId, int, bytes, float]]] = field(default_factory=dict)
    closed: dict[Proc, set[TxId]] = field(default_factory=dict)
    # (time, observer, target, suspected)
    suspicions: list[tuple[float, Proc, Proc, bool]] = field(default_factory=list)
    crash_time: dict[Proc, float] = field(default_factory=dict)  # crash (or pause-then-crash start)
    excluded: dict[Proc, float] = field(default_factory=dict)  # first exclusion by any host
    excluded_by: dict[Proc, Proc] = field(default_factory=dict)  # ... and by whom
    #: (src host, dst host) -> (sent, arrival) of each message whose own random delay (not an injected spike)
    #: was at least LATE_MESSAGE: on a FIFO channel it holds back everything sent after it (a heavy tail's
    #: performance failure, which an accuracy property cannot be asked to survive)
    late: dict[tuple[str, str], list[tuple[float, float]]] = field(default_factory=dict)
    ended: dict[Proc, float] = field(default_factory=dict)  # life ended (crash, restart, reincarnation)
    started: dict[Proc, float] = field(default_factory=dict)
    pauses: list[tuple[str, float, float]] = field(default_factory=list)  # (host, start, end)
    # (time, observer, target, reason): the observer marked the target incarnation permanently suspected
    dead_marks: list[tuple[float, Proc, Proc, str]] = field(default_factory=list)
    #: Log events of the safety nets that catch a bug instead of crashing the host (`agent_layer_error`): a
    #: checker reports each as a violation, so the nets do not hide bugs from the verifiers
    core_errors: list[tuple[float, Proc, str, str]] = field(default_factory=list)
    # (observer, crashed target) -> the observer's estimate of E(D) after the last heartbeat it received
    # from the target (the detection-time bound of eq. 4.4-2 is T_D^U + that estimate)
    ed_hat: dict[tuple[Proc, Proc], float] = field(default_factory=dict)
    rejected_proposals: int = 0

    def faulty(self) -> set[Proc]:
        return set(self.crash_time) | set(self.excluded) | set(self.ended)

    def correct(self) -> set[Proc]:
        bad = self.faulty()
        return {p for p in self.started if p not in bad}


class SimHost:
    __slots__ = (
        "backlog",
        "core",
        "crash_pending",
        "drift",
        "idx",
        "inc",
        "name",
        "offset",
        "pause_started",
        "state",
        "timers",
    )

    def __init__(self, name: str, idx: int, offset: float, drift: float) -> None:
        self.name = name
        self.idx = idx
        self.offset = offset
        self.drift = drift
        self.inc = 0
        self.core: SimCore | None = None
        self.state = ALIVE
        self.timers: dict[Hashable, int] = {}
        self.backlog: list[tuple[int, Any]] = []
        self.crash_pending: float | None = None
        self.pause_started = 0.0

    @property
    def live_core(self) -> SimCore:
        """The core of a host that has one (alive or paused); a crashed host has none."""
        core = self.core
        if core is None:
            raise RuntimeError(f"{self.name}#{self.inc} has no core (crashed)")
        return core

    @property
    def membership(self) -> Any:
        """The membership node of the host's core: an `AgentNode`'s `m`, else the core itself (None if crashed)."""
        core = self.core
        return core.m if isinstance(core, AgentNode) else core

    def local(self, t: float) -> float:
        return self.offset + (1.0 + self.drift) * t

    def virtual(self, local: float) -> float:
        return (local - self.offset) / (1.0 + self.drift)


class SimCluster:
    """Runs host cores on a virtual clock; see the module docstring."""

    def __init__(
        self,
        names: list[str],
        rng: random.Random,
        delay: DelayModel,
        config: CoreConfig,
        offsets: list[float] | None = None,
        drifts: list[float] | None = None,
        no_votes: set[tuple[bytes, str]] | None = None,
        trace: bool = False,
    ) -> None:
        self.names = list(names)
        self.rng = rng
        self.net_rng = random.Random(rng.random())
        self.delay = delay
        self.config = config
        self.hosts: dict[str, SimHost] = {}
        for i, n in enumerate(self.names):
            off = offsets[i] if offsets else 0.0
            dr = drifts[i] if drifts else 0.0
            self.hosts[n] = SimHost(n, i, off, dr)
        self.by_idx = [self.hosts[n] for n in self.names]
        self.no_votes = no_votes or set()
        #: the pending events (haa.lab.dsim.scheduler): items (kind, host index, data); EV_CALL items carry a
        #: callable and index -1
        self.heap: EventHeap[tuple[int, int, Any]] = EventHeap()
        self.now = 0.0
        self.chan_last: dict[tuple[int, int], float] = {}
        self.spikes: list[tuple[int, int, DelayModel, float, float]] = []  # (src|-1, dst|-1, extra, t0, t1)
        #: asked when an armed mid-step crash is about to fire (`crash(mid_step=True)`): False calls it off
        self.may_crash: Callable[[str], bool] | None = None
        self.history = History()
        self.msg_counts: Counter[str] = Counter()
        self.oac_in_flight = 0
        self.events = 0
        self._hash = hashlib.blake2b(digest_size=16)
        self.trace: list[str] | None = [] if trace else None
        self.external = config.fd_mode == FD_EXTERNAL
        self.on_restart: Callable[[str, int], None] | None = None
        #: builds the state machine a host boots (default: a `HostCore` over the static host list); it must
        #: offer HostCore's inputs, `drain()`, `peers` and `oac`, and record its votes in `history.votes`
        self.make_core: Callable[[SimHost, int], SimCore] | None = None
        #: receives effects this class does not know (those of a `MembershipNode`)
        self.on_effect: Callable[[SimHost, Any], None] | None = None

    # ------------------------------------------------------------------ set-up

    def start_all(self) -> None:
        for h in self.by_idx:  # everyone boots at t = 0 as incarnation 1
            h.inc = 1
        for h in self.by_idx:
            self._boot(h, 1)

    def _boot(self, h: SimHost, inc: int) -> None:
        h.inc = inc
        h.state = ALIVE
        h.timers = {}
        h.backlog = []
        h.crash_pending = None
        name = h.name

        core: SimCore
        if self.make_core is not None:
            core = self.make_core(h, inc)
        else:
            known = {n: self.hosts[n].inc for n in self.names if self.hosts[n].inc} if self.external else None
            no = [payload for payload, who in self.no_votes if who == name]
            core = HostCore(name, inc, self.names, self.config, no_votes=no, known_incs=known)
        h.core = core
        proc = (name, inc)
        self.history.started[proc] = self.now
        self.history.decided[proc] = {}
        self.history.delivered[proc] = []
        self.history.closed[proc] = set()
        core.step(h.local(self.now), Start())
        self._apply(h)
        self._note(f"boot {name}#{inc}")

    # ------------------------------------------------------------------ scheduling

    def _push(self, t: float, kind: int, idx: int, data: Any) -> None:
        self.heap.push(t, (kind, idx, data))

    def at(self, t: float, fn: Callable[[], object]) -> None:
        self._push(max(t, self.now), EV_CALL, -1, fn)

    # ------------------------------------------------------------------ faults and inputs

    def crash(self, name: str, mid_step: bool = False) -> None:
        h = self.hosts[name]
        if h.state == CRASHED:
            return
        if mid_step and h.state == ALIVE:
            # crash in the middle of the next broadcast (a step with two or more sends); if none comes
            # soon, crash anyway
            h.crash_pending = self.rng.random()
            inc = h.inc

            def fallback() -> None:
                if h.inc == inc and h.crash_pending is not None and h.state != CRASHED and self._still_may_crash(h):
                    self._crash_now(h)

            self.at(self.now + 0.1, fallback)
            return
        self._crash_now(h)

    def _still_may_crash(self, h: SimHost) -> bool:
        """An armed mid-step crash fires only if the owner's `may_crash` still allows it then (up to 0.1 s after
        it was armed a transaction may have begun that the crash would leave without a correct majority);
        otherwise it is called off."""
        if self.may_crash is None or self.may_crash(h.name):
            return True
        h.crash_pending = None
        self._note(f"crash-mid-step {h.name}#{h.inc} called off (assumptions)")
        return False

    def _crash_now(self, h: SimHost) -> None:
        h.crash_pending = None
        proc = (h.name, h.inc)
        start = h.pause_started if h.state == PAUSED else self.now
        h.state = CRASHED
        h.core = None
        h.timers = {}
        for kind, data in h.backlog:
            if kind == EV_MSG and type(data[3]) in OAC_TYPES:
                self.oac_in_flight -= 1
        h.backlog = []
        self.history.crash_time.setdefault(proc, start)
        self.history.ended.setdefault(proc, self.now)
        if not self.external:
            for obs in self.by_idx:
                if obs.core is not None and obs is not h:
                    self._record_ed_hat(obs, h.name, proc[1])
        self._note(f"crash {h.name}#{h.inc}")

    def pause(self, name: str) -> None:
        h = self.hosts[name]
        if h.state == ALIVE:
            h.state = PAUSED
            h.pause_started = self.now
            self._note(f"pause {name}#{h.inc}")

    def resume(self, name: str) -> None:
        h = self.hosts[name]
        if h.state != PAUSED:
            return
        h.state = ALIVE
        self.history.pauses.append((name, h.pause_started, self.now))
        backlog, h.backlog = h.backlog, []
        for kind, data in backlog:  # processed late, in their original order
            self._push(self.now, kind, h.idx, data)
        self._note(f"resume {name}#{h.inc}")

    def restart(self, name: str) -> None:
        """Crash (if needed) and boot a new incarnation."""
        h = self.hosts[name]
        if h.state != CRASHED:
            self._crash_now(h)
        self._boot(h, h.inc + 1)
        if self.on_restart:
            self.on_restart(name, h.inc)

    def spike(self, src: str | None, dst: str | None, extra: DelayModel, duration: float) -> None:
        si = self.hosts[src].idx if src else -1
        di = self.hosts[dst].idx if dst else -1
        self.spikes.append((si, di, extra, self.now, self.now + duration))
        self._note(f"spike {src or '*'}->{dst or '*'} {extra.describe()} for {duration:.3f}s")

    def suspect(self, observer: str, target: str, suspected: bool) -> None:
        """External failure detector output at `observer` about `target`."""
        h = self.hosts[observer]
        if h.state != ALIVE or h.core is None:
            if h.state == PAUSED:
                h.backlog.append((EV_CALL, lambda: self.suspect(observer, target, suspected)))
            return
        h.core.step(h.local(self.now), FdReport(target, suspected))
        self._apply(h)

    def peer_info(self, observer: str, target: str, inc: int) -> None:
        h = self.hosts[observer]
        if h.state != ALIVE or h.core is None:
            if h.state == PAUSED:
                h.backlog.append((EV_CALL, lambda: self.peer_info(observer, target, inc)))
            return
        h.core.step(h.local(self.now), PeerInfo(target, inc))
        self._apply(h)

    def propose(self, name: str, payload: bytes, participants: list[str] | None) -> TxId | None:
        h = self.hosts[name]
        if h.state != ALIVE or h.core is None:
            if h.state == PAUSED:
                h.backlog.append((EV_CALL, lambda: self.propose(name, payload, participants)))
            return None
        core = h.core
        if not isinstance(core, HostCore):
            raise TypeError(f"propose: {name}'s core is a {type(core).__name__}, not a HostCore")
        try:
            txid = core.propose(h.local(self.now), payload, participants)
        except ValueError:
            self.history.rejected_proposals += 1
            return None
        tx = core.oac.txs.get(txid)
        parts = tx.parts if tx is not None else ()
        self.history.proposals[txid] = Proposal((name, h.inc), tuple(parts), payload, self.now)
        self._note(f"propose {txid} by {name}#{h.inc} to {[f'{q}#{i}' for q, i in parts]}")
        self._apply(h)
        return txid

    # ------------------------------------------------------------------ the event loop

    def run(self, until: float) -> None:
        heap = self.heap
        entries = heap.entries
        pop = heap.pop
        hosts = self.by_idx
        upd = self._hash.update
        while entries and entries[0][0] <= until:
            t, _seq, (kind, idx, data) = pop()
            self.now = t
            self.events += 1
            if kind == EV_CALL:
                data()
                continue
            h = hosts[idx]
            if h.state != ALIVE:
                if h.state == PAUSED:
                    h.backlog.append((kind, data))
                elif kind == EV_MSG and type(data[3]) in OAC_TYPES:
                    self.oac_in_flight -= 1
                continue
            core = h.live_core  # alive
            if kind == EV_MSG:
                src, src_inc, dst_inc, msg = data
                if type(msg) in OAC_TYPES:
                    self.oac_in_flight -= 1
                upd(f"{t:.9f}m{idx}{src}{type(msg).__name__}".encode())
                if self.trace is not None:
                    self.trace.append(f"{t:.6f} {h.name}#{h.inc} <- {src}#{src_inc} {msg}")
                core.step(h.local(t), Receive(src, src_inc, dst_inc, msg))
                if type(msg) is Heartbeat and (src, src_inc) in self.history.crash_time:
                    self._record_ed_hat(h, src, src_inc)
            else:
                inc, key, gen, deadline = data
                if inc != h.inc or h.timers.get(key) != gen:
                    continue
                del h.timers[key]
                upd(f"{t:.9f}t{idx}{key}".encode())
                local = h.local(t)
                # local -> virtual -> local may lose an ulp: never report a timer before its deadline
                core.step(local if local >= deadline else deadline, TimerFired(key))
            self._apply(h)
        self.now = max(self.now, until)

    def _apply(self, h: SimHost) -> None:
        """Carry out the effects a core produced."""
        core = h.core
        if core is None:
            return
        effects = core.drain()
        if not effects:
            return
        now = self.now
        sends_allowed = None
        crash_after = False
        if h.crash_pending is not None:
            n_sends = sum(1 for e in effects if type(e) is Send)
            if n_sends >= 2 and self._still_may_crash(h):
                sends_allowed = int(h.crash_pending * n_sends)
                crash_after = True
                self._note(f"crash-mid-step {h.name}#{h.inc}: {sends_allowed}/{n_sends} sends leave")
        proc = (h.name, h.inc)
        hist = self.history
        for e in effects:
            match e:
                case Send():
                    if sends_allowed is not None:
                        if sends_allowed <= 0:
                            continue
                        sends_allowed -= 1
                    self._transmit(h, e)
                case SetTimer():
                    gen = self.heap.new_id()  # the timer's generation (haa.lab.dsim.scheduler)
                    h.timers[e.key] = gen
                    at = h.virtual(e.at)
                    self._push(at if at > now else now, EV_TIMER, h.idx, (h.inc, e.key, gen, e.at))
                case CancelTimer():
                    h.timers.pop(e.key, None)
                case Deliver():
                    hist.delivered[proc].append((e.txid, e.order, e.payload, now))
                    self._note(f"deliver {e.txid} order={e.order} at {h.name}#{h.inc}")
                case Decided():
                    hist.decided[proc].setdefault(e.txid, (e.commit, now))
                    self._note(f"decide {e.txid} {'commit' if e.commit else 'abort'} at {h.name}#{h.inc}")
                case Closed():
                    hist.closed[proc].add(e.txid)
                case Voted():
                    hist.votes.setdefault(e.txid, {})[proc] = e.ok
                case Suspicion():
                    hist.suspicions.append((now, proc, (e.peer, e.inc), e.suspected))
                    self._note(f"{h.name}#{h.inc} {'suspects' if e.suspected else 'trusts'} {e.peer}#{e.inc}")
                case PeerDead():
                    hist.dead_marks.append((now, proc, (e.peer, e.inc), e.reason))
                    if e.reason == "excluded":
                        hist.excluded.setdefault((e.peer, e.inc), now)
                        hist.excluded_by.setdefault((e.peer, e.inc), proc)
                    self._note(f"{h.name}#{h.inc}: {e.peer}#{e.inc} dead ({e.reason})")
                case Reincarnate():
                    self.at(now, functools.partial(self._reincarnate, h.name, h.inc))
                case Log():
                    if e.event in ERROR_EVENTS:
                        hist.core_errors.append((now, proc, e.event, str(e.fields)))
                    if self.trace is not None:
                        self._note(f"log {h.name}#{h.inc} {e.event} {e.fields}")
                case _:
                    if self.on_effect is not None:
                        self.on_effect(h, e)
        if crash_after:
            self._crash_now(h)

    def _record_ed_hat(self, h: SimHost, peer: str, inc: int) -> None:
        """The observer's E(D) estimate: mean offset delay minus the true clock offset (eq. 4.4-1)."""
        core = h.membership
        assert core is not None
        pst = core.peers.get(peer)
        if pst is None:
            return
        obs = pst.observer
        q = self.hosts[peer]
        if obs is None or not obs.offsets or pst.inc != inc:
            return
        t = self.now
        clock_gap = (h.offset - q.offset) + (h.drift - q.drift) * t
        self.history.ed_hat[((h.name, h.inc), (peer, inc))] = obs.mean_offset() - clock_gap

    def _reincarnate(self, name: str, inc: int) -> None:
        h = self.hosts[name]
        if h.inc != inc or h.state == CRASHED:
            return
        self.history.ended.setdefault((name, inc), self.now)
        self._note(f"reincarnate {name}#{inc}")
        h.state = CRASHED
        h.core = None
        self._boot(h, inc + 1)
        if self.on_restart:
            self.on_restart(name, h.inc)

    def _transmit(self, h: SimHost, e: Send) -> None:
        dst = self.hosts.get(e.dst)
        if dst is None:
            return
        msg = e.msg
        si, di = h.idx, dst.idx
        now = self.now
        d = self.delay.sample(self.net_rng)
        if d >= LATE_MESSAGE:
            self.history.late.setdefault((h.name, e.dst), []).append((now, now + d))
        if self.spikes:
            live = []
            for s in self.spikes:
                if s[4] > now:
                    live.append(s)
                    if s[3] <= now and (s[0] < 0 or s[0] == si) and (s[1] < 0 or s[1] == di):
                        d += s[2].sample(self.net_rng)
            self.spikes = live
        at = now + d
        key = (si, di)
        last = self.chan_last.get(key, 0.0)
        if at < last:
            at = last  # FIFO: never overtake an earlier message on this channel
        self.chan_last[key] = at
        name = type(msg).__name__
        self.msg_counts[name] += 1
        if type(msg) in OAC_TYPES:
            self.oac_in_flight += 1
        if self.trace is not None and type(msg) is not Heartbeat:
            self.trace.append(f"{now:.6f} {h.name}#{h.inc} -> {e.dst}#{e.dst_inc} {msg}")
        self._push(at, EV_MSG, di, (h.name, h.inc, e.dst_inc, msg))

    def _note(self, text: str) -> None:
        self._hash.update(f"{self.now:.9f}{text}".encode())
        if self.trace is not None:
            self.trace.append(f"{self.now:.6f} {text}")

    # ------------------------------------------------------------------ results

    def trace_hash(self) -> str:
        return self._hash.hexdigest()

    def alive(self) -> list[SimHost]:
        return [h for h in self.by_idx if h.state == ALIVE]

    def open_transactions(self) -> dict[Proc, int]:
        return {(h.name, h.inc): len(h.core.oac.txs) for h in self.by_idx if h.core is not None}
