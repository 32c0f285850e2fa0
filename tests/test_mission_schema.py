"""Mission files (haa.mission.schema): the shipped missions load, and bad files get one clear error line."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from haa.mission import MissionError, load_mission, parse_mission
from haa.mission.schema import MissionSpec
from haa.sim.arena import load_arena
from haa.sim.schedule import check_schedule

ROOT = Path(__file__).resolve().parent.parent
MISSIONS = ROOT / "missions"

ISSUE_EXAMPLE = """
name: af1
scenario: explore              # explore | congregate | forage
arena: small                   # small | large | a path to an arena YAML in the schema of haa/sim/arenas/
seed: 1
slam: jc-slam                  # jc-slam | discard | delay   (Table 7.2-4)
particles: 100
complete: {explored: 0.95, time_limit_s: 900}   # explored share of reachable cells (>0.73 or <0.27)
hosts:
  start: 4                     # h1..h4 when the mission brings its own cluster
  schedule:                    # times from mission start, in simulated seconds
    - {at_s: 60, leave: h4}    # leave | join | kill | restart
    - {at_s: 120, join: h5}
avatars:
  - {name: s1, type: seeker, pose: [0.5, 0.5, 0.0]}            # seeker | enhanced_seeker | sweeper | carrier
  - {name: s3, type: seeker, pose: [2.9, 0.5, 1.57], leave_at_s: 120}
  - {name: s4, type: seeker, pose: [2.5, 6.7, -1.57], join_at_s: 150}
