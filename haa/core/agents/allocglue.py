"""Allocation glue (thesis Alg. 4 on the agent layer): the agent table in, `Allocator` sessions out.

`haa.core.allocation.allocation.Allocator` is the HAA-AA algorithm itself (bids, consensus, sessions) and knows nothing
of the agent table; `AllocGlue` connects it to the host's agent layer (`haa.core.agents.agentnode.AgentNode`):

* it builds the allocator's inputs from the replicated table — `AgentSpec` per agent (cost, hardware, affinity
  on the scale of costs, current host, per-host limit) and `HostSpec` per member (K_h, H_h and draining flag
  as the members committed them; a member whose entry is not committed yet bids for nothing);
* it decides when a session starts (Alg. 4 l. 17): every host records a change, the leader starts a session
  when its `RebalancePolicy` allows (rate limit, periodic rebalancing unless paused);
* it turns the allocator's outputs into effects for the node (`haa.core.agents.agentstep`): bid updates as
  `HostSend("alloc")`, OAC(start)/OAC(finish) as agent transactions (`Propose`), the rebalance timer;
* it publishes this host's own K_h, H_h and draining flag (`publish_host`), again until the table holds them.

Each input method returns the effects to carry out, in order. Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from typing import cast

from haa.core.agents.agentstep import AgentTimer, AgentView, ArmTimer, HostSend, Note, Propose
from haa.core.allocation import allocwire
from haa.core.allocation.allocation import Allocated, Allocator, ProposeFinish, ProposeStart, SendUpdate
from haa.core.allocation.rebalance import RebalancePolicy
from haa.core.allocation.specs import (
    MAX_CAPACITY,
    MAX_COST,
    MAX_PER_HOST,
    MIN_CAPACITY,
    AgentSpec,
    HostSpec,
    SessionStart,
)
from haa.core.ddb import agenttable as at
from haa.core.effects import Log
from haa.core.membership.globalstate import TxAgent, decode_tx
from haa.pb import agenttx_pb2 as apb

#: bytes/s of messages between two agents that count as affinity 1.0 (the scale of an agent's CPU cost)
AFFINITY_SCALE = 1e5

GlueEffect = HostSend | Propose | Note | ArmTimer


class AllocGlue:
    """See the module docstring."""

    def __init__(self, view: AgentView, rebalance_period: float, min_session_gap: float,
                 capacity: float, hardware: tuple[str, ...]) -> None:
        self.view = view
        self.allocator = Allocator(view.name)
        self.policy = RebalancePolicy(period=rebalance_period if rebalance_period > 0 else 1e18,
                                      min_interval=min_session_gap)
        self.capacity = capacity
        self.hardware = tuple(sorted(hardware))
        self.draining = False
        self.host_published: tuple[float, tuple[str, ...], bool] | None = None
        self._starts: dict[int, SessionStart] = {}
        self._out: list[GlueEffect] = []

    def _done(self) -> list[GlueEffect]:
        out, self._out = self._out, []
        return out

    # ------------------------------------------------------------------ allocator inputs from the table

    def agent_specs(self) -> tuple[AgentSpec, ...]:
        t = self.view.table
        aff: dict[str, dict[str, float]] = {}
        for (a, b), rate in t.affinity.items():
            aff.setdefault(a, {})[b] = rate
            aff.setdefault(b, {})[a] = rate
        out = []
        for agent in t.agent_ids():
            r = t.records[agent]
            # affinity alpha_ij: bytes/s between the two agents, on the scale of costs (100 kB/s ~ 1.0)
            alphas = {k: min(1.0, v / AFFINITY_SCALE) for k, v in aff.get(agent, {}).items()}
            cost = r.cost()  # the table refuses costs outside [0, MAX_COST]; clamped anyway (NaN -> 0)
            cost = min(max(cost, 0.0), MAX_COST) if cost == cost else 0.0
            limit = r.spec.max_per_host
            if r.status == at.FAILED:
                cost = 0.0  # runs nowhere until an operator retries it
                limit = 0  # and takes none of its type's places on a host (issue 15)
            out.append(
                AgentSpec(
                    id=agent,
                    cost=cost,
                    hardware=frozenset(r.spec.hardware),
                    affinity=alphas,
                    transfer_penalty=r.spec.transfer_penalty,
                    current_host=(r.owner or None) if r.status == at.ACTIVE else None,
                    kind=r.spec.type if limit else "",
                    max_per_host=min(limit, MAX_PER_HOST),
                    placed=r.alloc or None,  # its last allocation: a bounded session keeps it there
                )
            )
        return tuple(out)

    def host_specs(self) -> tuple[HostSpec, ...]:
        """K_h and H_h of every member (thesis §4.7: the leader defines the session's properties), as the
        members committed them to the agent table. A member whose entry is not committed yet — a host that
        just joined: its `publish_host` follows its join by one OAC — takes part in the session but bids for
        nothing (`draining`), like a host leaving. Read as the default (one core, no hardware), a joiner with
        a smaller capacity took agents in the join's session and gave them back in the session its entry
        triggers about `min_session_gap` later (docs/allocation.md, "Joins and hysteresis"); its entry triggers
        that session anyway, and only then does the joiner get agents, on its real K_h."""
        out = []
        hosts = self.view.table.hosts
        for n in self.view.members():
            h = hosts.get(n)
            if h is None:
                out.append(HostSpec(n, 1.0, frozenset(), True))
                continue
            cap = h.capacity if MIN_CAPACITY <= h.capacity <= MAX_CAPACITY else 1.0
            out.append(HostSpec(n, cap, frozenset(h.hardware), bool(h.draining)))
        return tuple(out)

    # ------------------------------------------------------------------ inputs

    def change(self, now: float, why: str, force: bool = False) -> list[GlueEffect]:
        """Alg. 4 l. 17: every host records the new situation; the leader starts a session when its
        `RebalancePolicy` allows (rate limit, periodic rebalancing unless paused). The node calls it only
        while it is a member."""
        t = self.view.table
        group = tuple(self.view.members())
        leader = bool(group) and group[0] == self.view.name
        pol = self.policy
        if t.paused:
            pol.pause()
        else:
            pol.resume()
        if pol.running and not self.allocator.busy():
            pol.finished(now)  # the running session expired or lost its group: changes need not wait for it
        if not len(t) and not force:
            # nothing to allocate: no session (its OAC(start)/OAC(finish) would only add traffic)
            self.allocator.on_change(group, (), self.host_specs(), start=False)
            return self._done()
        if why == "periodic":
            due = leader and pol.due(now)
        else:  # a group change cannot wait for the running session: that session can no longer finish
            due = pol.changed(now, urgent=why == "membership changed") if leader else False
        if force and leader and not due:
            pol.force(now)
            due = True
        self.allocator.committed_ses = max(self.allocator.committed_ses, t.ses_id)
        self.allocator.on_change(group, self.agent_specs(), self.host_specs(), start=due)
        if due:
            self._out.append(Note("allocation_session", {"reason": why, "hosts": len(group), "agents": len(t)}))
        self._alloc_effects(now)
        if leader:
            nxt = pol.deadline()
            if nxt is not None and nxt < 1e17:
                self._out.append(ArmTimer(AgentTimer("rebalance"), max(nxt, now)))
        return self._done()

    def applied(self, now: float, res: at.AgentApplied, payload: bytes) -> list[GlueEffect]:
        """A committed agent transaction that concerns the allocation (the node calls it while a member)."""
        k = res.kind
        if k == "start":  # expired starts too: their ids are used up (allocation.py)
            return self.start_committed(now, payload, res.reason if not res.ok else "")
        if k == "finish" and res.ok:
            return self.finish_committed(now)
        if k in ("create", "remove") and res.ok and not res.existing:
            return self.change(now, "agent list changed")
        if k == "host" and res.ok:
            return self.change(now, "host capabilities changed")
        if k == "control":
            return self.change(now, "rebalancing resumed")
        return []

    def view_changed(self, now: float, joined: bool, only_new_hosts: bool = False) -> list[GlueEffect]:
        """The member list changed (this host `joined` it, or not): publish this host's entry if the table may
        not hold it, and record the change (a session if this host leads).

        `only_new_hosts`: nobody left and none of the hosts that joined has its entry in the agent table yet.
        They would bid for nothing (`host_specs`), so a session now could only re-run the same agents over the
        same hosts — and CBBA's outcome depends on the order bids arrive in, so it sometimes moves agents
        between the old hosts for nothing (`haactl verify join` seed 189: two agents moved between old hosts,
        then again to the joiner one session later, AA-Join-Stable). The change is recorded without a
        session; each joiner's entry, one OAC after its join, starts the session that gives it agents
        (docs/allocation.md, "Joins and hysteresis")."""
        if joined or self.host_published is None:
            self._publish(force=True)
        if only_new_hosts:
            self.allocator.on_change(tuple(self.view.members()), self.agent_specs(), self.host_specs(), start=False)
            self._alloc_effects(now)
            return self._done()
        return self._done() + self.change(now, "membership changed")

    def run(self, now: float, member: bool) -> list[GlueEffect]:
        """An operator asks for an allocation session now: the leader starts one; another member passes the
        request on to the leader (`AgentHostMsg("alloc_run")`)."""
        members = self.view.members()
        if members and members[0] != self.view.name:
            return [HostSend(members[0], "alloc_run", "", 0)]
        return self.change(now, "operator", force=True) if member else []

    def on_update(self, src: str, data: bytes) -> bool:
        """A bid update from `src` (Alg. 4 l. 59); False if it does not decode. Its effects come with the
        `end_of_inbox` of the input batch."""
        try:
            upd = allocwire.decode_update(data)
        except ValueError:
            return False
        self.allocator.on_update(src, upd)
        return True

    def end_of_inbox(self, now: float) -> list[GlueEffect]:
        """Alg. 4 l. 77: every update received in this input has been processed."""
        self.allocator.end_of_inbox()
        self._alloc_effects(now)
        return self._done()

    def start_committed(self, now: float, payload: bytes, verdict: str | None = None) -> list[GlueEffect]:
        """OAC(start) applied (valid or expired: its id is used up either way, allocation.py), Alg. 4 l. 38.
        `verdict`: the agent table's decision on it ("" = valid), taken where the start applied in the total
        order. The allocator follows it: its own `start_valid` would read `committed_ses`, which `change` keeps
        in step with the table's `ses_id` — read after a whole batch of transactions applied, so possibly
        already past this start (a later start of the same batch), and the hosts would disagree."""
        try:
            tx = decode_tx(payload)
            # a start is proposed as an agent transaction (another kind raises AttributeError here)
            start = allocwire.decode_start(at.decode(cast(TxAgent, tx).data).start.data)
        except (ValueError, AttributeError) as e:
            self._out.append(Note("allocation_bad_start", {"reason": str(e)}))
            return self._done()
        self.allocator.on_start_committed(start, tuple(self.view.members()), self.view.table.agent_ids(), verdict)
        self._alloc_effects(now)
        self._settle(now)
        return self._done()

    def finish_committed(self, now: float) -> list[GlueEffect]:
        t = self.view.table
        alloc = {r.id: r.alloc for r in t if r.alloc}
        self.allocator.on_finish_committed(t.finished_ses, alloc, tuple(self.view.members()), t.agent_ids())
        self._alloc_effects(now)
        self._settle(now)
        return self._done()

    def _settle(self, now: float) -> None:
        """The session the leader waited for ended without an allocation (its start expired, its group changed):
        the changes that waited for it (`RebalancePolicy.changed`) are due now."""
        pol = self.policy
        members = self.view.members()
        if not pol.running or self.allocator.busy() or not members or members[0] != self.view.name:
            return
        pol.finished(now)
        nxt = pol.deadline() if pol.pending else None
        if nxt is not None:
            self._out.append(ArmTimer(AgentTimer("rebalance"), max(nxt, now)))

    def written(self, now: float, kind: str, ses_id: int, ok: bool, member: bool) -> list[GlueEffect]:
        """This host's OAC(start|finish|host) committed (`ok`) or was given up."""
        if kind == "start":
            start = self._starts.pop(ses_id, None)
            if start is not None:
                self.allocator.on_start_decided(start, ok, tuple(self.view.members()), self.view.table.agent_ids())
                self._alloc_effects(now)
        elif kind == "finish":
            self.allocator.on_finish_decided(ses_id, ok)
            self._alloc_effects(now)
        elif kind == "host" and not ok and member:
            # our host entry was given up or refused (the first member's, proposed before the group is formed,
            # is refused): publish it again while we are a member and the table does not hold it
            h = self.view.table.hosts.get(self.view.name)
            want = self.host_published
            if h is None or want is None or (h.capacity, tuple(sorted(h.hardware)), h.draining) != want:
                self._publish(force=True)
        return self._done()

    def publish_host(self, force: bool = False) -> list[GlueEffect]:
        """Commit this host's K_h, H_h and draining flag to the agent table. Every member publishes them, the
        defaults too: the allocation gives a member whose entry is missing no agent (`host_specs`)."""
        self._publish(force)
        return self._done()

    def _publish(self, force: bool) -> None:
        want = (self.capacity, self.hardware, self.draining)
        if force or self.host_published != want:
            self.host_published = want
            tx = apb.AgentTx()
            h = tx.host
            h.name, h.capacity, h.draining = self.view.name, self.capacity, self.draining
            h.hardware.extend(want[1])
            self._out.append(Propose(tx, "host", "", 0))

    def _alloc_effects(self, now: float) -> None:
        for e in self.allocator.drain():
            if isinstance(e, SendUpdate):
                data = allocwire.encode_update(e.update)
                for h in e.dsts:
                    self._out.append(HostSend(h, "alloc", "", 0, data))
            elif isinstance(e, ProposeStart):
                st = e.start
                tx = apb.AgentTx()
                tx.start.data = allocwire.encode_start(st)
                tx.start.ses_id, tx.start.leader = st.ses_id, st.leader
                tx.start.group.extend(st.group)
                tx.start.agents.extend(st.agent_ids)
                self._starts[st.ses_id] = st
                self._out.append(Propose(tx, "start", "", st.ses_id))
            elif isinstance(e, ProposeFinish):
                tx = apb.AgentTx()
                tx.finish.ses_id, tx.finish.leader = e.ses_id, self.view.name
                for a, h in sorted(e.allocation.items()):
                    tx.finish.allocation[a] = h
                self._out.append(Propose(tx, "finish", "", e.ses_id))
            elif isinstance(e, Allocated):
                self.policy.finished(now)
                self._out.append(Note("allocation_accepted", {
                    "session": e.ses_id, "agents": len(e.allocation), "unallocatable": list(e.unallocatable),
                    "deferred": len(e.deferred)}))
                members = self.view.members()
                if members and members[0] == self.view.name:
                    if e.deferred:  # a bounded session left agents without a place: the next session is theirs
                        self.policy.more(now)
                    # changes that waited for this session's finish (`RebalancePolicy.changed`) are due now
                    nxt = self.policy.deadline() if self.policy.pending else None
                    if nxt is not None:
                        self._out.append(ArmTimer(AgentTimer("rebalance"), max(nxt, now)))
            elif isinstance(e, Log):
                self._out.append(Note(e.event, e.fields))
