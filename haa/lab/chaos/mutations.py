"""Deliberately broken hosts, to prove that each chaos check can fail (issue 18 §2, docs/chaos.md "Mutations").

A plan's `mutation: NAME` runs every host of a local chaos run as a broken variant of haa-hostd. Nothing in
the production classes knows about it: the runner puts `haa/lab/chaos/_site` on the hosts' PYTHONPATH (Python
imports its `sitecustomize` at interpreter start) and names the mutation in HAA_CHAOS_MUTATION; in a
haa-hostd process that module calls `apply_from_env()`, which patches the host's classes in that process
only (the way haa.lab.dsim.mutations patches the algorithms for the verifiers). Each mutation targets one check
and should leave the others green:

* `ack-before-commit` -> acked_writes_once: the host answers every 20th DDB write of an agent "committed"
  at once and drops it (a host that acknowledges from its queue and loses the queue);
* `diverge-replica`   -> replicas_agree: one host (HAA_CHAOS_MUTATION_HOST, default h2) applies a put of
  `chaos/stop` with a value of its own: its replica's hash differs from every other;
* `late-commit`       -> single_instance: after an instance's third write the host holds each of its writes
  HOLD_S seconds before proposing it, fencing it only when it arrived (not again when it is proposed): the
  last write of an instance killed meanwhile is committed after its recovered successor's first writes
  (thesis §4.6: an older instance's output accepted after a newer one's);
* `drop-message`      -> counter_streams: the host drops every 25th message it delivers to a local agent
  (operator requests excepted): the receiver sees a gap that is never filled;
* `no-recovery`       -> crashed_agents_recovered: the host never starts the recovery of a crashed agent
  (Alg. 8 l. 1 skipped; first starts still happen): the agent stays crashed.

`MUTATIONS` maps each name to the check it must fail; tests/test_chaos_mutations.py runs one short plan per
mutation and asserts exactly that.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

#: environment of the hosts: the mutation's name, and the host it applies to (diverge-replica)
ENV = "HAA_CHAOS_MUTATION"
ENV_HOST = "HAA_CHAOS_MUTATION_HOST"
#: the directory whose sitecustomize.py applies the mutation in haa-hostd processes
SITE_DIR = Path(__file__).with_name("_site")
#: late-commit: seconds a write is held; the instance's first writes that are not held
HOLD_S = 5.0
FREE_WRITES = 3
#: ack-before-commit / drop-message: every how many-th write / delivery
ACK_EVERY = 20
DROP_EVERY = 25

#: mutation -> the check it must make fail
MUTATIONS: dict[str, str] = {
    "ack-before-commit": "acked_writes_once",
    "diverge-replica": "replicas_agree",
    "late-commit": "single_instance",
    "drop-message": "counter_streams",
    "no-recovery": "crashed_agents_recovered",
}


def _ack_before_commit() -> None:
    from haa.hostd.agentdriver import AgentDriver

    orig = AgentDriver._ddb_write
    seen: Counter[str] = Counter()

    def mutated(self: AgentDriver, ev: Any) -> None:
        seen["n"] += 1
        if ev.ops and seen["n"] % ACK_EVERY == 0 and not self._fenced(ev.agent_id):
            self.host.counters["mutation_acked_uncommitted"] += 1
            self.sup.answer(ev.agent_id, ev.req_id, True, b"", op_errors=[""] * len(ev.ops))
            return
        orig(self, ev)

    AgentDriver._ddb_write = mutated  # type: ignore[method-assign]


def _diverge_replica(host: str) -> None:
    from haa.core.ddb.ddb import Ddb
    from haa.lab.chaos.workload import STOP_KEY
    from haa.pb import ddb_pb2 as pb

    if _own_name() != host:
        return
    orig = Ddb.apply

    def mutated(self: Ddb, payload: bytes, meta: Any = None) -> Any:
        with contextlib.suppress(Exception):
            batch = pb.DdbBatch.FromString(bytes(payload))
            hit = False
            for op in batch.ops:
                if op.WhichOneof("op") == "put" and op.put.key == STOP_KEY:
                    op.put.value = b'"diverged"'
                    hit = True
            if hit:
                payload = batch.SerializeToString()
        return orig(self, payload, meta)

    Ddb.apply = mutated  # type: ignore[method-assign]


def _late_commit() -> None:
    from haa.hostd.agentdriver import AgentDriver
    from haa.lab.chaos.workload import STOP_KEY

    orig = AgentDriver._ddb_write
    writes: Counter[tuple[str, int | None]] = Counter()

    def mutated(self: AgentDriver, ev: Any) -> None:
        agent, epoch = ev.agent_id, self.epochs.get(ev.agent_id)
        writes[(agent, epoch)] += 1
        if writes[(agent, epoch)] <= FREE_WRITES or not ev.ops or self._fenced(agent):
            orig(self, ev)  # as the host does (refused when stale)
            return

        async def held() -> None:
            await asyncio.sleep(HOLD_S)
            ddb = self._replica()
            if ddb is not None and ddb.get(STOP_KEY) is not None:  # the run is ending: let the replicas settle
                self.sup.answer(agent, ev.req_id, False, b"", "mutation late-commit: dropped after chaos/stop")
                return
            try:
                res = await self.host.ddb_write(list(ev.ops), ev.atomic)  # no fencing here: the mutation
                errors = ["" if r.ok else (r.reason or "failed") for r in res.results]
                if self.epochs.get(agent) == epoch:
                    self.sup.answer(agent, ev.req_id, True, b"", op_errors=errors)
            except Exception as e:
                if self.epochs.get(agent) == epoch:
                    self.sup.answer(agent, ev.req_id, False, b"", f"{type(e).__name__}: {e}")

        task = asyncio.create_task(held(), name="agent-ddb-write-held")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    AgentDriver._ddb_write = mutated  # type: ignore[method-assign]


def _drop_message() -> None:
    from haa.core import agentio as io
    from haa.hostd.agentdriver import AgentDriver

    orig = AgentDriver.command
    seen: Counter[str] = Counter()

    def mutated(self: AgentDriver, c: Any) -> None:
        if type(c) is io.DeliverAgent and not c.msg.src.startswith("@") and not c.msg.reply:
            seen["n"] += 1
            if seen["n"] % DROP_EVERY == 0:
                self.host.counters["mutation_dropped_messages"] += 1
                return
        orig(self, c)

    AgentDriver.command = mutated  # type: ignore[method-assign]


def _no_recovery() -> None:
    from haa.core.agents.recovery import Recovery
    from haa.core.ddb import agenttable as at

    orig = Recovery._recover

    def mutated(self: Recovery, r: Any) -> None:
        if r.status == at.NEW:
            orig(self, r)

    Recovery._recover = mutated  # type: ignore[method-assign]


_APPLY: dict[str, Callable[[str], None]] = {
    "ack-before-commit": lambda _h: _ack_before_commit(),
    "diverge-replica": _diverge_replica,
    "late-commit": lambda _h: _late_commit(),
    "drop-message": lambda _h: _drop_message(),
    "no-recovery": lambda _h: _no_recovery(),
}


def _own_name() -> str:
    """This haa-hostd's --name (from its command line)."""
    argv = sys.argv
    for i, a in enumerate(argv):
        if a == "--name" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--name="):
            return a.split("=", 1)[1]
    return os.environ.get("HAA_NAME", "")


