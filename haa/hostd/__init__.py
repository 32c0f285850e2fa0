"""The host daemon `haa-hostd`: the distributed algorithms of thesis Appendix II as sans-I/O state machines
(`ufd.py`, `oac.py`, composed in `core.py`) and the asyncio/gRPC runtime that drives them (`runtime.py`,
`transport.py`, `daemon.py`). The deterministic cluster simulator in `haa.dsim` drives the same cores."""
