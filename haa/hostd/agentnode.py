"""The agent layer of one host: allocation, routing, transfer, backup and recovery, as one sans-I/O machine.

`AgentNode` wraps a host's `MembershipNode` (Alg. 3, which owns the failure detector, OAC and the global
state) and adds what thesis Chapter 4 builds on it for agents:

* the agent table (`haa.hostd.agenttable`, part of the global state): every change is an `AgentTx` committed
  through OAC, so every member agrees on which agents exist, who owns each and what is queued for it;
* allocation HAA-AA (Alg. 4, `haa.hostd.allocation.Allocator`): the leader starts a session on a membership
  change, an agent-list change, a change of a host's capabilities and periodically (`RebalancePolicy`:
  rate-limited, can be paused); bid updates travel as `AgentHostMsg("alloc")`; OAC(start)/OAC(finish) are
  agent transactions;
* routing: every message between agents goes through the hosts (`_route`): to the local instance through
  its `Inbox` (exactly once, sender order), to the owner host, or into the agent's queue in the table while
  it is frozen, new or crashed (`haa.hostd.routing`);
* transfer (Alg. 5-6, `haa.hostd.transfer`) and backup / recovery (Alg. 7-8, `haa.hostd.recovery`), driven
  by `_reconcile`: after every change of the table each host compares what the table says with the instances
  it runs — an agent it runs but is no longer allocated is frozen, a frozen agent allocated to it is thawed,
  a new or crashed agent allocated to it is recovered, an instance the table does not know is killed;
* graceful leave (thesis AF-1): `leave()` first marks the host draining (it gets no agents), waits until it
  runs none, then leaves the group.

Agent instances are not started here: the node emits commands (`haa.hostd.agentio`: SpawnShell, StartAgent,
DeliverAgent, FreezeAgent, KillAgent, AnswerAgent) and takes events back through `on_agent_event`. The
daemon runs OS processes (`haa.hostd.agentproc`); the simulator runs simulated agents (`haa.dsim.agents`).
No I/O, no clock, no randomness: ids of new agents come from the caller.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Iterable
from dataclasses import dataclass, field
from typing import Any, cast

from google.protobuf.message import DecodeError

from haa.hostd import agenttable as at
from haa.hostd import allocwire
from haa.hostd.agentio import (
    AgentOpDone,
    AgentTimeline,
    AnswerAgent,
    BackupMade,
    DeliverAgent,
    Failed,
    Frozen,
    KillAgent,
    OperatorReply,
    Sent,
    ShellReady,
    SpawnChild,
    StartAgent,
    Stopped,
)
from haa.hostd.allocation import (
    MAX_CAPACITY,
    MAX_COST,
    MAX_PER_HOST,
    MIN_CAPACITY,
    AgentSpec,
    Allocated,
    Allocator,
    HostSpec,
    ProposeFinish,
    ProposeStart,
    RebalancePolicy,
    SendUpdate,
    SessionStart,
)
from haa.hostd.effects import Log, Send, SetTimer
from haa.hostd.globalstate import TxAgent, decode_tx
from haa.hostd.membership import AppliedTx, Left, MembershipNode, ViewChange, WriteDone
from haa.hostd.messages import AgentHostMsg, Message
from haa.hostd.oac import DONE
from haa.hostd.recovery import RecoveryMixin
from haa.hostd.routing import Inbox, Outbox
from haa.hostd.transfer import TransferMixin
from haa.pb import agenttx_pb2 as apb

#: a write of the agent layer that was given up or refused is retried after this long (seconds)
RETRY_AFTER = 0.1
#: bytes/s of messages between two agents that count as affinity 1.0 (the scale of an agent's CPU cost)
AFFINITY_SCALE = 1e5


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


@dataclass(slots=True)
class Local:
    """An agent instance this host runs or is preparing (the host side of its process)."""

    id: str
    epoch: int
    phase: str  # claiming, thawing (Alg. 6), recovering (Alg. 8), active, freezing (Alg. 5)
    mode: str  # fresh, thaw, recover
    ready: bool = False  # the shell said hello
    claimed: bool = False  # recovering: OAC(recovered) committed
    freeze_committed: bool = False
    after_l11: bool = False
    inbox: Inbox | None = None
    outbox: Outbox = field(default_factory=Outbox)
    life: int = 0
    local_q: list[apb.RoutedMsg] = field(default_factory=list)  # Alg. 6 l. 3
    q1: list[apb.RoutedMsg] = field(default_factory=list)  # Alg. 5 l. 4
    handed: list[apb.RoutedMsg] = field(default_factory=list)  # queues handed over by claim / recovered
    state: bytes | None = None
    frozen_state: bytes | None = None
    wait_acks: set[str] = field(default_factory=set)
    acks: set[str] = field(default_factory=set)
    respawns: int = 0
    started: float = -1.0  # when StartAgent was issued (the start grace counts from it); -1: not yet


def _agent_write(e: Any) -> bool:
    """A `WriteDone` of a transaction the agent layer proposed itself (`AgentNode._propose`)."""
    return type(e) is WriteDone and isinstance(e.req, tuple) and bool(e.req) and e.req[0] == "agent"


class AgentNode(TransferMixin, RecoveryMixin):
    """See the module docstring."""

    def __init__(self, node: MembershipNode, config: AgentConfig | None = None,
                 mutations: frozenset[str] = frozenset()) -> None:
        self.m = node
        self.config = config or AgentConfig()
        self.mutations = mutations
        self.name = node.name
        node.core.app_handler = self._on_host_msg
        self.local: dict[str, Local] = {}
        self.orphans: dict[str, list[apb.RoutedMsg]] = {}
        self.out: list[Any] = []
        self.counters: Counter[str] = Counter()
        self.allocator = Allocator(self.name)
        self.policy = RebalancePolicy(
            period=self.config.rebalance_period if self.config.rebalance_period > 0 else 1e18,
            min_interval=self.config.min_session_gap,
        )
        self._alloc_msgs = 0
        self._pushes: dict[str, list[apb.RoutedMsg]] = {}
        self._push_reqs: dict[int, tuple[str, list[apb.RoutedMsg]]] = {}
        self._ops: dict[int, Hashable] = {}
        self._seq = 0
        self._now = 0.0
        self._poll_armed = False
        self._host_published: tuple[float, tuple[str, ...], bool] | None = None
        self.draining = False
        self._drain_deadline = 0.0
        self._left_group = False
        self.backups_proposed = 0
        #: (agent, epoch) whose OAC(failed) this host has proposed and not yet seen decided
        self.failed_reported: set[tuple[str, int]] = set()
        #: (agent, epoch) -> (reason, early) of the failures reported, for a retry of the OAC(failed)
        self._failed_why: dict[tuple[str, int], tuple[str, bool]] = {}
        #: agent -> ((epoch, failures), due): a crashed agent whose recovery waits (start failure backoff)
        self._backoff: dict[str, tuple[tuple[int, int], float]] = {}
        #: agent -> (epoch, reason): a shell that could not start before its OAC(recovered) committed
        self._spawn_failed: dict[str, tuple[int, str]] = {}
        self._starts: dict[int, SessionStart] = {}
        self._retries: list[tuple[Any, str, int]] = []
        self._retry_armed = False

    def __getattr__(self, name: str) -> Any:
        # everything else is the membership node's (state, oac, peers, is_member, ...): drivers that know a
        # MembershipNode drive an AgentNode the same way
        if name == "m":
            raise AttributeError(name)
        return getattr(self.m, name)

    # ------------------------------------------------------------------ plumbing

    @property
    def table(self) -> at.AgentTable:
        return self.m.state.agents

    def _cmd(self, c: Any) -> None:
        if type(c) is StartAgent:  # the start grace of this instance counts from here
            loc = self.local.get(c.agent)
            if loc is not None and loc.epoch == c.epoch:
                loc.started = self._now
        self.out.append(c)

    def _log(self, event: str, **fields: Any) -> None:
        self.out.append(Log(event, fields))

    def _timeline(self, agent: str, event: str, detail: str = "") -> None:
        r = self.table.get(agent)
        self.out.append(AgentTimeline(agent, r.name if r else agent[:8], event, self.name, detail))

    def _member_names(self) -> list[str]:
        return [m.name for m in self.m.state.members]

    def _inc_of(self, host: str) -> int:
        for m in self.m.state.members:
            if m.name == host:
                return m.inc
        return 0

    def _send_agent_host(self, host: str, kind: str, agent: str, epoch: int, data: bytes) -> None:
        inc = self._inc_of(host)
        if not inc or host == self.name:
            return
        self.out.append(Send(host, inc, AgentHostMsg(kind, agent, epoch, data)))
        self.counters[f"sent_{kind}"] += 1

    def _propose(self, tx: apb.AgentTx, key: tuple[Any, ...]) -> int:
        self._seq += 1
        self.m.submit(self._now, at.encode(tx), ("agent", *key, self._seq), kind="agent")
        return self._seq

    def _oacs_settled(self) -> bool:
        """Alg. 6 l. 9 / Alg. 8 l. 3: every OAC this host knows of is decided and delivered."""
        if self.m.direct_q:
            return False
        return all(tx.state == DONE or not tx.content for tx in self.m.core.oac.txs.values())

    def _poll_later(self) -> None:
        if not self._poll_armed:
            self._poll_armed = True
            self.out.append(SetTimer(("a", "poll"), self._now + self.config.poll))

    # ------------------------------------------------------------------ inputs (wrapping the membership node)

    def start(self, now: float) -> None:
        self._now = now
        self.m.start(now)

    def on_message(self, now: float, src: str, src_inc: int, dst_inc: int, msg: Message) -> None:
        self._now = now
        self.m.on_message(now, src, src_inc, dst_inc, msg)

    def on_suspicion(self, now: float, peer: str, suspected: bool) -> None:
        self._now = now
        self.m.on_suspicion(now, peer, suspected)

    def on_peer_info(self, now: float, peer: str, inc: int) -> None:
        self._now = now
        self.m.on_peer_info(now, peer, inc)

    def on_timer(self, now: float, key: Hashable) -> None:
        self._now = now
        if not (isinstance(key, tuple) and key and key[0] == "a"):
            self.m.on_timer(now, key)
            return
        k = key[1]
        if k == "poll":
            self._poll_armed = False
            for loc in list(self.local.values()):
                if loc.phase == "thawing":
                    self._thaw_progress(loc)
        elif k == "retry":
            self._retry_armed = False
            retries, self._retries = self._retries, []
            for handler, agent, arg in retries:
                handler(agent, arg, False)
        elif k == "rebalance":
            self._maybe_session(now, "periodic")
        elif k == "backoff" and len(key) > 2:
            self._reconcile_one(key[2])
        elif k == "drain":
            self._drain_check(force=now >= self._drain_deadline)

    def submit(self, now: float, payload: bytes, req: Hashable, kind: str = "ddb") -> None:
        self._now = now
        self.m.submit(now, payload, req, kind)

    def leave(self, now: float) -> None:
        """Graceful leave (thesis AF-1): hand every agent over, then leave the group."""
        self._now = now
        if self.draining:
            return
        self.draining = True
        self._drain_deadline = now + self.config.drain_timeout
        self._log("draining", agents=len(self.local))
        if not self.m.is_member() or len(self.m.state.members) == 1 or not self.local:
            self._drain_check(force=True)
            return
        self._publish_host(force=True)
        self.out.append(SetTimer(("a", "drain"), self._drain_deadline))

    def _drain_check(self, force: bool = False) -> None:
        if not self.draining or self._left_group:
            return
        hosts = self.table.hosts
        takers = [n for n in self._member_names() if n != self.name and not (n in hosts and hosts[n].draining)]
        if self.local and not force and takers:
            return  # wait until every agent is handed over (or the deadline); nobody to take them: go now
        self._left_group = True
        for loc in list(self.local.values()):  # the deadline passed: these will be recovered elsewhere
            self._cmd(KillAgent(loc.id, loc.epoch, "host leaving"))
        self.local.clear()
        self.m.leave(self._now)

    # ------------------------------------------------------------------ operator requests

    def create_agent(
        self,
        now: float,
        agent_id: str,
        type_name: str,
        config: bytes = b"",
        *,
        parent: str = "",
        cost: float = 0.1,
        hardware: Iterable[str] = (),
        transfer_penalty: float = 0.1,
        recovery: str = "backup",
        max_per_host: int = 0,
        req: Hashable = None,
    ) -> None:
        self._now = now
        tx = apb.AgentTx()
        c = tx.create
        c.id, c.type, c.config, c.parent = agent_id, type_name, config, parent
        c.max_per_host = max(0, min(int(max_per_host), 2**32 - 1))  # check_create refuses > MAX_PER_HOST
        c.cost, c.transfer_penalty, c.recovery, c.host = cost, transfer_penalty, recovery, self.name
        c.hardware.extend(sorted(set(hardware)))
        why = at.check_create(c)
        if why:
            self.out.append(AgentOpDone(req, False, agent_id, "", why))
            return
        self._propose(tx, ("create", agent_id, self._op(req)))

    def _op(self, req: Hashable) -> int:
        self._seq += 1
        self._ops[self._seq] = req
        return self._seq

    def _op_tx(self, now: float, tx: apb.AgentTx, req: Hashable, agent: str = "") -> None:
        self._now = now
        n = self._op(req)
        self._propose(tx, ("op", agent, n))

    def remove_agent(self, now: float, ref: str, req: Hashable = None) -> None:
        r = self.table.resolve(ref)
        if r is None:
            self._now = now
            self.out.append(AgentOpDone(req, False, ref, "", "unknown agent"))
            return
        tx = apb.AgentTx()
        tx.remove.id, tx.remove.host = r.id, self.name
        self._op_tx(now, tx, req, r.id)

    def move_agent(self, now: float, ref: str, host: str, req: Hashable = None) -> None:
        r = self.table.resolve(ref)
        self._now = now
        if r is None:
            self.out.append(AgentOpDone(req, False, ref, "", "unknown agent"))
            return
        if host not in self._member_names():
            self.out.append(AgentOpDone(req, False, r.id, r.name, f"{host} is not a member of the group"))
            return
        tx = apb.AgentTx()
        tx.move.id, tx.move.host = r.id, host
        self._op_tx(now, tx, req, r.id)

    def set_paused(self, now: float, paused: bool, req: Hashable = None) -> None:
        tx = apb.AgentTx()
        tx.control.paused = paused
        self._op_tx(now, tx, req)

    def run_allocation(self, now: float) -> None:
        """An operator asks for an allocation session now: the leader starts one; another member passes the
        request on to the leader."""
        self._now = now
        members = self._member_names()
        if members and members[0] != self.name:
            self._send_agent_host(members[0], "alloc_run", "", 0, b"")
            return
        self._maybe_session(now, "operator", force=True)

    def report_costs(self, now: float, cpu: dict[str, float], affinity: dict[tuple[str, str], float]) -> None:
        """Measured CPU per local agent and message rates between agent pairs (bytes/s): committed so that the
        leader's next session uses them (Alg. 4 ll. 22-23)."""
        self._now = now
        if not self.m.is_member():
            return
        tx = apb.AgentTx()
        tx.costs.host = self.name
        changed = False
        for agent, c in sorted(cpu.items()):
            r = self.table.get(agent)
            if r is not None and r.owner == self.name and abs(r.cpu - c) > max(0.02, 0.2 * r.cpu):
                tx.costs.costs.add(id=agent, cpu=round(c, 4))
                changed = True
        for (a, b), rate in sorted(affinity.items()):
            key = (a, b) if a < b else (b, a)
            old = self.table.affinity.get(key, 0.0)
            if abs(old - rate) > max(100.0, 0.3 * old):
                tx.costs.affinity.add(a=key[0], b=key[1], rate=round(rate, 1))
                changed = True
        if changed:
            self._propose(tx, ("costs", "", 0))

    def operator_request(self, now: float, dst: str, payload: bytes, conv: int) -> bool:
        """A request from the operator, answered with an `OperatorReply` effect here (the reply travels back
        from the agent's host: the request's sender is "@<this host>")."""
        self._now = now
        r = self.table.resolve(dst)
        if r is None:
            return False
        self._route(apb.RoutedMsg(src="@" + self.name, dst=r.id, payload=payload, conv=conv))
        return True

    def operator_send(self, now: float, dst: str, payload: bytes) -> bool:
        """A message from the operator (no sender agent, unsequenced)."""
        self._now = now
        r = self.table.resolve(dst)
        if r is None:
            return False
        self._route(apb.RoutedMsg(src="", dst=r.id, payload=payload))
        return True

    # ------------------------------------------------------------------ events of local instances

    def on_agent_event(self, now: float, ev: Any) -> None:
        self._now = now
        loc = self.local.get(ev.agent)
        if loc is None or loc.epoch != ev.epoch:
            self.counters["stale_agent_events"] += 1  # an older instance (fenced): ignored
            return
        t = type(ev)
        if t is ShellReady:
            loc.ready = True
            if loc.phase == "thawing":
                self._thaw_progress(loc)
            elif loc.phase == "recovering":
                self._recover_progress(loc)
        elif t is Sent:
            self._on_sent(loc, ev)
        elif t is BackupMade:
            self._on_backup(loc, ev.data)
        elif t is Frozen:
            self._on_frozen(loc, ev.state)
        elif t is Failed:
            self._on_instance_failed(loc, ev.reason)
        elif t is Stopped:
            tx = apb.AgentTx()
            tx.remove.id, tx.remove.host, tx.remove.epoch = loc.id, self.name, loc.epoch
            self._propose(tx, ("stopped", loc.id, loc.epoch))
        elif t is SpawnChild:
            self.create_agent(now, ev.child_id, ev.type, ev.config, parent=loc.id,
                              max_per_host=ev.max_per_host, req=("child", loc.id, loc.epoch, ev.req))

    def undeliverable(self, now: float, agent: str, epoch: int, m: apb.RoutedMsg) -> None:
        """The driver could not hand `m` to the instance (its process is ending): hold the message until the
        table says where the agent is (its failure is being reported, or it stopped itself)."""
        self._now = now
        loc = self.local.get(agent)
        if loc is not None and loc.epoch == epoch and loc.phase == "freezing" and not loc.after_l11:
            loc.q1.append(m)
        else:
            self.orphans.setdefault(agent, []).append(m)

    def _on_sent(self, loc: Local, ev: Sent) -> None:
        if loc.phase not in ("active", "freezing"):
            self.counters["sent_by_inactive_instance"] += 1
            return
        if ev.dst.startswith("@"):  # a reply to an operator request made through host ev.dst[1:]
            if ev.reply:
                host = ev.dst[1:]
                if host == self.name:
                    self.out.append(OperatorReply(ev.conv, ev.payload, ev.error))
                else:
                    m = apb.RoutedMsg(src=loc.id, dst=ev.dst, payload=ev.payload, conv=ev.conv, reply=True,
                                      error=ev.error)
                    self._send_agent_host(host, "op_reply", loc.id, 0, m.SerializeToString())
            return
        dst = self.table.get(ev.dst)
        if dst is None:
            dst = self.table.resolve(ev.dst)
        if dst is None:
            self.counters["unknown_destination"] += 1
            if ev.conv and not ev.reply:  # a request to nobody: answer with an error at once
                self._route(apb.RoutedMsg(src="", dst=loc.id, conv=ev.conv, reply=True,
                                          error=f"unknown agent {ev.dst[:64]}"))
            return
        seq = loc.outbox.stamp(dst.id)
        self._route(apb.RoutedMsg(src=loc.id, src_life=loc.life, seq=seq, dst=dst.id, payload=ev.payload,
                                  conv=ev.conv, reply=ev.reply, error=ev.error))

    # ------------------------------------------------------------------ routing

    def _route(self, m: apb.RoutedMsg) -> None:
        """Where a message addressed to agent a (m.a.a.) goes from this host, now."""
        r = self.table.get(m.dst)
        if r is None:
            self.counters["routed_to_unknown"] += 1
            return
        loc = self.local.get(m.dst)
        if loc is not None:
            if loc.phase == "active":
                assert loc.inbox is not None
                for x in loc.inbox.offer(m):
                    self._cmd(DeliverAgent(loc.id, loc.epoch, x))
                return
            if loc.phase == "freezing" and not loc.after_l11:
                loc.q1.append(m)  # Alg. 5 l. 4
                return
            if loc.phase in ("claiming", "thawing", "recovering"):
                loc.local_q.append(m)  # Alg. 6 l. 3
                return
        if r.status == at.ACTIVE and r.owner and r.owner != self.name:
            self._send_agent_host(r.owner, "msg", m.dst, r.epoch, m.SerializeToString())
            return
        if r.status == at.ACTIVE and r.owner == self.name:
            # ours, but no instance here right now (its failure is being reported): hold until the table says
            self.orphans.setdefault(m.dst, []).append(m)
            return
        # frozen / freezing elsewhere (Alg. 5 l. 23), new or crashed: into queue2 (Alg. 5 l. 11, 23)
        self._pushes.setdefault(m.dst, []).append(m)

    def _flush_pushes(self) -> None:
        """Propose the messages held for queue2, one push transaction per agent at a time: while one is in
        OAC, later messages wait and go out together in the next (a frozen agent receiving 200 messages/s
        would otherwise cost 200 OACs/s, and the thaw waits for every one of them, Alg. 6 l. 9). Their
        order does not depend on it: the stream numbers put them in place."""
        if not self._pushes:
            return
        busy = {agent for agent, _msgs in self._push_reqs.values()}
        for agent in [a for a in self._pushes if a not in busy]:
            msgs = self._pushes.pop(agent)
            part, rest = msgs[: self.config.max_push], msgs[self.config.max_push :]
            if rest:
                self._pushes[agent] = rest
            tx = apb.AgentTx()
            tx.push.id, tx.push.queue = agent, 2
            tx.push.msgs.extend(part)
            n = self._propose(tx, ("push", agent, 0))
            self._push_reqs[n] = (agent, part)

    def _routed(self, data: bytes) -> apb.RoutedMsg | None:
        """A RoutedMsg from a peer's bytes; malformed bytes are counted, never fatal."""
        m = apb.RoutedMsg()
        try:
            m.ParseFromString(data)
        except DecodeError:
            self.counters["malformed_agent_msg"] += 1
            return None
        return m

    def _on_host_msg(self, src: str, src_inc: int, msg: Message) -> None:
        """An `AgentHostMsg` from another host (the core checked the sender's incarnation)."""
        if not isinstance(msg, AgentHostMsg):
            return
        if not self.m.is_member() or not self.m.state.is_member((src, src_inc)):
            self.counters["agent_msg_from_non_member"] += 1
            return
        k = msg.kind
        if k == "msg":
            m = self._routed(msg.data)
            if m is None:
                return
            self.counters["routed_in"] += 1
            self._route(m)
        elif k == "freeze_ack":
            self._on_freeze_ack(src, msg.agent)
        elif k == "claim_ack":
            self._on_claim_ack(src, msg.agent)
        elif k == "alloc":
            try:
                upd = allocwire.decode_update(msg.data)
            except ValueError:
                self.counters["malformed_bid_update"] += 1
                return
            self.allocator.on_update(src, upd)  # Alg. 4 l. 59
            self._alloc_msgs += 1
        elif k == "alloc_run":
            self.run_allocation(self._now)
        elif k == "op_reply":
            m = self._routed(msg.data)
            if m is not None:
                self.out.append(OperatorReply(m.conv, m.payload, m.error))

    # ------------------------------------------------------------------ drain: membership effects + ours

    def drain(self) -> list[Any]:
        res: list[Any] = []
        while True:
            effs = self.m.drain()
            if self._alloc_msgs:  # Alg. 4 l. 77: every update received in this input has been processed
                self._alloc_msgs = 0
                self.allocator.end_of_inbox()
                self._alloc_effects()
            self._flush_pushes()
            if not effs and not self.out and not self.m.out:
                break
            for e in effs:
                if not _agent_write(e):  # the agent layer's own writes stay here
                    res.append(e)
                try:
                    self._on_membership_effect(e)
                except Exception as err:
                    # A bug in the agent layer's reaction to one committed transaction must not take the rest
                    # of this drain with it: the remaining effects (sends, timers, deliveries) would be lost and
                    # the host would fall behind the group for good (issue 13, defect 1). The replicated state
                    # is already applied (identically everywhere); what is lost is this host's local reaction
                    # to one effect, which the next `_reconcile` repairs. Logged as an error, counted.
                    self.counters["core_errors"] += 1
                    self.out.append(Log("agent_layer_error", {
                        "effect": type(e).__name__, "error": f"{type(err).__name__}: {err}",
                    }))
            res.extend(self.out)
            self.out = []
        return res

    def _on_membership_effect(self, e: Any) -> None:
        t = type(e)
        if _agent_write(e):
            self._on_write_done(e)
        elif t is AppliedTx:
            self._on_applied(e)
        elif t is ViewChange:
            self._on_view(e)
        elif t is Left:
            self._left_group = True

    # ------------------------------------------------------------------ committed transactions

    def _on_write_done(self, e: WriteDone) -> None:
        key = cast("tuple[str, str, str, int, int]", e.req)  # ("agent", kind, agent, epoch or n, n): `_propose`
        kind, agent, epoch_or_n, n = key[1], key[2], key[3], key[4]
        if kind == "push":
            agent, msgs = self._push_reqs.pop(n, (agent, []))
            if not e.ok and self.m.is_member() and not self._left_group:
                for m in msgs:  # aborted or refused: the table may say something else now
                    self._route(m)
            elif not e.ok:
                # not a member (any more): a push is refused at once, and routing the messages again pushed
                # them again in the same drain, for ever (`haactl verify recovery` seed 238 once a joiner
                # publishes its HostInfo). The group fences a removed host's messages anyway.
                self.counters["push_dropped_not_member"] += len(msgs)
            return
        if kind in ("create", "op"):
            req = self._ops.pop(epoch_or_n, None)
            res = e.result
            if not e.ok:
                self._op_answer(req, False, agent, e.reason or "not committed")
            elif isinstance(res, at.AgentApplied):  # committed and applied here (WriteDone follows the apply)
                self._op_answer(req, res.ok, res.agent or agent, res.reason)
            return
        handler = getattr(self, f"_on_{kind}_done", None)
        if handler is None:
            return
        if e.ok:
            handler(agent, epoch_or_n, True)
            return
        # the membership node already re-proposed an aborted write (up to max_write_attempts) or refused it
        # (not a member, group not formed): the retries of Alg. 4-8 ("do ... while not committed") wait a
        # little, or a refusal would loop at once
        self._retries.append((handler, agent, epoch_or_n))
        if not self._retry_armed:
            self._retry_armed = True
            self.out.append(SetTimer(("a", "retry"), self._now + RETRY_AFTER))

    def _op_answer(self, req: Hashable, ok: bool, agent: str, reason: str = "") -> None:
        if isinstance(req, tuple) and req and req[0] == "child":
            _, parent, epoch, rid = req
            self._cmd(AnswerAgent(parent, epoch, rid, ok, agent if ok else "", reason))
            return
        r = self.table.get(agent) if agent else None
        self.out.append(AgentOpDone(req, ok, agent, r.name if r else "", reason))

    def _on_applied(self, e: AppliedTx) -> None:
        res = e.result
        if isinstance(res, tuple):  # a membership change that crashed the removed hosts' agents
            for agent in res:
                r = self.table.get(agent)
                if r is not None and r.status == at.CRASHED:
                    self._on_crashed(agent)
            self._reconcile()
            return
        if not isinstance(res, at.AgentApplied):
            return
        if not self.m.is_member():
            return
        k = res.kind
        if k == "create":
            if res.ok:
                created = self.table.get(res.agent)
                assert created is not None  # the create was applied
                self._timeline(res.agent, "created", created.type)
                self._maybe_session(self._now, "agent list changed")
        elif k == "remove":
            if res.ok:
                loc = self.local.pop(res.agent, None)
                if loc is not None:
                    self._cmd(KillAgent(loc.id, loc.epoch, "removed"))
                self.orphans.pop(res.agent, None)
                self.out.append(AgentTimeline(res.agent, res.agent[:8], "removed", self.name))
                self._maybe_session(self._now, "agent list changed")
        elif k == "start":
            self._on_start_applied(e.payload)  # expired starts too: their ids are used up (allocation.py)
        elif k == "finish":
            if res.ok:
                self._on_finish_applied()
        elif k == "freeze":
            self._on_freeze_applied(res)
        elif k == "release":
            self._on_release_applied(res)
        elif k == "claim":
            self._on_claim_applied(res)
        elif k == "recovered":
            self._on_recovered_applied(res)
        elif k == "failed":
            if res.ok:
                r = self.table.get(res.agent)
                if r is not None and r.status == at.FAILED:
                    self._on_failed_for_good(r)
                else:
                    self._on_crashed(res.agent)
        elif k == "push":
            if res.ok and res.reason == "deliver" and res.host == self.name:
                for m in res.msgs:
                    self._route(m)
        elif k == "host":
            if res.ok:
                self._maybe_session(self._now, "host capabilities changed")
        elif k == "control":
            self._maybe_session(self._now, "rebalancing resumed")
        self._reconcile()

    def _on_view(self, e: ViewChange) -> None:
        if not self.m.is_member():
            return
        if any(m.name == self.name for m in e.added) or self._host_published is None:
            self._publish_host(force=True)
        self._maybe_session(self._now, "membership changed")
        for loc in list(self.local.values()):  # Alg. 5 l. 10 / Alg. 6 l. 9: "or h is removed"
            if loc.phase == "freezing":
                self._freeze_progress(loc)
            elif loc.phase == "thawing":
                self._thaw_progress(loc)
        self._reconcile()

    def _publish_host(self, force: bool = False) -> None:
        """Commit this host's K_h, H_h and draining flag to the agent table. Every member publishes them, the
        defaults too: the allocation gives a member whose entry is missing no agent (`_host_specs`)."""
        want = (self.config.capacity, tuple(sorted(self.config.hardware)), self.draining)
        if not force and self._host_published == want:
            return
        self._host_published = want
        tx = apb.AgentTx()
        h = tx.host
        h.name, h.capacity, h.draining = self.name, self.config.capacity, self.draining
        h.hardware.extend(want[1])
        self._propose(tx, ("host", "", 0))

    # ------------------------------------------------------------------ allocation glue (Alg. 4)

    def _agent_specs(self) -> tuple[AgentSpec, ...]:
        t = self.table
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
                )
            )
        return tuple(out)

    def _host_specs(self) -> tuple[HostSpec, ...]:
        """K_h and H_h of every member (thesis §4.7: the leader defines the session's properties), as the
        members committed them to the agent table. A member whose entry is not committed yet — a host that
        just joined: its `_publish_host` follows its join by one OAC — takes part in the session but bids for
        nothing (`draining`), like a host leaving. Read as the default (one core, no hardware), a joiner with
        a smaller capacity took agents in the join's session and gave them back in the session its entry
        triggers about `min_session_gap` later (docs/allocation.md, "Joins and hysteresis"); its entry triggers
        that session anyway, and only then does the joiner get agents, on its real K_h."""
        out = []
        for n in self._member_names():
            h = self.table.hosts.get(n)
            if h is None:
                out.append(HostSpec(n, 1.0, frozenset(), True))
                continue
            cap = h.capacity if MIN_CAPACITY <= h.capacity <= MAX_CAPACITY else 1.0
            out.append(HostSpec(n, cap, frozenset(h.hardware), bool(h.draining)))
        return tuple(out)

    def _maybe_session(self, now: float, why: str, force: bool = False) -> None:
        """Alg. 4 l. 17: every host records the new situation; the leader starts a session when its
        `RebalancePolicy` allows (rate limit, periodic rebalancing unless paused)."""
        if not self.m.is_member():
            return
        group = tuple(self._member_names())
        leader = bool(group) and group[0] == self.name
        pol = self.policy
        if self.table.paused:
            pol.pause()
        else:
            pol.resume()
        if not len(self.table) and not force:
            # nothing to allocate: no session (its OAC(start)/OAC(finish) would only add traffic)
            self.allocator.on_change(group, (), self._host_specs(), start=False)
            return
        if why == "periodic":
            due = leader and pol.due(now)
        else:
            due = pol.changed(now) if leader else False
        if force and leader and not due:
            pol.force(now)
            due = True
        self.allocator.committed_ses = max(self.allocator.committed_ses, self.table.ses_id)
        self.allocator.on_change(group, self._agent_specs(), self._host_specs(), start=due)
        if due:
            self._log("allocation_session", reason=why, hosts=len(group), agents=len(self.table))
        self._alloc_effects()
        if leader:
            nxt = pol.deadline()
            if nxt is not None and nxt < 1e17:
                self.out.append(SetTimer(("a", "rebalance"), max(nxt, now)))

    def _alloc_effects(self) -> None:
        for e in self.allocator.drain():
            if isinstance(e, SendUpdate):
                data = allocwire.encode_update(e.update)
                for h in e.dsts:
                    self._send_agent_host(h, "alloc", "", 0, data)
            elif isinstance(e, ProposeStart):
                st = e.start
                tx = apb.AgentTx()
                tx.start.data = allocwire.encode_start(st)
                tx.start.ses_id, tx.start.leader = st.ses_id, st.leader
                tx.start.group.extend(st.group)
                tx.start.agents.extend(st.agent_ids)
                self._starts[st.ses_id] = st
                self._propose(tx, ("start", "", st.ses_id))
            elif isinstance(e, ProposeFinish):
                tx = apb.AgentTx()
                tx.finish.ses_id, tx.finish.leader = e.ses_id, self.name
                for a, h in sorted(e.allocation.items()):
                    tx.finish.allocation[a] = h
                self._propose(tx, ("finish", "", e.ses_id))
            elif isinstance(e, Allocated):
                self.policy.finished(self._now)
                self._log("allocation_accepted", session=e.ses_id, agents=len(e.allocation),
                          unallocatable=list(e.unallocatable))
            elif isinstance(e, Log):
                self.out.append(e)

    def _on_host_done(self, _agent: str, _n: int, ok: bool) -> None:
        """Our host entry was committed, or given up / refused (the first member's, proposed before the group
        is formed, is refused): publish it again while we are a member and the table does not hold it."""
        if ok or not self.m.is_member() or self._left_group:
            return
        h = self.table.hosts.get(self.name)
        want = self._host_published
        if h is None or want is None or (h.capacity, tuple(sorted(h.hardware)), h.draining) != want:
            self._publish_host(force=True)

    def _on_start_done(self, _agent: str, ses_id: int, ok: bool) -> None:
        start = self._starts.pop(ses_id, None)
        if start is not None:
            self.allocator.on_start_decided(start, ok, tuple(self._member_names()), self.table.agent_ids())
            self._alloc_effects()

    def _on_finish_done(self, _agent: str, ses_id: int, ok: bool) -> None:
        self.allocator.on_finish_decided(ses_id, ok)
        self._alloc_effects()

    def _on_start_applied(self, payload: bytes) -> None:
        try:
            tx = decode_tx(payload)
            # a start is proposed as an agent transaction (another kind raises AttributeError here)
            start = allocwire.decode_start(at.decode(cast(TxAgent, tx).data).start.data)
        except (ValueError, AttributeError) as e:
            self._log("allocation_bad_start", reason=str(e))
            return
        self.allocator.on_start_committed(start, tuple(self._member_names()), self.table.agent_ids())  # l. 38
        self._alloc_effects()

    def _on_finish_applied(self) -> None:
        t = self.table
        alloc = {r.id: r.alloc for r in t if r.alloc}
        self.allocator.on_finish_committed(t.finished_ses, alloc, tuple(self._member_names()), t.agent_ids())
        self._alloc_effects()

    # ------------------------------------------------------------------ reconcile: table vs. local instances

    def _new_local(self, r: at.AgentRecord, epoch: int, phase: str, mode: str) -> Local:
        loc = Local(r.id, epoch, phase, mode)
        self.local[r.id] = loc
        return loc

    def _reconcile(self) -> None:
        if not self.m.is_member() or self._left_group:
            return
        for agent in list(self.local):
            if self.table.get(agent) is None:
                loc = self.local.pop(agent)
                self._cmd(KillAgent(agent, loc.epoch, "agent no longer exists"))
        for r in list(self.table):
            self._reconcile_one(r.id)
        for agent in [a for a in self._backoff if self.table.get(a) is None]:  # removed while backing off
            del self._backoff[agent]
        if self.draining:
            self._drain_check()

    def _reconcile_one(self, agent: str) -> None:
        r = self.table.get(agent)
        me = self.name
        if agent in self._backoff and (r is None or r.status != at.CRASHED or r.alloc != me):
            # a backoff this host started for an agent it no longer has to recover (allocated elsewhere since,
            # recovered, removed): forget it, or a stale entry outlives the agent's troubles
            del self._backoff[agent]
        if r is None or not self.m.is_member() or self._left_group:
            return
        loc = self.local.get(agent)
        if loc is None:
            if r.owner == me and r.status in (at.ACTIVE, at.FREEZING):
                # the table says we run it but we do not (a restarted host, a lost instance): it failed
                self._report_failed(r.id, r.epoch, "not running on its owner")
            elif r.alloc == me and not self.draining:
                if r.status == at.FROZEN:
                    self._thaw(r)
                elif r.status == at.NEW or (r.status == at.CRASHED and r.spec.recovery != "none"):
                    if not self._backing_off(r):
                        self._recover(r)
            return
        if loc.phase == "active" and r.owner == me and r.status == at.ACTIVE:
            target = r.alloc
            h = self.table.hosts.get(target)
            if self.draining or (target and target != me and target in self._member_names() and not (h and h.draining)):
                self._freeze(loc)  # Alg. 5: we lost the bid for a (or we are leaving, thesis AF-1)
            elif not target and r.spec.max_per_host:
                # issue 15: an agent of a type with a per-host limit that the allocation found no place for
                # (agenttable._tx_finish cleared its allocation): frozen, its state kept until a place frees up
                self._freeze(loc)
