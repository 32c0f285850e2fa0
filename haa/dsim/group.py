"""Deterministic simulation of the host group: membership (Alg. 3) and the replicated DDB.

`draw_group(seed, hosts)` turns one seed into a scenario (swarm style, like `haa.dsim.schedule`): how many
hosts and core processes, when each host starts (late starts are joins), a workload of DDB writes from
random members, voluntary leaves, crashes (some in the middle of a broadcast, including the first core
process before it forms the group), restarts as new incarnations, pauses (resume, or "unresponsive, then
shut down") and delay spikes that make the failure detector suspect correct hosts. `run_group` runs it on a
`SimCluster` whose hosts are `MembershipNode`s, heals, runs to quiescence and checks (`check_group`):

* HM-Agreement: one view id, one member set, across every process; every process's view ids increase;
  every process applies the same transaction at the same global sequence number, with the same state
  hash afterwards (this is also "a joiner's replica equals the others'": a new member's first applied
  transaction comes after its installed snapshot).
* At most one acknowledged leader per view (the front of the view's list, the same for everyone).
* HM-Weak-Validity: when a removal commits, every participant that voted for it suspected (per its own
  failure detector output at the time of its vote) every removed member.
* HM-Formation, HM-Non-Triviality-Join/-Leave/-Remove, HM-Termination (after healing): the run goes
  quiet; every live host's current incarnation is a member of one final view, which holds no crashed,
  superseded or departed process.
* DDB: every correct member ends with the same content hash and sequence; every acknowledged write is in
  the common sequence; a write whose proposer crashed is applied everywhere or nowhere.

Faults that would break the thesis' own assumptions are not drawn: at most c_f core processes fail, and no
false suspicion is injected before FORMATION_TIMEOUT (§4.6.1: no erroneous exclusion during formation).
"""

from __future__ import annotations

import random
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from haa.dsim.cluster import ALIVE, CRASHED, PAUSED, SimCluster, SimHost
from haa.dsim.network import DelayModel
from haa.dsim.schedule import EXCLUDE_AFTER, SIM_UFD, Fault, _delay_model
from haa.hostd import ddb as ddbmod
from haa.hostd.core import CoreConfig
from haa.hostd.globalstate import TxRemove, decode_tx
from haa.hostd.membership import AppliedTx, Left, MembershipNode, NodeConfig, ViewChange, WriteDone
from haa.hostd.messages import TxId

Proc = tuple[str, int]

SIM_NODE = dict(
    formation_timeout=1.0,
    formation_retry=0.3,
    discovery=0.2,
    reapply=0.5,
    catchup_timeout=0.4,
    hash_every_apply=True,
)


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
    fault_end: float = 4.0
    deadline: float = 40.0

    def describe(self) -> list[str]:
        out = [
            f"seed={self.seed} hosts={self.names} core={self.core} c_f={self.c_f} delay={self.delay.describe()}",
            "features: " + ",".join(k for k, v in sorted(self.features.items()) if v),
            "starts: " + " ".join(f"{n}@{t:.2f}" for n, t in self.starts.items()),
        ]
        out += [f.describe() for f in self.faults]
        out += [f"t={t:.3f} leave {h}" for t, h in self.leaves]
        out.append(f"{len(self.writes)} writes")
        return out


def draw_group(seed: int, hosts: int = 7) -> GroupScenario:
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
    for _ in range(rng.randint(5, 40)):
        sc.writes.append((rng.uniform(0.5, sc.fault_end), rng.choice(names)))
    sc.faults.sort(key=lambda f: f.time)
    return sc


# ------------------------------------------------------------------------------------------------ the run


@dataclass
class GroupHistory:
    views: dict[Proc, list[tuple[str, int, tuple[Proc, ...], float]]] = field(default_factory=lambda: defaultdict(list))
    correct_groups: set[str] = field(default_factory=set)
    applied: dict[Proc, list[tuple[int, TxId, str, str]]] = field(default_factory=lambda: defaultdict(list))
    votes: list[tuple[float, Proc, TxId, bool, Any, dict[Proc, bool]]] = field(default_factory=list)
    acked: dict[Any, tuple[Proc, TxId, int]] = field(default_factory=dict)
    write_proposer: dict[TxId, Proc] = field(default_factory=dict)
    leave_requested: dict[Proc, float] = field(default_factory=dict)
    left: dict[Proc, float] = field(default_factory=dict)
    group_msgs: int = 0


