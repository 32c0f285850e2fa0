"""Chaos on a 10-container compose cluster, in order on one cluster:

1. the ten containers form one group with all ten members;
2. killing the leader, then a random member, removes each from every view (a killed container refuses
   connections); restarted, both rejoin with a full DDB equal to everyone else's;
3. a paused container (a hung host: TCP connections stay open, calls time out) is removed and, resumed,
   comes back as a new incarnation with an equal DDB;
4. while clients stream DDB writes through random hosts, hosts are killed and paused at random; at the end
   every replica's hash is equal and every acknowledged write is present on every replica.
"""

from __future__ import annotations

import os
import random
import socket
import threading
import time
from typing import Any

import grpc
import pytest
from chaoslib import NAMES, Chaos

from haa.core.ddb import objects as ddb
from haa.core.ddb import ops as ddb_ops

pytestmark = pytest.mark.docker


def put(chaos: Chaos, host: str, key: str, value: Any, timeout: float = 5.0) -> bool:
    """One DDB put through `host`; True if it was acknowledged (committed, applied, op ok)."""
    c = chaos.client(host, timeout=timeout)
    try:
        r = c.ddb_write([ddb_ops.put(key, "json", value)], timeout=timeout)
        return bool(r.committed and r.results and r.results[0].ok)
    except grpc.RpcError:
        return False
    finally:
        c.close()


def replica(chaos: Chaos, host: str, prefix: str) -> dict[str, Any]:
    c = chaos.client(host, timeout=10)
    try:
        return {
            o.key: ddb.TYPES[o.type].public(ddb.TYPES[o.type].decode(o.value)[0])
            for o in c.ddb_get(prefix=prefix).objects
        }
    finally:
        c.close()


def port_of(chaos: Chaos, name: str) -> int:
    return int(chaos.addr[name].rsplit(":", 1)[1])


def test_ten_containers_form_one_group(chaos: Chaos) -> None:
    st = chaos.wait_converged(NAMES, 30)
    members = list(next(iter(st.values())).members)
    assert sorted(members) == sorted(NAMES)
    for name, r in st.items():
        assert r.mode == "membership" and r.group_correct and not r.suspicions
        assert r.leader == members[0] and r.rank == members.index(name)
    assert members[0] in ("h1", "h2", "h3")  # a core process leads


def test_kill_leader_then_random_member_and_restart_both(chaos: Chaos) -> None:
    acked = {}
    for i in range(30):
        host = chaos.rng.choice(NAMES)
        if put(chaos, host, f"pre/{i}", {"i": i, "via": host}):
            acked[f"pre/{i}"] = {"i": i, "via": host}
    assert len(acked) == 30
    leader = chaos.leader()
    t0 = time.monotonic()
    chaos.backend.kill(leader)
    with pytest.raises(ConnectionRefusedError):  # a crashed host: connections are refused
        socket.create_connection(("127.0.0.1", port_of(chaos, leader)), timeout=2).close()
    chaos.wait_removed([leader], 15)
    print(f"leader {leader} killed: removed from every view after {time.monotonic() - t0:.2f} s")
    new_leader = chaos.leader()
    assert new_leader != leader
    victim = chaos.rng.choice([n for n in chaos.alive() if n != new_leader])
    t0 = time.monotonic()
    chaos.backend.kill(victim)
    chaos.wait_removed([leader, victim], 15)
    print(f"member {victim} killed: removed from every view after {time.monotonic() - t0:.2f} s")
    for i in range(30, 50):  # while both are down: they must get these from their sponsors
        host = chaos.rng.choice(chaos.alive())
        assert put(chaos, host, f"pre/{i}", {"i": i, "via": host}), f"write through {host} with 8 members"
        acked[f"pre/{i}"] = {"i": i, "via": host}
    t0 = time.monotonic()
    for n in (leader, victim):
        chaos.backend.restart(n)
    st = chaos.wait_converged(NAMES, 60)
    print(f"{leader} and {victim} restarted: rejoined with equal replicas after {time.monotonic() - t0:.2f} s")
    sizes = {r.ddb_size for r in st.values()}
    assert len(sizes) == 1 and sizes.pop() >= 50
    for n in (leader, victim):
        assert replica(chaos, n, "pre/") == acked


