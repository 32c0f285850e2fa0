"""The properties the allocation verifier checks (`haa.lab.dsim.allocation`; the list is `PROPS`).

`check_alloc(sim)` checks a finished `AllocSim` run: AA-Validity (with the exact unallocatable list and
AA-Per-Host-Limit), AA-Table-Fidelity (recorded by the engine as it runs), AA-Agreement, AA-Session-Order,
AA-Liveness, AA-Quiescent-Agreement and AA-Messages (`message_bound`); `premature` tells whether a committed
allocation differed from the bids members held once quiet (a statistic, not a property).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from haa.core.allocation.specs import SessionStart
from haa.lab.dsim.allocsim import AllocSim, Entry, _Node

PROPS = (
    "AA-Validity",
    "AA-Table-Fidelity",
    "AA-Agreement",
    "AA-Session-Order",
    "AA-Liveness",
    "AA-Quiescent-Agreement",
    "AA-Messages",
    "AA-Per-Host-Limit",
)


def message_bound(agents: int, hosts: int) -> int:
    """Bid-update messages one session may send: every host broadcasting a change of every bid a few dozen
    times. Far above what a converging session sends (docs/allocation.md, "verification"), far below a
    livelock's count within the liveness window."""
    return 40 * (agents + 2) * hosts * max(1, hosts - 1)


# --------------------------------------------------------------------------------------------- checks


@dataclass(frozen=True)
class AViolation:
    prop: str
    detail: str
    hosts: tuple[str, ...] = ()

    def __str__(self) -> str:
        return f"{self.prop}: {self.detail}"


def _no_place(start: SessionStart | None, capable: dict[str, list[str]]) -> set[str]:
    """The agents of limited kinds an allocation of `start` must leave out (a reference implementation of
    docs/allocation.md "per-host limits", independent of `haa.core.allocation.specs.over_limit`): a kind has
    max_per_host places on each capable member; agents running on a capable member keep theirs first (at most
    max_per_host per member), then the others in the start's order."""
    if start is None:
        return set()
    out: set[str] = set()
    for kind in sorted({a.kind for a in start.agents if a.max_per_host}):
        members = [a for a in start.agents if a.kind == kind and a.max_per_host and capable.get(a.id)]
        if not members:
            continue
        hosts = capable[members[0].id]
        places = members[0].max_per_host * len(hosts)
        seated: Counter[str] = Counter()
        order = []
        for a in members:
            if a.current_host in hosts and seated[a.current_host] < a.max_per_host:
                seated[a.current_host] += 1
                order.append(a.id)
        order += [a.id for a in members if a.id not in order]
        out.update(order[places:])
    return out


def _per_host_limit(e: Entry) -> str:
    """AA-Per-Host-Limit: why an accepted allocation puts too many agents of a limited kind on a host."""
    assert e.finish is not None
    spec = {a.id: a for a in e.world.agents}
    count: Counter[tuple[str, str]] = Counter()
    for a, h in e.finish.allocation.items():
        s = spec.get(a)
        if s is not None and s.max_per_host:
            count[(h, s.kind)] += 1
            if count[(h, s.kind)] > s.max_per_host:
                return (
                    f"session {e.finish.ses_id} puts {count[(h, s.kind)]} agents of kind {s.kind!r} on {h} "
                    f"(at most {s.max_per_host}): {sorted(x for x, y in e.finish.allocation.items() if y == h)}"
                )
    return ""


def _validity(e: Entry, start: SessionStart | None = None) -> str:
    """Why an accepted allocation is invalid in the world of its entry ("" = valid). `start`: the session's
    committed start — its agent list is the session's (agents added since wait for the next session, the
    places of agents removed since are ignored), its `auction` the agents it had to place; the others keep
    their host or are deferred (docs/allocation.md, "Sessions of a bounded size")."""
    assert e.finish is not None
    w = e.world
    alloc = e.finish.allocation
    hosts = [w.hosts[g] for g in w.group]
    agents = start.agents if start is not None else w.agents
    capable = {a.id: [h.name for h in hosts if h.can_run(a)] for a in agents}
    no_place = _no_place(start, capable)
    auction = set(start.auction) if start is not None and start.auction is not None else set(capable)
    allocatable = [a for a, hs in capable.items() if hs and a not in no_place]
    missing = [a for a in allocatable if a not in alloc and a in auction]
    if missing:
        return f"session {e.finish.ses_id} leaves allocatable agent(s) {missing} unallocated"
    extra = [a for a in alloc if a not in capable]
    if extra:
        return f"session {e.finish.ses_id} allocates agent(s) {extra} not in the agent list {list(capable)}"
    homes = {a.id: a.home for a in agents}
    for a, h in alloc.items():
        if h not in w.group:
            return f"session {e.finish.ses_id} puts {a} on {h}, not in the group {list(w.group)}"
        if h not in capable[a]:
            return f"session {e.finish.ses_id} puts {a} on {h}, which lacks its hardware or is draining"
        if a not in auction and h != homes[a]:
            return f"session {e.finish.ses_id} moves {a}, outside its auction, from {homes[a]} to {h}"
    unalloc = sorted(a for a, hs in capable.items() if not hs or a in no_place)
    if sorted(e.finish.unallocatable) != unalloc:
        return f"session {e.finish.ses_id} reports unallocatable {sorted(e.finish.unallocatable)}, expected {unalloc}"
    return ""


