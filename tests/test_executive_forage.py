"""ExecutiveMission's forage part (haa/agents/executive_mission.py, "Forage"; docs/team.md "Forage: the
mission") and the forage results (haa/mission/forage.py), with stand-ins: one SupervisorForage per identified
collectable at a bounded rate, spawned with the arena's regions under an idempotent key (a recovered executive
never spawns a second one), completion at the explored share *and* every identified collectable deposited or
lost, and the results keys and retirement lines made from a run's DDB state and agent timeline.

The executive runs on the stand-in context of tests/test_supervisor_forage.py (a real DDB replica) with a
stand-in agent table for its spawns: a spawn whose (parent, key) names a live child returns that child, as the
hosts' table does (docs/agents.md "Idempotent spawn"). No cluster, no haa-sim.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from test_supervisor_forage import Bus, Ctx, run

from haa.agents import team
from haa.agents.executive_mission import ExecutiveMission, forage_counts
from haa.mission import forage as mf
from haa.mission import load_mission
from haa.mission import transcript as tr

ROOT = Path(__file__).resolve().parent.parent
ARENA = ROOT / "haa" / "sim" / "arenas" / "small-forage.yaml"
MISSION = ROOT / "missions" / "forage-small.yaml"


class Table:
    """The hosts' agent table as far as spawns go: live children by (parent, key)."""

    def __init__(self) -> None:
        self.live: dict[tuple[str, str], str] = {}
        self.spawned: list[tuple[str, dict[str, Any], str | None, str]] = []  # (type, config, key, id)
        self.n = 0

    def retire(self, child: str) -> None:
        self.live = {k: v for k, v in self.live.items() if v != child}

    def of_type(self, type_name: str) -> list[tuple[str, dict[str, Any], str | None, str]]:
        return [s for s in self.spawned if s[0] == type_name]


class ExecCtx(Ctx):
    def __init__(self, bus: Bus, agent_id: str, config: dict[str, Any], table: Table) -> None:
        super().__init__(bus, agent_id, config)
        self.table = table
        self.counts: dict[str, int] = {}

    async def spawn_child(self, type_name: str, config: bytes, timeout: float, key: str | None = None) -> str:
        if key is None:  # the default key: type, config, the instance's count
            n = self.counts[type_name] = self.counts.get(type_name, 0) + 1
            key = f"{type_name}/{hash(config)}/{n}"
        got = self.table.live.get((self.agent_id, key))
        if got is not None:
            return got
        self.table.n += 1
        child = f"{type_name}-{self.table.n}"
        self.table.live[(self.agent_id, key)] = child
        self.table.spawned.append((type_name, json.loads(config), key, child))
        return child


def mission(**kw: Any) -> dict[str, Any]:
    m = load_mission(MISSION).spec.model_dump(mode="json")
    m["arena"] = str(ARENA)
    m.update(kw)
    return m


def executive(bus: Bus, table: Table, m: dict[str, Any], explored: list[float]) -> ExecutiveMission:
    ex = ExecutiveMission(ExecCtx(bus, "ex", {"mission": m, "expected_cells": 2400}, table))
    bus.agents["ex"] = ex

    async def read_explored() -> None:  # the explored share is tests/test_team_logic.py's; here it is given
        ex.explored = explored[0]

    ex._read_explored = read_explored  # type: ignore[method-assign]
    return ex


def identified(bus: Bus, *ids: int) -> None:
    bus.put(team.K_FORAGE_COLLECTABLES, {str(i): {"x": 0.5 + i, "y": 2.0 + i, "n": 2, "t_first": 1.0, "t_last": 2.0,
                                                  "std": 0.05} for i in ids})


def state(bus: Bus, cid: int, st: str, holder: str) -> None:
    bus.put(f"{team.K_FORAGE_STATE}{cid}", {"state": st, "holder": holder, "avatar": None, "t": bus.t})


async def check(bus: Bus, ex: ExecutiveMission) -> None:
    await ex._check()
    await bus.settle()


def status(bus: Bus) -> dict[str, Any]:
    got = bus.get(team.K_STATUS)
    assert isinstance(got, dict)
    return got


