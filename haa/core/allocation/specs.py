"""The problem data of agent allocation HAA-AA (thesis §4.7): agents, hosts, the session they are allocated in.

* `AgentSpec`: one agent a_i (cost c_i, hardware Q_i, affinities, transfer penalty t_i, current host, and the
  per-host limit of its kind); `HostSpec`: one host h (capacity K_h, hardware H_h, draining flag);
* `SessionStart`: the payload of OAC(start) (Alg. 4 l. 26), with the agents no host of its group can run
  (`unallocatable`: hardware, and the per-host limits of `limit_conflict` / `over_limit`);
* the bounds every spec is checked against (`MAX_COST`, `MAX_CAPACITY`, `MIN_CAPACITY`, `MAX_AFFINITY`,
  `MAX_NAME`, `MAX_PER_HOST`), which `haa.core.ddb.agenttable` applies to transactions too.

The algorithm over these is `haa.core.allocation.allocation.Allocator`. Pure: no I/O, no clock, no randomness.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

INF = math.inf

#: Bounds on the problem data (docs/limits.md, "Agent and host numbers"). Costs and capacities are in units of
#: one host's processor (K_h = 1.0 by default): no agent declares more than MAX_COST of them and no host more than
#: MAX_CAPACITY, and a capacity is at least MIN_CAPACITY. Within these bounds every sum and ratio the bundle
#: building computes (eq. 4.7-1 to 4.7-3, over at most a few thousand agents) stays finite, so comparisons of
#: bids never meet inf or NaN; `haa.core.ddb.agenttable` refuses transactions outside them before they apply.
MAX_COST = 1000.0
MAX_CAPACITY = 1000.0
MIN_CAPACITY = 1e-3
#: affinity alpha_ij (eq. 4.7-2) is clamped to [0, 1] by the host; a spec may not claim more than this
MAX_AFFINITY = 1000.0
#: longest agent id, host name and hardware name
MAX_NAME = 64
#: largest per-host limit an agent type may declare (`AgentSpec.max_per_host`; 0 = unlimited). Issue 15:
#: SupervisorSLAM runs "at most one sensor agent of each type per host" (thesis App. III); the bound only keeps
#: the number a count
MAX_PER_HOST = 1000
#: most agents one allocation session auctions (`SessionStart.auction`; docs/allocation.md, "Sessions of a
#: bounded size"). Bundle building is O(agents x bundle) per build and a session's builds grow with its agents,
#: so one session over all agents cost ~2.7 s of CPU at 150 agents and ~25 s at 300 (4 hosts, measured in the
#: AP-3 simulator) and a burst of 500 spawns never finished on a real 4-host group. Above this many agents a
#: session auctions a window of them (the agents that need a place first) and the others keep their host;
#: the leader chains sessions until every agent has a place. 64 = the clusters one bundle step examines
#: (`BundleBuilder.MAX_CLUSTERS`): a 64-agent session costs ~0.2 s of CPU over 4 hosts
MAX_SESSION_AGENTS = 64

# --------------------------------------------------------------------------------------------- problem data


def _finite(x: object, what: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ValueError(f"{what}: must be a finite number, got {x!r}")
    v = float(x)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ValueError(f"{what}: must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise ValueError(f"{what}: must be <= {hi:g}, got {v:g}")
    return v


def _name(x: object, what: str) -> str:
    if not isinstance(x, str) or not x:
        raise ValueError(f"{what}: must be a non-empty string, got {x!r}")
    if len(x) > MAX_NAME:
        raise ValueError(f"{what}: must be at most {MAX_NAME} characters, got {len(x)}")
    return x


@dataclass(frozen=True, repr=False)
class AgentSpec:
    """One agent a_i of §4.7: id, processing cost c_i (>= 0, in units of host capacity), required hardware
    Q_i, affinities A_i (other agent id -> alpha_ij >= 0), transfer penalty t_i in [0, 1] and the host that runs
    it now (L_h membership; None: not running yet).

    `kind` and `max_per_host` (not in the thesis; issue 15): at most `max_per_host` agents of the same `kind`
    (its agent type) on one host, 0 = no limit. Every agent of a limited kind in a session must declare the same
    limit and hardware (`SessionStart` refuses others; the agent table refuses such a create), so which agents
    of a kind can be placed is a count (docs/allocation.md, "per-host limits")."""

    id: str
    cost: float
    hardware: frozenset[str] = frozenset()
    affinity: Mapping[str, float] = field(default_factory=dict)
    transfer_penalty: float = 0.0
    current_host: str | None = None
    kind: str = ""
    max_per_host: int = 0
    placed: str | None = None

    def __post_init__(self) -> None:
        _name(self.id, "AgentSpec.id")
        m = self.max_per_host
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= MAX_PER_HOST:
            raise ValueError(f"AgentSpec({self.id}).max_per_host: must be an integer in [0, {MAX_PER_HOST}], got {m!r}")
        if not isinstance(self.kind, str) or len(self.kind) > MAX_NAME:
            raise ValueError(f"AgentSpec({self.id}).kind: must be a string of at most {MAX_NAME} characters")
        if m and not self.kind:
            raise ValueError(f"AgentSpec({self.id}).kind: an agent with a per-host limit must name its kind")
        object.__setattr__(self, "cost", _finite(self.cost, f"AgentSpec({self.id}).cost", 0.0, MAX_COST))
        pen = _finite(self.transfer_penalty, f"AgentSpec({self.id}).transfer_penalty", 0.0, 1.0)
        object.__setattr__(self, "transfer_penalty", pen)
        hw = frozenset(self.hardware)
        for h in hw:
            _name(h, f"AgentSpec({self.id}).hardware item")
        object.__setattr__(self, "hardware", hw)
        aff: dict[str, float] = {}
        for k, v in dict(self.affinity).items():
            _name(k, f"AgentSpec({self.id}).affinity key")
            if k == self.id:
                raise ValueError(f"AgentSpec({self.id}).affinity: an agent has no affinity with itself")
            aff[k] = _finite(v, f"AgentSpec({self.id}).affinity[{k}]", 0.0, MAX_AFFINITY)
        object.__setattr__(self, "affinity", aff)
        if self.current_host is not None:
            _name(self.current_host, f"AgentSpec({self.id}).current_host")
        if self.placed is not None:
            _name(self.placed, f"AgentSpec({self.id}).placed")

    @property
    def home(self) -> str | None:
        """The host the agent belongs to now: its last allocation (`placed`), else the host that runs it."""
        return self.placed if self.placed is not None else self.current_host

    def __hash__(self) -> int:
        return hash(
            (
                self.id,
                self.cost,
                self.hardware,
                tuple(self.affinity.items()),
                self.transfer_penalty,
                self.current_host,
                self.kind,
                self.max_per_host,
                self.placed,
            )
        )

    def __repr__(self) -> str:
        return _repr_sorted_hardware(self)


def _repr_sorted_hardware(spec: AgentSpec | HostSpec) -> str:
    """The dataclass repr with `hardware` sorted: a frozenset's own repr follows PYTHONHASHSEED, and these
    reprs go into the simulators' traces, whose hashes must not depend on it."""
    parts = []
    for f in dataclasses.fields(spec):
        v = getattr(spec, f.name)
        if f.name in ("kind", "max_per_host", "placed", "auction") and not v:
            continue  # left out when unset, so that the traces of schedules without limits keep their hashes
        parts.append(f"{f.name}={sorted(v) if f.name == 'hardware' else repr(v)}")
    return f"{type(spec).__name__}({', '.join(parts)})"


