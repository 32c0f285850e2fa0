from haa.pb import hostlink_pb2 as _hostlink_pb2
from haa.pb import ddb_pb2 as _ddb_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class StatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class PeerStatus(_message.Message):
    __slots__ = ("name", "address", "incarnation", "suspected", "excluded", "connected", "heartbeat_period", "alpha")
    NAME_FIELD_NUMBER: _ClassVar[int]
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    SUSPECTED_FIELD_NUMBER: _ClassVar[int]
    EXCLUDED_FIELD_NUMBER: _ClassVar[int]
    CONNECTED_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_PERIOD_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    name: str
    address: str
    incarnation: int
    suspected: bool
    excluded: bool
    connected: bool
    heartbeat_period: float
    alpha: float
    def __init__(self, name: _Optional[str] = ..., address: _Optional[str] = ..., incarnation: _Optional[int] = ..., suspected: _Optional[bool] = ..., excluded: _Optional[bool] = ..., connected: _Optional[bool] = ..., heartbeat_period: _Optional[float] = ..., alpha: _Optional[float] = ...) -> None: ...

class Counters(_message.Message):
    __slots__ = ("values",)
    class ValuesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.ScalarMap[str, int]
    def __init__(self, values: _Optional[_Mapping[str, int]] = ...) -> None: ...

class StatusReply(_message.Message):
    __slots__ = ("name", "incarnation", "peers", "active_transactions", "decided_transactions", "delivered", "delivered_hash", "counters", "cpu_percent", "rss_bytes", "uptime", "mode", "member", "members", "member_info", "leader", "view", "rank", "suspicions", "ddb_size", "ddb_hash", "ddb_seq", "global_seq", "state_hash", "group_id", "group_correct", "locked", "applicants", "leaving", "load_cpu_seconds")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    PEERS_FIELD_NUMBER: _ClassVar[int]
    ACTIVE_TRANSACTIONS_FIELD_NUMBER: _ClassVar[int]
    DECIDED_TRANSACTIONS_FIELD_NUMBER: _ClassVar[int]
    DELIVERED_FIELD_NUMBER: _ClassVar[int]
    DELIVERED_HASH_FIELD_NUMBER: _ClassVar[int]
    COUNTERS_FIELD_NUMBER: _ClassVar[int]
    CPU_PERCENT_FIELD_NUMBER: _ClassVar[int]
    RSS_BYTES_FIELD_NUMBER: _ClassVar[int]
    UPTIME_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    MEMBER_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    MEMBER_INFO_FIELD_NUMBER: _ClassVar[int]
    LEADER_FIELD_NUMBER: _ClassVar[int]
    VIEW_FIELD_NUMBER: _ClassVar[int]
    RANK_FIELD_NUMBER: _ClassVar[int]
    SUSPICIONS_FIELD_NUMBER: _ClassVar[int]
    DDB_SIZE_FIELD_NUMBER: _ClassVar[int]
    DDB_HASH_FIELD_NUMBER: _ClassVar[int]
    DDB_SEQ_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_SEQ_FIELD_NUMBER: _ClassVar[int]
    STATE_HASH_FIELD_NUMBER: _ClassVar[int]
    GROUP_ID_FIELD_NUMBER: _ClassVar[int]
    GROUP_CORRECT_FIELD_NUMBER: _ClassVar[int]
    LOCKED_FIELD_NUMBER: _ClassVar[int]
    APPLICANTS_FIELD_NUMBER: _ClassVar[int]
    LEAVING_FIELD_NUMBER: _ClassVar[int]
    LOAD_CPU_SECONDS_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    peers: _containers.RepeatedCompositeFieldContainer[PeerStatus]
    active_transactions: int
    decided_transactions: int
    delivered: int
    delivered_hash: str
    counters: Counters
    cpu_percent: float
    rss_bytes: int
    uptime: float
    mode: str
    member: bool
    members: _containers.RepeatedScalarFieldContainer[str]
    member_info: _containers.RepeatedCompositeFieldContainer[MemberInfo]
    leader: str
    view: int
    rank: int
    suspicions: _containers.RepeatedScalarFieldContainer[str]
    ddb_size: int
    ddb_hash: str
    ddb_seq: int
    global_seq: int
    state_hash: str
    group_id: str
    group_correct: bool
    locked: str
    applicants: _containers.RepeatedScalarFieldContainer[str]
    leaving: bool
    load_cpu_seconds: float
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., peers: _Optional[_Iterable[_Union[PeerStatus, _Mapping]]] = ..., active_transactions: _Optional[int] = ..., decided_transactions: _Optional[int] = ..., delivered: _Optional[int] = ..., delivered_hash: _Optional[str] = ..., counters: _Optional[_Union[Counters, _Mapping]] = ..., cpu_percent: _Optional[float] = ..., rss_bytes: _Optional[int] = ..., uptime: _Optional[float] = ..., mode: _Optional[str] = ..., member: _Optional[bool] = ..., members: _Optional[_Iterable[str]] = ..., member_info: _Optional[_Iterable[_Union[MemberInfo, _Mapping]]] = ..., leader: _Optional[str] = ..., view: _Optional[int] = ..., rank: _Optional[int] = ..., suspicions: _Optional[_Iterable[str]] = ..., ddb_size: _Optional[int] = ..., ddb_hash: _Optional[str] = ..., ddb_seq: _Optional[int] = ..., global_seq: _Optional[int] = ..., state_hash: _Optional[str] = ..., group_id: _Optional[str] = ..., group_correct: _Optional[bool] = ..., locked: _Optional[str] = ..., applicants: _Optional[_Iterable[str]] = ..., leaving: _Optional[bool] = ..., load_cpu_seconds: _Optional[float] = ...) -> None: ...

