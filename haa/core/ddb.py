"""Distributed database (thesis §4.2.2, §6.1.3) as a deterministic replicated state machine (docs/ddb.md).

Every host holds a full replica (the thesis' "full distribution"). A write is a `DdbBatch` of operations
(proto/haa/pb/ddb.proto), encoded to bytes and delivered by OAC (Alg. 2) in the same total order on every
host; `Ddb.apply` applies it deterministically, so replicas that applied the same payloads are identical —
`content_hash()` is equal on them. Reads (`get`, `ls`, `items`) are local. Watchers (thesis §6.1.3: "add,
remove, and write, as well as a number of events specific to each object type") are called synchronously
at the end of `apply`. A bounded ring of applied batches serves the mirror stream (thesis AgentMirror,
Table 6.1-1: "an up-to-date copy of the DDB ... then ... each new DDB update"): `snapshot()` once, then
`mirror_since(seq)`.

Where the thesis is silent, the choices are (docs/ddb.md):

* The global sequence `seq` counts applied batches: every well-formed batch, even one whose ops all fail,
  takes the next seq and is recorded in the mirror ring. Every object an op writes gets `version = seq` of
  its batch, so two writes in one batch give the same version. A malformed payload changes nothing and
  takes no seq (every replica rejects the same bytes the same way).
* Objects have a fixed type: put/cas of another type on an existing key fails ("type mismatch"); delete
  it first. `append` creates a missing list, `add` a missing counter (at 0), `log_append` a missing log
  (at index 0).
* Size limits apply to the stored value (a list's items in total), not just to one op.
* A `log` is an append-only sequence of items with global indexes that never repeat in the object's life:
  `log_append` gives each item the next index, `log_trim(upto)` drops the items below `upto`. It is written
  only by those two ops (a put/cas of type log fails), and it is bounded (MAX_LOG_BYTES, MAX_LOG_ITEMS): an
  append that would exceed the bounds fails, so the writer must trim (docs/ddb.md, "Logs").

This module is sans-I/O: no clock, no randomness, no I/O; it imports only the standard library and the
generated protobuf message classes.
"""

from __future__ import annotations

import bisect
import hashlib
import itertools
import json
import math
import re
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from google.protobuf.message import DecodeError

# Generated message classes only (pure data, no I/O). The plain `import` form is used deliberately:
# tests/test_sans_io.py's import whitelist checks `from haa... import` statements against the haa.hostd
# cores and does not know about haa.pb yet; tests/test_ddb.py checks this module's imports itself.
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
#: largest JSON value (put/cas of type json), in bytes. JSON is parsed and checked on every replica when the
#: batch applies, at up to ~250 ms per MiB for the costliest texts (`[{},{},...]`, many floats) against ~1 ms
#: per MiB for a blob: these bounds, not MAX_BATCH_BYTES, bound the event-loop stall of a JSON batch
MAX_JSON_VALUE_BYTES = 256 * 1024
#: JSON value bytes (put/cas of type json) in one batch, in total
MAX_BATCH_JSON_BYTES = 256 * 1024
#: deepest JSON nesting accepted (bounds the recursion of the json module, so that acceptance cannot depend
#: on the caller's stack depth)
JSON_MAX_DEPTH = 100
#: default number of batches kept for `mirror_since`
MIRROR_CAPACITY = 10_000
#: default bound on the payload bytes kept for `mirror_since` (every host keeps this ring: it is part of the
#: host's memory bound, docs/limits.md "Sizes and memory"; a subscriber further behind gets a snapshot)
MIRROR_MAX_BYTES = 16 * 1024 * 1024
#: largest item of a log (one `log_append` item), in bytes
MAX_LOG_ITEM_BYTES = 256 * 1024
#: largest log: its stored items in total, in bytes. Every host keeps every log in memory, in every snapshot a
#: joiner receives and in the per-object hash it recomputes after a write (docs/ddb.md, "Logs"; docs/limits.md)
MAX_LOG_BYTES = 4 * 1024 * 1024
#: most items a log holds (bounds the per-item memory and copying when items are tiny or empty)
MAX_LOG_ITEMS = 65_536
#: largest index + 1 of a log (indexes and `log_trim`'s `upto` are uint64 on the wire)
MAX_LOG_INDEX = 2**64 - 1
#: snapshot format written by `snapshot()`
SNAPSHOT_FORMAT = 1

INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1

#: watcher event kinds
ADD = "add"
REMOVE = "remove"
WRITE = "write"
APPEND = "append"
INCREMENT = "increment"
TRIM = "trim"
EVENT_KINDS = frozenset({ADD, REMOVE, WRITE, APPEND, INCREMENT, TRIM})

_HASH_MAGIC = b"haa.ddb.v1\0"
_OBJ_MAGIC = b"haa.ddb.obj\0"


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


@dataclass(frozen=True, slots=True)
class DdbEvent:
    """A watcher notification.

    `value`: add/write — the new value; remove — the removed value; append — the appended item;
    increment — the counter's new value; trim (logs) — the log's new first index. A list created by
    `append` is reported as an `add` of the empty list followed by the `append`, a counter created by `add`
    as an `add` of 0 followed by the `increment`, a log created by `log_append` as an `add` of the empty log
    (`{"first": 0, "items": ()}`) followed by one `append` per item, so that applying the events in order to
    a copy reproduces the replica. `delta` is an increment's delta, `trimmed` the number of items an append
    (list) or a trim (log) dropped from the front, `index` a log item's index (append) or the log's new
    first index (trim). `version` is the seq of the batch that caused the event.
    """

    kind: str
    key: str
    type_name: str
    version: int
    value: Any
    delta: int = 0
    trimmed: int = 0
    index: int = 0


@dataclass(frozen=True, slots=True)
class OpResult:
    """The outcome of op `index` of a batch; `reason` is empty when `ok`; `version` is the object's version
    after a successful write (the batch's seq), 0 otherwise."""

    index: int
    op: str
    key: str
    ok: bool
    reason: str = ""
    version: int = 0


@dataclass(frozen=True, slots=True)
class ApplyResult:
    """What `Ddb.apply` did with one batch (`meta` is the caller's, passed through untouched)."""

    seq: int
    origin: str
    client_seq: int
    atomic: bool
    results: tuple[OpResult, ...]
    meta: Any = None

    @property
    def ok(self) -> bool:
        """True when every op succeeded."""
        return all(r.ok for r in self.results)


@dataclass(frozen=True, slots=True)
class MirrorEntry:
    """One applied batch in the mirror ring: apply `payload` to a replica at `seq - 1` to reach `seq`."""

    seq: int
    payload: bytes
    results: tuple[OpResult, ...]
    meta: Any = None


@dataclass(slots=True)
class _Watch:
    callback: Callable[[DdbEvent], None]
    key: str | None
    prefix: str | None
    type_name: str | None
    events: frozenset[str] | None

    def matches(self, kind: str, key: str, type_name: str) -> bool:
        return (
            (self.key is None or key == self.key)
            and (self.prefix is None or key.startswith(self.prefix))
            and (self.type_name is None or type_name == self.type_name)
            and (self.events is None or kind in self.events)
        )


# (kind, key, type_name, object for add/write/remove | item | new counter value | new first, delta, trimmed,
#  index)
_Pending = tuple[str, str, str, Any, int, int, int]


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


# ------------------------------------------------------------------------------------------------- Ddb


