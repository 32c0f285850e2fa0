"""Ordered atomic commit HAA-OAC (thesis §4.5, Appendix II Alg. 2): `oac.py`, `OrderedAtomicCommit`.

Code inside haa imports from the defining module (`haa.core.oac.oac`); this file re-exports nothing.
"""
