"""The agent layer of one host: allocation, routing, transfer, backup and recovery, composed as one sans-I/O node.

`AgentNode` wraps a host's `MembershipNode` (Alg. 3, which owns the failure detector, OAC and the global
state) and composes what thesis Chapter 4 builds on it for agents; each part is a machine of its own:

* the agent table (`haa.core.ddb.agenttable`, part of the global state): every change is an `AgentTx` committed
  through OAC (`haa.core.agents.agentrequests` builds the operator's), so every member agrees on which agents exist, who
  owns each and what is queued for it;
* allocation HAA-AA (Alg. 4): `haa.core.agents.allocglue.AllocGlue` feeds the table to the `Allocator` and says when
  the leader starts a session (membership, agent list or capabilities changed, periodically, rate-limited);
* transfer (Alg. 5-6, `haa.core.agents.transfer.Transfer`) and backup / recovery (Alg. 7-8,
  `haa.core.agents.recovery.Recovery`), each with its own state and one `step(now, input) -> effects`;
* routing (`haa.core.agents.agentroute.Router`): every message between agents goes through the hosts: to the local
  instance through its `Inbox` (exactly once, sender order, `haa.core.agents.routing`), to the owner host, held by
  the transfer or recovery in progress here, or into the agent's queue in the table while it is frozen, new
  or crashed;
* reconcile (`_reconcile_one`, decided by `haa.core.agents.agentplan.reconcile`): after every change of the table
  each host compares what the table says with the instances it runs — an agent it runs but is no longer
  allocated is frozen, a frozen agent allocated to it is thawed, a new or crashed agent allocated to it is
  recovered, an instance the table does not know is killed;
* graceful leave (thesis AF-1, `haa.core.agents.agentleave.Leave`): `leave()` first marks the host draining (it gets
  no agents), waits until it runs none, then leaves the group.

The node keeps one record per instance (`local`: phase, epoch, streams; `haa.core.agents.agentstep.Local`) and
carries out the machines' effects in the order they come (`_apply`). Agent instances are not started here:
the node emits commands (`haa.core.agentio`: SpawnShell, StartAgent, DeliverAgent, FreezeAgent, KillAgent,
AnswerAgent) and takes events back as `InstanceEvent` inputs. Every input, the host's and the agent layer's, goes
through `step(now, input)` (`haa.core.inputs.AgentInput`); `drain()` returns the typed effects (`AgentNodeEffect`).
What the node reads of the membership node is `m` (its state, OAC, members). The daemon runs OS processes
(`haa.hostd.agentproc`); the simulator runs simulated agents (`haa.lab.dsim.agents`). No I/O, no clock, no
randomness: ids of new agents come from the caller.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import assert_never, cast

from haa.core.agentio import (
    AgentCommand,
    AgentEvent,
    AgentOpDone,
    AgentTimeline,
    AnswerAgent,
    KillAgent,
    OperatorReply,
    Sent,
    SpawnChild,
    StartAgent,
    Stopped,
)
from haa.core.agents import agentplan as plan
from haa.core.agents import agentrequests as ops
from haa.core.agents import recovery as rc
from haa.core.agents import transfer as tr
from haa.core.agents.agentleave import Go, Leave, LeaveEffect, PublishHost
from haa.core.agents.agentrequests import AgentWrite
from haa.core.agents.agentroute import RouteEffect, Router
from haa.core.agents.agentstep import (
    Activate,
    AgentTimer,
    ArmTimer,
    Cmd,
    Forget,
    Hold,
    HostSend,
    Local,
    Note,
    Propose,
    Reconcile,
    Retries,
    Route,
    SetPhase,
    Timeline,
)
from haa.core.agents.allocglue import AllocGlue, GlueEffect
from haa.core.ddb import agenttable as at
from haa.core.effects import Effect as CoreEffect
from haa.core.effects import Log, Send, SetTimer
from haa.core.inputs import (
    AgentInput,
    CreateAgent,
    FdReport,
    InstanceEvent,
    LeaveGroup,
    MoveAgent,
    OperatorSend,
    PeerInfo,
    Receive,
    RemoveAgent,
    ReportCosts,
    RunAllocation,
    SetPaused,
    Start,
    Submit,
    TimerFired,
    Undeliverable,
)
from haa.core.membership.groupeffects import NodeEffect
from haa.core.membership.membership import AppliedTx, Left, MembershipNode, ViewChange, WriteDone
from haa.core.messages import AgentHostMsg
from haa.core.oac.oac import DONE
from haa.pb import agenttx_pb2 as apb

__all__ = ["AgentConfig", "AgentNode", "AgentNodeEffect", "Local"]

#: a write of the agent layer that was given up or refused is retried after this long (seconds)
RETRY_AFTER = 0.1
#: the agent layer's own writes whose outcome a machine waits for (retried: "do ... while not committed")
_TRANSFER_WRITES = frozenset({"freeze", "release", "claim"})
_RECOVERY_WRITES = frozenset({"recovered", "failed"})
_ALLOC_WRITES = frozenset({"host", "start", "finish"})
#: what the machines ask the node to do
Effect = tr.TransferEffect | rc.RecoveryEffect | GlueEffect | RouteEffect | ops.OpEffect | LeaveEffect
#: what `drain()` returns: the host's effects (the core's and the membership node's, but the agent layer's own
#: writes), the commands for the agent instances, and the answers to operator requests
AgentNodeEffect = CoreEffect | NodeEffect | AgentCommand | AgentOpDone | OperatorReply | AgentTimeline


@dataclass(frozen=True, slots=True)
class AgentConfig:
    #: this host's processing capacity K_h (1.0 = one baseline core) and hardware H_h (Alg. 4)
    capacity: float = 1.0
    hardware: tuple[str, ...] = ()
    #: periodic load-balancing sessions (0 = none) and the shortest gap between two sessions (rate limit)
    rebalance_period: float = 30.0
    min_session_gap: float = 1.0
    #: how often waits on "all active OACs decided" (Alg. 6 l. 9) are re-checked
    poll: float = 0.01
    #: messages per queue push transaction
    max_push: int = 512
    #: graceful leave: hand agents over for at most this long, then leave anyway (they are recovered)
    drain_timeout: float = 10.0
    #: an instance that dies within this long after it was started (or before) failed early: a start failure,
    #: counted in the table (`AgentFailed.early`; agenttable.MAX_START_FAILURES of them in a row -> "failed")
    start_grace: float = 10.0
    #: the host that recovers an agent after n consecutive start failures first waits
    #: min(backoff_cap, backoff_base * 2 ** (n - 1)) seconds (docs/agents-host.md, "Start failures")
    backoff_base: float = 0.5
    backoff_cap: float = 30.0


class AgentNode:
    """See the module docstring."""

    def __init__(self, node: MembershipNode, config: AgentConfig | None = None) -> None:
        self.m = node
        self.config = cfg = config or AgentConfig()
        self.name = node.name
        self.local: dict[str, Local] = {}  # the instances this host runs or prepares
        self.out: list[AgentNodeEffect] = []
        self.counters: Counter[str] = Counter()
        self.transfer = tr.Transfer(self)
        self.recovery = rc.Recovery(self, rc.BackoffConfig(cfg.backoff_base, cfg.backoff_cap))
        self.alloc = AllocGlue(self, cfg.rebalance_period, cfg.min_session_gap, cfg.capacity, cfg.hardware)
        self.router = Router(self, self.local, cfg.max_push, self.counters)
        self.ops = ops.Operations(lambda: self.table)
        self.leaving = Leave(self, cfg.drain_timeout)
        self.retries = Retries(RETRY_AFTER)
        self._alloc_msgs = self._seq = 0
        self._now = 0.0
        self._poll_armed = False

    # ------------------------------------------------------------------ the view the machines read (AgentView)

    @property
    def table(self) -> at.AgentTable:
        return self.m.state.agents

    def members(self) -> list[str]:
        return [m.name for m in self.m.state.members]

    def oacs_settled(self) -> bool:
        """Alg. 6 l. 9 / Alg. 8 l. 3: every OAC this host knows of is decided and delivered."""
        return not self.m.direct_q and all(tx.state == DONE or not tx.content for tx in self.m.core.oac.txs.values())

    # ------------------------------------------------------------------ carrying out the machines' effects

    def _tr(self, inp: tr.TransferInput) -> None:
        self._apply(self.transfer.step(self._now, inp))

    def _rc(self, inp: rc.RecoveryInput) -> None:
        self._apply(self.recovery.step(self._now, inp))

    def _route(self, m: apb.RoutedMsg, here: bool = True) -> None:
        self._apply(self.router.route(m, here))

    def _apply(self, effects: Sequence[Effect]) -> None:
        for e in effects:
            match e:
                case Cmd():
                    self._cmd(e.cmd)
                case AnswerAgent():
                    self._cmd(e)
                case Propose():
                    self._seq += 1
                    req = AgentWrite(e.kind, e.agent, e.epoch, self._seq)
                    self.m.step(self._now, Submit(at.encode(e.tx), req, "agent"))
                case HostSend():
                    inc = next((m.inc for m in self.m.state.members if m.name == e.host), 0)
                    if inc and e.host != self.name:
                        self.out.append(Send(e.host, inc, AgentHostMsg(e.kind, e.agent, e.epoch, e.data)))
                        self.counters[f"sent_{e.kind}"] += 1
                case Timeline():
                    r = self.table.get(e.agent)
                    self.out.append(AgentTimeline(e.agent, r.name if r else e.agent[:8], e.event, self.name, e.detail))
                case Note():
                    self.out.append(Log(e.event, e.fields))
                case OperatorReply() | AgentOpDone():
                    self.out.append(e)
                case ArmTimer():
                    self.out.append(SetTimer(e.key, e.at))
                case Route():
                    for m in e.msgs:
                        self._route(m)
                case tr.PassOn():  # after Alg. 5 l. 11: not to the instance here, by the table
                    self._route(e.m, here=False)
                case SetPhase():
                    loc = self.local.setdefault(e.agent, Local(e.agent, e.epoch, e.phase))
                    loc.epoch, loc.phase = e.epoch, e.phase
                case Activate():
                    loc = self.local[e.agent]
                    loc.phase, loc.inbox, loc.outbox, loc.life = "active", e.inbox, e.outbox, e.life
                case Forget():
                    self._forget(e.agent)
                case Reconcile():
                    self._reconcile_one(e.agent)
                case plan.ToTransfer():
                    self._tr(e.inp)
                case plan.ToRecovery():
                    self._rc(e.inp)
                case tr.Lost():
                    self._rc(rc.InstanceFailed(e.agent, e.epoch, e.reason, e.early, e.msgs))
                case tr.ClaimedWithoutShell():
                    self._rc(rc.ReportFailed(e.agent, e.epoch, "claimed without a shell"))
                case tr.PollLater():
                    if not self._poll_armed:
                        self._poll_armed = True
                        self.out.append(SetTimer(AgentTimer("poll"), self._now + self.config.poll))
                case PublishHost():
                    self._apply(self.alloc.publish_host(force=True))
                case Go():
                    for agent in list(self.local):  # the deadline passed: these will be recovered elsewhere
                        self._forget(agent, kill="host leaving")
                    self.m.step(self._now, LeaveGroup())
                case _:
                    assert_never(e)

    def _cmd(self, c: AgentCommand) -> None:
        if type(c) is StartAgent:  # the start grace of this instance counts from here
            loc = self.local.get(c.agent)
            if loc is not None and loc.epoch == c.epoch:
                loc.started = self._now
        self.out.append(c)

    def _forget(self, agent: str, kill: str = "", removed: bool = False) -> None:
        """No instance of `agent` here any more (`kill`: end the one there is, for this reason)."""
        loc = self.local.pop(agent, None)
        if kill and loc is not None:
            self._cmd(KillAgent(agent, loc.epoch, kill))
        self._tr(tr.Drop(agent))
        self._rc(rc.Drop(agent, removed))

    # ------------------------------------------------------------------ inputs (wrapping the membership node)

    def step(self, now: float, inp: AgentInput) -> None:
        """One input (`haa.core.inputs`): the host's, handed to the membership node underneath, or the agent
        layer's own; effects accumulate for `drain()`."""
        self._now = now
        match inp:
            case Receive():
                if (up := self.m.step(now, inp)) is not None:  # an AgentHostMsg the core let through
                    self._on_host_msg(up.src, up.src_inc, up.msg)
            case TimerFired(key):
                self._on_timer(now, key)
            case LeaveGroup():
                self._leave(now)
            case Start() | FdReport() | PeerInfo() | Submit():
                self.m.step(now, inp)
            case CreateAgent():
                self._apply(self.ops.create(ops.create(
                    inp.agent_id, inp.type_name, inp.config, inp.parent, self.name, inp.cost, inp.hardware,
                    inp.transfer_penalty, inp.recovery, inp.max_per_host, inp.key), inp.req))
            case RemoveAgent(ref, req):
                self._apply(self.ops.remove(ref, self.name, req))
            case MoveAgent(ref, host, req):
                self._apply(self.ops.move(ref, host, self.members(), req))
            case SetPaused(paused, req):
                self._apply(self.ops.propose(ops.pause(paused), req))
            case RunAllocation():  # the leader starts one (`AllocGlue.run`)
                self._apply(self.alloc.run(now, self.m.is_member()))
            case ReportCosts(cpu, affinity):  # committed so that the leader's next session uses them
                tx = ops.costs(self.table, self.name, dict(cpu), dict(affinity)) if self.m.is_member() else None
                if tx is not None:
                    self._apply([Propose(tx, "costs", "", 0)])
            case OperatorSend(dst, payload, conv, src):
                if (r := self.table.resolve(dst)) is not None:
                    self._route(apb.RoutedMsg(src=src, dst=r.id, payload=payload, conv=conv))
            case InstanceEvent(ev):
                self._on_instance_event(now, ev)
            case Undeliverable(agent, epoch, m):
                self._undeliverable(agent, epoch, m)
            case _:
                assert_never(inp)

    def _on_timer(self, now: float, key: Hashable) -> None:
        if not isinstance(key, AgentTimer):
            self.m.step(now, TimerFired(key))
        elif key.what == "poll":  # Alg. 6 l. 9 again
            self._poll_armed = False
            for loc in list(self.local.values()):
                if loc.phase == "thawing":
                    self._tr(tr.Progress(loc.id))
        elif key.what == "retry":
            for kind, agent, arg in self.retries.fire():
                self._written(kind, agent, arg, False)
        elif key.what == "rebalance" and self.m.is_member():
            self._apply(self.alloc.change(now, "periodic"))
        elif key.what == "backoff" and key.agent:
            self._reconcile_one(key.agent)
        elif key.what == "drain":
            self._apply(self.leaving.check(len(self.local), force=now >= self.leaving.deadline))

    def _leave(self, now: float) -> None:
        """Graceful leave (thesis AF-1): hand every agent over, then leave the group (`haa.core.agents.agentleave`)."""
        self.alloc.draining = True
        self._apply(self.leaving.begin(now, len(self.local), self.m.is_member()))

    # ------------------------------------------------------------------ events of local instances, other hosts

    def _on_instance_event(self, now: float, ev: AgentEvent) -> None:
        loc = self.local.get(ev.agent)
        if loc is None or loc.epoch != ev.epoch:
            self.counters["stale_agent_events"] += 1  # an older instance (fenced): ignored
            return
        if type(ev) is Sent:  # the most frequent event first
            self._apply(self.router.sent(loc, ev))
        elif isinstance(to := plan.instance_input(loc, ev, now, self.config.start_grace), plan.ToTransfer):
            self._tr(to.inp)
        elif to is not None:
            self._rc(to.inp)
        elif type(ev) is Stopped:  # the agent ended itself: removed from the table
            self._apply([Propose(ops.remove(loc.id, self.name, loc.epoch), "stopped", loc.id, loc.epoch)])
        elif type(ev) is SpawnChild:
            self.step(now, CreateAgent(ev.child_id, ev.type, ev.config, parent=loc.id, max_per_host=ev.max_per_host,
                                       req=("child", loc.id, loc.epoch, ev.req), key=ev.key))

    def _undeliverable(self, agent: str, epoch: int, m: apb.RoutedMsg) -> None:
        """The driver could not hand `m` to the instance (its process is ending): hold the message until the
        table says where the agent is (its failure is being reported, or it stopped itself)."""
        loc = self.local.get(agent)
        if loc is not None and loc.epoch == epoch and loc.phase == "freezing":
            if not self.transfer.step(self._now, Hold(m)):  # queue1 before Alg. 5 l. 11; after it, an orphan
                return
        self._rc(rc.Orphan(agent, m))

    def _on_host_msg(self, src: str, src_inc: int, msg: AgentHostMsg) -> None:
        """An `AgentHostMsg` from another host (the core checked the sender's incarnation)."""
        if not self.m.is_member() or not self.m.state.is_member((src, src_inc)):
            self.counters["agent_msg_from_non_member"] += 1
        elif msg.kind == "alloc":  # a bid update (Alg. 4 l. 59), processed at the end of the batch (l. 77)
            if self.alloc.on_update(src, msg.data):
                self._alloc_msgs += 1
            else:
                self.counters["malformed_bid_update"] += 1
        elif msg.kind == "alloc_run":
            self._apply(self.alloc.run(self._now, self.m.is_member()))
        else:
            self._apply(self.router.from_host(src, msg))

    # ------------------------------------------------------------------ drain: membership effects + ours, commits

    def drain(self) -> list[AgentNodeEffect]:
        res: list[AgentNodeEffect] = []
        while True:
            effs = self.m.drain()
            if self._alloc_msgs:  # Alg. 4 l. 77: every update received in this input has been processed
                self._alloc_msgs = 0
                self._apply(self.alloc.end_of_inbox(self._now))
            if self.router.pushes:
                self._apply(self.router.flush())
            if not effs and not self.out and not self.m.out:
                break
            for e in effs:
                mine = type(e) is WriteDone and type(e.req) is AgentWrite
                if not mine:  # the agent layer's own writes stay here
                    res.append(e)
                try:
                    if mine:
                        self._on_write_done(cast(WriteDone, e))
                    elif type(e) is AppliedTx:
                        self._on_applied(e)
                    elif type(e) is ViewChange:
                        self._on_view(e)
                    elif type(e) is Left:
                        self.leaving.left = True
                except Exception as err:
                    # A bug in the reaction to one committed transaction must not take the rest of this drain with
                    # it (sends, timers, deliveries: the host would fall behind the group for good, issue 13 defect
                    # 1). The replicated state is applied (identically everywhere); what is lost is this host's
                    # local reaction to one effect, which the next `_reconcile` repairs. Logged, counted.
                    self.counters["core_errors"] += 1
                    self.out.append(Log("agent_layer_error", {
                        "effect": type(e).__name__, "error": f"{type(err).__name__}: {err}",
                    }))
            res.extend(self.out)
            self.out = []
        return res

    def _on_write_done(self, e: WriteDone) -> None:
        w = cast(AgentWrite, e.req)  # `drain` checked it
        member = self.m.is_member() and not self.leaving.left
        if w.kind == "push":
            self._apply(self.router.push_done(w.arg, e.ok, member))
        elif w.kind in ("create", "op"):
            self._apply(self.ops.done(w.arg, w.agent, e.ok, e.reason, e.result))
        elif e.ok:
            self._written(w.kind, w.agent, w.arg, True)
        elif w.kind in _TRANSFER_WRITES | _RECOVERY_WRITES | _ALLOC_WRITES:
            self._apply(self.retries.add(self._now, w.kind, w.agent, w.arg))

    def _written(self, kind: str, agent: str, arg: int, ok: bool) -> None:
        if kind in _TRANSFER_WRITES:
            self._tr(tr.Written(kind, agent, arg, ok))
        elif kind in _RECOVERY_WRITES:
            self._rc(rc.Written(kind, agent, arg, ok, agent in self.local))
        elif kind in _ALLOC_WRITES:
            self._apply(self.alloc.written(self._now, kind, arg, ok, self.m.is_member() and not self.leaving.left))

    def _on_applied(self, e: AppliedTx) -> None:
        res = e.result
        if isinstance(res, tuple):  # a membership change that crashed the removed hosts' agents
            for agent in res:
                r = self.table.get(agent)
                if r is not None and r.status == at.CRASHED:
                    self._rc(rc.Crashed(agent))
        elif isinstance(res, at.AgentApplied) and self.m.is_member():
            if res.kind == "create" and res.ok and res.existing:
                # a retried spawn answered with the child its first request created (docs/agents.md)
                if res.host == self.name:
                    r = self.table.records[res.agent]
                    self._apply([Note("spawn_repeated", {"agent": r.id, "name": r.name, "parent": r.parent,
                                                         "key": r.spec.key})])
            elif res.kind == "create" and res.ok:
                self._apply([Timeline(res.agent, "created", self.table.records[res.agent].type)])
            elif res.kind == "remove" and res.ok:
                self._forget(res.agent, kill="removed", removed=True)
                self.out.append(AgentTimeline(res.agent, res.agent[:8], "removed", self.name))
            elif isinstance(to := plan.applied_input(res), plan.ToTransfer):
                self._tr(to.inp)
            elif to is not None:
                self._rc(to.inp)
            elif res.kind == "push" and res.ok and res.reason == "deliver" and res.host == self.name:
                for m in res.msgs:
                    self._route(m)
            self._apply(self.alloc.applied(self._now, res, e.payload))
        else:
            return
        self._reconcile()

    def _on_view(self, e: ViewChange) -> None:
        if not self.m.is_member():
            return
        new = bool(e.added) and not e.removed and all(self.table.hosts.get(m.name) is None for m in e.added)
        self._apply(self.alloc.view_changed(self._now, any(m.name == self.name for m in e.added), new))
        for loc in list(self.local.values()):  # Alg. 5 l. 10 / Alg. 6 l. 9: "or h is removed"
            if loc.phase in ("freezing", "thawing"):
                self._tr(tr.Progress(loc.id))
        self._reconcile()

    # ------------------------------------------------------------------ reconcile: table vs. local instances

    def _reconcile(self) -> None:
        if not self.m.is_member() or self.leaving.left:
            return
        for agent in list(self.local):
            if self.table.get(agent) is None:
                self._forget(agent, kill="agent no longer exists")
        for r in list(self.table):
            self._reconcile_one(r.id)
        self._rc(rc.Check())  # forget the backoffs of agents removed meanwhile
        if self.leaving.draining:
            self._apply(self.leaving.check(len(self.local)))

    def _reconcile_one(self, agent: str) -> None:
        if self.recovery.backoff:  # (a read: most of the time there is no backoff to forget)
            self._rc(rc.Check(agent))
        r = self.table.get(agent)
        if r is None or not self.m.is_member() or self.leaving.left:
            return
        loc = self.local.get(agent)
        act = plan.reconcile(r, loc, self.name, self.leaving.draining, self.members, self.table.hosts)
        if isinstance(act, plan.FreezeLocal):
            assert loc is not None and loc.inbox is not None
            loc.phase = "freezing"
            self._tr(tr.Freeze(loc.id, loc.epoch, loc.inbox, loc.outbox))
        elif isinstance(act, tr.Thaw):
            self._tr(act)
        elif act is not None:
            self._rc(act)
