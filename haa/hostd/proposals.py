"""Proposals: the OAC transactions this host proposed, their waiters and the latency samples of thesis §5.2.

Two latencies are sampled on the local monotonic clock (the AP-1/AP-2 benchmarks read them through the
control API's `Latencies`, the statistics sampler and /metrics):

* propose -> decide, for every transaction this host proposed: through `HostRuntime.propose` (`start`),
  and those the machines propose on their own — membership changes, sequencer batches, agent-table
  transactions — which `catch_up` dates from the OAC sequence number after each input (so the sample covers
  every transaction this host proposes);
* decide -> deliver, for every transaction delivered here (`Decided` to `Deliver` of the same id).

A coroutine waiting in `HostRuntime.propose` gets its `ProposeResult` (or `TransactionAborted`) from
`decided`/`delivered`; `fail_all` ends every waiter (shutdown, new incarnation). Apart from the futures
this is plain bookkeeping: the caller passes the time in, as with the sans-I/O machines.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

from haa.core.effects import Decided, Deliver
from haa.core.host.hostcore import HostCore
from haa.core.messages import TxId
from haa.core.oac.oac import OrderedAtomicCommit
from haa.hostd.outcomes import ProposeResult, ProposeTimeout, TransactionAborted

#: how many latency samples are kept (oldest dropped first)
MAX_SAMPLES = 100_000
#: transactions whose participant list is remembered (for the replies) before the cache starts over
MAX_PARTICIPANTS_CACHE = 10_000


class Proposals:
    """See the module docstring."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.propose_to_decide: deque[float] = deque(maxlen=MAX_SAMPLES)
        self.decide_to_deliver: deque[float] = deque(maxlen=MAX_SAMPLES)
        self._proposed_at: dict[TxId, float] = {}
        #: the highest OAC transaction number of this incarnation whose proposal time is known
        self._oac_seq_seen = 0
        self._decided_at: dict[TxId, float] = {}
        self._p2d: dict[TxId, float] = {}
        self._participants: dict[TxId, tuple[str, ...]] = {}
        self._waiters: dict[TxId, asyncio.Future[ProposeResult]] = {}

    def participants_of(self, txid: TxId) -> tuple[str, ...]:
        return self._participants.get(txid, (self.name,))

    def start(self, now: float, core: HostCore, payload: bytes, participants: list[str] | None) -> TxId:
        """Propose `payload` to `core`'s OAC at `now` (None participants: this host and every peer it trusts)
        and start timing it; `OacError` (a ValueError) on bad participants."""
        txid = core.propose(now, payload, participants)
        self._proposed_at[txid] = now
        tx = core.oac.txs.get(txid)
        if len(self._participants) > MAX_PARTICIPANTS_CACHE:
            self._participants.clear()
        self._participants[txid] = tuple(q for q, _ in tx.parts) if tx is not None and tx.parts else (self.name,)
        return txid

    def catch_up(self, oac: OrderedAtomicCommit, clock: Callable[[], float]) -> None:
        """Date the transactions the machines proposed themselves since the last input (OAC numbers them);
        `clock` is read only if there are any."""
        seq = oac._seq
        if seq != self._oac_seq_seen:
            now = clock()
            inc = oac.inc
            for s in range(self._oac_seq_seen + 1, seq + 1):
                self._proposed_at.setdefault(TxId(self.name, inc, s), now)
            self._oac_seq_seen = seq

    def decided(self, now: float, e: Decided) -> None:
        txid = e.txid
        t0 = self._proposed_at.pop(txid, None)
        p2d = now - t0 if t0 is not None else 0.0
        if t0 is not None:
            self.propose_to_decide.append(p2d)
        if e.commit:
            self._decided_at[txid] = now
            if t0 is not None:
                self._p2d[txid] = p2d
        else:
            fut = self._waiters.get(txid)
            if fut is not None and not fut.done():
                fut.set_exception(TransactionAborted(txid, self.participants_of(txid), p2d))

    def delivering(self, now: float, e: Deliver) -> float:
        """Sample decide -> deliver of `e` (before it enters the delivered log); returns the sample."""
        t1 = self._decided_at.pop(e.txid, None)
        d2d = now - t1 if t1 is not None else 0.0
        self.decide_to_deliver.append(d2d)
        return d2d

    def delivered(self, txid: TxId, d2d: float) -> None:
        """`txid` is in the delivered log: wake its `wait`er."""
        fut = self._waiters.get(txid)
        p2d = self._p2d.pop(txid, 0.0)
        if fut is not None and not fut.done():
            fut.set_result(ProposeResult(txid, self.participants_of(txid), p2d, d2d))

    def expect(self, txid: TxId) -> asyncio.Future[ProposeResult]:
        """Register a waiter for `txid` (before the input that may decide it is carried out)."""
        fut: asyncio.Future[ProposeResult] = asyncio.get_running_loop().create_future()
        self._waiters[txid] = fut
        return fut

    async def wait(self, txid: TxId, fut: asyncio.Future[ProposeResult], timeout: float) -> ProposeResult:
        """Wait until `txid` was decided and delivered here (`TransactionAborted`, `ProposeTimeout`)."""
        try:
            try:
                return await asyncio.wait_for(fut, timeout)
            except TimeoutError:
                raise ProposeTimeout(txid, self.participants_of(txid)) from None
        finally:
            self._waiters.pop(txid, None)

    def fail_all(self, error: Callable[[TxId], Exception]) -> None:
        """End every waiter with `error(txid)` (shutdown, new incarnation)."""
        for txid, fut in self._waiters.items():
            if not fut.done():
                fut.set_exception(error(txid))

    def reset(self) -> None:
        """A new incarnation: its transactions are numbered from 1 again; the samples stay."""
        self._proposed_at.clear()
        self._decided_at.clear()
        self._p2d.clear()
        self._participants.clear()
        self._oac_seq_seen = 0

    def take_latencies(self, reset: bool) -> tuple[list[float], list[float]]:
        """(decide->deliver, propose->decide) samples; cleared if `reset`."""
        d2d, p2d = list(self.decide_to_deliver), list(self.propose_to_decide)
        if reset:
            self.decide_to_deliver.clear()
            self.propose_to_decide.clear()
        return d2d, p2d
