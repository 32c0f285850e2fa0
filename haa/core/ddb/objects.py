"""What the DDB stores: its bounds, its object types and one object (thesis §4.2.2, §6.1.3; docs/ddb.md).

* the size bounds every replica and every client applies (`MAX_KEY`, `MAX_VALUE_BYTES`, `MAX_BATCH_BYTES`, the
  JSON and log bounds), and `DdbError`, the error of anything a replica cannot accept;
* the object types (`blob`, `json`, `list`, `counter`, `log`): how a value of each is validated, stored,
  encoded, hashed and shown (`ObjectType`, `TYPES`);
* `DdbObject`, one object of a replica, and the key and size checks an op applies.

The replica that applies operations is `haa.core.ddb.ddb.Ddb`; the op builders clients use are
`haa.core.ddb.ops`. Sans-I/O: no clock, no randomness, no I/O; it imports only the standard library and the
generated protobuf message classes.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from google.protobuf.message import DecodeError

import haa.pb.ddb_pb2 as pb

#: longest key, in characters
MAX_KEY = 512
#: largest stored value (blob bytes, canonical JSON text, a list's items in total), in bytes
MAX_VALUE_BYTES = 1024 * 1024
#: largest encoded batch (one OAC payload), in bytes. A batch is copied, decoded and hashed about a dozen times
#: on every host within one event-loop callback; measured on a loaded 4-host group (bench-results/memory.json,
#: docs/limits.md "Sizes and memory") that costs 50-140 ms per MiB, and a stall must stay well below the
#: failure detector's margin (~0.7 s): 2 MiB stalled at most ~0.22 s, 16 MiB (the former bound) up to 2.2 s
MAX_BATCH_BYTES = 2 * 1024 * 1024
#: most ops in one batch, and in one sequencer transaction in total (`SeqConfig.seq_max_cost`). Bytes do not
#: bound the work of tiny ops: 100,000 deletes fit in 1.3 MB. Measured over the whole commit path on a 4-host
#: group (`haactl bench memory`, docs/limits.md): a batch of 10,000 tiny puts, adds or deletes cost a loop
#: 367-389 ms of CPU on one host (~39 us an op: decoded, applied, mirrored, hashed), as much as the largest
#: JSON batch and more than half the failure detector's margin (~0.7 s), with wall-clock stalls to 0.75 s on
#: the loaded 2-core machine. Half of that keeps an op-heavy batch near the largest blob batch (~0.2 s)
MAX_BATCH_OPS = 5_000
#: most keys one replica holds. Every host keeps every key in memory (~0.8-1.5 KB each with its digest and
#: index, measured), in every snapshot a joiner receives and in the content hash: 200,000 keys are ~200 MiB
#: of RSS per host and a ~12 MiB snapshot
MAX_DDB_KEYS = 200_000
#: most bytes (keys + stored values) one replica holds: a joiner receives the whole replica in one snapshot
#: (at most MAX_MESSAGE = 64 MiB with the agent table), so the DDB keeps 16 MiB of it for the rest
MAX_DDB_BYTES = 48 * 1024 * 1024
#: largest JSON value (put/cas of type json), in bytes. JSON is parsed and checked on every replica when the
#: batch applies, at up to ~250 ms per MiB for the costliest texts (`[{},{},...]`, many floats) against ~1 ms
#: per MiB for a blob: these bounds, not MAX_BATCH_BYTES, bound the event-loop stall of a JSON batch
MAX_JSON_VALUE_BYTES = 256 * 1024
#: JSON value bytes (put/cas of type json) in one batch, in total
MAX_BATCH_JSON_BYTES = 256 * 1024
#: deepest JSON nesting accepted (bounds the recursion of the json module, so that acceptance cannot depend
#: on the caller's stack depth)
JSON_MAX_DEPTH = 100
#: largest item of a log (one `log_append` item), in bytes
MAX_LOG_ITEM_BYTES = 256 * 1024
#: largest log: its stored items in total, in bytes. Every host keeps every log in memory, in every snapshot a
#: joiner receives and in the per-object hash it recomputes after a write (docs/ddb.md, "Logs"; docs/limits.md)
MAX_LOG_BYTES = 4 * 1024 * 1024
#: most items a log holds (bounds the per-item memory and copying when items are tiny or empty)
MAX_LOG_ITEMS = 65_536
#: largest index + 1 of a log (indexes and `log_trim`'s `upto` are uint64 on the wire)
MAX_LOG_INDEX = 2**64 - 1

INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1


class DdbError(ValueError):
    """A payload, snapshot or request the DDB cannot accept; the replica is unchanged."""


class _OpFailed(Exception):
    """An op's precondition or validation failed; `args[0]` is the deterministic reason."""


