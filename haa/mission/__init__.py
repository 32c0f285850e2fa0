"""Missions (issue 15): the mission-file schema; the runner, metrics and results come later.

`load_mission(path)` returns a checked `Mission`; a bad file raises `MissionError` (one line naming the
field path and the reason). The schema is documented in docs/missions.md.
"""

from haa.mission.schema import Mission, MissionError, MissionSpec, load_mission, parse_mission

__all__ = ["Mission", "MissionError", "MissionSpec", "load_mission", "parse_mission"]
