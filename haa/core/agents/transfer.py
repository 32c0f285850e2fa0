"""Agent transfer HAA-AT (thesis §4.8, Appendix II Alg. 5 freeze and Alg. 6 thaw): the host side, as a machine.

`Transfer` owns the state of every transfer this host takes part in — a freeze of an agent it runs (old
host, Alg. 5) and a thaw of an agent allocated to it (new host, Alg. 6) — and is driven through
`step(now, input) -> list[effect]`; it reads the agent table and the member list through an `AgentView`
and changes nothing else. `haa.core.agents.agentnode.AgentNode` decides *when* (its reconcile: an agent it runs
is allocated elsewhere -> `Freeze`; a frozen agent allocated to it -> `Thaw`), feeds it the events of the
instance and the committed transactions, and carries out the effects. `tests/test_agent_machines.py`
drives it alone. Line numbers are those of Alg. 5 (freeze) and Alg. 6 (thaw) as printed (the seed text of the
thesis: Alg. 5 at its line 2821, Alg. 6 at 2859, the prose at 877-879, the proofs at 2885-2915):

* freeze (old host, `Freeze`): ask the instance to freeze (l. 2), from then on hold messages for it as
  queue1 (l. 4, `Hold`), commit OAC(freeze) (ll. 5-8, retried while the agent is still ours), wait for the
  state (`StateArrived`, l. 19) and for a freezeAck from every host of the group at the time of the commit
  or its removal (l. 10), then route to queue2 (l. 11: `Hold` answers `PassOn`) and commit the state with
  OAC(release) (ll. 12-16);
* other hosts, on committing OAC(freeze) (ll. 21-24): route to queue2 (the node reads the table) and
  acknowledge (`HostSend` freeze_ack);
* thaw (new host, `Thaw`): spawn a shell (l. 2), hold messages in a local queue (l. 3), commit OAC(claim)
  (ll. 4-7; an invalid claim is abandoned, l. 18), wait for every claimAck or removal and for every active OAC
  to be decided (l. 9, `Progress` re-checks it), then send thaw(state, queue1, queue2, local) to the shell
  (l. 10, `StartAgent`) and route to it (l. 11, `Activate`);
* other hosts, on committing OAC(claim) (ll. 12-16): route to the new host and acknowledge.

Failure paths: a freeze whose instance dies (`ShellDied`) ends with `Lost` (the node reports the failure
through `haa.core.agents.recovery`, with queue1); a thaw's shell that dies before it was started is replaced up to
`MAX_RESPAWNS` times (the frozen state is in the table, nothing is lost), then `Lost`; a claim that commits
after others raised the epoch gets a shell for the real epoch; a claim refused (l. 18) or no longer possible
is abandoned (shell killed, held messages routed again); a removed host counts as acknowledged (l. 10, l. 9).

Choices where the pseudo-code is silent (docs/agents-host.md): queue1 stays with the old host and is
committed with the release (nobody reads it earlier; one OAC instead of one per message); claim hands both
queues to the new owner and clears them; messages carry sender-stream numbers, so the agent sees each
message once and in sender order even when the sender moved too (`haa.core.agents.routing`).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import assert_never

from haa.core.agentio import FreezeAgent, KillAgent, StartAgent
from haa.core.agents.agentstep import (
    MAX_RESPAWNS,
    Activate,
    AgentView,
    Cmd,
    Committed,
    Forget,
    Hold,
    HostSend,
    Note,
    Propose,
    Reconcile,
    Route,
    SetPhase,
    ShellUp,
    Timeline,
    spawn,
    start_messages,
)
from haa.core.agents.routing import Inbox, Outbox
from haa.core.ddb import agenttable as at
from haa.pb import agenttx_pb2 as apb

# ----------------------------------------------------------------------------------------------- inputs
# (and `Hold`, `ShellUp`, `Committed`, which both machines take: `haa.core.agents.agentstep`)


@dataclass(frozen=True, slots=True)
class Freeze:
    """freezeAgent(a), Alg. 5 l. 1: the node's instance (`agent`, `epoch`) is to be frozen; `inbox`/`outbox`
    are its stream positions (the node's; read when the release is proposed)."""

    agent: str
    epoch: int
    inbox: Inbox
    outbox: Outbox


@dataclass(frozen=True, slots=True)
class Thaw:
    """thawAgent(a), Alg. 6 l. 1: frozen `agent` is allocated to this host."""

    agent: str


@dataclass(frozen=True, slots=True)
class StateArrived:
    """Alg. 5 l. 19: (state) from the instance being frozen."""

    agent: str
    state: bytes


@dataclass(frozen=True, slots=True)
class ShellDied:
    """The instance of a freeze or a thaw died; `early`: within its start grace (the node measures it)."""

    agent: str
    reason: str
    early: bool


@dataclass(frozen=True, slots=True)
class Ack:
    """A freezeAck (Alg. 5 l. 24, `claim` False) or claimAck (Alg. 6 l. 16) from host `src`."""

    src: str
    agent: str
    claim: bool


@dataclass(frozen=True, slots=True)
class Written:
    """This host's OAC(`kind`) for (`agent`, `epoch`) committed (`ok`) or was given up (retry: ll. 8, 16, 7)."""

    kind: str
    agent: str
    epoch: int
    ok: bool


@dataclass(frozen=True, slots=True)
class Progress:
    """Re-check the wait of `agent` (Alg. 5 l. 10, Alg. 6 l. 9): a member was removed, or the poll timer."""

    agent: str


@dataclass(frozen=True, slots=True)
class Drop:
    """The node no longer has `agent`'s instance (removed, unknown, host leaving): forget its transfer."""

    agent: str


TransferInput = Freeze | Thaw | Hold | StateArrived | ShellUp | ShellDied | Ack | Committed | Written | Progress | Drop

# ----------------------------------------------------------------------------------------------- effects


@dataclass(frozen=True, slots=True)
class PassOn:
    """`m` is not held here (after l. 11): route it by the table."""

    m: apb.RoutedMsg


@dataclass(frozen=True, slots=True)
class Lost:
    """The instance of (`agent`, `epoch`) is gone mid-transfer: a failure for `haa.core.agents.recovery`, with the
    messages it held (`msgs`) and whether the failure was `early`."""

    agent: str
    epoch: int
    reason: str
    early: bool
    msgs: tuple[apb.RoutedMsg, ...]


@dataclass(frozen=True, slots=True)
class ClaimedWithoutShell:
    """OAC(claim) of this host committed but no shell waits for it: report the agent failed."""

    agent: str
    epoch: int


@dataclass(frozen=True, slots=True)
class PollLater:
    """Alg. 6 l. 9 waits for OACs to be decided: `Progress` again a little later."""


TransferEffect = (
    Cmd | Propose | HostSend | Timeline | Note | Route | SetPhase | Activate | Forget | Reconcile | PassOn | Lost
    | ClaimedWithoutShell | PollLater
)

# ----------------------------------------------------------------------------------------------- state


@dataclass(slots=True)
class _Freeze:
    """Alg. 5 on the old host."""

    epoch: int
    inbox: Inbox
    outbox: Outbox
    acks: set[str]
    committed: bool = False  # OAC(freeze) applied here (l. 9)
    after_l11: bool = False
    state: bytes | None = None  # l. 19
    q1: list[apb.RoutedMsg] = field(default_factory=list)  # l. 4
    wait_acks: set[str] = field(default_factory=set)  # commitGroup (l. 9)


@dataclass(slots=True)
class _Thaw:
    """Alg. 6 on the new host."""

    epoch: int
    phase: str = "claiming"  # then "thawing" once OAC(claim) committed
    ready: bool = False  # the shell said hello
    respawns: int = 0
    local_q: list[apb.RoutedMsg] = field(default_factory=list)  # l. 3
    handed: list[apb.RoutedMsg] = field(default_factory=list)  # queue1 then queue2, from the claim
    state: bytes | None = None
    inbox: Inbox | None = None
    outbox: Outbox = field(default_factory=Outbox)
    life: int = 0
    wait_acks: set[str] = field(default_factory=set)  # commitGroup (l. 8)
    acks: set[str] = field(default_factory=set)


class Transfer:
    """See the module docstring."""

    def __init__(self, view: AgentView) -> None:
        self.view = view
        self.freezes: dict[str, _Freeze] = {}
        self.thaws: dict[str, _Thaw] = {}
        self._out: list[TransferEffect] = []

    def step(self, now: float, inp: TransferInput) -> list[TransferEffect]:
        match inp:
            case Freeze():
                self._freeze(inp)
            case Thaw():
                self._thaw(inp.agent)
            case Hold():
                self._hold(inp.m)
            case StateArrived():
                f = self.freezes.get(inp.agent)
                if f is not None:
                    f.state = inp.state
                    self._freeze_progress(inp.agent, f)
            case ShellUp():
                t = self.thaws.get(inp.agent)
                if t is not None:
                    t.ready = True
                    self._thaw_progress(inp.agent, t)
            case ShellDied():
                self._died(inp)
            case Ack():
                self._ack(inp)
            case Committed():
                self._committed(inp.res)
            case Written():
                self._written(inp)
            case Progress():
                if inp.agent in self.freezes:
                    self._freeze_progress(inp.agent, self.freezes[inp.agent])
                elif inp.agent in self.thaws:
                    self._thaw_progress(inp.agent, self.thaws[inp.agent])
            case Drop():
                self.freezes.pop(inp.agent, None)
                self.thaws.pop(inp.agent, None)
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    # ------------------------------------------------------------------ Alg. 5: freeze (old host)

    def _freeze(self, inp: Freeze) -> None:
        r = self.view.table.get(inp.agent)
        assert r is not None
        f = _Freeze(inp.epoch, inp.inbox, inp.outbox, set())  # l. 10 counts this freeze's acks only
        self.freezes[inp.agent] = f
        self._out.append(Cmd(FreezeAgent(inp.agent, inp.epoch)))  # l. 2
        # l. 3 (clear the queues): they are empty while the agent is active (haa.core.ddb.agenttable)
        # l. 4: from now on, messages for a are held as queue1 (`Hold`)
        me = self.view.name
        self._out.append(Timeline(inp.agent, "freezing", f"to {r.alloc}" if r.alloc and r.alloc != me else ""))
        self._propose_freeze(inp.agent, f)

    def _propose_freeze(self, agent: str, f: _Freeze) -> None:
        tx = apb.AgentTx()
        tx.freeze.id, tx.freeze.host, tx.freeze.epoch = agent, self.view.name, f.epoch
        self._out.append(Propose(tx, "freeze", agent, f.epoch))  # ll. 5-8

    def _freeze_progress(self, agent: str, f: _Freeze) -> None:
        """l. 10: wait until the state arrived and every host of commitGroup acknowledged or was removed.

        A host sends its freezeAck once it committed OAC(freeze) (l. 24), after any message it had sent here for
        the agent before it knew (one channel, in order): with every ack in, nothing of theirs is on its way to
        this host any more, and what arrived went into queue1, which commits with the state in OAC(release).
        Only the acks of this freeze count. Counting the claimAcks of the thaw that had started the instance
        here (as the code did before transfer became a machine) released at once: a message a host had sent
        before it applied the freeze reached this host after l. 11 and was pushed to queue2 in a transaction of
        this host's own, which is lost when this host is removed before it commits, though the release did
        (`haactl verify transfer --seed 599 --hosts 5`: AT-Consistency, a receiver and a sender that never
        crashed)."""
        if not f.committed or f.state is None or f.after_l11:
            return
        members = set(self.view.members())
        if any(h in members and h not in f.acks for h in f.wait_acks):
            return
        f.after_l11 = True  # l. 11: from now on messages for a go to queue2
        self._propose_release(agent, f)  # ll. 12-16

    def _propose_release(self, agent: str, f: _Freeze) -> None:
        tx = apb.AgentTx()
        rel = tx.release
        rel.id, rel.host, rel.epoch = agent, self.view.name, f.epoch
        rel.state = f.state or b""
        rel.inbox.extend(f.inbox.positions())
        rel.outbox.extend(f.outbox.positions())
        # queue1 (l. 4) and whatever the inbox still holds back behind a gap
        rel.pending.extend(f.inbox.held())
        rel.pending.extend(f.q1)
        self._out.append(Propose(tx, "release", agent, f.epoch))

    # ------------------------------------------------------------------ Alg. 6: thaw (new host)

    def _thaw(self, agent: str) -> None:
        r = self.view.table.get(agent)
        assert r is not None
        t = _Thaw(r.epoch + 1)
        self.thaws[agent] = t
        self._out.append(SetPhase(agent, t.epoch, "claiming"))
        self._out.append(spawn(r, t.epoch))  # l. 2
        # l. 3: messages for a are held in t.local_q (`Hold`)
        self._out.append(Timeline(agent, "thawing"))
        self._propose_claim(agent, t)

    def _propose_claim(self, agent: str, t: _Thaw) -> None:
        tx = apb.AgentTx()
        tx.claim.id, tx.claim.host = agent, self.view.name
        self._out.append(Propose(tx, "claim", agent, t.epoch))  # ll. 4-7

    def _thaw_progress(self, agent: str, t: _Thaw) -> None:
        """l. 9: every claimAck (or removal), every active OAC decided, and the shell is up."""
        if t.phase != "thawing" or not t.ready:
            return
        members = set(self.view.members())
        if any(h in members and h not in t.acks for h in t.wait_acks):
            return
        if not self.view.oacs_settled():
            self._out.append(PollLater())
            return
        assert t.inbox is not None
        msgs = start_messages(t.inbox, t.handed, t.local_q)  # l. 10: queue1, queue2, local queue in that order
        del self.thaws[agent]
        self._out.append(Activate(agent, t.epoch, t.inbox, t.outbox, t.life))  # l. 11
        self._out.append(Cmd(StartAgent(agent, t.epoch, "thaw", t.state, msgs)))
        self._out.append(Timeline(agent, "thawed", f"{len(msgs)} queued messages"))
        self._out.append(Reconcile(agent))

    def _reshell(self, agent: str, t: _Thaw, r: at.AgentRecord) -> None:
        """Replace a shell spawned for a stale epoch by one for the agent's current epoch."""
        self._out.append(Cmd(KillAgent(agent, t.epoch, f"stale shell (epoch {t.epoch}, now {r.epoch})")))
        t.epoch = r.epoch
        t.ready = False
        self._out.append(SetPhase(agent, t.epoch, t.phase))
        self._out.append(spawn(r, t.epoch))

    def _abandon(self, agent: str, t: _Thaw, why: str) -> None:
        del self.thaws[agent]
        self._out.append(Forget(agent))
        self._out.append(Cmd(KillAgent(agent, t.epoch, f"abandoned: {why}")))
        self._out.append(Note("agent_abandoned", {"agent": agent, "epoch": t.epoch, "reason": why}))
        if t.local_q:  # messages held for the shell go where the table says now
            self._out.append(Route(tuple(t.local_q)))

    # ------------------------------------------------------------------ inputs of both halves

    def _hold(self, m: apb.RoutedMsg) -> None:
        f = self.freezes.get(m.dst)
        if f is not None and not f.after_l11:
            f.q1.append(m)  # Alg. 5 l. 4
            return
        t = self.thaws.get(m.dst)
        if t is not None:
            t.local_q.append(m)  # Alg. 6 l. 3
            return
        self._out.append(PassOn(m))

    def _died(self, inp: ShellDied) -> None:
        agent = inp.agent
        f = self.freezes.pop(agent, None)
        if f is not None:
            self._out.append(Lost(agent, f.epoch, inp.reason, inp.early, tuple(f.q1)))
            return
        t = self.thaws.get(agent)
        if t is None:
            return
        r = self.view.table.get(agent)
        if t.respawns < MAX_RESPAWNS and r is not None:
            # the shell died before it was started: nothing of the agent was in it, start another one
            t.respawns += 1
            t.ready = False
            self._out.append(Note("shell_respawn", {"agent": agent, "epoch": t.epoch, "reason": inp.reason}))
            self._out.append(spawn(r, t.epoch))
            return
        del self.thaws[agent]
        self._out.append(Lost(agent, t.epoch, inp.reason, True, (*t.local_q, *t.handed)))

    def _ack(self, inp: Ack) -> None:
        if inp.claim:
            t = self.thaws.get(inp.agent)
            if t is not None:
                t.acks.add(inp.src)
                self._thaw_progress(inp.agent, t)
            return
        f = self.freezes.get(inp.agent)
        if f is not None:
            f.acks.add(inp.src)
            self._freeze_progress(inp.agent, f)

    def _committed(self, res: at.AgentApplied) -> None:
        me = self.view.name
        agent = res.agent
        if res.kind == "freeze":  # Alg. 5 l. 9 (old host) and ll. 21-24 (every other host)
            if not res.ok:
                return
            if res.host != me:  # ll. 22-24
                # l. 23: messages for a now go to queue2 (the node's routing reads the table: status freezing)
                r = self.view.table.get(agent)
                self._out.append(HostSend(res.host, "freeze_ack", agent, r.epoch if r else 0))  # l. 24
                return
            f = self.freezes.get(agent)
            if f is None:
                return
            f.committed = True
            f.wait_acks = {m for m in self.view.members() if m != me}  # l. 9: commitGroup
            f.acks &= f.wait_acks
            self._freeze_progress(agent, f)
        elif res.kind == "release":
            if res.ok and res.host == me and self.freezes.pop(agent, None) is not None:
                self._out.append(Forget(agent))
                self._out.append(Timeline(agent, "frozen"))
                # anything routed to queue2 meanwhile was pushed; nothing is left here
        elif res.kind == "claim":  # Alg. 6 ll. 12-18 on every host
            self._claim_committed(res)

    def _claim_committed(self, res: at.AgentApplied) -> None:
        me = self.view.name
        agent = res.agent
        t = self.thaws.get(agent)
        if not res.ok:
            if res.host == me and t is not None and t.phase == "claiming":
                self._abandon(agent, t, res.reason)  # l. 18
            return
        r = self.view.table.get(agent)
        assert r is not None
        if res.host != me:  # ll. 14-16
            # l. 15: route to the new host (the node's routing reads the table: active, owner q)
            self._out.append(HostSend(res.host, "claim_ack", agent, r.epoch))
            return
        if t is None or t.phase != "claiming":
            # we claimed but no longer hold the shell (should not happen): release the claim as a failure
            self._out.append(ClaimedWithoutShell(agent, r.epoch))
            return
        if t.epoch != r.epoch:
            # the claim was proposed long ago and committed after other claims raised the epoch (the agent came
            # back to us): the shell was spawned for the epoch we expected then; start one for the real one
            self._reshell(agent, t, r)
        t.phase = "thawing"
        self._out.append(SetPhase(agent, t.epoch, "thawing"))
        t.state = r.state
        t.inbox = Inbox(r.inbox)
        t.outbox = Outbox(r.outbox)
        t.life = r.life
        t.handed = list(res.msgs)  # queue1 then queue2
        t.wait_acks = {m for m in self.view.members() if m != me}  # l. 8: commitGroup
        t.acks &= t.wait_acks
        self._thaw_progress(agent, t)

    def _written(self, inp: Written) -> None:
        agent, epoch = inp.agent, inp.epoch
        if inp.ok:
            return
        r = self.view.table.get(agent)
        if inp.kind == "freeze":  # l. 8: do ... while not committed (while the agent is still ours, freezing)
            f = self.freezes.get(agent)
            if f is not None and f.epoch == epoch and not f.committed:
                self._propose_freeze(agent, f)
        elif inp.kind == "release":  # l. 16: retried while the agent is still ours
            f = self.freezes.get(agent)
            if (f is not None and f.epoch == epoch and r is not None and r.owner == self.view.name
                    and r.status == at.FREEZING and r.epoch == epoch):
                self._propose_release(agent, f)
        elif inp.kind == "claim":
            t = self.thaws.get(agent)
            if t is None or t.epoch != epoch or t.phase != "claiming":
                return
            if r is not None and r.alloc == self.view.name and r.status == at.FROZEN:  # l. 7, while still possible
                self._propose_claim(agent, t)
            else:
                self._abandon(agent, t, "claim no longer possible")
