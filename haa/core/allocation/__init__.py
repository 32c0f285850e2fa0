"""Agent allocation HAA-AA (thesis §4.7, Appendix II Alg. 4): CBBA on processor usage.

* `allocation.py`: `Allocator`, the algorithm for one host (sessions, bid updates, consensus) and its effects;
* `bundle.py`: `BundleBuilder`, Appendix II's bundle building (the base class of `Allocator`);
* `bids.py`: `Bid`, `BidUpdate` and the bid order (Fig. II-1); `conflicts.py`: Table 4.7-1 (`resolve`);
* `session.py`: the per-session state (Alg. 4 ll. 3-16); `rewards.py`: eq. 4.7-1 to 4.7-3;
* `specs.py`: the problem data (`AgentSpec`, `HostSpec`, `SessionStart`) and its bounds;
* `rebalance.py`: `RebalancePolicy`, when a session starts (l. 17);
* `allocwire.py`: the protobuf codec of bid updates and the OAC(start)/OAC(finish) payloads.

The glue to the agent layer is `haa.core.agents.allocglue`. Code inside haa imports from the defining module
(`haa.core.allocation.allocation`, ...); this file re-exports nothing.
"""
