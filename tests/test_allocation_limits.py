"""Per-host limits of an agent kind (SupervisorSLAM's "at most one sensor agent of each type per
host"): the allocator never places more than `max_per_host` agents of a limited kind on one host, in the first
session and in rebalancing sessions, and reports the agents beyond the kind's places as unallocatable."""

from __future__ import annotations

import random
from collections import Counter

import pytest
from test_allocation import Net

from haa.core.allocation import allocwire
from haa.core.allocation.allocation import Allocator
from haa.core.allocation.specs import AgentSpec, HostSpec, SessionStart, over_limit


def sensor(i, kind="sonar", limit=1, cost=0.1, host=None, hw=frozenset()):
    return AgentSpec(f"{kind}{i}", cost, hw, current_host=host, kind=kind, max_per_host=limit)


def per_host(alloc, agents):
    kinds = {a.id: a.kind for a in agents if a.max_per_host}
    return Counter((h, kinds[a]) for a, h in alloc.items() if a in kinds)


def run(hosts, ags):
    net = Net(hosts, ags)
    net.change()
    acc = {h: a[-1] for h, a in net.accepted.items()}
    first = acc[hosts[0].name]
    assert all(x.allocation == first.allocation for x in acc.values())
    return net, first


def test_one_per_host_even_when_one_host_could_take_them_all():
    # h1 is far bigger: without the limit it wins every cheap sonar agent (its support is highest)
    hosts = (HostSpec("h1", 8.0), HostSpec("h2", 0.5), HostSpec("h3", 0.5))
    ags = [sensor(i) for i in range(3)] + [AgentSpec("other", 0.1)]
    _net, res = run(hosts, ags)
    assert max(per_host(res.allocation, ags).values()) == 1
    assert set(res.allocation) == {a.id for a in ags} and res.unallocatable == ()


def test_agents_beyond_the_places_are_unallocatable_like_a_hardware_mismatch():
    hosts = (HostSpec("h1", 4.0), HostSpec("h2", 4.0))
    ags = [sensor(i) for i in range(4)] + [sensor(i, "landmark", 2) for i in range(5)]
    _net, res = run(hosts, ags)
    counts = per_host(res.allocation, ags)
    assert all(n <= (1 if k == "sonar" else 2) for (_h, k), n in counts.items())
    assert res.unallocatable == ("sonar2", "sonar3", "landmark4")  # the session's order: the first ones placed
    assert len(res.allocation) == 2 + 4


def test_running_agents_keep_their_places_before_new_ones():
    hosts = (HostSpec("h1", 1.0), HostSpec("h2", 1.0))
    ags = [sensor(0), sensor(1, host="h2"), sensor(2, host="h1"), sensor(3, host="h1")]
    st = SessionStart("h1", 1, ("h1", "h2"), tuple(ags), hosts)
    # sonar1 and sonar2 run on h2 and h1: they keep the two places; sonar3 is a second one on h1
    assert st.unallocatable() == ("sonar0", "sonar3")


def test_hardware_and_draining_hosts_reduce_the_places():
    cam = frozenset({"camera"})
    hosts = (HostSpec("h1", 1.0, cam), HostSpec("h2", 1.0), HostSpec("h3", 1.0, cam, draining=True))
    ags = [sensor(i, "ff", 1, hw=cam) for i in range(3)]
    _net, res = run(hosts, ags)
    assert res.allocation == {"ff0": "h1"} and res.unallocatable == ("ff1", "ff2")
    assert over_limit(ags, hosts) == ["ff1", "ff2"]


