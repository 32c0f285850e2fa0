"""Agent allocation HAA-AA (Alg. 4): bid order, Table 4.7-1, rewards, bundle building, the session life cycle
and the rebalance policy, on the sans-I/O `Allocator` driven by hand."""

from __future__ import annotations

import ast
import itertools
import math
from collections import deque
from pathlib import Path

import pytest
from helpers import parse_source
from hypothesis import given, settings
from hypothesis import strategies as st

from haa.core.allocation import conflicts as al
from haa.core.allocation.allocation import Allocated, Allocator, ProposeFinish, ProposeStart, SendUpdate
from haa.core.allocation.bids import Bid, BidUpdate, bid_gt, bid_key, nil_bid
from haa.core.allocation.conflicts import resolve
from haa.core.allocation.rebalance import RebalancePolicy
from haa.core.allocation.rewards import agent_reward, bundle_reward
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart

ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------------------------------------ bid order


def B(winner, reward=1.0, support=0.5, rnd=0, agent="j"):
    return Bid(agent, winner, reward, support, rnd)


def test_within_capacity_beats_over_capacity_whatever_the_reward():
    assert bid_gt(B("h2", reward=0.1, support=0.01), B("h1", reward=9.0, support=-0.01))
    assert not bid_gt(B("h1", reward=9.0, support=0.0), B("h2", reward=0.1, support=0.01))  # support 0 is over


def test_within_capacity_higher_reward_then_higher_support_then_lower_host():
    assert bid_gt(B("h9", reward=0.6, support=0.1), B("h1", reward=0.5, support=0.9))
    assert bid_gt(B("h9", reward=0.5, support=0.2), B("h1", reward=0.5, support=0.1))
    assert bid_gt(B("h1", 0.5, 0.2), B("h2", 0.5, 0.2)) and not bid_gt(B("h2", 0.5, 0.2), B("h1", 0.5, 0.2))


def test_over_capacity_the_less_overloaded_host_wins_then_reward():
    assert bid_gt(B("h9", reward=0.1, support=-0.1), B("h1", reward=0.9, support=-0.2))
    assert bid_gt(B("h9", reward=0.2, support=-0.1), B("h1", reward=0.1, support=-0.1))


def test_nil_bid_is_below_every_bid_and_equal_to_itself():
    nil = nil_bid("j")
    assert nil == Bid("j", None, 0.0, -math.inf, 0)
    assert bid_gt(B("h1", 0.0, -5.0), nil) and not bid_gt(nil, B("h1", 0.0, -5.0))
    assert not bid_gt(nil, nil_bid("j"))


bids = st.builds(
    Bid,
    st.just("j"),
    st.sampled_from([None, "h1", "h2", "h3"]),
    st.sampled_from([0.0, 0.1, 0.5, 1.0]),
    st.sampled_from([-0.5, -0.1, 0.0, 0.1, 0.5]),
    st.integers(0, 3),
).map(lambda b: b if b.winner else nil_bid("j"))


@settings(max_examples=300, deadline=None)
@given(bids, bids, bids)
def test_the_bid_order_is_a_strict_total_order(a, b, c):
    same = bid_key(a) == bid_key(b) and a.winner == b.winner
    assert bid_gt(a, b) + bid_gt(b, a) + same == 1  # exactly one: a > b, b > a, or the same bid
    assert not (bid_gt(a, b) and bid_gt(b, c)) or bid_gt(a, c)  # transitive
    if bid_key(a) != bid_key(b):
        assert bid_gt(a, b) == (bid_key(a) > bid_key(b))


# ------------------------------------------------------------------------------------------ Table 4.7-1

HI, LO = (0.9, 0.5), (0.3, 0.5)


def _b(w, val, r):
    return Bid("j", w, val[0], val[1], r)


