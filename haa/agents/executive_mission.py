"""ExecutiveMission (thesis App. III L3047-3051; Table 4.2-1 item 1; §6.2.2 L1264): the mission's top agent.

"Defines mission parameters and controls when tasks are started. When a new task begins the ExecutiveMission
spawns the appropriate task supervisor and supporting agents." Spawned by the mission runner (the operator,
docs/team.md) with the mission spec; it

* writes `mission/params` and `mission/status` (docs/team.md), and the transcript's "Mission started" /
  "Mission finished" lines;
* spawns its children at start, as in the AF-1 transcript (L1417-1462): ExecutiveAvatar (a separate agent
  here; rolled in in the thesis, L1264), SupervisorSLAM and SupervisorExplore; for `scenario: congregate`,
  SupervisorCongregate once the congregation point's landmark is in the map (L1190: exploration goes on
  until it is found); for `scenario: forage`, one SupervisorForage per collectable the team identifies
  (`forage/collectables`, written by SupervisorSLAM; L1545 "When a collectable is located a SupervisorForage
  agent is spawned"), at most `forage_spawns_per_check` per check (below, "Forage");
* detects completion every `check_s`: **explore** — the explored share (thesis L1186: reachable cells with
  p > 0.73 or p < 0.27) ≥ `complete.explored`. The team does not know which cells are reachable (that is
  ground truth); what it knows is the arena's explorable area (thesis §6.2.1 gives it: 24.2 m² for the small
  arena), passed as `expected_cells` (cells at the map resolution). Explored reachable cells are the map's
  cells with p < 0.27 (seen free) and its obstacle marks (p > 0.73) next to seen-free cells — the floor
  finder's marks of an obstacle's foot land in front of it by the pose error, in reachable cells, and a thin
  panel fills reachable cells of the 50 % ideal grid —: the share is their count / `expected_cells`,
  capped at 1 (docs/team.md, "Completion"); **congregate** — SupervisorCongregate reports every avatar on its slot
  (`congregate/status`); **forage** — the explored share as for explore *and* every identified collectable's
  `forage/state/<id>` terminal (L1194: "once the exploration threshold has been reached and all identified
  collectables have been deposited"; "lost" counts as terminal, see "Forage"). The time limit
  (`complete.time_limit_s`, simulated) ends the mission as stopped.

Forage. Each check reads `forage/collectables` and `forage/state/*`; every id without a child gets a
SupervisorForage (config: the id, the arena's collection regions, the largest carrying avatar's radius) spawned
with the explicit key `forage/<id>` (docs/agents.md "Idempotent spawn": a recovered or moved executive that asks
again for an id whose spawn committed before its backup recorded it gets the same child back, whatever order or
count of spawns its new life goes through; the default key counts spawns per instance and would not). An id
whose `forage/state/<id>` already names a holder is recorded as that child without a spawn (a crash between the
spawn and the backup whose child has since retired: its key no longer answers, and a second SupervisorForage
would only find the collectable deposited and retire). Spawns are bounded to `forage_spawns_per_check` (1) per
check: a spawn is an allocation session and a new agent process, and it holds the executive's mailbox until it
is allocated (1-2 s, AP-4); SupervisorSLAM may publish several ids at once (one frame, or the first publication
after a long gap) and a recovered executive may find many unspawned, and a burst would delay this executive's
status writes and the other agents' spawns (SupervisorSLAM's sensor agents) for all of them together. At one per
second the thesis' AF-3 (20 collectables found over 28 min) is never held back.

Completion counts a collectable "lost" (its avatar crashed carrying it: haa-sim keeps it on the wreck,
SupervisorForage ends, docs/team.md) as finished. The thesis' criterion is "all identified collectables have
been deposited" and in AF-3 every one was; it never has a collectable out of the team's reach. Waiting for a lost
one would end every such mission at the time limit as stopped without anything left to do; counting it done
ends the mission when the team's work is done, and the results keep the two apart (`collectables_deposited`,
`collectables_lost`; the reason says "N lost"). The same holds for one "missing": an identified collectable
that two searches at its estimate did not find, with no sighting of it in between (a sighting placed by a
mislocalized avatar more than the 1 m gate from the collectable's estimate is identified as a new one, with
nothing at its place: seen in a CI forage mission; docs/team.md "SupervisorForage"); `collectables_missing`,
"N not found".

Arena facts it passes on are what the team may know of its arena (bounds for the map, the landmarks' marker
dictionary, size and ids, the congregation point's landmark id); never obstacle positions or poses.

Recovery: "Restore configuration, confirm that appropriate Supervisor agents are active": RECOVERY = "backup"
— the backup holds the children's ids and the mission state (running | complete | stopped, its times and
reason); children are recovered by their own hosts (Alg. 7/8), and a child that was never spawned (a crash
between start and spawn) is spawned on recovery. Recovered without a backup (a crash before the first one), it
resumes from `mission/status` (start time, state, children), or begins the mission if there is none yet. The
mission's start is recorded once: `mission/params` and the first `mission/status` go in one atomic batch whose
status op is a compare-and-set that only creates the key, and an instance whose create fails resumes from the
status an earlier instance recorded (that write was still on its way through the group when it read its host's
replica: `_record_start`). The
recovered instance writes `mission/status` again at once (a crash between deciding the end and writing it must
not leave the runner waiting) and says in the transcript what it resumed with. A crash after a child's
spawn committed and before the backup that records it (an OAC round at mission start) makes the recovered
instance ask for that child again: `spawn_child` is idempotent (its default key is the same for the same type,
config and order of requests, docs/agents.md "Idempotent spawn"), so it gets the first child back instead of
a second one (`haactl verify executive`: 14 duplicate children in 200 schedules before, 0 after; EX-Once).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pydantic

from haa.agents import team
from haa.core.ddb import ops as ddbops
from haa.sdk.registry import register
from haa.slam.replica import decode_map


class MissionAgentConfig(team.TeamConfig):
    mission: dict[str, Any]
    expected_cells: int = pydantic.Field(gt=0)
    check_s: float = pydantic.Field(1.0, gt=0, le=60)
    #: Forage: at most this many SupervisorForage spawned per check (module docstring, "Forage")
    forage_spawns_per_check: int = pydantic.Field(1, ge=1, le=100)


#: the SupervisorForage type, and its entries in `children` ("supervisor_forage/<id>")
FORAGE = "supervisor_forage"
#: `forage/state/<id>` states that end a collectable's foraging (completion)
TERMINAL = ("deposited", "lost", "missing")


def forage_child(cid: str) -> str:
    """The `children` entry of the SupervisorForage of collectable `cid`."""
    return f"{FORAGE}/{cid}"


def id_order(cid: str) -> int:
    """Collectable ids (digits) in numeric order ("2" before "10")."""
    return int(cid)


def forage_counts(ids: list[str], states: dict[str, Any]) -> dict[str, int]:
    """{"identified", "deposited", "lost", "missing", "open"} of the identified collectables `ids` by their
    states."""
    st = [states.get(c, {}).get("state") if isinstance(states.get(c), dict) else None for c in ids]
    dep, lost, missing = st.count("deposited"), st.count("lost"), st.count("missing")
    return {"identified": len(ids), "deposited": dep, "lost": lost, "missing": missing,
            "open": len(ids) - dep - lost - missing}


def arena_facts(mission: dict[str, Any]) -> dict[str, Any]:
    """What the team may know of the mission's arena (see the module docstring)."""
    from haa.sim.arena import BUILTIN, load_arena
    from haa.sim.avatars import avatar_spec
    from haa.sim.sensors import CAMERAS

    name = mission["arena"]
    arena = load_arena(name if name in BUILTIN else Path(name))
    kinds = {a["type"] for a in mission["avatars"]}
    specs = [avatar_spec(k) for k in kinds]
    return {
        "width": arena.width, "height": arena.height,
        "marker_dictionary": arena.marker_dictionary, "marker_size": arena.marker_size,
        "landmark_ids": sorted(arena.landmarks), "congregation_id": arena.congregation_id,
        "radius": max(s.radius for s in specs),
        # Forage: the largest avatar that may carry (SupervisorForage's `avatar_radius`: its drop points are
        # passable for it)
        "carrier_radius": max((s.radius for s in specs if s.capacity >= 1), default=max(s.radius for s in specs)),
        "camera_range": max(CAMERAS[s.camera].max_range for s in specs),
        # Forage: the predefined collection regions (SupervisorForage's `regions`)
        "collection_regions": {rid: [[float(x), float(y)] for x, y in poly] for rid, poly in arena.regions.items()},
    }


