"""The agent layer's machines driven alone: transfer (thesis Alg. 5-6, `haa.core.agents.transfer.Transfer`) and
backup/recovery (Alg. 7-8, `haa.core.agents.recovery.Recovery`).

No `AgentNode`, no membership, no runtime: each test builds a real replicated agent table, gives the machine a
small view of it (`View`: this host's name, the member list, whether every OAC is decided), feeds inputs through
`step(now, input)` and checks the effects. A proposal is "committed" by applying its transaction to the table
(`Group.commit`), which is what every member does when OAC delivers it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from haa.core.agentio import FreezeAgent, KillAgent, SpawnShell, StartAgent
from haa.core.agents import recovery as rc
from haa.core.agents import transfer as tr
from haa.core.agents.agentstep import (
    MAX_RESPAWNS,
    Activate,
    AgentTimer,
    ArmTimer,
    Cmd,
    Committed,
    Forget,
    Hold,
    HostSend,
    Note,
    Propose,
    Reconcile,
    Route,
    SetPhase,
    ShellUp,
    Timeline,
)
from haa.core.agents.routing import Inbox, Outbox
from haa.core.ddb import agenttable as at
from haa.pb import agenttx_pb2 as apb

AGENT = "agent-0001"


@dataclass
class Group:
    """The replicated agent table of a group, and its member list (what OAC would apply on every member)."""

    members: list[str] = field(default_factory=lambda: ["h1", "h2", "h3"])
    table: at.AgentTable = field(default_factory=at.AgentTable)

    def commit(self, tx: apb.AgentTx) -> at.AgentApplied:
        return self.table.apply(at.encode(tx), tuple(self.members))

    def record(self) -> at.AgentRecord:
        r = self.table.get(AGENT)
        assert r is not None
        return r


@dataclass
class View:
    """What one host's machine reads (`AgentView`)."""

    name: str
    group: Group
    settled: bool = True

    @property
    def table(self) -> at.AgentTable:
        return self.group.table

    def members(self) -> list[str]:
        return list(self.group.members)

    def oacs_settled(self) -> bool:
        return self.settled


def tx(**body: object) -> apb.AgentTx:
    t = apb.AgentTx()
    for k, v in body.items():
        getattr(t, k).CopyFrom(v)
    return t


def msg(src: str, seq: int, payload: bytes = b"x") -> apb.RoutedMsg:
    return apb.RoutedMsg(src=src, src_life=1, seq=seq, dst=AGENT, payload=payload)


def only(effects: list, kind: type) -> list:
    return [e for e in effects if isinstance(e, kind)]


def proposal(effects: list, kind: str) -> Propose:
    props = [e for e in effects if isinstance(e, Propose) and e.kind == kind]
    assert len(props) == 1, effects
    return props[0]


def created(g: Group, recovery: str = "backup") -> None:
    assert g.commit(tx(create=apb.AgentCreate(id=AGENT, type="counter", cost=0.1, recovery=recovery,
                                              host="h1"))).ok


def running_on(g: Group, host: str) -> at.AgentRecord:
    """The agent created, allocated to `host` and recovered there (active, epoch 1)."""
    created(g)
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host=host))).ok
    assert g.commit(tx(recovered=apb.AgentRecovered(id=AGENT, host=host))).ok
    return g.record()


def frozen_for(g: Group, new_host: str, state: bytes = b"S", queue1: tuple[apb.RoutedMsg, ...] = ()) -> None:
    """The agent ran on h1 and was frozen there (its state and queue1 in the table), allocated to `new_host`."""
    r = running_on(g, "h1")
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host=new_host))).ok
    assert g.commit(tx(freeze=apb.AgentFreeze(id=AGENT, host="h1", epoch=r.epoch))).ok
    rel = apb.AgentRelease(id=AGENT, host="h1", epoch=r.epoch, state=state)
    rel.pending.extend(queue1)
    assert g.commit(tx(release=rel)).ok


# ------------------------------------------------------------------------------------------- Alg. 5: freeze


def freezing(g: Group) -> tuple[tr.Transfer, list]:
    """h1 runs the agent; the allocation moved it to h2; h1 starts the freeze."""
    r = running_on(g, "h1")
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2"))).ok
    t = tr.Transfer(View("h1", g))
    return t, t.step(1.0, tr.Freeze(AGENT, r.epoch, Inbox(), Outbox()))


