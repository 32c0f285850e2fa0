"""Deterministic simulation of the host group: membership (Alg. 3) and the replicated DDB.

`draw_group(seed, hosts, workload)` turns one seed into a scenario (swarm style, like `haa.lab.dsim.schedule`):
how many hosts and core processes, when each host starts (late starts are joins), a workload of DDB writes
from random members (`workload="ddb"`: many more, in batches of put/delete/append/cas/add/log_append/log_trim,
some of them cut short by a crash in the middle of their broadcast), voluntary leaves, crashes (some in the middle of a
broadcast, including the first core process before it forms the group), restarts as new incarnations,
pauses and delay spikes that make the failure detector suspect correct hosts. `run_group` runs it on a
`SimCluster` whose hosts are `MembershipNode`s, heals, runs to quiescence and checks (`check_group`):

Membership (`haactl verify membership`, `MEMBERSHIP_PROPS`):

* HM-Formation: exactly one correct group is ever formed, and one is formed.
* HM-Termination: after healing the run goes quiet (no membership, OAC or state-transfer traffic), and no
  member is left locked.
* HM-Non-Triviality-Join/-Leave/-Remove: then every live host's current incarnation is a member of one
  final view, which holds no crashed, superseded (-Remove) or departed (-Leave) process.
* HM-Weak-Validity: when a removal commits, every participant that voted for it suspected (per its own
  failure detector output at the time of its vote) every removed member.
* HM-Agreement: one (group, view id), one member set; every process's view ids increase; every process
  applies the same transaction at the same global sequence number (the same series of views).
* HM-Single-Leader: at most one acknowledged leader per view: every remove or membership transaction that
  changed the view was proposed by the front of the list (without the members it removed; ll. 79, 111).

DDB (`haactl verify ddb`, `DDB_PROPS`, plus HM-Agreement which they rest on):

* DDB-Prefix: the same state hash after the same sequence number on every process (deterministic apply).
* DDB-Convergence: after quiescence every live member holds the same state (the run must get quiet first).
* DDB-Durability: every acknowledged write is in every final replica.
* DDB-Atomicity: a write whose proposer crashed (in particular in the middle of its broadcast) is in every
  final replica or in none.
* DDB-Joiner-Consistency: a joiner's replica, when it becomes a member, equals the others' at that point.
* DDB-Exactly-Once: no write a sequencer batched is applied by two batches (retried and re-forwarded writes
  are deduplicated by origin and client sequence; docs/oac.md, "The sequencer"). Batches are told apart by
  their transaction id, not by the global seq they were applied at: a member removed while it was running
  (and crashed before it learnt so) numbers what it still delivers differently from the group.
* DDB-Bounded-Batch: no sequencer batch of more than one write carries more DDB ops than `seq_max_cost`
  (`SIM_NODE` sets it low, so that the writes' costs split batches): the apply of one transaction is bounded
  by the ops of one request (docs/limits.md).

Schedules run with the sequencer (writes forwarded to the leader, batched) except SEQUENCER_OFF_SHARE of them
(every member proposes its own writes, Alg. 3 as printed); BURST_SHARE of the DDB schedules have bursts in
which every host writes several times at one instant (many concurrent proposers).

Faults are drawn so that the thesis' assumptions hold (see `GroupSim._safe`): at most c_f core processes
fail, no false suspicion before FORMATION_TIMEOUT (§4.6.1: no erroneous exclusion during formation), and a
fault is injected only while every view and every open transaction keeps a correct majority (§4.5.1).
"""

from __future__ import annotations

import dataclasses
import functools
import random
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import haa.pb.ddb_pb2 as ddb_pb2
from haa.core.ddb import ops as ddbmod
from haa.core.host.hostcore import CoreConfig
from haa.core.inputs import LeaveGroup, Submit
from haa.core.membership.globalstate import TxDdb, TxMembership, TxRemove, TxSeq, decode_tx
from haa.core.membership.membership import AppliedTx, Left, MembershipNode, NodeConfig, ViewChange, WriteDone
from haa.core.messages import TxId
from haa.lab.dsim.cluster import ALIVE, CRASHED, PAUSED, SimCluster, SimHost
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.schedule import EXCLUDE_AFTER, SIM_UFD, Fault, _delay_model

Proc = tuple[str, int]

#: the failure detector of the group simulation: as in `haa.lab.dsim.schedule`, but its QoS configuration is
#: recomputed every 50 heartbeats (the thesis' N) instead of 20, which is most of the cost of a schedule
GROUP_UFD = dataclasses.replace(SIM_UFD, reevaluate_every=50)

SIM_NODE: dict[str, Any] = dict(
    formation_timeout=1.0,
    formation_retry=0.3,
    discovery=0.2,
    reapply=0.5,
    catchup_timeout=0.4,
    hash_every_apply=True,
    seq_retry=0.5,
    # two or three writes of the DDB workload (1-6 ops each) per batch: the costs split batches under load
    seq_max_cost=12,
)
#: a fault that would break the assumptions is tried again this much later (until the fault window ends)
GATE_RETRY = 0.1
#: the run is quiescent once no membership, OAC or state-transfer message was sent for this long (longer than
#: every periodic timer of the nodes: `reapply` is the longest)
QUIET_FOR = 1.0
QUIET_STEP = 0.25
#: a paused or spiked process counts as failed for this long after the pause or spike ends
SETTLE = 1.0


