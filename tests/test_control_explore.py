"""SupervisorExplore's EM split (haa.control.explore) and coordinated frontier exploration
(haa.control.frontier) on the simulator's arenas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haa.control.explore import ExploreConfig, em_split, split_unexplored
from haa.control.frontier import FrontierConfig, assign_frontiers
from haa.control.pathplanner import PlannerConfig, plan_path
from haa.sim.arena import load_arena
from haa.sim.groundtruth import coverage
from haa.slam.grid import GridSpec
from haa.slam.metrics import EXPLORED_HIGH, EXPLORED_LOW


def revealed_map(name: str, res: float, around: list[tuple[float, float]], radius: float):
    """The true map (any solid part → 0.99, else 0.01) within `radius` of the given points, unknown elsewhere."""
    a = load_arena(name)
    spec = GridSpec(a.width, a.height, res)
    truth = np.where(coverage(a, res) > 0, 0.99, 0.01)
    rows, cols = spec.shape
    yy, xx = (np.mgrid[0:rows, 0:cols] + 0.5) * res
    seen = np.zeros(spec.shape, dtype=bool)
    for x, y in around:
        seen |= np.hypot(xx - x, yy - y) <= radius
    return a, np.where(seen, truth, 0.5), truth, spec


def test_em_split_blank_small_arena_partitions_the_reachable_cells():
    a, p, _truth, spec = revealed_map("small", 0.1, [], 0)
    avatars = {f"s{i}": a.start_poses[i][:2] for i in range(3)}
    sp = split_unexplored(p, avatars, spec)
    lab = sp.labels
    assert set(np.unique(lab)) == {-1, 0, 1, 2}
    assert sp.unexplored == int((lab >= 0).sum()) == sum(r.cells for r in sp.regions.values())
    sizes = [r.cells for r in sp.regions.values()]
    assert min(sizes) > 0.6 * max(sizes)  # similar sizes
    for k, name in enumerate(avatars):
        r = sp.regions[name]
        tx, ty = r.target
        cell = (int(ty / 0.1), int(tx / 0.1))
        assert lab[cell] == k  # the target is inside the avatar's own region
    assert not sp.done


def test_em_split_four_corners_large_arena():
    a = load_arena("large")
    spec = GridSpec(a.width, a.height, 0.1)
    p = np.full(spec.shape, 0.5)
    corners = {"ne": (16.5, 16.5), "sw": (1.5, 1.5), "nw": (1.5, 16.5), "se": (16.5, 1.5)}
    corners = {k: v for k, v in corners.items() if a.clearance(*v) > 0.3}
    sp = split_unexplored(p, corners, spec, ExploreConfig(planner=PlannerConfig(radius=0.2)))
    for name, (x, y) in corners.items():
        mx, my = sp.regions[name].mean
        # each avatar's region lies in its own quadrant of the 18 x 18 m arena
        assert (mx - 9) * (x - 9) > 0 and (my - 9) * (y - 9) > 0, (name, sp.regions[name])


def test_targets_are_reachable_unexplored_and_not_occupied():
    starts = [(0.5, 0.5), (1.7, 0.5), (2.9, 0.5)]
    a, p, _truth, spec = revealed_map("small", 0.05, starts, 2.0)
    avatars = {f"s{i}": xy for i, xy in enumerate(starts)}
    cfg = ExploreConfig(planner=PlannerConfig(radius=0.12))
    for target in ("centroid", "nearest"):
        sp = split_unexplored(p, avatars, spec, ExploreConfig(planner=cfg.planner, target=target))
        for name, (x, y) in avatars.items():
            r = sp.regions[name]
            assert r.target is not None
            tx, ty = r.target
            c = p[int(ty / 0.05), int(tx / 0.05)]
            assert EXPLORED_LOW <= c <= EXPLORED_HIGH
            assert a.clearance(tx, ty) > 0  # not in a true obstacle either (it is unknown to the map)
            plan = plan_path(p, (x, y), (tx, ty), spec=spec, config=cfg.planner)
            assert plan.ok and plan.target == pytest.approx((tx, ty)), (name, plan.reason)
    # "nearest" targets are nearer their avatars than the region centres
    near = split_unexplored(p, avatars, spec, ExploreConfig(target="nearest"))
    cent = split_unexplored(p, avatars, spec)
    for name, xy in avatars.items():
        assert math.dist(xy, near.regions[name].target) <= math.dist(xy, cent.regions[name].target) + 1e-9


def test_unreachable_cells_are_nobodys():
    a = load_arena("small")
    spec = GridSpec(a.width, a.height, 0.1)
    p = np.full(spec.shape, 0.01)
    p[50:60, 10:20] = 0.99  # a walled pocket (x 1..2, y 5..6) whose inside is unknown
    p[52:58, 12:18] = 0.5
    p[10:15, 25:30] = 0.5  # an open unknown patch
    sp = split_unexplored(p, {"s1": (0.5, 0.5), "s2": (2.9, 0.5)}, spec)
    assert (sp.labels[52:58, 12:18] == -1).all()
    assert sp.unexplored == int((sp.labels >= 0).sum()) > 0
    for r in sp.regions.values():
        if r.target is not None:
            assert 2.5 <= r.target[0] <= 3.0 and 1.0 <= r.target[1] <= 1.5


def test_everything_explored_means_done():
    _a, p, _truth, spec = revealed_map("small", 0.1, [(1.7, 3.6)], 100)
    sp = split_unexplored(p, {"s1": (0.5, 0.5)}, spec)
    assert sp.done and sp.targets() == {"s1": None}
    fa = assign_frontiers(p, {"s1": (0.5, 0.5)}, spec)
    assert fa.done and fa.targets == {"s1": None}


def test_split_is_deterministic_and_survives_coincident_avatars():
    _a, p, _truth, spec = revealed_map("small", 0.1, [(0.5, 0.5)], 1.0)
    avatars = {"a": (0.5, 0.5), "b": (0.5, 0.5), "c": (0.5, 0.5)}
    s1 = split_unexplored(p, avatars, spec)
    s2 = split_unexplored(p, avatars, spec)
    assert np.array_equal(s1.labels, s2.labels) and s1.targets() == s2.targets()
    assert all(r.cells > 0 for r in s1.regions.values())
    assert len({r.target for r in s1.regions.values()}) == 3


def test_em_split_restarts_an_empty_component():
    X = np.array([[0.0, 0.0], [0.1, 0.0], [5.0, 0.0], [5.1, 0.0]])
    lab, _mu, _ = em_split(X, np.array([[0.0, 0.0], [0.05, 0.0], [100.0, 100.0]]))
    assert set(lab.tolist()) == {0, 1, 2}


def test_frontier_cells_and_costs():
    starts = [(0.5, 0.5), (2.9, 0.5)]
    _a, p, _truth, spec = revealed_map("small", 0.05, starts, 1.2)
    fa = assign_frontiers(p, {"s1": starts[0], "s2": starts[1]}, spec)
    assert fa.count > 0
    fr, fc = np.nonzero(fa.frontier)
    assert (p[fr, fc] < EXPLORED_LOW).all()  # frontier cells are known free
    for name, xy in zip(("s1", "s2"), starts, strict=True):
        tx, ty = fa.targets[name]
        assert fa.frontier[int(ty / 0.05), int(tx / 0.05)]
        assert plan_path(p, xy, (tx, ty), spec=spec).ok
    # each avatar takes a frontier on its own side of the arena (cost term)
    assert fa.targets["s1"][0] < 1.7 < fa.targets["s2"][0]


def test_frontier_coordination_spreads_avatars():
    # a known-free corridor across an unknown map: two frontiers, at its two ends
    spec = GridSpec(10.0, 3.0, 0.1)
    p = np.full(spec.shape, 0.5)
    p[11:20, 10:90] = 0.99  # walls along the corridor
    p[13:18, 10:90] = 0.01
    avatars = {"a": (4.0, 1.5), "b": (4.1, 1.5)}
    coord = assign_frontiers(p, avatars, spec, FrontierConfig(range=3.0))
    alone = assign_frontiers(p, avatars, spec, FrontierConfig(coordinate=False))
    ends = sorted(t[0] for t in coord.targets.values())
    assert ends[0] < 2.0 and ends[1] > 8.0  # one to each end
    assert abs(alone.targets["a"][0] - alone.targets["b"][0]) < 1.0  # uncoordinated: both to the near end


def test_blank_map_frontiers_are_around_the_avatars():
    a = load_arena("small")
    spec = GridSpec(a.width, a.height, 0.1)
    p = np.full(spec.shape, 0.5)
    fa = assign_frontiers(p, {"s1": (0.5, 0.5)}, spec)
    assert fa.count > 0 and math.dist(fa.targets["s1"], (0.5, 0.5)) < 0.3


def test_a_spot_blocked_again_stays_out_of_the_split_longer_each_time() -> None:
    """SupervisorExplore's back-off (haa/agents/supervisor_explore.py docstring): 30, 90, 270 s for the same spot,
    30 s for another, and the memory of spots survives a backup."""
    from test_slam_team import FakeCtx

    from haa.agents.supervisor_explore import SupervisorExplore

    sup = SupervisorExplore(FakeCtx({}))  # type: ignore[arg-type]
    for dx in (0.0, 0.1, -0.1):  # within blocked_radius (0.3 m) of the first: the same spot
        sup._add_block(1.0 + dx, 2.0, 100.0)
    sup._add_block(2.0, 2.0, 100.0)
    assert [round(u - 100.0) for _, _, u in sup.blocked] == [30, 90, 270, 30]
    other = SupervisorExplore(FakeCtx({}))  # type: ignore[arg-type]
    other.unpack_state(sup.pack_state())
    assert other.spots == sup.spots and len(other.spots) == 2
    other._add_block(1.0, 2.0, 0.0)
    assert other.blocked[-1][2] == pytest.approx(30.0 * 27)