# ------------------------------------------------------------------------------------------------ types


class ObjectType:
    """An object type: how its values are validated, stored, encoded, hashed and shown.

    A value has three forms: the *wire* bytes in a put/cas (and in snapshots), the *internal* immutable
    representation a replica stores, and the *public* value readers and watchers see.
    """

    name = ""
    #: largest stored size (what `decode` returns as the size) a value may have
    max_bytes = MAX_VALUE_BYTES
    #: False: put/cas of this type fail (the type has ops of its own that keep an invariant)
    writable = True

    def decode(self, data: bytes) -> tuple[Any, int]:
        """Wire bytes -> (internal value, size in bytes); raises `_OpFailed` with the reason."""
        raise NotImplementedError

    def encode(self, raw: Any) -> bytes:
        """Internal value -> canonical wire bytes (equal values give equal bytes)."""
        raise NotImplementedError

    def public(self, raw: Any) -> Any:
        """Internal value -> the value readers see (a fresh object if it could be mutated)."""
        return raw

    def client_encode(self, value: Any) -> bytes:
        """A Python value -> wire bytes for a put/cas op; raises `DdbError`."""
        raise NotImplementedError


class BlobType(ObjectType):
    """`blob`: opaque bytes."""

    name = "blob"

    def decode(self, data: bytes) -> tuple[bytes, int]:
        return bytes(data), len(data)

    def encode(self, raw: bytes) -> bytes:
        return raw

    def client_encode(self, value: Any) -> bytes:
        if not isinstance(value, bytes | bytearray | memoryview):
            raise DdbError(f"a blob value must be bytes, not {type(value).__name__}")
        return bytes(value)


_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.S)
_JSON_BRACKET = re.compile(r"[\[\]{}]")


def _json_depth_ok(text: str) -> bool:
    if text.count("[") + text.count("{") <= JSON_MAX_DEPTH:
        return True  # cheap bound: brackets inside strings only over-count
    brackets = _JSON_BRACKET.findall(_JSON_STRING.sub("", text))
    steps = (1 if b in "[{" else -1 for b in brackets)
    return max(itertools.accumulate(steps), default=0) <= JSON_MAX_DEPTH


def _reject_constant(name: str) -> Any:
    raise _OpFailed(f"invalid json: {name} is not allowed")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _OpFailed(f"invalid json: number {text[:40]} is out of range")
    return value


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _OpFailed(f"invalid json: duplicate key {k[:40]!r}")
        out[k] = v
    return out


def _canonical_json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


