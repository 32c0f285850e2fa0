"""EffectDispatcher: carries out the effects the host's state machines return, one `match` over a closed union.

After every input the runtime drains its node (`AgentNode` -> `MembershipNode` -> `HostCore`, each layer
consuming what is meant for it and passing the rest up) and gives the list to `run`. `HostEffect` is every
effect that can reach it: the core's (`haa.core.effects.Effect`), the membership node's (`NodeEffect`) and
the agent layer's (its commands, timeline entries and operator answers, haa.core.agentio). The `match`
ends in `assert_never`, so an effect added to one of those unions and not handled here is a type error
(mypy), not a silent drop:

* `Send` -> the transport's per-peer queue (never blocks); `Connect` -> a new peer of the transport;
* `SetTimer`/`CancelTimer` -> the timer wheel (haa.hostd.timers);
* `Decided`/`Deliver` -> the latency samples and propose waiters (haa.hostd.proposals) and the delivered
  log (haa.hostd.delivered); `Closed` -> a counter;
* `Suspicion`, `PeerDead`, `Log` -> the JSON-lines log (a core `Log` that repeats a typed effect at debug
  level, a bug caught by a safety net at error level);
* `AppliedTx`, `ViewChange` -> counters, the mirror subscribers (haa.hostd.mirrors) and the known-hosts
  file (haa.hostd.datadir); `WriteDone` -> the writes (haa.hostd.writes); `Left` -> the runtime;
* agent commands and timeline entries -> the agent backend (processes); `AgentOpDone`, `OperatorReply` ->
  the waiting operator calls (haa.hostd.agentops);
* `Reincarnate` -> returned: the runtime replaces its node once the whole list is carried out.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from typing import assert_never

from haa.core import agentio as io
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
from haa.core.membership.membership import AppliedTx, Connect, Left, NodeEffect, ViewChange, WriteDone
from haa.hostd.agentops import AgentBackend, AgentCommand, AgentOps
from haa.hostd.datadir import HostDataDir
from haa.hostd.delivered import DeliveredLog
from haa.hostd.logs import LOGGER_NAME, log_event
from haa.hostd.mirrors import Mirrors
from haa.hostd.proposals import Proposals
from haa.hostd.timers import TimerWheel
from haa.hostd.transport import Transport
from haa.hostd.writes import Writes

log = logging.getLogger(LOGGER_NAME + ".runtime")

#: every effect a host's node returns to its runtime
HostEffect = Effect | NodeEffect | AgentCommand | io.AgentTimeline | io.AgentOpDone | io.OperatorReply
#: core `Log` events that duplicate a typed effect (`PeerDead`) the runtime logs itself
_TYPED_EVENTS = frozenset({"peer_dead"})
#: core Log events that report a bug caught by a safety net (logged at error level)
_ERROR_EVENTS = frozenset({"agent_layer_error"})


class EffectDispatcher:
    """See the module docstring. `agents` is None without the agent layer."""

    def __init__(
        self,
        *,
        transport: Transport,
        timers: TimerWheel,
        proposals: Proposals,
        delivered: DeliveredLog,
        writes: Writes,
        mirrors: Mirrors,
        agent_ops: AgentOps,
        agents: AgentBackend | None,
        data: HostDataDir,
        counters: Counter[str],
        on_left: Callable[[], None],
    ) -> None:
        self.transport = transport
        self.timers = timers
        self.proposals = proposals
        self.delivered = delivered
        self.writes = writes
        self.mirrors = mirrors
        self.agent_ops = agent_ops
        self.agents = agents
        self.data = data
        self.counters = counters
        self.on_left = on_left

    def run(self, effects: list[HostEffect]) -> str | None:
        """Carry out `effects` in order; the reason of a `Reincarnate` among them, else None."""
        # the frequent effects first, their sinks bound once per list (this loop is the runtime's hot path)
        send = self.transport.send
        set_timer = self.timers.set
        cancel_timer = self.timers.cancel
        counters = self.counters
        reincarnate_by: str | None = None
        now = time.monotonic()
        for e in effects:
            match e:
                case Send():
                    send(e.dst, e.dst_inc, e.msg, e.lazy)
                case SetTimer():
                    set_timer(e.key, e.at)
                case CancelTimer():
                    cancel_timer(e.key)
                case Decided():
                    self.proposals.decided(now, e)
                    counters["oac_committed" if e.commit else "oac_aborted"] += 1
                case Deliver():
                    d2d = self.proposals.delivering(now, e)
                    self.delivered.append(e.txid, e.order, e.payload)
                    counters["oac_delivered"] += 1
                    self.proposals.delivered(e.txid, d2d)
                case Closed():
                    counters["oac_closed"] += 1
                case Voted():
                    if not e.ok:
                        counters["oac_voted_no"] += 1
                case Suspicion():
                    log_event(log, logging.INFO, "suspicion", peer=e.peer, inc=e.inc, suspected=e.suspected)
                case PeerDead():
                    log_event(log, logging.WARNING, "peer_dead", peer=e.peer, inc=e.inc, reason=e.reason)
                case Reincarnate():
                    reincarnate_by = e.by
                case Log():
                    # the core also logs what a typed effect above already carries: keep those at debug level
                    ev = e.event
                    level = (logging.DEBUG if ev in _TYPED_EVENTS
                             else logging.ERROR if ev in _ERROR_EVENTS else logging.INFO)
                    log_event(log, level, ev, **e.fields)
                case Connect():
                    self.transport.add_peer(e.name, e.addr)
                case AppliedTx():
                    counters["global_applied"] += 1
                    self.mirrors.applied(e)
                case ViewChange():
                    counters["view_changes"] += 1
                    self.data.save_known_hosts(e.members)
                    self.mirrors.view(e)
                case WriteDone():
                    self.writes.done(e)
                case Left():
                    self.on_left()
                case (io.SpawnShell() | io.StartAgent() | io.DeliverAgent() | io.FreezeAgent() | io.KillAgent()
                      | io.AnswerAgent()):
                    if self.agents is not None:
                        self.agents.command(e)
                case io.AgentTimeline():
                    if self.agents is not None:
                        self.agents.on_timeline(e)
                case io.AgentOpDone():
                    self.agent_ops.op_done(e)
                case io.OperatorReply():
                    self.agent_ops.replied(e)
                case _:
                    assert_never(e)
        return reincarnate_by
