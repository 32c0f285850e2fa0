from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RoutedMsg(_message.Message):
    __slots__ = ("src", "src_life", "seq", "dst", "payload", "conv", "reply", "error")
    SRC_FIELD_NUMBER: _ClassVar[int]
    SRC_LIFE_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    DST_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    CONV_FIELD_NUMBER: _ClassVar[int]
    REPLY_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    src: str
    src_life: int
    seq: int
    dst: str
    payload: bytes
    conv: int
    reply: bool
    error: str
    def __init__(self, src: _Optional[str] = ..., src_life: _Optional[int] = ..., seq: _Optional[int] = ..., dst: _Optional[str] = ..., payload: _Optional[bytes] = ..., conv: _Optional[int] = ..., reply: _Optional[bool] = ..., error: _Optional[str] = ...) -> None: ...

class StreamPos(_message.Message):
    __slots__ = ("src", "src_life", "next")
    SRC_FIELD_NUMBER: _ClassVar[int]
    SRC_LIFE_FIELD_NUMBER: _ClassVar[int]
    NEXT_FIELD_NUMBER: _ClassVar[int]
    src: str
    src_life: int
    next: int
    def __init__(self, src: _Optional[str] = ..., src_life: _Optional[int] = ..., next: _Optional[int] = ...) -> None: ...

class SendPos(_message.Message):
    __slots__ = ("dst", "next")
    DST_FIELD_NUMBER: _ClassVar[int]
    NEXT_FIELD_NUMBER: _ClassVar[int]
    dst: str
    next: int
    def __init__(self, dst: _Optional[str] = ..., next: _Optional[int] = ...) -> None: ...

class AgentCreate(_message.Message):
    __slots__ = ("id", "type", "config", "parent", "cost", "hardware", "transfer_penalty", "recovery", "host", "req", "max_per_host", "key")
    ID_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    PARENT_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_FIELD_NUMBER: _ClassVar[int]
    TRANSFER_PENALTY_FIELD_NUMBER: _ClassVar[int]
    RECOVERY_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    REQ_FIELD_NUMBER: _ClassVar[int]
    MAX_PER_HOST_FIELD_NUMBER: _ClassVar[int]
    KEY_FIELD_NUMBER: _ClassVar[int]
    id: str
    type: str
    config: bytes
    parent: str
    cost: float
    hardware: _containers.RepeatedScalarFieldContainer[str]
    transfer_penalty: float
    recovery: str
    host: str
    req: int
    max_per_host: int
    key: str
    def __init__(self, id: _Optional[str] = ..., type: _Optional[str] = ..., config: _Optional[bytes] = ..., parent: _Optional[str] = ..., cost: _Optional[float] = ..., hardware: _Optional[_Iterable[str]] = ..., transfer_penalty: _Optional[float] = ..., recovery: _Optional[str] = ..., host: _Optional[str] = ..., req: _Optional[int] = ..., max_per_host: _Optional[int] = ..., key: _Optional[str] = ...) -> None: ...

class AgentRemove(_message.Message):
    __slots__ = ("id", "host", "epoch")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    epoch: int
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ..., epoch: _Optional[int] = ...) -> None: ...

class AgentFreeze(_message.Message):
    __slots__ = ("id", "host", "epoch")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    epoch: int
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ..., epoch: _Optional[int] = ...) -> None: ...

class AgentRelease(_message.Message):
    __slots__ = ("id", "host", "epoch", "state", "inbox", "outbox", "pending")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    INBOX_FIELD_NUMBER: _ClassVar[int]
    OUTBOX_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    epoch: int
    state: bytes
    inbox: _containers.RepeatedCompositeFieldContainer[StreamPos]
    outbox: _containers.RepeatedCompositeFieldContainer[SendPos]
    pending: _containers.RepeatedCompositeFieldContainer[RoutedMsg]
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ..., epoch: _Optional[int] = ..., state: _Optional[bytes] = ..., inbox: _Optional[_Iterable[_Union[StreamPos, _Mapping]]] = ..., outbox: _Optional[_Iterable[_Union[SendPos, _Mapping]]] = ..., pending: _Optional[_Iterable[_Union[RoutedMsg, _Mapping]]] = ...) -> None: ...

