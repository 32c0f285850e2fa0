"""Missions (issue 15): the mission-file schema (haa.mission.schema), the runner (haa.mission.runner: `MissionRun`,
`run_mission`; its parts in .plan, .simproc, .results, .plots, .chaosrun), attached missions (.attached, .compose),
metrics and transcripts (.metrics, .transcript).

`load_mission(path)` returns a checked `Mission`; a bad file raises `MissionError` (one line naming the
field path and the reason). The schema is documented in docs/missions.md.
"""

from haa.mission.schema import Mission, MissionError, MissionSpec, load_mission, parse_mission

__all__ = ["Mission", "MissionError", "MissionSpec", "load_mission", "parse_mission"]
