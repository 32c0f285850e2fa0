"""Agent transfer HAA-AT (thesis §4.8, Appendix II Alg. 5 freeze and Alg. 6 thaw), the host side.

A mixin of `haa.hostd.agentnode.AgentNode` (it uses the node's table, routing, proposals and commands), kept
in its own file so that the pseudo-code can be read next to it. Line numbers are Alg. 5 (freeze) and Alg. 6
(thaw). In short:

* freeze (old host, `_freeze`): ask the instance to freeze (l. 2), from then on hold messages for it as
  queue1 (l. 4), commit OAC(freeze) (ll. 5-8, retried while the agent is still ours), wait for the state and
  for a freezeAck from every host of the group at the time of the commit or its removal (l. 10), then route
  to queue2 (l. 11) and commit the state with OAC(release) (ll. 12-16);
* other hosts, on committing OAC(freeze) (ll. 21-24): route to queue2 and acknowledge;
* thaw (new host, `_thaw`): spawn a shell (l. 2), hold messages in a local queue (l. 3), commit OAC(claim)
  (ll. 4-7; an invalid claim is abandoned, l. 18), wait for every claimAck or removal and for every active OAC
  to be decided (l. 9), then send thaw(state, queue1, queue2, local) to the shell (l. 10) and route to it
  (l. 11);
* other hosts, on committing OAC(claim) (ll. 12-16): route to the new host and acknowledge.

Choices where the pseudo-code is silent (docs/agents-host.md): queue1 stays with the old host and is
committed with the release (nobody reads it earlier; one OAC instead of one per message); claim hands both
queues to the new owner and clears them; messages carry sender-stream numbers, so the agent sees each
message once and in sender order even when the sender moved too (`haa.hostd.routing`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from haa.hostd import agenttable as at
from haa.hostd.agentio import FreezeAgent, KillAgent, SpawnShell, StartAgent
from haa.hostd.routing import Inbox, Outbox
from haa.pb import agenttx_pb2 as apb

if TYPE_CHECKING:
    from haa.hostd.agentnode import AgentNode, Local


class TransferMixin:
    # ------------------------------------------------------------------ Alg. 5: freeze (old host)

    def _freeze(self: AgentNode, loc: Local) -> None:
        """freezeAgent(a), Alg. 5 l. 1."""
        r = self.table.get(loc.id)
        assert r is not None
        loc.phase = "freezing"
        loc.after_l11 = False
        loc.frozen_state = None
        self._cmd(FreezeAgent(loc.id, loc.epoch))  # l. 2
        # l. 3 (clear the queues): they are empty while the agent is active (haa.hostd.agenttable)
        # l. 4: from now on, messages for a are held as queue1 (`_route`, phase "freezing")
        self._timeline(loc.id, "freezing", f"to {r.alloc}" if r.alloc and r.alloc != self.name else "")
        self._propose_freeze(loc)

    def _propose_freeze(self: AgentNode, loc: Local) -> None:
        tx = apb.AgentTx()
        tx.freeze.id, tx.freeze.host, tx.freeze.epoch = loc.id, self.name, loc.epoch
        self._propose(tx, ("freeze", loc.id, loc.epoch))  # ll. 5-8

    def _on_freeze_done(self: AgentNode, agent: str, epoch: int, ok: bool) -> None:
        """l. 8: do ... while not committed (retried while the agent is still ours and freezing)."""
        loc = self.local.get(agent)
        if ok or loc is None or loc.epoch != epoch or loc.phase != "freezing" or loc.freeze_committed:
            return
        self._propose_freeze(loc)

    def _on_freeze_applied(self: AgentNode, res: at.AgentApplied) -> None:
        """Alg. 5 ll. 9 (old host) and ll. 21-24 (every other host)."""
        if not res.ok:
            return
        r = self.table.get(res.agent)
        if res.host != self.name:  # ll. 22-24
            # l. 23: messages for a now go to queue2 (`_route` reads the table: status freezing)
            self._send_agent_host(res.host, "freeze_ack", res.agent, r.epoch if r else 0, b"")  # l. 24
            return
        loc = self.local.get(res.agent)
        if loc is None:
            return
        loc.freeze_committed = True
        loc.wait_acks = {m for m in self._member_names() if m != self.name}  # l. 9: commitGroup
        loc.acks &= loc.wait_acks
        self._freeze_progress(loc)

    def _on_freeze_ack(self: AgentNode, src: str, agent: str) -> None:
        loc = self.local.get(agent)
        if loc is not None and loc.phase == "freezing":
            loc.acks.add(src)
            self._freeze_progress(loc)

    def _on_frozen(self: AgentNode, loc: Local, state: bytes) -> None:
        """Alg. 5 l. 19 arrived: (state) from a."""
        if loc.phase != "freezing":
            return
        loc.frozen_state = state
        loc.ready = False  # the instance has ended
        self._freeze_progress(loc)

    def _freeze_progress(self: AgentNode, loc: Local) -> None:
        """l. 10: wait until the state arrived and every host of commitGroup acknowledged or was removed."""
        if loc.phase != "freezing" or not loc.freeze_committed or loc.frozen_state is None or loc.after_l11:
            return
        members = set(self._member_names())
        if any(h in members and h not in loc.acks for h in loc.wait_acks):
            return
        loc.after_l11 = True  # l. 11: from now on messages for a go to queue2
        self._propose_release(loc)  # ll. 12-16

    def _propose_release(self: AgentNode, loc: Local) -> None:
        tx = apb.AgentTx()
        rel = tx.release
        rel.id, rel.host, rel.epoch = loc.id, self.name, loc.epoch
        rel.state = loc.frozen_state or b""
        assert loc.inbox is not None
        rel.inbox.extend(loc.inbox.positions())
        rel.outbox.extend(loc.outbox.positions())
        # queue1 (l. 4) and whatever the inbox still holds back behind a gap
        rel.pending.extend(loc.inbox.held())
        rel.pending.extend(loc.q1)
        self._propose(tx, ("release", loc.id, loc.epoch))

    def _on_release_done(self: AgentNode, agent: str, epoch: int, ok: bool) -> None:
        """l. 16: retried while the agent is still ours."""
        loc = self.local.get(agent)
        if ok or loc is None or loc.epoch != epoch or loc.phase != "freezing":
            return
        r = self.table.get(agent)
        if r is not None and r.owner == self.name and r.status == at.FREEZING and r.epoch == epoch:
            self._propose_release(loc)

    def _on_release_applied(self: AgentNode, res: at.AgentApplied) -> None:
        if not res.ok or res.host != self.name:
            return
        loc = self.local.pop(res.agent, None)
        if loc is not None:
            self._timeline(res.agent, "frozen")
            # anything routed to queue2 meanwhile was pushed; nothing is left here

    # ------------------------------------------------------------------ Alg. 6: thaw (new host)

    def _thaw(self: AgentNode, r: at.AgentRecord) -> None:
        """thawAgent(a), Alg. 6 l. 1."""
        loc = self._new_local(r, r.epoch + 1, "claiming", "thaw")
        self._cmd(SpawnShell(r.id, loc.epoch, r.type, r.name, r.spec.config, r.parent))  # l. 2
        # l. 3: messages for a are held in loc.local_q (`_route`, phase "claiming"/"thawing")
        self._timeline(r.id, "thawing")
        self._propose_claim(loc)

    def _propose_claim(self: AgentNode, loc: Local) -> None:
        tx = apb.AgentTx()
        tx.claim.id, tx.claim.host = loc.id, self.name
        self._propose(tx, ("claim", loc.id, loc.epoch))  # ll. 4-7

    def _on_claim_done(self: AgentNode, agent: str, epoch: int, ok: bool) -> None:
        loc = self.local.get(agent)
        if ok or loc is None or loc.epoch != epoch or loc.phase != "claiming":
            return
        r = self.table.get(agent)
        if r is not None and r.alloc == self.name and r.status == at.FROZEN:  # l. 7, while still possible
            self._propose_claim(loc)
        else:
            self._abandon(loc, "claim no longer possible")

    def _on_claim_applied(self: AgentNode, res: at.AgentApplied) -> None:
        """Alg. 6 ll. 12-18 on every host."""
        loc = self.local.get(res.agent)
        if not res.ok:
            if res.host == self.name and loc is not None and loc.phase == "claiming":
                self._abandon(loc, res.reason)  # l. 18
            return
        r = self.table.get(res.agent)
        assert r is not None
        if res.host != self.name:  # ll. 14-16
            # l. 15: route to the new host (`_route` reads the table: active, owner q)
            self._send_agent_host(res.host, "claim_ack", res.agent, r.epoch, b"")
            return
        if loc is None or loc.phase != "claiming":
            # we claimed but no longer hold the shell (should not happen): release the claim as a failure
            self._report_failed(r.id, r.epoch, "claimed without a shell")
            return
        if loc.epoch != r.epoch:
            # the claim was proposed long ago and committed after other claims raised the epoch (the agent came
            # back to us): the shell was spawned for the epoch we expected then; start one for the real one
            self._reshell(loc, r)
        loc.phase = "thawing"
        loc.state = r.state
        loc.inbox = Inbox(r.inbox)
        loc.outbox = Outbox(r.outbox)
        loc.life = r.life
        loc.handed = list(res.msgs)  # queue1 then queue2
        loc.wait_acks = {m for m in self._member_names() if m != self.name}  # l. 8: commitGroup
        loc.acks &= loc.wait_acks
        self._thaw_progress(loc)

    def _on_claim_ack(self: AgentNode, src: str, agent: str) -> None:
        loc = self.local.get(agent)
        if loc is not None and loc.phase in ("claiming", "thawing"):
            loc.acks.add(src)
            self._thaw_progress(loc)

    def _thaw_progress(self: AgentNode, loc: Local) -> None:
        """l. 9: every claimAck (or removal), every active OAC decided, and the shell is up."""
        if loc.phase != "thawing" or not loc.ready:
            return
        members = set(self._member_names())
        if any(h in members and h not in loc.acks for h in loc.wait_acks):
            return
        if not self._oacs_settled():
            self._poll_later()
            return
        assert loc.inbox is not None
        msgs = []
        for m in (*loc.handed, *loc.local_q):  # l. 10: queue1, queue2, local queue in that order
            msgs += loc.inbox.offer(m)
        loc.handed, loc.local_q = [], []
        loc.phase = "active"  # l. 11
        self._cmd(StartAgent(loc.id, loc.epoch, "thaw", loc.state, msgs))
        loc.state = None
        self._timeline(loc.id, "thawed", f"{len(msgs)} queued messages")
        self._reconcile_one(loc.id)

    def _reshell(self: AgentNode, loc: Local, r: at.AgentRecord) -> None:
        """Replace a shell spawned for a stale epoch by one for the agent's current epoch."""
        self._cmd(KillAgent(loc.id, loc.epoch, f"stale shell (epoch {loc.epoch}, now {r.epoch})"))
        loc.epoch = r.epoch
        loc.ready = False
        self._cmd(SpawnShell(r.id, loc.epoch, r.type, r.name, r.spec.config, r.parent))

    def _abandon(self: AgentNode, loc: Local, why: str) -> None:
        self.local.pop(loc.id, None)
        self._cmd(KillAgent(loc.id, loc.epoch, f"abandoned: {why}"))
        self._log("agent_abandoned", agent=loc.id, epoch=loc.epoch, reason=why)
        for m in loc.local_q:  # messages held for the shell go where the table says now
            self._route(m)
