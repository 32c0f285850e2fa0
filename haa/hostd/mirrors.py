"""Mirrors: the subscribers of the control API's `Mirror` stream (the thesis' AgentMirror, §4.7), fed by the runtime.

A subscriber (`MirrorSub`) is a queue of items the control service turns into `MirrorEvent`s:

* `("batch", ddb_seq, payload, global_seq)` — a DDB batch applied here (alone, or inside a sequencer batch:
  each applied DDB entry of it, in order), from the `AppliedTx` effects;
* `("view", ViewChange)` — a view change (Alg. 3), for subscribers that asked for views;
* `("resync",)` — send a fresh snapshot: the replica object was replaced (a joiner installed its sponsor's
  state, a new incarnation), or the subscriber fell more than `limit` items / `limit_bytes` payload bytes
  behind (its queue is cut back to this one item: bounded memory, docs/limits.md).

`Mirrors` holds the set of subscribers and turns effects into items; it only does work while someone
subscribes. `MirrorSub.get` is the one coroutine (the stream waits on it).

Bounds (docs/limits.md): at most `MAX_MIRRORS` streams per host and `MAX_MIRRORS_PER_CLIENT` per client
address (`subscribe` raises `MirrorRefused`); the control service ends a stream whose client has not taken an
event for `MIRROR_SEND_TIMEOUT` (what gRPC holds for it is freed). A new subscriber's snapshot is built once
and shared (`snapshot`): serialized once, reused for `SNAPSHOT_REUSE_S` by later subscribers, which catch up
from the replica's mirror ring — so many subscribers, or a client opening and dropping streams, cost one
snapshot a second, not one each.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from haa.core.ddb.ddb import ApplyResult, Ddb, MirrorEntry
from haa.core.membership.globalstate import SeqApplied, TxDdb, TxSeq, decode_tx
from haa.core.membership.membership import AppliedTx, ViewChange
from haa.hostd.outlink import length_delimited
from haa.pb import control_pb2 as cpb

#: a mirror subscriber whose queue holds more payload bytes than this is cut back to a resync (a snapshot)
MIRROR_SUB_MAX_BYTES = 16 << 20
#: mirror streams one host serves at once (each may hold a snapshot in gRPC's buffers until its client reads it)
MAX_MIRRORS = 64
#: ... and one client address of them
MAX_MIRRORS_PER_CLIENT = 16
#: a stream whose client has taken no event for this long is ended (status RESOURCE_EXHAUSTED)
MIRROR_SEND_TIMEOUT = 10.0
#: a snapshot built for one subscriber serves later ones for this long (they catch up from the mirror ring)
SNAPSHOT_REUSE_S = 1.0


class MirrorRefused(Exception):
    """A new mirror stream over one of the bounds; the text names it."""


@dataclass(frozen=True)
class Snapshot:
    """A replica's snapshot as one serialized `MirrorEvent` (snapshot and its content hash), at `seq`."""

    replica: Ddb
    seq: int
    event: bytes
    built: float


def snapshot_event(replica: Ddb) -> bytes:
    """`MirrorEvent(snapshot=<the replica's>, ddb_hash=...)` serialized, without decoding the snapshot bytes
    into message objects (field 1, length-delimited, is the `DdbSnapshot` as `Ddb.snapshot` encodes it)."""
    event = length_delimited(cpb.MirrorEvent.SNAPSHOT_FIELD_NUMBER, replica.snapshot())
    return event + cpb.MirrorEvent(ddb_hash=replica.content_hash()).SerializeToString()


class MirrorSub:
    """One mirror-stream subscriber (see the module docstring)."""

    def __init__(
        self, views: bool, limit: int = 10_000, limit_bytes: int = MIRROR_SUB_MAX_BYTES, client: str = ""
    ) -> None:
        self.views = views
        self.client = client
        self.limit = limit
        self.limit_bytes = limit_bytes
        self.queue: deque[tuple[Any, ...]] = deque()
        self.bytes = 0  # payload bytes of the queued batches
        self.closed = False
        self._event = asyncio.Event()

    def push(self, item: tuple[Any, ...]) -> None:
        size = len(item[2]) if item[0] == "batch" else 0
        if len(self.queue) >= self.limit or (self.queue and self.bytes + size > self.limit_bytes):
            self.queue.clear()
            self.bytes = 0
            item, size = ("resync",), 0
        self.queue.append(item)
        self.bytes += size
        self._event.set()

    def close(self) -> None:
        self.closed = True
        self._event.set()

    async def get(self) -> tuple[Any, ...] | None:
        """The next item, or None once closed."""
        while not self.queue:
            if self.closed:
                return None
            self._event.clear()
            await self._event.wait()
        item = self.queue.popleft()
        if item[0] == "batch":
            self.bytes -= len(item[2])
        return item