def test_a_rebalance_keeps_the_limit():
    hosts = (HostSpec("h1", 2.0), HostSpec("h2", 2.0), HostSpec("h3", 2.0))
    ags = [sensor(i, cost=0.3) for i in range(3)] + [AgentSpec(f"x{i}", 0.4) for i in range(4)]
    _net, res = run(hosts, ags)
    assert max(per_host(res.allocation, ags).values()) == 1
    # the agents now run where they were placed; a host leaves, and costs change: a new session
    moved = tuple(AgentSpec(a.id, a.cost * 1.5, a.hardware, {}, 0.3, res.allocation.get(a.id), a.kind, a.max_per_host)
                  for a in ags)
    _net2, res2 = run(hosts[:2], moved)
    assert max(per_host(res2.allocation, moved).values()) == 1
    assert len(res2.unallocatable) == 1 and res2.unallocatable[0].startswith("sonar")
    # the two that ran on the remaining hosts kept their places
    kept = {a for a, h in res.allocation.items() if a.startswith("sonar") and h in ("h1", "h2")}
    assert kept <= set(res2.allocation)


def test_limits_hold_on_random_instances():
    for seed in range(60):
        rng = random.Random(seed)
        hosts = tuple(HostSpec(f"h{i}", round(rng.uniform(0.3, 3.0), 2)) for i in range(rng.randint(1, 5)))
        names = [h.name for h in hosts]
        ags = []
        for k, kind in enumerate(("sonar", "landmark", "cooc")):
            limit = rng.randint(1, 2)
            for i in range(rng.randint(0, 5)):
                ags.append(sensor(i, kind, limit, round(rng.uniform(0.05, 0.6), 2),
                                  rng.choice([*names, None]) if k else None))
        ags += [
            AgentSpec(
                f"x{i}", round(rng.uniform(0.05, 0.6), 2), affinity={o.id: 0.2 for o in ags[:2] if rng.random() < 0.5}
            )
            for i in range(rng.randint(0, 4))
        ]
        _net, res = run(hosts, ags)
        lim = {a.kind: a.max_per_host for a in ags if a.max_per_host}
        for (_h, k), n in per_host(res.allocation, ags).items():
            assert n <= lim[k], (seed, res.allocation)
        assert set(res.allocation) | set(res.unallocatable) == {a.id for a in ags}
        # every place that exists is used
        for kind, limit in lim.items():
            members = [a for a in ags if a.kind == kind]
            placed = sum(1 for a in members if a.id in res.allocation)
            assert placed == min(len(members), limit * len(hosts)), seed


def test_without_the_limit_a_big_host_takes_several():
    class Ignore(Allocator):
        PER_HOST_LIMIT = False

    hosts = (HostSpec("h1", 8.0), HostSpec("h2", 0.5), HostSpec("h3", 0.5))
    ags = [sensor(i) for i in range(3)]
    net = Net(hosts, ags)
    net.allocs = {h: Ignore(h) for h in net.group}
    net.change()
    alloc = net.accepted["h1"][-1].allocation
    assert max(per_host(alloc, ags).values()) > 1  # what the verifier's `ignore-per-host-limit` variant does


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: AgentSpec("a", 0.1, kind="s", max_per_host=-1), "max_per_host"),
        (lambda: AgentSpec("a", 0.1, kind="s", max_per_host=1001), "max_per_host"),
        (lambda: AgentSpec("a", 0.1, kind="s", max_per_host=True), "max_per_host"),
        (lambda: AgentSpec("a", 0.1, kind="s", max_per_host=1.0), "max_per_host"),
        (lambda: AgentSpec("a", 0.1, max_per_host=1), "kind"),
        (lambda: AgentSpec("a", 0.1, kind="k" * 65), "kind"),
        (lambda: SessionStart("h", 1, ("h",), (sensor(0), sensor(1, limit=2)), (HostSpec("h", 1.0),)), "limits"),
        (lambda: SessionStart("h", 1, ("h",), (sensor(0), sensor(1, hw=frozenset({"x"}))), (HostSpec("h", 1.0),)),
         "hardware"),
        (lambda: SessionStart("h", 1, ("h",), (sensor(0), AgentSpec("b", 0.1, kind="sonar")), (HostSpec("h", 1.0),)),
         "limits"),
    ],
)
def test_bad_limits_are_a_clear_one_line_error(make, words):
    with pytest.raises(ValueError, match=words):
        make()


