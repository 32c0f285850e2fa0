"""Deterministic simulation of agent allocation (Alg. 4) on N hosts: the verifier, AP-3 and the quality study.

`AllocSim` drives one `haa.core.allocation.allocation.Allocator` (and one `RebalancePolicy`) per host:

* bid updates travel over reliable FIFO channels with random delays (`haa.lab.dsim.network.DelayModel`);
* OAC is modelled as an ideal totally ordered atomic broadcast: a proposal is decided after a random delay,
  aborted with probability `p_abort` (the proposer retries, Alg. 4 ll. 25-28 / 89-92) or appended to one global
  log that every member delivers in order, each after its own delay (the real OAC is verified separately);
* the group and the agent list are part of the same log ("world" entries), as they are in the real system
  (membership transactions and the replicated agent table): a crash is followed, after a detection delay, by
  a membership entry that removes the host; a host paused for longer than that, or falsely suspected, is
  removed too and, once it runs again, delivers its own removal and stops; hosts join at the end of the list;
  agents are added and removed, costs change; the operator pauses and resumes periodic rebalancing;
* the leader's `RebalancePolicy` starts sessions on changes (rate limited) and periodically.

`check_alloc` then checks the schedule (properties in `PROPS`):

* AA-Validity: every accepted allocation places each allocatable agent of the agent list current at that
  point of the total order exactly once, on a member of the current group that has its hardware (and is not
  draining), and reports exactly the agents no member can run as unallocatable;
* AA-Table-Fidelity: every bid a member sends is its own accepted bid at that moment, so that the leader's
  copy of each member's row is that member's real opinion (what the thesis' consensus check relies on);
* AA-Agreement: every host that delivers a given OAC(finish) takes the same accept/ignore decision, and all
  hosts accept the same allocation for a session id;
* AA-Session-Order: committed (valid) start ids strictly increase, a leader never proposes an id twice, and
  each host accepts sessions in increasing order;
* AA-Liveness: after the last fault or change, every live member accepts an allocation of a session started
  after it within `LIVENESS_BOUND` seconds, and the system then goes quiet;
* AA-Quiescent-Agreement: once quiet, every member's accepted bids (bidTable_p[p]) name the same winners
  (the conflict rules converge). Whether they are also the committed allocation is not a property: the
  leader checks consensus on the last bids each member sent, and a bid still in flight can change the
  outcome after that (`premature`, counted in the statistics; docs/allocation.md, "consensus");
* AA-Messages: the bid-update messages of each session stay below `message_bound(agents, hosts)`.
* AA-Per-Host-Limit (issue 15): no accepted allocation puts more agents of a limited kind on one host than
  the kind's `max_per_host`, and the agents it leaves out for lack of places are exactly those the rule of
  docs/allocation.md ("per-host limits") names (checked as part of AA-Validity's exact unallocatable list).
  Half of the schedules give some agents a limited kind (`_limited_kinds`).

Every schedule is drawn from its seed (`draw_alloc`) and reproducible; `haactl verify allocation` runs them.

The same engine measures AP-3 (`cpu=True`: the real CPU time of every Allocator call advances the virtual
clock of its host) and the allocation quality (`quality_instance`, `optimum`: exhaustive optimum of
eq. 4.7-1 on small instances).

This module is what the sweep runs (`run_schedule`, `seed_result`, `full_trace`, `trace_excerpt`); the pieces
are `haa.lab.dsim.allocschedule` (the schedules: `AllocScenario`, `draw_alloc`), `haa.lab.dsim.allocsim` (the
engine: `AllocSim`), `haa.lab.dsim.alloccheck` (the properties: `PROPS`, `check_alloc`) and
`haa.lab.dsim.allocquality` (the quality study: `quality_instance`, `optimum`, `run_quality`).
"""

from __future__ import annotations

from typing import Any

from haa.lab.dsim.alloccheck import AViolation, check_alloc, premature
from haa.lab.dsim.allocschedule import AllocScenario, draw_alloc
from haa.lab.dsim.allocsim import AllocSim

# --------------------------------------------------------------------------------------------- sweep adapters


def run_schedule(seed: int, hosts: int, trace: bool = False) -> tuple[AllocScenario, AllocSim, list[AViolation]]:
    sc = draw_alloc(seed, hosts)
    sim = AllocSim(sc, trace=trace)
    sim.run()
    return sc, sim, check_alloc(sim)


def seed_result(seed: int, hosts: int) -> dict[str, Any]:
    """The fields of `haa.lab.dsim.sweep.SeedResult` for one seed."""
    sc, sim, vs = run_schedule(seed, hosts)
    return {
        "seed": seed,
        "violations": [str(v) for v in vs],
        "liveness_checked": sim.quiet,
        "trace_hash": sim.hash.hexdigest()[:16],
        "events": sim.events,
        "messages": sim.messages,
        "stats": {
            "sessions": float(sim.ledger.committed_ses),
            "allocations": float(sum(1 for e in sim.log if e.kind == "finish" and e.accepted)),
            "faults": float(len(sc.faults)),
            "premature": float(premature(sim)),
        },
        "hosts": [h for v in vs for h in v.hosts],
        "description": sc.describe()[0],
    }


def full_trace(seed: int, hosts: int) -> list[str]:
    sc, sim, vs = run_schedule(seed, hosts, trace=True)
    out = [f"# {ln}" for ln in sc.describe()]
    out += sim.trace or []
    out += [f"# {v}" for v in vs]
    out.append(f"# trace hash {sim.hash.hexdigest()[:16]}")
    return out


def trace_excerpt(seed: int, hosts: int, bad_hosts: list[str], lines: int = 40) -> list[str]:
    """Scenario, then the log entries, faults and the concerned hosts' events (messages left to --trace)."""
    sc, sim, _vs = run_schedule(seed, hosts, trace=True)
    keys = tuple(f"{h}#" for h in sorted(set(bad_hosts)))
    picked = [
        ln
        for ln in sim.trace or []
        if " send ses=" not in ln and (" log[" in ln or " fault " in ln or not keys or any(k in ln for k in keys))
    ]
    out = [f"  scenario: {ln}" for ln in sc.describe()[:16]]
    if len(picked) > lines:
        out.append(f"  ... {len(picked) - lines} earlier lines ...")
        picked = picked[-lines:]
    return out + [f"  {ln}" for ln in picked]