ROWS = [
    # (sender q thinks, q's value, q's round, receiver p thinks, p's value, p's round) -> (row, action, broadcast)
    (("q", HI, 1, "p", LO, 1), (1, al.TRIM_UPDATE, True)),
    (("q", LO, 1, "p", HI, 1), (3, al.UPDATE_TIME, True)),
    (("q", LO, 2, "q", LO, 1), (4, al.UPDATE, True)),
    (("q", LO, 1, "q", LO, 1), (5, al.LEAVE, False)),
    (("q", LO, 1, "q", LO, 2), (6, al.LEAVE, False)),
    (("q", HI, 2, "m", LO, 1), (7, al.UPDATE, True)),
    (("q", LO, 1, "m", HI, 2), (8, al.LEAVE, True)),
    (("q", LO, 2, "m", HI, 1), (10, al.RESET, True)),
    (("q", HI, 1, "m", LO, 2), (11, al.RESET, True)),
    (("q", LO, 1, None, LO, 0), (12, al.UPDATE, True)),
    (("p", LO, 1, "p", LO, 1), (13, al.LEAVE, False)),
    (("p", LO, 1, "p", LO, 3), (13, al.LEAVE, True)),
    (("p", LO, 1, "q", LO, 1), (14, al.RESET, True)),
    (("p", LO, 1, "m", LO, 1), (15, al.LEAVE, True)),
    (("p", LO, 1, None, LO, 0), (16, al.LEAVE, True)),
    (("m", HI, 1, "p", LO, 1), (17, al.TRIM_UPDATE, True)),
    (("m", LO, 1, "p", HI, 1), (19, al.UPDATE_TIME, True)),
    (("m", LO, 2, "q", LO, 2), (20, al.UPDATE, True)),
    (("m", LO, 1, "q", LO, 2), (21, al.RESET, True)),
    (("m", LO, 3, "m", LO, 2), (22, al.UPDATE, True)),
    (("m", LO, 2, "m", LO, 2), (23, al.LEAVE, False)),
    (("m", LO, 1, "m", LO, 2), (24, al.LEAVE, False)),
    (("m", HI, 2, "n", LO, 1), (25, al.UPDATE, True)),
    (("m", LO, 1, "n", HI, 2), (26, al.LEAVE, True)),
    (("m", LO, 2, "n", HI, 1), (28, al.RESET, True)),
    (("m", HI, 1, "n", LO, 2), (29, al.RESET, True)),
    (("m", LO, 1, None, LO, 0), (30, al.UPDATE, True)),
    ((None, LO, 0, "p", LO, 1), (31, al.LEAVE, True)),
    ((None, LO, 0, "q", LO, 1), (32, al.UPDATE, True)),
    ((None, LO, 3, "m", LO, 1), (33, al.UPDATE, True)),
    ((None, LO, 0, "m", LO, 1), (33, al.LEAVE, True)),
    ((None, LO, 0, None, LO, 0), (34, al.LEAVE, False)),
]


@pytest.mark.parametrize(("case", "want"), ROWS, ids=[f"row{w[0]}-{w[1]}" for _c, w in ROWS])
def test_table_4_7_1_rows(case, want):
    zq, yq, rq, zp, yp, rp = case
    sb = _b(zq, yq, rq) if zq else Bid("j", None, 0.0, -math.inf, rq)
    rb = _b(zp, yp, rp) if zp else nil_bid("j")
    assert tuple(resolve("p", "q", sb, rb)) == want


def test_equal_values_tie_break_by_lower_host_name_is_rows_2_and_18():
    # equal y: the lower z wins (rows 2 and 18 are part of rows 1 and 17 through the bid order)
    assert resolve("p", "a", _b("a", LO, 1), _b("p", LO, 1)).action == al.TRIM_UPDATE
    assert resolve("p", "z", _b("z", LO, 1), _b("p", LO, 1)).action == al.UPDATE_TIME
    assert resolve("p", "q", _b("a", LO, 1), _b("p", LO, 1)).row == 17


# ------------------------------------------------------------------------------------------ rewards


def test_reward_eq_4_7_2_affinity_and_transfer_penalty():
    a = AgentSpec("a", 0.4, affinity={"b": 0.1, "c": 0.2}, transfer_penalty=0.25, current_host="h1")
    assert agent_reward(a, "h1", ["b", "x"]) == pytest.approx(0.5)  # local: no penalty, bonus of b only
    assert agent_reward(a, "h2", ["b", "c"]) == pytest.approx(0.7 * 0.75)