def test_paused_container_is_removed_and_comes_back(chaos: Chaos) -> None:
    leader = chaos.leader()
    victim = chaos.rng.choice([n for n in NAMES if n != leader])
    chaos.backend.pause(victim)
    t0 = time.monotonic()
    # a hung host: the TCP connection is accepted, the call hangs until its deadline
    socket.create_connection(("127.0.0.1", port_of(chaos, victim)), timeout=2).close()
    c = chaos.client(victim, timeout=1.0)
    with pytest.raises(grpc.RpcError) as e:
        c.status()
    c.close()
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    chaos.wait_removed([victim], 15)
    print(f"{victim} paused: removed from every view after {time.monotonic() - t0:.2f} s")
    for i in range(10):
        assert put(chaos, leader, f"paused/{i}", i)
    t0 = time.monotonic()
    chaos.backend.resume(victim)
    st = chaos.wait_converged(NAMES, 60)
    print(f"{victim} resumed: back in every view with an equal replica after {time.monotonic() - t0:.2f} s")
    assert replica(chaos, victim, "paused/") == {f"paused/{i}": i for i in range(10)}
    assert len({r.ddb_hash for r in st.values()}) == 1


class Writers:
    """Threads that put `chaos/<writer>/<i>` through random hosts and remember what was acknowledged."""

    def __init__(self, chaos: Chaos, n: int) -> None:
        self.chaos = chaos
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.acked: dict[str, Any] = {}
        self.failed = 0
        self.threads = [threading.Thread(target=self.run, args=(w,), daemon=True) for w in range(n)]

    def run(self, w: int) -> None:
        i = 0
        rng = random.Random(self.chaos.seed * 100 + w)  # the chaos thread owns chaos.rng
        while not self.stop.is_set():
            host = rng.choice(NAMES)
            key, value = f"chaos/{w}/{i}", {"w": w, "i": i, "via": host}
            ok = put(self.chaos, host, key, value, timeout=3.0)
            with self.lock:
                if ok:
                    self.acked[key] = value
                else:
                    self.failed += 1
            i += 1

    def __enter__(self) -> Writers:
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(10)


def test_writes_survive_random_kills_and_pauses(chaos: Chaos) -> None:
    seconds = float(os.environ.get("HAA_CHAOS_SECONDS", "45"))
    rng = chaos.rng
    killed: set[str] = set()
    paused: set[str] = set()
    actions: list[str] = []
    t_start = time.monotonic()
    with Writers(chaos, 3) as writers:
        chaos.wait(lambda: writers.acked, 30, "the first acknowledged writes")
        forced = ["kill", "pause"]  # both failure kinds happen in every run
        while time.monotonic() - t_start < seconds:
            down = killed | paused
            up = [n for n in NAMES if n not in down]
            if forced or not down or (len(down) < 3 and rng.random() < 0.6):
                kind = forced.pop(0) if forced else rng.choice(["kill", "pause"])
                victim = rng.choice(up)
                if kind == "kill":
                    chaos.backend.kill(victim)
                    killed.add(victim)
                else:
                    chaos.backend.pause(victim)
                    paused.add(victim)
            else:
                victim = rng.choice(sorted(down))
                if victim in killed:
                    kind = "restart"
                    chaos.backend.restart(victim)
                    killed.discard(victim)
                else:
                    kind = "resume"
                    chaos.backend.resume(victim)
                    paused.discard(victim)
            actions.append(f"{time.monotonic() - t_start:5.1f}s {kind} {victim}")
            time.sleep(rng.uniform(1.5, 4.0))  # the pace of the chaos
        for n in sorted(paused):
            chaos.backend.resume(n)
            actions.append(f"{time.monotonic() - t_start:5.1f}s resume {n} (end)")
        for n in sorted(killed):
            chaos.backend.restart(n)
            actions.append(f"{time.monotonic() - t_start:5.1f}s restart {n} (end)")
        time.sleep(2.0)  # writes go on while the hosts come back
    print("\n".join([f"chaos actions (seed {chaos.seed}):", *actions]))
    t0 = time.monotonic()
    st = chaos.wait_converged(NAMES, 90)
    print(f"all ten back in one view with equal replicas {time.monotonic() - t0:.1f} s after the chaos")
    acked = writers.acked
    print(f"writes: {len(acked)} acknowledged, {writers.failed} not (timeouts, hosts down or rejoining)")
    assert len(acked) > 100, "the group must keep committing writes through the chaos"
    assert len({r.ddb_hash for r in st.values()}) == 1
    for n in NAMES:
        rep = replica(chaos, n, "chaos/")
        missing = [k for k in acked if rep.get(k) != acked[k]]
        assert not missing, f"{n} lacks {len(missing)} acknowledged writes, e.g. {missing[:5]} (seed {chaos.seed})"