def test_freeze_asks_the_instance_holds_queue1_and_releases_after_state_and_every_ack():
    g = Group()
    t, effs = freezing(g)
    assert only(effs, Cmd) == [Cmd(FreezeAgent(AGENT, 1))]  # Alg. 5 l. 2
    assert Timeline(AGENT, "freezing", "to h2") in effs
    res = g.commit(proposal(effs, "freeze").tx)  # ll. 5-8
    assert res.ok and g.record().status == at.FREEZING
    m1 = msg("other", 1)
    assert t.step(1.1, Hold(m1)) == []  # l. 4: held as queue1
    assert t.step(1.2, Committed(res)) == []  # l. 9: waits for the state and the acks of h2, h3
    assert t.step(1.3, tr.StateArrived(AGENT, b"STATE")) == []  # l. 19
    assert t.step(1.4, tr.Ack("h2", AGENT, claim=False)) == []
    effs = t.step(1.5, tr.Ack("h3", AGENT, claim=False))  # l. 10 holds: l. 11, then OAC(release)
    rel = proposal(effs, "release").tx.release
    assert rel.state == b"STATE" and list(rel.pending) == [m1]  # queue1 goes with the release
    m2 = msg("other", 2)
    assert t.step(1.6, Hold(m2)) == [tr.PassOn(m2)]  # after l. 11: to queue2, by the table
    res = g.commit(proposal(effs, "release").tx)
    assert res.ok and g.record().status == at.FROZEN and g.record().queue1 == [m1]
    assert t.step(1.7, Committed(res)) == [Forget(AGENT), Timeline(AGENT, "frozen")]
    assert t.freezes == {}


def test_freeze_acks_before_the_local_commit_count_and_a_removed_host_counts_as_acknowledged():
    g = Group()
    t, effs = freezing(g)
    res = g.commit(proposal(effs, "freeze").tx)
    t.step(1.1, tr.Ack("h3", AGENT, claim=False))  # h3 applied OAC(freeze) before h1 did
    t.step(1.2, tr.StateArrived(AGENT, b"S"))
    assert t.step(1.3, Committed(res)) == []  # h2 has not acknowledged
    g.members.remove("h2")  # the target crashed mid-transfer and was removed from the group
    effs = t.step(1.4, tr.Progress(AGENT))  # l. 10: "or h is removed"
    assert proposal(effs, "release").tx.release.state == b"S"


def test_the_freeze_of_an_instance_thawed_here_waits_for_its_own_freeze_acks():
    """Alg. 5 l. 10 waits for a freezeAck from every host of commitGroup: each host sends it once it committed
    OAC(freeze), after any message it had sent this host for the agent before, so what is still on its way
    arrives before l. 11 and goes with the release as queue1. The claimAcks of the thaw that started the
    instance here say nothing about that. Counted as freezeAcks (as the code did before, one set of acks per
    instance), they let h5 release at once in `haactl verify transfer --seed 599 --hosts 5`: a message h4 had
    sent before it applied the freeze reached h5 after l. 11, h5 pushed it to queue2 on its own, was removed
    before the push committed, and the message was lost for a receiver and a sender that never crashed."""
    g = Group()
    t, effs = thawing(g)  # h2 thaws the agent, then is asked to freeze it again
    t.step(2.1, Committed(g.commit(proposal(effs, "claim").tx)))
    t.step(2.2, ShellUp(AGENT))
    t.step(2.3, tr.Ack("h1", AGENT, claim=True))
    effs = t.step(2.4, tr.Ack("h3", AGENT, claim=True))
    assert isinstance(effs[0], Activate) and t.thaws == {}  # thawed: epoch 2 runs on h2
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h3"))).ok
    effs = t.step(3.0, tr.Freeze(AGENT, 2, effs[0].inbox, effs[0].outbox))
    t.step(3.1, Committed(g.commit(proposal(effs, "freeze").tx)))
    late = msg("b", 1)
    assert t.step(3.2, tr.StateArrived(AGENT, b"S")) == []  # no freezeAck yet: not l. 11
    assert t.step(3.3, Hold(late)) == []  # sent by h1 before it applied OAC(freeze): queue1
    assert t.step(3.4, tr.Ack("h1", AGENT, claim=False)) == []
    effs = t.step(3.5, tr.Ack("h3", AGENT, claim=False))
    assert list(proposal(effs, "release").tx.release.pending) == [late]