def test_bundle_reward_eq_4_7_1_penalises_the_agents_past_the_capacity():
    h = HostSpec("h1", 1.0)
    a, b, c = AgentSpec("a", 0.5), AgentSpec("b", 0.4), AgentSpec("c", 0.3)
    assert bundle_reward([a, b], h) == pytest.approx(0.9)
    # c pushes the running cost to 1.2: s = (1 - 1.2) / 1
    assert bundle_reward([a, b, c], h) == pytest.approx(0.9 - 0.2)


# ------------------------------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: AgentSpec("a", -1.0), "AgentSpec(a).cost"),
        (lambda: AgentSpec("a", math.nan), "AgentSpec(a).cost"),
        (lambda: AgentSpec("a", 0.1, transfer_penalty=1.5), "transfer_penalty"),
        (lambda: AgentSpec("a", 0.1, affinity={"a": 0.1}), "affinity"),
        (lambda: AgentSpec("", 0.1), "AgentSpec.id"),
        (lambda: HostSpec("h1", 0.0), "HostSpec(h1).capacity"),
        (lambda: SessionStart("h2", 1, ("h1", "h2"), (), (HostSpec("h1", 1), HostSpec("h2", 1))), "leader"),
        (lambda: SessionStart("h1", 1, ("h1", "h2"), (), (HostSpec("h1", 1),)), "no HostSpec"),
        (lambda: SessionStart("h1", 0, ("h1",), (), (HostSpec("h1", 1),)), "ses_id"),
        (lambda: RebalancePolicy(period=0), "period"),
    ],
)
def test_bad_input_is_a_clear_one_line_error(make, words):
    with pytest.raises(ValueError, match=None) as e:
        make()
    assert words in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("path", sorted((ROOT / "haa/core/allocation").glob("*.py")), ids=lambda p: p.name)
def test_allocation_core_is_sans_io(path):
    forbidden = {"asyncio", "grpc", "time", "socket", "threading", "random", "os", "datetime", "subprocess"}
    tree = parse_source(path)
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not names & forbidden


# ------------------------------------------------------------------------------------------ a tiny driver


class Net:
    """N Allocators, FIFO channels delivered in rounds (each host handles its whole inbox, then
    end_of_inbox), OAC as an ideal total order delivered at once, world changes in that order."""

    def __init__(self, hosts, agents, abort=()):
        self.specs = {h.name: h for h in hosts}
        self.group = tuple(self.specs)
        self.agents = tuple(agents)
        self.allocs = {h: Allocator(h) for h in self.group}
        self.inbox = {h: deque() for h in self.group}
        self.accepted = {h: [] for h in self.group}
        self.proposals = []
        self.abort = list(abort)  # outcomes of the next OAC decisions (False = abort)
        self.messages = 0

    def change(self, start=True):
        for a in self.allocs.values():
            a.on_change(self.group, self.agents, self.specs.values(), start=start)
        self.pump()

    def pump(self, limit=100_000):
        for _ in range(limit):
            progressed = self._effects()
            for h in self.group:
                if self.inbox[h]:
                    progressed = True
                    a = self.allocs[h]
                    while self.inbox[h]:
                        a.on_update(*self.inbox[h].popleft())
                    a.end_of_inbox()
            if not progressed and not self._effects():
                return
        raise AssertionError("no quiescence")

    def _effects(self):
        any_ = False
        for h in self.group:
            for e in self.allocs[h].drain():
                any_ = True
                if isinstance(e, SendUpdate):
                    for d in e.dsts:
                        self.inbox[d].append((h, e.update))
                        self.messages += 1
                elif isinstance(e, (ProposeStart, ProposeFinish)):
                    self.proposals.append(e)
                    ok = self.abort.pop(0) if self.abort else True
                    self._decide(h, e, ok)
                elif isinstance(e, Allocated):
                    self.accepted[h].append(e)
        return any_

    def _decide(self, h, e, ok):
        a = self.allocs[h]
        if isinstance(e, ProposeStart):
            if ok:
                for x in self.allocs.values():
                    x.on_start_committed(e.start, self.group, tuple(g.id for g in self.agents))
            a.on_start_decided(e.start, ok, self.group, self.agents)
        else:
            if ok:
                for x in self.allocs.values():
                    x.on_finish_committed(e.ses_id, e.allocation, self.group, tuple(g.id for g in self.agents))
            a.on_finish_decided(e.ses_id, ok)