"""


def base() -> dict:
    return yaml.safe_load(ISSUE_EXAMPLE)


def write(tmp_path: Path, data: object, name: str = "m.yaml") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return p


def test_issue_example_works_as_written(tmp_path):
    m = load_mission(write(tmp_path, ISSUE_EXAMPLE))
    s = m.spec
    assert (s.name, s.scenario, s.seed, s.slam, s.particles) == ("af1", "explore", 1, "jc-slam", 100)
    assert s.drift == "thesis"
    assert (s.complete.explored, s.complete.time_limit_s) == (0.95, 900)
    assert s.hosts.initial == ["h1", "h2", "h3", "h4"]
    assert [(e.at_s, e.action, e.host) for e in s.hosts.events()] == [(60, "leave", "h4"), (120, "join", "h5")]
    assert [a.name for a in s.avatars] == ["s1", "s3", "s4"]
    assert s.avatars[1].leave_at_s == 120 and s.avatars[2].join_at_s == 150
    assert s.exploration == "em" and s.speed == 1.0  # extras default
    assert m.arena.name == "small"
    assert [a.name for a in m.avatars_at_start()] == ["s1", "s3"]
    assert m.host_timeline() == [
        (0.0, frozenset({"h1", "h2", "h3", "h4"})),
        (60, frozenset({"h1", "h2", "h3"})),
        (120, frozenset({"h1", "h2", "h3", "h5"})),
    ]


@pytest.mark.parametrize("name", ["af1", "af2", "quick", "forage-small"])
def test_shipped_missions_load(name):
    m = load_mission(MISSIONS / f"{name}.yaml")
    assert m.spec.name == name
    assert m.arena.name == ("small-forage" if name == "forage-small" else "small")
    # the avatar schedule is one the simulator accepts
    assert check_schedule(m.sim_schedule(), len(m.arena.start_poses)) is None


def test_af1_is_the_thesis_setup():
    s = load_mission(MISSIONS / "af1.yaml").spec
    assert s.scenario == "explore" and s.complete.explored == 0.95 and s.hosts.start == 4
    start = [a for a in s.avatars if a.join_at_s is None]
    assert len(start) == 3 and all(a.type == "seeker" for a in s.avatars)
    assert [a.leave_at_s for a in s.avatars if a.leave_at_s] == [120]  # one seeker retires after 2 min
    assert [a.join_at_s for a in s.avatars if a.join_at_s] == [150, 150]  # two join after 2.5 min
    acts = [(e.at_s, e.action) for e in s.hosts.events()]
    assert acts[:3] == [(60, "leave"), (120, "join"), (180, "leave")]  # odd minute leave, even minute join


def test_af2_is_the_thesis_setup():
    m = load_mission(MISSIONS / "af2.yaml")
    assert m.spec.scenario == "congregate" and len(m.spec.avatars) == 3 and m.spec.hosts.start == 4
    assert m.arena.congregation_point is not None


def test_sim_schedule_joins_and_retires():
    m = load_mission(MISSIONS / "af1.yaml")
    entries = [(e.at, e.join.id if e.join else None, e.retire) for e in m.sim_schedule()]
    assert entries[:3] == [(0.0, "s1", None), (0.0, "s2", None), (0.0, "s3", None)]
    assert (120, None, "s1") in entries and (150, "s4", None) in entries


def test_arena_path_relative_to_the_mission_file(tmp_path):
    sub = tmp_path / "arenas"
    sub.mkdir()
    (sub / "mine.yaml").write_text(load_arena("small").to_yaml())
    d = base()
    d["arena"] = "arenas/mine.yaml"
    m = load_mission(write(tmp_path, d))
    assert m.arena.width == 3.4


def test_extras(tmp_path):
    (tmp_path / "plan.yaml").write_text("name: p\nfaults: [{life_s: [30, 90], action: hang, target: agents, "
                                        "hang_s: 30}]\n")
    d = base()
    d.update(
        exploration="frontier",
        speed=4,
        chaos="plan.yaml",
        map_resolution=0.05,
        congregation={"radius_m": 0.8, "tolerance_m": 0.1},
        description="x",
    )
    s = load_mission(write(tmp_path, d)).spec
    assert (s.exploration, s.speed, s.chaos, s.map_resolution) == ("frontier", 4, "plan.yaml", 0.05)
    assert s.congregation.radius_m == 0.8


@pytest.mark.parametrize("plan, expect", [
    ("kills: []\n", "chaos: chaos plan"),
    ("name: p\nworkload: counters\n", "workload: counters is for `haactl chaos run`"),
    ("name: p\nfaults: [{at_s: 5, action: kill, target: host h4}]\n", "h4 is not a host of this mission"),
    ("name: p\nfaults: [{at_s: 5, action: partition, target: [h1, h2], for_s: 3}]\n", "partition is not available"),
])
def test_a_mission_refuses_a_chaos_plan_it_cannot_run(tmp_path, plan, expect):
    (tmp_path / "plan.yaml").write_text(plan)
    d = base()
    d["chaos"] = "plan.yaml"
    d["hosts"] = {"start": 3}
    with pytest.raises(MissionError) as e:
        load_mission(write(tmp_path, d))
    text = str(e.value)
    assert "\n" not in text and ": chaos: " in text and expect in text, text


@pytest.mark.parametrize("args, expect", [
    (["--agent-hang-timeout", "1"], None),
    (["--no-such-option", "1"], "hostd_args[0]: '--no-such-option' is not an haa-hostd option"),
    (["--agent-hang-timeout", "1", "--core=h1=x:1"], "hostd_args[2]: --core is set by the mission runner itself"),
])
def test_hostd_args_are_checked_against_haa_hostd(tmp_path, args, expect):
    d = base()
    d["hostd_args"] = args
    if expect is None:
        assert load_mission(write(tmp_path, d)).spec.hostd_args == args
        return
    with pytest.raises(MissionError) as e:
        load_mission(write(tmp_path, d))
    assert expect in str(e.value), str(e.value)


def test_schema_lists_the_issue_keys():
    keys = set(MissionSpec.model_fields)
    assert {"name", "scenario", "arena", "seed", "slam", "particles", "complete", "hosts", "avatars"} <= keys


def _set(path: str, value):
    """A mutation of the base document: dotted path with [i] indices; value DELETE removes the key."""

    def f(d):
        parts = path.replace("[", ".[").split(".")
        cur = d
        for p in parts[:-1]:
            cur = cur[int(p[1:-1])] if p.startswith("[") else cur[p]
        last = parts[-1]
        if last.startswith("["):
            cur[int(last[1:-1])] = value
        elif value is DELETE:
            del cur[last]
        else:
            cur[last] = value
        return d

    return f


DELETE = object()

BAD = [
    # (mutation, field path in the error, words of the reason)
    (_set("scenario", "gather"), "scenario", "'explore', 'congregate' or 'forage'"),
    (_set("scenario", "forage"), "scenario",
     "forage needs an arena with collectables and collection regions; arena 'small' has no collectables and no "
     "collection regions"),
    (_set("scenario", DELETE), "scenario", "required field is missing"),
    (_set("name", DELETE), "name", "required"),
    (_set("name", ""), "name", "at least 1"),
    (_set("name", "a b"), "name", "letters, digits"),
    (_set("slam", "fastslam"), "slam", "'jc-slam', 'discard' or 'delay'"),
    (_set("drift", "harsh"), "drift", "'thesis', 'table' or 'systematic'"),
    (_set("particles", 0), "particles", "greater than or equal to 1"),
    (_set("particles", 10**6), "particles", "less than or equal to 10000"),
    (_set("particles", "many"), "particles", "valid integer"),
    (_set("seed", -1), "seed", "greater than or equal to 0"),
    (_set("complete.explored", 0), "complete.explored", "(0, 1]"),
    (_set("complete.explored", 1.2), "complete.explored", "(0, 1]"),
    (_set("complete.explored", float("nan")), "complete.explored", "(0, 1]"),
    (_set("complete.time_limit_s", -5), "complete.time_limit_s", "greater than 0"),
    (_set("complete.colour", "red"), "complete.colour", "unknown field (allowed: explored, time_limit_s)"),
    (_set("robots", []), "robots", "unknown field (allowed: name,"),
    (_set("hosts.start", 0), "hosts.start", "greater than or equal to 1"),
    (_set("hosts.schedule[0]", {"at_s": 60}), "hosts.schedule[0]", "exactly one of leave, join, kill, restart"),
    (_set("hosts.schedule[0]", {"at_s": 60, "leave": "h4", "join": "h5"}), "hosts.schedule[0]", "exactly one"),
    (_set("hosts.schedule[0]", {"at_s": 60, "leave": "host4"}), "hosts.schedule[0]", "host names are h1, h2"),
    (_set("hosts.schedule[0]", {"at_s": -1, "leave": "h4"}), "hosts.schedule[0].at_s", "greater than or equal to 0"),
    (_set("hosts.schedule[0]", {"at_s": 60, "leave": "h9"}), "hosts.schedule[0].leave", "h9 is not in the host group"),
    (_set("hosts.schedule[1]", {"at_s": 120, "join": "h2"}), "hosts.schedule[1].join", "h2 is already in the host"),
    (_set("hosts.schedule[1]", {"at_s": 120, "restart": "h4"}), "hosts.schedule[1].restart", "was not killed"),
    (_set("hosts.schedule[1]", {"at_s": 30, "kill": "h4"}), "hosts.schedule[0].leave", "h4 is not in the host group"),
    (_set("hosts.schedule[1]", {"at_s": 950, "join": "h5"}), "hosts.schedule[1].at_s", "time_limit_s"),
    (_set("avatars", []), "avatars", "at least 1 item"),
    (_set("avatars[0].type", "robot"), "avatars[0].type", "'seeker', 'enhanced_seeker', 'sweeper' or 'carrier'"),
    (_set("avatars[1].name", "s1"), "avatars[1].name", "'s1' is already the name of avatars[0]"),
    (_set("avatars[0].pose", [0.5, 0.5]), "avatars[0].pose", "too few items (item 2 is missing)"),
    (_set("avatars[0].pose", [0.5, 0.5, 0, 1]), "avatars[0].pose", "at most 3 items"),
    (_set("avatars[0].pose", [0.5, float("inf"), 0]), "avatars[0].pose[1]", "finite"),
    (_set("avatars[0].pose", [5.0, 0.5, 0]), "avatars[0].pose", "outside the 3.4 x 7.2 m arena"),
    (_set("avatars[0].pose", [2.6, 2.9, 0]), "avatars[0].pose", "inside an obstacle or wall"),  # box-a
    (_set("avatars[0].pose", [1.2, 2.28, 0]), "avatars[0].pose", "a seeker needs 0.12 m"),  # by panel-a
    (_set("avatars[0].pose", [0.05, 3.0, 0]), "avatars[0].pose", "from an obstacle or wall"),  # by the wall
    (_set("avatars[1].pose", [0.6, 0.5, 0]), "avatars[1].pose", "overlaps avatars[0] (s1)"),
    (_set("avatars[1].leave_at_s", 0), "avatars[1]", "leave_at_s (0.0) must come after"),
    (_set("avatars[2].leave_at_s", 100), "avatars[2]", "must come after join_at_s (150.0)"),
    (_set("avatars[2].join_at_s", 1000), "avatars[2].join_at_s", "not before complete.time_limit_s"),
    (_set("avatars[0].colour", "red"), "avatars[0].colour", "unknown field (allowed: name, type, pose"),
    (_set("arena", "medium"), "arena", "no such file (built-in arenas: small, large)"),
    (_set("exploration", "random"), "exploration", "'em' or 'frontier'"),
    (_set("speed", 0), "speed", "greater than 0"),
    (_set("chaos", "nowhere.yaml"), "chaos", "no such file"),
    (_set("map_resolution", 5), "map_resolution", "less than or equal to 1"),
]


@pytest.mark.parametrize(("mutate", "field", "words"), BAD, ids=[f"{b[1]}-{i}" for i, b in enumerate(BAD)])
def test_bad_mission_one_clear_line(tmp_path, mutate, field, words):
    p = write(tmp_path, mutate(copy.deepcopy(base())))
    with pytest.raises(MissionError) as ei:
        load_mission(p)
    e = ei.value
    line = str(e)
    assert "\n" not in line
    assert e.field == field, line
    assert words in e.reason, line
    assert line == f"{p}: {field}: {e.reason}"


def test_every_avatar_joins_late(tmp_path):
    d = base()
    d["avatars"] = [d["avatars"][2]]
    with pytest.raises(MissionError, match=r"avatars: no avatar is there at the start"):
        load_mission(write(tmp_path, d))


def test_last_host_cannot_leave(tmp_path):
    d = base()
    d["hosts"] = {"start": 1, "schedule": [{"at_s": 10, "kill": "h1"}]}
    with pytest.raises(MissionError, match=r"hosts.schedule\[0\].kill: h1 is the last host"):
        load_mission(write(tmp_path, d))


def test_kill_then_restart_then_join_rules(tmp_path):
    d = base()
    d["hosts"]["schedule"] = [
        {"at_s": 10, "kill": "h2"},
        {"at_s": 20, "restart": "h2"},
        {"at_s": 30, "leave": "h2"},
        {"at_s": 40, "join": "h2"},  # a host that left may join again
    ]
    m = load_mission(write(tmp_path, d))
    assert m.host_timeline()[-1][1] == frozenset({"h1", "h2", "h3", "h4"})
    d["hosts"]["schedule"] = [{"at_s": 10, "kill": "h2"}, {"at_s": 20, "join": "h2"}]
    with pytest.raises(MissionError, match=r"schedule\[1\].join: h2 was killed; use restart: h2"):
        load_mission(write(tmp_path, d))


def test_schedule_is_replayed_in_time_order(tmp_path):
    d = base()
    d["hosts"]["schedule"] = [{"at_s": 120, "leave": "h5"}, {"at_s": 60, "join": "h5"}]
    m = load_mission(write(tmp_path, d))
    assert [e.host for e in m.spec.hosts.events()] == ["h5", "h5"]


def test_congregate_needs_a_congregation_point(tmp_path):
    arena = load_arena("small").spec.model_copy(update={"congregation": None})
    from haa.sim.arena import dump_spec

    (tmp_path / "plain.yaml").write_text(dump_spec(arena))
    d = base()
    d.update(scenario="congregate", arena="plain.yaml")
    with pytest.raises(MissionError, match=r"scenario: congregate needs an arena with a congregation point"):
        load_mission(write(tmp_path, d))


FORAGE = """
name: f
scenario: forage
arena: ARENA
complete: {explored: 0.7, time_limit_s: 300}
hosts: {start: 3}
avatars:
  - {name: s1, type: seeker, pose: [0.5, 0.5, 1.5708]}
  - {name: w1, type: sweeper, pose: [1.7, 0.5, 1.5708]}
  - {name: k1, type: carrier, pose: [2.9, 0.5, 1.5708]}
