"""Routing of agent messages on one host (thesis §4.8: "all messages between agents are routed via the hosts").

Agents never talk to each other directly: every message goes agent -> its host -> (the receiver's host) ->
agent. `Router` decides, from the replicated agent table and the instances this host runs
(`AgentNode.local`), where a message addressed to agent a (m.a.a.) goes from here, now:

* a's instance here is running -> to it, through its `Inbox` (exactly once, in sender order:
  `haa.core.agents.routing`), as `DeliverAgent` commands;
* a is being frozen here before Alg. 5 l. 11, or thawed (Alg. 6 l. 3) -> held by `haa.core.agents.transfer`
  (`agentstep.Hold`, addressed `agentplan.ToTransfer`); being recovered -> held by `haa.core.agents.recovery`
  (`ToRecovery(Hold)`);
* a is active on another host -> to that host (`HostSend` "msg");
* a is ours by the table but no instance runs here (its failure is being reported) -> held by the recovery
  (`ToRecovery(recovery.Orphan)`) until the table says where it is;
* a is frozen or freezing elsewhere, new or crashed -> pushed to its queue2 in the table (Alg. 5 ll. 11, 23),
  batched: one push transaction per agent in OAC at a time, of at most `max_push` messages and
  `at.MAX_QUEUE_BYTES` of payload (what a queue keeps: more would be dropped on apply anyway) unless one message
  is larger (`flush`). `held_bytes` counts the payload bytes waiting for or inside a push: the host admits a
  message for this route only while they are few (haa.hostd.budget, docs/limits.md "Messages in flight").

It also stamps what a local instance sends with its sender stream (`sent`: (sender, life, n) per receiver)
and passes replies to operator requests back to the host the request came through (`from_host` takes the
other hosts' agent messages, operator replies and transfer acknowledgements). Each method returns the
effects for `AgentNode` to carry out, in order. Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping

from google.protobuf.message import DecodeError

from haa.core.agentio import DeliverAgent, OperatorReply, Sent
from haa.core.agents import recovery as rc
from haa.core.agents import transfer as tr
from haa.core.agents.agentplan import ToRecovery, ToTransfer
from haa.core.agents.agentstep import AgentView, Cmd, Hold, HostSend, Local, Propose, Route
from haa.core.ddb import agenttable as at
from haa.core.messages import AgentHostMsg
from haa.pb import agenttx_pb2 as apb

RouteEffect = Cmd | HostSend | Propose | Route | OperatorReply | ToTransfer | ToRecovery


class Router:
    """See the module docstring."""

    def __init__(self, view: AgentView, local: Mapping[str, Local], max_push: int, counters: Counter[str]) -> None:
        self.view = view
        self.local = local
        self.max_push = max_push
        self.counters = counters
        #: messages waiting for a push to queue2, per agent
        self.pushes: dict[str, list[apb.RoutedMsg]] = {}
        #: push number -> (agent, messages) of the pushes in OAC
        self._push_reqs: dict[int, tuple[str, list[apb.RoutedMsg]]] = {}
        self._push_seq = 0
        #: payload bytes of the messages in `pushes` and in the pushes in OAC
        self.held_bytes = 0

    def route(self, m: apb.RoutedMsg, here: bool = True) -> list[RouteEffect]:
        """Where `m` goes from this host, now (`here` False: not to an instance of this host, whose transfer
        no longer holds messages: Alg. 5 l. 11)."""
        r = self.view.table.get(m.dst)
        if r is None:
            self.counters["routed_to_unknown"] += 1
            return []
        loc = self.local.get(m.dst) if here else None
        if loc is not None:
            if loc.phase == "active":
                assert loc.inbox is not None
                return [Cmd(DeliverAgent(loc.id, loc.epoch, x)) for x in loc.inbox.offer(m)]
            if loc.phase in ("freezing", "claiming", "thawing"):  # Alg. 5 l. 4 (queue1), Alg. 6 l. 3
                return [ToTransfer(Hold(m))]
            if loc.phase == "recovering":
                return [ToRecovery(Hold(m))]
        me = self.view.name
        if r.status == at.ACTIVE and r.owner and r.owner != me:
            return [HostSend(r.owner, "msg", m.dst, r.epoch, m.SerializeToString())]
        if r.status == at.ACTIVE and r.owner == me:
            # ours, but no instance here right now (its failure is being reported): hold until the table says
            return [ToRecovery(rc.Orphan(m.dst, m))]
        # frozen / freezing elsewhere (Alg. 5 l. 23), new or crashed: into queue2 (Alg. 5 l. 11, 23)
        self.pushes.setdefault(m.dst, []).append(m)
        self.held_bytes += len(m.payload)
        return []

    def sent(self, loc: Local, ev: Sent) -> list[RouteEffect]:
        """The local instance `loc` sent a message: stamp it with its sender stream and route it."""
        if loc.phase not in ("active", "freezing"):
            self.counters["sent_by_inactive_instance"] += 1
            return []
        if ev.dst.startswith("@"):  # a reply to an operator request made through host ev.dst[1:]
            if not ev.reply:
                return []
            host = ev.dst[1:]
            if host == self.view.name:
                return [OperatorReply(ev.conv, ev.payload, ev.error)]
            m = apb.RoutedMsg(src=loc.id, dst=ev.dst, payload=ev.payload, conv=ev.conv, reply=True, error=ev.error)
            return [HostSend(host, "op_reply", loc.id, 0, m.SerializeToString())]
        t = self.view.table
        dst = t.get(ev.dst)
        if dst is None:
            dst = t.resolve(ev.dst)
        if dst is None:
            self.counters["unknown_destination"] += 1
            if ev.conv and not ev.reply:  # a request to nobody: answer with an error at once
                return self.route(apb.RoutedMsg(src="", dst=loc.id, conv=ev.conv, reply=True,
                                                error=f"unknown agent {ev.dst[:64]}"))
            return []
        seq = loc.outbox.stamp(dst.id)
        return self.route(apb.RoutedMsg(src=loc.id, src_life=loc.life, seq=seq, dst=dst.id, payload=ev.payload,
                                        conv=ev.conv, reply=ev.reply, error=ev.error))

    def from_host(self, src: str, msg: AgentHostMsg) -> list[RouteEffect]:
        """A message of the agent layer from member `src` (not the allocation's): an agent message to route,
        the reply to an operator request made through this host, or a freezeAck/claimAck (Alg. 5 l. 24, Alg. 6
        l. 16) for the transfer."""
        k = msg.kind
        if k in ("freeze_ack", "claim_ack"):
            return [ToTransfer(tr.Ack(src, msg.agent, claim=k == "claim_ack"))]
        if k not in ("msg", "op_reply") or (m := self.parse(msg.data)) is None:
            return []
        if k == "op_reply":
            return [OperatorReply(m.conv, m.payload, m.error)]
        self.counters["routed_in"] += 1
        return self.route(m)

    def parse(self, data: bytes) -> apb.RoutedMsg | None:
        """A RoutedMsg from a peer's bytes; malformed bytes are counted, never fatal."""
        m = apb.RoutedMsg()
        try:
            m.ParseFromString(data)
        except DecodeError:
            self.counters["malformed_agent_msg"] += 1
            return None
        return m

    def flush(self) -> list[RouteEffect]:
        """Propose the messages held for queue2, one push transaction per agent at a time: while one is in
        OAC, later messages wait and go out together in the next (a frozen agent receiving 200 messages/s
        would otherwise cost 200 OACs/s, and the thaw waits for every one of them, Alg. 6 l. 9). Their
        order does not depend on it: the stream numbers put them in place."""
        if not self.pushes:
            return []
        out: list[RouteEffect] = []
        busy = {agent for agent, _msgs in self._push_reqs.values()}
        for agent in [a for a in self.pushes if a not in busy]:
            msgs = self.pushes.pop(agent)
            n = size = 0
            while n < len(msgs) and n < self.max_push and (n == 0 or size + len(msgs[n].payload) <= at.MAX_QUEUE_BYTES):
                size += len(msgs[n].payload)
                n += 1
            part, rest = msgs[:n], msgs[n:]
            if rest:
                self.pushes[agent] = rest
            tx = apb.AgentTx()
            tx.push.id, tx.push.queue = agent, 2
            tx.push.msgs.extend(part)
            self._push_seq += 1
            self._push_reqs[self._push_seq] = (agent, part)
            out.append(Propose(tx, "push", agent, self._push_seq))
        return out

    def push_done(self, n: int, ok: bool, member: bool) -> list[RouteEffect]:
        """Push `n` committed (`ok`) or was given up; `member`: this host is (still) a member of the group."""
        _agent, msgs = self._push_reqs.pop(n, ("", []))
        self.held_bytes -= sum(len(m.payload) for m in msgs)
        if ok:
            return []
        if member:  # aborted or refused: the table may say something else now
            return [Route(tuple(msgs))] if msgs else []
        # not a member (any more): a push is refused at once, and routing the messages again pushed them again
        # in the same drain, for ever (`haactl verify recovery` seed 238 once a joiner publishes its HostInfo).
        # The group fences a removed host's messages anyway.
        self.counters["push_dropped_not_member"] += len(msgs)
        return []