HOSTS3 = (HostSpec("h1", 1.0), HostSpec("h2", 1.0, frozenset({"gpu"})), HostSpec("h3", 0.6))


def agents(n=6):
    return [AgentSpec(f"a{i}", 0.1 + 0.05 * i, current_host=f"h{1 + i % 3}", transfer_penalty=0.2) for i in range(n)]


def test_only_the_leader_starts_a_session():
    net = Net(HOSTS3, agents())
    for name, a in net.allocs.items():
        a.on_change(net.group, net.agents, HOSTS3)
        effects = a.drain()
        starts = [e for e in effects if isinstance(e, ProposeStart)]
        assert len(starts) == (1 if name == "h1" else 0)
    assert starts == [] and net.allocs["h1"].ses_id == 1


def test_a_session_reaches_consensus_and_every_host_accepts_the_same_allocation():
    ags = [*agents(), AgentSpec("cam", 0.1, frozenset({"gpu"})), AgentSpec("lidar", 0.1, frozenset({"lidar"}))]
    net = Net(HOSTS3, ags)
    net.change()
    results = {h: acc for h, acc in net.accepted.items()}
    assert all(len(acc) == 1 for acc in results.values())
    first = results["h1"][0]
    assert all(acc[0].allocation == first.allocation for acc in results.values())
    assert first.unallocatable == ("lidar",)  # no host has a lidar: reported, not waited for
    assert set(first.allocation) == {a.id for a in ags} - {"lidar"}
    assert first.allocation["cam"] == "h2"  # the only host with a gpu
    assert set(first.allocation.values()) <= set(net.group)
    for a in net.allocs.values():  # quiet: every host holds the committed winners
        assert {j: b.winner for j, b in a.own_bids().items() if b.winner} == first.allocation


class NoClusters(Allocator):
    MAX_CLUSTER = 1


def test_bids_never_increase_along_a_bundle_even_with_affinity_bonuses():
    """z's reward jumps once `big` is in the bundle (0.1 + 0.4 > 0.3): warped to big's reward."""
    ags = [AgentSpec("big", 0.3), AgentSpec("z", 0.1, affinity={"big": 0.4}), AgentSpec("w", 0.05)]
    a = NoClusters("h1")
    a.on_change(("h1",), tuple(ags), (HostSpec("h1", 2.0),))
    st_ = a.drain()[-1].start
    a.on_start_committed(st_, ("h1",), st_.agent_ids)
    own = a.own_bids()
    assert a.bundle() == ["big", "z", "w"]
    keys = [bid_key(own[j]) for j in a.bundle()]
    assert keys == sorted(keys, reverse=True)
    assert own["z"].reward == pytest.approx(0.3)


def test_affine_agents_are_bid_for_as_one_cluster():
    ags = [
        AgentSpec("big", 0.3),
        AgentSpec("x", 0.2, affinity={"y": 0.5}),
        AgentSpec("y", 0.25, affinity={"x": 0.01}),
        AgentSpec("z", 0.1, affinity={"big": 0.4}),
    ]
    a = Allocator("h1")
    a.on_change(("h1",), tuple(ags), (HostSpec("h1", 2.0),))
    st_ = a.drain()[-1].start
    a.on_start_committed(st_, ("h1",), st_.agent_ids)
    own = a.own_bids()
    order = a.bundle()
    keys = [bid_key(own[j]) for j in order]
    assert keys == sorted(keys, reverse=True)
    s = a.session
    assert any(len(e.agents) > 1 for e in s.bundle), "the affine pair is bid for as one cluster"
    fin = [e for e in a.drain() if isinstance(e, ProposeFinish)]
    assert fin and set(fin[0].allocation) == {"big", "x", "y", "z"}


def test_a_host_keeps_capacity_for_agents_only_it_can_run():
    # h2 alone has the gpu; without the reservation it would fill up with the big local agent first
    hosts = (HostSpec("h1", 1.0), HostSpec("h2", 0.6, frozenset({"gpu"})))
    ags = (AgentSpec("local", 0.5, current_host="h2", transfer_penalty=0.1), AgentSpec("cam", 0.5, frozenset({"gpu"})))
    net = Net(hosts, ags)
    net.change()
    assert net.accepted["h1"][0].allocation == {"local": "h1", "cam": "h2"}


