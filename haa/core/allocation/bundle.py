"""Bundle building of agent allocation HAA-AA (thesis Appendix II, "HAA-AA Bundle Building Strategy"; Alg. 4 l. 56).

`BundleBuilder` is the part of the `Allocator` (`haa.core.allocation.allocation`, its subclass) that builds this
host's bundle: greedily add the winning bid — a single agent, or a cluster of affine agents — with the highest
return until no winning bid is left, then place the bids in the session's table and outbox. Its class
attributes are the choices docs/allocation.md measures (`WARP`, `MAX_CLUSTER`, `MAX_CLUSTERS`,
`BACK_AFFINITY`, `RESERVE`, `MIN_TRANSFER_PENALTY`, `HYSTERESIS`, `PER_HOST_LIMIT`, `BEAT_CLAIMS`); tests and
the verifier's broken variants set them on `Allocator`.

Pure: no I/O, no clock, no randomness; sums run in a fixed order (see `_build_bundle`).
"""

from __future__ import annotations

from collections.abc import Mapping

from haa.core.allocation.bids import Bid, _beats, _vals_key, bid_gt
from haa.core.allocation.rewards import transfer_factor
from haa.core.allocation.session import _Cluster, _Entry, _Session


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


class BundleBuilder:
    """Appendix II "HAA-AA Bundle Building Strategy" for host `me`: the bundle building of `Allocator`."""

    me: str

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
        used = s.base_used + sum(agents[a].cost for a in s.entry_of)  # the pinned agents' load first
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
        for j in s.pinned_mine:  # an agent pinned here gives the affinity bonus as one in the bundle would
            self._add_bonus(s, j, bonus, back, factor)
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
