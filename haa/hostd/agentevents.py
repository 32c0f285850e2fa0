"""The values and events between a host and its agent processes: what `AgentSupervisor` (haa.hostd.agentproc)
takes (`InstanceSpec`, `Envelope`), the events it reports (`AgentEvent`: Ready ... Failed; the module docstring
of haa.hostd.agentproc says when and in which order) and its per-agent measurements (`AgentStats`). Plain data:
the daemon's agent driver (haa.hostd.agentdriver) dispatches on these types.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field

from haa.pb import agent_pb2 as pb

__all__ = [
    "AgentEvent",
    "AgentStats",
    "Backup",
    "DdbGet",
    "DdbPut",
    "DdbScan",
    "DdbUnwatch",
    "DdbWatch",
    "DdbWrite",
    "Envelope",
    "Failed",
    "Frozen",
    "InstanceSpec",
    "Ready",
    "Sent",
    "SpawnChild",
    "Stopped",
]

UINT64_MAX = 2**64 - 1


# ---------------------------------------------------------------------------------------------- values


@dataclass(frozen=True)
class InstanceSpec:
    """One instance of an agent on this host. `epoch` fences instances: a new one (thaw, recovery) gets a
    larger epoch than every earlier instance of the same agent."""

    agent_id: str
    name: str
    type_name: str
    config: bytes = b""
    epoch: int = 0
    parent: str | None = None

    def validate(self) -> None:
        """Raise ValueError naming the field and the reason."""
        try:
            if str(uuid.UUID(self.agent_id)) != self.agent_id.lower():
                raise ValueError
        except (ValueError, TypeError, AttributeError):
            raise ValueError(f"agent_id: not a UUID string: {self.agent_id!r}") from None
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("name: must be a non-empty string")
        if not isinstance(self.type_name, str) or not self.type_name:
            raise ValueError("type_name: must be a non-empty string")
        if not isinstance(self.config, bytes):
            raise ValueError(f"config: must be bytes, not {type(self.config).__name__}")
        if isinstance(self.epoch, bool) or not isinstance(self.epoch, int) or not 0 <= self.epoch <= UINT64_MAX:
            raise ValueError(f"epoch: must be an int in 0..2**64-1, got {self.epoch!r}")
        if self.parent is not None and not isinstance(self.parent, str):
            raise ValueError(f"parent: must be an agent id or None, got {self.parent!r}")


@dataclass(frozen=True)
class Envelope:
    """A message between agents as the host sees it. `src` = "" for the host/operator; `conv` != 0 makes it
    a request (reply False) or its response (reply True, `error` set if it failed)."""

    src: str
    dst: str
    payload: bytes
    conv: int = 0
    reply: bool = False
    error: str = ""

    def to_pb(self) -> pb.AgentMsg:
        return pb.AgentMsg(src=self.src, dst=self.dst, payload=self.payload, conv=self.conv, reply=self.reply,
                           error=self.error)

    @staticmethod
    def from_pb(m: pb.AgentMsg) -> Envelope:
        return Envelope(src=m.src, dst=m.dst, payload=bytes(m.payload), conv=m.conv, reply=m.reply, error=m.error)


# ---------------------------------------------------------------------------------------------- events


@dataclass(frozen=True)
class Ready:
    """The agent started (`how` = "start"), thawed ("thaw") or recovered ("recover") and handled the
    messages queued for it."""

    agent_id: str
    how: str = "start"


@dataclass(frozen=True)
class Sent:
    """A message the agent sent (including responses to requests), in the agent's send order. `env.src` is
    always the agent's id (the supervisor sets it; an agent cannot pose as another)."""

    agent_id: str
    env: Envelope


@dataclass(frozen=True)
class Backup:
    """Alg. 7 l. 3: the agent's backup, for DDB.agents[a].backup."""

    agent_id: str
    data: bytes


@dataclass(frozen=True)
class Frozen:
    """Alg. 5 l. 19: the agent's packed state; the process is exiting. Terminal."""

    agent_id: str
    state: bytes


@dataclass(frozen=True)
class SpawnChild:
    """The agent asks for a child; answer with `answer(agent_id, req_id, ok, child_id.encode())`."""

    agent_id: str
    req_id: int
    type_name: str
    config: bytes
    #: the spawn's idempotence key (docs/agents.md, "Idempotent spawn"; "" = always a new child)
    key: str = ""


@dataclass(frozen=True)
class DdbGet:
    """Answer with `answer(agent_id, req_id, True, value)` or `answer(..., True, b"", missing=True)`."""

    agent_id: str
    req_id: int
    key: str


@dataclass(frozen=True)
class DdbScan:
    """Answer with `answer(agent_id, req_id, True, b"", keys=[...], values=[...], truncated=...)`."""

    agent_id: str
    req_id: int
    prefix: str
    limit: int


@dataclass(frozen=True)
class DdbPut:
    """Answer with `answer(agent_id, req_id, ok, b"", error)` once the write is committed (or refused)."""

    agent_id: str
    req_id: int
    key: str
    value: bytes
    type_name: str = "blob"


@dataclass(frozen=True)
class DdbWrite:
    """Several DDB ops (`haa.pb.ddb_pb2.DdbOp`) in one batch; answer with `answer(agent_id, req_id, committed,
    b"", error, op_errors=[...])` once the batch is committed (or refused)."""

    agent_id: str
    req_id: int
    ops: tuple[object, ...]
    atomic: bool = False


@dataclass(frozen=True)
class DdbWatch:
    """Notify DDB events on keys starting with `prefix` with `notify_watch(agent_id, watch_id, ...)`."""

    agent_id: str
    watch_id: int
    prefix: str


@dataclass(frozen=True)
class DdbUnwatch:
    agent_id: str
    watch_id: int


@dataclass(frozen=True)
class Stopped:
    """The agent ended itself normally (or after `stop()`); the process is exiting. Terminal."""

    agent_id: str


@dataclass(frozen=True)
class Failed:
    """The agent failed; its process is gone. Terminal. `reason`: see haa.hostd.agentproc's docstring."""

    agent_id: str
    reason: str


AgentEvent = (
    Ready | Sent | Backup | Frozen | SpawnChild | DdbGet | DdbScan | DdbPut | DdbWrite | DdbWatch | DdbUnwatch
    | Stopped | Failed
)


@dataclass
class AgentStats:
    """A snapshot of one agent process (see haa.hostd.agentproc's docstring, "Measurements")."""

    agent_id: str
    name: str
    type_name: str
    epoch: int
    pid: int
    state: str
    cpu: float = 0.0  # fraction of one core over the last window
    cpu_seconds: float = 0.0
    rss: int = 0
    msgs_in: dict[str, int] = field(default_factory=dict)
    bytes_in: dict[str, int] = field(default_factory=dict)
    msgs_out: dict[str, int] = field(default_factory=dict)
    bytes_out: dict[str, int] = field(default_factory=dict)
    buffered: int = 0  # messages held here until the agent starts
    mailbox: int = 0  # items waiting in the agent's mailbox (its last heartbeat)
    handled: int = 0
    uptime: float = 0.0
    spawn_seconds: float = 0.0  # spawn() call -> Hello