def test_aborted_start_and_finish_are_retried_while_nothing_changed():
    net = Net(HOSTS3, agents(), abort=[False, True, False, True])
    net.change()
    kinds = [type(p).__name__ for p in net.proposals]
    assert kinds == ["ProposeStart", "ProposeStart", "ProposeFinish", "ProposeFinish"]
    assert all(len(acc) == 1 for acc in net.accepted.values())


def test_an_aborted_start_is_given_up_when_the_group_changed():
    a = Allocator("h1")
    a.on_change(("h1", "h2"), tuple(agents(2)), HOSTS3)
    st_ = a.drain()[-1].start
    a.on_start_decided(st_, False, ("h1",), agents(2))
    assert not [e for e in a.drain() if isinstance(e, ProposeStart)]


@pytest.mark.parametrize(
    ("group", "ids", "committed", "reason"),
    [
        (("h2", "h1"), ("a0", "a1"), 0, "not the leader"),
        (("h1", "h2", "h3"), ("a0", "a1"), 0, "group changed"),
        (("h1", "h2"), ("a0", "a1"), 1, "not above"),
    ],
)
def test_an_expired_start_opens_no_session(group, ids, committed, reason):
    st_ = SessionStart("h1", 1, ("h1", "h2"), tuple(agents(2)), HOSTS3[:2])
    b = Allocator("h2", committed_ses=committed)
    assert reason in b.start_valid(st_, group, ids)
    b.on_start_committed(st_, group, ids)
    assert b.session is None or not b.session.ready
    assert not [e for e in b.drain() if isinstance(e, SendUpdate)]


def test_an_agent_list_change_expires_neither_start_nor_finish():
    """The start's agent list is a snapshot (docs/allocation.md, "Sessions of a bounded size"): an agent added
    or removed between the start and its commit, or between the start and the finish, leaves the session valid;
    the added agent waits for the next session. With ll. 39-40's rule a stream of spawns expired every session."""
    st_ = SessionStart("h1", 1, ("h1", "h2"), tuple(agents(2)), HOSTS3[:2])
    b = Allocator("h2")
    assert b.start_valid(st_, ("h1", "h2"), ("a0",)) == ""
    assert b.start_valid(st_, ("h1", "h2"), ("a0", "a1", "a9")) == ""
    b.on_start_committed(st_, ("h1", "h2"), ("a0", "a1", "a9"))
    assert b.session is not None and b.session.ready
    assert b.finish_valid(1, ("h1", "h2"), ("a1", "a9")) == ""
    assert "group changed" in b.finish_valid(1, ("h1", "h2", "h3"), ("a0", "a1"))


def test_a_start_id_used_up_by_an_expired_start_is_proposed_again_under_a_new_id():
    """The former leader h1's start 1 commits after the membership change (expired: h1 is not the leader) but
    before h2's own start 1, which h2 proposed without knowing of it: every host rejects h2's start 1 as
    'not above', so h2 proposes the session again as 2."""
    group = ("h2", "h3")
    ags = tuple(agents(2))
    old = SessionStart("h1", 1, ("h1", "h2", "h3"), ags, HOSTS3)
    h2, h3 = Allocator("h2"), Allocator("h3")
    for x in (h2, h3):
        x.on_change(group, ags, HOSTS3)
    mine = h2.drain()[-1].start
    assert mine.ses_id == 1
    h2.on_start_decided(mine, True, group, ags)  # the OAC outcome may reach h2 before the delivery
    for x in (h2, h3):
        x.on_start_committed(old, group, st_ids := tuple(a.id for a in ags))
        x.on_start_committed(mine, group, st_ids)
        assert x.committed_ses == 1 and x.committed_start is None
    again = [e.start for e in h2.drain() if isinstance(e, ProposeStart)]
    assert [s.ses_id for s in again] == [2] and again[0].group == group
    h3.on_start_committed(again[0], group, st_ids)
    assert h3.committed_start == again[0]


