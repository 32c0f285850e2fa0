"""Agent backup and recovery HAA-AB / HAA-AR (thesis §4.9, Appendix II Alg. 7 and Alg. 8): the host side, as a
machine.

`Recovery` owns what this host knows about backups, failures and recoveries — the recoveries it runs, the
failures it has reported and not yet seen decided, the start-failure backoffs, the messages held for agents
whose instance is gone — and is driven through `step(now, input) -> list[effect]`; it reads the agent table
and the member list through an `AgentView`. `haa.core.agents.agentnode.AgentNode` composes it (next to
`haa.core.agents.transfer.Transfer`); `tests/test_agent_machines.py` drives it alone. Line numbers are those of
Alg. 7 and Alg. 8 as printed (the seed text of the thesis: Alg. 7 at its line 2923, Alg. 8 at 2931, the prose
at 897-899, the AR-Recovery proof at 2951).

* Backup (Alg. 7): an instance sends (backup, a, b) to its host (l. 3, `Backup`); the host commits it to
  the agent table (l. 5). Only the owner's current epoch may write a backup, so a fenced instance — or a backup
  from an older epoch — cannot overwrite a newer one (haa.core.ddb.agenttable).
* Failure: an instance that dies or hangs (`InstanceFailed`) is reported with OAC(failed), retried while the
  agent is still this host's and no new instance runs; a host removed from the group takes its agents with
  it (the table marks them crashed when the removal commits: `Crashed`).
* Recovery (Alg. 8, `Recover`): the host the allocation gives a crashed (or new) agent spawns a shell (l. 2)
  and claims the agent with OAC(recovered) (ll. 6-9). **Order changed** (docs/agents-host.md, "recovery
  claims first"): Alg. 8 sends the backup to the shell (l. 4) and starts forwarding (l. 5) before the OAC;
  here the shell gets the backup only once OAC(recovered) has committed. The backup is then the one the table
  holds at that point in the total order — the latest committed backup, which is what l. 3 ("wait until all
  active OACs are decided") is for — and two hosts can never both run the agent, even when two allocation
  sessions overlap (the thesis relies on the allocation for that). The price is one OAC on the recovery path.
  Messages addressed to the agent while it was down were kept in its queue and are handed over too. A
  recovery refused or no longer possible (the agent was allocated elsewhere, the host holding it is gone and
  another recovered it first) is abandoned.
* Recovery strategies (`AgentCreate.recovery`): "backup" (the latest backup, or a fresh start if there is
  none), "restart" (always fresh), "none" (the agent stays crashed; an operator can remove it).
* Start failures (issue 13, defect 3): a failure is *early* when the instance was not up yet (its shell
  could not start, or it died before or within `AgentConfig.start_grace` of its StartAgent; the node measures
  it); the host that ran it says so in the OAC(failed) (`AgentFailed.early`), and the table counts consecutive
  early failures. The host that recovers an agent with n > 0 of them first waits
  min(backoff_cap, backoff_base * 2^(n-1)) (`ArmTimer` of `AgentTimer("backoff", agent)`: no clock is read
  here), so an agent that cannot start costs a few attempts, not a loop; at agenttable.MAX_START_FAILURES the
  table marks it "failed" and nobody recovers it until an operator moves it (a retry) or removes it.

Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import assert_never

from haa.core.agentio import KillAgent, StartAgent
from haa.core.agents.agentstep import (
    MAX_RESPAWNS,
    Activate,
    AgentTimer,
    AgentView,
    ArmTimer,
    Cmd,
    Committed,
    Forget,
    Hold,
    Note,
    Propose,
    Reconcile,
    Route,
    SetPhase,
    ShellUp,
    Timeline,
    spawn,
    start_messages,
)
from haa.core.agents.routing import Inbox, Outbox
from haa.core.ddb import agenttable as at
from haa.pb import agenttx_pb2 as apb

# ----------------------------------------------------------------------------------------------- inputs
# (and `Hold`, `ShellUp`, `Committed`, which both machines take: `haa.core.agents.agentstep`)


@dataclass(frozen=True, slots=True)
class Recover:
    """recoverAgent(a), Alg. 8 l. 1 (also the first start of a new agent): `agent`, new or crashed, is
    allocated to this host. Waits out a start-failure backoff first."""

    agent: str


@dataclass(frozen=True, slots=True)
class Backup:
    """Alg. 7 l. 3: (backup, a, `data`) from this host's instance (`agent`, `epoch`)."""

    agent: str
    epoch: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Orphan:
    """A message for `agent`, whose instance here is gone: held until the table says where the agent is."""

    agent: str
    m: apb.RoutedMsg


