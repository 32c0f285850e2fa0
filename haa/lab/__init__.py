"""The lab: the tooling that checks the framework and the robot team (docs/architecture.md).

dsim (the deterministic simulator and the verifiers), experiments and benchmarks, chaos, stats and reports,
playback readers and replay, the dashboard, the Foxglove bridge, and the demo agents (`counter`, `spawner`,
`busy`, `probe`). The lab imports the team and the framework; neither imports the lab.
"""