def test_a_finish_is_accepted_once_and_only_for_the_unexpired_last_session():
    net = Net(HOSTS3, agents())
    net.change()
    b = net.allocs["h2"]
    alloc = dict(net.accepted["h2"][0].allocation)
    b.on_finish_committed(1, alloc, net.group, tuple(a.id for a in net.agents))  # a duplicate
    assert not [e for e in b.drain() if isinstance(e, Allocated)]
    st2 = SessionStart("h1", 2, net.group, net.agents, HOSTS3)
    b.on_start_committed(st2, net.group, st2.agent_ids)
    b.drain()
    b.on_finish_committed(2, alloc, net.group[:2], st2.agent_ids)  # the group changed after the start
    assert "group changed" in b.finish_valid(2, net.group[:2], st2.agent_ids)
    assert not [e for e in b.drain() if isinstance(e, Allocated)]
    b.on_finish_committed(1, alloc, net.group, st2.agent_ids)  # an older session
    assert not [e for e in b.drain() if isinstance(e, Allocated)]


def test_updates_of_an_old_session_are_ignored_and_a_newer_one_is_joined_without_bidding():
    a = Allocator("h2")
    a.on_change(("h1", "h2"), tuple(agents(2)), HOSTS3)
    a.on_update("h1", BidUpdate(3, (Bid("a0", "h1", 0.2, 0.5, 4),)))  # session 3 started elsewhere (l. 62)
    a.end_of_inbox()
    assert a.ses_id == 3 and a.own_bids()["a0"].winner == "h1"
    assert not [e for e in a.drain() if isinstance(e, SendUpdate)]  # not ready: no bids, no sends
    a.on_update("h1", BidUpdate(2, (Bid("a1", "h1", 0.2, 0.5, 9),)))  # older: ignored (l. 60)
    assert "a1" not in a.own_bids()
    st_ = SessionStart("h1", 3, ("h1", "h2"), tuple(agents(2)), HOSTS3[:2])
    a.on_start_committed(st_, st_.group, st_.agent_ids)
    assert [e for e in a.drain() if isinstance(e, SendUpdate)]  # ready: builds and distributes


def test_reset_broadcasts_the_receivers_nil_bid():
    """Row 14 with the thesis' change: q thinks p wins, p thinks q wins: p resets and sends its nil bid."""
    a = Allocator("p")
    hosts = (HostSpec("p", 1), HostSpec("q", 1))
    st_ = SessionStart("p", 1, ("p", "q"), (AgentSpec("j", 0.1, frozenset({"x"})),), hosts)
    a.on_change(st_.group, st_.agents, st_.hosts, start=False)
    a.on_start_committed(st_, st_.group, st_.agent_ids)
    a.on_update("q", BidUpdate(1, (Bid("j", "q", 0.1, 0.9, 1),)))  # nobody has "x": q's word only
    a.end_of_inbox()
    a.drain()
    a.on_update("q", BidUpdate(1, (Bid("j", "p", 0.1, 0.9, 2),)))
    a.end_of_inbox()
    sent = [b for e in a.drain() if isinstance(e, SendUpdate) for b in e.update.bids]
    assert sent == [nil_bid("j")] and a.own_bids()["j"] == nil_bid("j")


def test_a_host_removed_from_the_group_goes_silent():
    net = Net(HOSTS3, agents())
    net.change()
    b = net.allocs["h3"]
    b.on_change(("h1", "h2"), net.agents, HOSTS3)
    assert b.session is None
    b.on_update("h1", BidUpdate(9, (Bid("a0", "h1", 0.2, 0.5, 1),)))
    b.end_of_inbox()
    assert not [e for e in b.drain() if isinstance(e, (SendUpdate, ProposeStart))]


def test_consensus_waits_for_the_queued_build():
    """l. 75-76 would check consensus before the build l. 77-79 queued: with the leader's own row equal to
    the sender's after the update, it would decide an allocation it is about to change."""
    hosts = (HostSpec("h1", 0.88), HostSpec("h2", 0.545))
    ags = (
        AgentSpec("a1", 0.295, transfer_penalty=0.195),
        AgentSpec("a2", 0.097, transfer_penalty=0.012, current_host="h1"),
        AgentSpec("a3", 0.513, transfer_penalty=0.026, current_host="h2"),
    )
    h1, h2 = Allocator("h1"), Allocator("h2")
    for x in (h1, h2):
        x.on_change(("h1", "h2"), ags, hosts)
    st_ = h1.drain()[-1].start
    h1.on_start_committed(st_, st_.group, st_.agent_ids)  # h1 bids a3 first, then a1, a2
    h1.drain()
    h2.on_start_committed(st_, st_.group, st_.agent_ids)  # h2 bids for everything, a3 higher than h1
    upd = next(e for e in h2.drain() if isinstance(e, SendUpdate)).update
    h1.on_update("h2", upd)  # h1 loses a3, its later bids are trimmed: its row now equals h2's ...
    assert h1.session.build_queued
    assert not [e for e in h1.drain() if isinstance(e, ProposeFinish)]  # ... but it must not decide yet
    h1.end_of_inbox()
    assert {j: b.winner for j, b in h1.own_bids().items()} == {"a1": "h1", "a2": "h1", "a3": "h2"}