@dataclass(frozen=True, slots=True)
class ShellDied:
    """The shell of a recovery died (before its agent was started, or with it)."""

    agent: str
    reason: str


@dataclass(frozen=True, slots=True)
class InstanceFailed:
    """Another instance of this host died or hung (running, freezing, or a thaw's shell given up): report it.
    `msgs`: the messages it held; `early`: a start failure (the node measured it)."""

    agent: str
    epoch: int
    reason: str
    early: bool
    msgs: tuple[apb.RoutedMsg, ...] = ()


@dataclass(frozen=True, slots=True)
class ReportFailed:
    """The table says this host runs (`agent`, `epoch`) but it does not: report it failed."""

    agent: str
    epoch: int
    reason: str


@dataclass(frozen=True, slots=True)
class Crashed:
    """The removal of a host committed and the table marked `agent` crashed."""

    agent: str


@dataclass(frozen=True, slots=True)
class Written:
    """This host's OAC(`kind`) for (`agent`, `epoch`) committed (`ok`) or was given up; `running`: the node
    runs an instance of `agent` (a failure is not reported again then)."""

    kind: str
    agent: str
    epoch: int
    ok: bool
    running: bool


@dataclass(frozen=True, slots=True)
class Check:
    """The node reconciles `agent` (or, with `agent` "", has reconciled every agent): forget a backoff this host
    no longer needs."""

    agent: str = ""


@dataclass(frozen=True, slots=True)
class Drop:
    """The node no longer has `agent`'s instance; `removed`: the agent was removed (its held messages go)."""

    agent: str
    removed: bool = False


RecoveryInput = (
    Recover | Backup | Hold | Orphan | ShellUp | ShellDied | InstanceFailed | ReportFailed | Committed | Crashed
    | Written | Check | Drop
)

RecoveryEffect = Cmd | Propose | Timeline | Note | Route | SetPhase | Activate | Forget | Reconcile | ArmTimer

# ----------------------------------------------------------------------------------------------- state


@dataclass(slots=True)
class _Recovery:
    """Alg. 8 on the recovering host."""

    epoch: int
    mode: str  # "fresh" (a new agent) or "recover"
    ready: bool = False  # the shell said hello
    claimed: bool = False  # OAC(recovered) committed
    respawns: int = 0
    local_q: list[apb.RoutedMsg] = field(default_factory=list)
    handed: list[apb.RoutedMsg] = field(default_factory=list)  # the agent's queues, from the table
    state: bytes | None = None
    inbox: Inbox | None = None
    life: int = 0


@dataclass(frozen=True, slots=True)
class BackoffConfig:
    """The wait before recovering an agent after n consecutive start failures: min(cap, base * 2 ** (n - 1))."""

    base: float = 0.5
    cap: float = 30.0