def test_the_wire_carries_kind_and_limit_and_refuses_bad_ones():
    hosts = (HostSpec("h1", 1.0),)
    st = SessionStart("h1", 3, ("h1",), (sensor(0), sensor(1), AgentSpec("x", 0.2)), hosts)
    assert allocwire.decode_start(allocwire.encode_start(st)) == st
    from haa.pb import alloc_pb2 as apb

    m = apb.AllocStart()
    m.ParseFromString(allocwire.encode_start(st))
    m.agents[1].max_per_host = 2  # disagrees with sonar0
    with pytest.raises(allocwire.AllocWireError, match="per-host limits"):
        allocwire.decode_start(m.SerializeToString())
    m.agents[1].max_per_host = 5000
    with pytest.raises(allocwire.AllocWireError, match="max_per_host"):
        allocwire.decode_start(m.SerializeToString())


# ------------------------------------------------------------------------------------------ the agent table


def _create(aid, type_="sonar", limit=1, hw=()):
    from haa.pb import agenttx_pb2 as apb

    tx = apb.AgentTx()
    c = tx.create
    c.id, c.type, c.recovery, c.cost, c.max_per_host = aid, type_, "backup", 0.1, limit
    c.hardware.extend(hw)
    return tx.SerializeToString()


def test_the_table_refuses_bad_limits_and_disagreeing_creates_on_every_replica():
    from haa.core.ddb import agenttable as at

    t1, t2 = at.AgentTable(), at.AgentTable()
    for t in (t1, t2):
        assert t.apply(_create("s1"), ("h1",)).ok
        bad = t.apply(_create("s2", limit=2), ("h1",))
        assert not bad.ok and "same max_per_host and hardware" in bad.reason
        bad = t.apply(_create("s3", hw=("camera",)), ("h1",))
        assert not bad.ok and "same max_per_host and hardware" in bad.reason
        bad = t.apply(_create("s4", type_="other", limit=5000), ("h1",))
        assert not bad.ok and "max_per_host must be an integer in [0, 1000]" in bad.reason
        assert t.apply(_create("s5"), ("h1",)).ok
        assert t.apply(_create("x1", type_="other", limit=0), ("h1",)).ok
    assert t1.content_hash() == t2.content_hash() and not t1.invalid_values()


def test_a_finish_unallocates_limited_agents_it_leaves_out_and_a_move_keeps_the_limit():
    from haa.core.ddb import agenttable as at
    from haa.pb import agenttx_pb2 as apb

    t = at.AgentTable()
    for a in ("s1", "s2"):
        assert t.apply(_create(a), ("h1",)).ok
    assert t.apply(_create("x", type_="other", limit=0), ("h1",)).ok

    def tx(fill):
        m = apb.AgentTx()
        fill(m)
        return m.SerializeToString()

    def start(m, ses):
        m.start.ses_id, m.start.leader = ses, "h1"
        m.start.group.extend(["h1", "h2"])
        m.start.agents.extend(t.agent_ids())

    def finish(m, ses, alloc):
        m.finish.ses_id, m.finish.leader = ses, "h1"
        m.finish.allocation.update(alloc)

    assert t.apply(tx(lambda m: start(m, 1)), ("h1", "h2")).ok
    assert t.apply(tx(lambda m: finish(m, 1, {"s1": "h1", "s2": "h2", "x": "h1"})), ("h1", "h2")).ok
    # an operator move onto a host that has its type's one agent is refused; onto a free one it is not
    mv = t.apply(tx(lambda m: (setattr(m.move, "id", "s2"), setattr(m.move, "host", "h1"))), ("h1", "h2"))
    assert not mv.ok and "at most 1 per host" in mv.reason
    assert t.apply(tx(lambda m: (setattr(m.move, "id", "x"), setattr(m.move, "host", "h2"))), ("h1", "h2")).ok
    # h2 left: the next allocation places s1 only; s2 is allocated nowhere, x keeps its allocation rule
    assert t.apply(tx(lambda m: start(m, 2)), ("h1",)).ok is False  # group changed: expired
    t.on_removed(["h2"])
    assert t.apply(tx(lambda m: (start(m, 3), m.start.ClearField("group"), m.start.group.append("h1"))), ("h1",)).ok
    res = t.apply(tx(lambda m: finish(m, 3, {"s2": "h1", "x": "h1"})), ("h1",))
    assert res.ok and t.get("s1").alloc == "" and t.get("s2").alloc == "h1" and "s1" in res.touched