class AgentClaim(_message.Message):
    __slots__ = ("id", "host")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ...) -> None: ...

class AgentRecovered(_message.Message):
    __slots__ = ("id", "host")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ...) -> None: ...

class AgentBackup(_message.Message):
    __slots__ = ("id", "host", "epoch", "data")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    epoch: int
    data: bytes
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ..., epoch: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class AgentFailed(_message.Message):
    __slots__ = ("id", "host", "epoch", "reason", "early")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    EARLY_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    epoch: int
    reason: str
    early: bool
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ..., epoch: _Optional[int] = ..., reason: _Optional[str] = ..., early: _Optional[bool] = ...) -> None: ...

class AgentPush(_message.Message):
    __slots__ = ("id", "queue", "msgs")
    ID_FIELD_NUMBER: _ClassVar[int]
    QUEUE_FIELD_NUMBER: _ClassVar[int]
    MSGS_FIELD_NUMBER: _ClassVar[int]
    id: str
    queue: int
    msgs: _containers.RepeatedCompositeFieldContainer[RoutedMsg]
    def __init__(self, id: _Optional[str] = ..., queue: _Optional[int] = ..., msgs: _Optional[_Iterable[_Union[RoutedMsg, _Mapping]]] = ...) -> None: ...

class AgentCost(_message.Message):
    __slots__ = ("id", "cpu")
    ID_FIELD_NUMBER: _ClassVar[int]
    CPU_FIELD_NUMBER: _ClassVar[int]
    id: str
    cpu: float
    def __init__(self, id: _Optional[str] = ..., cpu: _Optional[float] = ...) -> None: ...

class Affinity(_message.Message):
    __slots__ = ("a", "b", "rate")
    A_FIELD_NUMBER: _ClassVar[int]
    B_FIELD_NUMBER: _ClassVar[int]
    RATE_FIELD_NUMBER: _ClassVar[int]
    a: str
    b: str
    rate: float
    def __init__(self, a: _Optional[str] = ..., b: _Optional[str] = ..., rate: _Optional[float] = ...) -> None: ...

class AgentCosts(_message.Message):
    __slots__ = ("host", "costs", "affinity")
    HOST_FIELD_NUMBER: _ClassVar[int]
    COSTS_FIELD_NUMBER: _ClassVar[int]
    AFFINITY_FIELD_NUMBER: _ClassVar[int]
    host: str
    costs: _containers.RepeatedCompositeFieldContainer[AgentCost]
    affinity: _containers.RepeatedCompositeFieldContainer[Affinity]
    def __init__(self, host: _Optional[str] = ..., costs: _Optional[_Iterable[_Union[AgentCost, _Mapping]]] = ..., affinity: _Optional[_Iterable[_Union[Affinity, _Mapping]]] = ...) -> None: ...

class HostInfo(_message.Message):
    __slots__ = ("name", "capacity", "hardware", "draining")
    NAME_FIELD_NUMBER: _ClassVar[int]
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_FIELD_NUMBER: _ClassVar[int]
    DRAINING_FIELD_NUMBER: _ClassVar[int]
    name: str
    capacity: float
    hardware: _containers.RepeatedScalarFieldContainer[str]
    draining: bool
    def __init__(self, name: _Optional[str] = ..., capacity: _Optional[float] = ..., hardware: _Optional[_Iterable[str]] = ..., draining: _Optional[bool] = ...) -> None: ...

class AllocControl(_message.Message):
    __slots__ = ("paused",)
    PAUSED_FIELD_NUMBER: _ClassVar[int]
    paused: bool
    def __init__(self, paused: _Optional[bool] = ...) -> None: ...

class AllocStartTx(_message.Message):
    __slots__ = ("data", "ses_id", "leader", "group", "agents")
    DATA_FIELD_NUMBER: _ClassVar[int]
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    LEADER_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    ses_id: int
    leader: str
    group: _containers.RepeatedScalarFieldContainer[str]
    agents: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, data: _Optional[bytes] = ..., ses_id: _Optional[int] = ..., leader: _Optional[str] = ..., group: _Optional[_Iterable[str]] = ..., agents: _Optional[_Iterable[str]] = ...) -> None: ...

