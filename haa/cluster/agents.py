"""Every agent as the whole cluster sees it: `agent_lists` asks every alive host for its AgentList and
`merge_agents` folds the replies into one `AgentRow` per agent (used by `haactl agent`, the demo, the
dashboard and chaos; moved here from haactl.agentcli: haa must not import haactl).

What each host can tell (haa.hostd.agentcontrol): the replicated agent table (the same on every member, up to
the last few commits) and, for the instances it runs or prepares, their local phase (claiming, thawing,
recovering, active, freezing), measured CPU, pid and message counters. An agent's state is the local phase of
the host that runs or prepares it where one reports it (a "recovering" of a never-started agent, life 0 or 1,
is shown as "spawning", "claiming" as "thawing"), else its table status (new, active, freezing, frozen,
crashed, failed); its host is that host, else the table owner.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import grpc

from haa.cluster.backend import ALIVE, Backend, ClusterError, natural_key, rpc_error_text
from haa.pb import control_pb2 as cpb

#: table statuses (haa.core.ddb.agenttable) and local phases (haa.core.agents.agentnode.Local) -> the state shown
PHASE_STATE = {"claiming": "thawing", "thawing": "thawing", "recovering": "recovering", "active": "active",
               "freezing": "freezing"}


def agent_lists(backend: Backend, timeout: float | None = None) -> dict[str, cpb.AgentListReply | Exception]:
    """AgentList of every alive host, in parallel; failures as exceptions (raises if no cluster)."""
    hosts = [h for h in backend.require_hosts() if h.state == ALIVE]
    if not hosts:
        raise ClusterError(f"no host is alive in the {backend.describe()}")

    def one(h: Any) -> tuple[str, cpb.AgentListReply | Exception]:
        c = backend.connect(h, timeout)
        try:
            return h.name, c.agent_list()
        except grpc.RpcError as e:
            return h.name, e
        finally:
            c.close()

    with ThreadPoolExecutor(max_workers=min(16, len(hosts))) as pool:
        return dict(pool.map(one, hosts))


@dataclass
class AgentRow:
    """One agent as the whole cluster sees it (`merge_agents`)."""

    name: str
    id: str
    type: str
    state: str
    host: str  # the host that runs / prepares it, else the table owner ("" if none)
    cpu: float  # fraction of one core (the running host's latest measurement, else the table's)
    parent: str  # parent's display name ("" for a top-level agent)
    parent_id: str
    epoch: int
    backup: bool
    status: str  # table status
    owner: str
    alloc: str
    pid: int = 0
    queued: int = 0
    dropped: int = 0
    recovery: str = ""
    phases: dict[str, str] = field(default_factory=dict)  # host -> local phase, every host reporting one
    fail_reason: str = ""  # the latest failure's reason (state "failed": why it is not recovered)
    waiting: str = ""  # why it cannot run now, when allocated nowhere (no host offers its hardware, ...)
    failures: int = 0  # consecutive start failures
    msgs_in: int = 0  # agent messages the instance on `host` received since it started (0: none reported)
    msgs_out: int = 0  # ... and sent


def merge_agents(replies: dict[str, cpb.AgentListReply]) -> list[AgentRow]:
    """Merge what every host reports into one row per agent (module docstring)."""
    rows: dict[str, cpb.AgentInfo] = {}
    phases: dict[str, dict[str, cpb.AgentInfo]] = {}
    for host in sorted(replies, key=natural_key):
        for a in replies[host].agents:
            prev = rows.get(a.id)
            if prev is None or a.epoch > prev.epoch:
                rows[a.id] = a  # the most advanced replica's row
            if a.local_phase:
                phases.setdefault(a.id, {})[host] = a
    names = {i: a.name for i, a in rows.items()}
    out: list[AgentRow] = []
    for agent_id, a in rows.items():
        loc = phases.get(agent_id, {})
        # whose phase counts: the owner's, else the allocated host's (claiming, recovering), else a host that
        # prepares it rather than one still freezing it on an older replica
        order = sorted(loc, key=lambda h: (h != a.owner, h != a.alloc, loc[h].local_phase == "freezing"))
        mine = loc[order[0]] if order else None
        if mine is not None:
            host = order[0]
            state = PHASE_STATE.get(mine.local_phase, mine.local_phase)
            if mine.local_phase == "recovering" and (a.status == "new" or (a.status == "active" and a.life == 1)):
                # the first start of a new agent goes through recoverAgent (Alg. 8); once its OAC(recovered)
                # committed (life 1: no recovery yet) the process may still be starting
                state = "spawning"
            cpu = mine.local_cpu or a.cpu
            pid, msgs_in, msgs_out = mine.pid, mine.msgs_in, mine.msgs_out
        else:
            host, state, cpu, pid, msgs_in, msgs_out = a.owner, a.status, a.cpu, 0, 0, 0
        out.append(AgentRow(
            name=a.name, id=a.id, type=a.type, state=state, host=host, cpu=cpu,
            parent=names.get(a.parent, a.parent[:8]) if a.parent else "", parent_id=a.parent, epoch=a.epoch,
            backup=a.has_backup, status=a.status, owner=a.owner, alloc=a.alloc, pid=pid, queued=a.queued,
            dropped=a.dropped, recovery=a.recovery, phases={h: x.local_phase for h, x in loc.items()},
            fail_reason=a.fail_reason, failures=a.failures, msgs_in=msgs_in, msgs_out=msgs_out, waiting=a.waiting,
        ))
    return sorted(out, key=lambda r: name_key(r.name))


def name_key(name: str) -> tuple[Any, ...]:
    """A2 before A10, A1.2 before A1.10."""
    parts = name[1:].split(".") if name[:1] == "A" else [name]
    return tuple((0, int(p)) if p.isdigit() else (1, p) for p in parts)

def answering(backend: Backend, replies: dict[str, cpb.AgentListReply | Exception]) -> dict[str, cpb.AgentListReply]:
    """The hosts that answered; a clear error if none did (a wrong token, no agent layer, ...)."""
    ok = {n: r for n, r in replies.items() if isinstance(r, cpb.AgentListReply)}
    if ok:
        return ok
    name, e = next(iter(replies.items()))
    if isinstance(e, grpc.RpcError):
        raise ClusterError(rpc_error_text(name, backend.host(name).address, e, "AgentList"))
    raise ClusterError(f"no host answered AgentList in the {backend.describe()}")

def wait_rows(backend: Backend, pred: Callable[[list[AgentRow]], Any], timeout: float, what: str) -> Any:
    """Poll the merged agent list until `pred` returns something truthy."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            v = pred(merge_agents(answering(backend, agent_lists(backend))))
            if v:
                return v
        except ClusterError:
            pass
        if time.monotonic() > deadline:
            raise ClusterError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.1)

def active_row(rows: list[AgentRow], agent_id: str, host: str | None = None, min_epoch: int = 0) -> AgentRow | None:
    for r in rows:
        if r.id == agent_id and r.state == "active" and r.epoch >= min_epoch and (host is None or r.host == host):
            return r
    return None
