"""host_status: one host's state as the control API's `Status` reports it (and `haactl status` shows).

A plain function of the runtime's parts, evaluated at call time: who this host is, its view of every peer
(incarnation, suspected, excluded, the heartbeat period eta it asked for and the margin alpha, from
`HostCore.peer_view`, plus the link's address, connection and queue), OAC activity, the delivered count and
hash chain, every counter, and the process's CPU and RSS (psutil). In membership mode the group as this
member sees it is added: members in rank order, leader, view, own rank, suspicions, the DDB's size, hash and
sequence, the global sequence and state hash, whether the group is correct, locked, applicants, leaving.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import psutil

from haa.core.host.hostcore import HostCore
from haa.core.membership.membership import MembershipNode
from haa.hostd.delivered import DeliveredLog
from haa.hostd.transport import Transport


def group_status(node: MembershipNode) -> dict[str, Any]:
    """The membership part of the status (see the module docstring)."""
    st = node.state
    ns = node.status()
    return {
        "mode": "membership",
        "member": ns["member"],
        "members": ns["members"],
        "member_info": [
            {"name": m.name, "incarnation": m.inc, "address": m.addr, "suspected": node.view.suspected(m.proc)}
            for m in st.members
        ],
        "leader": ns["leader"],
        "view": ns["view"],
        "rank": ns["rank"],
        "suspicions": ns["suspected"],
        "ddb_size": st.ddb.size,
        "ddb_hash": st.ddb.content_hash(),
        "ddb_seq": st.ddb.seq,
        "global_seq": st.seq,
        "state_hash": ns["state_hash"],
        "group_id": st.genesis,
        "group_correct": st.group_correct,
        "locked": ns["locked"],
        "applicants": ns["applicants"],
        "leaving": node.lv.leaving,
    }


def host_status(
    *,
    name: str,
    core: HostCore,
    node: MembershipNode | None,
    transport: Transport,
    delivered: DeliveredLog,
    counters: Counter[str],
    proc: psutil.Process,
    uptime: float,
) -> dict[str, Any]:
    """See the module docstring (`node`: the membership node, None in static mode)."""
    peers = []
    for row in core.peer_view():
        q = row["name"]
        peers.append(
            {
                **row,
                "address": transport.peers.get(q, ""),
                "connected": transport.connected(q),
                "queued": transport.queued(q),
            }
        )
    mem = proc.memory_info()
    cpu = proc.cpu_times()
    group: dict[str, Any] = group_status(node) if node is not None else {"mode": "static"}
    return {
        **group,
        "cpu_seconds": cpu.user + cpu.system,
        "name": name,
        "incarnation": core.inc,
        "peers": peers,
        "active_transactions": core.oac.active_count,
        "decided_transactions": core.oac.decided_count,
        "delivered": delivered.count,
        "delivered_hash": delivered.hash,
        "counters": counters,
        "cpu_percent": proc.cpu_percent(None),
        "rss_bytes": mem.rss,
        "uptime": uptime,
    }
