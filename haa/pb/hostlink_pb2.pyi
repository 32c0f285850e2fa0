from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class TxId(_message.Message):
    __slots__ = ("host", "incarnation", "seq")
    HOST_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    host: str
    incarnation: int
    seq: int
    def __init__(self, host: _Optional[str] = ..., incarnation: _Optional[int] = ..., seq: _Optional[int] = ...) -> None: ...

class Participant(_message.Message):
    __slots__ = ("host", "incarnation")
    HOST_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    host: str
    incarnation: int
    def __init__(self, host: _Optional[str] = ..., incarnation: _Optional[int] = ...) -> None: ...

class Heartbeat(_message.Message):
    __slots__ = ("seq", "period", "sent_at")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    PERIOD_FIELD_NUMBER: _ClassVar[int]
    SENT_AT_FIELD_NUMBER: _ClassVar[int]
    seq: int
    period: float
    sent_at: float
    def __init__(self, seq: _Optional[int] = ..., period: _Optional[float] = ..., sent_at: _Optional[float] = ...) -> None: ...

class SetPeriod(_message.Message):
    __slots__ = ("period",)
    PERIOD_FIELD_NUMBER: _ClassVar[int]
    period: float
    def __init__(self, period: _Optional[float] = ...) -> None: ...

class OacTransaction(_message.Message):
    __slots__ = ("id", "payload", "participants", "order")
    ID_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    PARTICIPANTS_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    payload: bytes
    participants: _containers.RepeatedCompositeFieldContainer[Participant]
    order: int
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., payload: _Optional[bytes] = ..., participants: _Optional[_Iterable[_Union[Participant, _Mapping]]] = ..., order: _Optional[int] = ...) -> None: ...

class OacOrder(_message.Message):
    __slots__ = ("id", "order")
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    order: int
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., order: _Optional[int] = ...) -> None: ...

class OacEstimate(_message.Message):
    __slots__ = ("id", "order", "round", "precommit", "ts")
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    ROUND_FIELD_NUMBER: _ClassVar[int]
    PRECOMMIT_FIELD_NUMBER: _ClassVar[int]
    TS_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    order: int
    round: int
    precommit: bool
    ts: int
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., order: _Optional[int] = ..., round: _Optional[int] = ..., precommit: _Optional[bool] = ..., ts: _Optional[int] = ...) -> None: ...

class OacProposal(_message.Message):
    __slots__ = ("id", "order", "round", "precommit")
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    ROUND_FIELD_NUMBER: _ClassVar[int]
    PRECOMMIT_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    order: int
    round: int
    precommit: bool
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., order: _Optional[int] = ..., round: _Optional[int] = ..., precommit: _Optional[bool] = ...) -> None: ...

class OacAck(_message.Message):
    __slots__ = ("id", "order", "round", "ack")
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    ROUND_FIELD_NUMBER: _ClassVar[int]
    ACK_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    order: int
    round: int
    ack: bool
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., order: _Optional[int] = ..., round: _Optional[int] = ..., ack: _Optional[bool] = ...) -> None: ...

class OacDecide(_message.Message):
    __slots__ = ("id", "order", "round", "commit", "participants", "delivered")
    ID_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    ROUND_FIELD_NUMBER: _ClassVar[int]
    COMMIT_FIELD_NUMBER: _ClassVar[int]
    PARTICIPANTS_FIELD_NUMBER: _ClassVar[int]
    DELIVERED_FIELD_NUMBER: _ClassVar[int]
    id: TxId
    order: int
    round: int
    commit: bool
    participants: _containers.RepeatedCompositeFieldContainer[Participant]
    delivered: bool
    def __init__(self, id: _Optional[_Union[TxId, _Mapping]] = ..., order: _Optional[int] = ..., round: _Optional[int] = ..., commit: _Optional[bool] = ..., participants: _Optional[_Iterable[_Union[Participant, _Mapping]]] = ..., delivered: _Optional[bool] = ...) -> None: ...

class Excluded(_message.Message):
    __slots__ = ("incarnation",)
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    incarnation: int
    def __init__(self, incarnation: _Optional[int] = ...) -> None: ...

class Apply(_message.Message):
    __slots__ = ("addr",)
    ADDR_FIELD_NUMBER: _ClassVar[int]
    addr: str
    def __init__(self, addr: _Optional[str] = ...) -> None: ...

class Introduce(_message.Message):
    __slots__ = ("name", "incarnation", "addr", "group")
    NAME_FIELD_NUMBER: _ClassVar[int]
    INCARNATION_FIELD_NUMBER: _ClassVar[int]
    ADDR_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    name: str
    incarnation: int
    addr: str
    group: str
    def __init__(self, name: _Optional[str] = ..., incarnation: _Optional[int] = ..., addr: _Optional[str] = ..., group: _Optional[str] = ...) -> None: ...

