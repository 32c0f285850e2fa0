from haa.pb import agent_pb2 as _agent_pb2
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PlaybackInstance(_message.Message):
    __slots__ = ("init", "instance", "segment", "first_input", "first_output", "wall_start_ns", "format")
    INIT_FIELD_NUMBER: _ClassVar[int]
    INSTANCE_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_FIELD_NUMBER: _ClassVar[int]
    FIRST_INPUT_FIELD_NUMBER: _ClassVar[int]
    FIRST_OUTPUT_FIELD_NUMBER: _ClassVar[int]
    WALL_START_NS_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    init: _agent_pb2.HostToAgent.Init
    instance: str
    segment: int
    first_input: int
    first_output: int
    wall_start_ns: int
    format: str
    def __init__(self, init: _Optional[_Union[_agent_pb2.HostToAgent.Init, _Mapping]] = ..., instance: _Optional[str] = ..., segment: _Optional[int] = ..., first_input: _Optional[int] = ..., first_output: _Optional[int] = ..., wall_start_ns: _Optional[int] = ..., format: _Optional[str] = ...) -> None: ...

class PlaybackInput(_message.Message):
    __slots__ = ("seq", "wall_ns", "begin", "message", "timer", "watch", "log_item", "resume", "freeze", "stop", "answer", "reply", "request_timeout", "call_timeout", "clock", "random", "random_bits", "external", "perf_counter", "thread_done", "freeze_fed")
    class Begin(_message.Message):
        __slots__ = ("how", "has_blob", "blob")
        HOW_FIELD_NUMBER: _ClassVar[int]
        HAS_BLOB_FIELD_NUMBER: _ClassVar[int]
        BLOB_FIELD_NUMBER: _ClassVar[int]
        how: str
        has_blob: bool
        blob: bytes
        def __init__(self, how: _Optional[str] = ..., has_blob: _Optional[bool] = ..., blob: _Optional[bytes] = ...) -> None: ...
    class TimerFired(_message.Message):
        __slots__ = ("timer_id",)
        TIMER_ID_FIELD_NUMBER: _ClassVar[int]
        timer_id: int
        def __init__(self, timer_id: _Optional[int] = ...) -> None: ...
    class RequestTimeout(_message.Message):
        __slots__ = ("conv",)
        CONV_FIELD_NUMBER: _ClassVar[int]
        conv: int
        def __init__(self, conv: _Optional[int] = ...) -> None: ...
    class CallTimeout(_message.Message):
        __slots__ = ("req_id",)
        REQ_ID_FIELD_NUMBER: _ClassVar[int]
        req_id: int
        def __init__(self, req_id: _Optional[int] = ...) -> None: ...
    class RandomBits(_message.Message):
        __slots__ = ("k", "value")
        K_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        k: int
        value: bytes
        def __init__(self, k: _Optional[int] = ..., value: _Optional[bytes] = ...) -> None: ...
    class External(_message.Message):
        __slots__ = ("source", "method", "call", "payload", "end", "code", "details")
        SOURCE_FIELD_NUMBER: _ClassVar[int]
        METHOD_FIELD_NUMBER: _ClassVar[int]
        CALL_FIELD_NUMBER: _ClassVar[int]
        PAYLOAD_FIELD_NUMBER: _ClassVar[int]
        END_FIELD_NUMBER: _ClassVar[int]
        CODE_FIELD_NUMBER: _ClassVar[int]
        DETAILS_FIELD_NUMBER: _ClassVar[int]
        source: str
        method: str
        call: int
        payload: bytes
        end: bool
        code: int
        details: str
        def __init__(self, source: _Optional[str] = ..., method: _Optional[str] = ..., call: _Optional[int] = ..., payload: _Optional[bytes] = ..., end: _Optional[bool] = ..., code: _Optional[int] = ..., details: _Optional[str] = ...) -> None: ...
    SEQ_FIELD_NUMBER: _ClassVar[int]
    WALL_NS_FIELD_NUMBER: _ClassVar[int]
    BEGIN_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    TIMER_FIELD_NUMBER: _ClassVar[int]
    WATCH_FIELD_NUMBER: _ClassVar[int]
    LOG_ITEM_FIELD_NUMBER: _ClassVar[int]
    RESUME_FIELD_NUMBER: _ClassVar[int]
    FREEZE_FIELD_NUMBER: _ClassVar[int]
    STOP_FIELD_NUMBER: _ClassVar[int]
    ANSWER_FIELD_NUMBER: _ClassVar[int]
    REPLY_FIELD_NUMBER: _ClassVar[int]
    REQUEST_TIMEOUT_FIELD_NUMBER: _ClassVar[int]
    CALL_TIMEOUT_FIELD_NUMBER: _ClassVar[int]
    CLOCK_FIELD_NUMBER: _ClassVar[int]
    RANDOM_FIELD_NUMBER: _ClassVar[int]
    RANDOM_BITS_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_FIELD_NUMBER: _ClassVar[int]
    PERF_COUNTER_FIELD_NUMBER: _ClassVar[int]
    THREAD_DONE_FIELD_NUMBER: _ClassVar[int]
    FREEZE_FED_FIELD_NUMBER: _ClassVar[int]
    seq: int
    wall_ns: int
    begin: PlaybackInput.Begin
    message: _agent_pb2.AgentMsg
    timer: PlaybackInput.TimerFired
    watch: _agent_pb2.HostToAgent.WatchEvent
    log_item: _agent_pb2.HostToAgent.WatchEvent
    resume: str
    freeze: bool
    stop: bool
    answer: _agent_pb2.HostToAgent.Answer
    reply: _agent_pb2.AgentMsg
    request_timeout: PlaybackInput.RequestTimeout
    call_timeout: PlaybackInput.CallTimeout
    clock: float
    random: float
    random_bits: PlaybackInput.RandomBits
    external: PlaybackInput.External
    perf_counter: float
    thread_done: int
    freeze_fed: bool
    def __init__(self, seq: _Optional[int] = ..., wall_ns: _Optional[int] = ..., begin: _Optional[_Union[PlaybackInput.Begin, _Mapping]] = ..., message: _Optional[_Union[_agent_pb2.AgentMsg, _Mapping]] = ..., timer: _Optional[_Union[PlaybackInput.TimerFired, _Mapping]] = ..., watch: _Optional[_Union[_agent_pb2.HostToAgent.WatchEvent, _Mapping]] = ..., log_item: _Optional[_Union[_agent_pb2.HostToAgent.WatchEvent, _Mapping]] = ..., resume: _Optional[str] = ..., freeze: _Optional[bool] = ..., stop: _Optional[bool] = ..., answer: _Optional[_Union[_agent_pb2.HostToAgent.Answer, _Mapping]] = ..., reply: _Optional[_Union[_agent_pb2.AgentMsg, _Mapping]] = ..., request_timeout: _Optional[_Union[PlaybackInput.RequestTimeout, _Mapping]] = ..., call_timeout: _Optional[_Union[PlaybackInput.CallTimeout, _Mapping]] = ..., clock: _Optional[float] = ..., random: _Optional[float] = ..., random_bits: _Optional[_Union[PlaybackInput.RandomBits, _Mapping]] = ..., external: _Optional[_Union[PlaybackInput.External, _Mapping]] = ..., perf_counter: _Optional[float] = ..., thread_done: _Optional[int] = ..., freeze_fed: _Optional[bool] = ...) -> None: ...

