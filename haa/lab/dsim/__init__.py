"""Deterministic cluster simulator: N host cores in one process on a virtual clock.

`network` draws message delays, `cluster` runs the cores and injects faults, `schedule` draws a whole
fault schedule and workload from one seed (swarm style), `checks` verifies the thesis' properties on the
recorded history, and `sweep` runs thousands of seeds on every core. A run is a seed: the same seed gives
the same trace hash."""