class MemberInfo(_message.Message):
    __slots__ = ("name", "incarnation", "address", "suspected")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    SUSPECTED_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    address: str
    suspected: bool
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., address: _Optional[str] = ..., suspected: _Optional[bool] = ...) -> None: ...

class ProposeRequest(_message.Message):
    __slots__ = ("payload", "participants", "wait")
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    PARTICIPANTS_FIELD_NUMBER: _ClassVar[int]
    WAIT_FIELD_NUMBER: _ClassVar[int]
    payload: bytes
    participants: _containers.RepeatedScalarFieldContainer[str]
    wait: bool
    def __init__(self, payload: _Optional[bytes] = ..., participants: _Optional[_Iterable[str]] = ..., wait: _Optional[bool] = ...) -> None: ...

class ProposeReply(_message.Message):
    __slots__ = ("id", "decided", "committed", "propose_to_decide", "decide_to_deliver", "participants")
    ID_FIELD_NUMBER: _ClassVar[int]
    DECIDED_FIELD_NUMBER: _ClassVar[int]
    COMMITTED_FIELD_NUMBER: _ClassVar[int]
    PROPOSE_TO_DECIDE_FIELD_NUMBER: _ClassVar[int]
    DECIDE_TO_DELIVER_FIELD_NUMBER: _ClassVar[int]
    PARTICIPANTS_FIELD_NUMBER: _ClassVar[int]
    id: _hostlink_pb2.TxId
    decided: bool
    committed: bool
    propose_to_decide: float
    decide_to_deliver: float
    participants: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, id: _Optional[_Union[_hostlink_pb2.TxId, _Mapping]] = ..., decided: _Optional[bool] = ..., committed: _Optional[bool] = ..., propose_to_decide: _Optional[float] = ..., decide_to_deliver: _Optional[float] = ..., participants: _Optional[_Iterable[str]] = ...) -> None: ...

class DeliveriesRequest(_message.Message):
    __slots__ = ("from_index",)
    FROM_INDEX_FIELD_NUMBER: _ClassVar[int]
    from_index: int
    def __init__(self, from_index: _Optional[int] = ...) -> None: ...