@dataclass
class GroupScenario:
    seed: int
    names: list[str]
    core: list[str]
    c_f: int
    delay: DelayModel
    offsets: list[float]
    drifts: list[float]
    starts: dict[str, float]
    features: dict[str, bool]
    faults: list[Fault] = field(default_factory=list)
    writes: list[tuple[float, str]] = field(default_factory=list)  # (time, host)
    leaves: list[tuple[float, str]] = field(default_factory=list)
    #: once the healed group is quiet, every running host asks to leave within 50 ms (the group dissolves, as
    #: in `haactl cluster down`)
    dissolve: bool = False
    fault_end: float = 4.0
    deadline: float = 40.0
    workload: str = "membership"  # or "ddb": many more writes, in batches
    batch_max: int = 1  # DDB ops per write (1 .. batch_max)
    #: writes go through the sequencer (NodeConfig.sequencer); off in SEQUENCER_OFF_SHARE of the schedules, so
    #: that Alg. 3's own path (every member proposes its writes) stays verified
    sequencer: bool = True

    def describe(self) -> list[str]:
        out = [
            f"seed={self.seed} hosts={self.names} core={self.core} c_f={self.c_f} delay={self.delay.describe()}",
            "features: " + ",".join(k for k, v in sorted(self.features.items()) if v),
            "starts: " + " ".join(f"{n}@{t:.2f}" for n, t in self.starts.items()),
        ]
        out += [f.describe() for f in self.faults]
        out += [f"t={t:.3f} leave {h}" for t, h in self.leaves]
        if self.dissolve:
            out.append("once the group is quiet, every running host leaves (dissolution)")
        out.append(
            f"{len(self.writes)} writes ({self.workload} workload, up to {self.batch_max} ops per batch, "
            f"{'through the sequencer' if self.sequencer else 'each proposed by its member'})"
        )
        return out


WORKLOADS = ("membership", "ddb")


#: share of the membership and DDB schedules that end with the whole group leaving (`GroupScenario.dissolve`)
DISSOLVE_SHARE = 0.1
#: share of the schedules whose members propose their own writes (no sequencer, `GroupScenario.sequencer`)
SEQUENCER_OFF_SHARE = 0.3
#: share of the DDB schedules with bursts: every member writes several times at one instant (many concurrent
#: proposers without the sequencer; a sequencer fed by every member at once with it)
BURST_SHARE = 0.5


def draw_group(seed: int, hosts: int = 7, workload: str = "membership", dissolve: bool = True) -> GroupScenario:
    if workload not in WORKLOADS:
        raise ValueError(f"unknown workload {workload!r}; choose from {WORKLOADS}")
    rng = random.Random(seed)
    n = rng.randint(3, max(3, hosts))
    names = [f"h{i + 1}" for i in range(n)]
    c = rng.choice([1, 3, 3, 3]) if n >= 3 else 1
    core = names[:c]
    c_f = (c - 1) // 2
    feats = {k: rng.random() < 0.5 for k in ("crash", "late_join", "leave", "restart", "pause", "spike", "mid")}
    delay = _delay_model(rng)
    offsets = [rng.uniform(-1000, 1000) for _ in names]
    drifts = [rng.uniform(-1e-4, 1e-4) for _ in names]
    starts = {nm: rng.uniform(0.0, 0.3) for nm in names}
    if feats["late_join"]:
        for nm in rng.sample(names[c:], k=min(len(names) - c, rng.randint(1, 2))):
            starts[nm] = rng.uniform(0.5, 3.5)
    sc = GroupScenario(seed, names, core, c_f, delay, offsets, drifts, starts, feats)
    quiet_from = SIM_NODE["formation_timeout"] + 0.5  # no false suspicion before formation (§4.6.1)
    # hosts that crash, leave or pause: fewer than half of all hosts (a removal needs a quorum of the view,
    # docs/membership.md), and at most c_f core processes
    early = sum(1 for t in starts.values() if t < 0.5)
    budget = (early - 1) // 2  # every OAC's participants keep a correct majority (f < n/2, §4.5.1)
    budget_core = c_f
    troubled: set[str] = set()

    def pick(allow_core: bool) -> str | None:
        nonlocal budget, budget_core
        pool = [h for h in names if h not in troubled and (allow_core or h not in core)]
        if budget <= 0 or not pool:
            return None
        nm = rng.choice(pool)
        if nm in core:
            if budget_core <= 0:
                return None
            budget_core -= 1
        budget -= 1
        troubled.add(nm)
        return nm

    if feats["crash"]:
        for _ in range(rng.randint(1, 2)):
            nm = pick(True)
            if nm is None:
                continue
            t = rng.uniform(0.0, 0.15) if nm == core[0] and rng.random() < 0.3 else rng.uniform(0.3, 3.5)
            kind = "crash_mid" if feats["mid"] and rng.random() < 0.5 else "crash"
            sc.faults.append(Fault(t, kind, nm))
            if feats["restart"] and rng.random() < 0.7:
                sc.faults.append(Fault(t + rng.uniform(0.3, 1.5), "restart", nm))
    if feats["pause"]:
        for _ in range(rng.randint(1, 2)):
            nm = pick(True)
            if nm is None:
                continue
            t = rng.uniform(quiet_from, 3.5)
            sc.faults.append(Fault(t, "pause", nm, duration=rng.uniform(0.05, 2.5)))
    if feats["spike"]:
        for _ in range(rng.randint(1, 4)):
            a, b = rng.sample(names, 2)
            t = rng.uniform(quiet_from, 3.5)
            extra = DelayModel("uniform", rng.uniform(0.05, 0.4), rng.uniform(0.0, 0.3))
            sc.faults.append(Fault(t, "spike", a, b if rng.random() < 0.7 else "", rng.uniform(0.2, 1.0), extra))
    if feats["leave"]:
        for _ in range(rng.randint(1, 2)):
            nm = pick(False)
            if nm is not None:
                sc.leaves.append((rng.uniform(1.5, 3.8), nm))
    if workload == "ddb":
        sc.workload = workload
        sc.batch_max = 6
        n_writes = rng.randint(25, 70)
    else:
        n_writes = rng.randint(5, 40)
    for _ in range(n_writes):
        sc.writes.append((rng.uniform(0.5, sc.fault_end), rng.choice(names)))
    sc.faults.sort(key=lambda f: f.time)
    # one schedule in DISSOLVE_SHARE ends with every host leaving at once. Drawn from a generator of its own
    # so that the rest of every seed's schedule stays what it was before this was added.
    sc.dissolve = dissolve and random.Random(seed * 7907 + 23).random() < DISSOLVE_SHARE
    # (each from a generator of its own, like `dissolve`)
    rs = random.Random(seed * 104729 + 11)
    sc.sequencer = rs.random() >= SEQUENCER_OFF_SHARE
    if workload == "ddb" and rs.random() < BURST_SHARE:
        for _ in range(rs.randint(1, 3)):
            t = rs.uniform(0.5, sc.fault_end)
            for _ in range(rs.randint(1, 4)):
                for nm in names:
                    sc.writes.append((t, nm))
        sc.writes.sort()
    return sc


