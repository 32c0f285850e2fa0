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

class Envelope(_message.Message):
    __slots__ = ("sender", "sender_incarnation", "dest_incarnation", "heartbeat", "set_period", "oac_transaction", "oac_order", "oac_estimate", "oac_proposal", "oac_ack", "oac_decide", "excluded")
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
    def __init__(self, sender: _Optional[str] = ..., sender_incarnation: _Optional[int] = ..., dest_incarnation: _Optional[int] = ..., heartbeat: _Optional[_Union[Heartbeat, _Mapping]] = ..., set_period: _Optional[_Union[SetPeriod, _Mapping]] = ..., oac_transaction: _Optional[_Union[OacTransaction, _Mapping]] = ..., oac_order: _Optional[_Union[OacOrder, _Mapping]] = ..., oac_estimate: _Optional[_Union[OacEstimate, _Mapping]] = ..., oac_proposal: _Optional[_Union[OacProposal, _Mapping]] = ..., oac_ack: _Optional[_Union[OacAck, _Mapping]] = ..., oac_decide: _Optional[_Union[OacDecide, _Mapping]] = ..., excluded: _Optional[_Union[Excluded, _Mapping]] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("first_seq", "envelopes")
    FIRST_SEQ_FIELD_NUMBER: _ClassVar[int]
    ENVELOPES_FIELD_NUMBER: _ClassVar[int]
    first_seq: int
    envelopes: _containers.RepeatedCompositeFieldContainer[Envelope]
    def __init__(self, first_seq: _Optional[int] = ..., envelopes: _Optional[_Iterable[_Union[Envelope, _Mapping]]] = ...) -> None: ...

class LinkReply(_message.Message):
    __slots__ = ("receiver", "receiver_incarnation", "acked_seq")
    RECEIVER_FIELD_NUMBER: _ClassVar[int]
    RECEIVER_INCARNATION_FIELD_NUMBER: _ClassVar[int]
    ACKED_SEQ_FIELD_NUMBER: _ClassVar[int]
    receiver: str
    receiver_incarnation: int
    acked_seq: int
    def __init__(self, receiver: _Optional[str] = ..., receiver_incarnation: _Optional[int] = ..., acked_seq: _Optional[int] = ...) -> None: ...
