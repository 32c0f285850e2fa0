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

Where the pieces are: this module holds the replica `Ddb` (apply, watchers, the mirror ring, snapshots) and
what `apply` reports (`ApplyResult`, `OpResult`, `DdbEvent`, `MirrorEntry`); the bounds, the object types and
`DdbObject` are `haa.core.ddb.objects`; the op builders and batch encoding of the client side are
`haa.core.ddb.ops`. The replicated agent table (the thesis' "DDB.agents") is `haa.core.ddb.agenttable`.

This module is sans-I/O: no clock, no randomness, no I/O; it imports only the standard library, the generated
protobuf message classes and its sibling modules.
"""

from __future__ import annotations

import bisect
import hashlib
import itertools
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from google.protobuf.message import DecodeError

# Generated message classes only (pure data, no I/O); tests/test_ddb.py checks the DDB modules' imports.
import haa.pb.ddb_pb2 as pb
from haa.core.ddb.objects import (
    _I64,
    INT64_MAX,
    INT64_MIN,
    MAX_BATCH_BYTES,
    MAX_BATCH_OPS,
    MAX_DDB_BYTES,
    MAX_DDB_KEYS,
    MAX_LOG_BYTES,
    MAX_LOG_INDEX,
    MAX_LOG_ITEM_BYTES,
    MAX_LOG_ITEMS,
    MAX_VALUE_BYTES,
    CounterType,
    DdbError,
    DdbObject,
    ListType,
    LogType,
    _check_key,
    _check_size,
    _mismatch,
    _OpFailed,
    _type,
    key_error,
)
from haa.core.ddb.ops import check_json_sizes

#: default number of batches kept for `mirror_since`
MIRROR_CAPACITY = 10_000
#: default bound on the payload bytes kept for `mirror_since` (every host keeps this ring: it is part of the
#: host's memory bound, docs/limits.md "Sizes and memory"; a subscriber further behind gets a snapshot)
MIRROR_MAX_BYTES = 16 * 1024 * 1024
#: snapshot format written by `snapshot()`
SNAPSHOT_FORMAT = 1

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
        self._bytes = 0  # key characters + stored value bytes, over every object (bounded by MAX_DDB_BYTES)
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

    @property
    def footprint(self) -> int:
        """Key characters + stored value bytes over every object (what MAX_DDB_BYTES bounds)."""
        return self._bytes

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
            ddb._bytes += len(rec.key) + size
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
        does not decode, has no ops, more than `MAX_BATCH_OPS` or an op with no operation set, or when called
        from a watcher. Otherwise every op gets an `OpResult`; failing ops change nothing (an op that would take
        the replica over `MAX_DDB_KEYS` or `MAX_DDB_BYTES` fails, "ddb full: ..."); with `atomic`, one failing
        op fails them all ("atomic batch aborted: op i failed: <reason>") and nothing is written.
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
        if len(batch.ops) > MAX_BATCH_OPS:
            raise DdbError(f"batch of {len(batch.ops)} ops > {MAX_BATCH_OPS} (MAX_BATCH_OPS)")
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
        keys, size = len(self._objects), self._bytes  # what the replica will hold after the ops so far
        for i, (op, kind) in enumerate(zip(batch.ops, kinds, strict=True)):
            body = getattr(op, kind)
            key = body.key
            had = key in overlay
            before = overlay[key] if had else self._objects.get(key)
            n_pending = len(pending)
            try:
                unchanged = _APPLY[kind](self, body, seq, overlay, pending)
                after = overlay[key] if key in overlay else self._objects.get(key)
                if after is not before:
                    d_keys = (after is not None) - (before is not None)
                    d_size = (len(key) + after.size if after else 0) - (len(key) + before.size if before else 0)
                    if (d_keys > 0 and keys + d_keys > MAX_DDB_KEYS) or (d_size > 0 and size + d_size > MAX_DDB_BYTES):
                        if had:
                            overlay[key] = before
                        else:
                            overlay.pop(key, None)
                        del pending[n_pending:]
                        raise _OpFailed(
                            f"ddb full: {keys + d_keys} keys > {MAX_DDB_KEYS} (MAX_DDB_KEYS)" if d_keys > 0
                            and keys + d_keys > MAX_DDB_KEYS else
                            f"ddb full: {size + d_size} bytes > {MAX_DDB_BYTES} (MAX_DDB_BYTES); delete or trim first")
                    keys += d_keys
                    size += d_size
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

        new_keys: list[str] = []
        for key, obj in overlay.items():
            self._digests.pop(key, None)
            old = self._objects.get(key)
            if old is not None:
                self._bytes -= len(key) + old.size
            if obj is None:
                if self._objects.pop(key, None) is not None:  # else created and deleted in this batch
                    del self._keys[bisect.bisect_left(self._keys, key)]
            else:
                if old is None:
                    new_keys.append(key)
                self._objects[key] = obj
                self._bytes += len(key) + obj.size
        # a key inserted into the sorted index costs a memmove of it (~20 us at 200,000 keys); one merge of two
        # sorted runs (timsort) costs ~6 ms there whatever the number of new keys: cheaper from ~300 new keys
        if len(new_keys) > 256:
            new_keys.sort()
            self._keys.extend(new_keys)
            self._keys.sort()
        else:
            for key in new_keys:
                bisect.insort(self._keys, key)
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
