"""GroupCommit: this host's writes to the global state (thesis §4.6-4.7), with group commit of DDB writes.

A write is a global-state change proposed by OAC to every member and applied by each (`MembershipNode.submit`
-> a `WriteDone` effect once it committed and was applied here, or was given up). Two kinds of callers:

* `submit(payload, kind)`: one change as it is (`kind="ddb"`: an encoded `DdbBatch`; `"test"`: any bytes).
* `ddb_write(ops, atomic)`: DDB ops from the control API's `DdbWrite`/`DdbLoad` and the agents (through the
  agent driver). Group commit: at most `DDB_MAX_INFLIGHT` of this host's DDB batches are in OAC at a time;
  requests arriving meanwhile queue and go out merged into one batch, in arrival order (an op sees the
  effects of the ops before it, as if the requests had been committed one after the other; they share one
  version number), within `DDB_GROUP_MAX_OPS` ops, `DDB_GROUP_MAX_BYTES` bytes and the DDB's JSON budget.
  `atomic` requests always travel alone, so "all or none" covers exactly their ops. Each request gets its
  own ops' results (`DdbWriteResult`), sliced from the batch's.

The runtime hands the group commit what it needs as callables — `propose(payload, req, kind)` feeds the
node's `submit` input and carries out its effects, `gate()` raises when this host cannot write now (static
mode, leaving), `closed()` says the host is stopping or left — and passes each `WriteDone` to `done`. Request
numbers come from `next_req`, shared with the agent operations (one sequence per host, as before the split).
"""

from __future__ import annotations

import asyncio
import functools
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from haa.core.ddb import objects as ddbmod
from haa.core.ddb.ddb import ApplyResult
from haa.core.ddb.ops import check_json_sizes, encode_batch, json_bytes
from haa.core.membership.membership import WriteDone
from haa.hostd.outcomes import DdbWriteResult, WriteFailed, WriteResult

#: at most this many of this host's DDB batches are in OAC at a time (the rest wait and are merged)
DDB_MAX_INFLIGHT = 2
#: bounds of one merged batch (atomic writes always go alone)
DDB_GROUP_MAX_OPS = 2000
DDB_GROUP_MAX_BYTES = ddbmod.MAX_BATCH_BYTES // 2


@dataclass(eq=False)
class _QueuedWrite:
    ops: list[Any]
    atomic: bool
    size: int
    fut: asyncio.Future[DdbWriteResult]
    json: int = 0  # JSON value bytes (a group stays within ddb.MAX_BATCH_JSON_BYTES)
    abandoned: bool = False