class Recovery:
    """See the module docstring."""

    def __init__(self, view: AgentView, backoff: BackoffConfig = BackoffConfig()) -> None:
        self.view = view
        self.backoff_config = backoff
        self.recoveries: dict[str, _Recovery] = {}
        #: messages held for an agent whose instance here is gone, until the table says where it is
        self.orphans: dict[str, list[apb.RoutedMsg]] = {}
        #: (agent, epoch) whose OAC(failed) this host has proposed and not yet seen decided
        self.failed_reported: set[tuple[str, int]] = set()
        #: (agent, epoch) -> (reason, early) of the failures reported, for a retry of the OAC(failed)
        self._failed_why: dict[tuple[str, int], tuple[str, bool]] = {}
        #: agent -> ((epoch, failures), due): a crashed agent whose recovery waits (start failure backoff)
        self.backoff: dict[str, tuple[tuple[int, int], float]] = {}
        #: agent -> (epoch, reason): a shell that could not start before its OAC(recovered) committed
        self._spawn_failed: dict[str, tuple[int, str]] = {}
        self.backups_proposed = 0
        self._now = 0.0
        self._out: list[RecoveryEffect] = []

    def step(self, now: float, inp: RecoveryInput) -> list[RecoveryEffect]:
        self._now = now
        match inp:
            case Recover():
                r = self.view.table.get(inp.agent)
                if r is not None and not self._backing_off(r):
                    self._recover(r)
            case Backup():
                self._backup(inp)
            case Hold():
                rec = self.recoveries.get(inp.m.dst)
                if rec is not None:
                    rec.local_q.append(inp.m)  # Alg. 6 l. 3, the same for a recovery
            case Orphan():
                self.orphans.setdefault(inp.agent, []).append(inp.m)
            case ShellUp():
                rec = self.recoveries.get(inp.agent)
                if rec is not None:
                    rec.ready = True
                    self._progress(inp.agent, rec)
            case ShellDied():
                self._shell_died(inp)
            case InstanceFailed():
                self._failed(inp.agent, inp.epoch, inp.reason, inp.early, inp.msgs)
            case ReportFailed():
                self._report_failed(inp.agent, inp.epoch, inp.reason)
            case Committed():
                self._committed(inp.res)
            case Crashed():
                self._crashed(inp.agent)
            case Written():
                self._written(inp)
            case Check():
                self._check(inp.agent)
            case Drop():
                self.recoveries.pop(inp.agent, None)
                if inp.removed:
                    self.orphans.pop(inp.agent, None)
            case _:
                assert_never(inp)
        out, self._out = self._out, []
        return out

    # ------------------------------------------------------------------ Alg. 7: backup

    def _backup(self, inp: Backup) -> None:
        """Alg. 7 ll. 4-5."""
        if len(inp.data) > at.MAX_BLOB:
            self._out.append(Note("backup_rejected", {"agent": inp.agent, "reason": "backup too large",
                                                      "size": len(inp.data)}))
            return
        tx = apb.AgentTx()
        b = tx.backup
        b.id, b.host, b.epoch, b.data = inp.agent, self.view.name, inp.epoch, inp.data
        self.backups_proposed += 1
        self._out.append(Propose(tx, "backup", inp.agent, inp.epoch))

    # ------------------------------------------------------------------ failures

    def _shell_died(self, inp: ShellDied) -> None:
        rec = self.recoveries.get(inp.agent)
        if rec is None:
            return
        r = self.view.table.get(inp.agent)
        # a spawn that failed on a first start or a recovery is a start failure like any other (counted, backed
        # off): replacing the shell at once would only repeat it (a config its type refuses, ...)
        if rec.respawns < MAX_RESPAWNS and r is not None and not inp.reason.startswith("spawn failed"):
            # the shell died before it was started: nothing of the agent was in it, start another one
            rec.respawns += 1
            rec.ready = False
            self._out.append(Note("shell_respawn", {"agent": inp.agent, "epoch": rec.epoch, "reason": inp.reason}))
            self._out.append(spawn(r, rec.epoch))
            return
        del self.recoveries[inp.agent]
        self._failed(inp.agent, rec.epoch, inp.reason, True, (*rec.local_q, *rec.handed), unclaimed=not rec.claimed)

    def _failed(self, agent: str, epoch: int, reason: str, early: bool, msgs: tuple[apb.RoutedMsg, ...],
                unclaimed: bool = False) -> None:
        r = self.view.table.get(agent)
        self._out.append(Forget(agent))
        self._out.append(Timeline(agent, "crashed", reason))
        if r is not None and r.owner == self.view.name and r.epoch == epoch:
            self._report_failed(agent, epoch, reason, early)
            # messages held for the dead instance wait for the table to say where the agent is
            self.orphans.setdefault(agent, []).extend(msgs)
            return
        if unclaimed:  # a recovery's shell: its OAC(recovered) may still commit, then it fails with this reason
            self._spawn_failed[agent] = (epoch, reason)
        if msgs:
            self._out.append(Route(msgs))

    def _report_failed(self, agent: str, epoch: int, reason: str, early: bool = False) -> None:
        if (agent, epoch) in self.failed_reported:
            return  # already in OAC (every applied transaction re-checks the table: report once)
        self.failed_reported.add((agent, epoch))
        self._failed_why[(agent, epoch)] = (reason, early)
        tx = apb.AgentTx()
        f = tx.failed
        f.id, f.host, f.epoch, f.reason, f.early = agent, self.view.name, epoch, reason[:200], early
        self._out.append(Propose(tx, "failed", agent, epoch))

    def _written(self, inp: Written) -> None:
        agent, epoch = inp.agent, inp.epoch
        r = self.view.table.get(agent)
        if inp.kind == "failed":
            self.failed_reported.discard((agent, epoch))
            reason, early = self._failed_why.pop((agent, epoch), ("retry", False))
            if not inp.ok and r is not None and r.owner == self.view.name and r.epoch == epoch and not inp.running:
                self._report_failed(agent, epoch, reason, early)
        elif inp.kind == "recovered":
            rec = self.recoveries.get(agent)
            if inp.ok or rec is None or rec.epoch != epoch or rec.claimed:
                return
            if r is not None and r.alloc == self.view.name and r.status in (at.NEW, at.CRASHED):
                self._propose_recovered(agent, rec)  # ll. 6-9: do ... while not committed
            else:
                self._abandon(agent, rec, "recovery no longer possible")

    def _backing_off(self, r: at.AgentRecord) -> bool:
        """Whether the recovery of crashed `r` waits (start failure backoff); arms the timer if so."""
        if r.status != at.CRASHED or r.failures <= 0:
            self.backoff.pop(r.id, None)
            return False
        key = (r.epoch, r.failures)
        entry = self.backoff.get(r.id)
        if entry is None or entry[0] != key:
            cfg = self.backoff_config
            delay = min(cfg.cap, cfg.base * 2 ** (r.failures - 1))
            entry = (key, self._now + delay)
            self.backoff[r.id] = entry
            self._out.append(ArmTimer(AgentTimer("backoff", r.id), entry[1]))
            self._out.append(Note("agent_start_backoff", {
                "agent": r.id, "name": r.name, "failures": r.failures, "max_failures": at.MAX_START_FAILURES,
                "delay": delay, "reason": r.fail_reason}))
            self._out.append(Timeline(r.id, "backoff", f"start failure {r.failures} of {at.MAX_START_FAILURES}: "
                                                       f"retry in {delay:g} s ({r.fail_reason})"))
        if self._now < entry[1]:
            return True
        del self.backoff[r.id]
        return False

    def _check(self, agent: str) -> None:
        t = self.view.table
        if not agent:  # every agent reconciled: forget the backoffs of agents removed meanwhile
            for a in [a for a in self.backoff if t.get(a) is None]:
                del self.backoff[a]
            return
        r = t.get(agent)
        if agent in self.backoff and (r is None or r.status != at.CRASHED or r.alloc != self.view.name):
            # a backoff this host started for an agent it no longer has to recover (allocated elsewhere since,
            # recovered, removed): forget it, or a stale entry outlives the agent's troubles
            del self.backoff[agent]

    def _crashed(self, agent: str) -> None:
        """The table marked `agent` crashed (failed committed, or its host was removed)."""
        if self.view.table.get(agent) is None:
            return
        self._out.append(Timeline(agent, "crashed", ""))
        self._route_orphans(agent)

    def _route_orphans(self, agent: str) -> None:
        msgs = self.orphans.pop(agent, [])
        if msgs:
            self._out.append(Route(tuple(msgs)))

    # ------------------------------------------------------------------ Alg. 8: recovery (new host)

    def _recover(self, r: at.AgentRecord) -> None:
        """recoverAgent(a), Alg. 8 l. 1."""
        mode = "fresh" if r.status == at.NEW else "recover"
        rec = _Recovery(r.epoch + 1, mode)
        self.recoveries[r.id] = rec
        self._out.append(SetPhase(r.id, rec.epoch, "recovering"))
        self._out.append(spawn(r, rec.epoch))  # l. 2
        self._out.append(Timeline(r.id, "spawning" if mode == "fresh" else "recovering"))
        self._propose_recovered(r.id, rec)

    def _propose_recovered(self, agent: str, rec: _Recovery) -> None:
        tx = apb.AgentTx()
        tx.recovered.id, tx.recovered.host = agent, self.view.name
        self._out.append(Propose(tx, "recovered", agent, rec.epoch))  # ll. 6-9

    def _abandon(self, agent: str, rec: _Recovery, why: str) -> None:
        del self.recoveries[agent]
        self._out.append(Forget(agent))
        self._out.append(Cmd(KillAgent(agent, rec.epoch, f"abandoned: {why}")))
        self._out.append(Note("agent_abandoned", {"agent": agent, "epoch": rec.epoch, "reason": why}))
        if rec.local_q:  # messages held for the shell go where the table says now
            self._out.append(Route(tuple(rec.local_q)))

    def _committed(self, res: at.AgentApplied) -> None:
        if res.kind == "failed":
            if not res.ok:
                return
            r = self.view.table.get(res.agent)
            if r is not None and r.status == at.FAILED:  # not recovered until an operator moves it; say why
                self.backoff.pop(r.id, None)
                self._out.append(Timeline(r.id, "failed", f"{r.failures} start failures in a row: {r.fail_reason}"))
                self._out.append(Note("agent_failed_for_good", {"agent": r.id, "name": r.name,
                                                                "failures": r.failures, "reason": r.fail_reason}))
                self._route_orphans(r.id)
            else:
                self._crashed(res.agent)
            return
        if res.kind != "recovered":
            return
        me = self.view.name
        rec = self.recoveries.get(res.agent)
        if not res.ok:  # Alg. 8 ll. 13-15 on every host; the recovering host starts the shell
            if res.host == me and rec is not None and not rec.claimed:
                self._abandon(res.agent, rec, res.reason)
            return
        r = self.view.table.get(res.agent)
        assert r is not None
        if res.host != me:  # l. 15: route to q (the node's routing reads the table)
            self._route_orphans(res.agent)
            return
        if rec is None:
            failed = self._spawn_failed.pop(res.agent, None)
            why = failed[1] if failed is not None and failed[0] == r.epoch else "recovered without a shell"
            self._report_failed(r.id, r.epoch, why, early=True)
            return
        if rec.epoch != r.epoch:  # committed after other recoveries raised the epoch: a shell for this one
            self._out.append(Cmd(KillAgent(r.id, rec.epoch, f"stale shell (epoch {rec.epoch}, now {r.epoch})")))
            rec.epoch = r.epoch
            rec.ready = False
            self._out.append(SetPhase(r.id, rec.epoch, "recovering"))
            self._out.append(spawn(r, rec.epoch))
        rec.claimed = True
        rec.life = r.life
        # a new agent has seen nothing: its streams start at 1; a recovered one adopts what comes next
        rec.inbox = Inbox(adopt=rec.mode == "recover")
        rec.handed = list(res.msgs) + self.orphans.pop(res.agent, [])
        rec.state = r.backup if rec.mode == "recover" and r.spec.recovery == "backup" else None  # l. 4: latest
        self._progress(res.agent, rec)

    def _progress(self, agent: str, rec: _Recovery) -> None:
        if not rec.claimed or not rec.ready:
            return
        assert rec.inbox is not None
        msgs = start_messages(rec.inbox, rec.handed, rec.local_q)
        del self.recoveries[agent]
        self._spawn_failed.pop(agent, None)
        self._out.append(Activate(agent, rec.epoch, rec.inbox, Outbox(), rec.life))  # l. 5
        self._out.append(Cmd(StartAgent(agent, rec.epoch, rec.mode, rec.state, msgs)))  # l. 4
        self._out.append(Timeline(agent, "active" if rec.mode == "fresh" else "recovered",
                                  "from backup" if rec.state is not None else "fresh state"))
        self._out.append(Reconcile(agent))
