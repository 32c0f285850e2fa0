"""Writes: this host's writes to the global state (thesis §4.6-4.7), from the control API and the agents.

A write is a global-state change committed by OAC and applied by every member: `submit` feeds the node's
`Submit` input, and the node's `WriteDone` effect (`done`) answers it once it committed and was applied here, or
was given up. Two kinds of callers:

* `submit(payload, kind)`: one change as it is (`kind="ddb"`: an encoded `DdbBatch`; `"test"`: any bytes).
* `ddb_write(ops, atomic)`: DDB ops from the control API's `DdbWrite`/`DdbLoad` and the agents (through the
  agent driver). This is where a DDB write enters the host, and the one place it is validated
  (`haa.core.ddb.ops.encode_batch` runs `check_batch`: ops, bytes, JSON): an invalid batch raises
  `InvalidWrite` and nothing is proposed. Each request becomes one `DdbBatch`, so `atomic` ("all or none")
  covers exactly its ops and its results are its own.

There is one batching layer, in the core: the node hands DDB and test writes to the sequencer
(`haa.core.membership.sequencer`), which batches every member's writes into one OAC transaction and bounds how
many are in OAC at once. This module only keeps a future per request.

The runtime hands `Writes` what it needs as callables — `propose(payload, req, kind, cost)` feeds the node's
`Submit` input and carries out its effects (`cost`: the DDB ops, what the sequencer bounds a transaction by),
`gate()` raises when this host cannot write now (static mode, leaving), `closed()` says the host is stopping or
left. Request numbers come from `next_req`, shared with the agent operations (one sequence per host).
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable
from typing import Any

from haa.core.ddb import objects as ddbmod
from haa.core.ddb.ddb import ApplyResult
from haa.core.ddb.ops import encode_batch
from haa.core.membership.membership import WriteDone
from haa.hostd.outcomes import DdbWriteResult, InvalidWrite, WriteFailed, WriteResult


class Writes:
    """See the module docstring."""

    def __init__(
        self,
        name: str,
        counters: Counter[str],
        propose: Callable[[bytes, int, str, int], object],
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

    async def submit(self, payload: bytes, kind: str = "ddb", timeout: float = 30.0, cost: int = 1) -> WriteResult:
        """Propose one global-state change (`cost`: its apply cost, the DDB ops it carries) and wait until it is
        committed and applied here.

        Raises `WriteFailed` (not a member, leaving, gave up after aborts, this host restarted, timeout —
        after a timeout the change may still commit) or `NotMembershipMode`."""
        self._gate()
        if self._closed():
            raise WriteFailed("this host is stopping or left the group")
        req = self._next_req()
        fut: asyncio.Future[WriteResult] = asyncio.get_running_loop().create_future()
        self._writes[req] = fut
        self.counters["writes_submitted"] += 1
        try:
            self._propose(payload, req, kind, cost)
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise WriteFailed(f"not committed within {timeout:g} s (it may still commit)") from None
        finally:
            self._writes.pop(req, None)

    async def ddb_write(self, ops: list[Any], atomic: bool = False, timeout: float = 30.0) -> DdbWriteResult:
        """Write DDB ops (`haa.core.ddb.ops.put/...`) to the group as one batch and wait until it is committed
        and applied here. Raises `InvalidWrite` (not a valid batch: nothing proposed), `WriteFailed` (see
        `submit`) or `NotMembershipMode`."""
        self._gate()
        try:
            payload = encode_batch(ops, origin=self.name, atomic=atomic)
        except ddbmod.DdbError as e:
            raise InvalidWrite(str(e)) from None
        self.counters["ddb_writes"] += 1
        res = await self.submit(payload, "ddb", timeout, cost=len(ops))
        applied = res.result
        if not isinstance(applied, ApplyResult):  # (a DdbError on apply: refused identically on every replica)
            raise WriteFailed(res.reason or "committed but not applied")
        return DdbWriteResult(res.txid, res.global_seq, applied.seq, applied.results)

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
        """End every open write with `error()` (shutdown, new incarnation)."""
        for fut in list(self._writes.values()):
            if not fut.done():
                fut.set_exception(error())

    def forget(self) -> None:
        """A new incarnation: the old one's requests will never get a `WriteDone`."""
        self._writes.clear()