def is_hostd() -> bool:
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    return prog == "haa-hostd" or (prog == "-m" and "haa.hostd.daemon" in " ".join(sys.argv))


def apply_from_env() -> str:
    """Apply HAA_CHAOS_MUTATION in this process if it is a haa-hostd; the name applied ('' if none)."""
    name = os.environ.get(ENV, "")
    if not name or not is_hostd():
        return ""
    if name not in _APPLY:
        raise SystemExit(f"haa-hostd: {ENV}={name!r} is not a chaos mutation ({', '.join(MUTATIONS)})")
    _APPLY[name](os.environ.get(ENV_HOST) or "h2")
    return name


@contextlib.contextmanager
def mutation_env(name: str | None, host: str | None = None) -> Iterator[None]:
    """The environment of hosts started inside: mutation `name` applied in them (nothing when None)."""
    if not name:
        yield
        return
    if name not in MUTATIONS:
        raise ValueError(f"unknown mutation {name!r} ({', '.join(MUTATIONS)})")
    if not (SITE_DIR / "sitecustomize.py").is_file():
        raise ValueError(f"mutation {name}: {SITE_DIR}/sitecustomize.py is missing (mutations need a source "
                         "checkout or an editable install)")
    keys = (ENV, ENV_HOST, "PYTHONPATH")
    old = {k: os.environ.get(k) for k in keys}
    path = [str(SITE_DIR), *[p for p in (old["PYTHONPATH"] or "").split(os.pathsep) if p]]
    os.environ.update({ENV: name, ENV_HOST: host or "h2", "PYTHONPATH": os.pathsep.join(path)})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
