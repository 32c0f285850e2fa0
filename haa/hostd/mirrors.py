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
"""

from __future__ import annotations

import asyncio
from collections import deque
from typing import Any

from haa.core.ddb.ddb import ApplyResult, Ddb
from haa.core.membership.globalstate import SeqApplied, TxDdb, TxSeq, decode_tx
from haa.core.membership.membership import AppliedTx, ViewChange

#: a mirror subscriber whose queue holds more payload bytes than this is cut back to a resync (a snapshot)
MIRROR_SUB_MAX_BYTES = 16 << 20


class MirrorSub:
    """One mirror-stream subscriber (see the module docstring)."""

    def __init__(self, views: bool, limit: int = 10_000, limit_bytes: int = MIRROR_SUB_MAX_BYTES) -> None:
        self.views = views
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

    def __init__(self) -> None:
        self.subs: set[MirrorSub] = set()
        self._ddb_ref: Ddb | None = None

    def __bool__(self) -> bool:
        return bool(self.subs)

    def subscribe(self, views: bool, replica: Ddb) -> MirrorSub:
        """A new subscriber, which starts from a snapshot of `replica` (the one it is compared with later)."""
        sub = MirrorSub(views)
        self.subs.add(sub)
        self._ddb_ref = replica
        return sub

    def unsubscribe(self, sub: MirrorSub) -> None:
        self.subs.discard(sub)

    def close(self) -> None:
        for sub in list(self.subs):
            sub.close()

    def applied(self, e: AppliedTx) -> None:
        """An applied global-state transaction: its DDB batches go to every subscriber."""
        if e.result is None or not self.subs:
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
