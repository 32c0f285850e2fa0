"""A whole chaos run on a cluster of its own (`haactl chaos run PLAN [--local|--compose]`, docs/chaos.md).

`run_on(cluster, plan, out)` does the run on a `ChaosCluster`: `LocalChaosCluster` (haa-hostd processes in
`<out>/cluster`, `run_local`) or the compose cluster (haa.lab.chaos.compose.ComposeChaosCluster):

1. refuse what the cluster cannot do (`cluster.problems`) before anything starts;
2. start `plan.hosts` hosts (they load the workload's agent type through HAA_AGENT_MODULES; a plan's
   `mutation` makes every local host a broken variant, haa.lab.chaos.mutations) and wait until they form one
   group;
3. start the workload and wait until its agents are active; the chaos clock starts (t = 0);
4. inject the plan's faults until `duration_s` (`haa.lab.chaos.inject.Injector`), then end the pauses and stop
   the workload (writers: the key `chaos/stop`; counters: paused, then removed once their last counts are
   written);
5. end pauses and partitions still held, wait up to `settle_s` for the group to settle (`collect.settle`),
   read every live replica, stop the cluster and copy every host's log out of its data dir (a container's
   through the docker SDK, also of a stopped one);
6. check (`haa.lab.chaos.checks`) and build the time line (`haa.lab.chaos.timeline`) from those files alone.

Everything lands in the run directory `out`; `result.json` has `faults`, `checks` (name -> passed, detail),
`timeline` and `passed`.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from haa.cluster.agents import AgentRow, active_row, wait_rows
from haa.cluster.backend import Backend, ClusterError, wait_until
from haa.cluster.local_backend import LocalBackend
from haa.core.ddb import ops as ddbmod
from haa.lab.chaos import collect
from haa.lab.chaos.checks import Check, run_checks
from haa.lab.chaos.inject import Injected, Injector, local_problems
from haa.lab.chaos.mutations import SITE_DIR, mutation_env
from haa.lab.chaos.plan import Plan, PlanError
from haa.lab.chaos.timeline import Entry, build
from haa.lab.chaos.workload import STOP_KEY, WORKLOAD_MODULE, WRITER_TYPE
from haa.sdk.registry import ENV_MODULES

Progress = Callable[[str], None]

#: seconds to wait for the group to form and for the workload to start
FORM_TIMEOUT = 180.0  # a loaded 2-core machine: 5 containers took > 120 s once
WORKLOAD_TIMEOUT = 90.0


@dataclass
class RunResult:
    plan: Plan
    out: Path
    t0: float = 0.0
    t_end: float = 0.0  # unix time the replicas were read
    faults: list[Injected] = field(default_factory=list)
    checks: dict[str, Check] = field(default_factory=dict)
    timeline: list[Entry] = field(default_factory=list)
    settled: bool = False
    settle_note: str = ""
    settle_s: float = 0.0
    error: str = ""

    @property
    def passed(self) -> bool:
        return not self.error and bool(self.checks) and all(c.passed for c in self.checks.values())

    def to_json(self) -> dict[str, Any]:
        return {
            "plan": self.plan.name,
            "seed": self.plan.seed,
            "run_dir": str(self.out),
            "t0": self.t0,
            "t_end": self.t_end,
            "passed": self.passed,
            "error": self.error,
            "settle": {"settled": self.settled, "seconds": round(self.settle_s, 2), "note": self.settle_note},
            "faults": [f.to_json() for f in self.faults],
            "checks": {k: c.to_json() for k, c in self.checks.items()},
            "timeline": [e.to_json() for e in self.timeline],
        }


@contextlib.contextmanager
def agent_modules(module: str) -> Iterator[None]:
    """HAA_AGENT_MODULES with `module` added, for the hosts this process starts (restored afterwards)."""
    old = os.environ.get(ENV_MODULES)
    mods = [m for m in (old or "").split(",") if m]
    os.environ[ENV_MODULES] = ",".join([*mods, module] if module not in mods else mods)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(ENV_MODULES, None)
        else:
            os.environ[ENV_MODULES] = old


def _spawn(backend: Backend, type_name: str, config: dict[str, Any]) -> str:
    host = backend.pick_host()
    reply = backend.call(host, lambda c: c.agent_spawn(type_name, json.dumps(config).encode(), timeout=30.0),
                         "AgentSpawn", timeout=35.0)
    if not reply.ok:
        raise ClusterError(f"workload: spawn {type_name}: {reply.reason}")
    return str(reply.id)


def start_workload(plan: Plan, backend: Backend) -> list[str]:
    """Spawn the workload's agents and wait until every one (and every counter's peer) is active; their ids."""
    if plan.workload is None:
        return []
    ids = []
    for _ in range(plan.agents):
        if plan.workload == "ddb-writes":
            ids.append(_spawn(backend, WRITER_TYPE, {"period": plan.period_s}))
        else:
            ids.append(_spawn(backend, "counter", {"spawn_peer": True, "period": plan.period_s}))
    want = len(ids) * (2 if plan.workload == "counters" else 1)

    def all_active(rows: list[AgentRow]) -> bool:
        mine = [r for r in rows if r.id in ids or r.parent_id in ids]
        return len(mine) == want and all(active_row(rows, r.id) for r in mine)

    wait_rows(backend, all_active, WORKLOAD_TIMEOUT, f"the {want} workload agents to become active")
    return ids


def stop_workload(plan: Plan, backend: Backend, progress: Progress) -> None:
    """Writers: commit `chaos/stop`. Counters: pause every counter, let them write their last counts, remove
    them (so that their keys stop changing)."""
    if plan.workload == "ddb-writes":
        for attempt in range(10):
            try:
                host = backend.pick_host()
                rep = backend.call(host, lambda c: c.ddb_write([ddbmod.put(STOP_KEY, "json", True)], timeout=10.0),
                                   "DdbWrite", timeout=15.0)
                if rep.committed:
                    return
                progress(f"stopping the writers: not committed ({rep.reason}); again")
            except ClusterError as e:
                progress(f"stopping the writers: {e}; again")
            time.sleep(1.0 + attempt)
        raise ClusterError("could not commit chaos/stop: the group does not commit writes")
    if plan.workload == "counters":
        rows = collect._agents(backend) or []
        counters = [r for r in rows if r.type == "counter"]
        def pause(agent: str) -> Callable[[Any], Any]:
            return lambda c: c.agent_request(agent, b"pause", timeout=5.0)

        def remove(agent: str) -> Callable[[Any], Any]:
            return lambda c: c.agent_remove(agent)

        for r in counters:
            with contextlib.suppress(ClusterError):
                backend.call(backend.pick_host(), pause(r.id), "AgentRequest", timeout=10.0)
        time.sleep(2.5)  # > stats_period: the last counts reach the DDB
        for r in counters:
            with contextlib.suppress(ClusterError):
                backend.call(backend.pick_host(), remove(r.id), "AgentRemove", timeout=20.0)


class ChaosCluster(Protocol):
    """The cluster a run starts and takes down (`LocalChaosCluster`; the compose one is
    haa.lab.chaos.compose.ComposeChaosCluster). `backend` serves every fault and read in between."""

    @property
    def backend(self) -> Backend: ...

    def problems(self, plan: Plan) -> list[str]:
        """What the plan asks that this cluster cannot do, one line each (checked before anything starts)."""
        ...

    def start(self, plan: Plan, progress: Progress) -> list[str]:
        """Bring up `plan.hosts` hosts able to run the workload; their names."""
        ...

    def stop(self, out: Path, progress: Progress) -> None:
        """Stop every host and copy each host's JSON-lines log to `out/hosts/<name>.jsonl` (also hosts that
        were killed); the cluster is gone afterwards."""
        ...


class LocalChaosCluster:
    """A local cluster of its own under `<out>/cluster` (haa-hostd processes on loopback)."""

    def __init__(self, root: Path) -> None:
        self.backend = LocalBackend(root)
        self.data_dirs: dict[str, Path] = {}

    def problems(self, plan: Plan) -> list[str]:
        out = local_problems(plan)
        if plan.mutation and not (SITE_DIR / "sitecustomize.py").is_file():
            out.append(f"mutation: {SITE_DIR}/sitecustomize.py is missing (mutations need a source checkout or "
                       "an editable install)")
        return out

    def start(self, plan: Plan, progress: Progress) -> list[str]:
        progress(f"starting {plan.hosts} hosts in {self.backend.root}")
        with agent_modules(WORKLOAD_MODULE), mutation_env(plan.mutation):
            names = self.backend.up(plan.hosts, min(3, plan.hosts), hostd_args=list(plan.hostd_args))
        self.data_dirs = {n: Path(self.backend.state["hosts"][n]["data_dir"]) for n in names}
        try:
            self.backend.check_started()
        except ClusterError:
            self.stop(self.backend.root.parent, progress)
            raise
        return names

    def stop(self, out: Path, progress: Progress) -> None:
        progress("stopping the cluster")
        try:
            self.backend.down(grace=5.0)
        finally:
            collect.copy_logs(self.data_dirs, out)


def run_local(plan: Plan, out: Path, progress: Progress | None = None,
              on_fault: Callable[[Injected], None] | None = None) -> RunResult:
    """Run `plan` on a local cluster of its own under `out` (module docstring)."""
    return run_on(LocalChaosCluster(out.absolute() / "cluster"), plan, out, progress, on_fault)


def run_on(cluster: ChaosCluster, plan: Plan, out: Path, progress: Progress | None = None,
           on_fault: Callable[[Injected], None] | None = None) -> RunResult:
    """Run `plan` on `cluster` (started here, stopped at the end), everything in the run directory `out`."""
    say = progress or (lambda _s: None)
    if plan.duration_s is None:
        raise PlanError("duration_s: needed by `haactl chaos run` (only a plan a mission names may leave it out: "
                        "it then lasts until the mission ends)")
    problems = cluster.problems(plan)
    if problems:
        raise PlanError(problems[0])
    out = out.absolute()
    out.mkdir(parents=True, exist_ok=True)
    (out / "plan.json").write_text(plan.model_dump_json(indent=1) + "\n")
    res = RunResult(plan, out)
    backend = cluster.backend
    injector: Injector | None = None
    started = False
    try:
        names = cluster.start(plan, say)
        started = True
        wait_until(lambda: backend.formation(names), FORM_TIMEOUT, what=f"{plan.hosts} hosts to form a group")
        if plan.workload:
            say(f"starting the workload: {plan.workload}, {plan.agents} x")
            start_workload(plan, backend)
        injector = Injector(plan, backend, on_fault=on_fault)
        say(f"chaos for {plan.duration_s:g} s ({len(plan.faults)} fault lines)")
        try:
            injector.run()
        finally:
            injector.end_pauses()
            injector.end_partitions()
            res.t0, res.faults = injector.t0, injector.injected
        say("faults over: stopping the workload")
        stop_workload(plan, backend, say)
        res.settled, res.settle_note, res.settle_s = collect.settle(backend, plan.settle_s)
        say(f"settle: {res.settle_note} after {res.settle_s:.1f} s")
        res.t_end = time.time()
        collect.snapshot_replicas(backend, out)
        collect.write_agents(backend, out)
    except ClusterError as e:
        res.error = str(e)
    finally:
        try:
            if started:  # a start that failed cleaned up after itself (and never touches a cluster it did not start)
                cluster.stop(out, say)
        except ClusterError as e:
            if not res.error:
                res.error = f"stopping the cluster: {e}"
        (out / "faults.json").write_text(json.dumps(
            {"t0": res.t0, "t_end": res.t_end, "faults": [f.to_json() for f in res.faults]}, indent=1) + "\n")
    if not res.error:
        res.checks = run_checks(out, plan.workload)
    res.timeline = build(out) if res.t0 else []
    (out / "result.json").write_text(json.dumps(res.to_json(), indent=1) + "\n")
    return res
