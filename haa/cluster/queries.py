"""Quick questions to a running cluster, answered by the first alive host that can (moved here from the mission
runner, which polls with them; nothing here knows about missions).

* `alive_hosts` — the hosts the backend sees alive; `host_client` — a control client of one of them.
* `ddb_read` — {key: value} from one replica (values decoded by haa.core.ddb.ops.decode_value); `ddb_bytes` — the
  size of the DDB's values.
* `cluster_view` — the agreed group, every host's active agents, and every agent's most advanced table row.
* `registered_types`, `spawn_agent`, `remove_agents` (an agent and all its descendants, deepest first).

A host that does not answer is skipped for the next one; `None` (or an empty answer) when none does.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import grpc

from haa.cluster.backend import ALIVE, Backend, ClusterError, agreed_group
from haa.core.ddb import objects as ddb
from haa.core.ddb.ops import decode_value
from haa.pb import control_pb2 as cpb


def host_client(backend: Backend, name: str, timeout: float = 3.0) -> Any:
    """A control client of host `name` (no check that it is alive: the call says)."""
    return backend.connect(backend.host(name), timeout)


def alive_hosts(backend: Backend) -> list[str]:
    return [h.name for h in backend.hosts() if h.state == ALIVE]


def ddb_read(backend: Backend, keys: Sequence[str] = (), prefix: str = "", prefer: str | None = None,
             timeout: float = 3.0) -> tuple[str, dict[str, Any]] | None:
    """(the host that answered, {key: decoded value}) from the replica of one alive host (`prefer` first); None
    if no host answers. A value that does not decode is left out."""
    names = alive_hosts(backend)
    if prefer in names:
        names.remove(prefer)
        names.insert(0, prefer)
    for n in names:
        c = host_client(backend, n, timeout)
        try:
            reply = c.ddb_get(keys=list(keys), prefix=prefix)
        except grpc.RpcError:
            continue
        finally:
            c.close()
        out: dict[str, Any] = {}
        for o in reply.objects:
            with contextlib.suppress(ddb.DdbError):
                out[o.key] = decode_value(o.type, o.value)
        return n, out
    return None


def ddb_bytes(backend: Backend) -> int | None:
    """Total size of the DDB's keys and values (one replica); None if no host answers."""
    names = alive_hosts(backend)
    for n in names:
        c = host_client(backend, n, 30.0)
        try:
            reply = c.ddb_get(prefix="")
        except grpc.RpcError:
            continue
        finally:
            c.close()
        return sum(len(o.key) + len(o.value) for o in reply.objects)
    return None


def cluster_view(backend: Backend) -> tuple[list[str], dict[str, list[Any]], dict[str, Any]]:
    """(members of the agreed group, {host: its active agents (AgentInfo)}, {agent id: AgentInfo} — the most
    advanced table row of every agent)."""
    names = alive_hosts(backend)

    def one(n: str) -> tuple[str, Any, Any]:
        c = host_client(backend, n)
        try:
            st = c.status()
        except grpc.RpcError:
            st = None
        try:
            al = c.agent_list() if st is not None else None
        except grpc.RpcError:
            al = None
        finally:
            c.close()
        return n, st, al

    if not names:
        return [], {}, {}
    with ThreadPoolExecutor(max_workers=min(16, len(names))) as pool:
        got = list(pool.map(one, names))
    statuses = {n: st for n, st, _ in got if isinstance(st, cpb.StatusReply)}
    members, _, _ = agreed_group(statuses)
    per_host: dict[str, list[Any]] = {}
    rows: dict[str, Any] = {}
    for n, _, al in got:
        if al is None:
            continue
        for a in al.agents:
            prev = rows.get(a.id)
            if prev is None or a.epoch > prev.epoch:
                rows[a.id] = a
            if a.local_phase == "active":
                per_host.setdefault(n, []).append(a)
    return members, per_host, rows


def registered_types(backend: Backend) -> list[str] | None:
    """The agent types the first answering host can spawn; None if no host answers."""
    for n in alive_hosts(backend):
        c = host_client(backend, n)
        try:
            return list(c.agent_list().agent_types)
        except grpc.RpcError:
            continue
        finally:
            c.close()
    return None


def spawn_agent(backend: Backend, type_name: str, config: dict[str, Any], timeout: float = 15.0) -> tuple[str, str]:
    """Spawn a top-level agent through the first alive host that answers; (id, display name). ClusterError
    ("spawn TYPE: why") if that host refuses or none answers."""
    payload = json.dumps(config).encode()
    last = "no host is alive"
    for n in alive_hosts(backend):
        c = host_client(backend, n, timeout)
        try:
            r = c.agent_spawn(type_name, payload, timeout=timeout)
        except grpc.RpcError as e:
            last = f"{n}: {e.code().name}"
            continue
        finally:
            c.close()
        if r.ok:
            return r.id, r.name
        raise ClusterError(f"spawn {type_name}: {r.reason}")
    raise ClusterError(f"spawn {type_name}: {last}")


def remove_agents(backend: Backend, top: Iterable[str], timeout: float = 15.0) -> list[str]:
    """Remove the agents `top` (ids) and all their descendants, deepest first (AgentRemove leaves children
    alone); returns the display names removed."""
    _, _, rows = cluster_view(backend)
    children: dict[str, list[str]] = {}
    for a in rows.values():
        children.setdefault(a.parent, []).append(a.id)
    order: list[str] = []

    def walk(i: str, seen: set[str]) -> None:
        for ch in children.get(i, []):
            if ch not in seen:
                seen.add(ch)
                walk(ch, seen)
        order.append(i)

    seen: set[str] = set()
    for t in top:
        if t in rows and t not in seen:
            seen.add(t)
            walk(t, seen)
    removed = []
    for i in order:
        for n in alive_hosts(backend):
            c = host_client(backend, n, timeout)
            try:
                r = c.agent_remove(i, timeout=timeout)
            except grpc.RpcError:
                continue
            finally:
                c.close()
            if r.ok:
                removed.append(rows[i].name)
            break
    return removed