# ------------------------------------------------------------------------------------------------ the run


@dataclass
class GroupHistory:
    views: dict[Proc, list[tuple[str, int, tuple[Proc, ...], float]]] = field(default_factory=lambda: defaultdict(list))
    correct_groups: set[str] = field(default_factory=set)
    # per process: (seq, txid, state hash, group, front of the member list, view) after each applied transaction
    applied: dict[Proc, list[tuple[int, TxId, str, str, Proc | None, int]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    votes: list[tuple[float, Proc, TxId, bool, Any, dict[Proc, bool]]] = field(default_factory=list)
    acked: dict[Any, tuple[Proc, TxId, int]] = field(default_factory=dict)
    write_proposer: dict[TxId, Proc] = field(default_factory=dict)  # every DDB write transaction seen
    #: (group, batch txid) -> (global seq where first applied, the (origin, cseq) writes it applied) (DDB-Exactly-Once)
    seq_applied: dict[tuple[str, TxId], tuple[int, tuple[tuple[Proc, int], ...]]] = field(default_factory=dict)
    #: (group, batch txid) -> (writes, DDB ops) it carried (DDB-Bounded-Batch)
    seq_cost: dict[tuple[str, TxId], tuple[int, int]] = field(default_factory=dict)
    # per process: (group, seq, txid, decoded remove/membership transaction)
    group_txs: dict[Proc, list[tuple[str, int, TxId, Any]]] = field(default_factory=lambda: defaultdict(list))
    joins: dict[Proc, tuple[str, int, str]] = field(default_factory=dict)  # (group, seq, state hash) at join
    mid_commit: list[Proc] = field(default_factory=list)  # processes armed to crash inside a write broadcast
    leave_requested: dict[Proc, float] = field(default_factory=dict)
    left: dict[Proc, float] = field(default_factory=dict)
    group_msgs: int = 0
    dropped: list[Fault] = field(default_factory=list)  # faults the assumptions did not allow (`GroupSim._safe`)


class GroupSim:
    """Runs one `GroupScenario` (see the module docstring)."""

    def __init__(self, sc: GroupScenario, trace: bool = False) -> None:
        self.sc = sc
        self.rng = random.Random(sc.seed * 7919 + 1)
        cfg = CoreConfig(ufd=GROUP_UFD, exclude_after=EXCLUDE_AFTER)
        self.node_cfg = NodeConfig(core=cfg, c_f=sc.c_f, sequencer=sc.sequencer, **SIM_NODE)
        self.cl = SimCluster(sc.names, self.rng, sc.delay, cfg, sc.offsets, sc.drifts, trace=trace)
        self.cl.make_core = self._make_node
        self.cl.on_effect = self._on_effect
        self.cl.may_crash = self._may_crash_now
        self.armed: dict[str, Fault] = {}  # mid-step crashes armed and not fired yet
        self.gh = GroupHistory()
        self.core_list = [(nm, nm) for nm in sc.core]
        self.req = 0
        self.known: dict[str, dict[str, str]] = {}
        self.rreq = random.Random(sc.seed * 31 + 7)
        # which list appends become log ops, and their details: a stream of its own, so that the draws of
        # `rreq` (and with them every schedule the verifiers' pinned seeds rely on) stay as they were
        self.rlog = random.Random(sc.seed * 613 + 3)
        self.trouble: dict[Proc, float] = {}  # process -> until when it counts as failed for `_safe`
        self.quiescent = False
        self.restart_due = 0.0  # the latest restart scheduled so far
        self.dissolved = False
        self.before_dissolution: list[GroupViolation] = []
        for h in self.cl.by_idx:
            h.state = CRASHED  # not started yet

    def _make_node(self, h: SimHost, inc: int) -> MembershipNode:
        cl = self.cl
        # what the previous incarnation knew (the daemon keeps it in --data-dir)
        known = sorted(self.known.get(h.name, {}).items())
        node = MembershipNode(h.name, inc, h.name, self.core_list, self.node_cfg, known)
        proc = (h.name, inc)
        orig = node._evaluate

        def evaluate(txid: TxId, payload: bytes, participants: tuple[Proc, ...], _p: Proc = proc) -> bool:
            vote = orig(txid, payload, participants)
            try:
                tx = decode_tx(payload)
            except ValueError:
                tx = None
            if type(tx) in (TxDdb, TxSeq):
                self.gh.write_proposer.setdefault(txid, (txid.host, txid.inc))
            elif type(tx) is TxRemove:
                # the voter's failure-detector output about each member to remove, sampled at the vote
                fd = {q: node.core.is_suspected(q[0], q[1]) for q in tx.removal}
                self.gh.votes.append((cl.now, _p, txid, vote, tx, fd))
            cl.history.votes.setdefault(txid, {})[_p] = vote
            return vote

        setattr(node, "_evaluate", evaluate)  # noqa: B010 (the verifier records every vote the node takes)
        return node

    def _on_effect(self, h: SimHost, e: Any) -> None:
        proc = (h.name, h.inc)
        t = type(e)
        gh = self.gh
        if t is ViewChange:
            self.known[h.name] = {m.name: m.addr for m in e.members}
        if t is AppliedTx:
            st = h.membership.state
            gh.applied[proc].append((e.seq, e.txid, e.state_hash, st.genesis, e.front, e.view))
            if e.kind in ("remove", "membership"):
                gh.group_txs[proc].append((st.genesis, e.seq, e.txid, decode_tx(e.payload)))
            elif e.kind == "seq":
                gh.seq_applied.setdefault(
                    (st.genesis, e.txid), (e.seq, tuple((r.origin, r.cseq) for r in e.result if r.applied))
                )
                if (st.genesis, e.txid) not in gh.seq_cost:
                    gh.seq_cost[(st.genesis, e.txid)] = _seq_cost(e.payload)
        elif t is ViewChange:
            gh.views[proc].append((e.group, e.view, tuple(m.proc for m in e.members), self.cl.now))
            if e.correct:
                gh.correct_groups.add(e.group)
            if any(m.proc == proc for m in e.added):
                # the state hash at that seq (the node may have applied more before its effects are carried out)
                got = next((it[2] for it in reversed(gh.applied[proc]) if it[0] == e.seq), "")
                gh.joins[proc] = (e.group, e.seq, got)
            self.cl._note(f"view {e.view} at {h.name}#{h.inc}: {[m.name for m in e.members]}")
        elif t is WriteDone:
            if e.ok:
                gh.acked[e.req] = (proc, e.txid, e.seq)
        elif t is Left:
            gh.left[proc] = self.cl.now
            self.cl._note(f"left {h.name}#{h.inc}")
            h.state = CRASHED
            h.core = None
            self.cl.history.ended.setdefault(proc, self.cl.now)

    def _op(self, name: str, node: MembershipNode) -> Any:
        r = self.rreq
        key = f"k{r.randint(0, 5)}"
        kind = r.random()
        if kind < 0.4:
            return ddbmod.put(key, "json", {"v": r.randint(0, 1000), "by": name})
        if kind < 0.6:
            n, item = r.randint(0, 2), r.randbytes(4)
            return self._append_op(node, key, n, item)
        if kind < 0.8:
            return ddbmod.add(f"c{r.randint(0, 2)}", r.randint(-5, 5))
        if kind < 0.9:
            if self.sc.workload == "ddb":  # read-modify-write against the local replica: often races
                obj = node.state.ddb.get(key)
                ver = obj.version if obj is not None and obj.type_name == "blob" else 0
                return ddbmod.cas(key, ver if r.random() < 0.8 else ver + 1, "blob", r.randbytes(3))
            return ddbmod.cas(key, r.randint(0, 30), "blob", r.randbytes(3))
        return ddbmod.delete(key)

    def _append_op(self, node: MembershipNode, key: str, n: int, item: bytes) -> Any:
        """A list append, or (drawn from `rlog`) a log append or trim: on log `g<n>`, or now and then on `key`
        (type mismatches with the puts there; a delete there recreates the log at index 0). A trim reads the
        local replica, as the cas does, and aims around the log's range: a no-op below it, a failure above."""
        g = self.rlog
        pick = g.random()
        if pick < 0.4:
            return ddbmod.append(f"l{n}", item, 8)
        log_key = key if g.random() < 0.1 else f"g{n}"
        if pick < 0.75:
            return ddbmod.log_append(log_key, [item + bytes([j]) for j in range(g.randint(1, 3))])
        obj = node.state.ddb.get(log_key)
        if obj is not None and obj.type_name == "log":
            first, items = obj.raw
            return ddbmod.log_trim(log_key, g.randint(max(0, first - 1), first + len(items) + 1))
        return ddbmod.log_trim(log_key, g.randint(0, 3))

    def _write(self, name: str) -> None:
        h = self.cl.hosts[name]
        node = h.core
        if h.state != ALIVE or node is None or not isinstance(node, MembershipNode):
            return
        r = self.rreq
        n_ops = r.randint(1, self.sc.batch_max) if self.sc.batch_max > 1 else 1
        ops = [self._op(name, node) for _ in range(n_ops)]
        atomic = n_ops > 1 and r.random() < 0.3
        self.req += 1
        payload = ddbmod.encode_batch(ops, origin=name, client_seq=self.req, atomic=atomic)
        node.step(h.local(self.cl.now), Submit(payload, (name, self.req), cost=n_ops))
        self.cl._apply(h)

    def _leave(self, name: str) -> None:
        h = self.cl.hosts[name]
        node = h.core
        if h.inc == 0 and self.cl.now + GATE_RETRY <= self.sc.fault_end:  # not started yet
            self.cl.at(self.cl.now + GATE_RETRY, lambda: self._leave(name))
            return
        if h.state != ALIVE or node is None:
            return
        self.gh.leave_requested[(name, h.inc)] = self.cl.now
        node.step(h.local(self.cl.now), LeaveGroup())
        self.cl._apply(h)

    def run(self) -> None:
        cl = self.cl
        sc = self.sc
        for nm, t in sc.starts.items():
            cl.at(t, functools.partial(self._start, nm))
        restarts: dict[int, float] = {}  # index of a crash fault -> delay of the restart drawn for it
        for i, f in enumerate(sc.faults):
            if f.kind in ("crash", "crash_mid"):
                nxt = next((g for g in sc.faults[i + 1 :] if g.host == f.host and g.kind == "restart"), None)
                if nxt is not None and nxt.time >= f.time:
                    restarts[i] = nxt.time - f.time
        for i, f in enumerate(sc.faults):
            if f.kind in ("crash", "crash_mid"):
                cl.at(f.time, functools.partial(self._gated, f, functools.partial(self._crash, f, restarts.get(i))))
            elif f.kind == "pause":
                cl.at(f.time, functools.partial(self._gated, f, functools.partial(self._pause, f)))
            elif f.kind == "spike":
                cl.at(f.time, functools.partial(self._gated, f, functools.partial(self._spike, f)))
        for t, nm in sc.writes:
            cl.at(t, functools.partial(self._write, nm))
        for t, nm in sc.leaves:
            cl.at(t, functools.partial(self._leave, nm))
        cl.run(sc.fault_end)
        for h in cl.by_idx:  # heal
            if h.state == PAUSED:
                cl.resume(h.name)
        t = sc.fault_end
        quiet_for = 0.0
        while t < sc.deadline:
            t += QUIET_STEP
            before = self._activity()
            cl.run(t)
            if self._quiet() and self._activity() == before:
                quiet_for += QUIET_STEP
                if quiet_for >= QUIET_FOR:
                    if not sc.dissolve or self.dissolved:
                        break
                    if cl.now >= self.restart_due:  # a host restarted after its group is gone re-applies forever
                        # the checks of the settled group, before it is gone (`check_group` adds them)
                        self.quiescent = True
                        self.before_dissolution = _check(self)
                        self._dissolve()
                        quiet_for = 0.0
            else:
                quiet_for = 0.0
        self.quiescent = quiet_for >= QUIET_FOR

    # ------------------------------------------------------------------ faults, within the assumptions

    def _start(self, name: str) -> None:
        h = self.cl.hosts[name]
        if h.inc == 0:
            self.cl._boot(h, 1)

    def _gated(self, f: Fault, act: Any) -> None:
        """Inject fault `f` now if it keeps the thesis' failure assumptions, else retry a little later (until
        the end of the fault window, then drop it). See `_safe`."""
        h = self.cl.hosts[f.host]
        if h.inc > 0 and h.state == ALIVE and self._safe((f.host, h.inc), f.kind in ("crash", "crash_mid")):
            act()
            return
        nxt = self.cl.now + GATE_RETRY
        if nxt <= self.sc.fault_end:
            self.cl.at(nxt, lambda: self._gated(f, act))
        else:
            self.gh.dropped.append(f)
            self.cl._note(f"fault dropped (assumptions): {f.describe()}")

    def _safe(self, x: Proc, crash: bool = False) -> bool:
        """OAC (Alg. 2) decides only while fewer than half of a transaction's participants fail (§4.5.1), and
        Alg. 3 proposes to the members it does not suspect; a falsely suspected or paused process counts as
        failed (§4.3.1: a process at the end of a suspected channel "is assumed to have crashed"). A fault on
        `x` is allowed only if, in every current view and every open transaction that holds `x`, the
        processes in trouble (crashed, superseded, paused, spiked, permanently suspected) stay fewer than
        half with `x` added. Without this, a group of two blocks on the crash of one member with a
        transaction in flight, whatever the membership algorithm does (docs/membership.md).

        A crashed applicant may still be accepted (its failure is not detected yet, and a crash in the middle
        of a step happens up to 0.1 s later): for a crash, every view counts with `x` added."""
        cl = self.cl
        now = cl.now
        sets: set[tuple[Proc, ...]] = set()
        dead: set[Proc] = set()
        for h in cl.by_idx:
            node = h.membership  # an AgentNode (haa.lab.dsim.agents) wraps the membership node
            if node is None or h.state == CRASHED or not isinstance(node, MembershipNode):
                continue
            dead |= node.core.dead
            if node.is_member():
                view = tuple(node.state.procs())
                sets.add(view)
                if crash and x not in view:
                    sets.add((*view, x))
            for tx in node.oac.txs.values():
                if tx.parts:
                    sets.add(tuple(tx.parts))

        def bad(p: Proc) -> bool:
            h = cl.hosts[p[0]]
            return h.inc != p[1] or h.state != ALIVE or p in dead or self.trouble.get(p, -1.0) > now

        for s in sets:
            if x in s:
                n_bad = 1 + sum(1 for p in s if p != x and bad(p))
                if 2 * n_bad >= len(s):
                    return False
        return True

    def _may_crash_now(self, name: str) -> bool:
        """An armed mid-step crash of `name` is about to fire: only if it still keeps the assumptions (`_safe`);
        else it is dropped like any fault that would break them, and `name` is no longer in trouble."""
        h = self.cl.hosts[name]
        proc = (name, h.inc)
        f = self.armed.pop(name, None)
        self.trouble.pop(proc, None)  # (its own armed crash is not a fault of the others' views)
        if self._safe(proc, crash=True):
            self.trouble[proc] = float("inf")
            return True
        if f is not None:
            self.gh.dropped.append(f)
        return False

    def _crash(self, f: Fault, restart_after: float | None) -> None:
        h = self.cl.hosts[f.host]
        self.trouble[(f.host, h.inc)] = float("inf")
        if f.kind == "crash_mid":
            self.armed[f.host] = f
        self.cl.crash(f.host, mid_step=f.kind == "crash_mid")
        if f.kind == "crash_mid" and self.sc.workload == "ddb" and h.state == ALIVE:
            # a write whose broadcast the crash cuts short (DDB-Atomicity: everywhere or nowhere)
            self.gh.mid_commit.append((f.host, h.inc))
            self._write(f.host)
        if restart_after is not None:
            self.restart_due = max(self.restart_due, self.cl.now + restart_after)
            self.cl.at(self.cl.now + restart_after, lambda: self._restart(f.host))

    def _dissolve(self) -> None:
        """Every host leaves within 50 ms (`GroupScenario.dissolve`).

        Only a quiet group is dissolved, once no restart is due (by design, a host restarted after its group
        is gone re-applies to it forever). Leaving all at once in the middle of membership changes can block:
        a leader left alone that accepts an applicant whose incarnation has meanwhile ended proposes an OAC
        to the two of them, which Alg. 2 cannot decide with one of two participants gone (docs/membership.md,
        "dissolution")."""
        self.dissolved = True
        rd = random.Random(self.sc.seed * 7907 + 29)
        for nm in self.sc.names:
            self.cl.at(self.cl.now + rd.uniform(0.0, 0.05), functools.partial(self._leave, nm))

    def _pause(self, f: Fault) -> None:
        cl = self.cl
        h = cl.hosts[f.host]
        end = min(cl.now + f.duration, self.sc.fault_end)
        self.trouble[(f.host, h.inc)] = end + SETTLE
        cl.pause(f.host)
        cl.at(end, lambda: cl.resume(f.host))

    def _spike(self, f: Fault) -> None:
        cl = self.cl
        h = cl.hosts[f.host]
        self.trouble[(f.host, h.inc)] = cl.now + f.duration + SETTLE
        cl.spike(f.host, f.other or None, f.extra, f.duration)  # type: ignore[arg-type]

    def _restart(self, name: str) -> None:
        h = self.cl.hosts[name]
        if (name, h.inc) in self.gh.left or h.state != CRASHED:
            return  # it left, or was already reincarnated
        self.cl.restart(name)

    def _activity(self) -> int:
        c = self.cl.msg_counts
        return sum(v for k, v in c.items() if k not in ("Heartbeat", "SetPeriod"))

    def _quiet(self) -> bool:
        for h in self.cl.by_idx:
            node = h.membership
            if node is None:
                continue
            if node.oac.txs or node.upd.updating or node.direct_q or node.wr.held or node.wr.writes:
                return False
        return True


# ------------------------------------------------------------------------------------------------ checks


MEMBERSHIP_PROPS = frozenset(
    {
        "HM-Formation",
        "HM-Termination",
        "HM-Non-Triviality-Join",
        "HM-Non-Triviality-Leave",
        "HM-Non-Triviality-Remove",
        "HM-Weak-Validity",
        "HM-Agreement",
        "HM-Single-Leader",
    }
)
DDB_PROPS = frozenset(
    {"HM-Agreement", "DDB-Prefix", "DDB-Convergence", "DDB-Durability", "DDB-Atomicity", "DDB-Joiner-Consistency",
     "DDB-Exactly-Once", "DDB-Bounded-Batch"}
)
#: which properties each verifier reports (`haactl verify membership|ddb`)
VERIFIER_PROPS = {"membership": MEMBERSHIP_PROPS, "ddb": DDB_PROPS}


@dataclass
class GroupViolation:
    prop: str
    detail: str
    hosts: list[str] = field(default_factory=list)  # for picking trace lines

    def __str__(self) -> str:
        return f"{self.prop}: {self.detail}"


def _p(p: Proc | None) -> str:
    return f"{p[0]}#{p[1]}" if p else "-"


def check_group(sim: GroupSim, props: frozenset[str] | None = None) -> list[GroupViolation]:
    """Check a finished run (see the module docstring); `props` keeps only those properties."""
    out = _check(sim)
    seen = {(v.prop, v.detail) for v in out}
    out += [v for v in sim.before_dissolution if (v.prop, v.detail) not in seen]
    if props is not None:
        out = [v for v in out if v.prop in props]
    return out


def _seq_cost(payload: bytes) -> tuple[int, int]:
    """(writes, DDB ops) of an applied sequencer batch, counted from its bytes (a test write counts 1)."""
    tx = decode_tx(payload)
    assert isinstance(tx, TxSeq)
    ops = 0
    for entry in tx.entries:
        inner = decode_tx(entry.tx)
        ops += len(ddb_pb2.DdbBatch.FromString(inner.data).ops) if isinstance(inner, TxDdb) else 1
    return len(tx.entries), ops


def _check(sim: GroupSim) -> list[GroupViolation]:
    cl = sim.cl
    gh = sim.gh
    hist = cl.history
    out: list[GroupViolation] = []

    def bad(prop: str, detail: str, *procs: Proc | None) -> None:
        out.append(GroupViolation(prop, detail, sorted({p[0] for p in procs if p})))

    # HM-Formation (safety part): never two correct groups
    if len(gh.correct_groups) > 1:
        bad("HM-Formation", f"more than one correct group formed: {sorted(gh.correct_groups)}")
    # HM-Agreement: one (group, view id), one member set; increasing ids per process
    view_sets: dict[tuple[str, int], tuple[tuple[Proc, ...], Proc]] = {}
    for proc, vs in gh.views.items():
        last = 0
        for g, v, members, t in vs:
            if v <= last:
                bad("HM-Agreement", f"{_p(proc)} view ids not increasing: {last} then {v}", proc)
            last = v
            prev = view_sets.setdefault((g, v), (members, proc))
            if prev[0] != members:
                bad(
                    "HM-Agreement",
                    f"group {g} view {v}: {_p(proc)} has {[_p(m) for m in members]} at {t:.3f}, "
                    f"{_p(prev[1])} has {[_p(m) for m in prev[0]]}",
                    proc,
                    prev[1],
                )
                break
    # the global sequence: the same transaction (HM-Agreement) and the same state (DDB-Prefix) at every seq.
    # A member removed while it was running (false suspicion; it then restarts as a new incarnation) does not
    # deliver the transaction that removed it, so what it applies afterwards is not the group's sequence.
    groups = gh.correct_groups or {""}
    main = min(groups)
    removed_alive = {p for p in hist.ended if p not in hist.crash_time and p not in gh.left}
    join_at = {p: seq for p, (g, seq, _h) in gh.joins.items() if g == main}
    at_seq: dict[int, tuple[TxId, str, Proc, Proc | None, int]] = {}
    for proc, items in gh.applied.items():
        if proc in removed_alive:
            continue
        for seq, txid, h, g, front, view in items:
            if g == main and seq != join_at.get(proc):
                at_seq.setdefault(seq, (txid, h, proc, front, view))
    diverged: set[Proc] = set()
    for proc, (g, seq, h) in gh.joins.items():  # DDB-Joiner-Consistency
        ref = at_seq.get(seq)
        if g != main or proc in removed_alive or ref is None:
            continue
        if ref[1] != h:
            diverged.add(proc)
            bad(
                "DDB-Joiner-Consistency",
                f"{_p(proc)} joined at seq {seq} with state {h[:12]}, {_p(ref[2])} had {ref[1][:12]}",
                proc,
                ref[2],
            )
    for proc, items in gh.applied.items():
        if proc in removed_alive or proc in diverged:
            continue
        for seq, txid, h, g, _f, _v in items:
            ref = at_seq.get(seq)
            if g != main or ref is None or (ref[0] == txid and ref[1] == h):
                continue
            if ref[0] != txid:
                bad(
                    "HM-Agreement", f"seq {seq}: {_p(proc)} applied {txid}, {_p(ref[2])} applied {ref[0]}", proc, ref[2]
                )
            else:
                bad(
                    "DDB-Prefix",
                    f"seq {seq} ({txid}): state {h[:12]} at {_p(proc)}, {ref[1][:12]} at {_p(ref[2])}",
                    proc,
                    ref[2],
                )
            break
    # HM-Single-Leader: only the front of the list changes it (ll. 79, 111). A former leader's transaction
    # ordered after its replacement is applied as a no-op (GlobalState, "stale"): only changes count.
    seen: set[int] = set()
    for proc, recs in gh.group_txs.items():
        if proc in removed_alive:
            continue
        for g, seq, txid, tx in recs:
            if g != main or seq in seen:
                continue
            seen.add(seq)
            after, before = at_seq.get(seq), at_seq.get(seq - 1)
            if after is None or before is None or after[4] == before[4]:
                continue  # the view did not change (a lock, a no-op), or the view before is not known
            if type(tx) is TxRemove and after[3] != tx.proposer:
                bad(
                    "HM-Single-Leader",
                    f"seq {seq}: remove {txid} by {_p(tx.proposer)} committed, but the front of the list without "
                    f"the removed members is {_p(after[3])}",
                    tx.proposer,
                    after[3],
                )
            elif type(tx) is TxMembership and before[3] not in (None, tx.proposer):
                bad(
                    "HM-Single-Leader",
                    f"seq {seq}: membership {txid} by {_p(tx.proposer)} committed in view {before[4]}, whose "
                    f"leader is {_p(before[3])}",
                    tx.proposer,
                    before[3],
                )
    # HM-Weak-Validity
    committed = {it[1] for items in gh.applied.values() for it in items}
    for t, proc, txid, vote, tx, fd in gh.votes:
        if not vote or txid not in committed:
            continue
        for target in tx.removal:
            if not fd[target]:
                bad(
                    "HM-Weak-Validity",
                    f"{_p(proc)} voted to remove {_p(target)} in {txid} at {t:.3f} without suspecting it",
                    proc,
                    target,
                )
    if not sim.quiescent:
        bad("HM-Termination", f"not quiescent by t={sim.sc.deadline}")
        bad("DDB-Convergence", f"not quiescent by t={sim.sc.deadline}: replicas never settled")
        return out
    # after healing and quiescence
    live = [h for h in cl.by_idx if h.state == ALIVE and isinstance(h.core, MembershipNode)]
    for p, t in sorted(gh.leave_requested.items()):  # HM-Non-Triviality-Leave, also when nobody stays
        h = cl.hosts[p[0]]
        if p not in gh.left and (h.name, h.inc) == p and h.state == ALIVE:
            bad("HM-Non-Triviality-Leave", f"{_p(p)} asked to leave at {t:.3f} and is still running", p)
    if not live:
        return out
    if not gh.correct_groups:
        bad("HM-Formation", "no correct group was formed")
        return out
    nodes = {(h.name, h.inc): h.core for h in live if isinstance(h.core, MembershipNode)}  # `live` is these
    members = {p: n for p, n in nodes.items() if n.is_member()}
    if not members:
        bad("HM-Non-Triviality-Join", f"no live host is a member: {sorted(_p(p) for p in nodes)}", *nodes)
        return out
    ref_p = max(members, key=lambda p: (members[p].state.view, p))
    ref = members[ref_p].state
    final = set(ref.procs())
    for p, n in members.items():
        st = n.state
        if (st.view, st.procs()) != (ref.view, ref.procs()):
            bad(
                "HM-Agreement",
                f"final views differ: {_p(p)} view {st.view} {[_p(q) for q in st.procs()]}, {_p(ref_p)} view "
                f"{ref.view} {[_p(q) for q in ref.procs()]}",
                p,
                ref_p,
            )
        elif (st.seq, st.content_hash()) != (ref.seq, ref.content_hash()):
            bad(
                "DDB-Convergence",
                f"final replicas differ: {_p(p)} seq {st.seq} {st.content_hash()[:12]}, {_p(ref_p)} seq {ref.seq} "
                f"{ref.content_hash()[:12]}",
                p,
                ref_p,
            )
    for p, n in members.items():
        if n.upd.locked is not None:  # quiet, yet holding the global state for a membership change
            bad("HM-Termination", f"{_p(p)} is still locked ({n.upd.locked}) at the end", p)
    for p in sorted(set(nodes) - final):
        bad("HM-Non-Triviality-Join", f"live {_p(p)} is not in the final view {ref.view} {sorted(final)}", p)
    for p in sorted(final - set(nodes)):
        if p in gh.leave_requested:
            bad("HM-Non-Triviality-Leave", f"{_p(p)} asked to leave but is in the final view {ref.view}", p)
        else:
            bad("HM-Non-Triviality-Remove", f"{_p(p)} is gone but still in the final view {ref.view}", p)
    # DDB: acknowledged writes everywhere; writes of crashed proposers everywhere or nowhere
    for req, (proc, txid, s) in gh.acked.items():
        missing = [p for p, n in members.items() if txid not in n.state.recent]
        if missing:
            bad(
                "DDB-Durability",
                f"write {req} ({txid}, acknowledged by {_p(proc)} at seq {s}) missing at {[_p(p) for p in missing]}",
                proc,
                *missing,
            )
    # DDB-Exactly-Once: a write the sequencer batched twice (a retry, a new sequencer) is applied once
    once: dict[tuple[str, Proc, int], tuple[int, TxId]] = {}
    for (g, txid), (s, writes) in sorted(gh.seq_applied.items(), key=lambda kv: (kv[0][0], kv[1][0], str(kv[0][1]))):
        for origin, cseq in writes:
            first = once.setdefault((g, origin, cseq), (s, txid))
            if first[1] != txid:
                bad("DDB-Exactly-Once",
                    f"write {cseq} of {_p(origin)} applied at seq {first[0]} ({first[1]}) and again at {s} ({txid})",
                    origin)
    # DDB-Bounded-Batch: a batch of several writes stays within seq_max_cost DDB ops
    most = sim.node_cfg.seq_max_cost
    for (_g, txid), (n, ops) in sorted(gh.seq_cost.items(), key=lambda kv: str(kv[0][1])):
        if n > 1 and ops > most:
            bad("DDB-Bounded-Batch", f"batch {txid} of {n} writes carried {ops} DDB ops > seq_max_cost {most}",
                (txid.host, txid.inc))
    for txid, proc in gh.write_proposer.items():
        if proc not in hist.crash_time:
            continue
        have = [p for p, n in members.items() if txid in n.state.recent]
        if have and len(have) != len(members):
            lack = [_p(p) for p in members if p not in have]
            mid = " (crashed in the middle of its broadcast)" if proc in gh.mid_commit else ""
            bad(
                "DDB-Atomicity",
                f"write {txid} of crashed {_p(proc)}{mid} applied at {[_p(p) for p in have]}, not at {lack}",
                proc,
                *have,
            )
    return out


def run_group(
    seed: int, hosts: int = 7, workload: str = "membership"
) -> tuple[GroupSim, list[GroupViolation]]:
    sc = draw_group(seed, hosts, workload)
    sim = GroupSim(sc)
    sim.run()
    return sim, check_group(sim)
