"""Alg. 2 (OAC) on hand-built scenarios in the deterministic simulator.

Random schedules (test_dsim.py) explore; these pin down the behaviours one by one: the failure-free
path and its message count, unilateral abort, concurrent proposals, a proposer or coordinator that crashes
part-way through a broadcast, placeholders, and the closing-gate hole in the thesis' l. 41."""

import random

import pytest

from haa.core.host.hostcore import FD_EXTERNAL, CoreConfig
from haa.core.messages import OacTransaction
from haa.lab.dsim import mutations
from haa.lab.dsim.checks import check_oac
from haa.lab.dsim.cluster import SimCluster
from haa.lab.dsim.network import DelayModel
from haa.lab.dsim.schedule import SIM_UFD, Scenario

CONST = DelayModel("const", 0.001, 0.0)


def make(n, delay=CONST, no_votes=None, exclude_after=1.0):
    names = [f"h{i + 1}" for i in range(n)]
    cfg = CoreConfig(ufd=SIM_UFD, fd_mode=FD_EXTERNAL, exclude_after=exclude_after)
    cl = SimCluster(names, random.Random(1), delay, cfg, no_votes=no_votes, trace=True)
    cl.start_all()
    return cl


def scenario_for(cl, fault_end=0.0):
    return Scenario(
        seed=0,
        algorithm="oac",
        names=cl.names,
        fd_mode=FD_EXTERNAL,
        delay=cl.delay,
        offsets=[0.0] * len(cl.names),
        drifts=[0.0] * len(cl.names),
        faulty=[],
        features={},
        fault_end=fault_end,
    )


def quiescent(cl):
    return cl.oac_in_flight == 0 and all(v == 0 for v in cl.open_transactions().values())


def deliveries(cl, name):
    h = cl.hosts[name]
    return [t for t, _o, _p, _time in cl.history.delivered[(name, h.inc)]]


@pytest.mark.parametrize("n", [2, 3, 4, 5, 7, 10])
def test_failure_free_commit_and_message_count(n):
    cl = make(n)
    txid = cl.propose("h1", b"hello", None)
    cl.run(1.0)
    assert quiescent(cl)
    for name in cl.names:
        assert deliveries(cl, name) == [txid]
        assert cl.history.decided[(name, 1)][txid][0] is True
        assert txid in cl.history.closed[(name, 1)]
    oac_msgs = sum(v for k, v in cl.msg_counts.items() if k.startswith("Oac"))
    # tx n-1, estimates n-1, proposal n-1, acks n-1, decide n-1, rebroadcasts (n-1)^2, and the round-1
    # estimates that Task 2's loop (l. 43-47) sends before the decision arrives: n-2 (the round-1
    # coordinator keeps its own). n^2 + 4n - 6 in all, the thesis' "n^2 + 4n".
    assert oac_msgs == (n - 1) * (n + 4) + (n - 2) == n * n + 4 * n - 6
    assert check_oac(scenario_for(cl), cl, True).violations == []


def test_proposer_coordinates_round_zero_and_decides_in_four_message_delays():
    cl = make(5)
    cl.propose("h3", b"x", None)
    cl.run(1.0)
    (commit, t_decide) = cl.history.decided[("h3", 1)][next(iter(cl.history.proposals))]
    assert commit and t_decide == pytest.approx(0.004)  # tx, estimate, proposal, ack: 4 x 1 ms


def test_unilateral_abort_aborts_everywhere():
    cl = make(5, no_votes={(b"veto", "h4")})
    txid = cl.propose("h1", b"veto", None)
    cl.propose("h2", b"fine", None)
    cl.run(1.0)
    assert quiescent(cl)
    for name in cl.names:
        assert cl.history.decided[(name, 1)][txid][0] is False
        assert txid not in deliveries(cl, name)
        assert len(deliveries(cl, name)) == 1
    assert check_oac(scenario_for(cl), cl, True).violations == []


