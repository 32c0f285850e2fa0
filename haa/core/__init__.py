"""The core: HAA's distributed algorithms (thesis Appendix II) as sans-I/O state machines.

Every module here is pure: no I/O, no clock, no tasks, no processes, no other HAA package (only the generated
protobuf message classes, `haa.pb`). Inputs come in through `step(now, input)` / `on_*` calls with the time
passed in, decisions come out as returned effects that a driver carries out. Two drivers run the same code:
the host daemon `haa.hostd` (asyncio + gRPC, real processes) and the deterministic simulator `haa.lab.dsim`
(seeded fault schedules, virtual time). `.importlinter` (contract 1) and tests/test_sans_io.py enforce the
rule; mypy checks this package strictly (pyproject [tool.mypy]).

Where each thesis algorithm lives:

* `ufd.py` (+ `qos.py`): the unreliable failure detector, Alg. 1.
* `oac.py`: ordered atomic commit, Alg. 2.
* `hostcore.py`: `HostCore`, the UFD and OAC composed for one host incarnation.
* `inputs.py`: the host-level inputs every node takes through `step(now, input)`.
* `membership.py`: `MembershipNode`, Alg. 3, composed of `formation.py` (ll. 40-49, 158-165), `join.py`
  (ll. 35-39, 50-75), `update.py` (updateMembership and votes, ll. 76-157, 166-179), `groupwrites.py`
  (global-state changes, ll. 127-132), `groupleave.py` (ll. 14-21), `statetransfer.py`, `sequencer.py` (the
  DDB's global sequencer), read through `nodeview.py`, with `groupeffects.py` (typed timers and effects);
  `globalstate.py` is the replicated state (view, DDB) and `ddb.py` the distributed database's operations.
* `agentnode.py`: `AgentNode`, the agent layer of Alg. 5-8, composed of `transfer.py` (Alg. 5-6),
  `recovery.py` (Alg. 7-8), `allocation.py` (CBBA, Alg. 9-11) via `allocglue.py`, `agenttable.py`,
  `agentstep.py`, `agentroute.py`, `routing.py`, `agentleave.py`, `agentrequests.py`, `agentplan.py` and
  `agentio.py` (the interface to whatever runs the agents' processes).
* `messages.py`, `effects.py`, `wire.py`, `allocwire.py`: the messages, effects and their wire codecs.

See docs/architecture.md for the layers and how an input travels from a gRPC frame to an effect and back.
"""