class AllocFinishTx(_message.Message):
    __slots__ = ("ses_id", "leader", "allocation")
    class AllocationEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    LEADER_FIELD_NUMBER: _ClassVar[int]
    ALLOCATION_FIELD_NUMBER: _ClassVar[int]
    ses_id: int
    leader: str
    allocation: _containers.ScalarMap[str, str]
    def __init__(self, ses_id: _Optional[int] = ..., leader: _Optional[str] = ..., allocation: _Optional[_Mapping[str, str]] = ...) -> None: ...

class AgentMove(_message.Message):
    __slots__ = ("id", "host")
    ID_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    id: str
    host: str
    def __init__(self, id: _Optional[str] = ..., host: _Optional[str] = ...) -> None: ...

class AgentTx(_message.Message):
    __slots__ = ("create", "remove", "start", "finish", "freeze", "release", "claim", "recovered", "backup", "failed", "push", "costs", "host", "control", "move")
    CREATE_FIELD_NUMBER: _ClassVar[int]
    REMOVE_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    FINISH_FIELD_NUMBER: _ClassVar[int]
    FREEZE_FIELD_NUMBER: _ClassVar[int]
    RELEASE_FIELD_NUMBER: _ClassVar[int]
    CLAIM_FIELD_NUMBER: _ClassVar[int]
    RECOVERED_FIELD_NUMBER: _ClassVar[int]
    BACKUP_FIELD_NUMBER: _ClassVar[int]
    FAILED_FIELD_NUMBER: _ClassVar[int]
    PUSH_FIELD_NUMBER: _ClassVar[int]
    COSTS_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    CONTROL_FIELD_NUMBER: _ClassVar[int]
    MOVE_FIELD_NUMBER: _ClassVar[int]
    create: AgentCreate
    remove: AgentRemove
    start: AllocStartTx
    finish: AllocFinishTx
    freeze: AgentFreeze
    release: AgentRelease
    claim: AgentClaim
    recovered: AgentRecovered
    backup: AgentBackup
    failed: AgentFailed
    push: AgentPush
    costs: AgentCosts
    host: HostInfo
    control: AllocControl
    move: AgentMove
    def __init__(self, create: _Optional[_Union[AgentCreate, _Mapping]] = ..., remove: _Optional[_Union[AgentRemove, _Mapping]] = ..., start: _Optional[_Union[AllocStartTx, _Mapping]] = ..., finish: _Optional[_Union[AllocFinishTx, _Mapping]] = ..., freeze: _Optional[_Union[AgentFreeze, _Mapping]] = ..., release: _Optional[_Union[AgentRelease, _Mapping]] = ..., claim: _Optional[_Union[AgentClaim, _Mapping]] = ..., recovered: _Optional[_Union[AgentRecovered, _Mapping]] = ..., backup: _Optional[_Union[AgentBackup, _Mapping]] = ..., failed: _Optional[_Union[AgentFailed, _Mapping]] = ..., push: _Optional[_Union[AgentPush, _Mapping]] = ..., costs: _Optional[_Union[AgentCosts, _Mapping]] = ..., host: _Optional[_Union[HostInfo, _Mapping]] = ..., control: _Optional[_Union[AllocControl, _Mapping]] = ..., move: _Optional[_Union[AgentMove, _Mapping]] = ...) -> None: ...

