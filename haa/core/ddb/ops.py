"""The client side of the DDB: op builders and batch encoding (thesis §6.1.3; docs/ddb.md).

An agent, haactl or a test writes to the DDB by building ops (`put`, `delete`, `append`, `cas`, `add`,
`log_append`, `log_trim`), encoding them as one batch (`encode_batch`) and handing the bytes to its host, which
proposes them through OAC; every replica applies them with `haa.core.ddb.ddb.Ddb.apply`. The cheap checks a host
runs on ops it receives before proposing them are here too (`check_op`, `check_json_sizes`), and `decode_log`
reads a log's stored bytes.

Sans-I/O: no clock, no randomness, no I/O; it imports only the standard library, the generated protobuf message
classes and `haa.core.ddb.objects`.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import haa.pb.ddb_pb2 as pb
from haa.core.ddb.objects import (
    MAX_BATCH_BYTES,
    MAX_BATCH_JSON_BYTES,
    MAX_BATCH_OPS,
    MAX_JSON_VALUE_BYTES,
    MAX_LOG_INDEX,
    MAX_VALUE_BYTES,
    TYPES,
    DdbError,
    JsonType,
    LogType,
    LogValue,
    _log_error,
    _OpFailed,
    _type,
    key_error,
)

# ----------------------------------------------------------------------------------------- client side


def encode_value(type_name: str, value: Any) -> bytes:
    """A Python value -> the wire bytes of a put/cas of `type_name` (bytes pass through for unknown types)."""
    t = TYPES.get(type_name)
    if t is None:
        if isinstance(value, bytes):
            return value
        raise DdbError(f"unknown type {type_name!r}: give the value as bytes")
    data = t.client_encode(value)
    if t.writable and len(data) > MAX_VALUE_BYTES:
        raise DdbError(f"value too large: {len(data)} bytes > {MAX_VALUE_BYTES}")
    if type_name == JsonType.name and len(data) > MAX_JSON_VALUE_BYTES:
        raise DdbError(f"json value too large: {len(data)} bytes > {MAX_JSON_VALUE_BYTES} (MAX_JSON_VALUE_BYTES)")
    return data


def _op(**kw: Any) -> pb.DdbOp:
    try:
        return pb.DdbOp(**kw)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid op: {e}") from None


def _writable(type_name: str) -> None:
    t = TYPES.get(type_name)
    if t is not None and not t.writable:
        raise DdbError(f"a {type_name} is written only by its own ops, not by put or cas")


def put(key: str, type_name: str, value: Any) -> pb.DdbOp:
    """Put op: create `key` or replace its value (same type). `value` is a Python value of the type."""
    _writable(type_name)
    return _op(put=pb.DdbPut(key=key, type=type_name, value=encode_value(type_name, value)))


def delete(key: str) -> pb.DdbOp:
    """Delete op."""
    return _op(delete=pb.DdbDelete(key=key))


def append(key: str, item: bytes, max_len: int = 0) -> pb.DdbOp:
    """Append op on a list (created if absent); `max_len` > 0 trims the list from the front."""
    if not isinstance(item, bytes | bytearray | memoryview):
        raise DdbError(f"a list item must be bytes, not {type(item).__name__}")
    if len(item) > MAX_VALUE_BYTES:
        raise DdbError(f"value too large: item of {len(item)} bytes > {MAX_VALUE_BYTES}")
    try:
        body = pb.DdbAppend(key=key, item=bytes(item), max_len=max_len)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid append: {e}") from None
    return _op(append=body)


def cas(key: str, expected_version: int, type_name: str, value: Any) -> pb.DdbOp:
    """Compare-and-set op: put only if the object's version is `expected_version` (0 = must not exist)."""
    _writable(type_name)
    data = encode_value(type_name, value)
    try:
        body = pb.DdbCas(key=key, expected_version=expected_version, type=type_name, value=data)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid cas: {e}") from None
    return _op(cas=body)


def add(key: str, delta: int) -> pb.DdbOp:
    """Add op on a counter (created at 0 if absent)."""
    try:
        body = pb.DdbAdd(key=key, delta=delta)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid add: {e}") from None
    return _op(add=body)


def log_append(key: str, items: Iterable[bytes]) -> pb.DdbOp:
    """Log append op: append `items` (bytes, at least one) to the log `key`, created at index 0 if absent;
    they get the log's next indexes, in order. Raises `DdbError` for what would fail anyway (an item over
    MAX_LOG_ITEM_BYTES, more than MAX_LOG_BYTES / MAX_LOG_ITEMS in one op)."""
    if isinstance(items, bytes | bytearray | memoryview | str) or not isinstance(items, Iterable):
        raise DdbError("log_append takes an iterable of bytes items (a single item: [item])")
    batch = list(items)
    if not batch:
        raise DdbError("log_append with no items")
    for i, item in enumerate(batch):
        if not isinstance(item, bytes | bytearray | memoryview):
            raise DdbError(f"log item {i} must be bytes, not {type(item).__name__}")
    batch = [bytes(i) for i in batch]
    why = _log_error(0, tuple(batch), sum(map(len, batch)))
    if why:
        raise DdbError(why)
    try:
        body = pb.DdbLogAppend(key=key, items=batch)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid log_append: {e}") from None
    return _op(log_append=body)


