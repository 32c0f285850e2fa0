"""The agent layer of a host (thesis §4.8-4.9, Appendix II Alg. 4-8), on top of host membership.

* `agentnode.py`: `AgentNode`, the layer on a `MembershipNode`, composing the machines below;
* `transfer.py`: agent transfer HAA-AT (Alg. 5 freeze, Alg. 6 thaw); `recovery.py`: backup and recovery
  HAA-AB / HAA-AR (Alg. 7-8);
* `allocglue.py`: allocation (`haa.core.allocation`) on the agent layer: the agent table in, sessions out;
* `agentroute.py` (routing agent messages on a host) and `routing.py` (per-sender streams);
* `agentleave.py` (graceful leave), `agentrequests.py` (operator requests), `agentplan.py` (the stateless
  decisions), `agentstep.py` (what the machines share: view, effects, timer keys).

The replicated agent table they read and write is `haa.core.ddb.agenttable` (the thesis' "DDB.agents"); the
commands and events exchanged with whatever runs agent processes are `haa.core.agentio`. Code inside haa imports
from the defining module (`haa.core.agents.agentnode`, ...); this file re-exports nothing.
"""