"""
FORAGE_ARENA = ROOT / "haa" / "sim" / "arenas" / "small-forage.yaml"


def forage_base() -> dict:
    return yaml.safe_load(FORAGE.replace("ARENA", str(FORAGE_ARENA)))


def test_a_forage_mission_names_an_arena_with_collectables_and_a_mixed_team(tmp_path):
    m = load_mission(write(tmp_path, forage_base()))
    assert m.spec.scenario == "forage"
    assert len(m.arena.collectables) == 3 and list(m.arena.regions) == ["region-ne"]
    assert {a.type for a in m.spec.avatars} == {"seeker", "sweeper", "carrier"}


def _no_regions(tmp_path: Path) -> str:
    from haa.sim.arena import dump_spec

    spec = load_arena(FORAGE_ARENA).spec.model_copy(update={"collection_regions": []})
    (tmp_path / "noregions.yaml").write_text(dump_spec(spec))
    return "noregions.yaml"


@pytest.mark.parametrize(("mutate", "field", "words"), [
    (lambda d, tmp: {**d, "avatars": [{"name": "s1", "type": "seeker", "pose": [0.5, 0.5, 0]},
                                      {"name": "e1", "type": "enhanced_seeker", "pose": [1.7, 0.5, 0]}]},
     "avatars", "forage needs an avatar that can carry a collectable (sweeper or carrier); the team has only "
     "enhanced_seeker, seeker"),
    (lambda d, tmp: {**d, "arena": "small"}, "scenario", "arena 'small' has no collectables and no collection"),
    (lambda d, tmp: {**d, "arena": _no_regions(tmp)}, "scenario", "has no collection regions"),
    (lambda d, tmp: {**d, "forage": {"spawns": 2}}, "forage", "unknown field"),
], ids=["no-carrier", "no-collectables", "no-regions", "unknown-key"])
def test_a_broken_forage_file_gets_one_line(tmp_path, mutate, field, words):
    p = write(tmp_path, mutate(forage_base(), tmp_path))
    with pytest.raises(MissionError) as ei:
        load_mission(p)
    e = ei.value
    assert "\n" not in str(e)
    assert e.field == field, str(e)
    assert words in e.reason, str(e)


def test_large_arena_pose_check(tmp_path):
    d = base()
    d["arena"] = "large"
    d["avatars"] = [{"name": "w1", "type": "sweeper", "pose": list(load_arena("large").start_poses[0])}]
    assert load_mission(write(tmp_path, d)).arena.name == "large"


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("", "expected a mapping at the top level"),
        ("- 1\n- 2\n", "expected a mapping"),
        ("name: a\nname: b\n", "duplicate key 'name' at line 2"),
        ("name: [\n", "not valid YAML"),
        ("a: " + "[" * 100 + "]" * 100 + "\n", "nested deeper than 64 levels"),
        (
            "x: &a [1,1,1,1,1,1,1,1,1,1]\n"
            + "".join(
                f"{c}: &{c} [" + ",".join([f"*{p}"] * 10) + "]\n" for p, c in zip("abcdef", "bcdefg", strict=True)
            ),
            "more than 100000 nodes",
        ),
    ],
)
def test_file_level_errors(tmp_path, text, words):
    p = write(tmp_path, text)
    with pytest.raises(MissionError) as ei:
        load_mission(p)
    assert words in str(ei.value) and "\n" not in str(ei.value)
    assert str(ei.value).startswith(f"{p}: ")


def test_missing_and_huge_files(tmp_path):
    with pytest.raises(MissionError, match="no such file"):
        load_mission(tmp_path / "nope.yaml")
    big = tmp_path / "big.yaml"
    big.write_text("description: '" + "x" * (2 << 20) + "'\n")
    with pytest.raises(MissionError, match=r"larger than 1 MiB \(mission file limit\)"):
        load_mission(big)


def test_parse_mission_from_data():
    m = parse_mission(base(), "inline")
    assert m.path is None and m.spec.name == "af1"
    with pytest.raises(MissionError, match=r"^inline: avatars\[0\]\.type: "):
        bad = base()
        bad["avatars"][0]["type"] = "tank"
        parse_mission(bad, "inline")


def test_the_lab_offers_the_mission_extensions_and_a_team_without_it_refuses_a_chaos_plan(tmp_path, monkeypatch):
    """A mission reaches the lab's chaos plans and stats bundles through entry points (haa.mission.extensions):
    installed, they name the lab's modules; without them a mission with `chaos:` is refused with one line."""
    import importlib.metadata

    from haa.mission import extensions

    assert extensions.extension("chaos").__name__ == "haa.lab.chaos.inmission"
    assert extensions.extension("bundles").__module__ == "haa.lab.stats.inmission"
    (tmp_path / "plan.yaml").write_text("name: p\nfaults: [{at_s: 5, action: kill, target: host h2}]\n")
    d = base()
    d["chaos"] = "plan.yaml"
    d["hosts"] = {"start": 3}
    assert load_mission(write(tmp_path, d)).spec.chaos == "plan.yaml"
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **_kw: ())
    with pytest.raises(extensions.ExtensionMissing, match="mission extension 'bundles'"):
        extensions.extension("bundles")
    with pytest.raises(MissionError) as e:
        load_mission(write(tmp_path, d))
    text = str(e.value)
    assert "\n" not in text and "chaos: no installed package offers the mission extension 'chaos'" in text, text