class PlaybackOutput(_message.Message):
    __slots__ = ("seq", "after_input", "wall_ns", "frame", "external_call", "digest")
    class ExternalCall(_message.Message):
        __slots__ = ("source", "method", "call", "request")
        SOURCE_FIELD_NUMBER: _ClassVar[int]
        METHOD_FIELD_NUMBER: _ClassVar[int]
        CALL_FIELD_NUMBER: _ClassVar[int]
        REQUEST_FIELD_NUMBER: _ClassVar[int]
        source: str
        method: str
        call: int
        request: bytes
        def __init__(self, source: _Optional[str] = ..., method: _Optional[str] = ..., call: _Optional[int] = ..., request: _Optional[bytes] = ...) -> None: ...
    class Digest(_message.Message):
        __slots__ = ("sha256", "size", "kind", "dst")
        SHA256_FIELD_NUMBER: _ClassVar[int]
        SIZE_FIELD_NUMBER: _ClassVar[int]
        KIND_FIELD_NUMBER: _ClassVar[int]
        DST_FIELD_NUMBER: _ClassVar[int]
        sha256: bytes
        size: int
        kind: str
        dst: str
        def __init__(self, sha256: _Optional[bytes] = ..., size: _Optional[int] = ..., kind: _Optional[str] = ..., dst: _Optional[str] = ...) -> None: ...
    SEQ_FIELD_NUMBER: _ClassVar[int]
    AFTER_INPUT_FIELD_NUMBER: _ClassVar[int]
    WALL_NS_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_CALL_FIELD_NUMBER: _ClassVar[int]
    DIGEST_FIELD_NUMBER: _ClassVar[int]
    seq: int
    after_input: int
    wall_ns: int
    frame: _agent_pb2.AgentToHost
    external_call: PlaybackOutput.ExternalCall
    digest: PlaybackOutput.Digest
    def __init__(self, seq: _Optional[int] = ..., after_input: _Optional[int] = ..., wall_ns: _Optional[int] = ..., frame: _Optional[_Union[_agent_pb2.AgentToHost, _Mapping]] = ..., external_call: _Optional[_Union[PlaybackOutput.ExternalCall, _Mapping]] = ..., digest: _Optional[_Union[PlaybackOutput.Digest, _Mapping]] = ...) -> None: ...
