"""The vocabulary the membership layer adds to the core's: its effects and its typed timer keys.

`haa.core.membership.membership.MembershipNode` (thesis Alg. 3, §4.6) and the machines it is composed of
(`haa.core.membership.sequencer`, `haa.core.membership.formation`) produce, next to the core's effects of
`haa.core.effects`:

* `Connect` — open a link to a host (Alg. 3 "open connection to", ll. 37, 53, 66);
* `ViewChange` — the member list changed (ll. 136-151, 166-179 applied here);
* `AppliedTx` — the n-th global transaction was applied (the global state's total order);
* `WriteDone` — a global-state change requested with `MembershipNode.submit` committed or failed;
* `Left` — this host's voluntary leave committed (l. 16).

`NodeEffect` is their closed union. The drivers (`haa.hostd.runtime`, `haa.lab.dsim`) carry them out.

`NodeTimer` is the key of every timer the membership layer sets (the core's own keys are `("hb"|"fd", peer)`
and `("excl", peer, inc)`). It is a frozen dataclass, hashable and ordered, whose printed form is the
tuple `('m', what)` the node used before typed keys: the simulator feeds `str(key)` of every fired timer into
its trace hash (`haa.lab.dsim.cluster`), so the traces stay byte-identical.

This module does no I/O; it imports only the host messages.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Literal

from haa.core.messages import Member, TxId

Proc = tuple[str, int]

#: what a membership timer is for: the first core process' discovery wait (Alg. 3 l. 41), FORMATION_TIMEOUT
#: (l. 45), the applicant's re-application, a new member's catch-up wait, updateMembership's retry (l. 109),
#: and the sequencer's re-forwarding of pending writes (docs/oac.md)
TimerWhat = Literal["discovery", "formation", "reapply", "catchup", "retry", "seqretry"]


@dataclass(frozen=True, slots=True, order=True)
class NodeTimer:
    """A timer of the membership layer. Printed as the tuple `('m', what)` (see the module docstring)."""

    what: TimerWhat

    def __repr__(self) -> str:
        return f"('m', {self.what!r})"

    __str__ = __repr__


@dataclass(slots=True)
class Connect:
    """Open (or keep) a link to host `name` at `addr` (Alg. 3 "open connection to")."""

    name: str
    addr: str


@dataclass(slots=True)
class ViewChange:
    """This host applied a change of the member list."""

    view: int
    seq: int
    members: tuple[Member, ...]
    removed: tuple[Member, ...]
    added: tuple[Member, ...]
    txid: TxId
    group: str  # id of the group (the transaction that created it)
    correct: bool  # the group is correct (more than c_f core processes have been members)


@dataclass(slots=True)
class AppliedTx:
    """This host applied the `seq`-th global transaction; `state_hash` is its content hash afterwards
    (only computed when `NodeConfig.hash_every_apply` is set: the simulator's prefix-consistency check);
    `view` and `front` (the first member, None once the group dissolved) are the view right after it: the
    node may apply more transactions before its effects are carried out."""

    seq: int
    txid: TxId
    kind: str
    payload: bytes
    state_hash: str
    result: object | None
    view: int = 0
    front: Proc | None = None


@dataclass(slots=True)
class WriteDone:
    """A global-state change requested with `submit` was committed (`ok`) or given up (`reason`)."""

    req: Hashable
    ok: bool
    txid: TxId | None
    seq: int
    reason: str
    result: object | None = None


@dataclass(slots=True)
class Left:
    """The voluntary leave of this host was committed (Alg. 3 l. 16): it stops taking part."""


#: the effects the node adds to the core's (`haa.core.effects.Effect`)
NodeEffect = Connect | ViewChange | AppliedTx | WriteDone | Left