class Delivery(_message.Message):
    __slots__ = ("index", "id", "order", "payload", "chain_hash")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    CHAIN_HASH_FIELD_NUMBER: _ClassVar[int]
    index: int
    id: _hostlink_pb2.TxId
    order: int
    payload: bytes
    chain_hash: str
    def __init__(self, index: _Optional[int] = ..., id: _Optional[_Union[_hostlink_pb2.TxId, _Mapping]] = ..., order: _Optional[int] = ..., payload: _Optional[bytes] = ..., chain_hash: _Optional[str] = ...) -> None: ...

class LatencyRequest(_message.Message):
    __slots__ = ("reset",)
    RESET_FIELD_NUMBER: _ClassVar[int]
    reset: bool
    def __init__(self, reset: _Optional[bool] = ...) -> None: ...

class LatencyReply(_message.Message):
    __slots__ = ("decide_to_deliver", "propose_to_decide")
    DECIDE_TO_DELIVER_FIELD_NUMBER: _ClassVar[int]
    PROPOSE_TO_DECIDE_FIELD_NUMBER: _ClassVar[int]
    decide_to_deliver: _containers.RepeatedScalarFieldContainer[float]
    propose_to_decide: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, decide_to_deliver: _Optional[_Iterable[float]] = ..., propose_to_decide: _Optional[_Iterable[float]] = ...) -> None: ...

class DdbWriteRequest(_message.Message):
    __slots__ = ("ops", "atomic")
    OPS_FIELD_NUMBER: _ClassVar[int]
    ATOMIC_FIELD_NUMBER: _ClassVar[int]
    ops: _containers.RepeatedCompositeFieldContainer[_ddb_pb2.DdbOp]
    atomic: bool
    def __init__(self, ops: _Optional[_Iterable[_Union[_ddb_pb2.DdbOp, _Mapping]]] = ..., atomic: _Optional[bool] = ...) -> None: ...

class DdbOpResult(_message.Message):
    __slots__ = ("op", "key", "ok", "reason", "version")
    OP_FIELD_NUMBER: _ClassVar[int]
    KEY_FIELD_NUMBER: _ClassVar[int]
    OK_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    op: str
    key: str
    ok: bool
    reason: str
    version: int
    def __init__(self, op: _Optional[str] = ..., key: _Optional[str] = ..., ok: _Optional[bool] = ..., reason: _Optional[str] = ..., version: _Optional[int] = ...) -> None: ...

class DdbWriteReply(_message.Message):
    __slots__ = ("committed", "reason", "id", "global_seq", "ddb_seq", "results")
    COMMITTED_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_SEQ_FIELD_NUMBER: _ClassVar[int]
    DDB_SEQ_FIELD_NUMBER: _ClassVar[int]
    RESULTS_FIELD_NUMBER: _ClassVar[int]
    committed: bool
    reason: str
    id: _hostlink_pb2.TxId
    global_seq: int
    ddb_seq: int
    results: _containers.RepeatedCompositeFieldContainer[DdbOpResult]
    def __init__(self, committed: _Optional[bool] = ..., reason: _Optional[str] = ..., id: _Optional[_Union[_hostlink_pb2.TxId, _Mapping]] = ..., global_seq: _Optional[int] = ..., ddb_seq: _Optional[int] = ..., results: _Optional[_Iterable[_Union[DdbOpResult, _Mapping]]] = ...) -> None: ...

class DdbGetRequest(_message.Message):
    __slots__ = ("keys", "prefix", "keys_only", "limit")
    KEYS_FIELD_NUMBER: _ClassVar[int]
    PREFIX_FIELD_NUMBER: _ClassVar[int]
    KEYS_ONLY_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    keys: _containers.RepeatedScalarFieldContainer[str]
    prefix: str
    keys_only: bool
    limit: int
    def __init__(self, keys: _Optional[_Iterable[str]] = ..., prefix: _Optional[str] = ..., keys_only: _Optional[bool] = ..., limit: _Optional[int] = ...) -> None: ...

