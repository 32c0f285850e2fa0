"""Chaos experiments on a running HAA cluster (`haactl chaos run PLAN`, docs/chaos.md).

A plan (YAML, `haa.lab.chaos.plan`) schedules host and agent faults; a workload of its own
(`haa.lab.chaos.workload`) gives the cluster something to lose; `haa.lab.chaos.inject` carries the faults out;
`haa.lab.chaos.collect` gathers what every host persisted (its JSON-lines log in its data dir) and what every
live replica holds; `haa.lab.chaos.checks` judges the run Jepsen-style from that material alone, and
`haa.lab.chaos.timeline` puts faults and their effects on one time line. `haa.lab.chaos.run` ties them together.
"""
