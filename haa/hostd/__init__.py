"""The host daemon `haa-hostd`: the asyncio/gRPC runtime that drives the sans-I/O core (`haa.core`) on a real
host — the host link (`transport.py` and its parts `outlink.py`, `datagrams.py`, `grpclink.py`, `tcplink.py`,
`linkcommon.py`), effect dispatch and timers (`runtime.py`, `dispatch.py`, `timers.py`), the global-state writes
(`writes.py`), files, the control API (`control.py`), and the agents' OS processes (`agentproc.py` and its parts
`agentevents.py`, `agentinstance.py`, `agentmonitor.py`, `agenttypes.py`; `agentcontrol.py`, `agentdriver.py`);
`daemon.py` is the composition root. The deterministic cluster simulator in `haa.lab.dsim` drives the same
core."""