def test_messages_and_rounds_stay_small_on_a_clean_session():
    net = Net((HostSpec("h1", 1.0), HostSpec("h2", 1.0), HostSpec("h3", 1.0), HostSpec("h4", 1.0)), agents(8))
    net.change()
    assert net.messages < 200
    assert len(net.accepted["h4"]) == 1


# ------------------------------------------------------------------------------------------ rebalance policy


def test_rebalance_policy_rate_limits_changes_and_pauses_only_the_periodic_sessions():
    p = RebalancePolicy(period=10.0, min_interval=1.0, session_timeout=3.0)
    assert p.changed(0.0)  # first change: at once
    assert not p.changed(0.4)  # rate limited, and the session still runs ...
    assert p.deadline() == 3.0 and not p.due(2.9)  # ... so the change waits for its finish (or timeout)
    p.finished(0.6)
    assert p.deadline() == 1.0 and not p.due(0.9) and p.due(1.0)  # ... one session for the burst
    p.finished(1.5)
    assert p.deadline() == 11.0 and not p.due(10.9) and p.due(11.0)  # periodic
    p.pause()
    assert p.deadline() is None and not p.due(100.0)
    assert p.changed(100.0)  # a change still starts a session while paused
    p.resume()
    assert p.deadline() == 110.0  # running, period > session_timeout
    assert p.starts == 4


def test_a_group_change_does_not_wait_for_the_running_session_and_a_finish_with_agents_left_asks_for_more():
    p = RebalancePolicy(period=10.0, min_interval=1.0, session_timeout=3.0)
    assert p.changed(0.0)
    assert not p.changed(1.2)  # an agent-list change waits for the running session
    assert p.changed(1.3, urgent=True)  # a group change: the running session cannot finish any more
    p.finished(1.5)
    assert p.deadline() == 11.3  # nothing pending
    p.more(1.5)  # the bounded session left agents for the next one
    assert p.deadline() == 2.3 and p.due(2.3) and p.starts == 3


def test_periodic_rebalance_waits_for_a_running_session_up_to_its_timeout():
    p = RebalancePolicy(period=1.0, min_interval=0.0, session_timeout=5.0)
    assert p.changed(0.0)
    assert p.deadline() == 5.0 and not p.due(2.0) and p.due(5.0)


def test_rebalance_through_the_allocator_opens_a_new_session():
    net = Net(HOSTS3, agents())
    net.change()
    net.allocs["h1"].on_change(net.group, net.agents, HOSTS3, start=True)
    net.pump()
    assert [e.ses_id for e in net.accepted["h3"]] == [1, 2]


@pytest.mark.parametrize("n", [1, 2, 5])
def test_group_sizes_and_empty_agent_lists(n):
    hosts = tuple(HostSpec(f"h{i + 1}", 1.0) for i in range(n))
    for ags in ((), tuple(agents(4))):
        net = Net(hosts, ags)
        net.change()
        assert all(len(acc) == 1 and set(acc[0].allocation) == {a.id for a in ags} for acc in net.accepted.values())


def test_permutations_of_delivery_order_agree():
    """Whatever order the hosts handle their inboxes in, they end with one committed allocation each."""
    for perm in itertools.permutations(("h1", "h2", "h3")):
        net = Net(HOSTS3, agents(5))
        net.group = tuple(perm) if perm[0] == "h1" else net.group
        net.change()
        assert len({tuple(sorted(acc[0].allocation.items())) for acc in net.accepted.values()}) == 1
