"""A host joins: the allocation moves agents once, and only for a gain (docs/allocation.md, "Joins and
hysteresis"). Sans-I/O sessions on the `Allocator` (the hysteresis) and the agent layer in the deterministic
simulator (`haa.lab.dsim.joins`, `haactl verify join`: the joiner's capacity, the move-and-back)."""

from __future__ import annotations

import random

import pytest
from test_allocation import Net

from haa.core.allocation.allocation import Allocator
from haa.core.allocation.bids import bid_key
from haa.core.allocation.specs import AgentSpec, HostSpec
from haa.lab.dsim import mutations
from haa.lab.dsim.joins import draw_join, run_join
from haa.lab.dsim.sweep import run_seed


class NoHysteresis(Allocator):
    MIN_TRANSFER_PENALTY = 0.0
    HYSTERESIS = 0.0


def allocate(hosts, agents, cls=Allocator):
    net = Net(hosts, agents)
    net.allocs = {h: cls(h) for h in net.group}
    net.change()
    return net.accepted["h1"][0].allocation


def placed(agents, alloc):
    return [AgentSpec(a.id, a.cost, transfer_penalty=a.transfer_penalty, current_host=alloc[a.id]) for a in agents]


# ------------------------------------------------------------------------------------------ hysteresis


def test_within_capacity_a_running_agent_stays_when_the_rewards_tie():
    """t_i = 0 (most agent types): every host bids the same reward, and without hysteresis the support — the
    agent's place in each bundle — decided: `a` went to the emptier h2 for no gain in eq. 4.7-1."""
    hosts = (HostSpec("h1", 1.0), HostSpec("h2", 1.0))
    ags = [AgentSpec("a", 0.3, current_host="h1"), AgentSpec("b", 0.3, current_host="h1")]
    assert allocate(hosts, ags) == {"a": "h1", "b": "h1"}
    assert set(allocate(hosts, ags, NoHysteresis).values()) == {"h1", "h2"}


def test_over_capacity_an_agent_moves_only_to_a_host_less_overloaded_by_more_than_the_margin():
    hosts = (HostSpec("h1", 1.0), HostSpec("h2", 1.0))
    # h1 at 1.25, h2 at 1.1: moving c (0.1) leaves h2 at 1.2, overloaded by 0.05 less than h1's 1.25 (< 0.1)
    near = [AgentSpec("a", 0.6, current_host="h1"), AgentSpec("b", 0.55, current_host="h1"),
            AgentSpec("c", 0.1, current_host="h1"), AgentSpec("d", 1.1, current_host="h2")]
    assert allocate(hosts, near)["c"] == "h1"
    assert allocate(hosts, near, NoHysteresis)["c"] == "h2"
    # h1 at 1.6: h2 with c (1.2) is overloaded by 0.3 less
    far = [AgentSpec("a", 0.6, current_host="h1"), AgentSpec("b", 0.9, current_host="h1"),
           AgentSpec("c", 0.1, current_host="h1"), AgentSpec("d", 1.1, current_host="h2")]
    assert allocate(hosts, far)["c"] == "h2"


def test_an_agent_that_runs_nowhere_yet_is_placed_as_before():
    """New agents (and agents of a failed host) carry no margin: the least loaded host takes them."""
    hosts = (HostSpec("h1", 1.0), HostSpec("h2", 1.0))
    ags = [AgentSpec("a", 0.3, current_host="h1"), AgentSpec("new", 0.3)]
    assert allocate(hosts, ags) == allocate(hosts, ags, NoHysteresis) == {"a": "h1", "new": "h2"}


def test_bids_never_increase_along_a_bundle_with_the_margin():
    """A bid with the margin may be followed by one without: its support is warped like its reward, so the
    bundle's bids still decrease (diminishing marginal gains, docs/allocation.md "bid warping")."""
    ags = [AgentSpec("far", 0.05, current_host="h2"), AgentSpec("own", 0.01, current_host="h1"),
           AgentSpec("big", 0.3, current_host="h2")]
    a = Allocator("h1")
    hosts = (HostSpec("h1", 0.3), HostSpec("h2", 0.2))
    a.on_change(("h1", "h2"), tuple(ags), hosts)
    st_ = a.drain()[-1].start
    a.on_start_committed(st_, ("h1", "h2"), st_.agent_ids)
    own = a.own_bids()
    keys = [bid_key(own[j]) for j in a.bundle()]
    assert len(keys) == 3 and keys == sorted(keys, reverse=True)


