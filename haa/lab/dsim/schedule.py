"""One seed, one scenario: swarm-style fault schedules and workloads for the cluster simulator.

`draw(seed, hosts, algorithm)` uses only `random.Random(seed)`. First it draws which fault *kinds* this
schedule enables (swarm testing: a schedule with pauses only explores different corners than one with
everything at once), then the network, the clocks, the faulty set, the faults and the workload:

* Fault phase [0, fault_end): crashes (some in the middle of a broadcast), pauses (resume, or the thesis'
  "unresponsive for a while, then shut down"), restarts as a new incarnation, delay spikes on channels and
  hosts that cause false suspicions, and — with the external failure-detector model — false suspicions
  injected directly. Only hosts of the faulty set F crash, restart or pause for long; |F| < n/2, and every
  transaction's participant set P keeps |P ∩ F| < |P|/2 (the f < n/2 of §4.5.1).
* Healing at `fault_end`: spikes end, paused hosts resume (or stay crashed), no new false suspicion.
* Then the run continues until OAC is quiescent (nothing open anywhere, nothing in flight) or `deadline`;
  liveness properties are checked at the end.

The external failure-detector model is adversarial within the properties OAC relies on: a crashed host is
suspected by everyone after a random delay and forever (completeness), correct hosts may be suspected
falsely at any time during the fault phase, and never after healing (eventual accuracy).
"""

from __future__ import annotations

import functools
import random
from dataclasses import dataclass, field
from typing import Any

from haa.core.host.hostcore import FD_EXTERNAL, FD_UFD, CoreConfig
from haa.core.ufd.qos import QosTargets
from haa.core.ufd.ufd import UfdConfig
from haa.lab.dsim.cluster import SimCluster
from haa.lab.dsim.network import DelayModel

#: Failure-detector QoS used in simulation: time is scaled down so that one schedule stays short.
SIM_QOS = QosTargets(td_upper=0.25, tmr_lower=600.0, tm_upper=0.25)
SIM_UFD = UfdConfig(
    qos=SIM_QOS,
    initial_period=0.02,
    reevaluate_every=20,
    window=100,
    worst_loss=0.01,
    worst_delay_std=0.02,
    min_delay_std=0.001,
    eta_min=0.005,
)
EXCLUDE_AFTER = 1.5


@dataclass
class Fault:
    time: float
    kind: str  # crash, crash_mid, pause, resume, restart, spike, false_suspicion
    host: str = ""
    other: str = ""
    duration: float = 0.0
    extra: DelayModel | None = None

    def describe(self) -> str:
        s = f"t={self.time:.3f} {self.kind} {self.host}"
        if self.other:
            s += f"->{self.other}"
        if self.duration:
            s += f" for {self.duration:.3f}s"
        if self.extra is not None:
            s += f" +{self.extra.describe()}"
        return s


@dataclass
class Scenario:
    seed: int
    algorithm: str
    names: list[str]
    fd_mode: str
    delay: DelayModel
    offsets: list[float]
    drifts: list[float]
    faulty: list[str]
    features: dict[str, bool]
    faults: list[Fault] = field(default_factory=list)
    proposals: list[tuple[float, str, list[str], bytes]] = field(default_factory=list)
    no_votes: set[tuple[bytes, str]] = field(default_factory=set)
    fault_end: float = 2.0
    deadline: float = 14.0
    exclude_after: float = EXCLUDE_AFTER
    detect_max: float = 0.15  # external FD model: crash suspected within this delay

    def core_config(self) -> CoreConfig:
        return CoreConfig(ufd=SIM_UFD, fd_mode=self.fd_mode, exclude_after=self.exclude_after)

    def describe(self) -> str:
        on = ",".join(k for k, v in sorted(self.features.items()) if v) or "none"
        return (
            f"seed={self.seed} hosts={len(self.names)} fd={self.fd_mode} delay={self.delay.describe()} "
            f"faulty={self.faulty} features={on} faults={len(self.faults)} txs={len(self.proposals)}"
        )