def test_concurrent_proposals_are_delivered_in_one_total_order():
    delay = DelayModel("exp", 0.0002, 0.002)
    cl = make(6, delay=delay)
    for i, name in enumerate(cl.names * 3):
        parts = None if i % 2 == 0 else [name, cl.names[(i + 1) % 6], cl.names[(i + 3) % 6]]
        cl.at(0.0005 * (i % 4), lambda n=name, p=parts, i=i: cl.propose(n, f"t{i}".encode(), p))
    cl.run(3.0)
    assert quiescent(cl)
    assert len(cl.history.proposals) == 18
    full = [deliveries(cl, n) for n in cl.names]
    assert all(len(d) >= 9 for d in full)
    result = check_oac(scenario_for(cl), cl, True)
    assert result.violations == []


def test_proposer_crashing_mid_broadcast_is_relayed():
    """The proposer's l. 5 reaches only h2 before it crashes: h2 relays the transaction when it
    suspects the proposer, so h3..h5 are not left waiting for it (docs/oac.md, "relay")."""
    cl = make(5)
    h1 = cl.hosts["h1"]
    h1.crash_pending = 0.25  # 1 of the 4 sends of the next broadcast leaves: the one to h2
    txid = cl.propose("h1", b"x", None)
    assert cl.hosts["h1"].core is None  # crashed
    for p in ("h2", "h3", "h4", "h5"):
        cl.at(0.05, lambda p=p: cl.suspect(p, "h1", True))
    cl.run(5.0)
    assert quiescent(cl)
    relays = [ln for ln in cl.trace if "OacTransaction" in ln and "h2#1 -> " in ln]
    assert len(relays) == 3
    for name in ("h2", "h3", "h4", "h5"):
        assert cl.history.decided[(name, 1)][txid][0] is False  # h1's estimate can never arrive
    sc = scenario_for(cl)
    assert check_oac(sc, cl, True).violations == []


def test_coordinator_decision_reaching_one_participant_is_rebroadcast():
    cl = make(5)
    txid = cl.propose("h1", b"x", None)
    # h1 coordinates round 0; make its decide broadcast reach only h2, then crash it
    cl.run(0.0035)
    cl.hosts["h1"].crash_pending = 0.25
    for p in ("h2", "h3", "h4", "h5"):
        cl.at(0.05, lambda p=p: cl.suspect(p, "h1", True))
    cl.run(5.0)
    assert quiescent(cl)
    assert ("h1", 1) in cl.history.crash_time
    for name in ("h2", "h3", "h4", "h5"):
        assert cl.history.decided[(name, 1)][txid][0] is True
        assert deliveries(cl, name) == [txid]


def test_messages_before_the_transaction_wait_in_a_placeholder():
    cl = make(4)
    # h1 -> h3 is slow: h3 hears from the others (order, estimate) before it has the transaction
    cl.spike("h1", "h3", DelayModel("const", 0.05, 0.0), 1.0)
    a = cl.propose("h1", b"a", None)
    cl.at(0.0001, lambda: cl.propose("h2", b"b", None))
    cl.run(2.0)
    assert quiescent(cl)
    orders = {n: deliveries(cl, n) for n in cl.names}
    assert all(len(d) == 2 for d in orders.values())
    assert len({tuple(d) for d in orders.values()}) == 1
    assert a in orders["h3"]


def closing_gate_scenario():
    """The interleaving that breaks the thesis' l. 41 (see docs/oac.md, "the closing gate").

    m' = h5's transaction to all 7 hosts, m = h1's transaction to h1..h4, proposed 0.5 ms later.
    h2..h4 hear of m' first, so they order m after m' (order 2 > 1) and hold m, decided, behind the still
    undecided m'. h1 hears of m' only 50 ms later (slow channel h5 -> h1).
    """
    cl = make(7)
    cl.spike("h5", "h1", DelayModel("const", 0.05, 0.0), 1.0)
    m_prime = cl.propose("h5", b"m-prime", None)
    m: list = []
    cl.at(0.0005, lambda: m.append(cl.propose("h1", b"m", ["h1", "h2", "h3", "h4"])))
    cl.run(2.0)
    return cl, m[0], m_prime


def test_closing_gate_keeps_total_order():
    cl, m, m_prime = closing_gate_scenario()
    assert quiescent(cl)
    for name in ("h1", "h2", "h3", "h4"):
        seq = deliveries(cl, name)
        assert seq.index(m) < seq.index(m_prime) or seq.index(m) > seq.index(m_prime)
    firsts = {deliveries(cl, n).index(m) < deliveries(cl, n).index(m_prime) for n in ("h1", "h2", "h3", "h4")}
    assert len(firsts) == 1
    assert check_oac(scenario_for(cl), cl, True).violations == []


