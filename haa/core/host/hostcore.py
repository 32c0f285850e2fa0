"""HostCore: everything one host decides, as a single sans-I/O state machine.

It composes, for one host incarnation:

* the failure detector of Alg. 1 (`haa.core.ufd.ufd`): one `HeartbeatSender` and one `HeartbeatObserver`
  per peer, so every ordered host pair is monitored separately (full mesh);
* incarnations and permanent suspicion: every host life has an incarnation number; a message from an older
  incarnation is dropped, a newer incarnation makes the older one permanently suspected, and a peer that
  stays suspected for `exclude_after` seconds is excluded — its incarnation is permanently suspected, its
  messages are dropped, and it is told so (`Excluded`) so that it restarts as a new incarnation
  (docs/ufd.md, "exclusion"; the membership service of Alg. 3 will own this decision);
* the ordered atomic commit of Alg. 2 (`haa.core.oac.oac`).

Inputs (each with the current local time): `start`, `on_message`, `on_timer`, `on_suspicion` (external
failure detector mode, used by the simulator's adversarial FD model), `on_peer_info` (the transport learned
a peer's incarnation from a handshake), `propose`. Effects accumulate in `out`; the driver calls `drain()`.
A membership message (Alg. 3, `GROUP_TYPES`) is not the core's to handle: with `accept_group` (the
membership layer, `haa.core.membership.membership`, runs on top) `on_message` returns it as a `GroupMessage` for the
layer above to handle at once, and an agent-layer message (`APP_TYPES`) as an `AppMessage`, which the
membership layer hands up in turn; without it, both are counted as unknown messages.
The module performs no I/O, reads no clock and uses no randomness.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Iterable
from dataclasses import dataclass, field
from typing import Any, assert_never, cast

from haa.core.effects import (
    CancelTimer,
    Closed,
    Decided,
    Deliver,
    Effect,
    Log,
    PeerDead,
    Reincarnate,
    Send,
    SetTimer,
    Suspicion,
    Voted,
)
from haa.core.inputs import CoreInput, FdReport, PeerInfo, Receive, Start, TimerFired
from haa.core.messages import (
    GROUP_TYPES,
    OAC_TYPES,
    AgentHostMsg,
    Excluded,
    Heartbeat,
    Message,
    OacMessage,
    SetPeriod,
    TxId,
)
from haa.core.oac.oac import (
    Evaluate,
    Incoming,
    Learn,
    OacError,
    OacInput,
    OrderedAtomicCommit,
    PeerChanged,
    Propose,
    Vote,
)
from haa.core.ufd.ufd import (
    ArmFreshness,
    AskPeriod,
    Beat,
    Deadline,
    EmitHeartbeat,
    HeartbeatIn,
    HeartbeatObserver,
    HeartbeatSender,
    NewPeriod,
    ObserverEffect,
    Suspect,
    Trust,
    UfdConfig,
)

FD_UFD = "ufd"
FD_EXTERNAL = "external"


@dataclass(frozen=True, slots=True)
class CoreConfig:
    ufd: UfdConfig = field(default_factory=UfdConfig)
    fd_mode: str = FD_UFD
    #: a peer suspected without interruption for this long is permanently suspected (excluded)
    exclude_after: float = 10.0
    #: at most one `Excluded` notice per peer in this interval
    notice_interval: float = 1.0

    def __post_init__(self) -> None:
        if self.fd_mode not in (FD_UFD, FD_EXTERNAL):
            raise ValueError(f"fd_mode must be {FD_UFD!r} or {FD_EXTERNAL!r}")
        if self.exclude_after <= 0:
            raise ValueError("exclude_after must be positive")


@dataclass(frozen=True, slots=True)
class GroupMessage:
    """A membership message (`GROUP_TYPES`) that passed the core's checks (known sender, current
    incarnation, not excluded), returned by `HostCore.on_message` to the membership layer."""

    src: str
    src_inc: int
    msg: Message


@dataclass(frozen=True, slots=True)
class AppMessage:
    """An agent-layer message (`APP_TYPES`) that passed the core's checks, returned by `HostCore.on_message`
    and handed up by the membership layer to the agent layer (`haa.core.agents.agentnode`)."""

    src: str
    src_inc: int
    msg: AgentHostMsg


@dataclass(frozen=True, slots=True)
class VoteRequest:
    """OAC asks this host's vote on `txid` (Alg. 2 l. 27): the layer above answers with `HostCore.vote`."""

    txid: TxId
    payload: bytes
    participants: tuple[tuple[str, int], ...] = ()