class GroupSim:
    """Runs one `GroupScenario` (see the module docstring)."""

    def __init__(self, sc: GroupScenario, mutations: frozenset[str] = frozenset(), trace: bool = False) -> None:
        self.sc = sc
        self.rng = random.Random(sc.seed * 7919 + 1)
        self.mutations = mutations
        cfg = CoreConfig(ufd=SIM_UFD, exclude_after=EXCLUDE_AFTER)
        self.node_cfg = NodeConfig(core=cfg, c_f=sc.c_f, **SIM_NODE)
        self.cl = SimCluster(sc.names, self.rng, sc.delay, cfg, sc.offsets, sc.drifts, trace=trace)
        self.cl.make_core = self._make_node
        self.cl.on_effect = self._on_effect
        self.gh = GroupHistory()
        self.core_list = [(nm, nm) for nm in sc.core]
        self.req = 0
        self.known: dict[str, dict[str, str]] = {}
        self.rreq = random.Random(sc.seed * 31 + 7)
        for h in self.cl.by_idx:
            h.state = CRASHED  # not started yet

    def _make_node(self, h: SimHost, inc: int) -> MembershipNode:
        cl = self.cl
        # what the previous incarnation knew (the daemon keeps it in --data-dir)
        known = sorted(self.known.get(h.name, {}).items())
        node = MembershipNode(h.name, inc, h.name, self.core_list, self.node_cfg, self.mutations, known)
        proc = (h.name, inc)
        orig = node._evaluate

        def evaluate(txid: TxId, payload: bytes, _p: Proc = proc) -> bool:
            vote = orig(txid, payload)
            try:
                tx = decode_tx(payload)
            except ValueError:
                tx = None
            if type(tx) is TxRemove:
                # the voter's failure-detector output about each member to remove, sampled at the vote
                fd = {q: node.core.is_suspected(q[0], q[1]) for q in tx.removal}
                self.gh.votes.append((cl.now, _p, txid, vote, tx, fd))
            cl.history.votes.setdefault(txid, {})[_p] = vote
            return vote

        node.core.oac._evaluate = evaluate
        return node

    def _on_effect(self, h: SimHost, e: Any) -> None:
        proc = (h.name, h.inc)
        t = type(e)
        gh = self.gh
        if t is ViewChange:
            self.known[h.name] = {m.name: m.addr for m in e.members}
        if t is AppliedTx:
            gh.applied[proc].append((e.seq, e.txid, e.state_hash, h.core.state.genesis))  # type: ignore[union-attr]
        elif t is ViewChange:
            gh.views[proc].append((e.group, e.view, tuple(m.proc for m in e.members), self.cl.now))
            if e.correct:
                gh.correct_groups.add(e.group)
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

    def _write(self, name: str) -> None:
        h = self.cl.hosts[name]
        node = h.core
        if h.state != ALIVE or node is None or not isinstance(node, MembershipNode):
            return
        r = self.rreq
        key = f"k{r.randint(0, 5)}"
        kind = r.random()
        if kind < 0.4:
            op = ddbmod.put(key, "json", {"v": r.randint(0, 1000), "by": name})
        elif kind < 0.6:
            op = ddbmod.append(f"l{r.randint(0, 2)}", r.randbytes(4), 8)
        elif kind < 0.8:
            op = ddbmod.add(f"c{r.randint(0, 2)}", r.randint(-5, 5))
        elif kind < 0.9:
            op = ddbmod.cas(key, r.randint(0, 30), "blob", r.randbytes(3))
        else:
            op = ddbmod.delete(key)
        self.req += 1
        payload = ddbmod.encode_batch([op], origin=name, client_seq=self.req)
        node.submit(h.local(self.cl.now), payload, (name, self.req))
        self.cl._apply(h)

    def _leave(self, name: str) -> None:
        h = self.cl.hosts[name]
        node = h.core
        if h.state != ALIVE or node is None:
            return
        self.gh.leave_requested[(name, h.inc)] = self.cl.now
        node.leave(h.local(self.cl.now))  # type: ignore[attr-defined]
        self.cl._apply(h)

    def run(self) -> None:
        cl = self.cl
        sc = self.sc
        for nm, t in sc.starts.items():
            cl.at(t, lambda nm=nm: cl._boot(cl.hosts[nm], 1))
        for f in sc.faults:
            if f.kind in ("crash", "crash_mid"):
                cl.at(f.time, lambda f=f: cl.crash(f.host, mid_step=f.kind == "crash_mid"))
            elif f.kind == "restart":
                cl.at(f.time, lambda f=f: self._restart(f.host))
            elif f.kind == "pause":
                cl.at(f.time, lambda f=f: cl.pause(f.host))
                cl.at(min(f.time + f.duration, sc.fault_end), lambda f=f: cl.resume(f.host))
            elif f.kind == "spike":
                cl.at(f.time, lambda f=f: cl.spike(f.host, f.other or None, f.extra, f.duration))  # type: ignore[arg-type]
        for t, nm in sc.writes:
            cl.at(t, lambda nm=nm: self._write(nm))
        for t, nm in sc.leaves:
            cl.at(t, lambda nm=nm: self._leave(nm))
        cl.run(sc.fault_end)
        for h in cl.by_idx:  # heal
            if h.state == PAUSED:
                cl.resume(h.name)
        t = sc.fault_end
        quiet_for = 0.0
        while t < sc.deadline:
            t += 0.5
            before = self._activity()
            cl.run(t)
            if self._quiet() and self._activity() == before:
                quiet_for += 0.5
                if quiet_for >= 2.0:
                    break
            else:
                quiet_for = 0.0
        self.quiescent = quiet_for >= 2.0

    def _restart(self, name: str) -> None:
        h = self.cl.hosts[name]
        if (name, h.inc) in self.gh.left:
            return
        self.cl.restart(name)

    def _activity(self) -> int:
        c = self.cl.msg_counts
        return sum(v for k, v in c.items() if k not in ("Heartbeat", "SetPeriod"))

    def _quiet(self) -> bool:
        for h in self.cl.by_idx:
            node = h.core
            if node is None:
                continue
            if node.oac.txs or node.updating or node.direct_q or node.held or node.writes:  # type: ignore[attr-defined]
                return False
        return True


