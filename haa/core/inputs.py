"""The inputs a driver feeds a host's state machine: one closed union, one `step(now, input)`.

A host's state machine is a `HostCore` (static peer list), a `MembershipNode` over one (membership mode) or
an `AgentNode` over that (agents on). Each takes these inputs through `step(now, input)` — the model is
etcd-io/raft's `Step(msg)`; its `Ready` is `drain()`, which returns the effects accumulated since — and
dispatches them with one `match` ending in `assert_never`, so an input added here and forgotten by a node is
a mypy error. The real runtime (`haa.hostd.runtime`) and the simulator (`haa.lab.dsim.cluster`) feed every
host-level input this way, and an `AgentNode` takes the agent layer's inputs the same way (below).

* `Start` — the process started (groupJoin() in membership mode, Alg. 3 l. 35);
* `Receive` — a message from host `src`'s incarnation `src_inc`, addressed to incarnation `dst_inc`
  (0: any), already decoded and its envelope checked by the transport;
* `TimerFired` — the timer set by a `SetTimer(key, at)` effect fired;
* `FdReport` — an external failure detector's verdict on `peer` (fd_mode "external": the simulator's
  adversarial model);
* `PeerInfo` — the transport learnt `peer`'s incarnation from a handshake;
* `Submit` — a global-state change (`kind` "ddb", "agent" or "test"; membership mode only), answered by a
  `WriteDone` effect;
* `LeaveGroup` — groupLeave() (Alg. 3 l. 14; membership mode only).

The agent layer's inputs (`AgentNode.step`; the requests are built by `haa.core.agents.agentrequests`):

* `CreateAgent`, `RemoveAgent`, `MoveAgent`, `SetPaused` — operator requests, each answered by an
  `AgentOpDone` effect carrying `req`;
* `RunAllocation` — an operator asks for an allocation session now;
* `ReportCosts` — measured CPU per local agent and message rates between agent pairs (Alg. 4 ll. 22-23);
* `OperatorSend` — a message from the operator to an agent (`src` "@<host>": a request answered by an
  `OperatorReply` effect); the caller resolves `dst` first (an unknown agent is the caller's answer);
* `InstanceEvent` — what a local agent instance did (`haa.core.agentio`: shell ready, sent, backup, frozen,
  failed, stopped, spawn a child);
* `Undeliverable` — the driver could not hand a message to an instance whose process is ending.

`HostCore.step` and `MembershipNode.step` return what they hand to the layer above (a membership message
the core let through, an agent-layer message), the outer node consumes it; the driver ignores it.

No I/O.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping
from dataclasses import dataclass

from haa.core.agentio import AgentEvent
from haa.core.messages import Message
from haa.pb import agenttx_pb2 as apb


@dataclass(frozen=True, slots=True)
class Start:
    pass


@dataclass(frozen=True, slots=True)
class Receive:
    src: str
    src_inc: int
    dst_inc: int
    msg: Message


@dataclass(frozen=True, slots=True)
class TimerFired:
    key: Hashable


@dataclass(frozen=True, slots=True)
class FdReport:
    peer: str
    suspected: bool


@dataclass(frozen=True, slots=True)
class PeerInfo:
    peer: str
    inc: int


@dataclass(frozen=True, slots=True)
class Submit:
    """A global-state change of this host (`MembershipNode.submit`); `cost`: its apply cost (DDB ops)."""

    payload: bytes
    req: Hashable
    kind: str = "ddb"
    cost: int = 1


@dataclass(frozen=True, slots=True)
class LeaveGroup:
    pass


@dataclass(frozen=True, slots=True)
class CreateAgent:
    agent_id: str
    type_name: str
    config: bytes = b""
    parent: str = ""
    cost: float = 0.1
    hardware: tuple[str, ...] = ()
    transfer_penalty: float = 0.1
    recovery: str = "backup"
    max_per_host: int = 0
    req: Hashable = None
    key: str = ""


@dataclass(frozen=True, slots=True)
class RemoveAgent:
    ref: str
    req: Hashable = None


@dataclass(frozen=True, slots=True)
class MoveAgent:
    ref: str
    host: str
    req: Hashable = None


@dataclass(frozen=True, slots=True)
class SetPaused:
    paused: bool
    req: Hashable = None


@dataclass(frozen=True, slots=True)
class RunAllocation:
    pass


@dataclass(frozen=True, slots=True)
class ReportCosts:
    cpu: Mapping[str, float]
    affinity: Mapping[tuple[str, str], float]


@dataclass(frozen=True, slots=True)
class OperatorSend:
    dst: str
    payload: bytes
    conv: int = 0
    src: str = ""


@dataclass(frozen=True, slots=True)
class InstanceEvent:
    ev: AgentEvent


@dataclass(frozen=True, slots=True)
class Undeliverable:
    agent: str
    epoch: int
    msg: apb.RoutedMsg


#: what a bare `HostCore` takes
CoreInput = Start | Receive | TimerFired | FdReport | PeerInfo
#: what a `MembershipNode` takes
NodeInput = CoreInput | Submit | LeaveGroup
#: the agent layer's own inputs, and what an `AgentNode` takes
AgentLayerInput = (CreateAgent | RemoveAgent | MoveAgent | SetPaused | RunAllocation | ReportCosts | OperatorSend
                   | InstanceEvent | Undeliverable)
AgentInput = NodeInput | AgentLayerInput