def check_alloc(sim: AllocSim) -> list[AViolation]:
    """The properties of the module docstring, on a finished run."""
    out = [AViolation(p, d, tuple(h)) for p, d, h in sim.violations]
    starts: dict[int, SessionStart] = {}
    last_valid = 0
    for e in sim.log:
        if e.kind == "start" and e.accepted and e.start is not None:
            if e.start.ses_id <= last_valid:
                out.append(AViolation("AA-Session-Order", f"start {e.start.ses_id} committed after {last_valid}"))
            last_valid = max(last_valid, e.start.ses_id)
            starts.setdefault(e.start.ses_id, e.start)
        if e.kind != "finish" or e.finish is None:
            continue
        deciders = {n.name: n.decisions[e.index] for n in sim.nodes.values() if e.index in n.decisions}
        if len(set(deciders.values())) > 1:
            yes = sorted(h for h, v in deciders.items() if v)
            no = sorted(h for h, v in deciders.items() if not v)
            out.append(
                AViolation(
                    "AA-Agreement",
                    f"finish of session {e.finish.ses_id} (log[{e.index}]) accepted by {yes}, ignored by {no}",
                    tuple(yes + no),
                )
            )
        if any(deciders.values()) or (e.accepted and not deciders):
            why = _validity(e, starts.get(e.finish.ses_id))
            if why:
                out.append(AViolation("AA-Validity", why, (e.proposer,)))
            why = _per_host_limit(e)
            if why:
                out.append(AViolation("AA-Per-Host-Limit", why, (e.proposer,)))
    by_ses: dict[int, tuple[str, dict[str, str]]] = {}
    for n in sim.nodes.values():
        prev = 0
        for _idx, ses, _t, alloc in n.accepted:
            if ses <= prev:
                out.append(AViolation("AA-Session-Order", f"{n.name} accepted session {ses} after {prev}", (n.name,)))
            prev = ses
            other = by_ses.setdefault(ses, (n.name, alloc))
            if other[1] != alloc:
                out.append(
                    AViolation(
                        "AA-Agreement",
                        f"session {ses}: {n.name} accepted {sorted(alloc.items())}, {other[0]} "
                        f"{sorted(other[1].items())}",
                        (n.name, other[0]),
                    )
                )
    for ses, count in sim.msgs_by_ses.items():
        st = starts.get(ses)
        if st is None:
            continue
        bound = message_bound(len(st.agents), len(st.group))
        if count > bound:
            out.append(AViolation("AA-Messages", f"session {ses} sent {count} bid updates (bound {bound})"))
    out += _check_liveness(sim)
    return out


def _final_members(sim: AllocSim) -> list[_Node]:
    return [n for n in sim.nodes.values() if n.alive and n.member and n.name in sim.world.group]


def _check_liveness(sim: AllocSim) -> list[AViolation]:
    out: list[AViolation] = []
    deadline = sim.last_change + sim.sc.liveness
    for n in _final_members(sim):
        ok = [t for idx, _ses, t, _a in n.accepted if idx > sim.last_world_entry]
        if not ok or ok[0] > deadline:
            when = f"at {ok[0]:.3f} s" if ok else "never"
            out.append(
                AViolation(
                    "AA-Liveness",
                    f"{n.name} accepted no allocation within {sim.sc.liveness:g} s of the last change at "
                    f"{sim.last_change:.3f} s ({when}; sessions proposed {n.proposed[-5:]}, "
                    f"ledger at {sim.ledger.committed_ses}/{sim.ledger.finished_ses})",
                    (n.name,),
                )
            )
    if out or not sim.sc.final_pause:
        return out
    if not sim.quiet:
        return [AViolation("AA-Liveness", f"still busy at the horizon ({len(sim._q)} events queued)")]
    # every agent that can be placed has been, once quiet: the sessions chained after a bounded one, and those
    # that agents added during a session triggered, did their work
    w = sim.world
    hosts = [w.hosts[g] for g in w.group]
    capable = {a.id: [h.name for h in hosts if h.can_run(a)] for a in w.agents}
    no_place = _no_place(SessionStart(w.group[0], 1, w.group, w.agents, tuple(hosts)), capable)
    homeless = [a.id for a in w.agents if capable[a.id] and a.id not in no_place and a.current_host not in w.group]
    if homeless:
        return [AViolation("AA-Liveness", f"quiet, but agent(s) {homeless[:5]} ({len(homeless)}) have no place in "
                                          f"the group {list(w.group)}")]
    views: dict[str, dict[str, str]] = {}
    for n in _final_members(sim):
        s = n.alloc.session
        if s is None or not s.ready:
            continue
        views[n.name] = {j: b.winner for j, b in s.own.items() if b.winner is not None}
    distinct = {tuple(sorted(v.items())) for v in views.values()}
    if len(distinct) > 1:
        ref_name, ref = next(iter(views.items()))
        for name, v in views.items():
            if v != ref:
                diff = sorted(j for j in set(v) | set(ref) if v.get(j) != ref.get(j))
                out.append(
                    AViolation(
                        "AA-Quiescent-Agreement",
                        f"quiet, but {name} and {ref_name} accept different winners for {diff}: "
                        f"{[(j, v.get(j), ref.get(j)) for j in diff][:4]}",
                        (name, ref_name),
                    )
                )
    return out


def premature(sim: AllocSim) -> bool:
    """The last committed allocation differs from the winners every member holds once quiet: the leader's
    bid table showed agreement while older bids were still in flight (docs/allocation.md, "consensus")."""
    last = next((e for e in reversed(sim.log) if e.kind == "finish" and e.accepted), None)
    if last is None or last.finish is None or not sim.quiet:
        return False
    for n in _final_members(sim):
        s = n.alloc.session
        if s is not None and s.ses_id == last.finish.ses_id and s.ready:
            got = {j: b.winner for j, b in s.own.items() if b.winner is not None}
            return got != last.finish.allocation
    return False
