"""The Docker Swarm stack (compose/stack.yaml, haa.cluster.swarm_backend): a single-node swarm on
this machine's engine (`docker swarm init --advertise-addr 127.0.0.1` when the engine is in none; it leaves the
swarm again at the end if it made it and nothing else runs in it).

One stack of its own (`haaswarm<pid>`, so a user's `haa` stack is never touched) is deployed with
`haactl cluster up --swarm --tls --hosts 6` (core1..core3 and host1..host3; mutual TLS, every task enrolled for
a certificate of its own: haa.cluster.enroll): the six form one group. A client with the token but without a
certificate is refused, and a task asking for another host's certificate is refused. A counter pair
(haa/lab/demoagents.py) is spawned. `docker service scale <stack>_host=5` adds host4 and host5: the group grows to
eight. A1 is moved to host2, and host2's task container is killed (`docker kill`, SIGKILL): the group removes
host2, the agent is recovered on a survivor, and the swarm's replacement task of slot 2 (same name, same data
volume) joins as a new incarnation. A rolling update of the core service (`docker service update --force`: one
task at a time, stop-first) renews core1..core3 while the group keeps at least two of them. Then the counters
must be active on member hosts, still exchanging pings, with no message lost (outside Alg. 8's documented loss
after a recovery), none out of order, none duplicated; `agent events` (read from the tasks' logs) shows A1's
crash on host2 and its recovery elsewhere; the enrollment service issued a certificate to each of the eight
names, and a second one to host2's replacement and to each renewed core task.
`haactl cluster down --swarm` removes the stack, its data volumes and its TLS directory. Marker `docker`:
skipped without an engine or the image (failed with HAA_REQUIRE_DOCKER=1). ≈ 2 minutes on a loaded 2-core
machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import grpc
import pytest
from chaoslib import docker_problem
from helpers import Cli, wait_sync

from haa.cluster.backend import ClusterError, wait_until
from haa.cluster.swarm_backend import SwarmBackend
from haa.core.ddb import objects as ddb
from haa.hostd.control import ControlClient
from haa.pb import control_pb2 as cpb

pytestmark = pytest.mark.docker
CORE = ["core1", "core2", "core3"]


def docker(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)


class Swarm(Cli):
    """`haactl ... --swarm` for one stack, and its backend."""

    def __init__(self, stack: str) -> None:
        super().__init__(extra=("--swarm",), env={"HAA_SWARM_STACK": stack})
        self.stack = stack
        self.backend = SwarmBackend(stack=stack)

    def counters(self) -> dict[str, dict[str, Any]]:
        """The counters' stats as published in the DDB (`demo/<agent name>`), read on a member."""
        h = self.backend.host(self.backend.pick_host())
        c = self.backend.connect(h, 5.0)
        try:
            objs = c.ddb_get(prefix="demo/").objects
        finally:
            c.close()
        t = ddb.TYPES["json"]
        return {o.key.removeprefix("demo/"): t.public(t.decode(o.value)[0]) for o in objs if o.type == "json"}


#: what a poll of the swarm takes for "not yet" (a failing haactl command, the backend's errors)
NOT_YET = (AssertionError, ClusterError)


@pytest.fixture(scope="module")
def swarm() -> Iterator[Swarm]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    made_swarm = False
    state = docker("info", "--format", "{{.Swarm.LocalNodeState}}").stdout.strip()
    if state == "inactive":
        r = docker("swarm", "init", "--advertise-addr", "127.0.0.1")
        assert r.returncode == 0, f"docker swarm init: {r.stderr}"
        made_swarm = True
    s = Swarm(f"haaswarm{os.getpid()}")
    try:
        yield s
    finally:
        with contextlib.suppress(ClusterError):
            for h in s.backend.hosts():  # a paused task would not stop
                if h.state == "paused":
                    s.backend.resume(h.name)
        print(s("cluster", "down", ok=False).output)
        if made_swarm and not docker("service", "ls", "-q").stdout.strip():
            docker("swarm", "leave", "--force")


