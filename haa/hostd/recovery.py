"""Agent backup and recovery HAA-AB / HAA-AR (thesis §4.9, Appendix II Alg. 7 and Alg. 8), the host side.

A mixin of `haa.hostd.agentnode.AgentNode`, in its own file so that the pseudo-code can be read next to it.

* Backup (Alg. 7): an instance sends (backup, a, b) to its host (l. 3, `BackupMade`); the host commits it to
  the agent table (l. 5). Only the owner's current epoch may write a backup, so a fenced instance cannot
  overwrite a newer one (haa.hostd.agenttable).
* Failure: an instance that dies or hangs (`Failed` from the driver) is reported with OAC(failed); a host
  removed from the group takes its agents with it (the table marks them crashed when the removal commits).
* Recovery (Alg. 8): the host the allocation gives a crashed (or new) agent spawns a shell (l. 2) and claims
  the agent with OAC(recovered) (ll. 6-9). **Order changed** (docs/agents-host.md, "recovery claims first"):
  Alg. 8 sends the backup to the shell (l. 4) and starts forwarding (l. 5) before the OAC; here the shell gets
  the backup only once OAC(recovered) has committed. The backup is then the one the table holds at that point
  in the total order — the latest committed backup, which is what l. 3 ("wait until all active OACs are
  decided") is for — and two hosts can never both run the agent, even when two allocation sessions overlap
  (the thesis relies on the allocation for that). The price is one OAC on the recovery path (a few ms).
  Messages addressed to the agent while it was down were kept in its queue and are handed over too.
* Recovery strategies (`AgentCreate.recovery`): "backup" (the latest backup, or a fresh start if there is
  none), "restart" (always fresh), "none" (the agent stays crashed; an operator can remove it).
* Start failures (issue 13, defect 3): a failure is *early* when the instance was not up yet (its shell
  could not start, or it died before or within `AgentConfig.start_grace` of its StartAgent); the host that
  ran it says so in the OAC(failed) (`AgentFailed.early`), and the table counts consecutive early failures.
  The host that recovers an agent with n > 0 of them first waits min(backoff_cap, backoff_base * 2^(n-1))
  (a node timer: no clock is read here), so an agent that cannot start costs a few attempts, not a loop;
  at agenttable.MAX_START_FAILURES the table marks it "failed" and nobody recovers it (timeline "failed" with
  the reason) until an operator moves it (a retry, from a clean count) or removes it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from haa.hostd import agenttable as at
from haa.hostd.agentio import SpawnShell, StartAgent
from haa.hostd.effects import SetTimer
from haa.hostd.routing import Inbox, Outbox
from haa.pb import agenttx_pb2 as apb

#: a shell that dies before its agent was started is replaced this many times, then the attempt is abandoned
MAX_RESPAWNS = 3

if TYPE_CHECKING:
    from haa.hostd.agentnode import AgentNode, Local


class RecoveryMixin:
    # ------------------------------------------------------------------ Alg. 7: backup

    def _on_backup(self: AgentNode, loc: Local, data: bytes) -> None:
        """Alg. 7 ll. 4-5."""
        if loc.phase not in ("active", "freezing"):
            return
        if len(data) > at.MAX_BLOB:
            self._log("backup_rejected", agent=loc.id, reason="backup too large", size=len(data))
            return
        tx = apb.AgentTx()
        b = tx.backup
        b.id, b.host, b.epoch, b.data = loc.id, self.name, loc.epoch, data
        self.backups_proposed += 1
        self._propose(tx, ("backup", loc.id, loc.epoch))

    # ------------------------------------------------------------------ failures

    def _on_instance_failed(self: AgentNode, loc: Local, reason: str) -> None:
        r = self.table.get(loc.id)
        # a spawn that failed on a first start or a recovery is a start failure like any other (counted, backed
        # off): replacing the shell at once would only repeat it (a config its type refuses, ...). A thaw's
        # shell is replaced: the frozen state is only good while the claim stands
        spawn_failed = loc.phase == "recovering" and reason.startswith("spawn failed")
        early = loc.phase != "active" or loc.started < 0 or self._now - loc.started < self.config.start_grace
        if (loc.phase in ("claiming", "thawing", "recovering") and loc.respawns < MAX_RESPAWNS and r is not None
                and not spawn_failed):
            # the shell died before it was started: nothing of the agent was in it, start another one
            loc.respawns += 1
            loc.ready = False
            self._log("shell_respawn", agent=loc.id, epoch=loc.epoch, reason=reason)
            self._cmd(SpawnShell(loc.id, loc.epoch, r.type, r.name, r.spec.config, r.parent))
            return
        self.local.pop(loc.id, None)
        self._timeline(loc.id, "crashed", reason)
        if r is not None and r.owner == self.name and r.epoch == loc.epoch:
            self._report_failed(loc.id, loc.epoch, reason, early)
            # messages held for the dead instance wait for the table to say where the agent is
            self.orphans.setdefault(loc.id, []).extend([*loc.local_q, *loc.handed, *loc.q1])
        else:
            if loc.phase == "recovering" and not loc.claimed:
                # its OAC(recovered) may still commit: then the failure is reported with this reason
                self._spawn_failed[loc.id] = (loc.epoch, reason)
            for m in (*loc.local_q, *loc.handed, *loc.q1):
                self._route(m)

    def _report_failed(self: AgentNode, agent: str, epoch: int, reason: str, early: bool = False) -> None:
        if (agent, epoch) in self.failed_reported:
            return  # already in OAC (every applied transaction re-checks the table: report once)
        self.failed_reported.add((agent, epoch))
        self._failed_why[(agent, epoch)] = (reason, early)
        tx = apb.AgentTx()
        f = tx.failed
        f.id, f.host, f.epoch, f.reason, f.early = agent, self.name, epoch, reason[:200], early
        self._propose(tx, ("failed", agent, epoch))

    def _on_failed_done(self: AgentNode, agent: str, epoch: int, ok: bool) -> None:
        self.failed_reported.discard((agent, epoch))
        reason, early = self._failed_why.pop((agent, epoch), ("retry", False))
        r = self.table.get(agent)
        if not ok and r is not None and r.owner == self.name and r.epoch == epoch and agent not in self.local:
            self._report_failed(agent, epoch, reason, early)

    def _backing_off(self: AgentNode, r: at.AgentRecord) -> bool:
        """Whether the recovery of crashed `r` waits (start failure backoff); arms the node timer if so."""
        if r.status != at.CRASHED or r.failures <= 0:
            self._backoff.pop(r.id, None)
            return False
        key = (r.epoch, r.failures)
        entry = self._backoff.get(r.id)
        if entry is None or entry[0] != key:
            delay = min(self.config.backoff_cap, self.config.backoff_base * 2 ** (r.failures - 1))
            entry = (key, self._now + delay)
            self._backoff[r.id] = entry
            self.out.append(SetTimer(("a", "backoff", r.id), entry[1]))
            self._log("agent_start_backoff", agent=r.id, name=r.name, failures=r.failures,
                      max_failures=at.MAX_START_FAILURES, delay=delay, reason=r.fail_reason)
            self._timeline(r.id, "backoff", f"start failure {r.failures} of {at.MAX_START_FAILURES}: "
                                            f"retry in {delay:g} s ({r.fail_reason})")
        if self._now < entry[1]:
            return True
        del self._backoff[r.id]
        return False

    def _on_failed_for_good(self: AgentNode, r: at.AgentRecord) -> None:
        """The table marked `r` failed: it is not recovered (until an operator move); say why."""
        self._backoff.pop(r.id, None)
        self._timeline(r.id, "failed", f"{r.failures} start failures in a row: {r.fail_reason}")
        self._log("agent_failed_for_good", agent=r.id, name=r.name, failures=r.failures, reason=r.fail_reason)
        for m in self.orphans.pop(r.id, []):
            self._route(m)

    def _on_crashed(self: AgentNode, agent: str) -> None:
        """The table marked `agent` crashed (failed committed, or its host was removed)."""
        r = self.table.get(agent)
        if r is None:
            return
        self._timeline(agent, "crashed", "")
        for m in self.orphans.pop(agent, []):
            self._route(m)

    # ------------------------------------------------------------------ Alg. 8: recovery (new host)

    def _recover(self: AgentNode, r: at.AgentRecord) -> None:
        """recoverAgent(a), Alg. 8 l. 1 (also the first start of a new agent)."""
        mode = "fresh" if r.status == at.NEW else "recover"
        loc = self._new_local(r, r.epoch + 1, "recovering", mode)
        self._cmd(SpawnShell(r.id, loc.epoch, r.type, r.name, r.spec.config, r.parent))  # l. 2
        self._timeline(r.id, "spawning" if mode == "fresh" else "recovering")
        self._propose_recovered(loc)

    def _propose_recovered(self: AgentNode, loc: Local) -> None:
        tx = apb.AgentTx()
        tx.recovered.id, tx.recovered.host = loc.id, self.name
        self._propose(tx, ("recovered", loc.id, loc.epoch))  # ll. 6-9

    def _on_recovered_done(self: AgentNode, agent: str, epoch: int, ok: bool) -> None:
        loc = self.local.get(agent)
        if ok or loc is None or loc.epoch != epoch or loc.phase != "recovering" or loc.claimed:
            return
        r = self.table.get(agent)
        if r is not None and r.alloc == self.name and r.status in (at.NEW, at.CRASHED):
            self._propose_recovered(loc)
        else:
            self._abandon(loc, "recovery no longer possible")

    def _on_recovered_applied(self: AgentNode, res: at.AgentApplied) -> None:
        """Alg. 8 ll. 13-15 on every host; the recovering host starts the shell."""
        loc = self.local.get(res.agent)
        if not res.ok:
            if res.host == self.name and loc is not None and loc.phase == "recovering" and not loc.claimed:
                self._abandon(loc, res.reason)
            return
        r = self.table.get(res.agent)
        assert r is not None
        if res.host != self.name:  # l. 15: route to q (`_route` reads the table)
            for m in self.orphans.pop(res.agent, []):
                self._route(m)
            return
        if loc is None or loc.phase != "recovering":
            failed = self._spawn_failed.pop(res.agent, None)
            why = failed[1] if failed is not None and failed[0] == r.epoch else "recovered without a shell"
            self._report_failed(r.id, r.epoch, why, early=True)
            return
        if loc.epoch != r.epoch:  # committed after other recoveries raised the epoch: a shell for this one
            self._reshell(loc, r)
        loc.claimed = True
        loc.life = r.life
        loc.outbox = Outbox()
        # a new agent has seen nothing: its streams start at 1; a recovered one adopts what comes next
        loc.inbox = Inbox(adopt=loc.mode == "recover")
        loc.handed = list(res.msgs) + self.orphans.pop(res.agent, [])
        if loc.mode == "recover" and r.spec.recovery == "backup":
            loc.state = r.backup  # l. 4: the latest committed backup
        else:
            loc.state = None
        self._recover_progress(loc)

    def _recover_progress(self: AgentNode, loc: Local) -> None:
        if loc.phase != "recovering" or not loc.claimed or not loc.ready:
            return
        assert loc.inbox is not None
        msgs = []
        for m in (*loc.handed, *loc.local_q):
            msgs += loc.inbox.offer(m)
        loc.handed, loc.local_q = [], []
        loc.phase = "active"  # l. 5
        self._spawn_failed.pop(loc.id, None)
        self._cmd(StartAgent(loc.id, loc.epoch, loc.mode, loc.state, msgs))  # l. 4
        self._timeline(loc.id, "active" if loc.mode == "fresh" else "recovered",
                       "from backup" if loc.state is not None else "fresh state")
        loc.state = None
        self._reconcile_one(loc.id)