class AgentRecordPb(_message.Message):
    __slots__ = ("spec", "name", "children", "status", "owner", "alloc", "epoch", "life", "state", "has_state", "backup", "has_backup", "backup_epoch", "queue1", "queue2", "inbox", "outbox", "pending", "cpu", "dropped", "since", "failures", "fail_reason")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    CHILDREN_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    OWNER_FIELD_NUMBER: _ClassVar[int]
    ALLOC_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    LIFE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    HAS_STATE_FIELD_NUMBER: _ClassVar[int]
    BACKUP_FIELD_NUMBER: _ClassVar[int]
    HAS_BACKUP_FIELD_NUMBER: _ClassVar[int]
    BACKUP_EPOCH_FIELD_NUMBER: _ClassVar[int]
    QUEUE1_FIELD_NUMBER: _ClassVar[int]
    QUEUE2_FIELD_NUMBER: _ClassVar[int]
    INBOX_FIELD_NUMBER: _ClassVar[int]
    OUTBOX_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    CPU_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    SINCE_FIELD_NUMBER: _ClassVar[int]
    FAILURES_FIELD_NUMBER: _ClassVar[int]
    FAIL_REASON_FIELD_NUMBER: _ClassVar[int]
    spec: AgentCreate
    name: str
    children: int
    status: str
    owner: str
    alloc: str
    epoch: int
    life: int
    state: bytes
    has_state: bool
    backup: bytes
    has_backup: bool
    backup_epoch: int
    queue1: _containers.RepeatedCompositeFieldContainer[RoutedMsg]
    queue2: _containers.RepeatedCompositeFieldContainer[RoutedMsg]
    inbox: _containers.RepeatedCompositeFieldContainer[StreamPos]
    outbox: _containers.RepeatedCompositeFieldContainer[SendPos]
    pending: _containers.RepeatedCompositeFieldContainer[RoutedMsg]
    cpu: float
    dropped: int
    since: float
    failures: int
    fail_reason: str
    def __init__(self, spec: _Optional[_Union[AgentCreate, _Mapping]] = ..., name: _Optional[str] = ..., children: _Optional[int] = ..., status: _Optional[str] = ..., owner: _Optional[str] = ..., alloc: _Optional[str] = ..., epoch: _Optional[int] = ..., life: _Optional[int] = ..., state: _Optional[bytes] = ..., has_state: _Optional[bool] = ..., backup: _Optional[bytes] = ..., has_backup: _Optional[bool] = ..., backup_epoch: _Optional[int] = ..., queue1: _Optional[_Iterable[_Union[RoutedMsg, _Mapping]]] = ..., queue2: _Optional[_Iterable[_Union[RoutedMsg, _Mapping]]] = ..., inbox: _Optional[_Iterable[_Union[StreamPos, _Mapping]]] = ..., outbox: _Optional[_Iterable[_Union[SendPos, _Mapping]]] = ..., pending: _Optional[_Iterable[_Union[RoutedMsg, _Mapping]]] = ..., cpu: _Optional[float] = ..., dropped: _Optional[int] = ..., since: _Optional[float] = ..., failures: _Optional[int] = ..., fail_reason: _Optional[str] = ...) -> None: ...

class AgentTableSnapshot(_message.Message):
    __slots__ = ("records", "ses_id", "finished_ses", "top", "hosts", "paused", "affinity", "start_group", "start_agents", "valid_ses")
    RECORDS_FIELD_NUMBER: _ClassVar[int]
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    FINISHED_SES_FIELD_NUMBER: _ClassVar[int]
    TOP_FIELD_NUMBER: _ClassVar[int]
    HOSTS_FIELD_NUMBER: _ClassVar[int]
    PAUSED_FIELD_NUMBER: _ClassVar[int]
    AFFINITY_FIELD_NUMBER: _ClassVar[int]
    START_GROUP_FIELD_NUMBER: _ClassVar[int]
    START_AGENTS_FIELD_NUMBER: _ClassVar[int]
    VALID_SES_FIELD_NUMBER: _ClassVar[int]
    records: _containers.RepeatedCompositeFieldContainer[AgentRecordPb]
    ses_id: int
    finished_ses: int
    top: int
    hosts: _containers.RepeatedCompositeFieldContainer[HostInfo]
    paused: bool
    affinity: _containers.RepeatedCompositeFieldContainer[Affinity]
    start_group: _containers.RepeatedScalarFieldContainer[str]
    start_agents: _containers.RepeatedScalarFieldContainer[str]
    valid_ses: int
    def __init__(self, records: _Optional[_Iterable[_Union[AgentRecordPb, _Mapping]]] = ..., ses_id: _Optional[int] = ..., finished_ses: _Optional[int] = ..., top: _Optional[int] = ..., hosts: _Optional[_Iterable[_Union[HostInfo, _Mapping]]] = ..., paused: _Optional[bool] = ..., affinity: _Optional[_Iterable[_Union[Affinity, _Mapping]]] = ..., start_group: _Optional[_Iterable[str]] = ..., start_agents: _Optional[_Iterable[str]] = ..., valid_ses: _Optional[int] = ...) -> None: ...
