"""Deliberately broken variants of the algorithms, to prove that the checkers can fail.

Each mutation patches `OrderedAtomicCommit` (or the failure detector) in the current process and returns a
function that undoes the patch. The verifier applies a mutation before it forks its workers
(`haactl verify oac --mutate NAME`), and `tests/test_mutations.py` asserts that every mutation is caught.

* `skip-order-gate`  Alg. 2 l. 37 without the order condition: a committed transaction is delivered as soon
                     as it is decided. Breaks AC-Total-Order.
* `thesis-close`     Alg. 2 l. 41 exactly as printed: a decide rebroadcast counts for closing even when its
                     sender has not yet passed l. 38. Breaks AC-Total-Order (docs/oac.md, "the closing
                     gate") — the verifier found this hole in the thesis' algorithm.
* `no-order-confirm` Alg. 2 l. 22-25 skipped: a participant accepts the proposer's order even when it
                     conflicts with a transaction it already holds. Breaks AC-Total-Order.
* `commit-on-quorum` Alg. 2 l. 51 with a quorum instead of all n estimates: pre-commit without every vote.
                     Breaks AC-Uniform-Validity.
* `never-precommit`  Alg. 2 l. 51-52 removed: the coordinator never proposes pre-commit. Breaks
                     AC-Non-Triviality.
* `deaf-detector`    the failure detector never suspects a process that stopped sending heartbeats
                     (Alg. 1 l. 17-18 removed). Breaks UFD-Completeness.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable

from haa.hostd import oac as oac_mod
from haa.hostd import ufd as ufd_mod
from haa.hostd.effects import Deliver
from haa.hostd.messages import OacDecide

Undo = Callable[[], None]


def _patch(obj: object, name: str, new: object) -> Undo:
    old = getattr(obj, name)
    setattr(obj, name, new)
    return lambda: setattr(obj, name, old)


def skip_order_gate() -> Undo:
    cls = oac_mod.OrderedAtomicCommit

    def deliver_ready(self: oac_mod.OrderedAtomicCommit) -> None:
        for tx in list(self.txs.values()):
            if tx.state == oac_mod.DECIDED and tx.commit and tx.content:
                tx.state = oac_mod.DONE
                self.delivered += 1
                self._emit(Deliver(tx.id, tx.order, tx.payload))
                tx.decide_from.add(self.name)
                if tx.relayed_decide:
                    self._announce_delivered(tx)
                self._close_check(tx)
        while self._gate and self._gate[0][1] not in self.txs:
            heapq.heappop(self._gate)

    return _patch(cls, "_deliver_ready", deliver_ready)


def thesis_close() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._decide_msg

    def decide_msg(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> OacDecide:
        msg = original(self, tx)
        msg.delivered = True  # "received (id, q, -, -, outcome, decide) from q" as printed in l. 41
        return msg

    undo_msg = _patch(cls, "_decide_msg", decide_msg)
    undo_announce = _patch(cls, "_announce_delivered", lambda self, tx: None)  # l. 36 is the only rebroadcast

    def undo() -> None:
        undo_announce()
        undo_msg()

    return undo


def no_order_confirm() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._highest

    def highest(self: oac_mod.OrderedAtomicCommit, exclude: object = None) -> object:
        if exclude is not None:  # the l. 22 confirmation in atomicCommit sees no conflict
            return None
        return original(self, exclude)  # type: ignore[arg-type]

    return _patch(cls, "_highest", highest)


def commit_on_quorum() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._progress

    def progress(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> None:
        if tx.phase == oac_mod.C1 and tx.state == oac_mod.UNDECIDED:
            got = tx.ests.get((tx.order, tx.r))
            if got is not None and len(got) >= tx.quorum:
                for q, _qi in tx.parts:  # pretend the missing estimates arrived and said yes
                    got.setdefault(q, (False, 0))
        original(self, tx)

    return _patch(cls, "_progress", progress)


def never_precommit() -> Undo:
    cls = oac_mod.OrderedAtomicCommit
    original = cls._progress

    def progress(self: oac_mod.OrderedAtomicCommit, tx: oac_mod._Tx) -> None:
        if tx.phase == oac_mod.C1 and tx.state == oac_mod.UNDECIDED:
            got = tx.ests.get((tx.order, tx.r))
            if got is not None and len(got) == tx.n:  # hide one estimate: l. 51 never holds
                q = next(q for q, _qi in tx.parts if q != self.name)
                saved = got.pop(q)
                try:
                    if all(q2 in got or self._suspected(q2, qi) for q2, qi in tx.parts if q2 != q):
                        tx.est = False
                        prop = oac_mod.OacProposal(tx.id, tx.order, tx.r, False)
                        self._send_all(tx, prop)
                        tx.props[(tx.order, tx.r)] = False
                        tx.phase = oac_mod.P2
                finally:
                    got[q] = saved
        original(self, tx)

    return _patch(cls, "_progress", progress)


def deaf_detector() -> Undo:
    return _patch(ufd_mod.HeartbeatObserver, "on_deadline", lambda self, now: False)


MUTATIONS: dict[str, tuple[Callable[[], Undo], str, str]] = {
    # name: (apply, algorithm to verify with, property the verifier must report)
    "skip-order-gate": (skip_order_gate, "oac", "AC-Total-Order"),
    "thesis-close": (thesis_close, "oac", "AC-Total-Order"),
    "no-order-confirm": (no_order_confirm, "oac", "AC-Total-Order"),
    "commit-on-quorum": (commit_on_quorum, "oac", "AC-Uniform-Validity"),
    "never-precommit": (never_precommit, "oac", "AC-Non-Triviality"),
    "deaf-detector": (deaf_detector, "ufd", "UFD-Completeness"),
}


def apply(name: str) -> Undo:
    try:
        fn = MUTATIONS[name][0]
    except KeyError:
        raise ValueError(f"unknown mutation {name!r}; choose from {sorted(MUTATIONS)}") from None
    return fn()
