"""State transfer: a new member gets the global state and catches up with the group (thesis Alg. 3).

Alg. 3 (thesis L2358-2565; described at L698-706) makes a joining host "consistent with the global state"
through its sponsor: the leader sends it the global state (ll. 58-61, 123-126, 174-177: "send global state
to a") and forwards every later change to it until the OAC(membership) that adds it commits. The pseudo-code
leaves open how the joiner lines the forwarded stream up with the transactions it delivers itself once it
is a participant; HAA numbers applied transactions (`GlobalState.seq`) and completes it as documented in
docs/membership.md ("State transfer"). `StateTransfer` is the joiner's side, and the part of every member
that answers a joiner's request, as a sans-I/O machine with its own state:

* the sponsor's stream: `Snapshot(anchor=None)` (the state the sponsor sent) is installed when it is ahead of
  ours in the same group, or comes from a correct group while ours is not; `Forward(seq, …)` transactions
  are buffered by global sequence number and applied in order (`ApplyTx(direct=False)`: state only);
* the joiner's own deliveries (`Delivered`): from the transaction that adds it onwards it buffers what it
  delivers until its state has reached the one just before the first of them — from the sponsor's stream,
  or, if that does not arrive within `catchup_timeout` (`CatchupDue`), from a `StateRequest` to a member
  answered with a snapshot anchored at that transaction — then applies them (`ApplyTx(direct=True)`) and
  lets the held global-state changes go (`CaughtUp`);
* any member answers a `StateRequest` (`Request`) with its state once it has applied the anchor
  transaction (`Applied` reports each applied transaction).

Interface: `step(now, input) -> list[XferEffect]` over the closed unions `XferInput` and `XferEffect`. The
machine reads the global state and a few facts of its node through the read-only `XferHost` protocol; the
state itself changes only by effects the node carries out (`Restore`, `ApplyTx`). A drain — applying
buffered transactions one after the other, each seeing the state the previous one left — returns one
`ApplyTx` (or `Restore`) at a time as the last effect of a step; the node carries it out and steps the
machine with `Continue` for the next one, so every transaction is applied, with all its consequences,
exactly where the single-object node applied it.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.effects import Log, Send, SetTimer
from haa.core.membership.globalstate import GlobalState, GroupTxError
from haa.core.membership.groupeffects import NodeTimer
from haa.core.messages import StateRequest, TxId

Proc = tuple[str, int]

#: the key of the catch-up timer
CATCHUP_TIMER = NodeTimer("catchup")


class StateView(Protocol):
    """The parts of `GlobalState` the machine reads."""

    @property
    def seq(self) -> int: ...

    @property
    def genesis(self) -> str: ...

    @property
    def group_correct(self) -> bool: ...

    @property
    def recent(self) -> Mapping[TxId, int]: ...


class XferHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    @property
    def state(self) -> StateView: ...

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def request_target(self, txid: TxId) -> Proc:
        """Whom a catching-up member asks for the state anchored at `txid`."""


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class Forward:
    """`StateForward` from the sponsor: the `seq`-th global transaction."""

    seq: int
    txid: TxId
    payload: bytes


@dataclass(frozen=True, slots=True)
class Snapshot:
    """`StateSnapshot`: from the sponsor (`anchor` None) or the answer to our `StateRequest`."""

    seq: int
    data: bytes
    anchor: TxId | None
    anchor_seq: int
    #: an answer only: the lock (key, taken by) of a membership change in progress the answering member holds
    lock: tuple[str, Proc] | None = None


@dataclass(frozen=True, slots=True)
class Request:
    """`StateRequest` from `src`: the state as of the transaction `txid`."""

    src: Proc
    txid: TxId


@dataclass(frozen=True, slots=True)
class Delivered:
    """OAC delivered a transaction not yet applied here. `joining`: this host is not a member and the
    transaction is the one that adds it to an existing group (it needs the state before it)."""

    txid: TxId
    payload: bytes
    joining: bool


@dataclass(frozen=True, slots=True)
class Applied:
    """The node applied transaction `txid` as the `seq`-th."""

    txid: TxId
    seq: int


@dataclass(frozen=True, slots=True)
class CatchupDue:
    """The catch-up timer (`CATCHUP_TIMER`) fired."""


@dataclass(frozen=True, slots=True)
class Continue:
    """The node carried out the `ApplyTx`/`Restore` that ended the last step: go on with the drain."""


XferInput = Forward | Snapshot | Request | Delivered | Applied | CatchupDue | Continue


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class ApplyTx:
    """Apply this transaction to the global state (`direct`: delivered here, with all its consequences for
    the membership; otherwise from the sponsor's stream: the state only), then step with `Continue`."""

    txid: TxId
    payload: bytes
    direct: bool


@dataclass(frozen=True, slots=True)
class Restore:
    """Replace the global state with this snapshot, then step with `Continue`."""

    data: bytes


@dataclass(frozen=True, slots=True)
class SendSnapshot:
    """Send `to` the current global state, anchored at the transaction `anchor`, applied as `anchor_seq`."""

    to: Proc
    anchor: TxId
    anchor_seq: int


@dataclass(frozen=True, slots=True)
class InheritLock:
    """The answer this new member installed holds the global state locked for a membership change (Alg. 3 l.
    127) whose remove it skipped: take the lock and acknowledge it to `by` (l. 130), as applying the remove
    would have."""

    key: str
    by: Proc


@dataclass(frozen=True, slots=True)
class CaughtUp:
    """The new member's state has caught up: propose the global-state changes held meanwhile."""


@dataclass(frozen=True, slots=True)
class Rejected:
    """A snapshot did not decode (counted as `rejected_snapshot`)."""

    reason: str


XferEffect = ApplyTx | Restore | SendSnapshot | Send | SetTimer | Log | InheritLock | CaughtUp | Rejected

_Drain = Iterator[ApplyTx | Restore]


# ------------------------------------------------------------------------------------------------ machine


class StateTransfer:
    """The state transfer of one host incarnation. See the module docstring."""

    def __init__(self, me: Proc, host: XferHost, catchup_timeout: float = 2.0) -> None:
        self.me = me
        self.host = host
        self.catchup_timeout = catchup_timeout
        self.fwd_buffer: dict[int, tuple[TxId, bytes]] = {}  # the sponsor's stream, by global seq
        self.direct_q: list[tuple[TxId, bytes]] = []  # delivered here, waiting for the state to catch up
        self.direct_anchor: int = 0  # global seq of direct_q[0], 0 = unknown
        self.requests: dict[TxId, list[Proc]] = {}  # StateRequests waiting for their anchor to be applied
        self._drain: _Drain | None = None
        self._installed = False  # the last `_install` replaced the state
        self._now = 0.0
        self._out: list[XferEffect] = []

    def catching_up(self) -> bool:
        """A new member whose state has not caught up yet (its global-state changes are held)."""
        return bool(self.direct_q)

    def step(self, now: float, inp: XferInput) -> list[XferEffect]:
        self._now = now
        st = self.host.state
        match inp:
            case Continue():
                self._resume()
            case Applied(txid, seq):
                for q in self.requests.pop(txid, ()):
                    self._out.append(SendSnapshot(q, txid, seq))
            case Forward(seq, txid, payload):
                if not (self.host.is_member() and not self.direct_q) and seq > st.seq:
                    self.fwd_buffer[seq] = (txid, payload)
                    self._start(self._drain_forwarded())
            case Snapshot(seq, data, anchor, anchor_seq, lock):
                if anchor is None:  # from our sponsor (ll. 60, 125, 176)
                    if not (self.host.is_member() and not self.direct_q):
                        self._start(self._install_then_drain(data))
                elif self.direct_q and anchor == self.direct_q[0][0]:
                    self._start(self._install_anchored(data, anchor_seq, lock))
            case Request(src, txid):
                applied = st.recent.get(txid)
                if applied is None:
                    self.requests.setdefault(txid, []).append(src)  # answer once it is applied here
                else:
                    self._out.append(SendSnapshot(src, txid, applied))
            case Delivered(txid, payload, joining):
                if self.direct_q or joining:
                    # a new member: buffer until the state has caught up with the transaction that added us
                    self.direct_q.append((txid, payload))
                    if self.direct_anchor:
                        self._start(self._drain_direct())
                    else:
                        self._out.append(SetTimer(CATCHUP_TIMER, now + self.catchup_timeout))
                else:
                    self._out.append(ApplyTx(txid, payload, True))
            case CatchupDue():
                self._request_state()
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    # ------------------------------------------------------------------ drains

    def _start(self, drain: _Drain) -> None:
        if self._drain is not None:
            raise RuntimeError("state transfer: a drain started while another one waits for Continue")
        self._drain = drain
        self._resume()

    def _resume(self) -> None:
        drain = self._drain
        if drain is None:
            return
        try:
            eff = next(drain)
        except StopIteration:
            self._drain = None
            return
        self._out.append(eff)

    def _install(self, data: bytes) -> _Drain:
        """Install a snapshot that is ahead of our state in the same group, or that comes from a correct group
        while ours is not (a provisional group of one that never became correct, docs/membership.md)."""
        st = self.host.state
        try:
            seq, gid, correct = GlobalState.peek(data)
        except GroupTxError as e:
            self._out.append(Rejected(str(e)))
            return
        same = gid == st.genesis
        if not ((same and seq > st.seq) or (not same and correct and not st.group_correct) or st.seq == 0):
            return
        if not same:
            self.fwd_buffer.clear()
        self._installed = True
        yield Restore(data)

    def _install_then_drain(self, data: bytes) -> _Drain:
        yield from self._install(data)
        yield from self._drain_forwarded()

    def _install_anchored(self, data: bytes, anchor_seq: int, lock: tuple[str, Proc] | None) -> _Drain:
        """The answer to our `StateRequest`: usually past the anchor, so installing it skips deliveries of ours
        that it covers, and with them their consequences here (Alg. 3 ll. 117-157). The one another member
        waits for is the lock acknowledgement of a remove (l. 130; its leader waits at l. 103): the answer
        carries the lock its sender holds, and we take it (`InheritLock`). Without it the leader waited for
        good and held every write (`haactl verify recovery --hosts 7` seed 1610)."""
        self._installed = False
        yield from self._install(data)
        if self._installed and lock is not None:
            self._out.append(InheritLock(*lock))
        self.direct_anchor = anchor_seq
        self.fwd_buffer.clear()
        yield from self._drain_direct()

    def _drain_forwarded(self) -> _Drain:
        st = self.host.state
        while st.seq + 1 in self.fwd_buffer:
            txid, payload = self.fwd_buffer.pop(st.seq + 1)
            if self.direct_q and txid == self.direct_q[0][0]:
                self.direct_anchor = st.seq + 1
                self.fwd_buffer.clear()
                yield from self._drain_direct()
                return
            yield ApplyTx(txid, payload, False)
            st = self.host.state  # (a Restore replaces the state object)
        for s in [s for s in self.fwd_buffer if s <= st.seq]:
            del self.fwd_buffer[s]

    def _drain_direct(self) -> _Drain:
        """Apply buffered deliveries once the state has reached the one before the first of them."""
        if not self.direct_anchor or self.host.state.seq + 1 < self.direct_anchor:
            return
        q, self.direct_q = self.direct_q, []
        first = self.direct_anchor
        self.direct_anchor = 0
        for i, (txid, payload) in enumerate(q):
            st = self.host.state
            if first + i <= st.seq or txid in st.recent:
                continue
            yield ApplyTx(txid, payload, True)
        self._out.append(Log("caught_up", {"seq": self.host.state.seq}))
        self._out.append(CaughtUp())

    def _request_state(self) -> None:
        if not self.direct_q or self.direct_anchor:
            return
        txid = self.direct_q[0][0]
        target = self.host.request_target(txid)
        if target != self.me:
            self._out.append(Send(target[0], target[1], StateRequest(txid)))
        self._out.append(Log("state_request", {"to": target[0], "tx": str(txid)}))
        self._out.append(SetTimer(CATCHUP_TIMER, self._now + self.catchup_timeout))

