"""Agents: `AgentBase` (base.py), the type registry (registry.py), the agent process (runner.py), the fork
server that starts agent processes (forkserver.py), the host<->agent channel (channel.py), the AgentPlayback tap
interface the host injects (tap.py), the channel to haa-sim (simlink.py), and the agent types themselves
(demo.py, ...). The host side is `haa.hostd.agentproc`. See docs/agents.md.

This package's __init__ imports nothing, so that importing one module does not pull in every agent.
"""