# ------------------------------------------------------------------------------------------ the verifier


def test_the_verifier_checks_the_limit_in_schedules_with_faults():
    from haa.lab.dsim.alloccheck import PROPS
    from haa.lab.dsim.allocschedule import draw_alloc
    from haa.lab.dsim.sweep import run_seed

    assert "AA-Per-Host-Limit" in PROPS
    limited = [s for s in range(40) if any(a.max_per_host for a in draw_alloc(s, 5).agents)]
    assert len(limited) >= 10
    for s in limited[:12]:
        assert not run_seed("allocation", s, 5).violations, s


def test_an_unallocatable_limited_agent_gets_a_place_when_a_host_joins():
    from haa.lab.dsim.alloccheck import check_alloc
    from haa.lab.dsim.allocschedule import AFault, AllocScenario
    from haa.lab.dsim.allocsim import AllocSim

    names = ["h1", "h2"]
    agents = tuple(sensor(i) for i in range(3))
    sc = AllocScenario(seed=1, names=names, hosts={n: HostSpec(n, 1.0) for n in names}, agents=agents,
                       faults=[AFault(0.3, "join", "h3", HostSpec("h3", 1.0))])
    sim = AllocSim(sc)
    sim.run()
    assert check_alloc(sim) == []
    firsts = [n.accepted[0][3] for n in sim.nodes.values() if n.accepted and n.name != "h3"]
    lasts = [n.accepted[-1][3] for n in sim.nodes.values() if n.accepted]
    assert all(len(f) == 2 for f in firsts)  # two places for three sonar agents
    assert all(len(x) == 3 and len(set(x.values())) == 3 for x in lasts)  # h3 joined: one on each host


# ------------------------------------------------------------------------------------------ host capacities


def test_local_hosts_share_the_machines_cores(monkeypatch):
    from haa.cluster import local_backend as lb

    assert lb.share_of_cores(4, 2) == 0.5
    assert lb.share_of_cores(3, 2) == 0.667
    assert lb.share_of_cores(1, 8) == 8.0
    assert lb.share_of_cores(10**6, 1) == 0.001  # the allocator's MIN_CAPACITY
    assert 1 <= lb.machine_cores() <= (__import__("os").cpu_count() or 1)
    monkeypatch.delenv("HAA_CAPACITY", raising=False)
    assert not lb._sets_capacity(["--rebalance-period", "5"], {})
    assert lb._sets_capacity(["--capacity", "2"], {})
    assert lb._sets_capacity(["--capacity=2"], {})
    assert lb._sets_capacity([], {"capacity": 0.5})
    monkeypatch.setenv("HAA_CAPACITY", "3")
    assert lb._sets_capacity([], {})


def test_cluster_up_passes_the_share_or_the_explicit_capacity(tmp_path, monkeypatch):
    from haa.cluster import local_backend as lb

    monkeypatch.delenv("HAA_CAPACITY", raising=False)
    spawned = []
    monkeypatch.setattr(lb.LocalBackend, "_spawn", lambda self, name: spawned.append(list(self.state["args"])))
    monkeypatch.setattr(lb, "machine_cores", lambda: 2)
    b = lb.LocalBackend(tmp_path / "c1")
    b.up(4, 3)
    assert spawned[0][-2:] == ["--capacity", "0.5"] and len(spawned) == 4
    spawned.clear()
    lb.LocalBackend(tmp_path / "c2").up(2, 2, capacity=3.0)
    assert spawned[0][-2:] == ["--capacity", "3.0"]
    spawned.clear()
    lb.LocalBackend(tmp_path / "c3").up(2, 2, ["--capacity", "0.25"])
    assert spawned[0] == ["--capacity", "0.25"]  # the operator's own setting is left alone