def _delay_model(rng: random.Random) -> DelayModel:
    kind = rng.choice(["uniform", "exp", "lognormal", "pareto"])
    base = rng.uniform(0.0001, 0.001)
    if kind == "uniform":
        return DelayModel("uniform", base, rng.uniform(0.0005, 0.01))
    if kind == "exp":
        return DelayModel("exp", base, rng.uniform(0.0005, 0.005))
    if kind == "lognormal":
        return DelayModel("lognormal", base, rng.uniform(0.0005, 0.003), rng.uniform(0.3, 0.9))
    return DelayModel("pareto", base, rng.uniform(0.0005, 0.004), rng.uniform(2.2, 3.5))


def _participants(rng: random.Random, names: list[str], proposer: str, faulty: set[str]) -> list[str]:
    """A participant set containing the proposer with fewer than half of it in F."""
    if rng.random() < 0.4:
        return list(names)
    for _ in range(20):
        k = rng.randint(2, len(names))
        others = rng.sample([n for n in names if n != proposer], k - 1)
        parts = [proposer, *others]
        bad = sum(1 for p in parts if p in faulty)
        if 2 * bad < len(parts):
            return parts
    return list(names)


#: share of the OAC schedules with instants at which every host proposes (see `draw`)
ALL_PROPOSING_SHARE = 0.3


def draw(seed: int, hosts: int, algorithm: str) -> Scenario:
    """Draw a whole scenario from `seed` (see the module docstring)."""
    if hosts < 2:
        raise ValueError("a scenario needs at least 2 hosts")
    rng = random.Random(seed)
    names = [f"h{i + 1}" for i in range(hosts)]
    if algorithm == "ufd":
        fd_mode = FD_UFD
    else:
        fd_mode = FD_UFD if rng.random() < 0.15 else FD_EXTERNAL
    feats = {
        "crash": rng.random() < 0.6,
        "crash_mid": rng.random() < 0.5,
        "pause": rng.random() < 0.5,
        "restart": rng.random() < 0.35,
        "spike": rng.random() < 0.5,
        "false_suspicion": fd_mode == FD_EXTERNAL and rng.random() < 0.6,
        "no_votes": algorithm == "oac" and rng.random() < 0.3,
        "bursts": rng.random() < 0.5,
        "drift": rng.random() < 0.5,
    }
    delay = _delay_model(rng)
    offsets = [rng.uniform(-1000.0, 1000.0) for _ in names]
    drifts = [rng.uniform(-1e-4, 1e-4) if feats["drift"] else 0.0 for _ in names]
    max_f = (hosts - 1) // 2
    any_fault = feats["crash"] or feats["pause"] or feats["restart"]
    f = rng.randint(1 if any_fault else 0, max_f) if any_fault and max_f else 0
    faulty = sorted(rng.sample(names, f))
    fault_end = 2.0
    sc = Scenario(
        seed=seed,
        algorithm=algorithm,
        names=names,
        fd_mode=fd_mode,
        delay=delay,
        offsets=offsets,
        drifts=drifts,
        faulty=faulty,
        features=feats,
        fault_end=fault_end,
    )
    correct = [n for n in names if n not in faulty]
    # --- faults of the faulty set
    for h in faulty:
        kinds = [k for k in ("crash", "pause", "restart") if feats[k]]
        kind = rng.choice(kinds)
        t = rng.uniform(0.05, fault_end * 0.9)
        if kind == "crash":
            mid = feats["crash_mid"] and rng.random() < 0.7
            sc.faults.append(Fault(t, "crash_mid" if mid else "crash", h))
        elif kind == "pause":
            if rng.random() < 0.5:  # the thesis' "unresponsive for a while, then shut down"
                d = rng.uniform(0.05, 1.0)
                sc.faults.append(Fault(t, "pause", h, duration=d))
                sc.faults.append(Fault(min(t + d, fault_end), "crash", h))
            else:  # long enough to be excluded, or not
                d = rng.uniform(0.05, 2.5)
                sc.faults.append(Fault(t, "pause", h, duration=d))
                sc.faults.append(Fault(min(t + d, fault_end), "resume", h))
        else:
            d = rng.uniform(0.05, 1.0)
            sc.faults.append(Fault(t, "crash_mid" if feats["crash_mid"] else "crash", h))
            sc.faults.append(Fault(min(t + d, fault_end), "restart", h))
    # --- short pauses of correct hosts (they stay correct: shorter than the exclusion timeout)
    if feats["pause"]:
        for _ in range(rng.randint(0, 2)):
            h = rng.choice(correct)
            t = rng.uniform(0.05, fault_end * 0.9)
            d = rng.uniform(0.02, 0.4)
            sc.faults.append(Fault(t, "pause", h, duration=d))
            sc.faults.append(Fault(min(t + d, fault_end), "resume", h))
    # --- delay spikes (false suspicions through the real detector)
    if feats["spike"]:
        for _ in range(rng.randint(1, 4)):
            t = rng.uniform(0.0, fault_end * 0.9)
            d = min(rng.uniform(0.05, 0.5), fault_end - t)
            extra = DelayModel("uniform", rng.uniform(0.05, 0.4), rng.uniform(0.0, 0.2))
            src = rng.choice(names) if rng.random() < 0.7 else ""
            dst = rng.choice([n for n in names if n != src]) if rng.random() < 0.5 else ""
            sc.faults.append(Fault(t, "spike", src, dst, duration=d, extra=extra))
    # --- injected false suspicions (external detector model)
    if feats["false_suspicion"]:
        for _ in range(rng.randint(1, 3 * hosts)):
            p, q = rng.sample(names, 2)
            t = rng.uniform(0.0, fault_end * 0.95)
            d = min(rng.uniform(0.005, 0.5), fault_end - t)
            sc.faults.append(Fault(t, "false_suspicion", p, q, duration=d))
    sc.faults.sort(key=lambda fl: fl.time)
    # --- workload
    m = rng.randint(5, 30) if algorithm == "oac" else rng.randint(2, 10)
    times: list[float] = []
    while len(times) < m:
        t = rng.uniform(0.0, fault_end)
        if feats["bursts"] and rng.random() < 0.5:
            times.extend([t] * rng.randint(2, 5))
        else:
            times.append(t)
    times = sorted(times[:m])
    times += [fault_end + rng.uniform(0.05, 0.5) for _ in range(rng.randint(1, 3))]  # after healing
    for i, t in enumerate(times):
        proposer = rng.choice(names)
        parts = _participants(rng, names, proposer, set(faulty))
        payload = f"tx{i}".encode()
        sc.proposals.append((t, proposer, parts, payload))
        if feats["no_votes"] and rng.random() < 0.3:
            sc.no_votes.add((payload, rng.choice(parts)))
    if algorithm == "oac":
        # many concurrent proposers (issue 14): in ALL_PROPOSING_SHARE of the schedules, 1-2 instants at which
        # every host proposes, each to a participant set of its own (a mission's writes from every host at
        # once, without the sequencer). From a generator of its own: the rest of each seed stays as it was.
        ra = random.Random(seed * 15485863 + 3)
        if ra.random() < ALL_PROPOSING_SHARE:
            k = len(sc.proposals)
            for _ in range(ra.randint(1, 2)):
                t = ra.uniform(0.0, fault_end)
                for proposer in names:
                    parts = _participants(ra, names, proposer, set(faulty))
                    sc.proposals.append((t, proposer, parts, f"tx{k}".encode()))
                    k += 1
            sc.proposals.sort(key=lambda p: p[0])
    return sc


