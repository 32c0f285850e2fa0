"""Agent allocation HAA-AA (thesis §4.7, Appendix II Alg. 4), as a sans-I/O state machine.

One `Allocator` per host. The host feeds it, in this order of concern:

* `on_change(group, agents, hosts)`: the host group or the agent list changed, or the `RebalancePolicy`
  says a periodic load-balancing session is due (Alg. 4 l. 17). Only the undisputed leader (`group[0]`)
  starts a session: it emits `ProposeStart(SessionStart)` for the host to commit as OAC(start) (ll. 18-28).
* committed OAC transactions, in the OAC total order: `on_start_committed` (ll. 38-50) and
  `on_finish_committed` (ll. 93-96); and the OAC outcome of its own proposals, `on_start_decided` /
  `on_finish_decided`, to retry an aborted one while the situation is unchanged (ll. 25-28, 89-92);
* bid updates from peers (`on_update`, ll. 59-76) over reliable FIFO channels, followed by `end_of_inbox`
  once the host has handed over everything currently queued (ll. 77-81: the queued build / distribute).

It answers with effects (`drain()`): `SendUpdate` (a `BidUpdate` to the other session members), `ProposeStart`,
`ProposeFinish`, `Allocated` (a committed allocation this host accepts) and `Log`.

The algorithm is CBBA (Choi, Brunet, How 2009) in its asynchronous form (Johnson, Ponda, Choi, How 2010,
thesis ref. [69]) applied to processor usage instead of time: each host greedily builds a bundle of agents
(`_build`, "HAA-AA Bundle Building Strategy"), bids are compared by a total order (`bid_gt`, "HAA-AA Bid
Comparison Operator", Fig. II-1 reconstructed), and conflicting bids are resolved by the 34 rows of Table 4.7-1
(`resolve`). The leader checks consensus on its bid table (l. 86-88) and commits the result with OAC(finish).

Where the thesis is silent, garbled or the figure is missing, the choices are documented in docs/allocation.md.
In short:

* bid order (Fig. II-1): a bid within capacity (support > 0) beats one over it; within capacity higher reward,
  then higher support; over capacity higher support (the less overloaded host; eq. 4.7-3 rewards it with
  s = support), then higher reward; then the lower host name. The nil bid is below every bid.
* bundle building: single agents and clusters of affine agents; a bid's reward is its marginal gain in
  R(b_h); capacity is reserved for agents only this host can run; bids are warped so that a later bid of a
  bundle never beats an earlier one (diminishing marginal gains, which affinity bonuses break).
* trim (rows 1, 17) resets the bids of the agents removed after the lost one to nil and broadcasts them.
* rounds: a build always bids in a round no other bid of this host used (l. 53-55 generalised); consensus
  compares winners and values, not rounds.
* damping of the asynchronous rules (the verifier found message storms): resets of rows 10, 11, 28, 29 are
  skipped while the bid's owner still claims it; a new bid must beat every claim members made for themselves;
  a rebroadcast of an unchanged bid goes only to the stale sender, and only from the authority on that bid.
* consensus is not checked while a build is queued (l. 75-76 would decide before the queued build).
* a committed start is valid if its proposer is the leader, group and agent list are current (ll. 39-40) and
  its id is above every committed start id; a committed finish is accepted only for the last valid start,
  unchanged since (l. 94 accepts unconditionally). Both depend only on the total order.
* hardware: a host bids only for agents whose hardware it has; agents no host of the group can run are
  reported as `unallocatable` and left out of the consensus check (otherwise the session never ends).
* per-host limits (issue 15, not in the thesis): a host bids for at most `max_per_host` agents of a limited
  kind; the agents of a kind beyond its places in the group are unallocatable like a hardware mismatch.
* hysteresis (a join moved agents twice): a bid for an agent that runs on another host counts a transfer
  penalty of at least `MIN_TRANSFER_PENALTY` in its reward and, past the bidder's capacity, `HYSTERESIS` off
  its support; an agent that runs nowhere has transfer factor 1 on every host (eq. 4.7-2 read for agents
  that no allocation transfers).

The class does no I/O, reads no clock and uses no randomness; iteration orders are those of its inputs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple, cast

from haa.core.effects import Log

INF = math.inf

#: Bounds on the problem data (docs/limits.md, "Agent and host numbers"). Costs and capacities are in units of
#: one host's processor (K_h = 1.0 by default): no agent declares more than MAX_COST of them and no host more than
#: MAX_CAPACITY, and a capacity is at least MIN_CAPACITY. Within these bounds every sum and ratio the bundle
#: building computes (eq. 4.7-1 to 4.7-3, over at most a few thousand agents) stays finite, so comparisons of
#: bids never meet inf or NaN; `haa.core.agenttable` refuses transactions outside them before they apply.
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
        if f.name in ("kind", "max_per_host") and not v:
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


class Bid(NamedTuple):
    """One entry of bidTable_p: {j, z_j (winner; None = none), y_j = {reward, support}, r_j (round)}."""

    agent: str
    winner: str | None
    reward: float
    support: float
    round: int


_NILS: dict[str, Bid] = {}


def nil_bid(agent: str) -> Bid:
    """Table 4.7-1 "reset": {j, none, {0, -inf}, 0}."""
    b = _NILS.get(agent)
    if b is None:
        b = Bid(agent, None, 0.0, -INF, 0)
        if len(_NILS) < 100_000:
            _NILS[agent] = b
    return b


@dataclass(frozen=True)
class BidUpdate:
    """(update, q, sesId_q, for each updated bid j: {j, z_qj, y_qj, r_qj}) (Alg. 4 l. 59, l. 84)."""

    ses_id: int
    bids: tuple[Bid, ...]
    sender: str = ""


# --------------------------------------------------------------------------------------------- effects


@dataclass(slots=True)
class SendUpdate:
    """Send `update` to every host in `dsts` (l. 84; never to oneself)."""

    dsts: tuple[str, ...]
    update: BidUpdate


@dataclass(slots=True)
class ProposeStart:
    """Commit OAC(start, ...) with this payload among the group (l. 26); report with `on_start_decided`."""

    start: SessionStart


@dataclass(slots=True)
class ProposeFinish:
    """Commit OAC(finish, p, sesId_p, bidTable_p[p]) (l. 90); report with `on_finish_decided`."""

    ses_id: int
    allocation: dict[str, str]
    leader: str = ""
    unallocatable: tuple[str, ...] = ()


@dataclass(slots=True)
class Allocated:
    """A committed allocation this host accepts (l. 94): agent -> host. Every host that accepts session
    `ses_id` accepts the same map; `unallocatable` agents have no capable host in the group."""

    ses_id: int
    allocation: dict[str, str]
    unallocatable: tuple[str, ...] = ()


AllocEffect = SendUpdate | ProposeStart | ProposeFinish | Allocated | Log


# --------------------------------------------------------------------------------------------- bid order


def bid_key(b: Bid) -> tuple[int, float, float]:
    """The value part of the order (Fig. II-1 as reconstructed, docs/allocation.md): class 1 = within
    capacity (support > 0) ranked by (reward, support); class 0 = over capacity ranked by (support, reward);
    class -1 = the nil bid."""
    if b.winner is None:
        return (-1, 0.0, 0.0)
    if b.support > 0.0:
        return (1, b.reward, b.support)
    return (0, b.support, b.reward)


def bid_gt(a: Bid, b: Bid) -> bool:
    """a > b: the bid comparison operator, a strict total order on (values, winner). Equal values are
    broken by the lower host name (Appendix II: "ties can be broken by taking the bidder with the lower ID");
    two nil bids are equal. (`bid_key` spelled out, for speed.)"""
    _ja, wa, ra, sa, _ra = a
    _jb, wb, rb, sb, _rb = b
    if wa is None:
        return False
    if wb is None:
        return True
    fa = sa > 0.0
    if fa != (sb > 0.0):
        return fa
    if fa:
        if ra != rb:
            return ra > rb
        if sa != sb:
            return sa > sb
    else:
        if sa != sb:
            return sa > sb
        if ra != rb:
            return ra > rb
    return wa < wb


def _vals_key(reward: float, support: float) -> tuple[int, float, float]:
    """`bid_key` of a bid with a winner."""
    return (1, reward, support) if support > 0.0 else (0, support, reward)


def _beats(reward: float, support: float, me: str, t: Bid) -> bool:
    """bid_gt(Bid(j, me, reward, support, r), t), without building the bid."""
    tw = t[1]
    if tw is None:
        return True
    tr, ts = t[2], t[3]
    f = support > 0.0
    if f != (ts > 0.0):
        return f
    if f:
        if reward != tr:
            return reward > tr
        if support != ts:
            return support > ts
    else:
        if support != ts:
            return support > ts
        if reward != tr:
            return reward > tr
    return me < tw


def same_bid(a: Bid, b: Bid) -> bool:
    """Equal winner and value: the same bid, possibly confirmed in different rounds. Consensus (l. 87) and
    the "already sent" test compare bids this way; rounds only order information in Table 4.7-1."""
    return a[1] == b[1] and a[2] == b[2] and a[3] == b[3]


# --------------------------------------------------------------------------------------------- Table 4.7-1

LEAVE = "leave"
UPDATE = "update"
RESET = "reset"
TRIM_UPDATE = "trim & update"
UPDATE_TIME = "update time"


#: the resets of Table 4.7-1 driven by round comparisons with a third host's bid
_GUARDED_RESETS = frozenset({10, 11, 28, 29})


class Rule(NamedTuple):
    row: int
    action: str
    broadcast: bool


def resolve(p: str, q: str, sb: Bid, rb: Bid) -> Rule:
    """Table 4.7-1: receiver p's action on sender q's bid `sb` for agent j, p holding `rb` (bidTable_p[p][j]).

    y comparisons use `bid_gt` (values, then the lower winner name), so rows 2 and 18 (equal y, lower z) are
    part of rows 1 and 17. r is the round of each bid. Default: leave & broadcast (the thesis' header)."""
    zq, zp = sb.winner, rb.winner
    rq, rp = sb.round, rb.round
    if zq == q:  # sender thinks it wins (rows 1-12)
        if zp == p:
            if bid_gt(sb, rb):
                return Rule(1, TRIM_UPDATE, True)
            return Rule(3, UPDATE_TIME, True)
        if zp == q:
            if rq > rp:
                return Rule(4, UPDATE, True)
            return Rule(5 if rq == rp else 6, LEAVE, False)
        if zp is None:
            return Rule(12, UPDATE, True)
        return _third_party(sb, rb, 7)
    if zq == p:  # sender thinks the receiver wins (rows 13-16)
        if zp == p:
            if rq == rp:
                return Rule(13, LEAVE, False)
            return Rule(13, LEAVE, True)
        if zp == q:
            return Rule(14, RESET, True)
        if zp is None:
            return Rule(16, LEAVE, True)
        return Rule(15, LEAVE, True)
    if zq is None:  # sender has no winner (rows 31-34)
        if zp == p:
            return Rule(31, LEAVE, True)
        if zp == q:
            return Rule(32, UPDATE, True)
        if zp is None:
            return Rule(34, LEAVE, False)
        if rq > rp:
            return Rule(33, UPDATE, True)
        return Rule(33, LEAVE, True)
    # sender thinks a third host m wins (rows 17-30)
    if zp == p:
        if bid_gt(sb, rb):
            return Rule(17, TRIM_UPDATE, True)
        return Rule(19, UPDATE_TIME, True)
    if zp == q:
        if rq >= rp:
            return Rule(20, UPDATE, True)
        return Rule(21, RESET, True)
    if zp == zq:
        if rq > rp:
            return Rule(22, UPDATE, True)
        return Rule(23 if rq == rp else 24, LEAVE, False)
    if zp is None:
        return Rule(30, UPDATE, True)
    return _third_party(sb, rb, 25)


def _third_party(sb: Bid, rb: Bid, base: int) -> Rule:
    """Rows 7-11 (sender q thinks q, receiver thinks m) and 25-29 (sender thinks m, receiver thinks n)."""
    gt, lt = bid_gt(sb, rb), bid_gt(rb, sb)
    rq, rp = sb.round, rb.round
    if gt and rq >= rp:
        return Rule(base, UPDATE, True)
    if lt and rq <= rp:
        return Rule(base + 1, LEAVE, True)
    if not gt and not lt:
        return Rule(base + 2, LEAVE, True)
    return Rule(base + 3 if lt else base + 4, RESET, True)


# --------------------------------------------------------------------------------------------- rewards


def transfer_factor(agent: AgentSpec, host: str) -> float:
    """eq. 4.7-2: 1 on the current host (a_i in L_h), (1 - t_i) elsewhere. An agent that runs nowhere (new,
    crashed, or frozen in a transfer) is transferred by no allocation: 1 everywhere. Read literally, eq. 4.7-2
    gave it 1 - t_i on every host, so the session that placed it ranked it below what the next session did
    once it ran (t_i = 1: reward 0, placed last, over capacity) and that session moved agents again
    (docs/allocation.md, "Joins and hysteresis")."""
    h = agent.current_host
    return 1.0 if h is None or h == host else 1.0 - agent.transfer_penalty


def agent_reward(agent: AgentSpec, host: str, bundle: Iterable[str]) -> float:
    """r(a_i), eq. 4.7-2: (c_i + sum of alpha_ij over a_j in the bundle) x the transfer factor."""
    aff = agent.affinity
    bonus = sum(aff.get(j, 0.0) for j in bundle if j != agent.id)
    return (agent.cost + bonus) * transfer_factor(agent, host)


def bundle_reward(order: list[AgentSpec], host: HostSpec) -> float:
    """R(b_h), eq. 4.7-1 for one bundle order: r(a_i) while the running cost stays below K_h, then the
    penalty s(a_i) = (K_h - running cost) / K_h (eq. 4.7-3)."""
    ids = [a.id for a in order]
    k = host.capacity
    total = 0.0
    used = 0.0
    for a in order:
        used += a.cost
        total += agent_reward(a, host.name, ids) if used < k else (k - used) / k
    return total


# --------------------------------------------------------------------------------------------- the session


class _Entry(NamedTuple):
    agents: tuple[str, ...]
    reward: float
    support: float


class _Cluster(NamedTuple):
    agents: tuple[str, ...]
    cost: float  # of the members not already reserved
    inner: tuple[float, ...]  # per member: sum of its affinities with the other members


class _Session:
    """The per-session state of Alg. 4 ll. 3-16 (sesId, bidTable, outbox, bundle, r, flags)."""

    def __init__(self, ses_id: int, me: str) -> None:
        self.ses_id = ses_id
        self.me = me
        self.start: SessionStart | None = None
        self.ready = False  # sesReady_p
        self.decided = False  # decided_p
        self.build_queued = False
        self.distribute_queued = False
        self.r = 0  # r_p
        self.round_used = -1  # lastBuildRound_p, and rounds used by "update time"
        self.own: dict[str, Bid] = {}  # bidTable_p[p]
        self.rows: dict[str, dict[str, Bid]] = {}  # bidTable_p[q] for q != p
        self.outbox: dict[str, Bid] = {}
        self.replies: dict[str, dict[str, Bid]] = {}  # q -> bids only q needs (Allocator._broadcast)
        self.sent: dict[str, Bid] = {}  # the bid of each agent this host last sent to every member
        self.bundle: list[_Entry] = []
        self.entry_of: dict[str, int] = {}
        # known once ready
        self.group: tuple[str, ...] = ()
        self.others: tuple[str, ...] = ()
        self.agents: dict[str, AgentSpec] = {}
        self.allocatable: frozenset[str] = frozenset()
        self.unallocatable: tuple[str, ...] = ()
        self.spec: HostSpec | None = None
        self.eligible: tuple[str, ...] = ()
        self.exclusive: frozenset[str] = frozenset()
        self.limits: dict[str, tuple[str, int]] = {}  # agent -> (kind, max_per_host), limited eligible agents
        self.rev: dict[str, list[tuple[str, float]]] = {}  # j -> [(i, alpha_ij)]: who gains from j
        self.nbrs: dict[str, tuple[str, ...]] = {}  # affinity (either way) among eligible agents
        self.clusters: list[_Cluster] | None = None  # enumerated at the first build
        self.mismatch = 0  # (q, j) with bidTable_p[q][j] != bidTable_p[p][j]
        self.unclaimed = 0  # allocatable j with bidTable_p[p][j].z == none
        self.messages_sent = 0
        self.builds = 0

    def bid(self, j: str) -> Bid:
        b = self.own.get(j)
        return b if b is not None else nil_bid(j)

    def row_bid(self, q: str, j: str) -> Bid:
        b = self.rows.get(q, {}).get(j)
        return b if b is not None else nil_bid(j)

    # --- table maintenance (incremental consensus bookkeeping)

    def set_own(self, j: str, b: Bid) -> None:
        old = self.bid(j)
        if old == b:
            return
        self.own[j] = b
        if not self.ready:
            return
        if j in self.allocatable:
            self.unclaimed += (b.winner is None) - (old.winner is None)
        if same_bid(old, b):
            return
        for q in self.others:
            t = self.row_bid(q, j)
            self.mismatch += (not same_bid(t, b)) - (not same_bid(t, old))

    def set_row(self, q: str, j: str, b: Bid) -> None:
        row = self.rows.get(q)
        if row is None:
            row = self.rows[q] = {}
        old = row.get(j)
        if old is None:
            old = nil_bid(j)
        row[j] = b
        if self.ready and not same_bid(old, b):
            own = self.bid(j)
            self.mismatch += (not same_bid(b, own)) - (not same_bid(old, own))

    def make_ready(self, start: SessionStart, me: str) -> None:
        """ll. 45-49: take the session's parameters; drop what does not belong to it."""
        self.start = start
        self.group = start.group
        self.others = tuple(h for h in start.group if h != me)
        self.agents = {a.id: a for a in start.agents}
        self.spec = start.host(me) if me in start.group else None
        self.unallocatable = start.unallocatable()
        self.allocatable = frozenset(self.agents) - frozenset(self.unallocatable)
        spec = self.spec
        unalloc = frozenset(self.unallocatable)  # an agent left out for its kind's limit gets no bid either
        self.eligible = tuple(
            a.id for a in start.agents if spec is not None and spec.can_run(a) and a.id not in unalloc
        )
        # per-host limits (issue 15): eligible agent -> (kind, max_per_host)
        self.limits = {a.id: (a.kind, a.max_per_host) for a in start.agents if a.max_per_host and a.id in self.eligible}
        hosts = [start.host(g) for g in start.group]
        self.exclusive = frozenset(  # agents only this host of the group can run
            a.id for a in start.agents if a.id in self.eligible and sum(h.can_run(a) for h in hosts) == 1
        )
        rev: dict[str, list[tuple[str, float]]] = {}
        for a in start.agents:
            for j, alpha in a.affinity.items():
                if alpha > 0.0 and j in self.agents:
                    rev.setdefault(j, []).append((a.id, alpha))
        self.rev = rev
        el = set(self.eligible)
        self.nbrs = {
            i: tuple(
                j
                for j in self.eligible
                if j != i and self.agents[i].affinity.get(j, 0.0) + self.agents[j].affinity.get(i, 0.0) > 0.0
            )
            for i in self.eligible
            if i in el
        }
        known = self.agents
        self.own = {j: b for j, b in self.own.items() if j in known and (b.winner is None or b.winner in self.group)}
        self.outbox = {j: b for j, b in self.outbox.items() if j in known}
        self.rows = {
            q: {j: b for j, b in row.items() if j in known} for q, row in self.rows.items() if q in self.others
        }
        self.ready = True
        self.unclaimed = sum(1 for j in self.allocatable if self.bid(j).winner is None)
        self.mismatch = sum(
            1 for q in self.others for j in self.agents if not same_bid(self.row_bid(q, j), self.bid(j))
        )


def _within_limits(cluster: tuple[str, ...], limits: Mapping[str, tuple[str, int]], held: Mapping[str, int]) -> bool:
    """A cluster bid keeps every limited kind within its per-host limit on top of the bundle's `held`."""
    add: dict[str, int] = {}
    for i in cluster:
        kl = limits.get(i)
        if kl is not None:
            n = add[kl[0]] = add.get(kl[0], 0) + 1
            if held.get(kl[0], 0) + n > kl[1]:
                return False
    return True


# --------------------------------------------------------------------------------------------- allocator


class Allocator:
    """Alg. 4 for host `me` (see the module docstring for the inputs and effects).

    `committed_ses` is the highest id of any committed OAC(start), valid or expired, when this host joins an
    existing group (part of the replicated state a new member receives, e.g. the agent table's `ses_id`); a
    fresh group starts at 0.
    """

    # The choices below are class attributes so that tests and docs/allocation.md can measure each of them.

    #: bids later in a bundle never beat earlier ones (`_build_bundle`); without it affinity-rich instances
    #: can fail to converge (tests/test_allocation_verify.py)
    WARP = True
    #: largest cluster of affine agents bid for as one (Appendix II, bundle building step 2)
    MAX_CLUSTER = 4
    #: cluster candidates examined per bundle step (bounds the work on dense affinity graphs)
    MAX_CLUSTERS = 64
    #: a bid's reward is the bundle's marginal gain in R(b_h): it also counts the affinity bonus alpha_ji the
    #: agents already in the bundle gain from the new agent i (docs/allocation.md, "rewards")
    BACK_AFFINITY = True
    #: the support of our bids counts the cost of the agents only we can run as used, before they are in
    #: the bundle, so that we do not fill up with agents others could take (docs/allocation.md, "rewards")
    RESERVE = True
    #: hysteresis, within capacity: a bid for an agent that runs on another host counts at least this transfer
    #: penalty in its reward (eq. 4.7-2's 1 - t_i), so that the host running it wins a tie of rewards. Most agent
    #: types declare t_i = 0, and then the support (the bundle position) decided, so every session moved agents
    #: for nothing (docs/allocation.md, "Joins and hysteresis"). Not for agents of a limited kind: with per-host
    #: limits, transfer penalties can keep a released bid circulating for ever (a gap of the conflict rules
    #: left open, docs/allocation.md "Known gaps"), and those kinds keep their declared t_i. 0 turns it off.
    MIN_TRANSFER_PENALTY = 0.05
    #: hysteresis, over capacity: a bid past the bidder's capacity for an agent that runs on another host has its
    #: support lowered by this share of the bidder's capacity. Over capacity support decides (eq. 4.7-3 has no
    #: transfer penalty), so an agent moves from one overloaded host to another only if it ends up less
    #: overloaded by more than this. Within capacity the reward decides (MIN_TRANSFER_PENALTY). 0 turns it off.
    HYSTERESIS = 0.1

    def __init__(self, me: str, committed_ses: int = 0) -> None:
        self.me = _name(me, "Allocator.me")
        self.group: tuple[str, ...] = ()  # hostGroup
        self.agents: tuple[AgentSpec, ...] = ()  # agentList, with the current costs and affinities
        self.hosts: dict[str, HostSpec] = {}
        self.ses_id = committed_ses  # sesId_p: the newest session this host knows of
        self.committed_ses = committed_ses  # the highest id of any committed OAC(start), valid or expired
        self.committed_start: SessionStart | None = None
        self.finished_ses = 0  # the last accepted OAC(finish)
        self.session: _Session | None = None
        self._pending_start: SessionStart | None = None
        self._pending_finish: ProposeFinish | None = None
        self._out: list[AllocEffect] = []
        self.stats = {"updates_in": 0, "bids_in": 0, "updates_out": 0, "messages_out": 0, "builds": 0}

    # ------------------------------------------------------------------ queries

    def drain(self) -> list[AllocEffect]:
        out, self._out = self._out, []
        return out

    @property
    def member(self) -> bool:
        return self.me in self.group

    def own_bids(self) -> dict[str, Bid]:
        """bidTable_p[p] of the current session (empty when there is none)."""
        s = self.session
        return dict(s.own) if s is not None else {}

    def bundle(self) -> list[str]:
        s = self.session
        return [a for e in s.bundle for a in e.agents] if s is not None else []

    # ------------------------------------------------------------------ l. 17-28: initiation

    def on_change(
        self,
        group: tuple[str, ...],
        agents: tuple[AgentSpec, ...],
        hosts: Iterable[HostSpec],
        start: bool = True,
    ) -> None:
        """The host group or agent list changed, or a rebalance is due (l. 17). Records the new situation;
        if `start` and this host is the undisputed leader (l. 18), starts a new session (ll. 19-26).
        `hosts` must describe every member of `group`. With `start=False` (a rate-limited change) it only
        records, and the host calls again with `start=True` when its `RebalancePolicy` allows."""
        self.group = tuple(group)
        self.agents = tuple(agents)
        self.hosts = {h.name: h for h in hosts}
        if not self.member:
            if self.session is not None:
                self._log("alloc.left_group", ses=self.session.ses_id)
            self.session = None
            self._pending_start = self._pending_finish = None
            return
        if start and self.group[0] == self.me:
            missing = [g for g in self.group if g not in self.hosts]
            if missing:
                raise ValueError(f"Allocator.on_change: hosts: no HostSpec for group member(s) {missing}")
            ses = max(self.ses_id, self.committed_ses) + 1  # l. 19
            st = SessionStart(self.me, ses, self.group, self.agents, tuple(self.hosts[g] for g in self.group))
            self.ses_id = ses
            self.session = _Session(ses, self.me)  # l. 24 newSession()
            self._pending_start = st
            self._pending_finish = None
            self._log("alloc.propose_start", ses=ses, group=list(self.group), agents=len(self.agents))
            self._out.append(ProposeStart(st))

    def on_start_decided(
        self, start: SessionStart, committed: bool, group: tuple[str, ...], agents: Iterable[AgentSpec | str]
    ) -> None:
        """The OAC(start) this host proposed was decided (l. 27). Aborted: propose it again while this host
        is still the leader of that session and the group and agent list are unchanged (l. 28)."""
        if committed or self._pending_start is None or self._pending_start.ses_id != start.ses_id:
            return  # committed: kept pending until delivered (on_start_committed may have to retry it)
        ids = tuple(a if isinstance(a, str) else a.id for a in agents)
        if tuple(group) == start.group and ids == start.agent_ids and self.ses_id == start.ses_id:
            self._log("alloc.retry_start", ses=start.ses_id)
            self._out.append(ProposeStart(start))
        else:
            self._pending_start = None

    # ------------------------------------------------------------------ l. 38-50: start committed

    def start_valid(self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...]) -> str:
        """Why a committed OAC(start) is expired ("" = valid): ll. 39-40 plus increasing session ids. Depends
        only on totally ordered state, so every host decides the same."""
        if not group or start.leader != group[0]:
            return "proposer is not the leader"
        if start.group != tuple(group):
            return "group changed"
        if start.agent_ids != tuple(agent_ids):
            return "agent list changed"
        if start.ses_id <= self.committed_ses:
            return f"session id not above the last committed start ({self.committed_ses})"
        return ""

    def on_start_committed(self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...]) -> None:
        """OAC(start) committed (l. 38); `group` and `agent_ids` are this host's hostGroup and agentList at
        this point of the total order."""
        why = self.start_valid(start, tuple(group), tuple(agent_ids))
        # every committed start id is used up, even an expired one: the next leader proposes a higher one, and
        # a joiner that only knows the highest committed id decides like everyone else
        self.committed_ses = max(self.committed_ses, start.ses_id)
        mine = self._pending_start is not None and self._pending_start == start
        if mine:
            self._pending_start = None
        if why:  # l. 39-40 expired session
            self._log("alloc.start_expired", ses=start.ses_id, reason=why)
            if mine and "not above" in why and self.ses_id == start.ses_id:
                self._retry_with_new_id(start, tuple(group), tuple(agent_ids))
            return
        self.committed_start = start
        if self.me not in start.group:
            return
        if start.ses_id < self.ses_id:  # already joined a later session through its updates (l. 41)
            return
        if start.ses_id > self.ses_id or self.session is None or self.session.ses_id != start.ses_id:
            self.ses_id = start.ses_id  # ll. 42-44
            self.session = _Session(start.ses_id, self.me)
        s = self.session
        s.make_ready(start, self.me)  # ll. 45-49
        self._log("alloc.session", ses=s.ses_id, group=list(s.group), agents=len(s.agents))
        self._build(s)  # l. 50

    # ------------------------------------------------------------------ l. 59-76: bid updates

    def _retry_with_new_id(self, start: SessionStart, group: tuple[str, ...], agent_ids: tuple[str, ...]) -> None:
        """Our OAC(start) committed after another (expired) start with the same id, proposed by a former
        leader before we learned of it: propose the session again under a fresh id, if nothing else changed."""
        if group != start.group or agent_ids != start.agent_ids or not group or group[0] != self.me:
            return
        ses = max(self.ses_id, self.committed_ses) + 1
        st = SessionStart(self.me, ses, start.group, start.agents, start.hosts)
        self.ses_id = ses
        self.session = _Session(ses, self.me)
        self._pending_start = st
        self._log("alloc.propose_start", ses=ses, group=list(st.group), agents=len(st.agents), retry=True)
        self._out.append(ProposeStart(st))

    def on_update(self, src: str, upd: BidUpdate) -> None:
        """A bid update from `src` (l. 59). Conflicts are resolved now; the build and distribution this
        queues run at `end_of_inbox`."""
        self.stats["updates_in"] += 1
        if not self.member or src == self.me:
            return
        if upd.ses_id < self.ses_id:  # l. 60-61 old message
            return
        if upd.ses_id > self.ses_id:  # ll. 62-64 join the newer session
            self.ses_id = upd.ses_id
            self.session = _Session(upd.ses_id, self.me)
            self._pending_finish = None
        s = self.session
        if s is None:
            return
        if s.ready and src not in s.others:
            self._log("alloc.update_from_outsider", ses=s.ses_id, src=src)
            return
        for b in upd.bids:  # l. 65
            self.stats["bids_in"] += 1
            self._process_bid(s, src, b)
        if s.ready and (s.outbox or s.replies):  # l. 73-74
            s.distribute_queued = True
        if s.ready:  # l. 75-76
            self._check_consensus(s)

    def _process_bid(self, s: _Session, q: str, b: Bid) -> None:
        j, w, _reward, _support, rnd = b
        if s.ready and (j not in s.agents or (w is not None and w not in s.group)):
            return
        s.set_row(q, j, b)  # l. 66
        if rnd >= s.r:  # l. 67-68
            s.r = rnd + 1
        old = s.bid(j)  # l. 69
        rule = resolve(self.me, q, b, old)  # l. 70
        if rule.action == RESET and rule.row in _GUARDED_RESETS and self._owner_confirms(s, old):
            rule = Rule(rule.row, LEAVE, True)
        act = rule.action
        if act == LEAVE:
            if rule.broadcast:
                self._broadcast(s, q, j, self._broadcast_bid(s, j, b, act), b)
            return
        bundle_changed = False
        if act == UPDATE:
            s.set_own(j, b)
        elif act == TRIM_UPDATE:
            self._trim(s, j)
            s.set_own(j, b)
            bundle_changed = True
        elif act == RESET:
            s.set_own(j, nil_bid(j))
        elif act == UPDATE_TIME:
            s.set_own(j, old._replace(round=s.r))
            s.round_used = max(s.round_used, s.r)
        if rule.broadcast:
            self._broadcast(s, q, j, self._broadcast_bid(s, j, b, act), b)
        if bundle_changed or bid_gt(old, s.bid(j)):  # l. 71-72 (got worse), or our bundle shrank
            s.build_queued = True

    #: Table 4.7-1 "broadcast" to every member even when the bid is unchanged (the text as printed; for
    #: comparisons in docs/allocation.md only)
    LITERAL_BROADCAST = False

    #: rows 10, 11, 28, 29 reset when the sender's (lower or higher) bid is newer than the receiver's
    #: accepted bid of a third host m; the receiver keeps it if m's own last update still claims it
    OWNER_GUARD = True

    def _owner_confirms(self, s: _Session, held: Bid) -> bool:
        """The winner m of `held` claimed exactly this bid in its last update to us (bidTable_p[m][j]): with
        FIFO channels from every member, a newer round elsewhere cannot mean m gave it up (docs/allocation.md,
        "rounds")."""
        m = held.winner
        if not self.OWNER_GUARD or m is None or m == self.me:
            return False
        w = s.rows.get(m, {}).get(held.agent)
        return w is not None and w.winner == m and same_bid(w, held)

    def _broadcast_bid(self, s: _Session, j: str, sender_bid: Bid, action: str) -> Bid:
        """What "broadcast" puts in the outbox: bidTable_p[p][j], so a reset sends the receiver's nil bid (the
        thesis' change to [69])."""
        return s.bid(j)

    def _broadcast(self, s: _Session, q: str, j: str, b: Bid, sender_bid: Bid) -> None:
        """outbox_p[j] := b (l. 84 sends it to every member). When b is (`same_bid`) what this host last sent
        to every member, the rebroadcast is news only to q, whose view differs, and only when this host is
        the authority on it: b is our own claim, or q's bid names us as the winner. Every other member's
        bid reaches q from its owner, which replies to q itself (docs/allocation.md, "messages")."""
        if self.LITERAL_BROADCAST or j in s.outbox or not same_bid(s.sent.get(j, nil_bid(j)), b):
            s.outbox[j] = b
        elif b.winner == self.me or sender_bid.winner == self.me:
            s.replies.setdefault(q, {})[j] = b

    def _trim(self, s: _Session, j: str) -> None:
        """Rows 1 and 17: remove j's bundle entry (its cluster) and every later one; the other agents removed
        lose this host's bid (reset to nil, broadcast)."""
        k = s.entry_of.get(j)
        if k is None:
            return
        removed = s.bundle[k:]
        del s.bundle[k:]
        for e in removed:
            for a in e.agents:
                s.entry_of.pop(a, None)
                if a != j:
                    s.set_own(a, nil_bid(a))
                    s.outbox[a] = s.bid(a)

    def end_of_inbox(self) -> None:
        """ll. 77-81: every message currently in the inbox was processed."""
        s = self.session
        if s is None or not self.member:
            return
        if s.ready and s.build_queued:
            self._build(s)
        if s.distribute_queued:
            self._distribute(s)

    # ------------------------------------------------------------------ l. 51-58: bundle building

    def _build(self, s: _Session) -> None:
        s.build_queued = False  # l. 52
        if s.r <= s.round_used:  # l. 53-55 (a round no bid of ours used yet)
            s.r = s.round_used + 1
        s.round_used = s.r
        s.builds += 1
        self.stats["builds"] += 1
        self._build_bundle(s)  # l. 56
        self._distribute(s)  # l. 57
        self._check_consensus(s)  # l. 58

    def _build_bundle(self, s: _Session) -> None:
        """Appendix II "HAA-AA Bundle Building Strategy": greedily add the winning bid (single agent or
        cluster of affine agents) with the highest return until no winning bid is left.

        A candidate's reward is its marginal gain in R(b_h) (eq. 4.7-2 plus the bonus the bundle gains from
        it), its support eq. II-1 (with the capacity `RESERVE`d for agents only we can run). The highest
        candidate by `bid_key` wins the step; the bid it places is warped (`WARP`): a bid that would beat the
        previous bid of the bundle gets that bid's reward, so bids never increase along a bundle (diminishing
        marginal gains, the condition of CBBA's convergence proof that affinity bonuses break). A bid is
        winning if it beats `_to_beat`."""
        spec = s.spec
        if spec is None or not s.eligible:
            return
        me = self.me
        k = spec.capacity
        agents = s.agents
        # float sums run in a fixed order (the bundle's, then the session's agent order), never over a set:
        # the order of a set of strings changes with PYTHONHASHSEED, and so would the last bits of the sums,
        # the ties they break and the whole simulated schedule (a seed must reproduce its trace anywhere)
        in_bundle: set[str] = set(s.entry_of)
        used = sum(agents[a].cost for a in s.entry_of)
        if self.RESERVE:  # capacity kept for the agents no other member can run (docs/allocation.md)
            used += sum(agents[a].cost for a in s.eligible if a in s.exclusive and a not in in_bundle)
        # hysteresis (docs/allocation.md): for an agent that runs on another host, at least MIN_TRANSFER_PENALTY
        # in the reward and HYSTERESIS off the support; nothing for an agent that runs nowhere yet
        away = {i for i in s.eligible if agents[i].current_host not in (None, me)}
        # (not for agents of a limited kind: see MIN_TRANSFER_PENALTY)
        low = {i for i in away if not agents[i].max_per_host}
        stay = 1.0 - self.MIN_TRANSFER_PENALTY
        factor = {i: min(transfer_factor(agents[i], me), stay) if i in low else transfer_factor(agents[i], me)
                  for i in s.eligible}
        hyst = self.HYSTERESIS
        margin = {i: hyst if i in away else 0.0 for i in s.eligible}
        bonus: dict[str, float] = dict.fromkeys(s.eligible, 0.0)  # sum of alpha_ij over j in the bundle
        back: dict[str, float] = dict.fromkeys(s.eligible, 0.0)  # sum of alpha_ji x factor_j, j in the bundle
        for j in s.entry_of:
            self._add_bonus(s, j, bonus, back, factor)
        claims = self._claims(s)
        to_beat = {i: self._to_beat(s, i, claims) for i in s.eligible if i not in in_bundle}
        clusters = self._clusters(s, in_bundle)  # once per build; those that lose a member are skipped
        excl = s.exclusive if self.RESERVE else frozenset()
        warp = self.WARP
        # per-host limits (issue 15): agents of each limited kind in the bundle; a kind at its limit gets no
        # further bid from this host (a constraint on the bundle alone, like CBBA's bundle length L_t: it only
        # removes candidates, so marginal gains still diminish)
        limits = s.limits if self.PER_HOST_LIMIT else {}
        held: dict[str, int] = {}
        for a in in_bundle:
            kl = limits.get(a)
            if kl is not None:
                held[kl[0]] = held.get(kl[0], 0) + 1
        while True:
            prev = s.bundle[-1] if s.bundle and warp else None
            pkey = _vals_key(prev.reward, prev.support) if prev is not None else None
            prev_r, prev_s = (prev.reward, prev.support) if prev is not None else (0.0, 0.0)  # read iff pkey
            best: tuple[tuple[int, float, float], tuple[str, ...], float, float] | None = None
            for i in s.eligible:
                if i in in_bundle:
                    continue
                kl = limits.get(i)
                if kl is not None and held.get(kl[0], 0) >= kl[1]:
                    continue
                aspec = agents[i]
                reward = (aspec.cost + bonus[i]) * factor[i] + back[i]
                support = (k - used - (0.0 if i in excl else aspec.cost)) / k
                if support <= 0.0:  # over capacity: the margin (within it, the reward's decides)
                    support -= margin[i]
                key = _vals_key(reward, support)
                placed, placed_s = reward, support
                if pkey is not None and key > pkey:  # _warp, spelled out for speed
                    placed = min(reward, prev_r)
                    placed_s = min(support, prev_s)
                if not _beats(placed, placed_s, me, to_beat[i]):
                    continue
                if best is None or key > best[0]:
                    best = (key, (i,), placed, placed_s)
            for c in clusters:
                cl = c.agents
                if any(i in in_bundle for i in cl):
                    continue
                support = (k - used - c.cost) / k
                if support <= 0.0:  # the whole cluster must fit (so it carries no margin)
                    continue
                if limits and not _within_limits(cl, limits, held):
                    continue
                reward = 0.0
                for i, inner in zip(cl, c.inner, strict=True):
                    reward += (agents[i].cost + bonus[i] + inner) * factor[i] + back[i]
                key = _vals_key(reward, support)
                placed, placed_s = reward, support
                if pkey is not None and key > pkey:
                    placed = min(reward, prev_r)
                    placed_s = min(support, prev_s)
                if not all(_beats(placed, placed_s, me, to_beat[i]) for i in cl):
                    continue
                if best is None or key > best[0]:
                    best = (key, cl, placed, placed_s)
            if best is None:
                return
            _key, chosen, reward, support = best
            s.entry_of.update(dict.fromkeys(chosen, len(s.bundle)))
            s.bundle.append(_Entry(chosen, reward, support))
            for i in chosen:  # step 3c i-iii
                in_bundle.add(i)
                kl = limits.get(i)
                if kl is not None:
                    held[kl[0]] = held.get(kl[0], 0) + 1
                if i not in excl:
                    used += agents[i].cost
                self._add_bonus(s, i, bonus, back, factor)
                b = Bid(i, me, reward, support, s.r)
                s.set_own(i, b)
                s.outbox[i] = b

    #: a host bids for no more agents of a limited kind than its `max_per_host` (issue 15; off only in the
    #: verifier's deliberately broken variant `ignore-per-host-limit`)
    PER_HOST_LIMIT = True

    #: a winning bid must also beat every bid another member last claimed for itself (docs/allocation.md)
    BEAT_CLAIMS = True

    def _claims(self, s: _Session) -> dict[str, Bid]:
        """The best bid each agent is claimed with by another member for itself in its last update
        (bidTable_p[q][j] with z = q)."""
        out: dict[str, Bid] = {}
        if not self.BEAT_CLAIMS:
            return out
        for q in s.others:
            for j, b in s.rows.get(q, {}).items():
                if b.winner == q:
                    c = out.get(j)
                    if c is None or bid_gt(b, c):
                        out[j] = b
        return out

    def _to_beat(self, s: _Session, j: str, claims: dict[str, Bid]) -> Bid:
        """The bid a new bid of ours for j must beat: bidTable_p[p][j] (Appendix II step 3), and, damping the
        reset/re-bid cascades of the asynchronous rules, every bid bidTable_p[q][j] in which a member q
        claims j for itself in its last update (q's own word, so never stale by more than that update)."""
        best = s.bid(j)
        c = claims.get(j)
        if c is not None and bid_gt(c, best):
            return c
        return best

    def _add_bonus(
        self, s: _Session, j: str, bonus: dict[str, float], back: dict[str, float], factor: dict[str, float]
    ) -> None:
        """Agent j joined the bundle: every i with affinity alpha_ij gains it (eq. 4.7-2), and, since j's own
        reward r(a_j) gains alpha_ji once i joins, so does i's marginal gain (`BACK_AFFINITY`)."""
        for i, alpha in s.rev.get(j, ()):
            if i in bonus:
                bonus[i] += alpha
        if self.BACK_AFFINITY and j in factor:
            fj = factor[j]
            for i, alpha in s.agents[j].affinity.items():
                if i in back:
                    back[i] += alpha * fj

    def _clusters(self, s: _Session, in_bundle: set[str]) -> list[_Cluster]:
        """Appendix II step 2: connected sets (2..MAX_CLUSTER agents) of unbundled agents linked by affinity,
        grown recursively from each agent (enumerated once per session, in a deterministic order); at most
        MAX_CLUSTERS of those without a bundled member."""
        if self.MAX_CLUSTER < 2:
            return []
        if s.clusters is None:
            s.clusters = self._enumerate_clusters(s)
        out = []
        for c in s.clusters:
            if not any(i in in_bundle for i in c.agents):
                out.append(c)
                if len(out) >= self.MAX_CLUSTERS:
                    break
        return out

    def _enumerate_clusters(self, s: _Session) -> list[_Cluster]:
        pos = {a: n for n, a in enumerate(s.eligible)}
        found: list[tuple[str, ...]] = []
        seen: set[frozenset[str]] = set()
        limit = 4 * self.MAX_CLUSTERS

        def grow(members: list[str], frontier: list[str]) -> None:
            for n, c in enumerate(frontier):
                if len(found) >= limit:
                    return
                new = [*members, c]
                fs = frozenset(new)
                if fs in seen:
                    continue
                seen.add(fs)
                found.append(tuple(sorted(new, key=pos.__getitem__)))
                if len(new) < self.MAX_CLUSTER:
                    nxt = frontier[n + 1 :] + [
                        x for x in s.nbrs.get(c, ()) if pos[x] > pos[new[0]] and x not in fs and x not in frontier
                    ]
                    grow(new, nxt)

        for v in s.eligible:
            if s.nbrs.get(v):
                grow([v], [x for x in s.nbrs[v] if pos[x] > pos[v]])
        excl = s.exclusive if self.RESERVE else frozenset()
        out = []
        for cl in found:
            inner = tuple(sum(s.agents[i].affinity.get(j, 0.0) for j in cl if j != i) for i in cl)
            cost = sum(s.agents[i].cost for i in cl if i not in excl)
            out.append(_Cluster(cl, cost, inner))
        return out

    # ------------------------------------------------------------------ l. 82-92: distribute, consensus

    def _distribute(self, s: _Session) -> None:
        s.distribute_queued = False  # l. 83
        if not s.ready or not (s.outbox or s.replies):
            return
        everyone = tuple(q for q in s.others if q not in s.replies)
        if s.outbox and everyone:
            self._send(s, everyone, tuple(s.outbox.values()))  # l. 84
        for q in s.others:
            extra = s.replies.get(q)
            if extra:
                bids = {**s.outbox, **{j: b for j, b in extra.items() if j not in s.outbox}}
                self._send(s, (q,), tuple(bids.values()))
        s.sent.update(s.outbox)
        s.outbox = {}  # l. 85
        s.replies = {}

    def _send(self, s: _Session, dsts: tuple[str, ...], bids: tuple[Bid, ...]) -> None:
        self._out.append(SendUpdate(dsts, BidUpdate(s.ses_id, bids, self.me)))
        s.messages_sent += len(dsts)
        self.stats["updates_out"] += 1
        self.stats["messages_out"] += len(dsts)

    def _check_consensus(self, s: _Session) -> None:
        """l. 86-88: the leader decides once every allocatable agent is claimed and every member's last sent
        bids equal its own."""
        if not s.ready or s.decided or not s.group or s.group[0] != self.me:
            return
        if s.unclaimed or s.mismatch or s.build_queued:  # l. 75-76 would decide before the queued build
            return
        s.decided = True
        # every allocatable agent has a winner here (`s.unclaimed` is empty)
        alloc = cast("dict[str, str]", {j: s.own[j].winner for j in s.agents if j in s.allocatable})
        fin = ProposeFinish(s.ses_id, alloc, self.me, s.unallocatable)
        self._pending_finish = fin
        self._log("alloc.consensus", ses=s.ses_id, builds=s.builds, messages=s.messages_sent)
        self._out.append(fin)

    def on_finish_decided(self, ses_id: int, committed: bool) -> None:
        """The OAC(finish) this host proposed was decided (l. 91). Aborted: propose it again while the
        session is current and the group and agent list are unchanged (l. 92)."""
        fin = self._pending_finish
        if fin is None or fin.ses_id != ses_id:
            return
        if committed:
            self._pending_finish = None
            return
        s = self.session
        st = s.start if s is not None else None
        if (
            s is not None
            and st is not None
            and s.ses_id == ses_id
            and self.group == st.group
            and tuple(a.id for a in self.agents) == st.agent_ids
        ):
            self._log("alloc.retry_finish", ses=ses_id)
            self._out.append(fin)
        else:
            self._pending_finish = None

    # ------------------------------------------------------------------ l. 93-96: finish committed

    def finish_valid(self, ses_id: int, group: tuple[str, ...], agent_ids: tuple[str, ...]) -> str:
        """Why a committed OAC(finish) is not accepted ("" = accepted): it must finish the last committed
        start, which must not have expired since (group and agent list unchanged), and not be finished yet.
        Depends only on totally ordered state, so every host decides the same."""
        st = self.committed_start
        if st is None or ses_id != st.ses_id:
            return f"not the last valid session ({st.ses_id if st is not None else 0})"
        if ses_id <= self.finished_ses:
            return "session already finished"
        if st.group != tuple(group):
            return "group changed since the start"
        if st.agent_ids != tuple(agent_ids):
            return "agent list changed since the start"
        return ""

    def on_finish_committed(
        self,
        ses_id: int,
        allocation: Mapping[str, str],
        group: tuple[str, ...] | None = None,
        agent_ids: tuple[str, ...] | None = None,
    ) -> None:
        """OAC(finish) committed (l. 93). `group`/`agent_ids`: hostGroup and agentList at this point of the
        total order (default: as last given to `on_change`)."""
        g = tuple(group) if group is not None else self.group
        ids = tuple(agent_ids) if agent_ids is not None else tuple(a.id for a in self.agents)
        why = self.finish_valid(ses_id, g, ids)
        if why:
            self._log("alloc.finish_ignored", ses=ses_id, reason=why)
            return
        self.finished_ses = ses_id
        st = self.committed_start
        unalloc = st.unallocatable() if st is not None else ()
        self._log("alloc.allocated", ses=ses_id, agents=len(allocation))
        self._out.append(Allocated(ses_id, dict(allocation), unalloc))  # l. 94
        s = self.session
        if s is not None and s.ses_id == ses_id:  # l. 95-96
            s.decided = True
        if self._pending_finish is not None and self._pending_finish.ses_id == ses_id:
            self._pending_finish = None

    # ------------------------------------------------------------------ helpers

    def _log(self, event: str, **fields: Any) -> None:
        self._out.append(Log(event, {"host": self.me, **fields}))