def test_other_hosts_acknowledge_a_committed_freeze_and_claim():
    g = Group()
    _t, effs = freezing(g)
    res = g.commit(proposal(effs, "freeze").tx)
    assert tr.Transfer(View("h3", g)).step(2.0, Committed(res)) == [HostSend("h1", "freeze_ack", AGENT, 1)]


def test_a_freeze_given_up_is_proposed_again_while_the_agent_is_still_ours():
    g = Group()
    t, effs = freezing(g)
    again = t.step(1.1, tr.Written("freeze", AGENT, 1, False))  # l. 8: do ... while not committed
    assert proposal(again, "freeze").tx == proposal(effs, "freeze").tx
    assert t.step(1.2, tr.Written("freeze", AGENT, 0, False)) == []  # another epoch's: not ours
    t.step(1.3, Committed(g.commit(proposal(effs, "freeze").tx)))
    assert t.step(1.4, tr.Written("freeze", AGENT, 1, False)) == []  # committed meanwhile


def test_a_release_given_up_is_retried_only_while_the_table_says_freezing_on_this_host():
    g = Group()
    t, effs = freezing(g)
    t.step(1.1, Committed(g.commit(proposal(effs, "freeze").tx)))
    t.step(1.2, tr.StateArrived(AGENT, b"S"))
    t.step(1.3, tr.Ack("h2", AGENT, claim=False))
    effs = t.step(1.4, tr.Ack("h3", AGENT, claim=False))
    assert proposal(t.step(1.5, tr.Written("release", AGENT, 1, False)), "release")  # l. 16
    g.record().status = at.CRASHED  # e.g. this host was removed meanwhile: the table moved on
    assert t.step(1.6, tr.Written("release", AGENT, 1, False)) == []


def test_an_instance_that_dies_while_freezing_is_lost_with_its_queue1():
    g = Group()
    t, _effs = freezing(g)
    m1 = msg("other", 1)
    t.step(1.1, Hold(m1))
    assert t.step(1.2, tr.ShellDied(AGENT, "killed", early=False)) == [tr.Lost(AGENT, 1, "killed", False, (m1,))]
    assert t.freezes == {}


# ------------------------------------------------------------------------------------------- Alg. 6: thaw


def thawing(g: Group, queue1: tuple[apb.RoutedMsg, ...] = ()) -> tuple[tr.Transfer, list]:
    frozen_for(g, "h2", queue1=queue1)
    t = tr.Transfer(View("h2", g))
    return t, t.step(2.0, tr.Thaw(AGENT))


def test_thaw_claims_then_starts_the_shell_with_queue1_queue2_and_the_local_queue_in_order():
    g = Group()
    q1 = msg("a", 1)
    t, effs = thawing(g, queue1=(q1,))
    assert effs[:3] == [SetPhase(AGENT, 2, "claiming"), Cmd(SpawnShell(AGENT, 2, "counter", "A1", b"", "")),
                        Timeline(AGENT, "thawing")]  # Alg. 6 l. 2
    q2 = msg("a", 2)
    g.record().queue2.append(q2)  # pushed by another host while the agent was frozen (Alg. 5 l. 23)
    local = msg("a", 3)
    assert t.step(2.1, Hold(local)) == []  # l. 3: the local queue
    res = g.commit(proposal(effs, "claim").tx)  # ll. 4-7
    assert res.ok and g.record().owner == "h2" and g.record().epoch == 2
    assert t.step(2.2, Committed(res)) == [SetPhase(AGENT, 2, "thawing")]  # the shell is not up yet
    assert t.step(2.3, ShellUp(AGENT)) == []  # l. 9: every claimAck
    t.step(2.4, tr.Ack("h1", AGENT, claim=True))
    view = t.view
    assert isinstance(view, View)
    view.settled = False  # l. 9: an OAC is still undecided
    assert t.step(2.5, tr.Ack("h3", AGENT, claim=True)) == [tr.PollLater()]
    view.settled = True
    effs = t.step(2.6, tr.Progress(AGENT))
    assert isinstance(effs[0], Activate) and effs[0].agent == AGENT and effs[0].epoch == 2  # l. 11
    start = effs[1]
    assert start == Cmd(StartAgent(AGENT, 2, "thaw", b"S", [q1, q2, local]))  # l. 10, in that order
    assert effs[2:] == [Timeline(AGENT, "thawed", "3 queued messages"), Reconcile(AGENT)]
    assert t.thaws == {}