class Mirrors:
    """The subscribers of one host (see the module docstring)."""

    def __init__(self, max_subs: int = MAX_MIRRORS, max_per_client: int = MAX_MIRRORS_PER_CLIENT) -> None:
        self.subs: set[MirrorSub] = set()
        self.max_subs = max_subs
        self.max_per_client = max_per_client
        self._ddb_ref: Ddb | None = None
        self._snap: Snapshot | None = None

    def __bool__(self) -> bool:
        return bool(self.subs)

    def subscribe(self, views: bool, replica: Ddb, client: str = "") -> MirrorSub:
        """A new subscriber, which starts from a snapshot of `replica` (the one it is compared with later).
        `client`: its address without the port; raises `MirrorRefused` over `max_subs` or `max_per_client`."""
        if len(self.subs) >= self.max_subs:
            raise MirrorRefused(f"this host serves {len(self.subs)} mirror streams, its bound (MAX_MIRRORS)")
        if client and sum(1 for s in self.subs if s.client == client) >= self.max_per_client:
            raise MirrorRefused(f"{client} has {self.max_per_client} mirror streams here, the bound per client "
                                "(MAX_MIRRORS_PER_CLIENT)")
        sub = MirrorSub(views, client=client)
        self.subs.add(sub)
        self._ddb_ref = replica
        return sub

    def snapshot(self, replica: Ddb) -> tuple[Snapshot, list[MirrorEntry]]:
        """A snapshot of `replica` for a new subscriber, and the applied batches since it (oldest first): the
        last one built if it is of this replica, at most `SNAPSHOT_REUSE_S` old and the mirror ring still
        reaches back to it; else a new one."""
        snap = self._snap
        now = time.monotonic()
        if snap is not None and snap.replica is replica and now - snap.built <= SNAPSHOT_REUSE_S:
            since = replica.mirror_since(snap.seq)
            if since is not None:
                return snap, since
        snap = self._snap = Snapshot(replica, replica.seq, snapshot_event(replica), now)
        return snap, []

    def unsubscribe(self, sub: MirrorSub) -> None:
        self.subs.discard(sub)
        self._drop_stale()

    def _drop_stale(self) -> None:
        """Nobody subscribes and the snapshot can serve no one any more: do not keep a replica's worth of bytes."""
        if not self.subs and self._snap is not None and time.monotonic() - self._snap.built > SNAPSHOT_REUSE_S:
            self._snap = None

    def close(self) -> None:
        for sub in list(self.subs):
            sub.close()

    def applied(self, e: AppliedTx) -> None:
        """An applied global-state transaction: its DDB batches go to every subscriber."""
        if not self.subs:
            self._drop_stale()
            return
        if e.result is None:
            return
        if e.kind == "ddb":
            tx = decode_tx(e.payload)
            if isinstance(tx, TxDdb) and isinstance(e.result, ApplyResult):
                self._push(("batch", e.result.seq, tx.data, e.seq))
        elif e.kind == "seq":  # a sequencer batch: every DDB batch in it that was applied, in order
            tx = decode_tx(e.payload)
            if isinstance(tx, TxSeq) and isinstance(e.result, tuple):
                for entry, r in zip(tx.entries, e.result, strict=True):
                    if isinstance(r, SeqApplied) and r.applied and r.kind == "ddb" and r.result is not None:
                        inner = decode_tx(entry.tx)
                        if isinstance(inner, TxDdb) and isinstance(r.result, ApplyResult):
                            self._push(("batch", r.result.seq, inner.data, e.seq))

    def view(self, e: ViewChange) -> None:
        for sub in list(self.subs):
            if sub.views:
                sub.push(("view", e))

    def check_replica(self, replica: Ddb | None) -> None:
        """A joiner that installed its sponsor's state, or a new incarnation, has a new replica object:
        subscribers need a fresh snapshot."""
        if replica is None or replica is self._ddb_ref:
            return
        self._ddb_ref = replica
        for sub in list(self.subs):
            sub.push(("resync",))

    def _push(self, item: tuple[Any, ...]) -> None:
        for sub in list(self.subs):
            sub.push(item)
