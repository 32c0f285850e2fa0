"""A burst of agent spawns on a fresh local group (docs/limits.md; the reliability probe's D3): how long until
every agent is active, and how the DDB answers meanwhile.

`--hosts` membership-mode `haa-hostd` processes (h1-h3 core), then `--agents` `counter` spawns sent through the
hosts in turn from `--clients` threads as fast as they are answered; every 2 s the agent states (from h1's
table) and the latency of one DDB put through h2 are sampled, until every accepted spawn is active or
`--timeout` passes. Prints one line per sample and a summary; `--out FILE` writes the samples as JSON.

    .venv/bin/python -m haa.lab.bench.spawn_burst --agents 150 --hosts 4
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from haa.cluster.hostprocs import MemberGroup, wait_for
from haa.core.ddb import ops as ddb


def run(agents: int, hosts: int, clients: int, timeout: float, log: Any = print) -> dict[str, Any]:
    names = [f"h{i}" for i in range(1, hosts + 1)]
    with tempfile.TemporaryDirectory(prefix="haa-burst-") as tmp:
        group = MemberGroup(Path(tmp), names, core=names[:3], token="spawn-burst-" + str(time.time_ns()))
        try:
            for h in group.hosts.values():
                h.start()
            hs = list(group.hosts.values())
            wait_for(lambda: all(len(h.status().members) == hosts for h in hs), 60, f"a group of {hosts}")
            t0 = time.monotonic()

            def spawn(i: int) -> Any:
                return hs[i % hosts].client.agent_spawn("counter", json.dumps({"period": 1.0}).encode(), timeout=60)

            with ThreadPoolExecutor(clients) as pool:
                replies = list(pool.map(spawn, range(agents)))
            accepted = sum(r.ok for r in replies)
            log(f"{accepted}/{agents} spawns accepted in {time.monotonic() - t0:.1f} s")
            samples: list[dict[str, Any]] = []
            done_at = None
            while time.monotonic() - t0 < timeout:
                states: dict[str, int] = {}
                for a in hs[0].client.agent_list().agents:
                    states[a.status] = states.get(a.status, 0) + 1
                w0 = time.monotonic()
                ok = hs[1 % hosts].client.ddb_write([ddb.put("bench/burst/probe", "blob", b"x")], timeout=30).committed
                sample = {"t": round(time.monotonic() - t0, 2), "states": states,
                          "write_ms": round(1000 * (time.monotonic() - w0), 1), "write_ok": ok}
                samples.append(sample)
                log(f"t={sample['t']:6.1f} s {states} put {sample['write_ms']:.0f} ms")
                if states.get("active", 0) == accepted:
                    done_at = sample["t"]
                    break
                time.sleep(2.0)
            return {"agents": agents, "hosts": hosts, "clients": clients, "accepted": accepted,
                    "all_active_after_s": done_at, "samples": samples}
        finally:
            group.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=150)
    ap.add_argument("--hosts", type=int, default=4)
    ap.add_argument("--clients", type=int, default=16)
    ap.add_argument("--timeout", type=float, default=180.0)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    r = run(a.agents, a.hosts, a.clients, a.timeout)
    print(f"all {r['accepted']} active after {r['all_active_after_s']} s" if r["all_active_after_s"] is not None
          else f"not all active within {a.timeout:g} s")
    if a.out:
        a.out.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
