"""AgentPathPlanner's core (haa.control.pathplanner) on the simulator's arenas and on made-up maps."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from haa.control.pathplanner import CostMap, PlannerConfig, plan_path
from haa.sim.arena import load_arena
from haa.sim.groundtruth import coverage
from haa.slam.grid import GridSpec, OccupancyGrid


def true_map(name: str, res: float) -> tuple[object, np.ndarray, GridSpec]:
    a = load_arena(name)
    # any part of a cell inside a solid makes it an obstacle (the 0.04 m panels are thinner than a cell)
    p = np.where(coverage(a, res) > 0, 0.99, 0.01)
    return a, p, GridSpec(a.width, a.height, res)


def sampled_clearance(arena, start, waypoints) -> float:
    pts = [start, *waypoints]
    worst = math.inf
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        n = max(2, int(math.dist((x0, y0), (x1, y1)) / 0.01))
        for k in range(n + 1):
            worst = min(worst, arena.clearance(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n))
    return worst


@pytest.mark.parametrize(("name", "res", "radius", "n"), [("small", 0.05, 0.12, 25), ("large", 0.1, 0.2, 12)])
def test_paths_on_the_arenas_keep_clear_of_obstacles(name, res, radius, n):
    arena, p, spec = true_map(name, res)
    cm = CostMap(p, spec, PlannerConfig(radius=radius))
    rng = np.random.default_rng(3)
    for k in range(n):
        s = arena.start_poses[k % len(arena.start_poses)][:2]
        while True:
            g = (float(rng.uniform(0, arena.width)), float(rng.uniform(0, arena.height)))
            if arena.clearance(*g) > radius + 0.1:
                break
        plan = cm.plan(s, g, heading=1.0)
        assert plan.ok, (s, g, plan.reason)
        assert plan.waypoints[-1] == pytest.approx(g) and plan.target == pytest.approx(g) and plan.heading == 1.0
        assert plan.length >= math.dist(s, g) - 1e-9
        # the avatar's disc never touches a true face (one cell of slack for the discretization)
        assert sampled_clearance(arena, s, plan.waypoints) >= radius - res, (s, g)
        # simplified: far fewer waypoints than cells
        assert len(plan.waypoints) <= max(3, plan.cells // 4)


def test_path_goes_around_an_obstacle_not_through_it():
    _arena, p, spec = true_map("small", 0.05)
    # from below panel-a (x 0.6..1.8 at y 2.2) to straight above it
    plan = plan_path(p, (1.2, 1.6), (1.2, 2.8), spec=spec, config=PlannerConfig(radius=0.12))
    assert plan.ok
    assert plan.length > 1.2 + 0.5  # the straight line (1.2 m) is blocked: a detour round an end
    xs = [w[0] for w in plan.waypoints]
    assert min(xs) < 0.6 - 0.12 or max(xs) > 1.8 + 0.12


def test_penalty_prefers_the_wide_gap():
    # a wall across the map with a narrow gap (straight ahead) and a wide gap (a little to the side)
    spec = GridSpec(4.0, 4.0, 0.05)
    p = np.full(spec.shape, 0.01)
    p[39:41, :] = 0.99  # wall at y = 1.95..2.05
    p[39:41, 38:43] = 0.01  # narrow gap x = 1.9..2.15 (0.25 m; avatar diameter 0.24)
    p[39:41, 52:70] = 0.01  # wide gap x = 2.6..3.5
    cfg = PlannerConfig(radius=0.1)
    plan = plan_path(p, (2.0, 1.0), (2.0, 3.0), spec=spec, config=cfg)
    assert plan.ok
    crossing = [w for w in [(2.0, 1.0), *plan.waypoints] if 1.8 < w[1] < 2.2]
    segs = list(zip([(2.0, 1.0), *plan.waypoints[:-1]], plan.waypoints, strict=True))
    x_at_wall = [
        a[0] + (b[0] - a[0]) * (2.0 - a[1]) / (b[1] - a[1]) for a, b in segs if (a[1] - 2.0) * (b[1] - 2.0) <= 0
    ]
    assert x_at_wall and 2.6 <= x_at_wall[0] <= 3.5, (plan.waypoints, crossing)
    # without the penalty the short way through the narrow gap wins
    flat = plan_path(p, (2.0, 1.0), (2.0, 3.0), spec=spec, config=PlannerConfig(radius=0.1, clearance_weight=0))
    assert flat.ok and flat.length < plan.length


def test_a_gap_narrower_than_the_avatar_is_closed():
    spec = GridSpec(4.0, 4.0, 0.05)
    p = np.full(spec.shape, 0.01)
    p[39:41, :] = 0.99
    p[39:41, 38:42] = 0.01  # 0.2 m gap
    # clearance is measured from the obstacle cells' edges: the middle cells' centres are 0.075 m from them
    assert plan_path(p, (2.0, 1.0), (2.0, 3.0), spec=spec, config=PlannerConfig(radius=0.07)).ok
    assert not plan_path(p, (2.0, 1.0), (2.0, 3.0), spec=spec, config=PlannerConfig(radius=0.08)).ok
    plan = plan_path(p, (2.0, 1.0), (2.0, 3.0), spec=spec, config=PlannerConfig(radius=0.15))
    assert not plan.ok and plan.reason == "unreachable" and plan.waypoints == []


def test_unreachable_and_blocked_targets_are_results():
    _arena, p, spec = true_map("small", 0.05)
    cm = CostMap(p, spec, PlannerConfig(radius=0.12, snap=0.0))
    assert cm.plan((0.5, 0.5), (2.6, 2.9)).reason == "target blocked"  # inside box-a
    assert cm.plan((0.5, 0.5), (9.0, 1.0)).reason == "target outside the map"
    assert cm.plan((-1.0, 0.5), (1.0, 1.0)).reason == "start outside the map"
    assert cm.plan((2.6, 2.9), (1.0, 1.0)).reason == "start on an obstacle"
    # a walled-in pocket
    q = p.copy()
    q[60:80, 20:40] = 0.99
    q[63:77, 23:37] = 0.01
    plan = CostMap(q, spec, PlannerConfig(radius=0.05)).plan((0.5, 0.5), (1.5, 3.5))
    assert (plan.ok, plan.reason) == (False, "unreachable")


def test_blocked_target_snaps_to_the_nearest_passable_cell():
    arena, p, spec = true_map("small", 0.05)
    plan = plan_path(p, (0.5, 0.5), (2.6, 2.9), spec=spec, config=PlannerConfig(radius=0.12, snap=0.4))
    assert plan.ok and plan.target is not None
    assert 0.1 < math.dist(plan.target, (2.6, 2.9)) <= 0.4
    assert arena.clearance(*plan.target) >= 0.12 - 0.05


def test_unknown_cells_rule():
    spec = GridSpec(3.0, 3.0, 0.1)
    unknown = np.full(spec.shape, 0.5)
    plan = plan_path(unknown, (0.5, 0.5), (2.5, 2.5), spec=spec)
    assert plan.ok and len(plan.waypoints) == 1  # optimistic: a straight line through the unknown
    blocked = plan_path(unknown, (0.5, 0.5), (2.5, 2.5), spec=spec, config=PlannerConfig(unknown="blocked"))
    assert not blocked.ok
    # known free corridor along the edges vs unknown straight across: a moderate detour is taken
    p = np.full(spec.shape, 0.5)
    p[2:8, 2:28] = 0.01
    p[2:28, 22:28] = 0.01
    plan = plan_path(p, (0.5, 0.5), (2.5, 2.5), spec=spec, config=PlannerConfig(unknown_factor=3.0))
    assert plan.ok and plan.length > math.dist((0.5, 0.5), (2.5, 2.5)) + 0.5
    # all-known-free route only, with unknown blocked
    only = plan_path(p, (0.5, 0.5), (2.5, 2.5), spec=spec, config=PlannerConfig(unknown="blocked"))
    assert only.ok


def test_start_inside_the_inflation_can_leave():
    _arena, p, spec = true_map("small", 0.05)
    plan = plan_path(p, (0.06, 3.0), (1.0, 3.0), spec=spec, config=PlannerConfig(radius=0.12))
    assert plan.ok and plan.waypoints[-1] == pytest.approx((1.0, 3.0))


def test_other_avatars_are_avoided():
    spec = GridSpec(3.0, 1.0, 0.05)
    p = np.full(spec.shape, 0.01)
    free = plan_path(p, (0.3, 0.5), (2.7, 0.5), spec=spec, config=PlannerConfig(radius=0.1))
    assert free.ok and len(free.waypoints) == 1
    # an avatar in the middle of the 1 m corridor: go round it
    plan = plan_path(p, (0.3, 0.5), (2.7, 0.5), spec=spec, config=PlannerConfig(radius=0.1), avoid=[(1.5, 0.5, 0.12)])
    assert plan.ok and len(plan.waypoints) > 1
    pts = [(0.3, 0.5), *plan.waypoints]
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        for k in range(51):
            x, y = x0 + (x1 - x0) * k / 50, y0 + (y1 - y0) * k / 50
            assert math.hypot(x - 1.5, y - 0.5) >= 0.12 + 0.1 - 0.05
    # two avatars closing the corridor
    plan = plan_path(p, (0.3, 0.5), (2.7, 0.5), spec=spec, avoid=[(1.5, 0.25, 0.2), (1.5, 0.75, 0.2)])
    assert not plan.ok and plan.reason == "unreachable"


def test_occupancy_grid_input():
    spec = GridSpec(2.0, 2.0, 0.1, x0=-1.0, y0=-1.0)
    g = OccupancyGrid(spec)
    prob = np.full(spec.shape, 0.1)
    prob[8:12, 5:15] = 0.95
    g.set_prob(prob)
    plan = plan_path(g, (0.0, -0.7), (0.0, 0.7), config=PlannerConfig(radius=0.05))
    assert plan.ok and plan.length > 1.4 + 0.3
    with pytest.raises(ValueError, match="does not match"):
        plan_path(np.zeros((3, 3)), (0, 0), (1, 1), spec=spec)


def test_large_arena_timing():
    arena, p, spec = true_map("large", 0.1)
    cm = CostMap(p, spec, PlannerConfig(radius=0.2))
    plan = cm.plan(arena.start_poses[0][:2], (arena.width - 0.6, arena.height - 0.6))
    assert plan.ok and plan.length > 20
    assert plan.seconds < 2.0  # ~0.05 s measured (docs/control.md); loose for a loaded CI machine


def test_cost_field_is_the_plans_cost_to_every_cell():
    """One search to every cell gives what a plan to each cell costs (SupervisorCongregate weighs slots by it)."""
    _a, p, spec = true_map("small", 0.1)
    cm = CostMap(p, spec, PlannerConfig(radius=0.12))
    start = (0.5, 0.5)
    field = cm.cost_field(start)
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(200):
        x, y = rng.uniform(0.2, 3.2), rng.uniform(0.2, 6.8)
        cell = cm.cell(x, y)
        if not cm.passable[cell]:  # a plan snaps such a target to a passable cell: not the same question
            continue
        plan = cm.plan(start, cm.centre(*cell))
        assert plan.ok == math.isfinite(field[cell])
        if plan.ok:
            assert field[cell] == pytest.approx(plan.cost * spec.resolution, rel=1e-9)
            assert field[cell] >= math.dist(start, cm.centre(*cell)) - 0.15  # never shorter than a line
            checked += 1
    assert checked > 100
    assert np.isinf(cm.cost_field((-1.0, 0.5))).all()  # start outside the map
