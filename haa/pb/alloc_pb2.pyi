from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class AllocBid(_message.Message):
    __slots__ = ("agent", "winner", "reward", "support", "round")
    AGENT_FIELD_NUMBER: _ClassVar[int]
    WINNER_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    SUPPORT_FIELD_NUMBER: _ClassVar[int]
    ROUND_FIELD_NUMBER: _ClassVar[int]
    agent: str
    winner: str
    reward: float
    support: float
    round: int
    def __init__(self, agent: _Optional[str] = ..., winner: _Optional[str] = ..., reward: _Optional[float] = ..., support: _Optional[float] = ..., round: _Optional[int] = ...) -> None: ...

class AllocBidUpdate(_message.Message):
    __slots__ = ("sender", "ses_id", "bids")
    SENDER_FIELD_NUMBER: _ClassVar[int]
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    BIDS_FIELD_NUMBER: _ClassVar[int]
    sender: str
    ses_id: int
    bids: _containers.RepeatedCompositeFieldContainer[AllocBid]
    def __init__(self, sender: _Optional[str] = ..., ses_id: _Optional[int] = ..., bids: _Optional[_Iterable[_Union[AllocBid, _Mapping]]] = ...) -> None: ...

class AllocAffinity(_message.Message):
    __slots__ = ("agent", "alpha")
    AGENT_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    agent: str
    alpha: float
    def __init__(self, agent: _Optional[str] = ..., alpha: _Optional[float] = ...) -> None: ...

class AllocAgent(_message.Message):
    __slots__ = ("id", "cost", "hardware", "affinity", "transfer_penalty", "current_host", "kind", "max_per_host", "placed")
    ID_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    HARDWARE_FIELD_NUMBER: _ClassVar[int]
    AFFINITY_FIELD_NUMBER: _ClassVar[int]
    TRANSFER_PENALTY_FIELD_NUMBER: _ClassVar[int]
    CURRENT_HOST_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    MAX_PER_HOST_FIELD_NUMBER: _ClassVar[int]
    PLACED_FIELD_NUMBER: _ClassVar[int]
    id: str
    cost: float
    hardware: _containers.RepeatedScalarFieldContainer[str]
    affinity: _containers.RepeatedCompositeFieldContainer[AllocAffinity]
    transfer_penalty: float
    current_host: str
    kind: str
    max_per_host: int
    placed: str
    def __init__(self, id: _Optional[str] = ..., cost: _Optional[float] = ..., hardware: _Optional[_Iterable[str]] = ..., affinity: _Optional[_Iterable[_Union[AllocAffinity, _Mapping]]] = ..., transfer_penalty: _Optional[float] = ..., current_host: _Optional[str] = ..., kind: _Optional[str] = ..., max_per_host: _Optional[int] = ..., placed: _Optional[str] = ...) -> None: ...

class AllocHost(_message.Message):
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

class AllocStart(_message.Message):
    __slots__ = ("leader", "ses_id", "group", "agents", "hosts", "has_auction", "auction")
    LEADER_FIELD_NUMBER: _ClassVar[int]
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    HOSTS_FIELD_NUMBER: _ClassVar[int]
    HAS_AUCTION_FIELD_NUMBER: _ClassVar[int]
    AUCTION_FIELD_NUMBER: _ClassVar[int]
    leader: str
    ses_id: int
    group: _containers.RepeatedScalarFieldContainer[str]
    agents: _containers.RepeatedCompositeFieldContainer[AllocAgent]
    hosts: _containers.RepeatedCompositeFieldContainer[AllocHost]
    has_auction: bool
    auction: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, leader: _Optional[str] = ..., ses_id: _Optional[int] = ..., group: _Optional[_Iterable[str]] = ..., agents: _Optional[_Iterable[_Union[AllocAgent, _Mapping]]] = ..., hosts: _Optional[_Iterable[_Union[AllocHost, _Mapping]]] = ..., has_auction: _Optional[bool] = ..., auction: _Optional[_Iterable[str]] = ...) -> None: ...

class AllocPlacement(_message.Message):
    __slots__ = ("agent", "host")
    AGENT_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    agent: str
    host: str
    def __init__(self, agent: _Optional[str] = ..., host: _Optional[str] = ...) -> None: ...

class AllocFinish(_message.Message):
    __slots__ = ("leader", "ses_id", "allocation", "unallocatable")
    LEADER_FIELD_NUMBER: _ClassVar[int]
    SES_ID_FIELD_NUMBER: _ClassVar[int]
    ALLOCATION_FIELD_NUMBER: _ClassVar[int]
    UNALLOCATABLE_FIELD_NUMBER: _ClassVar[int]
    leader: str
    ses_id: int
    allocation: _containers.RepeatedCompositeFieldContainer[AllocPlacement]
    unallocatable: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, leader: _Optional[str] = ..., ses_id: _Optional[int] = ..., allocation: _Optional[_Iterable[_Union[AllocPlacement, _Mapping]]] = ..., unallocatable: _Optional[_Iterable[str]] = ...) -> None: ...
