"""Gathering a chaos run's material into its run directory, for the checks and the timeline.

    <run>/plan.json             the validated plan
    <run>/faults.json           every injected fault (haa.lab.chaos.inject.Injected), with t0 (unix time of t = 0)
    <run>/hosts/<name>.jsonl    each host's JSON-lines log, copied from its data dir: every agent event, every
                                acknowledged workload write (`chaos_ack`), membership changes, suspicions —
                                what the host persisted, including hosts that were killed
    <run>/replicas/<name>.json  each live host's replica of the workload's keys as the host itself holds it
                                (DdbGet of `chaos/` and `demo/`), and its Status (ddb_hash, view, members)
    <run>/agents.json           the merged agent list at the end (for the report; the checks do not use it)

`settle` waits, after the last fault, until the group is whole again: every live host a member of one view,
every agent active or given up (`failed`), and every live replica at the same DDB hash.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import grpc

from haa.cluster.agents import AgentRow, agent_lists, merge_agents
from haa.cluster.backend import ALIVE, Backend, ClusterError
from haa.cluster.events import parse_lines
from haa.core.ddb import ops as ddbmod
from haa.pb import control_pb2 as cpb

#: DDB prefixes the workloads write
PREFIXES = ("chaos/", "demo/")
#: agent states that are at rest
SETTLED = frozenset({"active", "failed"})


def _agents(backend: Backend) -> list[AgentRow] | None:
    try:
        replies = agent_lists(backend)
    except ClusterError:
        return None
    ok = {n: r for n, r in replies.items() if isinstance(r, cpb.AgentListReply)}
    if len(ok) != len(replies):
        return None
    return merge_agents(ok)


def group_state(backend: Backend) -> tuple[bool, str]:
    """(settled?, what is still moving): every alive host a member of one view with every alive host, one
    DDB hash, every agent active or failed."""
    alive = [h.name for h in backend.hosts() if h.state == ALIVE]
    st = backend.statuses(alive)
    bad = [n for n, r in st.items() if not isinstance(r, cpb.StatusReply)]
    if bad:
        return False, f"no answer from {', '.join(bad)}"
    replies: dict[str, cpb.StatusReply] = {n: r for n, r in st.items() if isinstance(r, cpb.StatusReply)}
    not_member = [n for n, r in replies.items() if not r.member or sorted(r.members) != sorted(alive)]
    if not_member:
        return False, f"membership not settled on {', '.join(not_member)}"
    if len({(r.view, r.ddb_hash) for r in replies.values()}) != 1:
        return False, "replicas differ (view or DDB hash)"
    rows = _agents(backend)
    if rows is None:
        return False, "agent list incomplete"
    moving = [f"{r.name} {r.state}" for r in rows if r.state not in SETTLED]
    if moving:
        return False, "agents " + ", ".join(moving[:6])
    return True, f"settled: view {next(iter(replies.values())).view}, DDB {next(iter(replies.values())).ddb_hash[:12]}"


def settle(backend: Backend, timeout: float, stable_for: float = 1.0) -> tuple[bool, str, float]:
    """Wait until `group_state` holds twice `stable_for` s apart; (settled, last note, seconds waited)."""
    t0 = time.monotonic()
    first_ok: float | None = None
    first_note = note = "not checked"
    while True:
        try:
            ok, note = group_state(backend)
        except (ClusterError, grpc.RpcError) as e:
            ok, note = False, str(e)
        now = time.monotonic()
        if ok:
            if first_ok is None or note != first_note:  # the same view and DDB hash `stable_for` s apart
                first_ok, first_note = now, note
            elif now - first_ok >= stable_for:
                return True, note, now - t0
        else:
            first_ok = None
        if now - t0 > timeout:
            return False, note, now - t0
        time.sleep(0.3)


def _value(obj: Any) -> Any:
    data = bytes(obj.value)
    if obj.type == "log":
        first, items = ddbmod.decode_log(data)
        return {"first": first, "items": [it.decode("utf-8", "replace") for it in items]}
    if obj.type == "json":
        return json.loads(data)
    return data.decode("utf-8", "replace")


def snapshot_replicas(backend: Backend, out: Path) -> list[str]:
    """Write replicas/<host>.json for every alive host that answers; the names written."""
    d = out / "replicas"
    d.mkdir(parents=True, exist_ok=True)
    written = []
    for h in backend.hosts():
        if h.state != ALIVE:
            continue
        try:
            def read(c: Any) -> tuple[cpb.StatusReply, dict[str, Any]]:
                objs: dict[str, Any] = {}
                for p in PREFIXES:
                    rep = c.ddb_get(prefix=p)
                    for o in rep.objects:
                        objs[o.key] = {"type": o.type, "version": o.version, "value": _value(o)}
                return c.status(), objs

            status, objs = backend.call(h.name, read, "DdbGet", timeout=10.0)
        except ClusterError:
            continue
        rec = {
            "host": h.name,
            "status": {
                "incarnation": status.incarnation, "member": status.member, "members": list(status.members),
                "view": status.view, "ddb_hash": status.ddb_hash, "ddb_seq": status.ddb_seq,
                "ddb_size": status.ddb_size,
            },
            "objects": objs,
        }
        (d / f"{h.name}.json").write_text(json.dumps(rec, indent=1, sort_keys=True) + "\n")
        written.append(h.name)
    return written


def copy_logs(data_dirs: dict[str, Path], out: Path) -> None:
    """Copy each host's JSON-lines log (<data dir>/<name>.jsonl) to hosts/<name>.jsonl."""
    d = out / "hosts"
    d.mkdir(parents=True, exist_ok=True)
    for name, dd in data_dirs.items():
        src = dd / f"{name}.jsonl"
        if src.exists():
            shutil.copyfile(src, d / f"{name}.jsonl")


def write_agents(backend: Backend, out: Path) -> None:
    rows = _agents(backend) or []
    (out / "agents.json").write_text(json.dumps([asdict(r) for r in rows], indent=1) + "\n")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The JSON objects of a JSON-lines file (lines that are not JSON, a traceback, are skipped)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return []
    return parse_lines(text.splitlines())


def host_logs(run: Path) -> dict[str, list[dict[str, Any]]]:
    """hosts/<name>.jsonl of a run directory: host name -> its records in file order."""
    return {p.stem: read_jsonl(p) for p in sorted((run / "hosts").glob("*.jsonl"))}


def replicas(run: Path) -> dict[str, dict[str, Any]]:
    """replicas/<name>.json of a run directory: host name -> the record `snapshot_replicas` wrote."""
    return {p.stem: json.loads(p.read_text()) for p in sorted((run / "replicas").glob("*.json"))}