def test_a_claim_refused_by_the_table_is_abandoned_and_its_held_messages_routed_again():
    g = Group()
    t, effs = thawing(g)
    held = msg("a", 1)
    t.step(2.1, Hold(held))
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h3"))).ok  # the allocation moved on
    res = g.commit(proposal(effs, "claim").tx)
    assert not res.ok
    effs = t.step(2.2, Committed(res))  # Alg. 6 l. 18
    assert effs[:2] == [Forget(AGENT), Cmd(KillAgent(AGENT, 2, f"abandoned: {res.reason}"))]
    assert effs[-1] == Route((held,))


def test_a_claim_given_up_is_retried_while_possible_then_abandoned():
    g = Group()
    t, effs = thawing(g)
    assert proposal(t.step(2.1, tr.Written("claim", AGENT, 2, False)), "claim")  # l. 7
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h3")))
    effs = t.step(2.2, tr.Written("claim", AGENT, 2, False))
    assert effs[0] == Forget(AGENT) and Note("agent_abandoned", {"agent": AGENT, "epoch": 2,
                                                                 "reason": "claim no longer possible"}) in effs


def test_a_claim_committed_at_a_later_epoch_gets_a_shell_for_that_epoch():
    g = Group()
    t, effs = thawing(g)
    g.record().epoch += 1  # another claim and freeze came back to us before ours committed
    res = g.commit(proposal(effs, "claim").tx)
    effs = t.step(2.2, Committed(res))
    assert effs[:3] == [Cmd(KillAgent(AGENT, 2, "stale shell (epoch 2, now 3)")), SetPhase(AGENT, 3, "claiming"),
                        Cmd(SpawnShell(AGENT, 3, "counter", "A1", b"", ""))]


def test_a_thaw_shell_that_dies_is_replaced_then_given_up():
    g = Group()
    t, effs = thawing(g)
    for i in range(MAX_RESPAWNS):
        effs = t.step(2.0 + i, tr.ShellDied(AGENT, "died", early=True))
        assert Cmd(SpawnShell(AGENT, 2, "counter", "A1", b"", "")) in effs
    held = msg("a", 1)
    t.step(3.0, Hold(held))
    assert t.step(4.0, tr.ShellDied(AGENT, "died", early=True)) == [tr.Lost(AGENT, 2, "died", True, (held,))]


def test_a_claim_committed_without_a_shell_is_reported():
    g = Group()
    frozen_for(g, "h2")
    res = g.commit(tx(claim=apb.AgentClaim(id=AGENT, host="h2")))
    assert tr.Transfer(View("h2", g)).step(2.0, Committed(res)) == [tr.ClaimedWithoutShell(AGENT, 2)]


# ------------------------------------------------------------------------------------------- Alg. 7: backup


def test_a_backup_is_proposed_for_the_instance_epoch_and_an_oversized_one_is_rejected():
    g = Group()
    running_on(g, "h1")
    r = rc.Recovery(View("h1", g))
    b = proposal(r.step(1.0, rc.Backup(AGENT, 1, b"B1")), "backup").tx
    assert g.commit(b).ok and g.record().backup == b"B1"  # Alg. 7 l. 5
    effs = r.step(1.1, rc.Backup(AGENT, 1, b"x" * (at.MAX_BLOB + 1)))
    assert effs == [Note("backup_rejected", {"agent": AGENT, "reason": "backup too large",
                                             "size": at.MAX_BLOB + 1})]
    assert r.backups_proposed == 1


def test_a_backup_from_an_older_epoch_does_not_replace_the_latest_and_recovery_uses_the_latest():
    g = Group()
    running_on(g, "h1")
    old = rc.Recovery(View("h1", g))
    late = proposal(old.step(1.0, rc.Backup(AGENT, 1, b"OLD")), "backup").tx  # still in OAC
    assert g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=1, reason="died"))).ok
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2"))).ok
    new = rc.Recovery(View("h2", g))
    effs = new.step(2.0, rc.Recover(AGENT))
    assert g.commit(proposal(effs, "recovered").tx).ok  # epoch 2 on h2
    assert g.commit(proposal(new.step(2.1, rc.Backup(AGENT, 2, b"NEW")), "backup").tx).ok
    assert not g.commit(late).ok  # the fenced epoch-1 instance cannot overwrite it
    assert g.record().backup == b"NEW"


# ------------------------------------------------------------------------------------------- Alg. 8: recovery