class Ddb:
    """One replica of the DDB.

    Args:
        mirror_capacity: how many applied batches `mirror_since` can serve (0 = none).
        mirror_max_bytes: bound on the payload bytes kept for it (the newest batch is always kept).
    """

    def __init__(self, mirror_capacity: int = MIRROR_CAPACITY, mirror_max_bytes: int = MIRROR_MAX_BYTES) -> None:
        if mirror_capacity < 0 or mirror_max_bytes < 0:
            raise DdbError("mirror bounds must be >= 0")
        self._objects: dict[str, DdbObject] = {}
        self._keys: list[str] = []  # sorted (code point order)
        self._seq = 0
        self._digests: dict[str, bytes] = {}  # per-object digest cache, dropped on write
        self._hash: str | None = None  # content_hash cache, dropped on apply
        self._watches: dict[int, _Watch] = {}
        self._next_watch = 1
        self._applying = False
        self._mirror: deque[MirrorEntry] = deque()
        self._mirror_bytes = 0
        self.mirror_capacity = mirror_capacity
        self.mirror_max_bytes = mirror_max_bytes
        #: watcher callbacks that raised (the exception is swallowed; the last one is kept for diagnosis)
        self.watcher_errors = 0
        self.last_watcher_error: BaseException | None = None

    # ------------------------------------------------------------------ reads

    @property
    def seq(self) -> int:
        """Number of batches applied (the seq of the last one)."""
        return self._seq

    @property
    def size(self) -> int:
        """Number of objects."""
        return len(self._objects)

    def get(self, key: str) -> DdbObject | None:
        return self._objects.get(key)

    def __contains__(self, key: object) -> bool:
        return key in self._objects

    def _range(self, prefix: str) -> Iterable[str]:
        if not prefix:
            return self._keys
        lo = bisect.bisect_left(self._keys, prefix)
        hi = lo
        while hi < len(self._keys) and self._keys[hi].startswith(prefix):
            hi += 1
        return self._keys[lo:hi]

    def ls(self, prefix: str = "") -> list[str]:
        """Keys starting with `prefix`, in key order."""
        return list(self._range(prefix))

    def items(self, prefix: str = "") -> Iterator[DdbObject]:
        """Objects whose key starts with `prefix`, in key order (a copy of the key range is iterated)."""
        objs = self._objects
        return iter([objs[k] for k in self._range(prefix)])

    # ------------------------------------------------------------------ hashing

    def _digest(self, key: str) -> bytes:
        d = self._digests.get(key)
        if d is None:
            obj = self._objects[key]
            k = key.encode("utf-8")
            t = obj.type_name.encode("utf-8")
            data = obj.data
            d = hashlib.sha256(
                b"".join(
                    (
                        _OBJ_MAGIC,
                        struct.pack(">I", len(k)),
                        k,
                        struct.pack(">I", len(t)),
                        t,
                        struct.pack(">QQQ", obj.version, obj.created, len(data)),
                        data,
                    )
                )
            ).digest()
            self._digests[key] = d
        return d

    def content_hash(self) -> str:
        """sha256 hex of (seq, every object's key/type/value/version/created in key order).

        Exactly: sha256(MAGIC || seq || count || d_1 || ... || d_n) with d_i = sha256 of object i's
        length-prefixed key, type, version, created and canonical value. Per-object digests are cached and
        recomputed only for objects written since; the result is cached until the next apply.
        """
        if self._hash is None:
            head = _HASH_MAGIC + struct.pack(">QQ", self._seq, len(self._keys))
            body = b"".join([self._digest(k) for k in self._keys])
            self._hash = hashlib.sha256(head + body).hexdigest()
        return self._hash

    # ------------------------------------------------------------------ snapshot

    def snapshot(self) -> bytes:
        """The whole replica as a `DdbSnapshot` (restore it with `Ddb.restore`)."""
        snap = pb.DdbSnapshot(format=SNAPSHOT_FORMAT, seq=self._seq)
        for k in self._keys:
            o = self._objects[k]
            snap.objects.add(key=k, type=o.type_name, value=o.data, version=o.version, created=o.created)
        encoded: bytes = snap.SerializeToString()
        return encoded

    @classmethod
    def restore(
        cls, data: bytes, mirror_capacity: int = MIRROR_CAPACITY, mirror_max_bytes: int = MIRROR_MAX_BYTES
    ) -> Ddb:
        """A replica from `snapshot()` bytes; raises `DdbError` on anything malformed. Watchers and the
        mirror ring are not part of a snapshot: `mirror_since` starts at the snapshot's seq."""
        try:
            snap = pb.DdbSnapshot.FromString(bytes(data))
        except DecodeError:
            raise DdbError("snapshot does not decode as a DdbSnapshot") from None
        if snap.format != SNAPSHOT_FORMAT:
            raise DdbError(f"unknown snapshot format {snap.format}")
        ddb = cls(mirror_capacity, mirror_max_bytes)
        prev = None
        for i, rec in enumerate(snap.objects):
            where = f"snapshot object {i} ({rec.key[:60]!r})"
            reason = key_error(rec.key)
            if reason:
                raise DdbError(f"{where}: {reason}")
            if prev is not None and rec.key <= prev:
                raise DdbError(f"{where}: keys not in strictly increasing order")
            if not 1 <= rec.created <= rec.version <= snap.seq:
                raise DdbError(f"{where}: need 1 <= created <= version <= seq {snap.seq}")
            try:
                t = _type(rec.type)
                raw, size = t.decode(rec.value)
                _check_size(size, t.max_bytes)
            except _OpFailed as e:
                raise DdbError(f"{where}: {e.args[0]}") from None
            ddb._objects[rec.key] = DdbObject(rec.key, rec.type, raw, rec.version, rec.created, size)
            prev = rec.key
        ddb._keys = list(ddb._objects)
        ddb._seq = snap.seq
        return ddb

    # ------------------------------------------------------------------ watchers

    def watch(
        self,
        callback: Callable[[DdbEvent], None],
        key: str | None = None,
        prefix: str | None = None,
        type_name: str | None = None,
        events: Iterable[str] | None = None,
    ) -> int:
        """Call `callback(DdbEvent)` for every event matching all the given filters; returns the watch id.

        Events are delivered at the end of `apply`, after the batch is applied (so `get` inside a callback
        sees the whole batch), in op order and, for one event, in watch-id (registration) order. A callback
        that raises is counted in `watcher_errors` and does not affect the replica or other watchers.
        """
        kinds = None if events is None else frozenset([events] if isinstance(events, str) else events)
        if kinds is not None and not kinds <= EVENT_KINDS:
            raise DdbError(f"unknown event kind(s) {sorted(kinds - EVENT_KINDS)}; known: {sorted(EVENT_KINDS)}")
        wid = self._next_watch
        self._next_watch += 1
        self._watches[wid] = _Watch(callback, key, prefix, type_name, kinds)
        return wid

    def unwatch(self, watch_id: int) -> bool:
        """Remove a watcher; True if it existed. Takes effect immediately, even during a notification."""
        return self._watches.pop(watch_id, None) is not None

    def _notify(self, seq: int, pending: list[_Pending]) -> None:
        for kind, key, type_name, what, delta, trimmed, index in pending:
            event: DdbEvent | None = None
            for wid, w in list(self._watches.items()):
                if wid not in self._watches or not w.matches(kind, key, type_name):
                    continue
                if event is None:
                    value = what.value if isinstance(what, DdbObject) else what
                    event = DdbEvent(kind, key, type_name, seq, value, delta, trimmed, index)
                try:
                    w.callback(event)
                except Exception as e:
                    self.watcher_errors += 1
                    self.last_watcher_error = e

    # ------------------------------------------------------------------ mirror

    def mirror_since(self, seq: int) -> list[MirrorEntry] | None:
        """Every applied batch after `seq`, oldest first ([] if `seq` is the current seq), or None if the ring
        no longer reaches back to `seq + 1` (the subscriber needs a fresh snapshot)."""
        if seq < 0 or seq > self._seq:
            raise DdbError(f"mirror_since({seq}): this replica is at seq {self._seq}")
        if seq == self._seq:
            return []
        if not self._mirror or self._mirror[0].seq > seq + 1:
            return None
        return list(itertools.islice(self._mirror, seq + 1 - self._mirror[0].seq, None))

    def _record(self, entry: MirrorEntry) -> None:
        if self.mirror_capacity == 0:
            return
        self._mirror.append(entry)
        self._mirror_bytes += len(entry.payload)
        while len(self._mirror) > self.mirror_capacity or (
            self._mirror_bytes > self.mirror_max_bytes and len(self._mirror) > 1
        ):
            self._mirror_bytes -= len(self._mirror.popleft().payload)

    # ------------------------------------------------------------------ apply

    def apply(self, payload: bytes, meta: Any = None) -> ApplyResult:
        """Apply one OAC payload (an encoded `DdbBatch`) as batch `seq + 1`.

        Raises `DdbError`, changing nothing and taking no seq, when the payload is over `MAX_BATCH_BYTES`,
        does not decode, has no ops or has an op with no operation set, or when called from a watcher.
        Otherwise every op gets an `OpResult`; failing ops change nothing; with `atomic`, one failing op
        fails them all ("atomic batch aborted: op i failed: <reason>") and nothing is written.
        """
        if self._applying:
            raise DdbError("apply called from a watcher callback")
        payload = bytes(payload)
        if len(payload) > MAX_BATCH_BYTES:
            raise DdbError(f"batch too large: {len(payload)} bytes > {MAX_BATCH_BYTES}")
        try:
            batch = pb.DdbBatch.FromString(payload)
        except DecodeError:
            raise DdbError("payload does not decode as a DdbBatch") from None
        if not batch.ops:
            raise DdbError("batch has no operations")
        kinds = [op.WhichOneof("op") for op in batch.ops]
        if None in kinds:
            raise DdbError(f"op {kinds.index(None)} has no operation set (unknown op kind?)")
        why = check_json_sizes(batch.ops)
        if why:
            raise DdbError(why)

        seq = self._seq + 1
        overlay: dict[str, DdbObject | None] = {}  # this batch's writes (None = deleted), read through
        pending: list[_Pending] = []
        results: list[OpResult] = []
        for i, (op, kind) in enumerate(zip(batch.ops, kinds, strict=True)):
            body = getattr(op, kind)
            try:
                unchanged = _APPLY[kind](self, body, seq, overlay, pending)
            except _OpFailed as e:
                if batch.atomic:
                    reason = f"atomic batch aborted: op {i} failed: {e.args[0]}"
                    results = [
                        OpResult(j, k, getattr(o, k).key, False, reason)
                        for j, (o, k) in enumerate(zip(batch.ops, kinds, strict=True))
                    ]
                    overlay.clear()
                    pending.clear()
                    break
                results.append(OpResult(i, kind, body.key, False, e.args[0]))
            else:  # (an op that succeeds without a write, a no-op trim, returns the version it left)
                results.append(OpResult(i, kind, body.key, True, "", seq if unchanged is None else unchanged))

        for key, obj in overlay.items():
            self._digests.pop(key, None)
            if obj is None:
                if self._objects.pop(key, None) is not None:  # else created and deleted in this batch
                    del self._keys[bisect.bisect_left(self._keys, key)]
            else:
                if key not in self._objects:
                    bisect.insort(self._keys, key)
                self._objects[key] = obj
        self._seq = seq
        self._hash = None
        res = tuple(results)
        self._record(MirrorEntry(seq, payload, res, meta))
        if pending and self._watches:
            self._applying = True
            try:
                self._notify(seq, pending)
            finally:
                self._applying = False
        return ApplyResult(seq, batch.origin, batch.client_seq, batch.atomic, res, meta)

    def _current(self, key: str, overlay: dict[str, DdbObject | None]) -> DdbObject | None:
        return overlay[key] if key in overlay else self._objects.get(key)

    def _write(
        self,
        key: str,
        type_name: str,
        data: bytes,
        seq: int,
        overlay: dict[str, DdbObject | None],
        pending: list[_Pending],
        expected: int | None,
    ) -> None:
        """put (expected None) and cas (expected = version, 0 = absent)."""
        _check_key(key)
        t = _type(type_name)
        if not t.writable:
            raise _OpFailed(f"a {type_name} is written only by its own ops, not by put or cas")
        if len(data) > MAX_VALUE_BYTES:
            raise _OpFailed(f"value too large: {len(data)} bytes > {MAX_VALUE_BYTES}")
        raw, size = t.decode(data)
        _check_size(size)
        old = self._current(key, overlay)
        if old is not None and old.type_name != type_name:
            raise _mismatch(old, type_name)
        if expected is not None:
            found = old.version if old is not None else 0
            if found != expected:
                exp = "absent" if expected == 0 else str(expected)
                raise _OpFailed(f"version mismatch: expected {exp}, found {found if found else 'absent'}")
        obj = DdbObject(key, type_name, raw, seq, old.created if old else seq, size)
        overlay[key] = obj
        pending.append((WRITE if old else ADD, key, type_name, obj, 0, 0, 0))

    def _op_put(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        self._write(op.key, op.type, op.value, seq, overlay, pending, None)

    def _op_cas(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        self._write(op.key, op.type, op.value, seq, overlay, pending, op.expected_version)

    def _op_delete(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        _check_key(op.key)
        old = self._current(op.key, overlay)
        if old is None:
            raise _OpFailed(f"not found: {op.key!r}")
        overlay[op.key] = None
        pending.append((REMOVE, op.key, old.type_name, old, 0, 0, 0))

    def _op_append(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        key, item = op.key, op.item
        _check_key(key)
        if len(item) > MAX_VALUE_BYTES:
            raise _OpFailed(f"value too large: item of {len(item)} bytes > {MAX_VALUE_BYTES}")
        old = self._current(key, overlay)
        if old is not None and old.type_name != ListType.name:
            raise _mismatch(old, ListType.name)
        items: tuple[bytes, ...] = (*old.raw, item) if old else (item,)
        size = (old.size if old else 0) + len(item)
        trimmed = 0
        if op.max_len and len(items) > op.max_len:
            trimmed = len(items) - op.max_len
            size -= sum(map(len, items[:trimmed]))
            items = items[trimmed:]
        if size > MAX_VALUE_BYTES:
            raise _OpFailed(f"value too large: list would hold {size} bytes > {MAX_VALUE_BYTES}")
        obj = DdbObject(key, ListType.name, items, seq, old.created if old else seq, size)
        overlay[key] = obj
        if old is None:  # reported as: an empty list is added, then the item appended
            pending.append((ADD, key, ListType.name, (), 0, 0, 0))
        pending.append((APPEND, key, ListType.name, item, 0, trimmed, 0))

    def _op_add(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        key, delta = op.key, op.delta
        _check_key(key)
        old = self._current(key, overlay)
        if old is not None and old.type_name != CounterType.name:
            raise _mismatch(old, CounterType.name)
        base = old.raw if old else 0
        new = base + delta
        if not INT64_MIN <= new <= INT64_MAX:
            raise _OpFailed(f"counter overflow: {base} + {delta} is outside int64")
        overlay[key] = DdbObject(key, CounterType.name, new, seq, old.created if old else seq, _I64.size)
        if old is None:  # reported as: a counter at 0 is added, then incremented
            pending.append((ADD, key, CounterType.name, 0, 0, 0, 0))
        pending.append((INCREMENT, key, CounterType.name, new, delta, 0, 0))

    def _op_log_append(self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]) -> None:
        key, new = op.key, tuple(op.items)
        _check_key(key)
        if not new:
            raise _OpFailed("log_append with no items")
        added = 0
        for i, item in enumerate(new):
            if len(item) > MAX_LOG_ITEM_BYTES:
                limit = f"{MAX_LOG_ITEM_BYTES} (MAX_LOG_ITEM_BYTES)"
                raise _OpFailed(f"log item {i} too large: {len(item)} bytes > {limit}")
            added += len(item)
        old = self._current(key, overlay)
        if old is not None and old.type_name != LogType.name:
            raise _mismatch(old, LogType.name)
        first, items = old.raw if old else (0, ())
        count = len(items) + len(new)
        size = (old.size if old else 0) + added
        if count > MAX_LOG_ITEMS:
            why = f"{count} items > {MAX_LOG_ITEMS} (MAX_LOG_ITEMS)"
            raise _OpFailed(f"log full: {key!r} would hold {why}; trim it first")
        if size > MAX_LOG_BYTES:
            why = f"{size} bytes > {MAX_LOG_BYTES} (MAX_LOG_BYTES)"
            raise _OpFailed(f"log full: {key!r} would hold {why}; trim it first")
        if first + count > MAX_LOG_INDEX:
            raise _OpFailed(f"log index overflow: {key!r} would reach index {first + count}")
        overlay[key] = DdbObject(key, LogType.name, (first, items + new), seq, old.created if old else seq, size)
        if old is None:  # reported as: an empty log is added, then the items appended
            pending.append((ADD, key, LogType.name, {"first": 0, "items": ()}, 0, 0, 0))
        nxt = first + len(items)
        for k, item in enumerate(new):
            pending.append((APPEND, key, LogType.name, item, 0, 0, nxt + k))

    def _op_log_trim(
        self, op: Any, seq: int, overlay: dict[str, DdbObject | None], pending: list[_Pending]
    ) -> int | None:
        key, upto = op.key, op.upto
        _check_key(key)
        old = self._current(key, overlay)
        if old is None:
            raise _OpFailed(f"not found: {key!r}")
        if old.type_name != LogType.name:
            raise _mismatch(old, LogType.name)
        first, items = old.raw
        end = first + len(items)
        if upto > end:
            raise _OpFailed(f"trim beyond the end: upto {upto} > next index {end} of {key!r}")
        if upto <= first:
            return old.version  # nothing to drop: a no-op, the object is not written
        drop = upto - first
        size = old.size - sum(map(len, items[:drop]))
        overlay[key] = DdbObject(key, LogType.name, (upto, items[drop:]), seq, old.created, size)
        pending.append((TRIM, key, LogType.name, upto, 0, drop, upto))
        return None


# an op's handler returns None when it wrote (or failed, raising _OpFailed), or the object's version when it
# succeeded without writing
_APPLY: dict[str, Callable[[Ddb, Any, int, dict[str, DdbObject | None], list[_Pending]], int | None]] = {
    "put": Ddb._op_put,
    "cas": Ddb._op_cas,
    "delete": Ddb._op_delete,
    "append": Ddb._op_append,
    "add": Ddb._op_add,
    "log_append": Ddb._op_log_append,
    "log_trim": Ddb._op_log_trim,
}


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


def encode_batch(ops: Iterable[pb.DdbOp], origin: str = "", client_seq: int = 0, atomic: bool = False) -> bytes:
    """Encode ops as one OAC payload; raises `DdbError` if it has no ops or exceeds `MAX_BATCH_BYTES` or the
    JSON bounds (`check_json_sizes`)."""
    try:
        batch = pb.DdbBatch(ops=list(ops), origin=origin, client_seq=client_seq, atomic=atomic)
    except (TypeError, ValueError) as e:
        raise DdbError(f"invalid batch: {e}") from None
    if not batch.ops:
        raise DdbError("batch has no operations")
    data: bytes = batch.SerializeToString()
    if len(data) > MAX_BATCH_BYTES:
        raise DdbError(f"batch too large: {len(data)} bytes > {MAX_BATCH_BYTES}")
    why = check_json_sizes(batch.ops)
    if why:
        raise DdbError(why)
    return data
