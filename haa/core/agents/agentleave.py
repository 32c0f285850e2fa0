"""Graceful leave of a host that runs agents (thesis AF-1: "a host can leave the group without losing agents").

`Leave` is the small machine behind `AgentNode.leave`: the host first marks itself draining — committed to
the agent table with its capacity, so that the allocation gives it no agent and its agents are transferred
elsewhere (Alg. 4-6) — then waits until it runs no instance, or until `timeout` passes (its remaining agents
are then recovered elsewhere, Alg. 8), or at once when nobody could take them; then it leaves the group
(Alg. 3). `AgentNode` carries out the effects (`PublishHost`: publish the draining flag; `Go`: kill what is
left and leave the group).

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass

from haa.core.agents.agentstep import AgentTimer, AgentView, ArmTimer, Note


@dataclass(frozen=True, slots=True)
class PublishHost:
    """Commit this host's entry (now draining) to the agent table."""


@dataclass(frozen=True, slots=True)
class Go:
    """Leave the group now: every instance still here is killed (and recovered elsewhere)."""


LeaveEffect = Note | PublishHost | ArmTimer | Go


class Leave:
    """See the module docstring."""

    def __init__(self, view: AgentView, timeout: float) -> None:
        self.view = view
        self.timeout = timeout
        self.draining = False
        self.left = False  # the leave was carried out (or the group left us)
        self.deadline = 0.0

    def begin(self, now: float, instances: int, member: bool) -> list[LeaveEffect]:
        """The operator asks this host to leave; it runs `instances` instances, `member`: of the group."""
        if self.draining:
            return []
        self.draining = True
        self.deadline = now + self.timeout
        out: list[LeaveEffect] = [Note("draining", {"agents": instances})]
        if not member or len(self.view.members()) == 1 or not instances:
            return out + self.check(instances, force=True)
        return [*out, PublishHost(), ArmTimer(AgentTimer("drain"), self.deadline)]

    def check(self, instances: int, force: bool = False) -> list[LeaveEffect]:
        """Whether to go now: every agent handed over, the deadline passed (`force`), or nobody to take them."""
        if not self.draining or self.left:
            return []
        hosts = self.view.table.hosts
        me = self.view.name
        takers = [n for n in self.view.members() if n != me and not (n in hosts and hosts[n].draining)]
        if instances and not force and takers:
            return []  # wait until every agent is handed over (or the deadline)
        self.left = True
        return [Go()]
