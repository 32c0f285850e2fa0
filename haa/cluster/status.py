"""The status of a whole cluster as `haactl cluster status` shows it (moved here from haactl/cluster.py).

`gather_status(backend)` asks every host of a haa.cluster backend (local, compose or swarm) for its Status
(haa.hostd.control) and returns one JSON-able dict: per host its state in the backend and its reply (member,
rank, view, suspicions, DDB size/sequence/hash, CPU, RSS) or the error; the group the members agree on
(`agreed_group`); whether every member has that view and the same DDB hash. The keys are the interface of
`haactl cluster status --json`.
"""

from __future__ import annotations

import time
from typing import Any

import grpc

from haa.cluster.backend import Backend, agreed_group
from haa.pb import control_pb2 as cpb


def host_row(h: Any, reply: cpb.StatusReply | Exception | None, cpu: float | None) -> dict[str, Any]:
    """One host of `gather_status`: what the backend knows of it (address, state, pid or container) and, if it
    answered, its Status reply; else the error."""
    row: dict[str, Any] = {
        "name": h.name,
        "address": h.address,
        "state": h.state,
        "core": h.core,
        "pid": h.pid,
        "container": h.container,
        "detail": h.detail,
        "metrics_url": h.metrics_url or None,
        "error": None,
    }
    if isinstance(reply, cpb.StatusReply):
        row.update(
            mode=reply.mode,
            incarnation=reply.incarnation,
            member=reply.member,
            members=list(reply.members),
            leader=reply.leader,
            view=reply.view,
            rank=reply.rank,
            suspicions=list(reply.suspicions),
            ddb_size=reply.ddb_size,
            ddb_hash=reply.ddb_hash,
            ddb_seq=reply.ddb_seq,
            global_seq=reply.global_seq,
            state_hash=reply.state_hash,
            group_id=reply.group_id,
            locked=reply.locked,
            applicants=list(reply.applicants),
            leaving=reply.leaving,
            cpu_percent=round(cpu if cpu is not None else reply.cpu_percent, 2),
            rss_bytes=reply.rss_bytes,
            uptime=round(reply.uptime, 3),
        )
    elif isinstance(reply, grpc.RpcError):
        row["error"] = f"{reply.code().name}: {reply.details()}"
    elif reply is not None:
        row["error"] = str(reply)
    return row


def gather_status(backend: Backend, sample: float = 0.5) -> dict[str, Any]:
    """The cluster's status (the object `haactl cluster status --json` prints): every host's row, the group the
    members agree on, whether their views and DDB hashes agree. Asks every host's Status twice, `sample`
    seconds apart, for each host's CPU share over that interval (0: the daemon's own estimate)."""
    hosts = backend.require_hosts()
    first = backend.statuses()
    backend.check_token(first)
    second = first
    if sample > 0 and first:
        time.sleep(sample)
        second = backend.statuses(list(first))
    cpu: dict[str, float] = {}
    for n, b in second.items():
        a = first.get(n)
        if (
            isinstance(a, cpb.StatusReply)
            and isinstance(b, cpb.StatusReply)
            and b.incarnation == a.incarnation
            and b.uptime > a.uptime
            and b.load_cpu_seconds > 0
        ):
            cpu[n] = 100.0 * (b.load_cpu_seconds - a.load_cpu_seconds) / (b.uptime - a.uptime)
    replies = {n: r for n, r in second.items() if isinstance(r, cpb.StatusReply)}
    members, leader, view = agreed_group(replies)
    rows = [host_row(h, second.get(h.name), cpu.get(h.name)) for h in hosts]
    member_rows = [r for r in rows if r.get("member")]
    return {
        "backend": backend.kind,
        "cluster": backend.describe(),
        "members": members,
        "leader": leader,
        "view": view,
        "group_id": next((r.group_id for r in replies.values() if r.member), ""),
        "agreed": bool(member_rows) and all(r["view"] == view and r["members"] == members for r in member_rows),
        "ddb_hashes_equal": len({r["ddb_hash"] for r in member_rows}) == 1 if member_rows else False,
        "hosts": rows,
    }
