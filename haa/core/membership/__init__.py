"""Host membership HAA-HM (thesis §4.6, Appendix II Alg. 3).

* `membership.py`: `MembershipNode`, the node on top of a `HostCore` (`haa.core.host.hostcore`): routes inputs to
  its machines, carries out their effects, applies the global sequence;
* its machines: `formation.py` (ll. 40-49, 158-165), `join.py` (ll. 35-39, 50-75), `update.py` (updateMembership
  and votes, ll. 76-157, 166-179), `groupwrites.py` (global-state changes, ll. 127-132), `groupleave.py`
  (ll. 14-21), `statetransfer.py` (state transfer to a joiner), `sequencer.py` (the DDB's global sequencer);
* `nodeview.py`: what the machines read of their node; `groupeffects.py`: the layer's effects and timer keys;
* `globalstate.py`: the replicated global state every member applies (view, the DDB, the agent table).

Code inside haa imports from the defining module (`haa.core.membership.membership`, ...); this file re-exports
nothing.
"""
