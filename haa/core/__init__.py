"""The core: HAA's distributed algorithms (thesis Appendix II) as sans-I/O state machines.

Every module here is pure: no I/O, no clock, no tasks, no processes, no other HAA package (only the generated
protobuf message classes, `haa.pb`). Inputs come in through `step(now, input)` / `on_*` calls with the time
passed in, decisions come out as returned effects that a driver carries out. Two drivers run the same code:
the host daemon `haa.hostd` (asyncio + gRPC, real processes) and the deterministic simulator `haa.lab.dsim`
(seeded fault schedules, virtual time). `.importlinter` (contract 1) and tests/test_sans_io.py enforce the
rule; mypy checks this package strictly (pyproject [tool.mypy]).

Where each thesis algorithm lives (one subpackage per algorithm, each module named after what it holds):

* `ufd/`: the unreliable failure detector, Alg. 1 (`ufd.py`, with `qos.py`, its configuration from QoS targets).
* `oac/`: ordered atomic commit, Alg. 2 (`oac.py`).
* `host/`: `HostCore` (`hostcore.py`), the UFD and OAC composed for one host incarnation.
* `membership/`: `MembershipNode` (`membership.py`), Alg. 3, composed of `formation.py` (ll. 40-49, 158-165),
  `join.py` (ll. 35-39, 50-75), `update.py` (updateMembership and votes, ll. 76-157, 166-179), `groupwrites.py`
  (global-state changes, ll. 127-132), `groupleave.py` (ll. 14-21), `statetransfer.py`, `sequencer.py` (the
  DDB's global sequencer), read through `nodeview.py`, with `groupeffects.py` (typed timers and effects);
  `globalstate.py` is the replicated state (view, DDB, agent table).
* `ddb/`: the distributed database: the replica `Ddb` (`ddb.py`), its object types and bounds (`objects.py`),
  the op builders clients use (`ops.py`), and the replicated agent table (`agenttable.py`, the thesis'
  "DDB.agents").
* `allocation/`: agent allocation, Alg. 4 (CBBA): `Allocator` (`allocation.py`), its bundle building
  (`bundle.py`), bids and their order (`bids.py`), Table 4.7-1 (`conflicts.py`), the session state
  (`session.py`), the rewards (`rewards.py`), the problem data (`specs.py`), `RebalancePolicy`
  (`rebalance.py`) and the wire codec (`allocwire.py`).
* `agents/`: `AgentNode` (`agentnode.py`), the agent layer of Alg. 5-8, composed of `transfer.py` (Alg. 5-6),
  `recovery.py` (Alg. 7-8), `allocglue.py` (allocation on the agent layer), `agentstep.py`, `agentroute.py`,
  `routing.py`, `agentleave.py`, `agentrequests.py` and `agentplan.py`.

What every layer and every driver shares stays here, at the top: `messages.py` (host-to-host messages),
`effects.py` (the effects every machine returns), `inputs.py` (the inputs every node takes through
`step(now, input)`), `wire.py` (the protobuf codec of the messages) and `agentio.py` (the commands and events
exchanged between the agent layer and whatever runs agent processes; `inputs.py` names its events). They are the
vocabulary of the core's interface, used by the algorithms and by both drivers, and import no algorithm but
`wire.py` (the OAC's messages). Subpackages import one another only downwards: ufd, oac -> host -> membership ->
agents, with allocation under ddb (the agent table checks specs with its bounds) and ddb under membership; no
import cycle (`.importlinter`, contract `acyclic`).

See docs/architecture.md for the layers and how an input travels from a gRPC frame to an effect and back.
"""