def test_thesis_l41_as_printed_breaks_total_order():
    undo = mutations.apply("thesis-close")
    try:
        cl, m, m_prime = closing_gate_scenario()
    finally:
        undo()
    assert deliveries(cl, "h1").index(m) < deliveries(cl, "h1").index(m_prime)
    assert deliveries(cl, "h2").index(m_prime) < deliveries(cl, "h2").index(m)
    props = {v.prop for v in check_oac(scenario_for(cl), cl, True).violations}
    assert "AC-Total-Order" in props


def test_malformed_transactions_are_rejected_without_state():
    cl = make(3)
    core = cl.hosts["h2"].core
    # h2 is not among the participants
    bad = OacTransaction(("h1", 1, 99), b"x", (("h1", 1), ("h3", 1)), 1)  # type: ignore[arg-type]
    core.on_message(0.0, "h1", 1, 1, bad)
    assert not core.oac.txs
    # the sender is not a participant
    bad2 = OacTransaction(("h3", 1, 5), b"x", (("h3", 1), ("h2", 1)), 1)  # type: ignore[arg-type]
    core.on_message(0.0, "h1", 1, 1, bad2)
    assert not core.oac.txs
    logs = [e for e in core.drain() if type(e).__name__ == "Log"]
    assert [e.event for e in logs] == ["oac_bad_transaction", "oac_bad_transaction"]


def test_unknown_participant_is_refused_at_propose():
    cl = make(3)
    core = cl.hosts["h1"].core
    with pytest.raises(ValueError, match="unknown participant"):
        core.propose(0.0, b"x", ["h1", "h9"])


def test_restarted_peer_that_never_speaks_is_still_excluded():
    """A new incarnation learned from a handshake (or a participant list) that then dies without a single
    heartbeat must become permanently suspected, or transactions naming it never close (l. 41)."""
    from haa.core.effects import PeerDead, SetTimer
    from haa.core.host.hostcore import CoreConfig, HostCore

    core = HostCore("h1", 1, ["h1", "h2"], CoreConfig(exclude_after=2.0))
    core.start(0.0)
    core.on_peer_info(0.0, "h2", 5)
    core.on_peer_info(1.0, "h2", 6)  # restarted again before we ever heard from it
    timers = [e for e in core.drain() if isinstance(e, SetTimer) and e.key[0] == "excl"]
    assert timers[-1].key == ("excl", "h2", 6) and timers[-1].at == pytest.approx(3.0)
    core.on_timer(3.0, ("excl", "h2", 6))
    assert any(isinstance(e, PeerDead) and e.inc == 6 for e in core.drain())
    assert core.is_dead("h2", 6)


def locked_round_zero_scenario():
    """Round 0 commits with a quorum while a participant that suspected the coordinator runs round 1.

    h1 coordinates round 0 of a transaction to (h1, h2, h3); its proposal reaches h3 but not h2 (slow
    channel), h3 acks, h1 decides commit with the quorum {h1, h3}; its decide to h3 is slow too. h2
    suspects h1, nacks, and coordinates round 1 with its own estimate and h3's (which adopted round 0's
    pre-commit). The thesis' pseudo-code starts rounds at 0 and timestamps at 0 (l. 19-20), so h3's
    adoption (ts := 0, l. 60) looks like no adoption at all, and h2 picks its own pre-abort.
    """
    cl = make(3)
    slow = DelayModel("const", 0.05, 0.0)
    cl.at(0.0015, lambda: cl.spike("h1", "h2", slow, 1.0))
    cl.at(0.0035, lambda: cl.spike("h1", "h3", slow, 1.0))
    cl.at(0.0032, lambda: cl.suspect("h2", "h1", True))  # after h3 acked, so h1 counts that ack first
    cl.at(0.2, lambda: cl.suspect("h2", "h1", False))
    txid = cl.propose("h1", b"x", None)
    cl.run(3.0)
    return cl, txid


