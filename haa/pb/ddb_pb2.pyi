from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DdbPut(_message.Message):
    __slots__ = ("key", "type", "value")
    KEY_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    key: str
    type: str
    value: bytes
    def __init__(self, key: _Optional[str] = ..., type: _Optional[str] = ..., value: _Optional[bytes] = ...) -> None: ...

class DdbDelete(_message.Message):
    __slots__ = ("key",)
    KEY_FIELD_NUMBER: _ClassVar[int]
    key: str
    def __init__(self, key: _Optional[str] = ...) -> None: ...

class DdbAppend(_message.Message):
    __slots__ = ("key", "item", "max_len")
    KEY_FIELD_NUMBER: _ClassVar[int]
    ITEM_FIELD_NUMBER: _ClassVar[int]
    MAX_LEN_FIELD_NUMBER: _ClassVar[int]
    key: str
    item: bytes
    max_len: int
    def __init__(self, key: _Optional[str] = ..., item: _Optional[bytes] = ..., max_len: _Optional[int] = ...) -> None: ...

class DdbCas(_message.Message):
    __slots__ = ("key", "expected_version", "type", "value")
    KEY_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_VERSION_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    key: str
    expected_version: int
    type: str
    value: bytes
    def __init__(self, key: _Optional[str] = ..., expected_version: _Optional[int] = ..., type: _Optional[str] = ..., value: _Optional[bytes] = ...) -> None: ...

class DdbAdd(_message.Message):
    __slots__ = ("key", "delta")
    KEY_FIELD_NUMBER: _ClassVar[int]
    DELTA_FIELD_NUMBER: _ClassVar[int]
    key: str
    delta: int
    def __init__(self, key: _Optional[str] = ..., delta: _Optional[int] = ...) -> None: ...

class DdbLogAppend(_message.Message):
    __slots__ = ("key", "items")
    KEY_FIELD_NUMBER: _ClassVar[int]
    ITEMS_FIELD_NUMBER: _ClassVar[int]
    key: str
    items: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, key: _Optional[str] = ..., items: _Optional[_Iterable[bytes]] = ...) -> None: ...

class DdbLogTrim(_message.Message):
    __slots__ = ("key", "upto")
    KEY_FIELD_NUMBER: _ClassVar[int]
    UPTO_FIELD_NUMBER: _ClassVar[int]
    key: str
    upto: int
    def __init__(self, key: _Optional[str] = ..., upto: _Optional[int] = ...) -> None: ...

class DdbOp(_message.Message):
    __slots__ = ("put", "delete", "append", "cas", "add", "log_append", "log_trim")
    PUT_FIELD_NUMBER: _ClassVar[int]
    DELETE_FIELD_NUMBER: _ClassVar[int]
    APPEND_FIELD_NUMBER: _ClassVar[int]
    CAS_FIELD_NUMBER: _ClassVar[int]
    ADD_FIELD_NUMBER: _ClassVar[int]
    LOG_APPEND_FIELD_NUMBER: _ClassVar[int]
    LOG_TRIM_FIELD_NUMBER: _ClassVar[int]
    put: DdbPut
    delete: DdbDelete
    append: DdbAppend
    cas: DdbCas
    add: DdbAdd
    log_append: DdbLogAppend
    log_trim: DdbLogTrim
    def __init__(self, put: _Optional[_Union[DdbPut, _Mapping]] = ..., delete: _Optional[_Union[DdbDelete, _Mapping]] = ..., append: _Optional[_Union[DdbAppend, _Mapping]] = ..., cas: _Optional[_Union[DdbCas, _Mapping]] = ..., add: _Optional[_Union[DdbAdd, _Mapping]] = ..., log_append: _Optional[_Union[DdbLogAppend, _Mapping]] = ..., log_trim: _Optional[_Union[DdbLogTrim, _Mapping]] = ...) -> None: ...

class DdbBatch(_message.Message):
    __slots__ = ("ops", "origin", "client_seq", "atomic")
    OPS_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_FIELD_NUMBER: _ClassVar[int]
    CLIENT_SEQ_FIELD_NUMBER: _ClassVar[int]
    ATOMIC_FIELD_NUMBER: _ClassVar[int]
    ops: _containers.RepeatedCompositeFieldContainer[DdbOp]
    origin: str
    client_seq: int
    atomic: bool
    def __init__(self, ops: _Optional[_Iterable[_Union[DdbOp, _Mapping]]] = ..., origin: _Optional[str] = ..., client_seq: _Optional[int] = ..., atomic: _Optional[bool] = ...) -> None: ...

class DdbListValue(_message.Message):
    __slots__ = ("items",)
    ITEMS_FIELD_NUMBER: _ClassVar[int]
    items: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, items: _Optional[_Iterable[bytes]] = ...) -> None: ...

class DdbLogValue(_message.Message):
    __slots__ = ("first", "items")
    FIRST_FIELD_NUMBER: _ClassVar[int]
    ITEMS_FIELD_NUMBER: _ClassVar[int]
    first: int
    items: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, first: _Optional[int] = ..., items: _Optional[_Iterable[bytes]] = ...) -> None: ...

class DdbObjectRecord(_message.Message):
    __slots__ = ("key", "type", "value", "version", "created")
    KEY_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CREATED_FIELD_NUMBER: _ClassVar[int]
    key: str
    type: str
    value: bytes
    version: int
    created: int
    def __init__(self, key: _Optional[str] = ..., type: _Optional[str] = ..., value: _Optional[bytes] = ..., version: _Optional[int] = ..., created: _Optional[int] = ...) -> None: ...

class DdbSnapshot(_message.Message):
    __slots__ = ("format", "seq", "objects")
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    format: int
    seq: int
    objects: _containers.RepeatedCompositeFieldContainer[DdbObjectRecord]
    def __init__(self, format: _Optional[int] = ..., seq: _Optional[int] = ..., objects: _Optional[_Iterable[_Union[DdbObjectRecord, _Mapping]]] = ...) -> None: ...
