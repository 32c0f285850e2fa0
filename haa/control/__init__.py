"""Control algorithms of the Appendix III agents, as pure library code (no I/O, no clock, no agent API).

* `pathplanner` — AgentPathPlanner's core: weighted-distance planning over the occupancy map (L2955-2957).
* `explore` — SupervisorExplore's core: EM split of the unexplored reachable cells, one target per avatar
  (L3077-3079).
* `frontier` — coordinated frontier exploration (Burgard et al. 2005), the second strategy of issue 15.
* `landmarks` — AgentSensorLandmark's core: ArUco markers in camera frames → landmark sightings (L2995-2997).
* `floorfinder` — AgentSensorFloorFinder's core: floor colour match + homography → free polygon (L2983-2985).
* `collectables` — the Forage sensor's core: red collectables in camera frames → sightings (§7.1.3).

The agents of issue 15 wrap these; docs/control.md documents the choices made where the thesis is vague.
"""
