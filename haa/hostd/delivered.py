"""DeliveredLog: every transaction this host process delivered, in delivery order, with a running hash chain.

Each entry is `(index, txid, order, payload, chain_hash)` with

    chain_i = sha256(chain_{i-1} + "\\n" + "host.inc.seq" + "\\n" + payload)   (hex; chain_{-1} = 64 zeros)

so two hosts have delivered the same sequence iff their last hashes are equal (the OAC total order of
thesis §4.5, checked end to end by the tests and `haactl` through `Status`/`Deliveries`). Memory is bounded:
at most `MAX_DELIVERED` entries and `MAX_DELIVERED_BYTES` payload bytes are kept; when either is exceeded
the oldest entries are dropped until half of each is left (the newest always stays). The count and the
chain go on: `base` is the index of the first entry still kept, `count` the number ever delivered.

`wait(count)` lets a coroutine (the control service's `Deliveries` stream) sleep until the log grows. Apart
from that asyncio event the log is plain data (tests drive it without a loop).
"""

from __future__ import annotations

import asyncio
import hashlib
from dataclasses import dataclass

from haa.core.messages import TxId

GENESIS_HASH = "0" * 64
#: the delivered log keeps at most this many entries in memory (the older half is dropped when it is full;
#: the hash chain and the count go on)
MAX_DELIVERED = 200_000
#: ... and at most this many payload bytes (a few maximum-size DDB batches; the older entries are dropped
#: until half of it is left): part of the host's memory bound (docs/limits.md, "Sizes and memory")
MAX_DELIVERED_BYTES = 16 << 20


def chain_hash(prev: str, txid: TxId, payload: bytes) -> str:
    """One step of the delivered-log hash chain (see the module docstring)."""
    h = hashlib.sha256(f"{prev}\n{txid.host}.{txid.inc}.{txid.seq}\n".encode())
    h.update(payload)
    return h.hexdigest()


@dataclass(slots=True)
class DeliveredEntry:
    """One delivered transaction: its index in this process's delivery order, id, OAC order number, payload
    and the chain hash up to and including it."""

    index: int
    txid: TxId
    order: int
    payload: bytes
    chain_hash: str


class DeliveredLog:
    """See the module docstring."""

    def __init__(self, max_entries: int | None = None, max_bytes: int | None = None) -> None:
        self.max_entries = MAX_DELIVERED if max_entries is None else max_entries
        self.max_bytes = MAX_DELIVERED_BYTES if max_bytes is None else max_bytes
        self.entries: list[DeliveredEntry] = []
        self.base = 0  # index of entries[0]: the ones before it were dropped
        self.bytes = 0  # payload bytes in `entries`
        self.hash = GENESIS_HASH
        self._event = asyncio.Event()

    @property
    def count(self) -> int:
        """Transactions delivered since this process started (the log keeps the latest ones)."""
        return self.base + len(self.entries)

    def append(self, txid: TxId, order: int, payload: bytes) -> DeliveredEntry:
        """Record one delivery, extend the chain and wake every `wait`er."""
        self.hash = chain_hash(self.hash, txid, payload)
        entry = DeliveredEntry(self.count, txid, order, payload, self.hash)
        self.entries.append(entry)
        self.bytes += len(payload)
        if len(self.entries) > self.max_entries or self.bytes > self.max_bytes:
            self._trim()
        ev = self._event
        self._event = asyncio.Event()
        ev.set()
        return entry

    def get(self, index: int) -> DeliveredEntry:
        """The entry with this index (IndexError if it was dropped or is not there yet)."""
        if index < self.base:
            raise IndexError(f"entries before {self.base} are no longer kept")
        return self.entries[index - self.base]

    async def wait(self, count: int) -> None:
        """Return once at least `count` transactions were delivered."""
        while self.count < count:
            await self._event.wait()

    def _trim(self) -> None:
        """Drop the oldest entries until at most half of `max_entries` entries and half of `max_bytes`
        payload bytes are left (the newest entry always stays)."""
        log_ = self.entries
        left = self.bytes
        drop = max(0, len(log_) - self.max_entries // 2)
        for entry in log_[:drop]:
            left -= len(entry.payload)
        while drop < len(log_) - 1 and left > self.max_bytes // 2:
            left -= len(log_[drop].payload)
            drop += 1
        del log_[:drop]
        self.base += drop
        self.bytes = left
