"""The unreliable failure detector HAA-UFD (thesis §4.4, Appendix II Alg. 1).

* `ufd.py`: the heartbeat sender and observer (`HeartbeatSender`, `HeartbeatObserver`), Alg. 1;
* `qos.py`: the heartbeat period and safety margin from QoS targets (§4.4.2; Chen, Toueg & Aguilera [66]).

Code inside haa imports from the defining module (`haa.core.ufd.ufd`, `haa.core.ufd.qos`); this file re-exports
nothing.
"""