class Sponsor(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Connections(_message.Message):
    __slots__ = ("peers",)
    PEERS_FIELD_NUMBER: _ClassVar[int]
    peers: _containers.RepeatedCompositeFieldContainer[Participant]
    def __init__(self, peers: _Optional[_Iterable[_Union[Participant, _Mapping]]] = ...) -> None: ...

class Leave(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Locked(_message.Message):
    __slots__ = ("key",)
    KEY_FIELD_NUMBER: _ClassVar[int]
    key: str
    def __init__(self, key: _Optional[str] = ...) -> None: ...

class StateSnapshot(_message.Message):
    __slots__ = ("seq", "data", "anchor", "anchor_seq", "part", "parts", "lock_key", "lock_by", "lock_by_incarnation")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    ANCHOR_FIELD_NUMBER: _ClassVar[int]
    ANCHOR_SEQ_FIELD_NUMBER: _ClassVar[int]
    PART_FIELD_NUMBER: _ClassVar[int]
    PARTS_FIELD_NUMBER: _ClassVar[int]
    LOCK_KEY_FIELD_NUMBER: _ClassVar[int]
    LOCK_BY_FIELD_NUMBER: _ClassVar[int]
    LOCK_BY_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    seq: int
    data: bytes
    anchor: TxId
    anchor_seq: int
    part: int
    parts: int
    lock_key: str
    lock_by: str
    lock_by_incarnation: int
    def __init__(self, seq: _Optional[int] = ..., data: _Optional[bytes] = ..., anchor: _Optional[_Union[TxId, _Mapping]] = ..., anchor_seq: _Optional[int] = ..., part: _Optional[int] = ..., parts: _Optional[int] = ..., lock_key: _Optional[str] = ..., lock_by: _Optional[str] = ..., lock_by_incarnation: _Optional[int] = ...) -> None: ...

class StateForward(_message.Message):
    __slots__ = ("seq", "txid", "payload")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    TXID_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    seq: int
    txid: TxId
    payload: bytes
    def __init__(self, seq: _Optional[int] = ..., txid: _Optional[_Union[TxId, _Mapping]] = ..., payload: _Optional[bytes] = ...) -> None: ...

class StateRequest(_message.Message):
    __slots__ = ("txid",)
    TXID_FIELD_NUMBER: _ClassVar[int]
    txid: TxId
    def __init__(self, txid: _Optional[_Union[TxId, _Mapping]] = ...) -> None: ...

class AgentHost(_message.Message):
    __slots__ = ("kind", "agent", "epoch", "data")
    KIND_FIELD_NUMBER: _ClassVar[int]
    AGENT_FIELD_NUMBER: _ClassVar[int]
    EPOCH_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    kind: str
    agent: str
    epoch: int
    data: bytes
    def __init__(self, kind: _Optional[str] = ..., agent: _Optional[str] = ..., epoch: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class SeqWrite(_message.Message):
    __slots__ = ("floor", "writes")
    FLOOR_FIELD_NUMBER: _ClassVar[int]
    WRITES_FIELD_NUMBER: _ClassVar[int]
    floor: int
    writes: _containers.RepeatedCompositeFieldContainer[SeqWriteEntry]
    def __init__(self, floor: _Optional[int] = ..., writes: _Optional[_Iterable[_Union[SeqWriteEntry, _Mapping]]] = ...) -> None: ...

class SeqWriteEntry(_message.Message):
    __slots__ = ("cseq", "payload", "cost")
    CSEQ_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    COST_FIELD_NUMBER: _ClassVar[int]
    cseq: int
    payload: bytes
    cost: int
    def __init__(self, cseq: _Optional[int] = ..., payload: _Optional[bytes] = ..., cost: _Optional[int] = ...) -> None: ...

class Envelope(_message.Message):
    __slots__ = ("sender", "sender_incarnation", "dest_incarnation", "heartbeat", "set_period", "oac_transaction", "oac_order", "oac_estimate", "oac_proposal", "oac_ack", "oac_decide", "excluded", "apply", "introduce", "sponsor", "connections", "leave", "locked", "state_snapshot", "state_forward", "state_request", "agent_host", "seq_write")
    SENDER_FIELD_NUMBER: _ClassVar[int]
    SENDER_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    DEST_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_FIELD_NUMBER: _ClassVar[int]
    SET_PERIOD_FIELD_NUMBER: _ClassVar[int]
    OAC_TRANSACTION_FIELD_NUMBER: _ClassVar[int]
    OAC_ORDER_FIELD_NUMBER: _ClassVar[int]
    OAC_ESTIMATE_FIELD_NUMBER: _ClassVar[int]
    OAC_PROPOSAL_FIELD_NUMBER: _ClassVar[int]
    OAC_ACK_FIELD_NUMBER: _ClassVar[int]
    OAC_DECIDE_FIELD_NUMBER: _ClassVar[int]
    EXCLUDED_FIELD_NUMBER: _ClassVar[int]
    APPLY_FIELD_NUMBER: _ClassVar[int]
    INTRODUCE_FIELD_NUMBER: _ClassVar[int]
    SPONSOR_FIELD_NUMBER: _ClassVar[int]
    CONNECTIONS_FIELD_NUMBER: _ClassVar[int]
    LEAVE_FIELD_NUMBER: _ClassVar[int]
    LOCKED_FIELD_NUMBER: _ClassVar[int]
    STATE_SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    STATE_FORWARD_FIELD_NUMBER: _ClassVar[int]
    STATE_REQUEST_FIELD_NUMBER: _ClassVar[int]
    AGENT_HOST_FIELD_NUMBER: _ClassVar[int]
    SEQ_WRITE_FIELD_NUMBER: _ClassVar[int]
    sender: str
    sender_incarnation: int
    dest_incarnation: int
    heartbeat: Heartbeat
    set_period: SetPeriod
    oac_transaction: OacTransaction
    oac_order: OacOrder
    oac_estimate: OacEstimate
    oac_proposal: OacProposal
    oac_ack: OacAck
    oac_decide: OacDecide
    excluded: Excluded
    apply: Apply
    introduce: Introduce
    sponsor: Sponsor
    connections: Connections
    leave: Leave
    locked: Locked
    state_snapshot: StateSnapshot
    state_forward: StateForward
    state_request: StateRequest
    agent_host: AgentHost
    seq_write: SeqWrite
    def __init__(self, sender: _Optional[str] = ..., sender_incarnation: _Optional[int] = ..., dest_incarnation: _Optional[int] = ..., heartbeat: _Optional[_Union[Heartbeat, _Mapping]] = ..., set_period: _Optional[_Union[SetPeriod, _Mapping]] = ..., oac_transaction: _Optional[_Union[OacTransaction, _Mapping]] = ..., oac_order: _Optional[_Union[OacOrder, _Mapping]] = ..., oac_estimate: _Optional[_Union[OacEstimate, _Mapping]] = ..., oac_proposal: _Optional[_Union[OacProposal, _Mapping]] = ..., oac_ack: _Optional[_Union[OacAck, _Mapping]] = ..., oac_decide: _Optional[_Union[OacDecide, _Mapping]] = ..., excluded: _Optional[_Union[Excluded, _Mapping]] = ..., apply: _Optional[_Union[Apply, _Mapping]] = ..., introduce: _Optional[_Union[Introduce, _Mapping]] = ..., sponsor: _Optional[_Union[Sponsor, _Mapping]] = ..., connections: _Optional[_Union[Connections, _Mapping]] = ..., leave: _Optional[_Union[Leave, _Mapping]] = ..., locked: _Optional[_Union[Locked, _Mapping]] = ..., state_snapshot: _Optional[_Union[StateSnapshot, _Mapping]] = ..., state_forward: _Optional[_Union[StateForward, _Mapping]] = ..., state_request: _Optional[_Union[StateRequest, _Mapping]] = ..., agent_host: _Optional[_Union[AgentHost, _Mapping]] = ..., seq_write: _Optional[_Union[SeqWrite, _Mapping]] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("first_seq", "envelopes", "more", "part")
    FIRST_SEQ_FIELD_NUMBER: _ClassVar[int]
    ENVELOPES_FIELD_NUMBER: _ClassVar[int]
    MORE_FIELD_NUMBER: _ClassVar[int]
    PART_FIELD_NUMBER: _ClassVar[int]
    first_seq: int
    envelopes: _containers.RepeatedCompositeFieldContainer[Envelope]
    more: bool
    part: bytes
    def __init__(self, first_seq: _Optional[int] = ..., envelopes: _Optional[_Iterable[_Union[Envelope, _Mapping]]] = ..., more: _Optional[bool] = ..., part: _Optional[bytes] = ...) -> None: ...

class LinkReply(_message.Message):
    __slots__ = ("receiver", "receiver_incarnation", "acked_seq", "heartbeat_port")
    RECEIVER_FIELD_NUMBER: _ClassVar[int]
    RECEIVER_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    ACKED_SEQ_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_PORT_FIELD_NUMBER: _ClassVar[int]
    receiver: str
    receiver_incarnation: int
    acked_seq: int
    heartbeat_port: int
    def __init__(self, receiver: _Optional[str] = ..., receiver_incarnation: _Optional[int] = ..., acked_seq: _Optional[int] = ..., heartbeat_port: _Optional[int] = ...) -> None: ...