@dataclass(frozen=True, repr=False)
class HostSpec:
    """One host h of §4.7: processor capacity K_h (> 0) and available hardware H_h. A `draining` host (leaving
    gracefully) takes part in the session but bids for nothing."""

    name: str
    capacity: float
    hardware: frozenset[str] = frozenset()
    draining: bool = False

    def __post_init__(self) -> None:
        _name(self.name, "HostSpec.name")
        object.__setattr__(
            self, "capacity", _finite(self.capacity, f"HostSpec({self.name}).capacity", MIN_CAPACITY, MAX_CAPACITY)
        )
        hw = frozenset(self.hardware)
        for h in hw:
            _name(h, f"HostSpec({self.name}).hardware item")
        object.__setattr__(self, "hardware", hw)

    def can_run(self, agent: AgentSpec) -> bool:
        """Q_i subset of H_h, and not draining."""
        return not self.draining and agent.hardware <= self.hardware

    def __repr__(self) -> str:
        return _repr_sorted_hardware(self)


@dataclass(frozen=True)
class SessionStart:
    """The payload of OAC(start, p, sesId, sesGroup, sesAgents, sesCosts, sesAffinity) (Alg. 4 l. 26); the
    agents carry costs, affinities, hardware and transfer penalties, the hosts capacities and hardware."""

    leader: str
    ses_id: int
    group: tuple[str, ...]
    agents: tuple[AgentSpec, ...]
    hosts: tuple[HostSpec, ...]
    #: the agents this session auctions (`choose_auction`); None: all of them (the thesis' session). The others
    #: keep the host they are `pinned` to, or wait for the next session (`deferred`)
    auction: tuple[str, ...] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "group", tuple(self.group))
        object.__setattr__(self, "agents", tuple(self.agents))
        object.__setattr__(self, "hosts", tuple(self.hosts))
        if isinstance(self.ses_id, bool) or not isinstance(self.ses_id, int) or self.ses_id < 1:
            raise ValueError(f"SessionStart.ses_id: must be an integer >= 1, got {self.ses_id!r}")
        if not self.group:
            raise ValueError("SessionStart.group: must not be empty")
        for g in self.group:
            _name(g, "SessionStart.group member")
        if len(set(self.group)) != len(self.group):
            raise ValueError(f"SessionStart.group: duplicate host in {list(self.group)}")
        if self.leader != self.group[0]:
            raise ValueError(f"SessionStart.leader: must be group[0] ({self.group[0]!r}), got {self.leader!r}")
        ids = [a.id for a in self.agents]
        if len(set(ids)) != len(ids):
            raise ValueError("SessionStart.agents: duplicate agent id")
        names = {h.name for h in self.hosts}
        if len(names) != len(self.hosts):
            raise ValueError("SessionStart.hosts: duplicate host")
        missing = [g for g in self.group if g not in names]
        if missing:
            raise ValueError(f"SessionStart.hosts: no HostSpec for group member(s) {missing}")
        why = limit_conflict(self.agents)
        if why:
            raise ValueError(f"SessionStart.agents: {why}")
        if self.auction is not None:
            object.__setattr__(self, "auction", tuple(self.auction))
            known = set(ids)
            if len(set(self.auction)) != len(self.auction):
                raise ValueError("SessionStart.auction: duplicate agent id")
            stray = [a for a in self.auction if a not in known]
            if stray:
                raise ValueError(f"SessionStart.auction: agent(s) {stray[:3]} not in the session's agents")

    @property
    def agent_ids(self) -> tuple[str, ...]:
        return tuple(a.id for a in self.agents)

    def host(self, name: str) -> HostSpec:
        for h in self.hosts:
            if h.name == name:
                return h
        raise KeyError(name)

    def unallocatable(self) -> tuple[str, ...]:
        """Agents no host of the group can run (hardware, draining), and agents of a limited kind beyond the
        kind's places in the group (`max_per_host` x capable members): left out of the allocation. Depends only
        on the start, so every host computes the same list."""
        hs = [self.host(g) for g in self.group]
        out = {a.id for a in self.agents if not any(h.can_run(a) for h in hs)}
        out.update(over_limit(self.agents, hs, out))
        return tuple(a.id for a in self.agents if a.id in out)

    def pinned(self) -> dict[str, str]:
        """Agents outside the `auction` that keep their `home` host this session (a member that can run them),
        in the start's agent order. Empty when the session auctions every agent."""
        if self.auction is None:
            return {}
        inside = set(self.auction)
        hs = {g: self.host(g) for g in self.group}
        gone = set(self.unallocatable())
        out: dict[str, str] = {}
        for a in self.agents:
            h = a.home
            if a.id not in inside and a.id not in gone and h in hs and hs[h].can_run(a):
                out[a.id] = h
        return out

    def deferred(self) -> tuple[str, ...]:
        """Agents that need a place but did not fit in this session's `auction`: the next session's."""
        if self.auction is None:
            return ()
        skip = set(self.auction) | set(self.pinned()) | set(self.unallocatable())
        return tuple(a.id for a in self.agents if a.id not in skip)


