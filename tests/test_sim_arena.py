"""Arena files: the thesis' two arenas (counts and areas of §6.2.1), schema errors, ideal grid, pictures."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from haa.sim.arena import ArenaError, builtin_path, load_arena, parse_arena
from haa.sim.arenas import design
from haa.sim.groundtruth import explorable_area, explorable_grid, ideal_grid, surface_grid
from haa.sim.schedule import ScheduleError, load_schedule

BASE = textwrap.dedent(
    """\
    name: t
    size: [4.0, 3.0]
    obstacles:
      - {id: box, box: {center: [2.0, 1.5], size: [1.0, 0.5]}}
    landmarks:
      - {id: 3, pos: [0.0, 1.0]}
      - {id: 4, pos: [2.0, 1.25]}
    collectables:
      - {id: c1, pos: [3.5, 0.5]}
    collection_regions:
      - {id: r1, box: {center: [0.5, 2.5], size: [0.6, 0.6]}}
    start_poses: [[0.5, 0.5, 0.0], [1.2, 0.5, 0.0]]
    """
)


def test_small_arena_matches_the_thesis() -> None:
    a = load_arena("small")
    assert (a.width, a.height) == (3.4, 7.2)
    assert len(a.obstacles) == 5
    assert a.congregation_id is not None and a.congregation_point is not None
    assert len(a.landmarks) - 1 == 34
    assert explorable_area(a, 0.02) == pytest.approx(24.2, abs=0.1)


def test_the_surface_grid_marks_every_cell_a_solid_touches() -> None:
    """The mission metrics' ideal map (docs/team.md, "Map metrics"): a superset of the half-cell grid that
    also holds the cells of the small arena's 4 cm panels, which the half-cell rule leaves free."""
    a = load_arena("small")
    half, surf = ideal_grid(a, 0.1).grid, surface_grid(a, 0.1).grid
    assert surf.shape == half.shape and np.all(surf >= half)
    # at the missions' 0.1 m the 4 cm panels cover 40 % of their cells: the half-cell grid holds the two boxes
    # only (12 cells), the surface grid the three 1.2 m panels too
    assert half.sum() == 12 and surf.sum() >= half.sum() + 3 * 12
    panels = [o for o in a.obstacles if o.id.startswith("panel")]
    assert panels
    for o in panels:  # a panel's cells: a surface in each, whatever the half-cell rule says
        xs, ys = zip(*o.polygon, strict=True)
        cx, cy = sum(xs) / len(xs), sum(ys) / len(ys)
        assert surf[int(cy / 0.1), int(cx / 0.1)] == 1


def test_large_arena_matches_the_thesis() -> None:
    a = load_arena("large")
    assert (a.width, a.height) == (18.0, 18.0)
    assert len(a.obstacles) == 18
    assert len(a.landmarks) == 139 and a.congregation_id is None
    assert len(a.collectables) == 20
    assert len(a.regions) == 3
    assert explorable_area(a, 0.05) == pytest.approx(216, abs=1.0)
    # every collectable and every region is reachable from the start area
    g = explorable_grid(a, 0.1).grid
    for x, y in a.collectables.values():
        assert g[int(y / 0.1), int(x / 0.1)] == 1
    for poly in a.regions.values():
        cx, cy = np.mean(poly, axis=0)
        assert g[int(cy / 0.1), int(cx / 0.1)] == 1


def test_shipped_yaml_is_what_the_design_generates() -> None:
    for name, text in design.designs().items():
        assert builtin_path(name).read_text() == text, f"run `python -m haa.sim.arenas.design` ({name}.yaml)"


def test_landmarks_face_free_space_and_get_their_face() -> None:
    a = parse_arena(BASE)
    m3 = next(m for m in a.markers if m.id == 3)
    assert m3.normal == pytest.approx((1.0, 0.0))  # west wall, seen from the east
    m4 = next(m for m in a.markers if m.id == 4)
    assert m4.normal == pytest.approx((0.0, -1.0))  # south face of the box
    assert a.landmarks[4] == pytest.approx((2.0, 1.25))