def test_swarm_stack_scales_and_replaces_a_killed_task(swarm: Swarm) -> None:
    b = swarm.backend
    t0 = time.monotonic()
    up = swarm.json("cluster", "up", "--hosts", "6", "--tls", "--timeout", "150")
    first = [*CORE, "host1", "host2", "host3"]
    assert sorted(up["members"]) == sorted(first), up
    assert up["backend"] == "swarm"
    print(f"6 hosts formed one group in {up['formed_seconds']:.1f} s")
    hosts = {h.name: h for h in b.hosts()}
    assert [n for n, h in hosts.items() if h.core] == CORE
    assert all(h.state == "alive" and h.metrics_url for h in hosts.values()), hosts
    st = swarm.json("cluster", "status", "--sample", "0")
    assert st["agreed"] and st["ddb_hashes_equal"] and sorted(st["members"]) == sorted(first), st

    # mutual TLS: a client with the token but no certificate is refused; a task cannot enroll as another host
    plain = ControlClient(hosts["host1"].address, b.token, timeout=3)
    with pytest.raises(grpc.RpcError):
        plain.status()
    plain.close()
    r = b.container("host1").exec_run(["/opt/haa/bin/python", "-m", "haa.cluster.enroll", "request", "--name",
                                        "core2", "--out", "/tmp/stolen", "--timeout", "2"])
    assert r.exit_code == 2 and b"403 core2 resolves to" in r.output, r.output

    # a counter pair, A1 on the host that will be killed
    swarm("agent", "spawn", "counter", "--config", json.dumps({"spawn_peer": True, "period": 0.1, "backup_every": 5}))
    wait_sync(lambda: (a := swarm.agents()) and len(a) == 2 and all(x["state"] == "active" for x in a.values()),
              60, "both counters active", interval=0.5, ignore=NOT_YET)

    # docker service scale: two more hosts join
    t1 = time.monotonic()
    assert b.next_name() == "host4"
    r = docker("service", "scale", "--detach", f"{swarm.stack}_host=5")
    assert r.returncode == 0, r.stderr
    eight = [*first, "host4", "host5"]
    f, _ = wait_until(lambda: b.formation(eight), 120, what="8 hosts in one group")
    print(f"scaled to 8: one group in {time.monotonic() - t1:.1f} s (view {f.view})")

    # a killed task: removed from the group, then its replacement (same slot, same name) joins again. A1 is
    # moved there first (now: the joins of host4 and host5 may have rebalanced the agents)
    # (the allocation may place it elsewhere again; the victim is the non-core host that runs it)
    def a1_host() -> str | None:
        a = swarm.agents()["A1"]
        return a["host"] if a["state"] == "active" and a["host"] in eight and a["host"] not in CORE else None

    for _attempt in range(3):
        # --no-wait: what counts is A1 active on some non-core host (polled next), not on host2 exactly; waiting
        # for host2 failed a run where the allocation moved A1 on within the move's 30 s
        swarm("agent", "move", "A1", "host2", "--no-wait")
        with contextlib.suppress(AssertionError):
            victim_host = wait_sync(a1_host, 20, "A1 active on a non-core host", interval=0.5, ignore=NOT_YET)
            break
    else:
        raise AssertionError(f"A1 never settled on a non-core host: {swarm.agents()}")
    inc_before = {m.name: m.incarnation for m in b.call("core1", lambda c: c.status(), "Status").member_info}
    t2 = time.monotonic()
    victim_host = a1_host() or victim_host  # where A1 is now (the allocation may have moved it back meanwhile)
    victim = b.container(victim_host)
    r = docker("kill", victim.id)
    assert r.returncode == 0, r.stderr
    wait_sync(lambda: b.host(victim_host).state == "killed", 20, f"{victim_host} killed", interval=0.5,
              ignore=NOT_YET)
    wait_until(lambda: b.removed_everywhere([victim_host]), 30, what=f"{victim_host} removed from every view")
    t_removed = time.monotonic() - t2
    f, _ = wait_until(lambda: b.rejoined(victim_host), 90, what=f"the replacement of {victim_host} to join")
    assert b.container(victim_host).id != victim.id  # a new task's container
    inc_after = {m.name: m.incarnation for m in b.call("core1", lambda c: c.status(), "Status").member_info}
    assert inc_after[victim_host] != inc_before[victim_host]
    wait_until(lambda: b.formation(eight), 60, what="8 hosts in one group again")
    print(f"{victim_host} removed {t_removed:.1f} s after the kill, its replacement a member "
          f"{time.monotonic() - t2:.1f} s after the kill (view {f.view})")

    # a rolling update of the core (`docker service update --force`): one task at a time, stop-first, so the
    # group keeps two of its three core processes throughout; every core host ends as a new incarnation
    t3 = time.monotonic()
    r = docker("service", "update", "--force", "--detach", f"{swarm.stack}_core")
    assert r.returncode == 0, r.stderr
    fewest, service = len(CORE), b.docker.services.get(f"{swarm.stack}_core")
    timeline: list[str] = []  # each new view of the update: when, its number, its core members (printed on failure)

    def updated() -> bool:
        nonlocal fewest
        views = [x for x in b.statuses(timeout=1.0).values() if isinstance(x, cpb.StatusReply) and x.member]
        if views:
            newest = max(views, key=lambda x: x.view)
            fewest = min(fewest, len([m for m in newest.members if m in CORE]))
            line = f"view {newest.view}: {sorted(m for m in newest.members if m in CORE)}"
            if not timeline or not timeline[-1].endswith(line):
                timeline.append(f"{time.monotonic() - t3:6.1f} s {line}")
        service.reload()
        return (service.attrs.get("UpdateStatus") or {}).get("State") == "completed" and b.formation(eight).done

    wait_sync(updated, 240, "the core's rolling update", interval=0.5, ignore=NOT_YET)
    inc_core = {m.name: m.incarnation for m in b.call("host1", lambda c: c.status(), "Status").member_info}
    assert all(inc_core[n] != inc_after[n] for n in CORE), (inc_core, inc_after)
    assert fewest >= 2, (f"the core was down to {fewest} member(s) during the rolling update:\n"
                         + "\n".join(timeline))
    print(f"rolling update of the core: {time.monotonic() - t3:.1f} s, at least {fewest} core members throughout")
    print("\n".join(timeline))

    # the agents survived the lot: recovered from the killed host, both active on members, counting cleanly
    members = set(eight)
    wait_sync(lambda: (a := swarm.agents()) and len(a) == 2
              and all(x["state"] == "active" and x["host"] in members for x in a.values()),
              60, "both counters active on members", interval=0.5, ignore=NOT_YET)
    before = wait_sync(lambda: (c := swarm.counters()) and len(c) == 2 and c, 30, "counter stats", interval=0.5,
                       ignore=NOT_YET)

    def progressing() -> dict[str, dict[str, Any]] | None:
        now = swarm.counters()
        ok = len(now) == 2 and all(now[n]["received"] > before[n]["received"] for n in now)
        return now if ok else None

    after = wait_sync(progressing, 30, "both counters receiving", interval=0.5, ignore=NOT_YET)
    for name, s in after.items():
        assert s["lost"] == 0 and s["out_of_order"] == 0 and s["duplicate"] == 0, (name, s)
    evs = [json.loads(ln) for ln in swarm.out("agent", "events", "--json").splitlines()]  # read from the tasks' logs
    a1 = [e for e in evs if e["name"] == "A1"]
    crash = [e for e in a1 if e["event"] == "crashed" and e["host"] == victim_host]
    # was A1 on the victim when it was killed? Its last event there before the victim's removal says: the
    # allocation may have moved it off between the check above and the kill (seen in CI: thawed by host2, then
    # frozen on host2 and thawed by core1 before the kill) — then nothing of A1 may have crashed there. Killed
    # while freezing, it is still there: it crashes and is recovered from its backup (seen here too)
    removed = next(i for i, e in enumerate(evs) if e["text"] == f"{victim_host} removed")
    there = [e for e in evs[:removed] if e["name"] == "A1" and e["host"] == victim_host]
    on_victim = bool(there) and there[-1]["event"] not in ("frozen", "crashed")  # freezing: still there
    if on_victim:
        assert crash, "\n".join(e["text"] for e in evs)
        assert any(e["event"] == "recovered" and e["host"] != victim_host and e["time"] > crash[0]["time"]
                   for e in a1)
    else:
        assert not crash, "\n".join(e["text"] for e in evs)
        print(f"A1 had left {victim_host} before the kill: its recovery was not exercised in this run")

    # every task enrolled for its own certificate: the scaled ones and the replacement too
    issued: dict[str, int] = {}
    service = {"label": f"com.docker.swarm.service.name={swarm.stack}_enroll"}
    for c in b.docker.containers.list(all=True, filters=service, ignore_removed=True):
        for ln in c.logs().decode().splitlines():
            rec = json.loads(ln)
            if rec["event"] == "enroll_issued":
                issued[rec["name"]] = issued.get(rec["name"], 0) + 1
    assert set(issued) == set(eight) and all(issued[n] == 2 for n in [victim_host, *CORE]), issued
    print("counters:", {n: {k: s[k] for k in ("received", "lost", "lost_after_recovery")} for n, s in after.items()})
    print(f"swarm scenario: {time.monotonic() - t0:.1f} s")

    # down removes the stack and the data volumes of every slot
    swarm("cluster", "down")
    assert not b.hosts() and not b.volumes() and not b.tls_dir.exists()
