"""The mission runner's rules, without I/O: pure functions of a mission file and of `mission/status`.

* The schedules the runner plays (issue 15 §3), in mission time: the hosts' (`host_plan`; `host_kill_problems`
  names the kills the group could not survive), the avatars' (`avatar_plan`, or haa-sim's `--schedule` file:
  `schedule_yaml`), and `due`: how many entries of a schedule are due now.
* The end of a mission: `status_outcome` (what ExecutiveMission says), `time_limit_reached`, and
  `mission_duration` (its `finished_t - started_t`).
* `MissionRunError`: the one-line error of everything that runs a mission (haa.mission.runner, .simproc,
  .attached).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from haa.mission.schema import Mission

#: the runner stops this many simulated seconds after the time limit if ExecutiveMission has not
TIME_LIMIT_GRACE = 2.0


class MissionRunError(Exception):
    """The mission could not be run (one line for the operator)."""


def due(times: Sequence[float], done: int, now: float) -> int:
    """Entries of a time-ordered schedule are applied one after the other: given `done` applied so far, how
    many are due at `now` in total (entries at exactly `now` are due)."""
    k = done
    while k < len(times) and times[k] <= now:
        k += 1
    return k


def host_plan(mission: Mission) -> list[tuple[float, str, str]]:
    """The host schedule as (at_s, action, host), time ordered (equal times keep file order)."""
    return [(e.at_s, e.action, e.host) for e in mission.spec.hosts.events()]


#: hosts a group needs for one of them to crash and the rest to go on (more than half must stay: below)
MIN_GROUP_FOR_KILL = 3


def host_kill_problems(mission: Mission) -> list[str]:
    """The `kill` entries of the host schedule that the host group cannot survive, one line each.

    A host crash is survived only while more than half of the group stays alive: OAC (Alg. 2) decides a
    transaction only while fewer than half of its participants have failed, and during a mission there is
    always one in flight (the team writes the DDB all the time). A group of two that loses a member blocks
    for good — no removal, no recovery of the dead host's agents, no commit, and a restarted host cannot join
    (docs/membership.md, "Faults within the assumptions" and "Open problems"). So a kill needs at least
    MIN_GROUP_FOR_KILL hosts in the group at its time (the group as the schedule leaves it: earlier kills
    removed, joins and restarts in). Leaves are graceful and always fine."""
    live = set(mission.spec.hosts.initial)
    out = []
    for e in mission.spec.hosts.events():
        if e.action == "kill" and len(live) < MIN_GROUP_FOR_KILL:
            out.append(f"hosts.schedule: kill {e.host} at {e.at_s:g} s leaves {len(live) - 1} of {len(live)} hosts "
                       "running: the group needs more than half of its members alive to remove a crashed host "
                       "(with two hosts it blocks for good: docs/membership.md, Open problems); start at least "
                       f"{MIN_GROUP_FOR_KILL} hosts or let it leave")
        if e.action in ("join", "restart"):
            live.add(e.host)
        else:
            live.discard(e.host)
    return out


def avatar_plan(mission: Mission) -> list[tuple[float, str, str]]:
    """The avatar schedule as (at_s, "join" | "retire", avatar), time ordered (SimControl Join/Retire at these
    mission times when the runner attaches to an haa-sim it did not start)."""
    out = []
    for a in mission.spec.avatars:
        out.append((a.join_at_s or 0.0, "join", a.name))
        if a.leave_at_s is not None:
            out.append((a.leave_at_s, "retire", a.name))
    return sorted(out, key=lambda e: e[0])


def schedule_yaml(mission: Mission) -> str:
    """haa-sim `--schedule` file text for the mission's avatars (`Mission.sim_schedule()`)."""
    import yaml

    entries = [e.model_dump(mode="json", exclude_none=True) for e in mission.sim_schedule()]
    return yaml.safe_dump({"schedule": entries}, sort_keys=False)


def time_limit_reached(mission_t: float, limit: float, grace: float = TIME_LIMIT_GRACE) -> bool:
    return mission_t >= limit + grace


def status_outcome(status: dict[str, Any] | None) -> tuple[bool, str] | None:
    """(completed, reason) once `mission/status` says the mission ended, else None."""
    if not isinstance(status, dict):
        return None
    state = status.get("state")
    if state == "complete":
        return True, str(status.get("reason") or "complete")
    if state == "stopped":
        return False, str(status.get("reason") or "stopped")
    return None


def mission_duration(status: dict[str, Any] | None, now: float) -> float:
    """finished_t - started_t of `mission/status` (`now` while it has not finished; `now` from 0 without a
    status)."""
    if not isinstance(status, dict):
        return max(0.0, now)
    start = as_float(status.get("started_t"), 0.0)
    end = as_float(status.get("finished_t"), now)
    return max(0.0, end - start)


def as_float(v: Any, default: float) -> float:
    """`v` as a finite float, else `default`."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f if math.isfinite(f) else default