def choose_auction(
    agents: tuple[AgentSpec, ...], group: tuple[str, ...], hosts: Mapping[str, HostSpec], ses_id: int,
    size: int = MAX_SESSION_AGENTS,
) -> tuple[str, ...] | None:
    """The agents a session of `ses_id` auctions (docs/allocation.md, "Sessions of a bounded size"): None (all)
    when there are at most `size`; else every agent of a limited kind (their places are counted per session),
    then the agents that need a place (no home, or a home that is not a member or cannot run them), then, to fill
    `size`, placed agents taken in turn from a position that advances with the session id, so that successive
    load-balancing sessions reach every agent. A deterministic function of its arguments."""
    if len(agents) <= size:
        return None
    members = {g: hosts[g] for g in group if g in hosts}
    limited = [a.id for a in agents if a.max_per_host]
    needy: list[str] = []
    placed: list[str] = []
    for a in agents:
        if a.max_per_host or not any(h.can_run(a) for h in members.values()):
            continue  # limited: always in; no capable member: unallocatable, and must not take a needy one's room
        h = a.home
        if h is None or h not in members or not members[h].can_run(a):
            needy.append(a.id)
        else:
            placed.append(a.id)
    # at least half a window for the agents that need a place, however many limited ones there are: every
    # session then places some, and a chain of sessions ends
    room = max(size - len(limited), (size + 1) // 2)
    chosen = needy[:room]
    room -= len(chosen)
    if room and placed:
        first = (ses_id * room) % len(placed)
        chosen += (placed[first:] + placed[:first])[:room]
    inside = set(limited) | set(chosen)
    return tuple(a.id for a in agents if a.id in inside)


def limit_conflict(agents: Iterable[AgentSpec]) -> str:
    """'' when the agents of every limited kind agree on the limit and the hardware, else the reason. With the
    same hardware every agent of a kind has the same capable hosts, so `max_per_host` x their number places
    are all there is to count, and any greedy auction fills them (issue 15, docs/allocation.md)."""
    first: dict[str, AgentSpec] = {}
    for a in agents:
        if not a.kind:
            continue
        f = first.setdefault(a.kind, a)
        if f.max_per_host != a.max_per_host or (a.max_per_host and f.hardware != a.hardware):
            return (
                f"agents {f.id} and {a.id} of kind {a.kind!r} declare different per-host limits or hardware "
                f"({f.max_per_host}, {sorted(f.hardware)} / {a.max_per_host}, {sorted(a.hardware)})"
            )
    return ""


def over_limit(agents: Iterable[AgentSpec], hosts: Iterable[HostSpec], skip: Iterable[str] = ()) -> list[str]:
    """The agents of limited kinds that find no place: a kind has `max_per_host` places on every host that can
    run it (hardware, not draining). Agents already running on a capable host keep their place first (at most
    `max_per_host` per host, so a rebalance never evicts a running agent for a new one), then the others in the
    session's agent order. `skip`: agents already unallocatable."""
    hs = list(hosts)
    gone = set(skip)
    kinds: dict[str, list[AgentSpec]] = {}
    for a in agents:
        if a.max_per_host and a.id not in gone:
            kinds.setdefault(a.kind, []).append(a)
    out: list[str] = []
    for members in kinds.values():
        limit = members[0].max_per_host
        capable = {h.name for h in hs if h.can_run(members[0])}
        places = limit * len(capable)
        if len(members) <= places:
            continue
        seated: dict[str, int] = {}
        first: list[AgentSpec] = []
        rest: list[AgentSpec] = []
        for a in members:
            h = a.current_host
            if h is not None and h in capable and seated.get(h, 0) < limit:
                seated[h] = seated.get(h, 0) + 1
                first.append(a)
            else:
                rest.append(a)
        out += [a.id for a in (first + rest)[places:]]
    return out
