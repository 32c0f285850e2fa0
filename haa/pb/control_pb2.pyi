from haa.pb import hostlink_pb2 as _hostlink_pb2
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
    __slots__ = ("name", "incarnation", "peers", "active_transactions", "decided_transactions", "delivered", "delivered_hash", "counters", "cpu_percent", "rss_bytes", "uptime")
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
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., peers: _Optional[_Iterable[_Union[PeerStatus, _Mapping]]] = ..., active_transactions: _Optional[int] = ..., decided_transactions: _Optional[int] = ..., delivered: _Optional[int] = ..., delivered_hash: _Optional[str] = ..., counters: _Optional[_Union[Counters, _Mapping]] = ..., cpu_percent: _Optional[float] = ..., rss_bytes: _Optional[int] = ..., uptime: _Optional[float] = ...) -> None: ...

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
