"""A forage mission's results (thesis Table 6.2-1 scenario 3, L1194; AF-3 Table 7.1-3 "Cargo Collected"): what
the team identified and deposited, what haa-sim says it holds, and each SupervisorForage's life.

The runner reads, at the end of a `scenario: forage` mission (haa.mission.runner.MissionRun.collect):

* the team's view: `forage/collectables` (SupervisorSLAM's identified collectables) and `forage/state/<id>`
  (each one's forage state, written by its SupervisorForage) — docs/team.md "Forage";
* haa-sim's view (ground truth, asked by the runner, which the agents never are: `sim_truth_calls` leaves the
  runner's own calls out): every collectable's state (floor | carried | deposited), the check that the team's
  "deposited" — its estimate of the drop point — is real;
* the hosts' agent timeline (transcript.host_agent_events): when each SupervisorForage was requested and removed
  (it retires itself once its collectable is deposited or lost), and how often it was recovered.

`forage_results` makes the results keys of docs/missions.md ("Forage results"); `forage_lines` the transcript's
retirement lines ("A1.6 (SupervisorForage) retired: collectable 2 deposited, after 02:13"), next to the
hosts' "requested by" / "spawned by" lines of each spawn (Fig. 7.1-3 wording).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from typing import Any

import grpc

from haa.mission import transcript as tr
from haa.mission.schema import Mission

K_COLLECTABLES = "forage/collectables"
K_STATE = "forage/state/"
FORAGE_TYPE = "supervisor_forage"


def read_team(backend: Any, prefer: str = "") -> tuple[dict[str, Any], dict[str, Any]]:
    """(`forage/collectables`, {id: `forage/state/<id>`}) from one host's replica; empty when none answers."""
    from haa.cluster import queries

    got = queries.ddb_read(backend, keys=[K_COLLECTABLES], prefer=prefer, timeout=10.0)
    found = got[1].get(K_COLLECTABLES) if got is not None else None
    got = queries.ddb_read(backend, prefix=K_STATE, prefer=prefer, timeout=10.0)
    states = {k[len(K_STATE):]: v for k, v in got[1].items()} if got is not None else {}
    return (found if isinstance(found, dict) else {}), states


def read_sim(sim: Any) -> dict[str, str] | None:
    """haa-sim's collectables {id: state} (floor | carried | deposited); None if it does not answer."""
    if sim is None:
        return None
    with contextlib.suppress(grpc.RpcError), sim.client() as c:
        return {x.id: x.state for x in c.collectables().collectables}
    return None


def supervisor_lives(agent_events: Iterable[dict[str, Any]], clock: tr.ClockMap, t0: float,
                     states: dict[str, Any]) -> list[dict[str, Any]]:
    """Each SupervisorForage of the hosts' agent timeline: its collectable (the state whose holder it is), display
    name, mission times of its request ("created") and removal (its retirement; None while it lived at the end),
    lifetime, recoveries and the collectable's final state; in order of request."""
    holder = {str(v.get("holder")): cid for cid, v in states.items() if isinstance(v, dict) and v.get("holder")}
    lives: dict[str, dict[str, Any]] = {}

    def at(wall: float) -> float:
        return round(clock.to_sim(wall) - t0, 3) if clock else 0.0

    for e in tr.dedup_agent_events(list(agent_events)):
        aid, kind = e["agent"], e["event"]
        if kind == "created" and e["detail"] == FORAGE_TYPE and aid not in lives:
            cid = holder.get(aid)
            st = states.get(cid) if cid is not None else None
            lives[aid] = {"collectable": int(cid) if cid is not None and cid.isdigit() else cid, "agent": e["name"],
                          "id": aid, "spawned_s": at(e["time"]), "retired_s": None, "lifetime_s": None,
                          "recoveries": 0, "transfers": 0,
                          "state": st.get("state") if isinstance(st, dict) else None}
        elif aid in lives:
            life = lives[aid]
            if kind == "recovered":
                life["recoveries"] += 1
            elif kind == "thawed":
                life["transfers"] += 1
            elif kind == "removed" and life["retired_s"] is None:
                life["retired_s"] = at(e["time"])
                life["lifetime_s"] = round(life["retired_s"] - life["spawned_s"], 3)
    return sorted(lives.values(), key=lambda v: v["spawned_s"])


def forage_results(mission: Mission, found: dict[str, Any], states: dict[str, Any], sim: dict[str, str] | None,
                   lives: list[dict[str, Any]]) -> dict[str, Any]:
    """The forage results keys (module docstring): totals from the arena, the team's counts from
    `forage/state/*` over the identified ids, haa-sim's deposited count, the supervisors' lives."""
    ids = [c for c in found]
    state = {c: (states.get(c) or {}).get("state") if isinstance(states.get(c), dict) else None for c in ids}
    deposited = sum(s == "deposited" for s in state.values())
    done = [v["lifetime_s"] for v in lives if v["lifetime_s"] is not None]
    return {
        "collectables_total": len(mission.arena.collectables),
        "collectables_identified": len(ids),
        "collectables_deposited": deposited,
        "collectables_lost": sum(s == "lost" for s in state.values()),
        "collectables_missing": sum(s == "missing" for s in state.values()),
        "collectables_open": sum(s not in ("deposited", "lost", "missing") for s in state.values()),
        "cargo_collected": deposited,  # Table 7.1-3's "Cargo Collected"
        "collectables_deposited_sim": None if sim is None else sum(s == "deposited" for s in sim.values()),
        "collectables_sim": sim,
        "collectable_states": {c: state[c] for c in sorted(ids, key=lambda c: (len(c), c))},
        "forage_supervisors": lives,
        "forage_lifetime_s": ({"mean": round(sum(done) / len(done), 3), "min": min(done), "max": max(done),
                               "n": len(done)} if done else None),
    }


def forage_lines(lives: list[dict[str, Any]]) -> list[tr.Line]:
    """A transcript line per retired SupervisorForage (its removal by the hosts, with what it achieved)."""
    out = []
    for v in lives:
        if v["retired_s"] is None:
            continue
        what = f"collectable {v['collectable']} {v['state']}" if v["collectable"] is not None else "no collectable"
        out.append(tr.Line(v["retired_s"], f"{v['agent']} (SupervisorForage) retired: {what}, after "
                                           f"{tr.clock(v['lifetime_s'] or 0.0)}", "runner", "forage",
                           agent=v["agent"]))
    return out


def collect(mission: Mission, backend: Any, prefer: str, sim: Any, agent_events: list[dict[str, Any]],
            clock: tr.ClockMap, t0: float) -> tuple[dict[str, Any], list[tr.Line]]:
    """Everything above for one finished run: (results keys, retirement lines)."""
    found, states = read_team(backend, prefer)
    lives = supervisor_lives(agent_events, clock, t0, states)
    return forage_results(mission, found, states, read_sim(sim), lives), forage_lines(lives)
