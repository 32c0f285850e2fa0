"""haa-hostd with `--host-link tcp` (haa.hostd.tcplink): a 3-host membership cluster whose host links are framed
TCP connections forms, commits DDB writes through every host, survives a host killed with SIGKILL (removed from
every view, the survivors keep committing) and takes it back as a new incarnation; a host started with the other
carrier is refused with a clear log line on both sides, never silently (docs/transport.md, "The TCP host link").
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from haa.cluster.hostprocs import MemberGroup, MemberHost
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import ops as ddb

TOKEN = "tcplink-test-token"
NAMES = ["h1", "h2", "h3"]
ARGS = ["--host-link", "tcp", "--no-agents"]


def agreed(hosts: list[MemberHost], names: list[str]) -> bool:
    views = set()
    for h in hosts:
        s = h.status()
        if not s.member:
            return False
        views.add((tuple(s.members), s.view, s.ddb_hash))
    return len(views) == 1 and set(next(iter(views))[0]) == set(names)


def events(h: MemberHost) -> list[dict[str, Any]]:
    if not h.log_file.exists():
        return []
    return [json.loads(x) for x in h.log_file.read_text().splitlines() if x.strip()]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, MemberHost]]:
    root = tmp_path_factory.mktemp("tcplink")
    group = MemberGroup(root, NAMES, core=NAMES, token=TOKEN, args=ARGS)
    hosts = dict(group.hosts)
    hosts["odd"] = group.new_host("odd", ["--host-link", "grpc", "--no-agents"])
    group.start()
    try:
        yield hosts
    finally:
        group.close()


def test_a_tcp_linked_cluster_commits_and_survives_a_killed_host(cluster: dict[str, MemberHost]) -> None:
    hosts = [cluster[n] for n in NAMES]
    wait(lambda: agreed(hosts, NAMES), 30, "three hosts in one view")
    for h in hosts:
        start = next(e for e in events(h) if e.get("event") == "startup")["fields"]
        assert start["host_link"] == "tcp" and start["link_port"] > 0
    for i, h in enumerate(hosts * 3):
        r = h.client.ddb_write([ddb.put(f"k/{i}", "json", {"i": i})])
        assert r.committed, r.reason
    for h in hosts:
        c = h.status().counters.values
        assert c["link_accepts"] >= 2 and c["rx_frames"] > 0 and c.get("link_wrong_carrier", 0) == 0
    # SIGKILL h3: removed from every view within the failure detector's bound, as over gRPC
    victim = cluster["h3"]
    assert victim.proc is not None
    victim.proc.kill()
    t0 = time.monotonic()
    victim.proc.wait(10)
    rest = hosts[:2]
    wait(lambda: agreed(rest, NAMES[:2]), 20, "h3 removed everywhere")
    took = time.monotonic() - t0
    assert took < 5.0, f"crash to removal took {took:.2f} s"
    r = cluster["h2"].client.ddb_write([ddb.put("after-crash", "blob", b"x")])
    assert r.committed, r.reason
    # it restarts as a new incarnation (its TCP link on a new port, found through its gRPC server) and rejoins
    victim.start()
    wait(lambda: agreed(hosts, NAMES), 30, "h3 back in every view")
    r = victim.client.ddb_write([ddb.put("after-rejoin", "blob", b"y")])
    assert r.committed, r.reason
    wait(lambda: agreed(hosts, NAMES), 10, "equal replicas")


def test_a_host_with_the_other_carrier_is_refused_loudly(cluster: dict[str, MemberHost]) -> None:
    """`odd` runs the gRPC carrier: the TCP hosts refuse its links (`reject_wrong_carrier`, FAILED_PRECONDITION
    that `odd` logs as `link_refused` with the reason); it never becomes a member. (The other direction, a TCP
    sender and a gRPC receiver, is tests/test_runtime_transport.py's.)"""
    odd = cluster["odd"]
    odd.start()
    hosts = [cluster[n] for n in NAMES]
    wait(lambda: any(e.get("event") == "link_refused" and "tcp host link" in e.get("fields", {}).get("reason", "")
                     for e in events(odd)), 20, "odd told that the cluster uses the tcp host link")
    wait(lambda: any(h.status().counters.values["rejected_wrong_carrier"] >= 1 for h in hosts), 10,
         "the tcp hosts count the refusal")
    assert not odd.status().member
    assert agreed(hosts, NAMES)
    odd.kill()


def test_a_static_mesh_over_tls_on_tcp_links_commits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Mutual TLS on the TCP carrier with real daemons (uvloop): `LocalCluster(tls=True)` started with
    HAA_HOST_LINK=tcp in the environment the hosts inherit, as `haactl bench ap1 --tls` would be."""
    from haa.cluster.hostprocs import LocalCluster

    monkeypatch.setenv("HAA_HOST_LINK", "tcp")
    with LocalCluster(["h1", "h2", "h3"], tmp_path, tls=True) as c:
        c.start()
        c.wait_trusted(timeout=60)
        r = c["h2"].client.propose(b"over tls and tcp", wait=True)
        assert r.decided and r.committed and sorted(r.participants) == ["h1", "h2", "h3"]
        for h in c.hosts.values():
            start = next(e for e in h.log_events() if e.get("event") == "startup")["fields"]
            assert start["host_link"] == "tcp"
            counters = dict(h.status().counters.values)
            assert counters["link_accepts"] >= 2 and counters["rx_frames"] >= 1
            assert counters.get("rejected_name_mismatch", 0) == 0 and counters.get("link_wrong_carrier", 0) == 0