class DdbGetReply(_message.Message):
    __slots__ = ("objects", "ddb_seq", "ddb_hash", "truncated")
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    DDB_SEQ_FIELD_NUMBER: _ClassVar[int]
    DDB_HASH_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    objects: _containers.RepeatedCompositeFieldContainer[_ddb_pb2.DdbObjectRecord]
    ddb_seq: int
    ddb_hash: str
    truncated: bool
    def __init__(self, objects: _Optional[_Iterable[_Union[_ddb_pb2.DdbObjectRecord, _Mapping]]] = ..., ddb_seq: _Optional[int] = ..., ddb_hash: _Optional[str] = ..., truncated: _Optional[bool] = ...) -> None: ...

class MirrorRequest(_message.Message):
    __slots__ = ("views",)
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    views: bool
    def __init__(self, views: _Optional[bool] = ...) -> None: ...

class MirrorBatch(_message.Message):
    __slots__ = ("ddb_seq", "payload", "global_seq")
    DDB_SEQ_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_SEQ_FIELD_NUMBER: _ClassVar[int]
    ddb_seq: int
    payload: bytes
    global_seq: int
    def __init__(self, ddb_seq: _Optional[int] = ..., payload: _Optional[bytes] = ..., global_seq: _Optional[int] = ...) -> None: ...

class ViewEvent(_message.Message):
    __slots__ = ("view", "global_seq", "members", "removed", "added", "leader")
    VIEW_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_SEQ_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    ADDED_FIELD_NUMBER: _ClassVar[int]
    LEADER_FIELD_NUMBER: _ClassVar[int]
    view: int
    global_seq: int
    members: _containers.RepeatedCompositeFieldContainer[MemberInfo]
    removed: _containers.RepeatedScalarFieldContainer[str]
    added: _containers.RepeatedScalarFieldContainer[str]
    leader: str
    def __init__(self, view: _Optional[int] = ..., global_seq: _Optional[int] = ..., members: _Optional[_Iterable[_Union[MemberInfo, _Mapping]]] = ..., removed: _Optional[_Iterable[str]] = ..., added: _Optional[_Iterable[str]] = ..., leader: _Optional[str] = ...) -> None: ...

class MirrorEvent(_message.Message):
    __slots__ = ("snapshot", "batch", "view", "ddb_hash")
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    BATCH_FIELD_NUMBER: _ClassVar[int]
    VIEW_FIELD_NUMBER: _ClassVar[int]
    DDB_HASH_FIELD_NUMBER: _ClassVar[int]
    snapshot: _ddb_pb2.DdbSnapshot
    batch: MirrorBatch
    view: ViewEvent
    ddb_hash: str
    def __init__(self, snapshot: _Optional[_Union[_ddb_pb2.DdbSnapshot, _Mapping]] = ..., batch: _Optional[_Union[MirrorBatch, _Mapping]] = ..., view: _Optional[_Union[ViewEvent, _Mapping]] = ..., ddb_hash: _Optional[str] = ...) -> None: ...

class LeaveRequest(_message.Message):
    __slots__ = ("exit",)
    EXIT_FIELD_NUMBER: _ClassVar[int]
    exit: bool
    def __init__(self, exit: _Optional[bool] = ...) -> None: ...

class LeaveReply(_message.Message):
    __slots__ = ("left", "reason")
    LEFT_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    left: bool
    reason: str
    def __init__(self, left: _Optional[bool] = ..., reason: _Optional[str] = ...) -> None: ...

class AgentListRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class AgentInfo(_message.Message):
    __slots__ = ("id", "name", "type", "parent", "status", "owner", "alloc", "epoch", "life", "cpu", "local_phase", "local_cpu", "pid", "has_backup", "queued", "dropped", "recovery", "fail_reason", "failures", "msgs_in", "msgs_out", "bytes_in", "bytes_out", "waiting")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    PARENT_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    OWNER_FIELD_NUMBER: _ClassVar[int]
    ALLOC_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    LIFE_FIELD_NUMBER: _ClassVar[int]
    CPU_FIELD_NUMBER: _ClassVar[int]
    LOCAL_PHASE_FIELD_NUMBER: _ClassVar[int]
    LOCAL_CPU_FIELD_NUMBER: _ClassVar[int]
    PID_FIELD_NUMBER: _ClassVar[int]
    HAS_BACKUP_FIELD_NUMBER: _ClassVar[int]
    QUEUED_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    RECOVERY_FIELD_NUMBER: _ClassVar[int]
    FAIL_REASON_FIELD_NUMBER: _ClassVar[int]
    FAILURES_FIELD_NUMBER: _ClassVar[int]
    MSGS_IN_FIELD_NUMBER: _ClassVar[int]
    MSGS_OUT_FIELD_NUMBER: _ClassVar[int]
    BYTES_IN_FIELD_NUMBER: _ClassVar[int]
    BYTES_OUT_FIELD_NUMBER: _ClassVar[int]
    WAITING_FIELD_NUMBER: _ClassVar[int]
    id: str
    name: str
    type: str
    parent: str
    status: str
    owner: str
    alloc: str
    epoch: int
    life: int
    cpu: float
    local_phase: str
    local_cpu: float
    pid: int
    has_backup: bool
    queued: int
    dropped: int
    recovery: str
    fail_reason: str
    failures: int
    msgs_in: int
    msgs_out: int
    bytes_in: int
    bytes_out: int
    waiting: str
    def __init__(self, id: _Optional[str] = ..., name: _Optional[str] = ..., type: _Optional[str] = ..., parent: _Optional[str] = ..., status: _Optional[str] = ..., owner: _Optional[str] = ..., alloc: _Optional[str] = ..., epoch: _Optional[int] = ..., life: _Optional[int] = ..., cpu: _Optional[float] = ..., local_phase: _Optional[str] = ..., local_cpu: _Optional[float] = ..., pid: _Optional[int] = ..., has_backup: _Optional[bool] = ..., queued: _Optional[int] = ..., dropped: _Optional[int] = ..., recovery: _Optional[str] = ..., fail_reason: _Optional[str] = ..., failures: _Optional[int] = ..., msgs_in: _Optional[int] = ..., msgs_out: _Optional[int] = ..., bytes_in: _Optional[int] = ..., bytes_out: _Optional[int] = ..., waiting: _Optional[str] = ...) -> None: ...

class AgentListReply(_message.Message):
    __slots__ = ("host", "agents", "session", "finished_session", "paused", "agent_types")
    HOST_FIELD_NUMBER: _ClassVar[int]
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    SESSION_FIELD_NUMBER: _ClassVar[int]
    FINISHED_SESSION_FIELD_NUMBER: _ClassVar[int]
    PAUSED_FIELD_NUMBER: _ClassVar[int]
    AGENT_TYPES_FIELD_NUMBER: _ClassVar[int]
    host: str
    agents: _containers.RepeatedCompositeFieldContainer[AgentInfo]
    session: int
    finished_session: int
    paused: bool
    agent_types: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, host: _Optional[str] = ..., agents: _Optional[_Iterable[_Union[AgentInfo, _Mapping]]] = ..., session: _Optional[int] = ..., finished_session: _Optional[int] = ..., paused: _Optional[bool] = ..., agent_types: _Optional[_Iterable[str]] = ...) -> None: ...

class AgentSpawnRequest(_message.Message):
    __slots__ = ("type", "config", "parent", "cost", "hardware", "transfer_penalty", "recovery")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    PARENT_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_FIELD_NUMBER: _ClassVar[int]
    TRANSFER_PENALTY_FIELD_NUMBER: _ClassVar[int]
    RECOVERY_FIELD_NUMBER: _ClassVar[int]
    type: str
    config: bytes
    parent: str
    cost: float
    hardware: _containers.RepeatedScalarFieldContainer[str]
    transfer_penalty: float
    recovery: str
    def __init__(self, type: _Optional[str] = ..., config: _Optional[bytes] = ..., parent: _Optional[str] = ..., cost: _Optional[float] = ..., hardware: _Optional[_Iterable[str]] = ..., transfer_penalty: _Optional[float] = ..., recovery: _Optional[str] = ...) -> None: ...