class _Peer:
    __slots__ = ("inc", "last_notice", "name", "observer", "sender", "suspected")

    def __init__(self, name: str) -> None:
        self.name = name
        self.inc = 0  # 0: never heard from
        self.sender: HeartbeatSender | None = None
        self.observer: HeartbeatObserver | None = None
        self.suspected = True
        self.last_notice = float("-inf")


class HostCore:
    """One host incarnation: UFD + permanent suspicion + OAC. See the module docstring."""

    def __init__(
        self,
        name: str,
        inc: int,
        peers: Iterable[str],
        config: CoreConfig | None = None,
        no_votes: Iterable[bytes] = (),
        known_incs: dict[str, int] | None = None,
        accept_group: bool = False,
    ) -> None:
        if inc <= 0:
            raise ValueError("incarnation numbers start at 1")
        self.name = name
        self.inc = inc
        self.config = config or CoreConfig()
        self.out: list[Effect] = []
        self.peers: dict[str, _Peer] = {}
        for q in peers:
            if q != name:
                self.peers[q] = _Peer(q)
        for q, qi in (known_incs or {}).items():
            if q in self.peers:
                self.peers[q].inc = qi
        self.dead: set[tuple[str, int]] = set()
        #: the incarnations the group removed (`mark_dead(..., "removed")`, Alg. 3 l. 118), a subset of `dead`:
        #: OAC decides a two-participant transaction alone when its partner is one of them (docs/oac.md)
        self.removed: set[tuple[str, int]] = set()
        self.counters: Counter[str] = Counter()
        self._unknown_logged: dict[str, float] = {}  # unknown sender -> when it was last logged
        #: a membership layer runs on top (`haa.core.membership.membership.MembershipNode`): `on_message` returns the
        #: membership messages of Alg. 3 to it, and one from a host this core has never heard of adds that host
        #: as a peer (an applicant, or a member introduced to us) instead of being rejected
        #: and answers OAC's `Evaluate` requests (`VoteRequest`: `step` returns them to it). Without one the core
        #: votes itself: yes, but no on the payloads of `no_votes` (the simulator's unilateral aborts, Alg. 2 l. 27)
        self.accept_group = accept_group
        self.no_votes = frozenset(no_votes)
        self.started = False
        self._now = 0.0
        self.oac = OrderedAtomicCommit(name, inc, self)

    # ------------------------------------------------------------------ queries used by OAC

    def is_dead(self, q: str, qi: int) -> bool:
        if (q, qi) in self.dead:
            return True
        p = self.peers.get(q)
        return p is None or p.inc > qi

    def is_removed(self, q: str, qi: int) -> bool:
        return (q, qi) in self.removed

    def is_suspected(self, q: str, qi: int) -> bool:
        if (q, qi) in self.dead:
            return True
        p = self.peers.get(q)
        if p is None or p.inc != qi:
            return True
        return p.suspected

    def trusted_peers(self) -> list[str]:
        return [
            q
            for q, p in self.peers.items()
            if p.inc and not p.suspected and (q, p.inc) not in self.dead
        ]

    # ------------------------------------------------------------------ effects

    def drain(self) -> list[Effect]:
        out = self.out
        if not out:
            return []
        res = out.copy()
        out.clear()
        return res

    def _send(self, dst: str, dst_inc: int, msg: Message) -> None:
        self.out.append(Send(dst, dst_inc, msg))

    def _oac(self, now: float, inp: OacInput) -> VoteRequest | None:
        """Step OAC and carry out its effects in order; a vote it asks for is answered here without a layer above
        (static mode), else returned for that layer to answer (`vote`)."""
        ask: VoteRequest | None = None
        for e in self.oac.step(now, inp):
            match e:
                case Send(dst, dst_inc):
                    if (dst, dst_inc) in self.dead:
                        self.counters["oac_not_sent_to_dead"] += 1
                    else:
                        self.out.append(e)
                case Learn(parts):
                    self._learn_participants(parts)
                case Evaluate(txid, payload, parts):
                    if self.accept_group:
                        ask = VoteRequest(txid, payload, parts)
                    else:
                        ask = self._oac(now, Vote(txid, payload not in self.no_votes))
                case Decided() | Deliver() | Closed() | Log() | Voted():
                    self.out.append(e)
                case _:
                    assert_never(e)
        return ask

    def vote(self, now: float, txid: TxId, ok: bool) -> None:
        """The layer above answers a `VoteRequest` (Alg. 2 ll. 27-30)."""
        self._now = now
        if self._oac(now, Vote(txid, ok)) is not None:  # (a vote never asks for another one)
            raise OacError(f"the vote on {txid} asked for another vote")

    def _timer(self, key: Hashable, at: float) -> None:
        self.out.append(SetTimer(key, at))

    def _log(self, event: str, **fields: Any) -> None:
        self.out.append(Log(event, fields))

    # ------------------------------------------------------------------ inputs

    def step(self, now: float, inp: CoreInput) -> GroupMessage | AppMessage | VoteRequest | None:
        """One input (`haa.core.inputs`); its effects accumulate for `drain()`. A message for the layer above
        (membership or agent layer) that passed the core's checks is returned."""
        match inp:
            case Receive(src, src_inc, dst_inc, msg):
                return self.on_message(now, src, src_inc, dst_inc, msg)
            case TimerFired(key):
                self.on_timer(now, key)
            case Start():
                self.start(now)
            case FdReport(peer, suspected):
                self.on_suspicion(now, peer, suspected)
            case PeerInfo(peer, inc):
                self.on_peer_info(now, peer, inc)
            case _:
                assert_never(inp)
        return None

    def start(self, now: float) -> None:
        """Begin heartbeating every peer (Alg. 1 ll. 1-5 and 13-16)."""
        self._now = now
        if self.started:
            return
        self.started = True
        ufd = self.config.fd_mode == FD_UFD
        for p in self.peers.values():
            if ufd:
                self._start_ufd(now, p)
                if p.inc:  # an incarnation we were told about but have not heard from yet
                    self._timer(("excl", p.name, p.inc), now + self.config.exclude_after)
            else:
                p.suspected = not p.inc

    def _start_ufd(self, now: float, p: _Peer) -> None:
        p.sender = HeartbeatSender(self.config.ufd.initial_period, now)
        p.observer = HeartbeatObserver(self.config.ufd, now)
        p.suspected = True  # l. 15-17: q_tau_0 = now, nothing received yet
        self._timer(("hb", p.name), now)

    def on_timer(self, now: float, key: Hashable) -> None:
        self._now = now
        k = cast("tuple[str, str, int]", key)  # ("hb"|"fd", peer) or ("excl", peer, incarnation): see _timer calls
        kind = k[0]
        q = k[1]
        p = self.peers.get(q)
        if p is None:
            return
        if kind == "hb":  # Alg. 1 l. 6
            if p.sender is None:
                return
            for s in p.sender.step(now, Beat()):
                if isinstance(s, EmitHeartbeat):
                    self._send(q, p.inc, s.hb)
                    self._timer(("hb", q), s.next_at)
        elif kind == "fd":  # Alg. 1 l. 17-18
            if p.observer is not None:
                self._observed(now, p, p.observer.step(now, Deadline()))
        elif kind == "excl":
            if k[2] == p.inc and p.suspected and (q, p.inc) not in self.dead:
                self._exclude(now, p)

    def on_message(
        self, now: float, src: str, src_inc: int, dst_inc: int, msg: Message
    ) -> GroupMessage | AppMessage | VoteRequest | None:
        """A message from `src`; a membership message (with `accept_group`) is returned for the layer above."""
        self._now = now
        p = self.peers.get(src)
        if p is None and self.accept_group and type(msg) in GROUP_TYPES and src != self.name:
            p = self.add_peer(now, src)
        if p is None:
            # (in membership mode an applicant's first heartbeats can precede its `apply` on the link: log
            # each unknown sender at most once a second, not every message)
            self.counters["rejected_unknown_sender"] += 1
            if now - self._unknown_logged.get(src, -1e18) >= 1.0:
                if len(self._unknown_logged) > 1000:
                    self._unknown_logged.clear()
                self._unknown_logged[src] = now
                self._log("reject", reason="unknown sender", src=src)
            return None
        if dst_inc and dst_inc != self.inc:
            self.counters["dropped_misaddressed"] += 1
            return None
        if src_inc < p.inc:
            self.counters["dropped_stale_incarnation"] += 1
            return None
        if src_inc > p.inc:
            self._new_incarnation(now, p, src_inc)
        if (src, src_inc) in self.dead:
            self.counters["dropped_from_excluded"] += 1
            if now - p.last_notice >= self.config.notice_interval:
                p.last_notice = now
                self._send(src, src_inc, Excluded(src_inc))
            return None
        t = type(msg)
        if isinstance(msg, Heartbeat):
            if p.observer is not None:
                self._observed(now, p, p.observer.step(now, HeartbeatIn(msg)))
        elif t in OAC_TYPES:
            return self._oac(now, Incoming(src, src_inc, cast(OacMessage, msg)))
        elif isinstance(msg, SetPeriod):
            if p.sender is not None and p.sender.step(now, NewPeriod(msg.period)):  # PeriodRefused
                self.counters["rejected_bad_period"] += 1
        elif isinstance(msg, Excluded):
            if msg.incarnation == self.inc:
                self._log("excluded_by_peer", by=src)
                self.out.append(Reincarnate(by=src))
        elif self.accept_group and t in GROUP_TYPES:
            return GroupMessage(src, src_inc, msg)
        elif self.accept_group and isinstance(msg, AgentHostMsg):  # (APP_TYPES)
            return AppMessage(src, src_inc, msg)
        else:
            self.counters["rejected_unknown_message"] += 1
        return None

    def _observed(self, now: float, p: _Peer, effects: list[ObserverEffect]) -> None:
        """Carry out what `p`'s heartbeat observer decided (Alg. 1 ll. 17-27)."""
        for e in effects:
            match e:
                case ArmFreshness(at):
                    self._timer(("fd", p.name), at)
                case AskPeriod(period):
                    self._send(p.name, p.inc, SetPeriod(period))  # Alg. 1 l. 27
                case Trust():
                    self._set_suspected(now, p, False)
                case Suspect():
                    self._set_suspected(now, p, True)
                case _:
                    assert_never(e)

    def on_suspicion(self, now: float, peer: str, suspected: bool) -> None:
        """External failure detector output (fd_mode='external')."""
        self._now = now
        p = self.peers.get(peer)
        if p is None or p.suspected == suspected:
            return
        self._set_suspected(now, p, suspected)

    def on_peer_info(self, now: float, peer: str, inc: int) -> None:
        """The transport learned `peer`'s incarnation (handshake) before any message from it."""
        self._now = now
        p = self.peers.get(peer)
        if p is not None and inc > p.inc:
            self._new_incarnation(now, p, inc)

    def add_peer(self, now: float, name: str, inc: int = 0, hearsay: bool = False) -> _Peer:
        """Start monitoring a host learned at run time (an applicant, or a member we were introduced to).
        `hearsay`: `inc` comes from a third host (a relayed introduction), not from `name` itself."""
        self._now = now
        p = self.peers.get(name)
        if p is None:
            p = self.peers[name] = _Peer(name)
            if self.started and self.config.fd_mode == FD_UFD:
                self._start_ufd(now, p)
        if inc > p.inc and (not hearsay or self._believe_hearsay(p)):
            self._new_incarnation(now, p, inc)
        return p

    def _believe_hearsay(self, p: _Peer) -> bool:
        """Whether another host's word that `p` has a newer incarnation is taken (issue 13, defect 4): only
        while we trust no incarnation of `p` — never heard from, suspected, or excluded. A peer we hear from
        is never superseded by hearsay: anyone with the cluster token could otherwise name (h1, 2^64 - 1) in
        a participant list and lock the live h1 out for good. A host that really restarted loses nothing:
        its old incarnation falls silent and is suspected, and the new one's own handshake or first message
        (`on_peer_info`, `on_message`, checked by the transport) is believed at once."""
        if p.inc == 0 or p.suspected or (p.name, p.inc) in self.dead:
            return True
        self.counters["hearsay_incarnation_ignored"] += 1
        return False

    def mark_dead(self, now: float, name: str, inc: int, reason: str) -> None:
        """Permanently suspect `name` incarnation `inc` (for example: the group removed it, Alg. 3 l. 118) and
        tell it, so that a correct host removed by mistake comes back as a new incarnation."""
        self._now = now
        p = self.peers.get(name)
        if p is None or inc <= 0:
            return
        if reason == "removed" and (name, inc) not in self.removed:
            self.removed.add((name, inc))
            if (name, inc) in self.dead:  # already excluded or superseded: OAC learns that it was removed
                self._oac(now, PeerChanged(name))
        if (name, inc) in self.dead:
            return
        self._mark_dead(p, inc, reason)
        if p.inc == inc:
            p.sender = None
            self.out.append(CancelTimer(("hb", name)))
            self.out.append(CancelTimer(("excl", name, inc)))
        p.last_notice = now
        self._send(name, inc, Excluded(inc))

    def new_txid(self) -> TxId:
        """A fresh OAC transaction id of this host incarnation, for `propose_to` (chosen before proposing)."""
        return self.oac.new_txid()

    def propose_to(self, now: float, txid: TxId, payload: bytes,
                   participants: Iterable[tuple[str, int]]) -> VoteRequest | None:
        """Propose OAC transaction `txid` (`new_txid`) to exactly these host incarnations (this host is always
        included); this host's own vote on it is asked for at once (a `VoteRequest` for the layer above)."""
        self._now = now
        parts = tuple(pq for pq in participants if pq[0] != self.name)
        return self._oac(now, Propose(txid, payload, parts))

    def propose(self, now: float, payload: bytes, participants: Iterable[str] | None = None) -> TxId:
        """Propose an OAC transaction; default participants: this host and every peer it trusts."""
        self._now = now
        if participants is None:
            names = self.trusted_peers()
        else:
            names = []
            for q in participants:
                if q == self.name:
                    continue
                p = self.peers.get(q)
                if p is None:
                    raise OacError(f"unknown participant {q!r}")
                if not p.inc or (q, p.inc) in self.dead:
                    raise OacError(f"participant {q!r} is not reachable (no live incarnation known)")
                names.append(q)
        parts = tuple((q, self.peers[q].inc) for q in sorted(set(names)))
        txid = self.oac.new_txid()
        if self._oac(now, Propose(txid, payload, parts)) is not None:
            raise OacError("propose() is the static mode's: a layer above proposes with propose_to and votes")
        return txid

    # ------------------------------------------------------------------ internals

    def _set_suspected(self, now: float, p: _Peer, suspected: bool) -> None:
        p.suspected = suspected
        self.out.append(Suspicion(p.name, p.inc, suspected))
        if p.inc:
            key = ("excl", p.name, p.inc)
            if suspected:
                self._timer(key, now + self.config.exclude_after)
            else:
                self.out.append(CancelTimer(key))
        self._oac(self._now, PeerChanged(p.name))

    def _learn_participants(self, parts: tuple[tuple[str, int], ...]) -> None:
        """A participant list names an incarnation we never heard from: it exists (its proposer heard
        from it), so track it — and if we cannot hear it, suspect and eventually exclude it."""
        for q, qi in parts:
            p = self.peers.get(q)
            if p is not None and qi > p.inc and self._believe_hearsay(p):
                self._new_incarnation(self._now, p, qi)

    def _mark_dead(self, p: _Peer, inc: int, reason: str) -> None:
        if (p.name, inc) in self.dead:
            return
        self.dead.add((p.name, inc))
        self.out.append(PeerDead(p.name, inc, reason))
        self._log("peer_dead", peer=p.name, inc=inc, reason=reason)
        self._oac(self._now, PeerChanged(p.name))

    def _exclude(self, now: float, p: _Peer) -> None:
        """Permanent suspicion after `exclude_after` of continuous suspicion."""
        self.mark_dead(now, p.name, p.inc, "excluded")

    def _new_incarnation(self, now: float, p: _Peer, inc: int) -> None:
        old = p.inc
        p.inc = inc
        self._log("peer_incarnation", peer=p.name, old=old, new=inc)
        if not old:
            # first contact: our heartbeats (addressed to incarnation 0) already reach it, keep them going;
            # any older incarnation named in a transaction is now known to be superseded
            if self.config.fd_mode == FD_EXTERNAL:
                p.suspected = False
            elif p.suspected:
                # the detector's output for an incarnation it has not heard from yet is SUSPECTED (l. 15-18)
                self.out.append(Suspicion(p.name, inc, True))
                self._timer(("excl", p.name, inc), now + self.config.exclude_after)
            self._oac(self._now, PeerChanged(p.name))
            return
        self.out.append(CancelTimer(("excl", p.name, old)))
        self._mark_dead(p, old, "restarted")
        if self.config.fd_mode == FD_UFD:
            # a new life: its observer of us starts from l = -1 and it needs our heartbeats at once
            self._start_ufd(now, p)
            self.out.append(Suspicion(p.name, inc, True))  # a new life starts suspected (l. 15-18)
            # suspected until its first heartbeat: if that never comes, it must still be excluded
            self._timer(("excl", p.name, inc), now + self.config.exclude_after)
        else:
            p.suspected = False
        self._oac(self._now, PeerChanged(p.name))

    # ------------------------------------------------------------------ introspection

    def peer_view(self) -> list[dict[str, Any]]:
        rows = []
        for q, p in sorted(self.peers.items()):
            obs = p.observer
            rows.append(
                {
                    "name": q,
                    "incarnation": p.inc,
                    "suspected": p.suspected,
                    "excluded": (q, p.inc) in self.dead,
                    "eta": obs.eta if obs else 0.0,
                    "alpha": (self.config.ufd.qos.td_upper - obs.eta) if obs else 0.0,
                }
            )
        return rows