def _join_instance(seed):
    rng = random.Random(seed)
    k = rng.choice([0.5, 2 / 3, 1.0])
    old = [HostSpec(f"h{i + 1}", k) for i in range(3)]
    ags = [AgentSpec(f"a{i}", round(rng.uniform(0.05, 0.3), 3), transfer_penalty=rng.choice([0, 0, 0, 0.1, 0.5]))
           for i in range(rng.randint(5, 12))]
    return old, ags, HostSpec("h4", k)


@pytest.mark.parametrize(("cls", "most_moves", "least_shuffles"), [(Allocator, 40, 0), (NoHysteresis, None, 30)])
def test_a_join_moves_agents_to_the_joiner_not_among_the_others(cls, most_moves, least_shuffles):
    """60 groups of 3 hosts (0.5-1 core, 5-12 agents, up to 2x overloaded) are allocated, then a 4th host
    joins. Without hysteresis the join's session moved 176 agents, 52 of them among the 3 hosts (seeds
    0..59); with it 26, every one to the joiner."""
    moves = shuffles = 0
    for seed in range(60):
        old, ags, joiner = _join_instance(seed)
        before = allocate(old, ags, cls)
        after = allocate([*old, joiner], placed(ags, before), cls)
        for j in before:
            if after[j] != before[j]:
                moves += 1
                shuffles += after[j] != "h4"
    if most_moves is not None:
        assert moves <= most_moves
    assert shuffles >= least_shuffles if cls is NoHysteresis else shuffles == 0


def test_a_second_session_on_the_same_group_moves_nothing():
    for seed in range(30):
        old, ags, joiner = _join_instance(seed)
        hosts = [*old, joiner]
        first = allocate(hosts, placed(ags, allocate(old, ags)))
        assert allocate(hosts, placed(ags, first)) == first, seed


# ------------------------------------------------------------------------------------------ the agent layer

#: seeds of `haactl verify join` on which the agent layer as it was moved agents twice after one join
#: (AA-Join-Stable), at 7 hosts: HEAD before the fix failed 24 of seeds 0..39, these among them
FLAPPED = (0, 1, 3, 6)
#: and with that fix, seed 189 still moved two agents between old hosts in the join's session (the joiner bid
#: for nothing, but CBBA re-ran over the same agents and hosts) and again to the joiner a session later: the
#: join's session is now skipped while no joiner has its entry (AllocGlue.view_changed, only_new_hosts)
FLAPPED += (189,)


@pytest.mark.parametrize("seed", FLAPPED)
def test_after_a_join_no_agent_is_transferred_twice(seed):
    sim, vs = run_join(seed, 7)
    assert [str(v) for v in vs] == []
    assert sim.joined_at, "a host joined"
    members = {m.name for m in sim._members()[0].core.m.state.members}
    # every member's capacity is in the agent table, the first host's too (its first write is refused: the
    # group is not formed yet; it is written again)
    assert set(sim._members()[0].core.table.hosts) == members


def test_a_joiner_read_as_one_core_moves_agents_twice():
    """The mutation puts the old `_host_specs` back (a joiner without HostInfo bids as one core): caught."""
    undo = mutations.apply("joiner-default-capacity")
    try:
        r = run_seed("join", 5, 7)
    finally:
        undo()
    assert any(v.startswith("AA-Join-Stable") for v in r.violations), r.violations


def test_a_joiner_without_host_info_bids_for_nothing():
    from haa.lab.dsim.joins import JoinSim

    sim = JoinSim(draw_join(0, 7))
    sim.run()
    node = sim._members()[0].core
    name = node.name
    info = node.table.hosts.pop(name)
    try:
        spec = {h.name: h for h in node.alloc.host_specs()}[name]
        assert spec.draining and not spec.hardware
    finally:
        node.table.hosts[name] = info
    assert not {h.name: h for h in node.alloc.host_specs()}[name].draining


def test_a_host_that_left_the_group_does_not_push_for_ever():
    """Once every member publishes its HostInfo, `haactl verify recovery` seed 238 let a host that had left
    route a refused queue push again in the same drain, for ever; it drops them now (the group fences them)."""
    r = run_seed("recovery", 238, 7)
    assert r.violations == [] and r.liveness_checked