def test_round_zero_lock_survives_a_later_round():
    cl, txid = locked_round_zero_scenario()
    outcomes = {n: cl.history.decided[(n, 1)][txid][0] for n in cl.names}
    assert outcomes == {"h1": True, "h2": True, "h3": True}
    assert check_oac(scenario_for(cl), cl, True).violations == []


def test_thesis_initial_timestamp_breaks_agreement():
    """The same schedule with ts_p initialised to 0 as printed (l. 20): h1 commits, h2 and h3 abort."""
    from haa.core.oac import oac as oac_mod

    original = oac_mod.INITIAL_TS
    oac_mod.INITIAL_TS = 0
    try:
        cl, txid = locked_round_zero_scenario()
    finally:
        oac_mod.INITIAL_TS = original
    outcomes = {n: cl.history.decided[(n, 1)][txid][0] for n in cl.names}
    assert outcomes["h1"] is True and outcomes["h2"] is False
    assert "AC-Uniform-Agreement" in {v.prop for v in check_oac(scenario_for(cl), cl, True).violations}


class _Host:
    """What OAC reads of its host (`OacHost`), from plain functions."""

    def __init__(self, suspected=lambda _h, _i: False, dead=lambda _h, _i: False, removed=lambda _h, _i: False):
        self.is_suspected, self.is_dead, self.is_removed = suspected, dead, removed


class _Driven:
    """An `OrderedAtomicCommit` driven by hand the way `HostCore` drives it: its sends go to `send`, a vote it
    asks for is yes (`Evaluate` -> `Vote`), the rest of its effects are kept in `emitted`."""

    def __init__(self, name, host, send=lambda *_a: None):
        from haa.core.oac.oac import OrderedAtomicCommit

        self.oac = OrderedAtomicCommit(name, 1, host)
        self.send = send
        self.emitted: list = []

    def step(self, inp):
        from haa.core.effects import Send
        from haa.core.oac.oac import Evaluate, Learn, Vote

        for e in self.oac.step(0.0, inp):
            if isinstance(e, Send):
                self.send(e.dst, e.dst_inc, e.msg, e.lazy)
            elif isinstance(e, Evaluate):
                self.step(Vote(e.txid, True))
            elif not isinstance(e, Learn):
                self.emitted.append(e)

    def propose(self, payload, parts):
        from haa.core.oac.oac import Propose

        txid = self.oac.new_txid()
        self.step(Propose(txid, payload, tuple(parts)))
        return txid

    def on_message(self, src, src_inc, msg):
        from haa.core.oac.oac import Incoming

        self.step(Incoming(src, src_inc, msg))

    def on_peer_change(self, peer):
        from haa.core.oac.oac import PeerChanged

        self.step(PeerChanged(peer))


def _direct_group(n):
    """n OrderedAtomicCommit objects wired through one FIFO queue of (src, dst, msg, lazy), no failure detector."""
    from collections import deque

    names = [f"h{i + 1}" for i in range(n)]
    wire = deque()
    sent = []
    emitted = {q: [] for q in names}
    oacs = {}
    for q in names:

        def send(dst, dst_inc, msg, lazy, q=q):
            wire.append((q, dst, msg))
            sent.append((q, dst, type(msg).__name__, lazy))

        oacs[q] = _Driven(q, _Host(), send)
        emitted[q] = oacs[q].emitted

    def run():
        while wire:
            src, dst, msg = wire.popleft()
            oacs[dst].on_message(src, 1, msg)

    return names, oacs, sent, emitted, run


@pytest.mark.parametrize("n", [3, 5, 10])
def test_lazy_marks_exactly_the_messages_nobody_waits_for(n):
    """Failure-free: the rebroadcasts of a decision learned from the coordinator (l. 36) and the round-1
    estimates sent after a positive ack are lazy; the transaction, the round-0 estimates, the proposal, the
    acks and the coordinator's decide are not (docs/oac.md, "Lazy messages")."""
    names, oacs, sent, _emitted, run = _direct_group(n)
    oacs["h1"].propose(b"x", [(q, 1) for q in names])
    run()
    lazy = [(src, kind) for src, _dst, kind, lz in sent if lz]
    eager = [(src, kind) for src, _dst, kind, lz in sent if not lz]
    assert len(sent) == n * n + 4 * n - 6
    assert sorted({k for _s, k in lazy}) == ["OacDecide", "OacEstimate"]
    assert sum(1 for _s, k in lazy if k == "OacDecide") == (n - 1) * (n - 1)
    assert sum(1 for _s, k in lazy if k == "OacEstimate") == n - 2
    assert all(s != "h1" for s, _k in lazy)  # the coordinator's own messages are all on the critical path
    assert len(eager) == 5 * (n - 1)


