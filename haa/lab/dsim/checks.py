"""Property checkers over a simulated run's `History` (thesis §4.4, §4.5 and Appendix II).

A *process* is one host incarnation (host, inc). It is *correct* if it never crashed, was never excluded
(permanently suspected) by any host, and did not end (restart, reincarnation) before the run did.

OAC (Alg. 2):
  AC-Uniform-Agreement  no two processes decide differently on a transaction (correct or not).
  AC-Uniform-Validity   a transaction is committed only if every participant voted yes.
  AC-Non-Triviality     if every participant voted yes and no participant was suspected (by anyone), paused
                        or crashed between the proposal and the last decision, the outcome is commit.
                        (Every process suspects a peer until its first heartbeat, so "ever" would make the
                        property vacuous: we read it over the transaction's lifetime.)
  AC-Total-Order        any two correct processes deliver the transactions they both deliver in the same
                        relative order.
  Integrity             each process delivers a transaction at most once, only after deciding commit,
                        with the proposed payload.
  AC-Termination        (liveness, after healing, when every transaction has f < n/2 faulty participants)
                        every correct participant decides every transaction that a correct process
                        proposed or that a correct process decided, and every correct process closes
                        everything it opened (Alg. 2 l. 41) with nothing left in flight.

UFD (Alg. 1):
  UFD-Completeness      every crashed process is suspected by every correct process within
                        T_D^U + Ê(D) of the crash (Ê(D): that observer's estimate of the mean delay,
                        eq. 4.4-1/4.4-2), and never trusted again.
  UFD-Eventual-Accuracy after healing no correct process stays suspected by a correct process, and no
                        correct process is excluded.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

from haa.core.messages import TxId
from haa.lab.dsim.cluster import History, Proc, SimCluster
from haa.lab.dsim.schedule import SIM_QOS, Scenario

#: allowance for clock drift in the detection-time bound (|drift| <= 1e-4 over a ~20 s window)
DRIFT_TOLERANCE = 0.005
#: after healing, a correct process may still be suspected for this long (in-flight spiked messages)
SETTLE = 1.0


@dataclass
class Violation:
    prop: str
    detail: str
    txids: list[TxId] = field(default_factory=list)
    hosts: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        return f"{self.prop}: {self.detail}"


@dataclass
class CheckResult:
    violations: list[Violation]
    liveness_checked: bool
    stats: dict[str, float]


def suspicion_intervals(h: History) -> dict[Proc, list[tuple[float, float]]]:
    """When each process was suspected by someone: [start, end] intervals (end = inf when it never ended).

    Built from every observer's suspicion records, permanent suspicion (dead marks), the end of the
    process's life, and the pauses of its host (a paused host is unresponsive)."""
    out: dict[Proc, list[tuple[float, float]]] = defaultdict(list)
    inf = float("inf")
    open_at: dict[tuple[Proc, Proc], float] = {}
    for t, obs, target, s in sorted(h.suspicions, key=lambda r: r[0]):
        key = (obs, target)
        if s:
            open_at.setdefault(key, t)
        elif key in open_at:
            out[target].append((open_at.pop(key), t))
    for (_obs, target), t in open_at.items():
        out[target].append((t, inf))
    for t, _obs, target, _reason in h.dead_marks:
        out[target].append((t, inf))
    for p, t in h.ended.items():
        out[p].append((t, inf))
    for name, t0, t1 in h.pauses:
        for p in h.started:
            if p[0] == name:
                out[p].append((t0, t1))
    return out


def _fmt(p: Proc) -> str:
    return f"{p[0]}#{p[1]}"