class GroupCommit:
    """See the module docstring."""

    def __init__(
        self,
        name: str,
        counters: Counter[str],
        propose: Callable[[bytes, int, str], object],
        gate: Callable[[], None],
        closed: Callable[[], bool],
        next_req: Callable[[], int],
    ) -> None:
        self.name = name
        self.counters = counters
        self._propose = propose
        self._gate = gate
        self._closed = closed
        self._next_req = next_req
        self._writes: dict[int, asyncio.Future[WriteResult]] = {}
        self._queue: deque[_QueuedWrite] = deque()
        self._inflight = 0

    async def submit(self, payload: bytes, kind: str = "ddb", timeout: float = 30.0) -> WriteResult:
        """Propose one global-state change and wait until it is committed and applied here.

        Raises `WriteFailed` (not a member, leaving, gave up after aborts, this host restarted, timeout —
        after a timeout the change may still commit) or `NotMembershipMode`."""
        self._gate()
        req = self._next_req()
        fut: asyncio.Future[WriteResult] = asyncio.get_running_loop().create_future()
        self._writes[req] = fut
        self.counters["writes_submitted"] += 1
        try:
            self._propose(payload, req, kind)
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise WriteFailed(f"not committed within {timeout:g} s (it may still commit)") from None
        finally:
            self._writes.pop(req, None)

    async def ddb_write(self, ops: list[Any], atomic: bool = False, timeout: float = 30.0) -> DdbWriteResult:
        """Write DDB ops (`haa.core.ddb.ops.put/...`) to the group through the group commit (module docstring)
        and wait until they are committed and applied here. Raises `WriteFailed` (see `submit`) or
        `NotMembershipMode`."""
        self._gate()
        if not ops:
            raise WriteFailed("empty batch")
        size = sum(op.ByteSize() for op in ops)
        if size > ddbmod.MAX_BATCH_BYTES:  # checked before anything is queued (docs/limits.md)
            raise WriteFailed(f"batch of {size} bytes > {ddbmod.MAX_BATCH_BYTES} (MAX_BATCH_BYTES)")
        why = check_json_sizes(ops)
        if why:
            raise WriteFailed(why)
        fut: asyncio.Future[DdbWriteResult] = asyncio.get_running_loop().create_future()
        fut.add_done_callback(_retrieve)
        q = _QueuedWrite(list(ops), atomic, size, fut, sum(json_bytes(op) for op in ops))
        self._queue.append(q)
        self.counters["ddb_writes"] += 1
        self._flush()
        try:
            return await asyncio.wait_for(asyncio.shield(fut), timeout)
        except TimeoutError:
            q.abandoned = True  # not proposed yet: it never will be
            raise WriteFailed(f"not committed within {timeout:g} s (it may still commit)") from None

    def done(self, e: WriteDone) -> None:
        """A `WriteDone` effect: the write `e.req` committed and was applied here, or was given up."""
        if not isinstance(e.req, int):  # not one of ours (our requests are numbers)
            return
        fut = self._writes.pop(e.req, None)
        if fut is None or fut.done():
            return
        if e.ok and e.txid is not None:
            fut.set_result(WriteResult(e.txid, e.seq, e.result, e.reason))
        else:
            fut.set_exception(WriteFailed(e.reason))

    def fail_all(self, error: Callable[[], Exception]) -> None:
        """End every write in OAC with `error()` (shutdown, new incarnation); queued ones follow (`_flush`)."""
        for fut in list(self._writes.values()):
            if not fut.done():
                fut.set_exception(error())

    def forget(self) -> None:
        """A new incarnation: the old one's requests will never get a `WriteDone`."""
        self._writes.clear()

    def _flush(self) -> None:
        queue = self._queue
        if self._closed():
            while queue:
                q = queue.popleft()
                if not q.fut.done():
                    q.fut.set_exception(WriteFailed("this host is stopping or left the group"))
            return
        loop = asyncio.get_running_loop()
        while queue and self._inflight < DDB_MAX_INFLIGHT:
            group = self._take_group()
            if not group:
                return
            ops = [op for q in group for op in q.ops]
            try:
                payload = encode_batch(ops, origin=self.name, atomic=group[0].atomic)
            except ddbmod.DdbError as e:  # (ddb_write checked each request; a group of them stays in bounds)
                for q in group:
                    if not q.fut.done():
                        q.fut.set_exception(WriteFailed(str(e)))
                continue
            req = self._next_req()
            gfut: asyncio.Future[WriteResult] = loop.create_future()
            self._writes[req] = gfut
            self._inflight += 1
            self.counters["ddb_batches"] += 1
            self.counters["ddb_merged_writes"] += len(group) - 1
            gfut.add_done_callback(functools.partial(self._group_done, group))
            self._propose(payload, req, "ddb")

    def _take_group(self) -> list[_QueuedWrite]:
        """The next requests of the queue that fit one batch (an atomic one alone)."""
        queue = self._queue
        group: list[_QueuedWrite] = []
        n_ops = size = json_size = 0
        while queue:
            q = queue[0]
            if q.abandoned or q.fut.done():
                queue.popleft()
                continue
            if group and (
                q.atomic
                or n_ops + len(q.ops) > DDB_GROUP_MAX_OPS
                or size + q.size > DDB_GROUP_MAX_BYTES
                or json_size + q.json > ddbmod.MAX_BATCH_JSON_BYTES
            ):
                break
            queue.popleft()
            group.append(q)
            n_ops += len(q.ops)
            size += q.size
            json_size += q.json
            if q.atomic:
                break
        return group

    def _group_done(self, group: list[_QueuedWrite], gfut: asyncio.Future[WriteResult]) -> None:
        self._inflight -= 1
        exc = gfut.exception() if not gfut.cancelled() else WriteFailed("cancelled")
        res = None if exc is not None else gfut.result()
        applied = res.result if res is not None else None
        if exc is None and not isinstance(applied, ApplyResult):
            exc = WriteFailed(res.reason if res is not None and res.reason else "committed but not applied")
        if exc is not None:
            reason = getattr(exc, "reason", None) or str(exc)
            for q in group:
                if not q.fut.done():
                    q.fut.set_exception(WriteFailed(reason))
        else:
            assert res is not None and isinstance(applied, ApplyResult)
            i = 0
            for q in group:
                n = len(q.ops)
                if not q.fut.done():
                    q.fut.set_result(
                        DdbWriteResult(res.txid, res.global_seq, applied.seq, applied.results[i : i + n], len(group))
                    )
                i += n
        self._flush()


def _retrieve(fut: asyncio.Future[Any]) -> None:
    """Mark a future's exception as retrieved (its waiter may have timed out and gone)."""
    if not fut.cancelled():
        fut.exception()

