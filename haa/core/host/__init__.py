"""One host incarnation (thesis §4.3): `hostcore.py`, `HostCore`, the failure detector (`haa.core.ufd.ufd`) and
ordered atomic commit (`haa.core.oac.oac`) composed for one host, with its peers and their exclusion. The membership
node (`haa.core.membership.membership`) wraps one.

Code inside haa imports from the defining module (`haa.core.host.hostcore`); this file re-exports nothing.
"""