def crashed_on_h1(g: Group, backup: bytes = b"B") -> None:
    """The agent ran on h1 with a backup; h1 was removed from the group (the table crashed its agents)."""
    running_on(g, "h1")
    assert g.commit(tx(backup=apb.AgentBackup(id=AGENT, host="h1", epoch=1, data=backup))).ok
    g.members.remove("h1")
    g.table.on_removed(["h1"])


def test_recovery_when_the_host_that_ran_the_agent_is_gone_claims_first_then_starts_from_the_latest_backup():
    g = Group()
    crashed_on_h1(g, backup=b"LATEST")
    r = rc.Recovery(View("h2", g))
    orphan = msg("a", 5)
    r.step(3.0, rc.Orphan(AGENT, orphan))  # held while the agent was down
    assert r.step(3.1, rc.Crashed(AGENT)) == [Timeline(AGENT, "crashed", ""), Route((orphan,))]
    assert g.record().status == at.CRASHED and g.record().backup == b"LATEST"
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2"))).ok
    effs = r.step(3.2, rc.Recover(AGENT))
    assert effs[:3] == [SetPhase(AGENT, 2, "recovering"), Cmd(SpawnShell(AGENT, 2, "counter", "A1", b"", "")),
                        Timeline(AGENT, "recovering")]  # Alg. 8 l. 2
    held = msg("b", 1)  # another sender's stream (one stream keeps its order: a gap holds the rest back)
    r.step(3.3, Hold(held))
    assert r.step(3.4, ShellUp(AGENT)) == []  # the backup only once OAC(recovered) committed
    queued = msg("a", 4)
    g.record().queue1.append(queued)
    res = g.commit(proposal(effs, "recovered").tx)  # ll. 6-9
    effs = r.step(3.5, Committed(res))
    assert isinstance(effs[0], Activate) and effs[0].life == 2
    assert effs[1] == Cmd(StartAgent(AGENT, 2, "recover", b"LATEST", [queued, held]))  # l. 4, the latest backup
    assert effs[2:] == [Timeline(AGENT, "recovered", "from backup"), Reconcile(AGENT)]


@pytest.mark.parametrize(("strategy", "state"), [("backup", b"B"), ("restart", None)])
def test_recovery_strategy(strategy: str, state: bytes | None):
    g = Group()
    created(g, recovery=strategy)
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h1"))).ok
    assert g.commit(tx(recovered=apb.AgentRecovered(id=AGENT, host="h1"))).ok
    assert g.commit(tx(backup=apb.AgentBackup(id=AGENT, host="h1", epoch=1, data=b"B"))).ok
    assert g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=1, reason="x"))).ok
    r = rc.Recovery(View("h1", g))
    effs = r.step(5.0, rc.Recover(AGENT))
    r.step(5.1, ShellUp(AGENT))
    effs = r.step(5.2, Committed(g.commit(proposal(effs, "recovered").tx)))
    assert effs[1] == Cmd(StartAgent(AGENT, 2, "recover", state, []))


def test_a_new_agent_starts_fresh():
    g = Group()
    created(g)
    assert g.commit(tx(move=apb.AgentMove(id=AGENT, host="h1"))).ok
    r = rc.Recovery(View("h1", g))
    effs = r.step(1.0, rc.Recover(AGENT))
    assert Timeline(AGENT, "spawning") in effs
    r.step(1.1, Committed(g.commit(proposal(effs, "recovered").tx)))
    effs = r.step(1.2, ShellUp(AGENT))
    assert effs[1] == Cmd(StartAgent(AGENT, 1, "fresh", None, []))
    assert effs[2] == Timeline(AGENT, "active", "fresh state")


def test_a_recovery_another_host_won_is_abandoned():
    g = Group()
    crashed_on_h1(g)
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2")))
    r2 = rc.Recovery(View("h2", g))
    mine = proposal(r2.step(1.0, rc.Recover(AGENT)), "recovered").tx
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h3")))  # two sessions overlapped: h3 recovers it first
    assert g.commit(tx(recovered=apb.AgentRecovered(id=AGENT, host="h3"))).ok
    res = g.commit(mine)
    assert not res.ok
    effs = r2.step(1.1, Committed(res))
    assert effs[:2] == [Forget(AGENT), Cmd(KillAgent(AGENT, 2, f"abandoned: {res.reason}"))]
    assert r2.recoveries == {}