# --------------------------------------------------------------------------------------------- rebalancing


class RebalancePolicy:
    """When to start an allocation session (Alg. 4 l. 17 and §6.1: "every time a new agent is requested,
    whenever an agent or host fails, and at regular intervals in order to balance processing load").

    * `changed(now)`: the group or agent list changed. A session is due at once, but never sooner than
      `min_interval` after the previous one (rate limit: a burst of changes makes one session).
    * periodic load balance: every `period` seconds after the last start, unless paused by the operator
      (`pause()` / `resume()`) or a session is still running (at most `session_timeout`). Pausing stops only
      the periodic sessions: a change still needs one, or agents of a failed host would stay unallocated.
    * `due(now)` at `deadline()`: True when the host should call `Allocator.on_change(..., start=True)`.
    * `finished(now)`: the host accepted an allocation (`Allocated`).

    Sans-I/O: time is an argument; the host sets a timer for `deadline()`.
    """

    def __init__(self, period: float = 30.0, min_interval: float = 1.0, session_timeout: float = 10.0) -> None:
        self.period = _finite(period, "RebalancePolicy.period", 0.0, lo_open=True)
        self.min_interval = _finite(min_interval, "RebalancePolicy.min_interval", 0.0)
        self.session_timeout = _finite(session_timeout, "RebalancePolicy.session_timeout", 0.0, lo_open=True)
        self.paused = False
        self.pending = False
        self.running = False
        self.last_start = -INF
        self.starts = 0

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    def changed(self, now: float) -> bool:
        self.pending = True
        return self.due(now)

    def finished(self, now: float) -> None:
        self.running = False

    def force(self, now: float) -> None:
        """An operator asks for a session now: start one whatever the rate limit (counted like any start)."""
        self.pending = False
        self.running = True
        self.last_start = now
        self.starts += 1

    def deadline(self) -> float | None:
        if self.pending:
            return self.last_start + self.min_interval
        if self.paused:
            return None
        t = self.last_start + self.period
        if self.running:
            t = max(t, self.last_start + self.session_timeout)
        return t

    def due(self, now: float) -> bool:
        if self.pending:
            wait = now < self.last_start + self.min_interval
        else:  # periodic
            wait = self.paused or now < self.last_start + self.period
            wait = wait or (self.running and now < self.last_start + self.session_timeout)
        if wait:
            return False
        self.pending = False
        self.running = True
        self.last_start = now
        self.starts += 1
        return True
