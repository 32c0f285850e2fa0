"""The inputs a driver feeds a host's state machine: one closed union, one `step(now, input)`.

A host's state machine is a `HostCore` (static peer list), a `MembershipNode` over one (membership mode) or
an `AgentNode` over that (agents on). Each takes these inputs through `step(now, input)` — the model is
etcd-io/raft's `Step(msg)`; its `Ready` is `drain()`, which returns the effects accumulated since — and
dispatches them with one `match` ending in `assert_never`, so an input added here and forgotten by a node is
a mypy error. The real runtime (`haa.hostd.runtime`) and the simulator (`haa.lab.dsim.cluster`) feed every
host-level input this way. (The agent layer's own requests — create, move, an agent's events — are
`AgentNode` methods: `haa.core.agentrequests`.)

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

`HostCore.step` and `MembershipNode.step` return what they hand to the layer above (a membership message
the core let through, an agent-layer message), the outer node consumes it; the driver ignores it.

No I/O.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass

from haa.core.messages import Message


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
    payload: bytes
    req: Hashable
    kind: str = "ddb"


@dataclass(frozen=True, slots=True)
class LeaveGroup:
    pass


#: what a bare `HostCore` takes
CoreInput = Start | Receive | TimerFired | FdReport | PeerInfo
#: what a `MembershipNode` (and an `AgentNode`) takes
NodeInput = CoreInput | Submit | LeaveGroup
