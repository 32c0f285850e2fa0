"""What the host runtime's calls return and raise: the outcomes of proposals, global-state writes and leaves.

`HostRuntime.propose` (static mode, OAC of thesis Alg. 2) answers with a `ProposeResult` or raises
`TransactionAborted`, `ProposeTimeout` or `HostReincarnated`; `HostRuntime.submit` and `ddb_write`
(membership mode: a global-state change committed by OAC and applied by every member, §4.6-4.7) answer with
a `WriteResult` / `DdbWriteResult` or raise `WriteFailed` (`InvalidWrite`: refused before proposing); every
membership-only call raises `NotMembershipMode` on a host running a static peer list. The control service
(haa.hostd.control) maps these exceptions onto gRPC status codes.

Plain data, no behaviour: a leaf module the runtime's parts (haa.hostd.proposals, writes, agentops),
the control service and the agent driver all import, so none of them imports another to name an outcome.
"""

from __future__ import annotations

from dataclasses import dataclass

from haa.core.ddb.ddb import OpResult
from haa.core.messages import TxId


@dataclass(frozen=True)
class ProposeResult:
    """A transaction this host proposed, committed and delivered locally."""

    txid: TxId
    participants: tuple[str, ...]
    propose_to_decide: float
    decide_to_deliver: float


class TransactionAborted(Exception):
    """The transaction was decided abort."""

    def __init__(self, txid: TxId, participants: tuple[str, ...], propose_to_decide: float) -> None:
        super().__init__(f"transaction {txid} aborted")
        self.txid = txid
        self.participants = participants
        self.propose_to_decide = propose_to_decide


class ProposeTimeout(TimeoutError):
    """No local decision and delivery within the timeout (the transaction may still finish later)."""

    def __init__(self, txid: TxId, participants: tuple[str, ...]) -> None:
        super().__init__(f"transaction {txid} not delivered in time")
        self.txid = txid
        self.participants = participants


class HostReincarnated(Exception):
    """This host restarted as a new incarnation while the transaction was open; its outcome is unknown here."""


class WriteFailed(Exception):
    """A global-state change (DDB batch, test payload) was not committed: `reason` says why. A timeout does
    not mean it will never commit."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class InvalidWrite(WriteFailed):
    """A DDB write that is not a valid batch (`haa.core.ddb.ops.check_batch`): refused where it entered the
    host, nothing proposed. `reason` names the bound."""


class NotMembershipMode(Exception):
    """The operation needs group membership (`--core`); this host runs a static peer list (`--peers`)."""


@dataclass(frozen=True)
class WriteResult:
    """A committed global-state change, applied on this host."""

    txid: TxId
    global_seq: int
    result: object | None  # haa.core.ddb.ddb.ApplyResult for DDB batches
    reason: str  # non-empty if the payload was committed but could not be applied (malformed)


@dataclass(frozen=True)
class DdbWriteResult:
    """One `ddb_write` request, committed and applied on this host: its ops' results (in request order) and
    the DDB seq of its batch."""

    txid: TxId
    global_seq: int
    ddb_seq: int
    results: tuple[OpResult, ...]