def explored_share(prob: np.ndarray, expected_cells: int) -> float:
    """Share of the arena's explorable cells explored (see the module docstring): cells seen free, and
    obstacle marks with a seen-free cell among their 8 neighbours, against `expected_cells`."""
    free = prob < 0.27
    near_free = cv2.dilate(free.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    marks = (prob > 0.73) & near_free
    return min(1.0, float(free.sum() + marks.sum()) / expected_cells)


@register
class ExecutiveMission(team.TeamAgent):
    TYPE = "executive_mission"
    CONFIG = MissionAgentConfig
    COST = 0.02
    RECOVERY = "backup"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: MissionAgentConfig
        self.m = self.cfg.mission
        self.children: dict[str, str] = {}
        self.state = "running"
        self.started_t: float | None = None
        self.finished_t: float | None = None
        self.explored = 0.0
        self.reason = ""
        self.facts: dict[str, Any] = {}
        self.forage: dict[str, int] = {}  # forage_counts at the last check (forage missions)

    def pack_state(self) -> bytes:
        return team.dumps({"children": self.children, "state": self.state, "started_t": self.started_t,
                           "finished_t": self.finished_t, "explored": self.explored, "reason": self.reason,
                           "forage": self.forage})

    def unpack_state(self, data: bytes) -> None:
        st = json.loads(data)
        self.children = st.get("children", {})
        self.state = st.get("state", "running")
        self.started_t, self.finished_t = st.get("started_t"), st.get("finished_t")
        self.explored = float(st.get("explored", 0.0))
        self.reason = str(st.get("reason", ""))
        self.forage = {str(k): int(v) for k, v in dict(st.get("forage") or {}).items()}

    def recover(self, backup: bytes | None) -> None:
        if backup:
            self.unpack_state(backup)

    async def begin(self, how: str) -> None:
        if how == "recover" and self.started_t is None:
            # no backup (a crash before the first one, right after the start): the mission's state is in the
            # DDB if the first instance wrote it; if it did not, the mission has not begun and begins now
            how = await self._resume_from_status()
        if how == "start":
            how = await self._record_start()
        if how == "start":
            await team.transcript(self, f"Mission started: {self.m.get('name')} ({self.m.get('scenario')})")
        elif how == "recover":
            if self.state == "running":  # the backup's share is old: the map says what it is now
                await self._read_explored()
            await self._status(self.reason)
            await team.transcript(self, f"resumed after a crash: mission {self.state}, explored {self.explored:.1%}, "
                                        f"children {', '.join(sorted(self.children)) or 'none yet'}")
        self.facts = arena_facts(self.m)
        await self._spawn_children()
        if self.m.get("scenario") == "congregate":
            self.watch(team.K_SLAM_LANDMARKS, self._on_landmarks)
            self.watch("congregate/status", self._on_congregate)
        self.every(self.cfg.check_s, self._check)

    async def _resume_from_status(self) -> str:
        """The mission state of `mission/status` (its start time, state, children): "recover" if there was
        one, "start" if the mission had not begun (found by running this agent in the simulator, haa.lab.dsim.vagent:
        a recovered instance without a backup had no start time, so its time limit never ended the mission, and
        one whose first instance died before writing anything never said "Mission started")."""
        st = await team.get_json(self, team.K_STATUS)
        if not isinstance(st, dict) or st.get("started_t") is None:
            return "start"
        self.started_t = float(st["started_t"])
        self.state = str(st.get("state", "running"))
        self.finished_t = st.get("finished_t")
        self.explored = float(st.get("explored", 0.0))
        self.reason = str(st.get("reason", ""))
        self.children = {str(k): str(v) for k, v in dict(st.get("children") or {}).items()}
        return "recover"

    async def _record_start(self) -> str:
        """Begin the mission: `mission/params` and the first `mission/status` in one atomic batch whose status is
        a compare-and-set that only creates the key (version 0: absent), so that the mission's start is recorded
        once. "start" if this instance recorded it; "recover" if the status was there — an earlier instance of
        this executive recorded the start (the runner deletes `mission/` before it spawns the executive,
        docs/team.md): its write was still on its way through the group when this one read `mission/status`
        (a write is applied in total order, and a recovered instance reads its host's replica), so this one
        resumes from it instead of starting a second mission. (Found by `haactl verify executive --hosts 7`,
        seeds 569, 807, 1043, 1583: the first start committed after the recovered instance had read no status,
        and `mission/status` then carried two start times.)"""
        self.started_t = self.now()
        params = team.op_put_json(team.K_PARAMS, {
            "mission": self.m, "speed": self.cfg.speed, "sim": self.cfg.sim, "seed": self.cfg.seed,
            "expected_cells": self.cfg.expected_cells})
        create = ddbops.cas(team.K_STATUS, 0, "json", self._status_value(""))
        errors = await self.ddb_write([params, create], atomic=True)
        if not any(errors):
            return "start"
        if await self._resume_from_status() == "recover":
            return "recover"
        # a status without a start time (not this executive's): nothing to resume from, the mission begins
        self.started_t = self.now()
        await self.ddb_write([params, team.op_put_json(team.K_STATUS, self._status_value(""))])
        return "start"

    async def _spawn_children(self) -> None:
        f = self.facts
        res = float(self.m.get("map_resolution", 0.1))
        wanted = {
            "executive_avatar": team.team_config(self),
            "supervisor_slam": team.team_config(
                self, mode=self.m.get("slam", "jc-slam"), particles=int(self.m.get("particles", 100)),
                grid=(0.0, 0.0, f["width"], f["height"], res), landmark_ids=f["landmark_ids"],
                marker_dictionary=f["marker_dictionary"], marker_size=f["marker_size"],
                discard_agents=int(self.m.get("hosts", {}).get("start", 1)),
                # Forage: the landmark agents report collectables too (the key only then: the other
                # scenarios' configs stay as they were)
                **({"collectables": True} if self.m.get("scenario") == "forage" else {})),
            "supervisor_explore": team.team_config(
                self, exploration=self.m.get("exploration", "em"), radius=f["radius"],
                camera_range=f["camera_range"]),
        }
        for type_name, config in wanted.items():
            if type_name not in self.children:
                self.children[type_name] = await self.spawn_child(type_name, config)
                self.backup()

    def _status_value(self, reason: str) -> dict[str, Any]:
        v = {"state": self.state, "t": round(self.now(), 3), "explored": round(self.explored, 4),
             "reason": reason, "started_t": self.started_t, "finished_t": self.finished_t,
             "children": self.children}
        if self.m.get("scenario") == "forage":
            v["forage"] = self.forage
        return v

    async def _status(self, reason: str) -> None:
        await self.ddb_write([team.op_put_json(team.K_STATUS, self._status_value(reason))])

    async def _check(self) -> None:
        if self.state != "running":
            return
        await self._read_explored()
        complete = self.m.get("complete", {})
        reason = ""
        scenario = self.m.get("scenario", "explore")
        explored = self.explored >= float(complete.get("explored", 0.95))
        foraged, forage_text = await self._forage() if scenario == "forage" else (True, "")
        if scenario == "explore" and explored:
            self.state, reason = "complete", f"explored {self.explored:.1%}"
        elif scenario == "forage" and explored and foraged:
            self.state, reason = "complete", f"explored {self.explored:.1%}, {forage_text}"
        elif self.started_t is not None and self.now() - self.started_t >= float(complete.get("time_limit_s", 900)):
            self.state, reason = "stopped", "time limit"
        if self.state != "running":
            self.finished_t = self.now()
            self.reason = reason
            self.backup()
            await team.transcript(self, f"Mission finished: {reason}")
        await self._status(reason)
        await self._trim_events()

    async def _forage(self) -> tuple[bool, str]:
        """Forage (module docstring): spawn the SupervisorForage of identified collectables that have none (at
        most `forage_spawns_per_check`); (whether every identified collectable is deposited or lost and has
        had its supervisor, the counts as reason text)."""
        found = await team.get_json(self, team.K_FORAGE_COLLECTABLES, {})
        found = found if isinstance(found, dict) else {}
        states: dict[str, Any] = {}
        for key, data in (await self.ddb_scan(team.K_FORAGE_STATE)).items():
            try:
                states[key[len(team.K_FORAGE_STATE):]] = json.loads(data)
            except ValueError:
                continue
        ids = sorted((str(c) for c in found if str(c).isdigit()), key=id_order)  # SupervisorSLAM's ids: 1, 2, ...
        spawned = 0
        for cid in ids:
            child = forage_child(cid)
            if child in self.children:
                continue
            st = states.get(cid)
            if isinstance(st, dict) and st.get("holder"):
                self.children[child] = str(st["holder"])
                self.backup()
                continue
            if spawned >= self.cfg.forage_spawns_per_check:
                break
            spawned += 1
            if not await self._spawn_forager(cid, found[cid]):
                break
        self.forage = forage_counts(ids, states)
        done = self.forage["open"] == 0 and all(forage_child(c) in self.children for c in ids)
        n = self.forage
        text = f"{n['deposited']} of {n['identified']} identified collectables deposited" + (
            f", {n['lost']} lost" if n["lost"] else "") + (f", {n['missing']} not found" if n["missing"] else "")
        return done, text

    async def _spawn_forager(self, cid: str, est: Any) -> bool:
        """Spawn the SupervisorForage of collectable `cid` (estimate `est`); False if the spawn failed (the next
        check asks again, with the same key)."""
        f = self.facts
        cfg = team.team_config(self, collectable=int(cid), regions=f["collection_regions"],
                               avatar_radius=float(f.get("carrier_radius", f.get("radius", 0.2))))
        try:
            self.children[forage_child(cid)] = await self.spawn_child(FORAGE, cfg, key=f"forage/{cid}")
        except Exception as e:  # no host could take it now, a timeout: the next check tries again
            self.log("forage_spawn_failed", level="warning", collectable=cid, error=str(e))
            return False
        self.backup()
        where = ""
        if isinstance(est, dict) and isinstance(est.get("x"), int | float) and isinstance(est.get("y"), int | float):
            where = f" at ({float(est['x']):.2f}, {float(est['y']):.2f})"
        await team.transcript(self, f"collectable {cid} identified{where}: SupervisorForage spawned for it")
        return True

    async def _read_explored(self) -> None:
        data = await self.ddb_get(team.K_SLAM_MAP)
        if data is not None:
            _, prob = decode_map(data)
            self.explored = explored_share(prob, self.cfg.expected_cells)

    async def _trim_events(self) -> None:
        data = await self.ddb_get(team.K_EVENTS)
        if data is None:
            return
        first, items = ddbops.decode_log(data)
        if len(items) > team.EVENTS_KEEP:
            await self.ddb_write([ddbops.log_trim(team.K_EVENTS, first + len(items) - team.EVENTS_KEEP)])

    async def _on_landmarks(self, kind: str, key: str, value: bytes | None) -> None:
        cid = self.facts.get("congregation_id")
        if value is None or cid is None or "supervisor_congregate" in self.children:
            return
        lms = json.loads(value)
        if str(cid) in lms:
            x, y = lms[str(cid)][:2]
            await team.transcript(self, f"congregation point found at ({x:.2f}, {y:.2f})")
            cong = self.m.get("congregation", {})
            self.children["supervisor_congregate"] = await self.spawn_child(
                "supervisor_congregate",
                team.team_config(self, landmark=int(cid), radius_m=float(cong.get("radius_m", 0.6)),
                                 tolerance_m=float(cong.get("tolerance_m", 0.15)),
                                 avatar_radius=float(self.facts.get("radius", 0.12))))
            self.backup()
            explore = self.children.get("supervisor_explore")
            if explore:  # exploration is abandoned once the point is found (L1512)
                self.send(explore, team.dumps({"op": "abandon"}))

    async def _on_congregate(self, kind: str, key: str, value: bytes | None) -> None:
        if value is None or self.state != "running":
            return
        st = json.loads(value)
        if st.get("done"):
            self.state = "complete"
            self.finished_t = self.now()
            self.reason = "every avatar on its slot"
            self.backup()
            await team.transcript(self, "Mission finished: every avatar on its slot")
            await self._status("every avatar on its slot")
