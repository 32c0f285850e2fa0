from haa.pb import ddb_pb2 as _ddb_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class AgentMsg(_message.Message):
    __slots__ = ("src", "dst", "payload", "conv", "reply", "error")
    SRC_FIELD_NUMBER: _ClassVar[int]
    DST_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    CONV_FIELD_NUMBER: _ClassVar[int]
    REPLY_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    src: str
    dst: str
    payload: bytes
    conv: int
    reply: bool
    error: str
    def __init__(self, src: _Optional[str] = ..., dst: _Optional[str] = ..., payload: _Optional[bytes] = ..., conv: _Optional[int] = ..., reply: _Optional[bool] = ..., error: _Optional[str] = ...) -> None: ...

class HostToAgent(_message.Message):
    __slots__ = ("init", "start", "thaw", "recover", "resume", "deliver", "freeze", "stop", "answer", "watch_event")
    class Init(_message.Message):
        __slots__ = ("agent_id", "name", "type_name", "config", "epoch", "parent", "host", "heartbeat_period", "max_frame")
        AGENT_ID_FIELD_NUMBER: _ClassVar[int]
        NAME_FIELD_NUMBER: _ClassVar[int]
        TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
        CONFIG_FIELD_NUMBER: _ClassVar[int]
        EPOCH_FIELD_NUMBER: _ClassVar[int]
        PARENT_FIELD_NUMBER: _ClassVar[int]
        HOST_FIELD_NUMBER: _ClassVar[int]
        HEARTBEAT_PERIOD_FIELD_NUMBER: _ClassVar[int]
        MAX_FRAME_FIELD_NUMBER: _ClassVar[int]
        agent_id: str
        name: str
        type_name: str
        config: bytes
        epoch: int
        parent: str
        host: str
        heartbeat_period: float
        max_frame: int
        def __init__(self, agent_id: _Optional[str] = ..., name: _Optional[str] = ..., type_name: _Optional[str] = ..., config: _Optional[bytes] = ..., epoch: _Optional[int] = ..., parent: _Optional[str] = ..., host: _Optional[str] = ..., heartbeat_period: _Optional[float] = ..., max_frame: _Optional[int] = ...) -> None: ...
    class Start(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Thaw(_message.Message):
        __slots__ = ("state",)
        STATE_FIELD_NUMBER: _ClassVar[int]
        state: bytes
        def __init__(self, state: _Optional[bytes] = ...) -> None: ...
    class Recover(_message.Message):
        __slots__ = ("has_backup", "backup")
        HAS_BACKUP_FIELD_NUMBER: _ClassVar[int]
        BACKUP_FIELD_NUMBER: _ClassVar[int]
        has_backup: bool
        backup: bytes
        def __init__(self, has_backup: _Optional[bool] = ..., backup: _Optional[bytes] = ...) -> None: ...
    class Resume(_message.Message):
        __slots__ = ("how",)
        HOW_FIELD_NUMBER: _ClassVar[int]
        how: str
        def __init__(self, how: _Optional[str] = ...) -> None: ...
    class Freeze(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Stop(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Answer(_message.Message):
        __slots__ = ("req_id", "ok", "value", "error", "missing", "op_errors", "keys", "values", "truncated")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        OK_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        ERROR_FIELD_NUMBER: _ClassVar[int]
        MISSING_FIELD_NUMBER: _ClassVar[int]
        OP_ERRORS_FIELD_NUMBER: _ClassVar[int]
        KEYS_FIELD_NUMBER: _ClassVar[int]
        VALUES_FIELD_NUMBER: _ClassVar[int]
        TRUNCATED_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        ok: bool
        value: bytes
        error: str
        missing: bool
        op_errors: _containers.RepeatedScalarFieldContainer[str]
        keys: _containers.RepeatedScalarFieldContainer[str]
        values: _containers.RepeatedScalarFieldContainer[bytes]
        truncated: bool
        def __init__(self, req_id: _Optional[int] = ..., ok: _Optional[bool] = ..., value: _Optional[bytes] = ..., error: _Optional[str] = ..., missing: _Optional[bool] = ..., op_errors: _Optional[_Iterable[str]] = ..., keys: _Optional[_Iterable[str]] = ..., values: _Optional[_Iterable[bytes]] = ..., truncated: _Optional[bool] = ...) -> None: ...
    class WatchEvent(_message.Message):
        __slots__ = ("watch_id", "event", "key", "has_value", "value", "index")
        WATCH_ID_FIELD_NUMBER: _ClassVar[int]
        EVENT_FIELD_NUMBER: _ClassVar[int]
        KEY_FIELD_NUMBER: _ClassVar[int]
        HAS_VALUE_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        INDEX_FIELD_NUMBER: _ClassVar[int]
        watch_id: int
        event: str
        key: str
        has_value: bool
        value: bytes
        index: int
        def __init__(self, watch_id: _Optional[int] = ..., event: _Optional[str] = ..., key: _Optional[str] = ..., has_value: _Optional[bool] = ..., value: _Optional[bytes] = ..., index: _Optional[int] = ...) -> None: ...
    INIT_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    THAW_FIELD_NUMBER: _ClassVar[int]
    RECOVER_FIELD_NUMBER: _ClassVar[int]
    RESUME_FIELD_NUMBER: _ClassVar[int]
    DELIVER_FIELD_NUMBER: _ClassVar[int]
    FREEZE_FIELD_NUMBER: _ClassVar[int]
    STOP_FIELD_NUMBER: _ClassVar[int]
    ANSWER_FIELD_NUMBER: _ClassVar[int]
    WATCH_EVENT_FIELD_NUMBER: _ClassVar[int]
    init: HostToAgent.Init
    start: HostToAgent.Start
    thaw: HostToAgent.Thaw
    recover: HostToAgent.Recover
    resume: HostToAgent.Resume
    deliver: AgentMsg
    freeze: HostToAgent.Freeze
    stop: HostToAgent.Stop
    answer: HostToAgent.Answer
    watch_event: HostToAgent.WatchEvent
    def __init__(self, init: _Optional[_Union[HostToAgent.Init, _Mapping]] = ..., start: _Optional[_Union[HostToAgent.Start, _Mapping]] = ..., thaw: _Optional[_Union[HostToAgent.Thaw, _Mapping]] = ..., recover: _Optional[_Union[HostToAgent.Recover, _Mapping]] = ..., resume: _Optional[_Union[HostToAgent.Resume, _Mapping]] = ..., deliver: _Optional[_Union[AgentMsg, _Mapping]] = ..., freeze: _Optional[_Union[HostToAgent.Freeze, _Mapping]] = ..., stop: _Optional[_Union[HostToAgent.Stop, _Mapping]] = ..., answer: _Optional[_Union[HostToAgent.Answer, _Mapping]] = ..., watch_event: _Optional[_Union[HostToAgent.WatchEvent, _Mapping]] = ...) -> None: ...

class AgentToHost(_message.Message):
    __slots__ = ("hello", "ready", "heartbeat", "sent", "backup", "frozen", "spawn_child", "ddb_get", "ddb_put", "ddb_watch", "ddb_unwatch", "log", "stopped", "error", "ddb_write", "ddb_scan")
    class Hello(_message.Message):
        __slots__ = ("pid", "type_name")
        PID_FIELD_NUMBER: _ClassVar[int]
        TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
        pid: int
        type_name: str
        def __init__(self, pid: _Optional[int] = ..., type_name: _Optional[str] = ...) -> None: ...
    class Ready(_message.Message):
        __slots__ = ("how",)
        HOW_FIELD_NUMBER: _ClassVar[int]
        how: str
        def __init__(self, how: _Optional[str] = ...) -> None: ...
    class Heartbeat(_message.Message):
        __slots__ = ("queued", "handled")
        QUEUED_FIELD_NUMBER: _ClassVar[int]
        HANDLED_FIELD_NUMBER: _ClassVar[int]
        queued: int
        handled: int
        def __init__(self, queued: _Optional[int] = ..., handled: _Optional[int] = ...) -> None: ...
    class Backup(_message.Message):
        __slots__ = ("data",)
        DATA_FIELD_NUMBER: _ClassVar[int]
        data: bytes
        def __init__(self, data: _Optional[bytes] = ...) -> None: ...
    class Frozen(_message.Message):
        __slots__ = ("state",)
        STATE_FIELD_NUMBER: _ClassVar[int]
        state: bytes
        def __init__(self, state: _Optional[bytes] = ...) -> None: ...
    class SpawnChild(_message.Message):
        __slots__ = ("req_id", "type_name", "config", "key")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
        CONFIG_FIELD_NUMBER: _ClassVar[int]
        KEY_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        type_name: str
        config: bytes
        key: str
        def __init__(self, req_id: _Optional[int] = ..., type_name: _Optional[str] = ..., config: _Optional[bytes] = ..., key: _Optional[str] = ...) -> None: ...
    class DdbGet(_message.Message):
        __slots__ = ("req_id", "key")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        KEY_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        key: str
        def __init__(self, req_id: _Optional[int] = ..., key: _Optional[str] = ...) -> None: ...
    class DdbScan(_message.Message):
        __slots__ = ("req_id", "prefix", "limit")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        PREFIX_FIELD_NUMBER: _ClassVar[int]
        LIMIT_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        prefix: str
        limit: int
        def __init__(self, req_id: _Optional[int] = ..., prefix: _Optional[str] = ..., limit: _Optional[int] = ...) -> None: ...
    class DdbPut(_message.Message):
        __slots__ = ("req_id", "key", "value", "type_name")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        key: str
        value: bytes
        type_name: str
        def __init__(self, req_id: _Optional[int] = ..., key: _Optional[str] = ..., value: _Optional[bytes] = ..., type_name: _Optional[str] = ...) -> None: ...
    class DdbWrite(_message.Message):
        __slots__ = ("req_id", "ops", "atomic")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        OPS_FIELD_NUMBER: _ClassVar[int]
        ATOMIC_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        ops: _containers.RepeatedCompositeFieldContainer[_ddb_pb2.DdbOp]
        atomic: bool
        def __init__(self, req_id: _Optional[int] = ..., ops: _Optional[_Iterable[_Union[_ddb_pb2.DdbOp, _Mapping]]] = ..., atomic: _Optional[bool] = ...) -> None: ...
    class DdbWatch(_message.Message):
        __slots__ = ("watch_id", "prefix")
        WATCH_ID_FIELD_NUMBER: _ClassVar[int]
        PREFIX_FIELD_NUMBER: _ClassVar[int]
        watch_id: int
        prefix: str
        def __init__(self, watch_id: _Optional[int] = ..., prefix: _Optional[str] = ...) -> None: ...
    class DdbUnwatch(_message.Message):
        __slots__ = ("watch_id",)
        WATCH_ID_FIELD_NUMBER: _ClassVar[int]
        watch_id: int
        def __init__(self, watch_id: _Optional[int] = ...) -> None: ...
    class Log(_message.Message):
        __slots__ = ("level", "event", "fields_json")
        LEVEL_FIELD_NUMBER: _ClassVar[int]
        EVENT_FIELD_NUMBER: _ClassVar[int]
        FIELDS_JSON_FIELD_NUMBER: _ClassVar[int]
        level: str
        event: str
        fields_json: str
        def __init__(self, level: _Optional[str] = ..., event: _Optional[str] = ..., fields_json: _Optional[str] = ...) -> None: ...
    class Stopped(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Error(_message.Message):
        __slots__ = ("message",)
        MESSAGE_FIELD_NUMBER: _ClassVar[int]
        message: str
        def __init__(self, message: _Optional[str] = ...) -> None: ...
    HELLO_FIELD_NUMBER: _ClassVar[int]
    READY_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_FIELD_NUMBER: _ClassVar[int]
    SENT_FIELD_NUMBER: _ClassVar[int]
    BACKUP_FIELD_NUMBER: _ClassVar[int]
    FROZEN_FIELD_NUMBER: _ClassVar[int]
    SPAWN_CHILD_FIELD_NUMBER: _ClassVar[int]
    DDB_GET_FIELD_NUMBER: _ClassVar[int]
    DDB_PUT_FIELD_NUMBER: _ClassVar[int]
    DDB_WATCH_FIELD_NUMBER: _ClassVar[int]
    DDB_UNWATCH_FIELD_NUMBER: _ClassVar[int]
    LOG_FIELD_NUMBER: _ClassVar[int]
    STOPPED_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    DDB_WRITE_FIELD_NUMBER: _ClassVar[int]
    DDB_SCAN_FIELD_NUMBER: _ClassVar[int]
    hello: AgentToHost.Hello
    ready: AgentToHost.Ready
    heartbeat: AgentToHost.Heartbeat
    sent: AgentMsg
    backup: AgentToHost.Backup
    frozen: AgentToHost.Frozen
    spawn_child: AgentToHost.SpawnChild
    ddb_get: AgentToHost.DdbGet
    ddb_put: AgentToHost.DdbPut
    ddb_watch: AgentToHost.DdbWatch
    ddb_unwatch: AgentToHost.DdbUnwatch
    log: AgentToHost.Log
    stopped: AgentToHost.Stopped
    error: AgentToHost.Error
    ddb_write: AgentToHost.DdbWrite
    ddb_scan: AgentToHost.DdbScan
    def __init__(self, hello: _Optional[_Union[AgentToHost.Hello, _Mapping]] = ..., ready: _Optional[_Union[AgentToHost.Ready, _Mapping]] = ..., heartbeat: _Optional[_Union[AgentToHost.Heartbeat, _Mapping]] = ..., sent: _Optional[_Union[AgentMsg, _Mapping]] = ..., backup: _Optional[_Union[AgentToHost.Backup, _Mapping]] = ..., frozen: _Optional[_Union[AgentToHost.Frozen, _Mapping]] = ..., spawn_child: _Optional[_Union[AgentToHost.SpawnChild, _Mapping]] = ..., ddb_get: _Optional[_Union[AgentToHost.DdbGet, _Mapping]] = ..., ddb_put: _Optional[_Union[AgentToHost.DdbPut, _Mapping]] = ..., ddb_watch: _Optional[_Union[AgentToHost.DdbWatch, _Mapping]] = ..., ddb_unwatch: _Optional[_Union[AgentToHost.DdbUnwatch, _Mapping]] = ..., log: _Optional[_Union[AgentToHost.Log, _Mapping]] = ..., stopped: _Optional[_Union[AgentToHost.Stopped, _Mapping]] = ..., error: _Optional[_Union[AgentToHost.Error, _Mapping]] = ..., ddb_write: _Optional[_Union[AgentToHost.DdbWrite, _Mapping]] = ..., ddb_scan: _Optional[_Union[AgentToHost.DdbScan, _Mapping]] = ...) -> None: ...

class ForkServerRequest(_message.Message):
    __slots__ = ("req_id", "type_name", "agent_id", "log_path", "exec", "validate", "config_size", "describe")
    REQ_ID_FIELD_NUMBER: _ClassVar[int]
    TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    LOG_PATH_FIELD_NUMBER: _ClassVar[int]
    EXEC_FIELD_NUMBER: _ClassVar[int]
    VALIDATE_FIELD_NUMBER: _ClassVar[int]
    CONFIG_SIZE_FIELD_NUMBER: _ClassVar[int]
    DESCRIBE_FIELD_NUMBER: _ClassVar[int]
    req_id: int
    type_name: str
    agent_id: str
    log_path: str
    exec: bool
    validate: bool
    config_size: int
    describe: bool
    def __init__(self, req_id: _Optional[int] = ..., type_name: _Optional[str] = ..., agent_id: _Optional[str] = ..., log_path: _Optional[str] = ..., exec: _Optional[bool] = ..., validate: _Optional[bool] = ..., config_size: _Optional[int] = ..., describe: _Optional[bool] = ...) -> None: ...

class AgentTypeInfo(_message.Message):
    __slots__ = ("type_name", "cost", "hardware", "transfer_penalty", "recovery", "module", "has_config", "memory_limit_mb", "cpu_limit", "max_per_host")
    TYPE_NAME_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_FIELD_NUMBER: _ClassVar[int]
    TRANSFER_PENALTY_FIELD_NUMBER: _ClassVar[int]
    RECOVERY_FIELD_NUMBER: _ClassVar[int]
    MODULE_FIELD_NUMBER: _ClassVar[int]
    HAS_CONFIG_FIELD_NUMBER: _ClassVar[int]
    MEMORY_LIMIT_MB_FIELD_NUMBER: _ClassVar[int]
    CPU_LIMIT_FIELD_NUMBER: _ClassVar[int]
    MAX_PER_HOST_FIELD_NUMBER: _ClassVar[int]
    type_name: str
    cost: float
    hardware: _containers.RepeatedScalarFieldContainer[str]
    transfer_penalty: float
    recovery: str
    module: str
    has_config: bool
    memory_limit_mb: int
    cpu_limit: float
    max_per_host: int
    def __init__(self, type_name: _Optional[str] = ..., cost: _Optional[float] = ..., hardware: _Optional[_Iterable[str]] = ..., transfer_penalty: _Optional[float] = ..., recovery: _Optional[str] = ..., module: _Optional[str] = ..., has_config: _Optional[bool] = ..., memory_limit_mb: _Optional[int] = ..., cpu_limit: _Optional[float] = ..., max_per_host: _Optional[int] = ...) -> None: ...

class ForkServerEvent(_message.Message):
    __slots__ = ("ready", "reply", "exit")
    class Ready(_message.Message):
        __slots__ = ("pid", "types", "load_errors", "preload_seconds", "lazy_types")
        PID_FIELD_NUMBER: _ClassVar[int]
        TYPES_FIELD_NUMBER: _ClassVar[int]
        LOAD_ERRORS_FIELD_NUMBER: _ClassVar[int]
        PRELOAD_SECONDS_FIELD_NUMBER: _ClassVar[int]
        LAZY_TYPES_FIELD_NUMBER: _ClassVar[int]
        pid: int
        types: _containers.RepeatedCompositeFieldContainer[AgentTypeInfo]
        load_errors: _containers.RepeatedScalarFieldContainer[str]
        preload_seconds: float
        lazy_types: _containers.RepeatedScalarFieldContainer[str]
        def __init__(self, pid: _Optional[int] = ..., types: _Optional[_Iterable[_Union[AgentTypeInfo, _Mapping]]] = ..., load_errors: _Optional[_Iterable[str]] = ..., preload_seconds: _Optional[float] = ..., lazy_types: _Optional[_Iterable[str]] = ...) -> None: ...
    class Reply(_message.Message):
        __slots__ = ("req_id", "pid", "error", "config_error", "info")
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        PID_FIELD_NUMBER: _ClassVar[int]
        ERROR_FIELD_NUMBER: _ClassVar[int]
        CONFIG_ERROR_FIELD_NUMBER: _ClassVar[int]
        INFO_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        pid: int
        error: str
        config_error: str
        info: AgentTypeInfo
        def __init__(self, req_id: _Optional[int] = ..., pid: _Optional[int] = ..., error: _Optional[str] = ..., config_error: _Optional[str] = ..., info: _Optional[_Union[AgentTypeInfo, _Mapping]] = ...) -> None: ...
    class ChildExit(_message.Message):
        __slots__ = ("pid", "exit_code", "signal")
        PID_FIELD_NUMBER: _ClassVar[int]
        EXIT_CODE_FIELD_NUMBER: _ClassVar[int]
        SIGNAL_FIELD_NUMBER: _ClassVar[int]
        pid: int
        exit_code: int
        signal: int
        def __init__(self, pid: _Optional[int] = ..., exit_code: _Optional[int] = ..., signal: _Optional[int] = ...) -> None: ...
    READY_FIELD_NUMBER: _ClassVar[int]
    REPLY_FIELD_NUMBER: _ClassVar[int]
    EXIT_FIELD_NUMBER: _ClassVar[int]
    ready: ForkServerEvent.Ready
    reply: ForkServerEvent.Reply
    exit: ForkServerEvent.ChildExit
    def __init__(self, ready: _Optional[_Union[ForkServerEvent.Ready, _Mapping]] = ..., reply: _Optional[_Union[ForkServerEvent.Reply, _Mapping]] = ..., exit: _Optional[_Union[ForkServerEvent.ChildExit, _Mapping]] = ...) -> None: ...
