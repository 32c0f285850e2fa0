"""Agent allocation HAA-AA (thesis §4.7, Appendix II Alg. 4), as a sans-I/O state machine.

One `Allocator` per host. The host feeds it, in this order of concern:

* `on_change(group, agents, hosts)`: the host group or the agent list changed, or the `RebalancePolicy`
  says a periodic load-balancing session is due (Alg. 4 l. 17). Only the undisputed leader (`group[0]`)
  starts a session: it emits `ProposeStart(SessionStart)` for the host to commit as OAC(start) (ll. 18-28).
* committed OAC transactions, in the OAC total order: `on_start_committed` (ll. 38-50) and
  `on_finish_committed` (ll. 93-96); and the OAC outcome of its own proposals, `on_start_decided` /
  `on_finish_decided`, to retry an aborted one while the situation is unchanged (ll. 25-28, 89-92);
* bid updates from peers (`on_update`, ll. 59-76) over reliable FIFO channels, followed by `end_of_inbox`
  once the host has handed over everything currently queued (ll. 77-81: the queued build / distribute).

It answers with effects (`drain()`): `SendUpdate` (a `BidUpdate` to the other session members), `ProposeStart`,
`ProposeFinish`, `Allocated` (a committed allocation this host accepts) and `Log`.

The algorithm is CBBA (Choi, Brunet, How 2009) in its asynchronous form (Johnson, Ponda, Choi, How 2010,
thesis ref. [69]) applied to processor usage instead of time: each host greedily builds a bundle of agents
(`_build`, "HAA-AA Bundle Building Strategy"), bids are compared by a total order (`bid_gt`, "HAA-AA Bid
Comparison Operator", Fig. II-1 reconstructed), and conflicting bids are resolved by the 34 rows of Table 4.7-1
(`resolve`). The leader checks consensus on its bid table (l. 86-88) and commits the result with OAC(finish).

This module holds the `Allocator` (sessions, bid updates, consensus) and its effects; the pieces it is made of are
`haa.core.allocation.bundle` (`BundleBuilder._build_bundle`, its base class), `haa.core.allocation.bids` (the
bid order), `haa.core.allocation.conflicts` (Table 4.7-1), `haa.core.allocation.session` (the per-session
state), `haa.core.allocation.rewards` (eq. 4.7-1 to 4.7-3), `haa.core.allocation.specs` (the problem data and
its bounds) and `haa.core.allocation.rebalance` (`RebalancePolicy`).

Where the thesis is silent, garbled or the figure is missing, the choices are documented in docs/allocation.md.
In short:

* bid order (Fig. II-1): a bid within capacity (support > 0) beats one over it; within capacity higher reward,
  then higher support; over capacity higher support (the less overloaded host; eq. 4.7-3 rewards it with
  s = support), then higher reward; then the lower host name. The nil bid is below every bid.
* bundle building: single agents and clusters of affine agents; a bid's reward is its marginal gain in
  R(b_h); capacity is reserved for agents only this host can run; bids are warped so that a later bid of a
  bundle never beats an earlier one (diminishing marginal gains, which affinity bonuses break).
* trim (rows 1, 17) resets the bids of the agents removed after the lost one to nil and broadcasts them.
* rounds: a build always bids in a round no other bid of this host used (l. 53-55 generalised); consensus
  compares winners and values, not rounds.
* damping of the asynchronous rules (the verifier found message storms): resets of rows 10, 11, 28, 29 are
  skipped while the bid's owner still claims it; a new bid must beat every claim members made for themselves;
  a rebroadcast of an unchanged bid goes only to the stale sender, and only from the authority on that bid.
* consensus is not checked while a build is queued (l. 75-76 would decide before the queued build).
* a committed start is valid if its proposer is the leader, its group is current (ll. 39-40; its agent list
  is a snapshot, not required current) and its id is above every committed start id; a committed finish is
  accepted only for the last valid start, group unchanged since (l. 94 accepts unconditionally). Both depend
  only on the total order.
* sessions of a bounded size: above `SESSION_AGENTS` agents a session auctions a window of them
  (`specs.choose_auction`), the others keep their host (pinned, their load counted first) or wait for the next
  session (deferred), which the leader starts when this one finishes.
* hardware: a host bids only for agents whose hardware it has; agents no host of the group can run are
  reported as `unallocatable` and left out of the consensus check (otherwise the session never ends).
* per-host limits (issue 15, not in the thesis): a host bids for at most `max_per_host` agents of a limited
  kind; the agents of a kind beyond its places in the group are unallocatable like a hardware mismatch.
* hysteresis (a join moved agents twice): a bid for an agent that runs on another host counts a transfer
  penalty of at least `MIN_TRANSFER_PENALTY` in its reward and, past the bidder's capacity, `HYSTERESIS` off
  its support; an agent that runs nowhere has transfer factor 1 on every host (eq. 4.7-2 read for agents
  that no allocation transfers).

The class does no I/O, reads no clock and uses no randomness; iteration orders are those of its inputs.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, cast

from haa.core.allocation.bids import Bid, BidUpdate, bid_gt, nil_bid, same_bid
from haa.core.allocation.bundle import BundleBuilder
from haa.core.allocation.conflicts import _GUARDED_RESETS, LEAVE, RESET, TRIM_UPDATE, UPDATE, UPDATE_TIME, Rule, resolve
from haa.core.allocation.session import _Session
from haa.core.allocation.specs import MAX_SESSION_AGENTS, AgentSpec, HostSpec, SessionStart, _name, choose_auction
from haa.core.effects import Log

# --------------------------------------------------------------------------------------------- effects


@dataclass(slots=True)
class SendUpdate:
    """Send `update` to every host in `dsts` (l. 84; never to oneself)."""

    dsts: tuple[str, ...]
    update: BidUpdate


@dataclass(slots=True)
class ProposeStart:
    """Commit OAC(start, ...) with this payload among the group (l. 26); report with `on_start_decided`."""

    start: SessionStart


@dataclass(slots=True)
class ProposeFinish:
    """Commit OAC(finish, p, sesId_p, bidTable_p[p]) (l. 90); report with `on_finish_decided`."""

    ses_id: int
    allocation: dict[str, str]
    leader: str = ""
    unallocatable: tuple[str, ...] = ()


@dataclass(slots=True)
class Allocated:
    """A committed allocation this host accepts (l. 94): agent -> host. Every host that accepts session
    `ses_id` accepts the same map; `unallocatable` agents have no capable host in the group."""

    ses_id: int
    allocation: dict[str, str]
    unallocatable: tuple[str, ...] = ()
    #: agents that need a place but were outside this bounded session's auction: the leader starts the next
    #: session for them (`SessionStart.deferred`, docs/allocation.md "Sessions of a bounded size")
    deferred: tuple[str, ...] = ()


AllocEffect = SendUpdate | ProposeStart | ProposeFinish | Allocated | Log


# --------------------------------------------------------------------------------------------- allocator


class Allocator(BundleBuilder):
    """Alg. 4 for host `me` (see the module docstring for the inputs and effects).

    `committed_ses` is the highest id of any committed OAC(start), valid or expired, when this host joins an
    existing group (part of the replicated state a new member receives, e.g. the agent table's `ses_id`); a
    fresh group starts at 0.
    """


    #: most agents one session auctions (`choose_auction`); the verifier sets a small one to exercise chaining
    SESSION_AGENTS = MAX_SESSION_AGENTS

    def __init__(self, me: str, committed_ses: int = 0) -> None:
        self.me = _name(me, "Allocator.me")
        self.group: tuple[str, ...] = ()  # hostGroup
        self.agents: tuple[AgentSpec, ...] = ()  # agentList, with the current costs and affinities
        self.hosts: dict[str, HostSpec] = {}
        self.ses_id = committed_ses  # sesId_p: the newest session this host knows of
        self.committed_ses = committed_ses  # the highest id of any committed OAC(start), valid or expired
        self.committed_start: SessionStart | None = None
        self.finished_ses = 0  # the last accepted OAC(finish)
        self.session: _Session | None = None
        self._pending_start: SessionStart | None = None
        self._pending_finish: ProposeFinish | None = None
        self._out: list[AllocEffect] = []
        self.stats = {"updates_in": 0, "bids_in": 0, "updates_out": 0, "messages_out": 0, "builds": 0}

    # ------------------------------------------------------------------ queries

    def drain(self) -> list[AllocEffect]:
        out, self._out = self._out, []
        return out

    @property
    def member(self) -> bool:
        return self.me in self.group

    def busy(self) -> bool:
        """A session this host knows of may still end in an allocation: its start is not decided yet, or it
        committed valid, is not finished and its group is still the current one. False once it expired, was
        finished, or its group changed (`RebalancePolicy` then stops waiting for it)."""
        if self._pending_start is not None:
            return True
        s, st = self.session, self.committed_start
        if s is None or st is None or st.ses_id != s.ses_id or s.ses_id <= self.finished_ses:
            return False
        return st.group == self.group

    def own_bids(self) -> dict[str, Bid]:
        """bidTable_p[p] of the current session (empty when there is none)."""
        s = self.session
        return dict(s.own) if s is not None else {}

    def bundle(self) -> list[str]:
        s = self.session
        return [a for e in s.bundle for a in e.agents] if s is not None else []

    # ------------------------------------------------------------------ l. 17-28: initiation

    def on_change(
        self,
        group: tuple[str, ...],
        agents: tuple[AgentSpec, ...],
        hosts: Iterable[HostSpec],
        start: bool = True,
    ) -> None:
        """The host group or agent list changed, or a rebalance is due (l. 17). Records the new situation;
        if `start` and this host is the undisputed leader (l. 18), starts a new session (ll. 19-26).
        `hosts` must describe every member of `group`. With `start=False` (a rate-limited change) it only
        records, and the host calls again with `start=True` when its `RebalancePolicy` allows."""
        self.group = tuple(group)
        self.agents = tuple(agents)
        self.hosts = {h.name: h for h in hosts}
        if not self.member:
            if self.session is not None:
                self._log("alloc.left_group", ses=self.session.ses_id)
            self.session = None
            self._pending_start = self._pending_finish = None
            return
        if start and self.group[0] == self.me:
            missing = [g for g in self.group if g not in self.hosts]
            if missing:
                raise ValueError(f"Allocator.on_change: hosts: no HostSpec for group member(s) {missing}")
            ses = max(self.ses_id, self.committed_ses) + 1  # l. 19
            auction = choose_auction(self.agents, self.group, self.hosts, ses, self.SESSION_AGENTS)
            st = SessionStart(self.me, ses, self.group, self.agents, tuple(self.hosts[g] for g in self.group), auction)
            self.ses_id = ses
            self.session = _Session(ses, self.me)  # l. 24 newSession()
            self._pending_start = st
            self._pending_finish = None
            self._log("alloc.propose_start", ses=ses, group=list(self.group), agents=len(self.agents))
            self._out.append(ProposeStart(st))

    def on_start_decided(
        self, start: SessionStart, committed: bool, group: tuple[str, ...], agents: Iterable[AgentSpec | str]
    ) -> None:
        """The OAC(start) this host proposed was decided (l. 27). Aborted: propose it again while this host
        is still the leader of that session and the group is unchanged (l. 28; the agent list is the start's
        snapshot, `start_valid`)."""
        if committed or self._pending_start is None or self._pending_start.ses_id != start.ses_id:
            return  # committed: kept pending until delivered (on_start_committed may have to retry it)
        if tuple(group) == start.group and self.ses_id == start.ses_id:
            self._log("alloc.retry_start", ses=start.ses_id)
            self._out.append(ProposeStart(start))
        else:
            self._pending_start = None

    # ------------------------------------------------------------------ l. 38-50: start committed

    def start_valid(self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...] = ()) -> str:
        """Why a committed OAC(start) is expired ("" = valid): ll. 39-40 plus increasing session ids. Depends
        only on totally ordered state, so every host decides the same.

        Ll. 39-40 also expire a start whose agent list is no longer current; here the start's agent list is a
        snapshot (`agent_ids` is not consulted): agents added since wait for the next session, which their
        creation triggers, and the places of agents removed since are ignored. With the thesis' rule a stream
        of spawns expired every start and finish and no session ended (docs/allocation.md, "Sessions of a
        bounded size")."""
        if not group or start.leader != group[0]:
            return "proposer is not the leader"
        if start.group != tuple(group):
            return "group changed"
        if start.ses_id <= self.committed_ses:
            return f"session id not above the last committed start ({self.committed_ses})"
        return ""

    def on_start_committed(
        self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...], verdict: str | None = None
    ) -> None:
        """OAC(start) committed (l. 38); `group` and `agent_ids` are this host's hostGroup and agentList at
        this point of the total order. `verdict`: the replicated state's own decision on this start ("" =
        valid; the agent table's, `AllocGlue.start_committed`), taken instead of `start_valid`."""
        why = self.start_valid(start, tuple(group), tuple(agent_ids)) if verdict is None else verdict
        # every committed start id is used up, even an expired one: the next leader proposes a higher one, and
        # a joiner that only knows the highest committed id decides like everyone else
        self.committed_ses = max(self.committed_ses, start.ses_id)
        mine = self._pending_start is not None and self._pending_start == start
        if mine:
            self._pending_start = None
        if why:  # l. 39-40 expired session
            self._log("alloc.start_expired", ses=start.ses_id, reason=why)
            if mine and "not above" in why and self.ses_id == start.ses_id:
                self._retry_with_new_id(start, tuple(group), tuple(agent_ids))
            return
        self.committed_start = start
        if self.me not in start.group:
            return
        if start.ses_id < self.ses_id:  # already joined a later session through its updates (l. 41)
            return
        if start.ses_id > self.ses_id or self.session is None or self.session.ses_id != start.ses_id:
            self.ses_id = start.ses_id  # ll. 42-44
            self.session = _Session(start.ses_id, self.me)
        s = self.session
        s.make_ready(start, self.me)  # ll. 45-49
        self._log("alloc.session", ses=s.ses_id, group=list(s.group), agents=len(s.agents))
        self._build(s)  # l. 50

    # ------------------------------------------------------------------ l. 59-76: bid updates

    def _retry_with_new_id(self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...]) -> None:
        """Our OAC(start) committed after another (expired) start with the same id, proposed by a former
        leader before we learned of it: propose the session again under a fresh id, if nothing else changed."""
        if group != start.group or not group or group[0] != self.me:
            return
        ses = max(self.ses_id, self.committed_ses) + 1
        st = SessionStart(self.me, ses, start.group, start.agents, start.hosts, start.auction)
        self.ses_id = ses
        self.session = _Session(ses, self.me)
        self._pending_start = st
        self._log("alloc.propose_start", ses=ses, group=list(st.group), agents=len(st.agents), retry=True)
        self._out.append(ProposeStart(st))

    def on_update(self, src: str, upd: BidUpdate) -> None:
        """A bid update from `src` (l. 59). Conflicts are resolved now; the build and distribution this
        queues run at `end_of_inbox`."""
        self.stats["updates_in"] += 1
        if not self.member or src == self.me:
            return
        if upd.ses_id < self.ses_id:  # l. 60-61 old message
            return
        if upd.ses_id > self.ses_id:  # ll. 62-64 join the newer session
            self.ses_id = upd.ses_id
            self.session = _Session(upd.ses_id, self.me)
            self._pending_finish = None
        s = self.session
        if s is None:
            return
        if s.ready and src not in s.others:
            self._log("alloc.update_from_outsider", ses=s.ses_id, src=src)
            return
        for b in upd.bids:  # l. 65
            self.stats["bids_in"] += 1
            self._process_bid(s, src, b)
        if s.ready and (s.outbox or s.replies):  # l. 73-74
            s.distribute_queued = True
        if s.ready:  # l. 75-76
            self._check_consensus(s)

    def _process_bid(self, s: _Session, q: str, b: Bid) -> None:
        j, w, _reward, _support, rnd = b
        if s.ready and (j not in s.agents or (w is not None and w not in s.group)):
            return
        s.set_row(q, j, b)  # l. 66
        if rnd >= s.r:  # l. 67-68
            s.r = rnd + 1
        old = s.bid(j)  # l. 69
        rule = resolve(self.me, q, b, old)  # l. 70
        if rule.action == RESET and rule.row in _GUARDED_RESETS and self._owner_confirms(s, old):
            rule = Rule(rule.row, LEAVE, True)
        act = rule.action
        if act == LEAVE:
            if rule.broadcast:
                self._broadcast(s, q, j, self._broadcast_bid(s, j, b, act), b)
            return
        bundle_changed = False
        if act == UPDATE:
            s.set_own(j, b)
        elif act == TRIM_UPDATE:
            self._trim(s, j)
            s.set_own(j, b)
            bundle_changed = True
        elif act == RESET:
            s.set_own(j, nil_bid(j))
        elif act == UPDATE_TIME:
            s.set_own(j, old._replace(round=s.r))
            s.round_used = max(s.round_used, s.r)
        if rule.broadcast:
            self._broadcast(s, q, j, self._broadcast_bid(s, j, b, act), b)
        if bundle_changed or bid_gt(old, s.bid(j)):  # l. 71-72 (got worse), or our bundle shrank
            s.build_queued = True

    #: Table 4.7-1 "broadcast" to every member even when the bid is unchanged (the text as printed; for
    #: comparisons in docs/allocation.md only)
    LITERAL_BROADCAST = False

    #: rows 10, 11, 28, 29 reset when the sender's (lower or higher) bid is newer than the receiver's
    #: accepted bid of a third host m; the receiver keeps it if m's own last update still claims it
    OWNER_GUARD = True

    def _owner_confirms(self, s: _Session, held: Bid) -> bool:
        """The winner m of `held` claimed exactly this bid in its last update to us (bidTable_p[m][j]): with
        FIFO channels from every member, a newer round elsewhere cannot mean m gave it up (docs/allocation.md,
        "rounds")."""
        m = held.winner
        if not self.OWNER_GUARD or m is None or m == self.me:
            return False
        w = s.rows.get(m, {}).get(held.agent)
        return w is not None and w.winner == m and same_bid(w, held)

    def _broadcast_bid(self, s: _Session, j: str, sender_bid: Bid, action: str) -> Bid:
        """What "broadcast" puts in the outbox: bidTable_p[p][j], so a reset sends the receiver's nil bid (the
        thesis' change to [69])."""
        return s.bid(j)

    def _broadcast(self, s: _Session, q: str, j: str, b: Bid, sender_bid: Bid) -> None:
        """outbox_p[j] := b (l. 84 sends it to every member). When b is (`same_bid`) what this host last sent
        to every member, the rebroadcast is news only to q, whose view differs, and only when this host is
        the authority on it: b is our own claim, or q's bid names us as the winner. Every other member's
        bid reaches q from its owner, which replies to q itself (docs/allocation.md, "messages")."""
        if self.LITERAL_BROADCAST or j in s.outbox or not same_bid(s.sent.get(j, nil_bid(j)), b):
            s.outbox[j] = b
        elif b.winner == self.me or sender_bid.winner == self.me:
            s.replies.setdefault(q, {})[j] = b

    def _trim(self, s: _Session, j: str) -> None:
        """Rows 1 and 17: remove j's bundle entry (its cluster) and every later one; the other agents removed
        lose this host's bid (reset to nil, broadcast)."""
        k = s.entry_of.get(j)
        if k is None:
            return
        removed = s.bundle[k:]
        del s.bundle[k:]
        for e in removed:
            for a in e.agents:
                s.entry_of.pop(a, None)
                if a != j:
                    s.set_own(a, nil_bid(a))
                    s.outbox[a] = s.bid(a)

    def end_of_inbox(self) -> None:
        """ll. 77-81: every message currently in the inbox was processed."""
        s = self.session
        if s is None or not self.member:
            return
        if s.ready and s.build_queued:
            self._build(s)
        if s.distribute_queued:
            self._distribute(s)

    # ------------------------------------------------------------------ l. 51-58: bundle building

    def _build(self, s: _Session) -> None:
        s.build_queued = False  # l. 52
        if s.r <= s.round_used:  # l. 53-55 (a round no bid of ours used yet)
            s.r = s.round_used + 1
        s.round_used = s.r
        s.builds += 1
        self.stats["builds"] += 1
        self._build_bundle(s)  # l. 56
        self._distribute(s)  # l. 57
        self._check_consensus(s)  # l. 58

    # ------------------------------------------------------------------ l. 82-92: distribute, consensus

    def _distribute(self, s: _Session) -> None:
        s.distribute_queued = False  # l. 83
        if not s.ready or not (s.outbox or s.replies):
            return
        everyone = tuple(q for q in s.others if q not in s.replies)
        if s.outbox and everyone:
            self._send(s, everyone, tuple(s.outbox.values()))  # l. 84
        for q in s.others:
            extra = s.replies.get(q)
            if extra:
                bids = {**s.outbox, **{j: b for j, b in extra.items() if j not in s.outbox}}
                self._send(s, (q,), tuple(bids.values()))
        s.sent.update(s.outbox)
        s.outbox = {}  # l. 85
        s.replies = {}

    def _send(self, s: _Session, dsts: tuple[str, ...], bids: tuple[Bid, ...]) -> None:
        self._out.append(SendUpdate(dsts, BidUpdate(s.ses_id, bids, self.me)))
        s.messages_sent += len(dsts)
        self.stats["updates_out"] += 1
        self.stats["messages_out"] += len(dsts)

    def _check_consensus(self, s: _Session) -> None:
        """l. 86-88: the leader decides once every allocatable agent is claimed and every member's last sent
        bids equal its own."""
        if not s.ready or s.decided or not s.group or s.group[0] != self.me:
            return
        if s.unclaimed or s.mismatch or s.build_queued:  # l. 75-76 would decide before the queued build
            return
        s.decided = True
        # every allocatable agent has a winner here (`s.unclaimed` is empty); the agents a bounded session pinned
        # are in it too, on their host (the agent table clears the place of a limited agent left out)
        pinned = s.pinned
        alloc = cast(
            "dict[str, str]",
            {
                j: s.own[j].winner if j in s.allocatable else pinned[j]
                for j in s.agents
                if j in s.allocatable or j in pinned
            },
        )
        fin = ProposeFinish(s.ses_id, alloc, self.me, s.unallocatable)
        self._pending_finish = fin
        self._log("alloc.consensus", ses=s.ses_id, builds=s.builds, messages=s.messages_sent)
        self._out.append(fin)

    def on_finish_decided(self, ses_id: int, committed: bool) -> None:
        """The OAC(finish) this host proposed was decided (l. 91). Aborted: propose it again while the
        session is current and the group unchanged (l. 92; a changed agent list does not expire it, see
        `finish_valid`)."""
        fin = self._pending_finish
        if fin is None or fin.ses_id != ses_id:
            return
        if committed:
            self._pending_finish = None
            return
        s = self.session
        st = s.start if s is not None else None
        if s is not None and st is not None and s.ses_id == ses_id and self.group == st.group:
            self._log("alloc.retry_finish", ses=ses_id)
            self._out.append(fin)
        else:
            self._pending_finish = None

    # ------------------------------------------------------------------ l. 93-96: finish committed

    def finish_valid(self, ses_id: int, group: tuple[str, ...], agent_ids: tuple[str, ...] = ()) -> str:
        """Why a committed OAC(finish) is not accepted ("" = accepted): it must finish the last committed
        start, whose group must not have changed since, and not be finished yet. Depends only on totally
        ordered state, so every host decides the same.

        Agents added or removed since the start do not expire it (`agent_ids` is not consulted): a removed
        agent's place is ignored, an added one waits for the next session, which its creation triggers. An
        expiry on every agent-list change left no session finishing while spawns kept arriving (a burst of
        150 spawns kept a 4-host group allocating for minutes; docs/allocation.md "Sessions of a bounded size")."""
        st = self.committed_start
        if st is None or ses_id != st.ses_id:
            return f"not the last valid session ({st.ses_id if st is not None else 0})"
        if ses_id <= self.finished_ses:
            return "session already finished"
        if st.group != tuple(group):
            return "group changed since the start"
        return ""

    def on_finish_committed(
        self,
        ses_id: int,
        allocation: Mapping[str, str],
        group: tuple[str, ...] | None = None,
        agent_ids: tuple[str, ...] | None = None,
    ) -> None:
        """OAC(finish) committed (l. 93). `group`/`agent_ids`: hostGroup and agentList at this point of the
        total order (default: as last given to `on_change`)."""
        g = tuple(group) if group is not None else self.group
        ids = tuple(agent_ids) if agent_ids is not None else tuple(a.id for a in self.agents)
        why = self.finish_valid(ses_id, g, ids)
        if why:
            self._log("alloc.finish_ignored", ses=ses_id, reason=why)
            return
        self.finished_ses = ses_id
        st = self.committed_start
        unalloc = st.unallocatable() if st is not None else ()
        deferred = st.deferred() if st is not None else ()
        self._log("alloc.allocated", ses=ses_id, agents=len(allocation), deferred=len(deferred))
        self._out.append(Allocated(ses_id, dict(allocation), unalloc, deferred))  # l. 94
        s = self.session
        if s is not None and s.ses_id == ses_id:  # l. 95-96
            s.decided = True
        if self._pending_finish is not None and self._pending_finish.ses_id == ses_id:
            self._pending_finish = None

    # ------------------------------------------------------------------ helpers

    def _log(self, event: str, **fields: Any) -> None:
        self._out.append(Log(event, {"host": self.me, **fields}))