# ------------------------------------------------------------------------------------------------ checks


@dataclass
class GroupViolation:
    prop: str
    detail: str


def check_group(sim: GroupSim) -> list[GroupViolation]:
    cl = sim.cl
    gh = sim.gh
    out: list[GroupViolation] = []
    # HM-Agreement: one view id, one member set; increasing ids per process
    view_sets: dict[tuple[str, int], tuple[Proc, ...]] = {}
    if len(gh.correct_groups) > 1:
        out.append(GroupViolation("HM-Formation", f"more than one correct group formed: {sorted(gh.correct_groups)}"))
    for proc, vs in gh.views.items():
        last = 0
        for g, v, members, t in vs:
            if v <= last:
                out.append(GroupViolation("HM-Agreement", f"{proc} view ids not increasing: {last} then {v}"))
            last = v
            prev = view_sets.setdefault((g, v), members)
            if prev != members:
                out.append(
                    GroupViolation(
                        "HM-Agreement", f"group {g} view {v}: {proc} has {list(members)} at {t:.3f}, other {list(prev)}"
                    )
                )
                break
    # one leader per view is the front of the (agreed) list; check nobody acted as leader outside it
    # global sequence: same txid and hash at every seq
    at_seq: dict[int, tuple[TxId, str, Proc]] = {}
    groups = gh.correct_groups or {""}
    main = min(groups)
    # a member removed while it was running (false suspicion; it then restarts as a new incarnation) does not
    # deliver the transaction that removed it, so what it applies afterwards is not the group's sequence
    hist = cl.history
    removed_alive = {p for p in hist.ended if p not in hist.crash_time and p not in gh.left}
    for proc, items in gh.applied.items():
        if proc in removed_alive:
            continue
        for seq, txid, h, g in items:
            if g != main:
                continue  # a provisional group of one that was abandoned
            prev = at_seq.get(seq)
            if prev is None:
                at_seq[seq] = (txid, h, proc)
            elif prev[0] != txid or prev[1] != h:
                what = "transaction" if prev[0] != txid else "state hash"
                out.append(
                    GroupViolation(
                        "DDB-Prefix" if prev[0] == txid else "HM-Agreement",
                        f"seq {seq}: {proc} applied {txid} ({h[:12]}), {prev[2]} applied {prev[0]} ({prev[1][:12]})"
                        f" - different {what}",
                    )
                )
                break
    # HM-Weak-Validity
    committed = {txid for items in gh.applied.values() for _s, txid, _h, _g in items}
    for t, proc, txid, vote, tx, fd in gh.votes:
        if not vote or txid not in committed:
            continue
        for target in tx.removal:
            if not fd[target]:
                out.append(
                    GroupViolation(
                        "HM-Weak-Validity",
                        f"{proc} voted to remove {target} in {txid} at {t:.3f} without suspecting it",
                    )
                )
    if not sim.quiescent:
        out.append(GroupViolation("HM-Termination", f"not quiescent by t={sim.sc.deadline}"))
        return out
    # final view
    live = [h for h in cl.by_idx if h.state == ALIVE and h.core is not None]
    if not live:
        return out
    finals = {}
    for h in live:
        node: MembershipNode = h.core  # type: ignore[assignment]
        finals[(h.name, h.inc)] = (
            node.state.view,
            tuple(node.state.procs()),
            node.state.content_hash(),
            node.state.seq,
        )
    want = {(h.name, h.inc) for h in live}
    distinct = set(finals.values())
    if len(distinct) != 1:
        detail = "; ".join(f"{p[0]}#{p[1]}: view {v[0]} {[m[0] for m in v[1]]} seq {v[3]}" for p, v in finals.items())
        out.append(GroupViolation("HM-Non-Triviality/DDB-Convergence", f"final states differ: {detail}"))
        return out
    view, members, _h, seq = distinct.pop()
    if set(members) != want:
        missing = sorted(want - set(members))
        extra = sorted(set(members) - want)
        prop = "HM-Non-Triviality-Join" if missing else "HM-Non-Triviality-Remove/Leave"
        out.append(GroupViolation(prop, f"final view {view}: missing {missing}, should be gone {extra}"))
    in_group = {v[0] for v in at_seq.values()}
    for req, (_proc, txid, s) in gh.acked.items():
        if txid not in in_group:
            out.append(GroupViolation("DDB-Durability", f"acknowledged write {req} ({txid} at seq {s}) lost"))
    return out


def run_group(
    seed: int, hosts: int = 7, mutations: frozenset[str] = frozenset()
) -> tuple[GroupSim, list[GroupViolation]]:
    sc = draw_group(seed, hosts)
    sim = GroupSim(sc, mutations)
    sim.run()
    return sim, check_group(sim)