def _pair_with_removal():
    """h1 and h2 wired through per-destination FIFO queues that the test releases by hand; `removed` is what
    h1's group removed (`HostCore.removed`): such an incarnation is also permanently suspected."""
    from collections import deque

    removed: set = set()
    wires = {"h1": deque(), "h2": deque()}
    emitted = {"h1": [], "h2": []}
    oacs = {}
    for q in ("h1", "h2"):

        def send(dst, _dst_inc, msg, _lazy, q=q):
            wires[dst].append((q, msg))

        def dead(h, i, q=q):
            return q == "h1" and (h, i) in removed

        oacs[q] = _Driven(q, _Host(dead, dead, dead), send)
        emitted[q] = oacs[q].emitted

    def deliver(dst, count=None):
        k = 0
        while wires[dst] and (count is None or k < count):
            src, msg = wires[dst].popleft()
            oacs[dst].on_message(src, 1, msg)
            k += 1

    return oacs, wires, emitted, removed, deliver


def _outcomes(effects):
    from haa.core.effects import Decided, Deliver

    return [e.commit for e in effects if type(e) is Decided], [e.payload for e in effects if type(e) is Deliver]


def test_a_partner_the_group_removed_before_it_voted_leaves_an_abort():
    """verify recovery seed 1229: the front of a group of two removed its partner; a transaction of just
    those two never decided (quorum 2, the removed incarnation never votes) and held the survivor's l. 37
    gate for good. The survivor now decides alone, with its own estimate: here pre-abort."""
    oacs, wires, emitted, removed, _deliver = _pair_with_removal()
    oacs["h1"].propose(b"x", [("h2", 1)])
    wires["h2"].clear()  # h2 never gets the transaction (removed, then restarted)
    assert _outcomes(emitted["h1"]) == ([], [])
    removed.add(("h2", 1))
    oacs["h1"].on_peer_change("h2")
    assert _outcomes(emitted["h1"]) == ([False], [])
    assert oacs["h1"].oac.active_count == 0 and not oacs["h1"].oac.txs  # decided and closed (l. 41: h2 is dead)


def test_a_partner_the_group_removed_after_it_decided_commit_agrees():
    """h2 proposes and coordinates round 0; h1 adopts its pre-commit and acks; h2 decides commit and
    delivers, and is removed before its decision reaches h1. h1 decides alone — commit, the same outcome
    (AC-Uniform-Agreement): h2's decision needed h1's ack, whose value h1's estimate holds."""
    oacs, wires, emitted, removed, deliver = _pair_with_removal()
    oacs["h2"].propose(b"y", [("h1", 1)])
    deliver("h1")  # the transaction: h1 votes yes, sends its round-0 estimate
    deliver("h2")  # h2 has both estimates: proposes pre-commit
    deliver("h1")  # h1 adopts it, acks, and sends its round-1 estimate (h1 coordinates round 1)
    deliver("h2")  # h2 has both acks: decides commit and delivers
    assert _outcomes(emitted["h2"]) == ([True], [b"y"])
    wires["h1"].clear()  # h2's decision is lost with its removal
    assert _outcomes(emitted["h1"]) == ([], [])
    removed.add(("h2", 1))
    oacs["h1"].on_peer_change("h2")
    assert _outcomes(emitted["h1"]) == ([True], [b"y"])


def test_a_merely_suspected_partner_still_blocks_a_two_participant_transaction():
    """Only the group's removal lets a participant decide alone: with n = 2 a suspicion (or an exclusion that
    is not a removal) is a crash Alg. 2 does not tolerate (f < n/2 = 1), and the transaction waits."""
    oac = _Driven("h1", _Host(lambda *_a: True, lambda *_a: True))
    oac.propose(b"z", [("h2", 1)])
    oac.on_peer_change("h2")
    assert _outcomes(oac.emitted) == ([], []) and oac.oac.active_count == 1
