"""The agent SDK: what an agent needs and nothing of the robot team (docs/agents.md).

* `haa.sdk.base` — `AgentBase`, the class every agent derives from, and `AgentContext`, the machinery behind it
* `haa.sdk.sched` — the clock and scheduler an agent runs on (wall time in a process, virtual in the simulator)
* `haa.sdk.registry` — type name -> class; built-in and third-party types are entry points, imported when first
  spawned
* `haa.sdk.channel` — the host <-> agent channel; `haa.sdk.runner` — the agent process; `haa.sdk.forkserver` —
  the zygote that forks agent processes
* `haa.sdk.tap`, `haa.sdk.recorder`, `haa.sdk.external` — AgentPlayback's agent side: the recorder that runs
  inside agents (replay and readers are in the lab, haa.lab.playback)

This package's __init__ imports nothing, so that importing one module does not pull in the others.
"""