def test_a_failed_instance_is_reported_once_and_again_only_while_no_instance_runs():
    g = Group()
    running_on(g, "h1")
    r = rc.Recovery(View("h1", g))
    held = msg("a", 1)
    effs = r.step(1.0, rc.InstanceFailed(AGENT, 1, "died", early=True, msgs=(held,)))
    assert effs[:2] == [Forget(AGENT), Timeline(AGENT, "crashed", "died")]
    f = proposal(effs, "failed").tx.failed
    assert (f.epoch, f.reason, f.early) == (1, "died", True)
    assert r.orphans == {AGENT: [held]}  # until the table says where the agent is
    assert r.step(1.1, rc.ReportFailed(AGENT, 1, "again")) == []  # already in OAC
    assert proposal(r.step(1.2, rc.Written("failed", AGENT, 1, False, running=False)), "failed")
    r.step(1.3, rc.ReportFailed(AGENT, 1, "x"))
    assert r.step(1.4, rc.Written("failed", AGENT, 1, False, running=True)) == []
    res = g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=1, reason="died", early=True)))
    assert r.step(1.5, Committed(res)) == [Timeline(AGENT, "crashed", ""), Route((held,))]


def test_start_failures_back_off_before_the_next_recovery():
    g = Group()
    running_on(g, "h1")
    assert g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=1, reason="boom", early=True))).ok
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h1")))
    g.commit(tx(recovered=apb.AgentRecovered(id=AGENT, host="h1")))
    assert g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=2, reason="boom", early=True))).ok
    assert g.record().failures == 2
    r = rc.Recovery(View("h1", g), rc.BackoffConfig(base=0.5, cap=30.0))
    effs = r.step(10.0, rc.Recover(AGENT))
    assert effs[0] == ArmTimer(AgentTimer("backoff", AGENT), 11.0)  # 0.5 * 2 ** (2 - 1)
    assert not only(effs, Propose) and not only(effs, Cmd)
    assert r.step(10.5, rc.Recover(AGENT)) == []  # still waiting, the timer is armed
    assert proposal(r.step(11.0, rc.Recover(AGENT)), "recovered")
    assert r.backoff == {}


def test_a_backoff_is_forgotten_once_the_agent_is_allocated_elsewhere():
    g = Group()
    running_on(g, "h1")
    g.commit(tx(failed=apb.AgentFailed(id=AGENT, host="h1", epoch=1, reason="boom", early=True)))
    r = rc.Recovery(View("h1", g))
    r.step(1.0, rc.Recover(AGENT))
    assert AGENT in r.backoff
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2")))
    r.step(1.1, rc.Check(AGENT))
    assert r.backoff == {}


def test_a_recovery_shell_is_replaced_but_a_failed_spawn_is_a_start_failure():
    g = Group()
    created(g)
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h1")))
    r = rc.Recovery(View("h1", g))
    effs = r.step(1.0, rc.Recover(AGENT))
    assert Note("shell_respawn", {"agent": AGENT, "epoch": 1, "reason": "died"}) in r.step(
        1.1, rc.ShellDied(AGENT, "died"))
    effs2 = r.step(1.2, rc.ShellDied(AGENT, "spawn failed: bad config"))
    assert effs2 == [Forget(AGENT), Timeline(AGENT, "crashed", "spawn failed: bad config")]
    res = g.commit(proposal(effs, "recovered").tx)  # it commits after all: reported with the spawn's reason
    f = proposal(r.step(1.3, Committed(res)), "failed").tx.failed
    assert (f.reason, f.early) == ("spawn failed: bad config", True)


def test_a_dropped_agent_leaves_no_state_behind():
    g = Group()
    crashed_on_h1(g)
    g.commit(tx(move=apb.AgentMove(id=AGENT, host="h2")))
    r = rc.Recovery(View("h2", g))
    r.step(1.0, rc.Recover(AGENT))
    r.step(1.1, rc.Orphan(AGENT, msg("a", 1)))
    r.step(1.2, rc.Drop(AGENT, removed=True))
    assert r.recoveries == {} and r.orphans == {}


def test_timer_keys_print_as_the_tuples_they_replaced():
    assert str(AgentTimer("poll")) == str(("a", "poll"))
    assert str(AgentTimer("backoff", AGENT)) == str(("a", "backoff", AGENT))
    assert AgentTimer("retry") == AgentTimer("retry") and len({AgentTimer("retry"), AgentTimer("retry")}) == 1