def test_one_supervisor_forage_per_identified_collectable_one_per_check_with_the_arena_regions() -> None:
    async def main() -> None:
        bus, table = Bus(), Table()
        ex = executive(bus, table, mission(), [0.1])
        await ex.on_start()
        await bus.settle()
        assert [s[0] for s in table.spawned] == ["executive_avatar", "supervisor_slam", "supervisor_explore"]
        assert table.spawned[1][1]["collectables"] is True  # SupervisorSLAM reports collectables (forage only)
        await check(bus, ex)
        assert table.of_type("supervisor_forage") == []  # nothing identified yet
        identified(bus, 2, 1, 3)  # one publication with three new ids
        for n in (1, 2, 3, 3):  # one spawn per check, lowest id first, none again
            await check(bus, ex)
            assert [s[1]["collectable"] for s in table.of_type("supervisor_forage")] == [1, 2, 3][:n]
        for _, cfg, key, child in table.of_type("supervisor_forage"):
            assert key == f"forage/{cfg['collectable']}"
            assert {r: [[round(x, 6), round(y, 6)] for x, y in poly] for r, poly in cfg["regions"].items()} == {
                "region-ne": [[1.8, 5.8], [3.4, 5.8], [3.4, 7.2], [1.8, 7.2]]}
            assert cfg["avatar_radius"] == 0.2  # the sweeper's and the carrier's
            assert ex.children[f"supervisor_forage/{cfg['collectable']}"] == child
        assert status(bus)["forage"] == {"identified": 3, "deposited": 0, "lost": 0, "missing": 0, "open": 3}
        texts = [json.loads(x)["text"] for x in _log(bus)]
        assert "collectable 1 identified at (1.50, 3.00): SupervisorForage spawned for it" in texts

    run(main())


def _log(bus: Bus) -> list[bytes]:
    from haa.core.ddb import ops as ddbops

    o = bus.ddb.get(team.K_EVENTS)
    return [] if o is None else list(ddbops.decode_log(o.data)[1])


def test_a_recovered_executive_never_spawns_a_second_supervisor_for_a_collectable() -> None:
    async def main() -> None:
        bus, table = Bus(), Table()
        ex = executive(bus, table, mission(), [0.1])
        await ex.on_start()
        await bus.settle()
        backup = bus.backups["ex"]  # its start-up children, no forager yet
        identified(bus, 1, 2, 3)
        await check(bus, ex)  # forage/1 spawned ...
        await check(bus, ex)  # ... and forage/2; the executive crashes before a backup records either (here: it
        # recovers from the backup before them). Meanwhile forage/1's supervisor took the collectable up,
        # delivered it and retired (its key no longer answers); forage/2's is alive
        first = ex.children["supervisor_forage/1"]
        state(bus, 1, "deposited", first)
        table.retire(first)
        bus.down("ex")
        again = executive(bus, table, mission(), [0.1])
        again.recover(backup)
        await again.on_resume("recover")
        await bus.settle()
        assert "supervisor_forage/2" not in again.children
        for _ in range(3):
            await check(bus, again)
        foragers = table.of_type("supervisor_forage")
        assert [s[1]["collectable"] for s in foragers] == [1, 2, 3]  # none twice
        assert again.children["supervisor_forage/1"] == first  # recorded from forage/state, not spawned
        assert again.children["supervisor_forage/2"] == foragers[1][3]  # the same child, by its key
        assert [s[0] for s in table.spawned[:3]] == ["executive_avatar", "supervisor_slam", "supervisor_explore"]
        assert len(table.spawned) == 6  # and its start-up children were not spawned again either

    run(main())


def test_completion_needs_the_explored_share_and_every_identified_collectable_deposited_or_lost() -> None:
    async def main() -> None:
        bus, table = Bus(), Table()
        explored = [0.5]
        ex = executive(bus, table, mission(), explored)  # complete.explored 0.6
        await ex.on_start()
        identified(bus, 1, 2, 3)
        for _ in range(3):
            await check(bus, ex)
        kids = {c: ex.children[f"supervisor_forage/{c}"] for c in (1, 2, 3)}
        for c in (1, 2, 3):
            state(bus, c, "deposited", kids[c])
        await check(bus, ex)
        assert ex.state == "running"  # every one deposited, not explored enough
        explored[0] = 0.7
        state(bus, 3, "carried", kids[3])
        await check(bus, ex)
        assert ex.state == "running"  # explored, one still carried
        state(bus, 3, "lost", kids[3])
        identified(bus, 1, 2, 3, 4)  # a fourth identified: it needs its supervisor first
        await check(bus, ex)
        assert ex.state == "running" and "supervisor_forage/4" in ex.children
        await check(bus, ex)
        assert ex.state == "running"  # forage/4 is "seen" (no state yet: not taken up)
        state(bus, 4, "deposited", ex.children["supervisor_forage/4"])
        await check(bus, ex)
        assert ex.state == "complete"
        st = status(bus)
        assert st["state"] == "complete" and st["finished_t"] is not None
        assert st["reason"] == "explored 70.0%, 3 of 4 identified collectables deposited, 1 lost"
        assert st["forage"] == {"identified": 4, "deposited": 3, "lost": 1, "missing": 0, "open": 0}
        assert any("Mission finished: explored 70.0%" in json.loads(x)["text"] for x in _log(bus))

    run(main())