def check_oac(sc: Scenario, cl: SimCluster, quiescent: bool) -> CheckResult:
    h: History = cl.history
    v: list[Violation] = []
    correct = h.correct()
    faulty = h.faulty()
    susp = suspicion_intervals(h)
    outcomes: dict[TxId, dict[Proc, tuple[bool, float]]] = defaultdict(dict)
    for proc, decs in h.decided.items():
        for txid, (commit, t) in decs.items():
            outcomes[txid][proc] = (commit, t)

    # --- AC-Uniform-Agreement, AC-Uniform-Validity, AC-Non-Triviality
    for txid, decs in outcomes.items():
        values = {c for c, _t in decs.values()}
        if len(values) > 1:
            who = ", ".join(f"{_fmt(p)}={'commit' if c else 'abort'}" for p, (c, _t) in sorted(decs.items()))
            v.append(Violation("AC-Uniform-Agreement", f"{txid} decided differently: {who}", [txid]))
        prop = h.proposals.get(txid)
        if prop is None:
            v.append(Violation("Integrity", f"{txid} decided but never proposed", [txid]))
            continue
        votes = h.votes.get(txid, {})
        if True in values:
            missing = [p for p in prop.participants if votes.get(p) is not True]
            if missing:
                v.append(
                    Violation(
                        "AC-Uniform-Validity",
                        f"{txid} committed without a yes vote from {[_fmt(p) for p in missing]}",
                        [txid],
                    )
                )
        if False in values and all(votes.get(p) is True for p in prop.participants):
            last = max(t for _c, t in decs.values())
            quiet = not any(
                a <= last and b >= prop.time for p in prop.participants for a, b in susp.get(p, ())
            )
            if quiet:
                v.append(
                    Violation(
                        "AC-Non-Triviality",
                        f"{txid} aborted though every participant voted yes and none was suspected",
                        [txid],
                    )
                )

    # --- Integrity
    for proc, seq in h.delivered.items():
        seen: set[TxId] = set()
        for txid, _order, payload, _t in seq:
            if txid in seen:
                v.append(Violation("Integrity", f"{_fmt(proc)} delivered {txid} twice", [txid]))
            seen.add(txid)
            dec = h.decided[proc].get(txid)
            if dec is None or not dec[0]:
                v.append(Violation("Integrity", f"{_fmt(proc)} delivered {txid} without deciding commit", [txid]))
            prop = h.proposals.get(txid)
            if prop is not None and prop.payload != payload:
                v.append(Violation("Integrity", f"{_fmt(proc)} delivered {txid} with a wrong payload", [txid]))

    # --- AC-Total-Order among correct processes
    positions = {p: {txid: i for i, (txid, _o, _pl, _t) in enumerate(h.delivered[p])} for p in correct}
    procs = sorted(correct)
    for i, p in enumerate(procs):
        pos_p = positions[p]
        for q in procs[i + 1 :]:
            pos_q = positions[q]
            common = sorted((pos_p[t], t) for t in pos_p if t in pos_q)
            last_q = -1
            prev: TxId | None = None
            for _i, txid in common:
                j = pos_q[txid]
                if j < last_q:
                    assert prev is not None
                    v.append(
                        Violation(
                            "AC-Total-Order",
                            f"{_fmt(p)} delivered {prev} before {txid}, {_fmt(q)} the other way round",
                            [prev, txid],
                        )
                    )
                    break
                last_q = j
                prev = txid

    # --- liveness
    live_ok = True
    for _txid, prop in h.proposals.items():
        parts = prop.participants
        if not parts:
            continue
        bad = sum(1 for p in parts if p in faulty)
        if 2 * bad >= len(parts):
            live_ok = False
            break
    if live_ok:
        for txid, prop in h.proposals.items():
            correct_decided = any(p in correct for p in outcomes.get(txid, {}))
            if not (correct_decided or prop.proposer in correct):
                continue
            for p in prop.participants:
                if p in correct and txid not in h.decided.get(p, {}):
                    v.append(
                        Violation("AC-Termination", f"correct participant {_fmt(p)} never decided {txid}", [txid])
                    )
        if not quiescent:
            open_at = {
                (hst.name, hst.inc): [str(t) for t in hst.core.oac.txs]
                for hst in cl.by_idx
                if hst.core is not None and (hst.name, hst.inc) in correct and hst.core.oac.txs
            }
            detail = f"not quiescent by t={cl.now:.2f}: open {open_at}, {cl.oac_in_flight} OAC messages in flight"
            txids = [t for hst in cl.by_idx if hst.core is not None for t in hst.core.oac.txs]
            v.append(Violation("AC-Termination", detail, txids[:4]))
    stats = {
        "transactions": float(len(h.proposals)),
        "committed": float(sum(1 for d in outcomes.values() if any(c for c, _ in d.values()))),
        "deliveries": float(sum(len(s) for s in h.delivered.values())),
    }
    return CheckResult(v, live_ok, stats)


def _state_at(records: list[tuple[float, bool]], t: float) -> bool:
    """Suspicion state (True = suspected) at time t from sorted records; initially suspected."""
    state = True
    for rt, s in records:
        if rt > t:
            break
        state = s
    return state