class JsonType(ObjectType):
    """`json`: a JSON value, stored as canonical text (sorted keys, no whitespace, UTF-8, no NaN/Infinity).

    Objects with duplicate keys are rejected rather than resolved. Readers get a freshly parsed value.
    """

    name = "json"

    def decode(self, data: bytes) -> tuple[str, int]:
        try:
            text = bytes(data).decode("utf-8")
        except UnicodeDecodeError as e:
            raise _OpFailed(f"invalid json: not UTF-8 (byte {e.start})") from None
        if not _json_depth_ok(text):
            raise _OpFailed(f"invalid json: nested deeper than {JSON_MAX_DEPTH}")
        try:
            value = json.loads(
                text,
                parse_constant=_reject_constant,
                parse_float=_finite_float,
                object_pairs_hook=_no_duplicate_keys,
            )
        except json.JSONDecodeError as e:
            raise _OpFailed(f"invalid json: {e.msg} at offset {e.pos}") from None
        except ValueError as e:  # e.g. an integer beyond the interpreter's digit limit
            raise _OpFailed(f"invalid json: {e}") from None
        canon = _canonical_json(value)
        try:
            size = len(canon.encode("utf-8"))
        except UnicodeEncodeError:
            raise _OpFailed("invalid json: lone surrogate in a string") from None
        return canon, size

    def encode(self, raw: str) -> bytes:
        return raw.encode("utf-8")

    def public(self, raw: str) -> Any:
        return json.loads(raw)

    def client_encode(self, value: Any) -> bytes:
        try:
            return _canonical_json(value).encode("utf-8")
        except (TypeError, ValueError) as e:
            raise DdbError(f"json value cannot be encoded: {e}") from None


class ListType(ObjectType):
    """`list`: an append-only sequence of byte items (a queue when appends give `max_len`)."""

    name = "list"

    def decode(self, data: bytes) -> tuple[tuple[bytes, ...], int]:
        try:
            items = tuple(pb.DdbListValue.FromString(bytes(data)).items)
        except DecodeError:
            raise _OpFailed("invalid list value: not a DdbListValue") from None
        return items, sum(map(len, items))

    def encode(self, raw: tuple[bytes, ...]) -> bytes:
        encoded: bytes = pb.DdbListValue(items=raw).SerializeToString()
        return encoded

    def client_encode(self, value: Any) -> bytes:
        if isinstance(value, bytes | str) or not isinstance(value, Iterable):
            raise DdbError("a list value must be an iterable of bytes items")
        items = list(value)
        if not all(isinstance(i, bytes) for i in items):
            raise DdbError("list items must be bytes")
        encoded: bytes = pb.DdbListValue(items=items).SerializeToString()
        return encoded


_I64 = struct.Struct(">q")


class CounterType(ObjectType):
    """`counter`: an int64; wire form 8 bytes big-endian two's complement."""

    name = "counter"

    def decode(self, data: bytes) -> tuple[int, int]:
        if len(data) != _I64.size:
            raise _OpFailed(f"invalid counter value: expected 8 bytes, got {len(data)}")
        return _I64.unpack(data)[0], _I64.size

    def encode(self, raw: int) -> bytes:
        return _I64.pack(raw)

    def client_encode(self, value: Any) -> bytes:
        if not isinstance(value, int) or isinstance(value, bool) or not INT64_MIN <= value <= INT64_MAX:
            raise DdbError(f"a counter value must be an int64, not {value!r}")
        return _I64.pack(value)


#: the internal value of a log: (first index, items); item k has index first + k
LogValue = tuple[int, tuple[bytes, ...]]


def _log_error(first: int, items: tuple[bytes, ...], size: int) -> str:
    """'' if a log (first, items) of `size` item bytes is within the bounds, else the reason."""
    big = next((i for i, item in enumerate(items) if len(item) > MAX_LOG_ITEM_BYTES), None)
    if big is not None:
        return f"log item {big} too large: {len(items[big])} bytes > {MAX_LOG_ITEM_BYTES} (MAX_LOG_ITEM_BYTES)"
    if len(items) > MAX_LOG_ITEMS:
        return f"log too long: {len(items)} items > {MAX_LOG_ITEMS} (MAX_LOG_ITEMS)"
    if size > MAX_LOG_BYTES:
        return f"log too large: {size} bytes > {MAX_LOG_BYTES} (MAX_LOG_BYTES)"
    if first + len(items) > MAX_LOG_INDEX:
        return f"log index overflow: {first} + {len(items)} items > {MAX_LOG_INDEX}"
    return ""


