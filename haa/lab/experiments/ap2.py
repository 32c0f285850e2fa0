"""Experiment AP-2 (thesis §7.2.2): join, leave and removal delays of the host group, real processes.

`haactl bench ap2` grows a group of `haa-hostd` processes in membership mode on loopback (h1-h3 core) from
one host to `max_hosts`. For each group size n = 2..max_hosts, host h_n

1. joins the group of n-1 (and again after each leave and each crash below);
2. leaves it gracefully (`Leave` RPC), `reps` times;
3. is killed (SIGKILL), `reps` times, and removed by the others.

The delays are read from the hosts' JSON-lines logs (one machine, one wall clock; `ts` of each event):

* join: the joiner's `startup` (its server is bound and its node starts, right before it applies) to the
  `view` event that adds it — at the leader (`join`) and at the last member to commit it (`join_all`);
* leave: the leaver's `leave_requested` to the last remaining member's `view` event without it;
* removal: the first `suspicion` of the victim by any survivor to the last survivor's `view` without it
  (`remove`), and the SIGKILL to that same view (`crash_to_removal`), with the default failure detector.

The process start-up (Python imports, ~0.5-1 s on this machine) is not part of any delay.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc

from haa.cluster.hostprocs import MemberGroup, MemberHost, wait_for

CORE = 3


def _members(h: MemberHost) -> list[str]:
    return list(h.client.status().members)


def _view_at(host: MemberHost, since: float, pred: Callable[[dict[str, Any]], bool]) -> float | None:
    for e in host.events(since, {"view"}):
        if pred(e["fields"]):
            return float(e["ts"])
    return None


class Ap2Run:
    def __init__(self, root: Path, max_hosts: int, log: Callable[[str], None]) -> None:
        self.root = root
        # membership only: the agent layer's own transactions would add OAC traffic to what AP-2 measures
        self.cluster = MemberGroup(root, max_hosts, core=CORE, args=["--no-agents"])
        self.token = self.cluster.token
        self.hosts = self.cluster.hosts
        self.log = log

    def close(self) -> None:
        self.cluster.close()

    def group(self, n: int) -> list[MemberHost]:
        return [self.hosts[f"h{i}"] for i in range(1, n + 1)]

    def wait_members(self, hosts: list[MemberHost], names: set[str], timeout: float = 30.0) -> None:
        wait_for(lambda: all(set(_members(h)) == names for h in hosts), timeout, f"view {sorted(names)}")

    def join(self, h: MemberHost, others: list[MemberHost]) -> dict[str, float]:
        t0 = time.time()
        h.start()
        names = {x.name for x in others} | {h.name}
        self.wait_members([*others, h], names)
        time.sleep(0.05)
        start = h.events(t0, {"startup"})
        if not start:
            raise RuntimeError(f"{h.name}: no startup event in its log")
        ts = float(start[-1]["ts"])
        leader = self.hosts[_members(others[0])[0]]

        def adds(f: dict[str, Any]) -> bool:
            return h.name in f.get("added", [])

        at_leader = _view_at(leader, ts, adds)
        at_all = [_view_at(x, ts, adds) for x in others]
        found = [a for a in at_all if a is not None]
        if at_leader is None or len(found) != len(at_all):
            raise RuntimeError(f"{h.name}: join not found in every member's log")
        return {"join": at_leader - ts, "join_all": max(found) - ts}

    def leave(self, h: MemberHost, others: list[MemberHost]) -> float:
        t0 = time.time()
        reply = h.client.leave(exit=True, timeout=30)
        if not reply.left:
            raise RuntimeError(f"{h.name}: leave failed: {reply.reason}")
        assert h.proc is not None
        h.proc.wait(10)
        self.wait_members(others, {x.name for x in others})
        req = h.events(t0, {"leave_requested"})
        ts = float(req[-1]["ts"])
        ends = [_view_at(x, ts, lambda f: h.name in f.get("removed", [])) for x in others]
        found = [e for e in ends if e is not None]
        if len(found) != len(ends):
            raise RuntimeError(f"{h.name}: leave not found in every member's log")
        return max(found) - ts

    def crash(self, h: MemberHost, others: list[MemberHost]) -> dict[str, float]:
        time.sleep(0.3)  # let the failure detectors settle after the join
        t_kill = time.time()
        h.kill()
        self.wait_members(others, {x.name for x in others})
        time.sleep(0.05)
        susp = [
            float(e["ts"])
            for x in others
            for e in x.events(t_kill, {"suspicion"})
            if e["fields"].get("peer") == h.name and e["fields"].get("suspected")
        ]
        ends = [_view_at(x, t_kill, lambda f: h.name in f.get("removed", [])) for x in others]
        found = [e for e in ends if e is not None]
        if not susp or len(found) != len(ends):
            raise RuntimeError(f"{h.name}: suspicion or removal not found in the survivors' logs")
        end = max(found)
        return {"remove": end - min(susp), "crash_to_removal": end - t_kill}


def _stats(xs: list[float]) -> dict[str, float]:
    if not xs:
        return {}
    return {
        "n": len(xs),
        "mean": statistics.fmean(xs),
        "median": statistics.median(xs),
        "max": max(xs),
        "min": min(xs),
    }


def run_ap2(root: Path, max_hosts: int = 10, reps: int = 3, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Grow the group from 1 to `max_hosts` hosts, measuring at each size (see the module docstring)."""
    run = Ap2Run(root, max_hosts, log)
    rows: list[dict[str, Any]] = []
    try:
        first = run.hosts["h1"]
        first.start()
        wait_for(lambda: _members(first) == ["h1"], 30, "h1's group of one")
        for n in range(2, max_hosts + 1):
            h = run.hosts[f"h{n}"]
            others = run.group(n - 1)
            samples: dict[str, list[float]] = {"join": [], "join_all": [], "leave": [], "remove": [], "c2r": []}

            def add_join(j: dict[str, float], s: dict[str, list[float]] = samples) -> None:
                s["join"].append(j["join"])
                s["join_all"].append(j["join_all"])

            add_join(run.join(h, others))
            for _ in range(reps):
                samples["leave"].append(run.leave(h, others))
                add_join(run.join(h, others))
            for _ in range(reps):
                c = run.crash(h, others)
                samples["remove"].append(c["remove"])
                samples["c2r"].append(c["crash_to_removal"])
                add_join(run.join(h, others))
            row: dict[str, Any] = {
                "hosts": n,
                "join": _stats(samples["join"]),
                "join_all": _stats(samples["join_all"]),
                "leave": _stats(samples["leave"]),
                "remove": _stats(samples["remove"]),
                "crash_to_removal": _stats(samples["c2r"]),
            }
            rows.append(row)
            log(
                f"n={n}: join {row['join']['median'] * 1e3:.0f} ms, leave {row['leave']['median'] * 1e3:.0f} ms, "
                f"remove {row['remove']['median'] * 1e3:.0f} ms, crash->removal "
                f"{row['crash_to_removal']['median'] * 1e3:.0f} ms"
            )
    except (grpc.RpcError, RuntimeError, AssertionError) as e:
        log(f"AP-2 stopped: {e}")
        raise
    finally:
        run.close()
    return rows
