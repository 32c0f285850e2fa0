"""The robot team's agents (thesis Appendix III; docs/team.md): executives, supervisors, the avatar agent, the
path planner and the sensor-processing agents, with what they share (team.py) and the avatar's channel to haa-sim
(simlink.py). Each type is an entry point of group `haa.agents` (pyproject.toml), imported when first spawned.

The agent SDK they are written with is `haa.sdk`; `haa.agents.base` and `haa.agents.registry` remain as
deprecated re-exports of `haa.sdk.base` and `haa.sdk.registry`.

This package's __init__ imports nothing, so that importing one module does not pull in every agent.
"""