class ExternalFd:
    """The adversarial failure-detector model for fd_mode='external' (see the module docstring)."""

    def __init__(self, sc: Scenario, cl: SimCluster, rng: random.Random) -> None:
        self.sc = sc
        self.cl = cl
        self.rng = rng
        self.state: dict[tuple[str, str], bool] = {}
        self.crashed: set[str] = set()
        self.episodes: dict[tuple[str, str], int] = {}

    def _set(self, p: str, q: str, s: bool) -> None:
        if p == q:
            return
        if not s and q in self.crashed:
            return
        self.state[(p, q)] = s
        self.cl.suspect(p, q, s)

    def on_crash(self, q: str) -> None:
        self.crashed.add(q)
        for p in self.sc.names:
            if p != q:
                d = self.rng.uniform(0.001, self.sc.detect_max)
                self.cl.at(self.cl.now + d, functools.partial(self._set, p, q, True))

    def on_pause(self, q: str, duration: float) -> None:
        for p in self.sc.names:
            if p == q:
                continue
            d = self.rng.uniform(0.001, self.sc.detect_max)
            if d < duration:
                self.cl.at(self.cl.now + d, functools.partial(self._set, p, q, True))
                back = self.rng.uniform(0.001, 0.05)
                self.cl.at(self.cl.now + duration + back, functools.partial(self._set, p, q, False))

    def on_restart(self, q: str, inc: int) -> None:
        self.crashed.discard(q)
        # the new process's detector must come to suspect the crashed hosts (sorted: the rng draws must not
        # follow the order of a set of names, which changes with PYTHONHASHSEED)
        for x in sorted(self.crashed):
            d = self.rng.uniform(0.001, self.sc.detect_max)
            self.cl.at(self.cl.now + d, functools.partial(self._set, q, x, True))
        for p in self.sc.names:
            if p == q:
                continue
            d = self.rng.uniform(0.001, 0.05)

            def tell(p: str = p) -> None:
                self.state[(p, q)] = False
                self.cl.peer_info(p, q, inc)

            self.cl.at(self.cl.now + d, tell)

    def false_suspicion(self, p: str, q: str, duration: float) -> None:
        key = (p, q)
        self.episodes[key] = self.episodes.get(key, 0) + 1
        self._set(p, q, True)

        def end() -> None:
            self.episodes[key] -= 1
            if self.episodes[key] == 0 and self.cl.now <= self.sc.fault_end + 1e-9:
                self._set(p, q, False)

        self.cl.at(self.cl.now + duration, end)

    def heal(self) -> None:
        for (p, q), s in list(self.state.items()):
            if s and q not in self.crashed:
                self._set(p, q, False)


