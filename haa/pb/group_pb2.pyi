from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class GroupProc(_message.Message):
    __slots__ = ("name", "incarnation")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ...) -> None: ...

class GroupMember(_message.Message):
    __slots__ = ("name", "incarnation", "addr")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    ADDR_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    addr: str
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., addr: _Optional[str] = ...) -> None: ...

class GroupRemove(_message.Message):
    __slots__ = ("key", "proposer", "removal")
    KEY_FIELD_NUMBER: _ClassVar[int]
    PROPOSER_FIELD_NUMBER: _ClassVar[int]
    REMOVAL_FIELD_NUMBER: _ClassVar[int]
    key: str
    proposer: GroupProc
    removal: _containers.RepeatedCompositeFieldContainer[GroupProc]
    def __init__(self, key: _Optional[str] = ..., proposer: _Optional[_Union[GroupProc, _Mapping]] = ..., removal: _Optional[_Iterable[_Union[GroupProc, _Mapping]]] = ...) -> None: ...

class GroupMembership(_message.Message):
    __slots__ = ("key", "proposer", "members")
    KEY_FIELD_NUMBER: _ClassVar[int]
    PROPOSER_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    key: str
    proposer: GroupProc
    members: _containers.RepeatedCompositeFieldContainer[GroupMember]
    def __init__(self, key: _Optional[str] = ..., proposer: _Optional[_Union[GroupProc, _Mapping]] = ..., members: _Optional[_Iterable[_Union[GroupMember, _Mapping]]] = ...) -> None: ...

class GroupFormation(_message.Message):
    __slots__ = ("proposer", "members")
    PROPOSER_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    proposer: GroupProc
    members: _containers.RepeatedCompositeFieldContainer[GroupMember]
    def __init__(self, proposer: _Optional[_Union[GroupProc, _Mapping]] = ..., members: _Optional[_Iterable[_Union[GroupMember, _Mapping]]] = ...) -> None: ...

class GroupTx(_message.Message):
    __slots__ = ("remove", "membership", "formation", "ddb", "test", "agent", "seq")
    REMOVE_FIELD_NUMBER: _ClassVar[int]
    MEMBERSHIP_FIELD_NUMBER: _ClassVar[int]
    FORMATION_FIELD_NUMBER: _ClassVar[int]
    DDB_FIELD_NUMBER: _ClassVar[int]
    TEST_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    remove: GroupRemove
    membership: GroupMembership
    formation: GroupFormation
    ddb: bytes
    test: bytes
    agent: bytes
    seq: SeqBatch
    def __init__(self, remove: _Optional[_Union[GroupRemove, _Mapping]] = ..., membership: _Optional[_Union[GroupMembership, _Mapping]] = ..., formation: _Optional[_Union[GroupFormation, _Mapping]] = ..., ddb: _Optional[bytes] = ..., test: _Optional[bytes] = ..., agent: _Optional[bytes] = ..., seq: _Optional[_Union[SeqBatch, _Mapping]] = ...) -> None: ...

class SeqEntry(_message.Message):
    __slots__ = ("origin", "origin_incarnation", "cseq", "floor", "tx")
    ORIGIN_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    CSEQ_FIELD_NUMBER: _ClassVar[int]
    FLOOR_FIELD_NUMBER: _ClassVar[int]
    TX_FIELD_NUMBER: _ClassVar[int]
    origin: str
    origin_incarnation: int
    cseq: int
    floor: int
    tx: bytes
    def __init__(self, origin: _Optional[str] = ..., origin_incarnation: _Optional[int] = ..., cseq: _Optional[int] = ..., floor: _Optional[int] = ..., tx: _Optional[bytes] = ...) -> None: ...

class SeqBatch(_message.Message):
    __slots__ = ("entries",)
    ENTRIES_FIELD_NUMBER: _ClassVar[int]
    entries: _containers.RepeatedCompositeFieldContainer[SeqEntry]
    def __init__(self, entries: _Optional[_Iterable[_Union[SeqEntry, _Mapping]]] = ...) -> None: ...

class SeqOrigin(_message.Message):
    __slots__ = ("name", "incarnation", "floor", "done")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    FLOOR_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    floor: int
    done: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., floor: _Optional[int] = ..., done: _Optional[_Iterable[int]] = ...) -> None: ...

class AppliedTx(_message.Message):
    __slots__ = ("host", "incarnation", "seq", "applied_seq")
    HOST_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    APPLIED_SEQ_FIELD_NUMBER: _ClassVar[int]
    host: str
    incarnation: int
    seq: int
    applied_seq: int
    def __init__(self, host: _Optional[str] = ..., incarnation: _Optional[int] = ..., seq: _Optional[int] = ..., applied_seq: _Optional[int] = ...) -> None: ...

class GlobalSnapshot(_message.Message):
    __slots__ = ("seq", "view", "members", "group_correct", "core_members", "ddb", "recent", "chain", "genesis", "agents", "seq_origins")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    VIEW_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    GROUP_CORRECT_FIELD_NUMBER: _ClassVar[int]
    CORE_MEMBERS_FIELD_NUMBER: _ClassVar[int]
    DDB_FIELD_NUMBER: _ClassVar[int]
    RECENT_FIELD_NUMBER: _ClassVar[int]
    CHAIN_FIELD_NUMBER: _ClassVar[int]
    GENESIS_FIELD_NUMBER: _ClassVar[int]
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    SEQ_ORIGINS_FIELD_NUMBER: _ClassVar[int]
    seq: int
    view: int
    members: _containers.RepeatedCompositeFieldContainer[GroupMember]
    group_correct: bool
    core_members: _containers.RepeatedScalarFieldContainer[str]
    ddb: bytes
    recent: _containers.RepeatedCompositeFieldContainer[AppliedTx]
    chain: str
    genesis: str
    agents: bytes
    seq_origins: _containers.RepeatedCompositeFieldContainer[SeqOrigin]
    def __init__(self, seq: _Optional[int] = ..., view: _Optional[int] = ..., members: _Optional[_Iterable[_Union[GroupMember, _Mapping]]] = ..., group_correct: _Optional[bool] = ..., core_members: _Optional[_Iterable[str]] = ..., ddb: _Optional[bytes] = ..., recent: _Optional[_Iterable[_Union[AppliedTx, _Mapping]]] = ..., chain: _Optional[str] = ..., genesis: _Optional[str] = ..., agents: _Optional[bytes] = ..., seq_origins: _Optional[_Iterable[_Union[SeqOrigin, _Mapping]]] = ...) -> None: ...