class AgentRef(_message.Message):
    __slots__ = ("ref",)
    REF_FIELD_NUMBER: _ClassVar[int]
    ref: str
    def __init__(self, ref: _Optional[str] = ...) -> None: ...

class AgentMoveRequest(_message.Message):
    __slots__ = ("ref", "host")
    REF_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    ref: str
    host: str
    def __init__(self, ref: _Optional[str] = ..., host: _Optional[str] = ...) -> None: ...

class AgentOpReply(_message.Message):
    __slots__ = ("ok", "id", "name", "reason", "owner")
    OK_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    OWNER_FIELD_NUMBER: _ClassVar[int]
    ok: bool
    id: str
    name: str
    reason: str
    owner: str
    def __init__(self, ok: _Optional[bool] = ..., id: _Optional[str] = ..., name: _Optional[str] = ..., reason: _Optional[str] = ..., owner: _Optional[str] = ...) -> None: ...

class AllocRequest(_message.Message):
    __slots__ = ("action",)
    ACTION_FIELD_NUMBER: _ClassVar[int]
    action: str
    def __init__(self, action: _Optional[str] = ...) -> None: ...

class AgentEventsRequest(_message.Message):
    __slots__ = ("history",)
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    history: bool
    def __init__(self, history: _Optional[bool] = ...) -> None: ...

class AgentEvent(_message.Message):
    __slots__ = ("time", "agent", "name", "event", "host", "detail")
    TIME_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    EVENT_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    time: float
    agent: str
    name: str
    event: str
    host: str
    detail: str
    def __init__(self, time: _Optional[float] = ..., agent: _Optional[str] = ..., name: _Optional[str] = ..., event: _Optional[str] = ..., host: _Optional[str] = ..., detail: _Optional[str] = ...) -> None: ...

class AgentSendRequest(_message.Message):
    __slots__ = ("ref", "payload", "timeout")
    REF_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    TIMEOUT_FIELD_NUMBER: _ClassVar[int]
    ref: str
    payload: bytes
    timeout: float
    def __init__(self, ref: _Optional[str] = ..., payload: _Optional[bytes] = ..., timeout: _Optional[float] = ...) -> None: ...

class AgentRequestReply(_message.Message):
    __slots__ = ("ok", "payload", "error")
    OK_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    ok: bool
    payload: bytes
    error: str
    def __init__(self, ok: _Optional[bool] = ..., payload: _Optional[bytes] = ..., error: _Optional[str] = ...) -> None: ...

class DdbLoadRequest(_message.Message):
    __slots__ = ("writers", "seconds", "value_bytes", "prefix", "start_at")
    WRITERS_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    VALUE_BYTES_FIELD_NUMBER: _ClassVar[int]
    PREFIX_FIELD_NUMBER: _ClassVar[int]
    START_AT_FIELD_NUMBER: _ClassVar[int]
    writers: int
    seconds: float
    value_bytes: int
    prefix: str
    start_at: float
    def __init__(self, writers: _Optional[int] = ..., seconds: _Optional[float] = ..., value_bytes: _Optional[int] = ..., prefix: _Optional[str] = ..., start_at: _Optional[float] = ...) -> None: ...

class DdbLoadReply(_message.Message):
    __slots__ = ("committed", "failed", "latencies", "elapsed", "global_applied")
    COMMITTED_FIELD_NUMBER: _ClassVar[int]
    FAILED_FIELD_NUMBER: _ClassVar[int]
    LATENCIES_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_FIELD_NUMBER: _ClassVar[int]
    GLOBAL_APPLIED_FIELD_NUMBER: _ClassVar[int]
    committed: int
    failed: int
    latencies: _containers.RepeatedScalarFieldContainer[float]
    elapsed: float
    global_applied: int
    def __init__(self, committed: _Optional[int] = ..., failed: _Optional[int] = ..., latencies: _Optional[_Iterable[float]] = ..., elapsed: _Optional[float] = ..., global_applied: _Optional[int] = ...) -> None: ...
