"""haa-sim: the avatar simulator (thesis "Hardware-in-the-Loop", §6.2.1, §7).

The control system is real; the robots are simulated. Modules:

* `arena` — arena files (YAML, pydantic schema) and the compiled `Arena`; `arenas/` has the thesis' two.
* `geometry` — polygons, edges and vectorised ray casting.
* `avatars` — the four avatar types of Table 6.2-3 and the odometry drift model.
* `sensors` — sonar and camera specifications of Table 6.2-4, reading types.
* `camera` — camera frames rendered by a column ray-caster, ArUco markers on landmarks, floor homography.
* `actions` — the AvatarBase action interface (wait, move, rotate, capture, pick up, drop).
* `world` — `World`: pymunk physics, avatars, sensors, collectables, ground truth (the library API).
* `groundtruth` — the ideal occupancy grid and the explorable area.
* `schedule` — avatars joining, retiring and crashing at given times.
* `render` — top-down pictures of an arena and of a world's true state (`haactl sim show`).
* `service` — the gRPC service `haa-sim` (avatar API + ground-truth API) and a small client.

See docs/sim.md.
"""
