"""A host rejoins a group whose state is larger than one link frame (docs/membership.md, "State transfer").

The reliability probe: after 72 x 1 MiB of puts (or a `DdbLoad` of 213 MB) a killed and restarted host never
rejoined — its state arrived as one link message over the 64 MiB frame bound, the sponsor's links failed with
"INTERNAL: Internal error from Core" 43 times and the leader was expelled too. The DDB is bounded
(`MAX_DDB_BYTES`), but the agent table adds agents' configs, states, backups and queues on top, so the state
crosses links in parts (`SNAPSHOT_PART`). Here: ~46 MB of DDB and 26 agents with ~1 MB configs (~72 MB of
state), writes going on, h3 killed and restarted: it is back in the view with an equal replica."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

from hostilecluster import agreed

from haa.cluster.hostprocs import MemberGroup
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import ops as ddb

NAMES = ["h1", "h2", "h3"]


def test_a_restarted_host_rejoins_a_state_larger_than_a_link_frame(tmp_path: Path) -> None:
    group = MemberGroup(tmp_path, NAMES, core=NAMES, token="big-state-" + str(time.time_ns()),
                        args=["--rebalance-period", "0"])
    try:
        for h in group.hosts.values():
            h.start()
        hs = list(group.hosts.values())
        wait(lambda: agreed(hs), 60, "a group of 3")
        h1 = hs[0].client
        blob = b"\x07" * 1_000_000  # under MAX_VALUE_BYTES (1 MiB)
        for i in range(23):  # ~46 MB of the 48 MiB the DDB takes, 2 MB a batch
            r = h1.ddb_write([ddb.put(f"big/{i:02d}a", "blob", blob), ddb.put(f"big/{i:02d}b", "blob", blob)],
                             timeout=60)
            assert r.committed, r.reason
        config = json.dumps({"count": 0, "config": "c" * 1_000_000}).encode()
        for _ in range(26):
            assert h1.agent_spawn("spawner", config, timeout=60).ok
        wait(lambda: sum(a.status == "active" for a in h1.agent_list().agents) == 26, 120, "26 spawners active")
        stop = threading.Event()
        written: list[int] = []

        def load() -> None:
            i = 0
            while not stop.is_set():
                op = ddb.put(f"load/{i % 50}", "blob", str(i).encode())
                try:
                    if hs[1].client.ddb_write([op], timeout=10).committed:
                        written.append(i)
                except Exception:  # a write may time out while the group changes
                    pass
                i += 1
                time.sleep(0.02)

        writer = threading.Thread(target=load, daemon=True)
        writer.start()
        try:
            h3 = group.hosts["h3"]
            h3.kill9()
            wait(lambda: len(group.members("h1")) == 2, 60, "h3 removed")
            h3.start()
            wait(lambda: agreed(hs), 120, "h3 back in the view")
        finally:
            stop.set()
            writer.join(15)
        wait(lambda: len({(s.ddb_seq, s.ddb_hash) for s in (h.status() for h in hs)}) == 1, 30, "equal replicas")
        assert len(written) >= 5
        t0 = time.monotonic()
        assert hs[2].client.ddb_write([ddb.put("load/after", "blob", b"x")], timeout=10).committed
        assert time.monotonic() - t0 < 1.0
        s3 = group.hosts["h3"].status()
        assert s3.counters.values.get("core.snapshot_parts_joined", 0) >= 1, "h3's state did not come in parts"
    finally:
        group.close()