def log_trim(key: str, upto: int) -> pb.DdbOp:
    """Log trim op: drop the items of log `key` whose index is < `upto` (a no-op if `upto` <= its first index;
    fails if `upto` is beyond its next index)."""
    if not isinstance(upto, int) or isinstance(upto, bool) or not 0 <= upto <= MAX_LOG_INDEX:
        raise DdbError(f"log_trim upto must be an int in [0, {MAX_LOG_INDEX}], not {upto!r}")
    try:
        body = pb.DdbLogTrim(key=key, upto=upto)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid log_trim: {e}") from None
    return _op(log_trim=body)


def decode_value(type_name: str, data: bytes) -> Any:
    """A record's canonical value bytes (what `DdbGet`, a watch event or a snapshot record carries) -> the value
    a reader of the replica sees (`DdbObject.value`): json parsed, counter an int, list a tuple of bytes items,
    log {"first": index, "items": tuple of bytes}, blob bytes. Raises `DdbError` for an unknown type or
    malformed bytes. The one decoder of DDB values: haa.cluster.values.plain_value (the operator's JSON-able
    form) and haa.cluster.queries.ddb_read build on it."""
    try:
        t = _type(type_name)
        raw, _ = t.decode(data)
    except _OpFailed as e:
        raise DdbError(e.args[0]) from None
    return t.public(raw)


def decode_log(data: bytes) -> LogValue:
    """A log's stored bytes (its canonical value: what `DdbGet` and an agent's `ddb_get` return, a snapshot
    record's value) -> `(first, items)`: item k has index first + k. Raises `DdbError` if malformed."""
    try:
        return LogType().decode(data)[0]
    except _OpFailed as e:
        raise DdbError(e.args[0]) from None


def check_op(op: pb.DdbOp) -> str:
    """'' if `op` passes the checks that need no replica (an operation set, a valid key, a known and
    writable type, the size bounds of one value, item or op), else the reason. Cheap; a host runs it on
    ops it receives before proposing them (an op that passes may still fail on apply: type mismatch, a
    full log, a version mismatch...)."""
    kind = op.WhichOneof("op")
    if kind is None:
        return "op has no operation set (unknown op kind?)"
    body = getattr(op, kind)
    why = key_error(body.key)
    if why:
        return why
    if kind in ("put", "cas"):
        t = TYPES.get(body.type)
        if t is None:
            return f"unknown type {body.type[:40]!r}"
        if not t.writable:
            return f"a {body.type} is written only by its own ops, not by put or cas"
        limit = MAX_JSON_VALUE_BYTES if body.type == JsonType.name else MAX_VALUE_BYTES
        if len(body.value) > limit:
            return f"value too large: {len(body.value)} bytes > {limit}"
    elif kind == "append":
        if len(body.item) > MAX_VALUE_BYTES:
            return f"value too large: item of {len(body.item)} bytes > {MAX_VALUE_BYTES}"
    elif kind == "log_append":
        if not body.items:
            return "log_append with no items"
        items = tuple(body.items)
        return _log_error(0, items, sum(map(len, items)))
    return ""


def json_bytes(op: pb.DdbOp) -> int:
    """Bytes of JSON text an op makes a replica parse (put/cas of type json), else 0."""
    kind = op.WhichOneof("op")
    if kind in ("put", "cas"):
        body = getattr(op, kind)
        if body.type == JsonType.name:
            return len(body.value)
    return 0


def check_json_sizes(ops: Iterable[pb.DdbOp]) -> str:
    """'' if no JSON value exceeds MAX_JSON_VALUE_BYTES and their sum MAX_BATCH_JSON_BYTES, else the reason.
    Cheap (lengths only): run before any parsing, at the edge and when a batch applies."""
    total = 0
    for i, op in enumerate(ops):
        n = json_bytes(op)
        if n > MAX_JSON_VALUE_BYTES:
            return f"op {i}: json value of {n} bytes > {MAX_JSON_VALUE_BYTES} (MAX_JSON_VALUE_BYTES)"
        total += n
    if total > MAX_BATCH_JSON_BYTES:
        return f"json values of {total} bytes in one batch > {MAX_BATCH_JSON_BYTES} (MAX_BATCH_JSON_BYTES)"
    return ""


def check_batch(batch: pb.DdbBatch) -> str:
    """'' if `batch` is one a host may propose, else the reason: the one definition of a valid batch (at least
    one op, at most `MAX_BATCH_OPS` ops and `MAX_BATCH_BYTES` encoded, so every replica's `Ddb.apply` takes it,
    and the JSON bounds of `check_json_sizes`). Cheap (sizes only); `encode_batch` runs it, where a write enters a host
    (`haa.hostd.writes.Writes.ddb_write`) and wherever else a batch is made."""
    if not batch.ops:
        return "empty batch"
    if len(batch.ops) > MAX_BATCH_OPS:
        return f"batch of {len(batch.ops)} ops > {MAX_BATCH_OPS} (MAX_BATCH_OPS)"
    size = batch.ByteSize()
    if size > MAX_BATCH_BYTES:
        return f"batch of {size} bytes > {MAX_BATCH_BYTES} (MAX_BATCH_BYTES)"
    return check_json_sizes(batch.ops)


def encode_batch(ops: Iterable[pb.DdbOp], origin: str = "", client_seq: int = 0, atomic: bool = False) -> bytes:
    """Encode ops as one OAC payload; raises `DdbError` with `check_batch`'s reason if it is not a valid
    batch."""
    try:
        batch = pb.DdbBatch(ops=list(ops), origin=origin, client_seq=client_seq, atomic=atomic)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid batch: {e}") from None
    why = check_batch(batch)
    if why:
        raise DdbError(why)
    data: bytes = batch.SerializeToString()
    return data
