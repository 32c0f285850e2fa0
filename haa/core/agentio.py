"""The vocabulary between the agent layer (`haa.core.agents.agentnode`) and whatever runs agent instances.

`AgentNode` is sans-I/O: it never starts a process. It asks its driver to, with the *commands* below, and
learns what the instances did from the *events* the driver feeds back (`InstanceEvent` inputs of
`AgentNode.step`). The real driver is the daemon with its `haa.hostd.agentproc.AgentSupervisor` (OS processes);
the deterministic simulator (`haa.lab.dsim.agents`) runs simulated agents. Every command and event names the
instance by agent id *and epoch* (the fencing epoch of the agent table): an event of an older instance is ignored.

Messages cross this boundary as `haa.v1.RoutedMsg` (proto/haa/pb/agenttx.proto).
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

from haa.pb import agenttx_pb2 as apb

# ----------------------------------------------------------------------------------------------- commands


@dataclass(slots=True)
class SpawnShell:
    """Start a process for `agent` that waits for its first command (Alg. 6 l. 2, Alg. 8 l. 2)."""

    agent: str
    epoch: int
    type: str
    name: str
    config: bytes
    parent: str


@dataclass(slots=True)
class StartAgent:
    """Start the shell: `mode` "fresh" (a new agent: on_start), "thaw" (Alg. 6 l. 10: unpack `state`, then the
    messages in order) or "recover" (Alg. 8 l. 4: recover(`state` = the latest backup, None if none)).
    `messages` are passed to the agent, in order, before anything delivered later."""

    agent: str
    epoch: int
    mode: str
    state: bytes | None
    messages: list[apb.RoutedMsg] = field(default_factory=list)


@dataclass(slots=True)
class DeliverAgent:
    """Pass one message to a running instance (in the order of these commands)."""

    agent: str
    epoch: int
    msg: apb.RoutedMsg


@dataclass(slots=True)
class FreezeAgent:
    """Alg. 5 l. 2: the instance finishes the messages delivered so far, packs its state (-> `Frozen`) and ends."""

    agent: str
    epoch: int


@dataclass(slots=True)
class KillAgent:
    """End the instance now (abandoned claim, removed agent, fenced instance)."""

    agent: str
    epoch: int
    reason: str


@dataclass(slots=True)
class AnswerAgent:
    """The answer to an instance's request (`SpawnChild`): `value` is the child's id."""

    agent: str
    epoch: int
    req: int
    ok: bool
    value: str
    error: str = ""


@dataclass(slots=True)
class AgentOpDone:
    """An operator request (create, remove, move, pause) was committed (`ok`) or refused (`reason`)."""

    req: Hashable
    ok: bool
    agent: str = ""
    name: str = ""
    reason: str = ""


@dataclass(slots=True)
class OperatorReply:
    """An agent answered the operator request `conv` (made through this host)."""

    conv: int
    payload: bytes
    error: str = ""


@dataclass(slots=True)
class AgentTimeline:
    """One line of the allocation timeline (thesis Fig. 7.1-2 style): `event` on agent `name` at this host."""

    agent: str
    name: str
    #: spawning, active, freezing, frozen, thawing, thawed, crashed, backoff, failed, recovering, recovered, removed
    event: str
    host: str
    detail: str = ""


AGENT_COMMANDS = (SpawnShell, StartAgent, DeliverAgent, FreezeAgent, KillAgent, AnswerAgent)
#: the commands a driver of agent instances carries out
AgentCommand = SpawnShell | StartAgent | DeliverAgent | FreezeAgent | KillAgent | AnswerAgent

# ----------------------------------------------------------------------------------------------- events


@dataclass(slots=True)
class ShellReady:
    agent: str
    epoch: int


@dataclass(slots=True)
class Sent:
    """The instance sent `payload` to agent `dst` (in the instance's send order)."""

    agent: str
    epoch: int
    dst: str
    payload: bytes
    conv: int = 0
    reply: bool = False
    error: str = ""


@dataclass(slots=True)
class BackupMade:
    """Alg. 7 l. 3: (backup, a, b)."""

    agent: str
    epoch: int
    data: bytes


@dataclass(slots=True)
class Frozen:
    """Alg. 5 l. 19: (state) from a; every `Sent` of the instance came before it."""

    agent: str
    epoch: int
    state: bytes


@dataclass(slots=True)
class Failed:
    """The instance died or hung (the driver has made sure it is gone)."""

    agent: str
    epoch: int
    reason: str


@dataclass(slots=True)
class Stopped:
    """The agent ended itself (`AgentBase.stop()`): it is removed from the table."""

    agent: str
    epoch: int


@dataclass(slots=True)
class SpawnChild:
    """The instance asks for a child agent; the driver drew `child_id` (a UUID: the core has no randomness)."""

    agent: str
    epoch: int
    req: int
    type: str
    config: bytes
    child_id: str
    #: the child type's per-host limit (AgentTypeInfo.max_per_host; issue 15)
    max_per_host: int = 0
    #: the spawn's idempotence key ("" = always a new child; docs/agents.md, "Idempotent spawn")
    key: str = ""


AgentEvent = ShellReady | Sent | BackupMade | Frozen | Failed | Stopped | SpawnChild