class LogType(ObjectType):
    """`log`: an append-only sequence of byte items with global indexes, trimmed from the front.

    Internal value `(first, items)`: the item at position k has index first + k; readers see
    `{"first": first, "items": items}` (items a tuple of bytes, as a list's). Written only by `log_append`
    and `log_trim` (`writable` is False), so that an index is never given to two items in the object's life.
    """

    name = "log"
    max_bytes = MAX_LOG_BYTES
    writable = False

    def decode(self, data: bytes) -> tuple[LogValue, int]:
        try:
            v = pb.DdbLogValue.FromString(bytes(data))
        except DecodeError:
            raise _OpFailed("invalid log value: not a DdbLogValue") from None
        items = tuple(v.items)
        size = sum(map(len, items))
        why = _log_error(v.first, items, size)
        if why:
            raise _OpFailed(f"invalid log value: {why}")
        return (v.first, items), size

    def encode(self, raw: LogValue) -> bytes:
        encoded: bytes = pb.DdbLogValue(first=raw[0], items=raw[1]).SerializeToString()
        return encoded

    def public(self, raw: LogValue) -> dict[str, Any]:
        return {"first": raw[0], "items": raw[1]}

    def client_encode(self, value: Any) -> bytes:
        if isinstance(value, dict):
            first, items = value.get("first", 0), value.get("items", ())
        elif isinstance(value, tuple) and len(value) == 2:
            first, items = value
        else:
            raise DdbError('a log value is (first, items) or {"first": n, "items": [...]}')
        if not isinstance(first, int) or isinstance(first, bool) or not 0 <= first <= MAX_LOG_INDEX:
            raise DdbError(f"a log's first index must be an int in [0, {MAX_LOG_INDEX}], not {first!r}")
        if isinstance(items, bytes | str) or not all(isinstance(i, bytes) for i in items):
            raise DdbError("log items must be bytes")
        encoded: bytes = pb.DdbLogValue(first=first, items=list(items)).SerializeToString()
        return encoded


#: every object type, by name
TYPES: dict[str, ObjectType] = {t.name: t for t in (BlobType(), JsonType(), ListType(), CounterType(), LogType())}


# ---------------------------------------------------------------------------------------------- objects


@dataclass(frozen=True, slots=True)
class DdbObject:
    """One object of a replica. Immutable: a write replaces it.

    `raw` is the type's internal representation; read `value` (blob: bytes, json: a fresh parse, list:
    tuple of bytes, counter: int, log: {"first": n, "items": tuple of bytes}). `version` is the seq of the
    batch that last wrote it, `created` the seq of the batch that created it, `size` its value's size in
    bytes (a log's: its items').
    """

    key: str
    type_name: str
    raw: Any
    version: int
    created: int
    size: int

    @property
    def value(self) -> Any:
        return TYPES[self.type_name].public(self.raw)

    @property
    def data(self) -> bytes:
        """The value's canonical wire encoding (what snapshots store and the hash covers)."""
        return TYPES[self.type_name].encode(self.raw)



def key_error(key: str) -> str:
    """The reason `key` is not a valid key, or "" if it is."""
    if not key:
        return "invalid key: empty"
    if len(key) > MAX_KEY:
        return f"invalid key: {len(key)} characters > {MAX_KEY}"
    if "\0" in key:
        return "invalid key: contains NUL"
    return ""


def _check_key(key: str) -> None:
    reason = key_error(key)
    if reason:
        raise _OpFailed(reason)


def _check_size(size: int, limit: int = MAX_VALUE_BYTES) -> None:
    if size > limit:
        raise _OpFailed(f"value too large: {size} bytes > {limit}")


def _type(name: str) -> ObjectType:
    t = TYPES.get(name)
    if t is None:
        raise _OpFailed(f"unknown type {name[:40]!r}")
    return t


def _mismatch(obj: DdbObject, wanted: str) -> _OpFailed:
    return _OpFailed(f"type mismatch: {obj.key!r} is a {obj.type_name}, not a {wanted}")

