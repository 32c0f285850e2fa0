"""The end of one incarnation's membership: groupLeave() and removal (thesis Alg. 3 ll. 14-21, 117-118, 136-143).

A host leaves on purpose by telling every member (l. 15), the group removes it by the next membership change
(ll. 18-21 at the leader), and the host stops once that has committed (l. 17). HAA's completions
(docs/membership.md): an applicant that leaves withdraws its application from every host it knows; the last
member leaves at once (nobody remains to commit its removal); a member removed without having asked to leave
— falsely suspected, or excluded — restarts as a new incarnation and applies again (`Reincarnate`), as does
a provisional group that learns of a different correct group; a host excluded while leaving has left.

`GroupLeave` is this life-cycle of one host incarnation as a sans-I/O machine with its own state —
`leaving` (groupLeave() was called) and `left` (this incarnation is out of the group for good). Interface:
`step(now, input) -> list[LeaveEffect]` over the closed unions `LeaveInput` and `LeaveEffect`; what it reads
of its node comes through the read-only `LeaveHost`.

No I/O, no clock, no randomness.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, assert_never

from haa.core.effects import Log, Reincarnate, Send
from haa.core.membership.globalstate import GlobalState
from haa.core.membership.groupeffects import Left
from haa.core.messages import Leave

Proc = tuple[str, int]


class LeaveHost(Protocol):
    """What the machine reads of the node it runs in (read-only)."""

    @property
    def state(self) -> GlobalState:
        """The group's global state as applied here."""

    def is_member(self) -> bool:
        """This incarnation is in the member list."""

    def peer_list(self) -> Sequence[Proc]:
        """Every host this one knows, with the incarnation it knows (sorted by name)."""


# ------------------------------------------------------------------------------------------------ inputs


@dataclass(frozen=True, slots=True)
class LeaveCalled:
    """groupLeave() (ll. 14-17)."""


@dataclass(frozen=True, slots=True)
class RemovedHere:
    """A committed change no longer lists this incarnation."""


@dataclass(frozen=True, slots=True)
class Excluded:
    """While leaving, host `by` told us we were removed (a permanent suspicion)."""

    by: str


@dataclass(frozen=True, slots=True)
class Abandoned:
    """This provisional group learnt of the correct group `existing` (docs/membership.md, "restarts")."""

    existing: str


LeaveInput = LeaveCalled | RemovedHere | Excluded | Abandoned


# ------------------------------------------------------------------------------------------------ effects


@dataclass(frozen=True, slots=True)
class LeaveSelf:
    """l. 15 for this host itself: record its own leave request (as a `Leave` from itself would)."""


LeaveEffect = Send | Log | Left | Reincarnate | LeaveSelf


# ------------------------------------------------------------------------------------------------ machine


class GroupLeave:
    """The leave and removal life-cycle of one host incarnation (see the module docstring)."""

    def __init__(self, me: Proc, host: LeaveHost) -> None:
        self.me = me
        self.host = host
        self.leaving = False
        self.left = False

    def step(self, now: float, inp: LeaveInput) -> list[LeaveEffect]:
        out: list[LeaveEffect] = []
        st = self.host.state
        match inp:
            case LeaveCalled():
                if self.leaving:
                    return out
                self.leaving = True
                out.append(Log("leave_requested", {}))
                if not self.host.is_member():
                    # an applicant withdraws: every host it knows drops it from its join list, so that no leader
                    # proposes a group with it after it is gone (that transaction would wait for it)
                    for q, inc in self.host.peer_list():
                        out.append(Send(q, inc, Leave()))  # inc 0: any incarnation (as our Apply went)
                    self.left = True
                    out.append(Left())
                elif len(st.members) == 1:
                    # the last member: nobody remains to commit its removal (Alg. 3 assumes a group remains)
                    self.left = True
                    out += [Log("left", {"view": st.view, "last_member": True}), Left()]
                else:
                    for m in st.members:  # l. 15
                        out.append(LeaveSelf() if m.proc == self.me else Send(m.name, m.inc, Leave()))
            case RemovedHere():  # after a leave, stop (l. 17); otherwise re-apply as a new incarnation
                if not self.left:
                    self.left = True
                    if self.leaving:
                        out += [Log("left", {"view": st.view}), Left()]
                    else:
                        out += [Log("removed", {"view": st.view}), Reincarnate(by=self.me[0])]
            case Excluded(by):
                # we are leaving on purpose: a peer's removal notice is no reason to come back. Removed (excluded)
                # before our leave committed, we are out of the group all the same (seen when the whole group
                # leaves at once and the last two members suspect each other)
                if not self.left:
                    self.left = True
                    out += [Log("left", {"view": st.view, "excluded_by": by}), Left()]
            case Abandoned(existing):
                self.left = True
                out += [Log("provisional_group_abandoned", {"group": st.genesis, "existing": existing}),
                        Reincarnate(by=self.me[0])]
            case _:
                assert_never(inp)
        return out