def test_the_explore_and_congregate_scenarios_spawn_no_forager_and_report_no_forage_counts() -> None:
    async def main() -> None:
        bus, table = Bus(), Table()
        ex = executive(bus, table, mission(scenario="explore", arena="small"), [0.7])
        await ex.on_start()
        identified(bus, 1)
        await check(bus, ex)
        assert table.of_type("supervisor_forage") == [] and "collectables" not in table.spawned[1][1]
        assert ex.state == "complete" and "forage" not in status(bus)

    run(main())


def test_forage_counts() -> None:
    states = {"1": {"state": "deposited"}, "2": {"state": "lost"}, "3": {"state": "carried"}, "9": {"state": "lost"},
              "5": {"state": "missing"}}
    assert forage_counts(["1", "2", "3", "4", "5"], states) == {"identified": 5, "deposited": 1, "lost": 1,
                                                                "missing": 1, "open": 2}


# ---------------------------------------------------------------------------------------------- results


def test_forage_results_and_the_retirement_lines_from_the_team_state_and_the_agent_timeline() -> None:
    m = load_mission(MISSION)
    clock = tr.ClockMap(4.0)
    clock.add(1000.0, 0.0)
    clock.add(1100.0, 400.0)  # 4 simulated s per wall s
    found = {"1": {"x": 2.4, "y": 1.9}, "2": {"x": 0.6, "y": 3.4}}
    states = {"1": {"state": "deposited", "holder": "id-a"}, "2": {"state": "lost", "holder": "id-b"}}

    def ev(t: float, aid: str, name: str, kind: str, detail: str = "", host: str = "h1") -> dict[str, Any]:
        return {"time": t, "agent": aid, "name": name, "event": kind, "host": host, "detail": detail}

    events = [
        ev(1010, "id-a", "A1.4", "created", "supervisor_forage"), ev(1010.5, "id-a", "A1.4", "created",
                                                                     "supervisor_forage", "h2"),
        ev(1011, "id-a", "A1.4", "active"), ev(1020, "id-a", "A1.4", "recovered", "from backup", "h3"),
        ev(1040, "id-a", "A1.4", "removed"),
        ev(1015, "id-b", "A1.5", "created", "supervisor_forage"), ev(1016, "id-b", "A1.5", "thawed", host="h2"),
        ev(1050, "id-b", "A1.5", "removed"),
        ev(1060, "id-c", "A1.6", "created", "supervisor_explore"),
    ]
    lives = mf.supervisor_lives(events, clock, 8.0, states)
    assert [(v["agent"], v["collectable"], v["spawned_s"], v["retired_s"], v["lifetime_s"], v["recoveries"],
             v["transfers"], v["state"]) for v in lives] == [
        ("A1.4", 1, 32.0, 152.0, 120.0, 1, 0, "deposited"), ("A1.5", 2, 52.0, 192.0, 140.0, 0, 1, "lost")]
    r = mf.forage_results(m, found, states, {"c1": "deposited", "c2": "carried", "c3": "floor"}, lives)
    assert {k: r[k] for k in ("collectables_total", "collectables_identified", "collectables_deposited",
                              "collectables_lost", "collectables_open", "cargo_collected",
                              "collectables_deposited_sim")} == {
        "collectables_total": 3, "collectables_identified": 2, "collectables_deposited": 1, "collectables_lost": 1,
        "collectables_open": 0, "cargo_collected": 1, "collectables_deposited_sim": 1}
    assert r["forage_lifetime_s"] == {"mean": 130.0, "min": 120.0, "max": 140.0, "n": 2}
    assert [ln.format() for ln in mf.forage_lines(lives)] == [
        "02:32 A1.4 (SupervisorForage) retired: collectable 1 deposited, after 02:00",
        "03:12 A1.5 (SupervisorForage) retired: collectable 2 lost, after 02:20"]
    assert json.dumps(r)  # results.json takes it as it is


def test_a_removed_supervisor_forage_is_named_as_it_was_spawned_in_the_transcript() -> None:
    """A host reports a removal after the agent left its table, naming it by its id's first part: the line uses
    the display name its earlier events gave."""
    clock = tr.ClockMap(1.0)
    clock.add(0.0, 0.0)
    aid = "cabd7789-0ce8-4a9e-9c1b-86085fa31e92"
    events = [{"time": 1.0, "agent": aid, "name": "A1.5", "event": "created", "host": "h1",
               "detail": "supervisor_forage"},
              {"time": 9.0, "agent": aid, "name": "cabd7789", "event": "removed", "host": "h1", "detail": ""}]
    assert [ln.text for ln in tr.host_agent_lines(events, clock)] == [
        "A1.5 (SupervisorForage) requested by A1", "A1.5 (SupervisorForage) removed"]