def _held_back(h: History, q: Proc, t: float) -> bool:
    """The exclusion of `q` at `t` came from a heavy-tailed delay, not from `q`: a single message of `q` to its
    excluder, sent before the excluder began to suspect `q` for good, was still in flight at `t`, and on a FIFO
    channel held back every later heartbeat (the network failed its timeliness, not `q`)."""
    p = h.excluded_by.get(q)
    if p is None:
        return False
    onset = max((ts for ts, obs, tgt, sus in h.suspicions if obs == p and tgt == q and sus and ts <= t), default=None)
    if onset is None:
        return False
    return any(sent <= onset and arrival >= t for sent, arrival in h.late.get((q[0], p[0]), ()))


def check_ufd(sc: Scenario, cl: SimCluster) -> CheckResult:
    h: History = cl.history
    v: list[Violation] = []
    correct = h.correct()
    td = SIM_QOS.td_upper
    recs: dict[tuple[Proc, Proc], list[tuple[float, bool]]] = defaultdict(list)
    for t, obs, target, s in h.suspicions:
        recs[(obs, target)].append((t, s))
    for t, obs, target, _reason in h.dead_marks:
        recs[(obs, target)].append((t, True))
    for key in recs:
        recs[key].sort(key=lambda r: r[0])
    paused: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for name, t0, t1 in h.pauses:
        paused[name].append((t0, t1))
    mean_d = sc.delay.mean()
    excess: list[float] = []
    detect: list[float] = []
    # --- completeness
    for q, tc in h.crash_time.items():
        for p in correct:
            if p[0] == q[0] or h.started[p] > tc:
                continue
            ed = h.ed_hat.get((p, q), 0.0)
            bound = td + max(ed, 0.0) + DRIFT_TOLERANCE
            deadline = tc + bound
            # a correct observer that was itself paused processes the timeout late: allow its pause
            for t0, t1 in paused[p[0]]:
                if t0 <= deadline and t1 >= tc:
                    deadline = max(deadline, t1 + DRIFT_TOLERANCE)
            if deadline > cl.now:
                continue
            r = recs.get((p, q), [])
            if not _state_at(r, deadline):
                v.append(
                    Violation(
                        "UFD-Completeness",
                        f"{_fmt(p)} still trusted crashed {_fmt(q)} {bound:.3f}s after its crash at t={tc:.3f}",
                        hosts=[p[0], q[0]],
                    )
                )
                continue
            later_trust = [rt for rt, s in r if rt > deadline and not s]
            if later_trust:
                v.append(
                    Violation(
                        "UFD-Completeness",
                        f"{_fmt(p)} trusted crashed {_fmt(q)} again at t={later_trust[0]:.3f}",
                        hosts=[p[0], q[0]],
                    )
                )
                continue
            onsets = [rt for rt, s in r if s and rt >= tc]
            if onsets:
                detect.append(onsets[-1] - tc)
                excess.append(onsets[-1] - tc - td - mean_d)
    # --- eventual accuracy
    heal = sc.fault_end
    for p in correct:
        for q in correct:
            if p == q or p[0] == q[0]:
                continue
            r = recs.get((p, q), [])
            if not r:
                continue
            final = r[-1]
            if final[1] and final[0] < cl.now - SETTLE and cl.now > heal + SETTLE:
                v.append(
                    Violation(
                        "UFD-Eventual-Accuracy",
                        f"{_fmt(p)} suspects correct {_fmt(q)} since t={final[0]:.3f} (healed at {heal:.2f})",
                        hosts=[p[0], q[0]],
                    )
                )
    excused = 0
    for proc, t in h.excluded.items():
        if proc[0] not in sc.faulty and proc not in h.crash_time:
            if _held_back(h, proc, t):
                excused += 1
                continue
            v.append(
                Violation(
                    "UFD-Eventual-Accuracy",
                    f"{_fmt(proc)} (never crashed, not in the faulty set) was excluded at t={t:.3f}",
                    hosts=[proc[0]],
                )
            )
    stats = {
        "exclusions_behind_a_late_message": float(excused),
        "detections": float(len(detect)),
        "max_detection": max(detect, default=0.0),
        "max_excess_over_td_plus_ed": max(excess, default=0.0),
    }
    return CheckResult(v, True, stats)