@pytest.mark.parametrize(
    ("edit", "expect"),
    [
        (lambda s: s.replace("size: [4.0, 3.0]", "size: [4.0, -3.0]"), "size: width and height must be positive"),
        (lambda s: s.replace("name: t\n", ""), "name: Field required"),
        (lambda s: s + "colour: red\n", "colour: Extra inputs are not permitted"),
        (
            lambda s: s.replace("{id: 4, pos: [2.0, 1.25]}", "{id: 4, pos: [2.0, 1.0]}"),
            "landmarks[1].pos: not on a wall or obstacle face (nearest is 0.25 m away)",
        ),
        (lambda s: s.replace("{id: 4,", "{id: 3,"), "landmarks[1].id: duplicate id 3"),
        (lambda s: s.replace("{id: 4,", "{id: 999,"), "landmarks[1].id: 999 is not in DICT_4X4_250"),
        (
            lambda s: s.replace(
                "box: {center: [2.0, 1.5], size: [1.0, 0.5]}", "polygon: [[1, 1], [3, 1], [2, 1.2], [2, 2]]"
            ),
            "obstacles[0]: polygon must be convex",
        ),
        (lambda s: s.replace("[3.5, 0.5]", "[2.0, 1.5]"), "collectables[0].pos: inside obstacle 'box'"),
        (lambda s: s.replace("[1.2, 0.5, 0.0]]", "[0.7, 0.5, 0.0]]"), "start_poses[1]: closer than 0.5 m"),
        (lambda s: s.replace("[0.5, 0.5, 0.0],", "[0.1, 0.5, 0.0],"), "start_poses[0]: needs 0.25 m of free space"),
        (lambda s: s + "schedule: [{at: 5, retire: ghost}]\n", "schedule[0].retire: 'ghost' has not joined"),
        (lambda s: s + "schedule: [{at: 5, join: {type: tank}}]\n", "schedule[0].join.type: Input should be"),
        (lambda s: s.replace("obstacles:", "obstacles: 7\nx:"), "obstacles: Input should be a valid list"),
        (lambda s: s + "  - [\n", "not valid YAML"),
    ],
)
def test_bad_arena_files_get_one_clear_line(edit, expect) -> None:
    with pytest.raises(ArenaError) as e:
        parse_arena(edit(BASE), "arena t.yaml")
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("arena t.yaml")
    assert expect.split(":")[0] in msg and expect.split(":")[-1].strip() in msg, msg


def test_polygon_obstacle_must_be_convex() -> None:
    bad = BASE.replace("box: {center: [2.0, 1.5], size: [1.0, 0.5]}", "polygon: [[1, 1], [3, 1], [2, 1.2], [2, 2]]")
    with pytest.raises(ArenaError, match=r"obstacles\[0\]: polygon must be convex"):
        parse_arena(bad.replace("{id: 4, pos: [2.0, 1.25]}", "{id: 4, pos: [2.0, 0.0]}"), "t")


def test_missing_file_and_builtins() -> None:
    with pytest.raises(ArenaError, match=r"no such file .*small, large"):
        load_arena("nowhere.yaml")


def test_ideal_grid_marks_solids_and_nothing_else() -> None:
    a = parse_arena(BASE)
    g, origin, res = ideal_grid(a, 0.05)
    assert origin == (0.0, 0.0) and res == 0.05
    assert g.shape == (60, 80) and g.dtype == np.uint8
    assert g.sum() * res * res == pytest.approx(0.5, abs=0.01)  # the 1.0 x 0.5 box
    assert g[int(1.5 / res), int(2.0 / res)] == 1
    assert g[int(0.5 / res), int(0.5 / res)] == 0
    # resolutions that do not divide the size: the partial last cells are outside the arena, so occupied
    g2, _, _ = ideal_grid(a, 0.07)
    assert g2.shape == (math.ceil(3.0 / 0.07), math.ceil(4.0 / 0.07))
    with pytest.raises(ValueError, match="resolution"):
        ideal_grid(a, 0.0)


def test_enclosed_room_is_not_explorable() -> None:
    room = BASE + textwrap.dedent(
        """\
        walls:
          - {id: w1, start: [3.0, 2.0], end: [4.0, 2.0], thickness: 0.04}
          - {id: w2, start: [3.0, 2.0], end: [3.0, 3.0], thickness: 0.04}
        """
    )
    a = parse_arena(room)
    free_total = 12.0 - 0.5
    enclosed = 1.0 * 1.0
    assert explorable_area(a, 0.02) == pytest.approx(free_total - enclosed - 0.04 * 2, abs=0.05)


def test_schedule_files(tmp_path: Path) -> None:
    f = tmp_path / "mission.yaml"
    f.write_text("mission: x\nschedule:\n  - {at: 1, join: {type: seeker, id: s1}}\n  - {at: 2, crash: s1}\n")
    entries = load_schedule(f, start_poses=3)
    assert [e.kind for e in entries] == ["join", "crash"]
    f.write_text("schedule:\n  - {at: 1, join: {type: seeker, id: s1, start: 5}}\n")
    with pytest.raises(ScheduleError, match=r"schedule\[0\].join.start: no start pose 5"):
        load_schedule(f, start_poses=3)
    f.write_text("schedule:\n  - {at: -1, retire: s1}\n")
    with pytest.raises(ScheduleError, match=r"schedule\[0\].at: Input should be greater than or equal to 0"):
        load_schedule(f, start_poses=3)


def test_haactl_sim_show_writes_pictures(tmp_path: Path) -> None:
    import cv2

    from haactl.main import app

    runner = CliRunner()
    for name in ("small", "large"):
        out = tmp_path / f"{name}.png"
        r = runner.invoke(app, ["sim", "show", name, "-o", str(out)])
        assert r.exit_code == 0, r.output
        img = cv2.imread(str(out))
        assert img is not None and img.shape[0] > 400 and img.shape[1] > 400
        # obstacles are drawn (their blue is in the picture)
        assert np.any(np.all(np.abs(img.astype(int) - (158, 108, 72)) < 8, axis=2))
    bad = tmp_path / "bad.yaml"
    bad.write_text(BASE.replace("name: t\n", ""))
    r = runner.invoke(app, ["sim", "show", str(bad), "-o", str(tmp_path / "x.png")])
    assert r.exit_code == 2
    assert "name: Field required" in r.output