def build(sc: Scenario, trace: bool = False) -> tuple[SimCluster, ExternalFd | None]:
    """Create the cluster for a scenario and schedule its faults and workload."""
    rng = random.Random(sc.seed ^ 0x5EED)
    cl = SimCluster(
        sc.names,
        rng,
        sc.delay,
        sc.core_config(),
        offsets=sc.offsets,
        drifts=sc.drifts,
        no_votes=sc.no_votes,
        trace=trace,
    )
    fd = ExternalFd(sc, cl, random.Random(sc.seed ^ 0xFD)) if sc.fd_mode == FD_EXTERNAL else None
    if fd is not None:
        cl.on_restart = fd.on_restart
    cl.start_all()

    def schedule(fl: Fault) -> None:
        def fire() -> None:
            if fl.kind in ("crash", "crash_mid"):
                if fd is not None and cl.hosts[fl.host].inc and fl.host not in fd.crashed:
                    fd.on_crash(fl.host)
                cl.crash(fl.host, mid_step=fl.kind == "crash_mid")
            elif fl.kind == "pause":
                if fd is not None:
                    fd.on_pause(fl.host, fl.duration)
                cl.pause(fl.host)
            elif fl.kind == "resume":
                cl.resume(fl.host)
            elif fl.kind == "restart":
                cl.restart(fl.host)
            elif fl.kind == "spike":
                assert fl.extra is not None
                cl.spike(fl.host or None, fl.other or None, fl.extra, fl.duration)
            elif fl.kind == "false_suspicion" and fd is not None:
                fd.false_suspicion(fl.host, fl.other, fl.duration)

        cl.at(fl.time, fire)

    for fl in sc.faults:
        schedule(fl)

    def heal() -> None:
        for h in sc.names:
            cl.resume(h)
        if fd is not None:
            fd.heal()

    cl.at(sc.fault_end, heal)
    for t, proposer, parts, payload in sc.proposals:
        cl.at(t, functools.partial(cl.propose, proposer, payload, parts))
    return cl, fd


def run(sc: Scenario, trace: bool = False, step: float = 0.25) -> tuple[SimCluster, dict[str, Any]]:
    """Run a scenario to quiescence (or its deadline). Returns the cluster and run statistics."""
    cl, _fd = build(sc, trace=trace)
    last_proposal = max((p[0] for p in sc.proposals), default=0.0)
    t = max(sc.fault_end, last_proposal)
    cl.run(t)
    quiescent = False
    while t < sc.deadline:
        t += step
        cl.run(t)
        if cl.oac_in_flight == 0 and all(n == 0 for n in cl.open_transactions().values()):
            if sc.algorithm != "ufd" or t >= sc.fault_end + 3 * sc.exclude_after:
                quiescent = True
                break
    stats = {"end": t, "quiescent": quiescent, "events": cl.events, "messages": sum(cl.msg_counts.values())}
    return cl, stats
