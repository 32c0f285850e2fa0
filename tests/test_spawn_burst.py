"""A burst of spawns on a real 4-host group converges (docs/allocation.md, "Sessions of a bounded size").

The reliability probe's 150 spawns in 1.6 s left 149 agents `new` for minutes: every session over all agents
cost seconds of CPU per host, and every create expired the running session. This runs the benchmark
`python -m haa.lab.bench.spawn_burst` at the size docs/limits.md promises: 120 counters on 4 hosts, every one
active within 90 s, and the DDB answering meanwhile."""

from __future__ import annotations

import statistics

from haa.lab.bench.spawn_burst import run


def test_120_spawns_on_4_hosts_are_all_active_within_90_s_and_the_ddb_answers_meanwhile() -> None:
    r = run(agents=120, hosts=4, clients=16, timeout=90.0, log=lambda _line: None)
    assert r["accepted"] == 120, r
    assert r["all_active_after_s"] is not None, r["samples"][-3:]
    writes = [s["write_ms"] for s in r["samples"]]
    assert all(s["write_ok"] for s in r["samples"]), r["samples"]
    # a put through another host than the table's reader, every 2 s: under a second typically. The samples are
    # few and a loaded CI machine slows some (1.25-1.33 s seen in a full suite run beside other work); before,
    # the median itself was 1.33 s and single puts took 1.6-2.1 s
    assert statistics.median(writes) < 1000.0, writes
    assert max(writes) < 2500.0, writes
