"""Maximum-size operator messages with many in flight (docs/limits.md, "Control API and agent messages"; the
reliability probe's D4): each host's RSS and event-loop stalls while one client floods an agent.

`--hosts` membership-mode `haa-hostd` processes (h1-h3 core) form a group; a `counter` agent is spawned and
moved to the owner host (`--owner`, default h2). One client then sends `--sends` `AgentSend` of
MAX_AGENT_MESSAGE bytes to it with `--inflight` calls in flight, through the entry host (`--via`, default h1:
the messages cross a host link; `--via h2` sends them straight to the owner), retrying a send the host refuses
as over its budget (`RESOURCE_EXHAUSTED`) after `--backoff` seconds. A sampler reads every host's RSS every
50 ms. Afterwards: per host the RSS at start, its peak and 10 s after the flood, `loop_lag_max_ms` and the
largest `loop_stall` logged during the flood; the sends accepted, refused and failed; how long the flood took;
whether the view changed; and how long a DDB write then takes. Prints a summary; `--out FILE` writes it as JSON,
`--runs N` repeats it on fresh groups (and prints mean ± spread).

    .venv/bin/python -m haa.lab.bench.agent_send_flood --sends 300 --inflight 32 --runs 3
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import grpc
import psutil

from haa.cluster.hostprocs import MemberGroup, MemberHost, wait_for
from haa.core.ddb import ops as ddb
from haa.hostd.linkcommon import MD_TOKEN
from haa.pb import control_pb2 as cpb
from haa.pb import control_pb2_grpc
from haa.sdk.channel import MAX_AGENT_MESSAGE

MiB = 1 << 20


class RssSampler(threading.Thread):
    """The RSS of every host process every `interval` seconds."""

    def __init__(self, hosts: dict[str, MemberHost], interval: float = 0.05) -> None:
        super().__init__(daemon=True)
        self.procs = {n: psutil.Process(h.proc.pid) for n, h in hosts.items() if h.proc is not None}
        self.interval = interval
        self.samples: dict[str, list[tuple[float, int]]] = {n: [] for n in self.procs}
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.is_set():
            t = time.monotonic()
            for n, p in self.procs.items():
                with contextlib.suppress(psutil.Error):
                    self.samples[n].append((t, p.memory_info().rss))
            self.halt.wait(self.interval)

    def peak(self, name: str, t0: float, t1: float) -> int:
        return max((r for t, r in self.samples[name] if t0 <= t <= t1), default=0)


def owner_of(h: MemberHost, agent: str) -> str:
    """The owner of `agent` if the table says it is active and that host runs it, else ""."""
    for a in h.client.agent_list().agents:
        if a.id == agent and a.status == "active":
            return a.owner
    return ""


def flood(address: str, token: str, agent: str, sends: int, inflight: int, backoff: float,
          payload: bytes, deadline: float = 60.0) -> dict[str, Any]:
    """`sends` AgentSend of `payload` to `agent` through `address`, `inflight` at a time; a refusal for lack of
    budget is retried after `backoff` s. Counts the outcomes."""
    opts = [("grpc.max_send_message_length", 64 * MiB), ("grpc.max_receive_message_length", 64 * MiB)]
    out: dict[str, Any] = {"ok": 0, "refused": 0, "failed": 0, "errors": {}, "latency_ms": []}
    lock = threading.Lock()
    with grpc.insecure_channel(address, options=opts) as ch:
        stub = control_pb2_grpc.HostControlStub(ch)
        md = ((MD_TOKEN, token),)

        def one(_i: int) -> None:
            while True:
                t0 = time.monotonic()
                try:
                    r = stub.AgentSend(cpb.AgentSendRequest(ref=agent, payload=payload), metadata=md,
                                       timeout=deadline)
                except grpc.RpcError as e:
                    with lock:
                        if e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                            out["refused"] += 1
                            key = (e.details() or "")[:120]
                            out["errors"][key] = out["errors"].get(key, 0) + 1
                        else:
                            out["failed"] += 1
                            key = f"{e.code().name}: {(e.details() or '')[:100]}"
                            out["errors"][key] = out["errors"].get(key, 0) + 1
                            return
                    time.sleep(backoff)
                    continue
                with lock:
                    if r.ok:
                        out["ok"] += 1
                        out["latency_ms"].append(round(1000 * (time.monotonic() - t0), 1))
                    else:
                        out["failed"] += 1
                        out["errors"][r.reason[:120]] = out["errors"].get(r.reason[:120], 0) + 1
                return

        with ThreadPoolExecutor(inflight) as pool:
            list(pool.map(one, range(sends)))
    lat = sorted(out.pop("latency_ms"))
    out["latency_ms_p50"] = lat[len(lat) // 2] if lat else None
    out["latency_ms_max"] = lat[-1] if lat else None
    return out


def run(hosts: int = 4, sends: int = 300, inflight: int = 32, via: str = "h1", owner: str = "h2",
        backoff: float = 0.05, settle: float = 10.0, root: Path | None = None, log: Any = print) -> dict[str, Any]:
    names = [f"h{i}" for i in range(1, hosts + 1)]
    with tempfile.TemporaryDirectory(prefix="haa-flood-") as tmp:
        group = MemberGroup(root or Path(tmp), names, core=names[:3], token="flood-" + str(time.time_ns()),
                            args=["--rebalance-period", "0"])
        try:
            group.form(60, what=f"a group of {hosts}")
            hs = group.hosts
            first = hs[names[0]]
            r = first.client.agent_spawn("counter", json.dumps({"period": 1.0}).encode(), timeout=30)
            assert r.ok, r
            agent = r.id
            wait_for(lambda: owner_of(first, agent), 30, "the counter active")
            if owner_of(first, agent) != owner:
                assert first.client.agent_move(agent, owner, timeout=30).ok
                wait_for(lambda: owner_of(first, agent) == owner, 30, f"the counter on {owner}")
            time.sleep(1.0)
            view0 = {n: h.status().view for n, h in hs.items()}
            lag0 = {n: h.status().counters.values.get("loop_lag_max_ms", 0) for n, h in hs.items()}
            sampler = RssSampler(hs)
            sampler.start()
            time.sleep(0.5)
            t_wall = time.time()
            t0 = time.monotonic()
            res = flood(hs[via].address, group.token, agent, sends, inflight, backoff, b"m" * MAX_AGENT_MESSAGE)
            t1 = time.monotonic()
            took = t1 - t0
            w0 = time.monotonic()
            committed = hs[names[-1]].client.ddb_write([ddb.put("bench/flood/probe", "blob", b"x")],
                                                        timeout=30).committed
            write_ms = round(1000 * (time.monotonic() - w0), 1)
            time.sleep(settle)
            sampler.halt.set()
            sampler.join()
            st = {n: h.status() for n, h in hs.items()}
            per_host: dict[str, Any] = {}
            for n, h in hs.items():
                stalls = [(e["fields"]["ms"], e["fields"].get("cpu_ms", 0)) for e in h.events(t_wall, {"loop_stall"})]
                worst = max(stalls, default=(0, 0))
                c = st[n].counters.values
                per_host[n] = {
                    "rss_start_mib": round(sampler.samples[n][0][1] / MiB, 1),
                    "rss_peak_mib": round(sampler.peak(n, t0, t1 + 2.0) / MiB, 1),
                    "rss_after_mib": round(sampler.samples[n][-1][1] / MiB, 1),
                    "loop_lag_max_ms": c.get("loop_lag_max_ms", 0),
                    "loop_lag_max_before_ms": lag0[n],
                    "largest_stall_ms": worst[0],
                    "largest_stall_cpu_ms": min(worst),  # the loop thread's CPU in it: the rest is the scheduler
                    "stalls_over_250ms": sum(ms > 250 for ms, _cpu in stalls),
                    "counters": {k: v for k, v in c.items() if k.startswith(("budget.", "acks_", "dropped_"))},
                }
            out = {
                "hosts": hosts, "sends": sends, "inflight": inflight, "via": via, "owner": owner,
                "message_bytes": MAX_AGENT_MESSAGE, "seconds": round(took, 2),
                "mib_per_s": round(res["ok"] * MAX_AGENT_MESSAGE / MiB / took, 1) if took > 0 else None,
                **res,
                "view_changed": any(st[n].view != view0[n] for n in hs),
                "write_after_ms": write_ms, "write_committed": committed,
                "per_host": per_host,
            }
            log(f"{res['ok']}/{sends} accepted in {took:.1f} s, {res['refused']} refusals, {res['failed']} failed; "
                f"view changed: {out['view_changed']}; write after {write_ms:.0f} ms")
            for n, p in per_host.items():
                log(f"  {n}: RSS {p['rss_start_mib']:.0f} -> peak {p['rss_peak_mib']:.0f} -> {p['rss_after_mib']:.0f}"
                    f" MiB, largest stall {p['largest_stall_ms']} ms ({p['largest_stall_cpu_ms']} ms of CPU)")
            return out
        finally:
            group.close()


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean ± spread (half the range) over runs: the largest peak RSS of any host, the largest stall."""
    def ms(xs: list[float]) -> dict[str, float]:
        return {"mean": round(statistics.fmean(xs), 1), "spread": round((max(xs) - min(xs)) / 2, 1),
                "min": round(min(xs), 1), "max": round(max(xs), 1)}

    peak = [max(p["rss_peak_mib"] for p in r["per_host"].values()) for r in runs]
    stall = [max(p["largest_stall_ms"] for p in r["per_host"].values()) for r in runs]
    owner = [r["per_host"][r["owner"]]["rss_peak_mib"] for r in runs]
    via = [r["per_host"][r["via"]]["rss_peak_mib"] for r in runs]
    return {"runs": len(runs), "rss_peak_mib_max_host": ms(peak), "rss_peak_mib_via": ms(via),
            "rss_peak_mib_owner": ms(owner), "largest_stall_ms": ms(stall),
            "seconds": ms([r["seconds"] for r in runs]),
            "view_changed": sum(r["view_changed"] for r in runs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hosts", type=int, default=4)
    ap.add_argument("--sends", type=int, default=300)
    ap.add_argument("--inflight", type=int, default=32)
    ap.add_argument("--via", default="h1")
    ap.add_argument("--owner", default="h2")
    ap.add_argument("--backoff", type=float, default=0.05)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--keep", type=Path, help="run the hosts under this folder (their logs kept), not a temporary one")
    a = ap.parse_args()
    runs = [run(a.hosts, a.sends, a.inflight, a.via, a.owner, a.backoff, root=a.keep / f"run{i}" if a.keep else None)
            for i in range(a.runs)]
    s = summary(runs)
    print(json.dumps(s))
    if a.out:
        a.out.write_text(json.dumps({"summary": s, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
