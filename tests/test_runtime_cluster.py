"""A 3-host cluster of real `haa-hostd` subprocesses on loopback (short QoS: T_D^U = 0.5 s).

The tests run in file order against one cluster: trust and commit, foreign clients with the wrong token,
garbage on the host link, kill -9 and restart, SIGSTOP until excluded (reincarnation), graceful shutdown.
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from grpc import aio

from haa.cluster.hostprocs import LocalCluster, wait_for
from haa.hostd.control import ControlClient
from haa.hostd.transport import MD_HB_KEY, MD_INC, MD_SENDER, MD_TOKEN, OPEN_METHOD

NAMES = ["h1", "h2", "h3"]
EXCLUDE_AFTER = 1.5


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalCluster]:
    root: Path = tmp_path_factory.mktemp("hostd")
    c = LocalCluster(NAMES, root, args=["--qos-td", "0.5", "--exclude-after", str(EXCLUDE_AFTER)])
    c.start()
    try:
        c.wait_trusted(timeout=30)
        yield c
    finally:
        c.close()


def counter(h: object, key: str) -> int:
    return int(h.status().counters.values.get(key, 0))  # type: ignore[attr-defined]


def commit_everywhere(c: LocalCluster, payload: bytes, proposer: str = "h1", names: list[str] = NAMES) -> None:
    """Propose at `proposer` with `names` as participants; check it commits and every one delivers it."""
    before = {n: c[n].status().delivered for n in names}
    r = c[proposer].client.propose(payload, participants=names, wait=True, timeout=10)
    assert r.decided and r.committed, r
    assert sorted(r.participants) == sorted(names)
    for n in names:
        wait_for(lambda n=n: c[n].status().delivered > before[n], 5, f"{n} to deliver")
        stream = c[n].client.deliveries(from_index=c[n].status().delivered - 1, timeout=5)
        last = next(stream)
        stream.cancel()  # type: ignore[attr-defined]
        assert last.payload == payload
        assert (last.id.host, last.id.incarnation, last.id.seq) == (r.id.host, r.id.incarnation, r.id.seq)


# ---------------------------------------------------------------------------------------------- (b)


def test_cluster_trusts_commits_and_agrees_on_the_delivered_hash(cluster: LocalCluster) -> None:
    st = {n: cluster[n].status() for n in NAMES}
    for n in NAMES:
        assert st[n].name == n
        assert {p.name for p in st[n].peers} == set(NAMES) - {n}
        for p in st[n].peers:
            assert p.incarnation == st[p.name].incarnation
            assert not p.suspected and p.connected
            assert 0 < p.heartbeat_period <= 0.5 and p.alpha > 0
        assert st[n].rss_bytes > 0 and st[n].uptime > 0
    r = cluster["h1"].client.propose(b"first", wait=True)  # empty participant list: everyone h1 trusts
    assert r.decided and r.committed
    assert sorted(r.participants) == NAMES
    assert r.propose_to_decide > 0
    wait_for(lambda: all(cluster[n].status().delivered == 1 for n in NAMES), 5, "delivery everywhere")
    hashes = {cluster[n].status().delivered_hash for n in NAMES}
    assert len(hashes) == 1 and hashes != {"0" * 64}
    for i in range(5):
        commit_everywhere(cluster, f"tx-{i}".encode(), proposer=NAMES[i % 3])
    st = {n: cluster[n].status() for n in NAMES}
    assert len({s.delivered_hash for s in st.values()}) == 1
    assert all(s.delivered == 6 for s in st.values())
    # the delivered logs are identical, entry by entry, and chained
    logs = {n: [(d.id.host, d.id.seq, d.payload, d.chain_hash) for d in _take(cluster[n].client, 6)] for n in NAMES}
    assert logs["h1"] == logs["h2"] == logs["h3"]
    assert logs["h1"][-1][3] == st["h1"].delivered_hash
    lat = cluster["h1"].client.latencies()
    assert len(lat.propose_to_decide) == 3 and len(lat.decide_to_deliver) == 6
    assert all(0 < x < 5 for x in lat.propose_to_decide)
    c = st["h1"].counters.values
    assert c["tx_msgs.oac_transaction"] >= 2 and c["rx_msgs.heartbeat"] > 0 and c["tx_bytes.heartbeat"] > 0


def _take(client: ControlClient, n: int) -> list[object]:
    it = client.deliveries(from_index=0, timeout=5)
    out = [next(it) for _ in range(n)]
    it.cancel()  # type: ignore[attr-defined]
    return out


def test_deliveries_stream_follows_new_deliveries(cluster: LocalCluster) -> None:
    h3 = cluster["h3"]
    start = h3.status().delivered
    stream = h3.client.deliveries(from_index=start, timeout=10)
    cluster["h2"].client.propose(b"live", wait=False)
    d = next(stream)
    assert d.index == start and d.payload == b"live"
    stream.cancel()  # type: ignore[attr-defined]


def test_propose_with_an_unknown_participant_is_invalid(cluster: LocalCluster) -> None:
    with pytest.raises(grpc.RpcError) as exc:
        cluster["h1"].client.propose(b"x", participants=["h1", "nobody"])
    assert exc.value.code() == grpc.StatusCode.INVALID_ARGUMENT  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------------- (c)


def test_foreign_client_with_wrong_token_is_rejected_and_counted(cluster: LocalCluster) -> None:
    h1 = cluster["h1"]
    before = counter(h1, "rejected_unauthenticated")
    with ControlClient(h1.address, "not-the-token") as foreign, pytest.raises(grpc.RpcError) as exc:
        foreign.status()
    assert exc.value.code() == grpc.StatusCode.UNAUTHENTICATED  # type: ignore[attr-defined]
    with ControlClient(h1.address, "not-the-token") as foreign, pytest.raises(grpc.RpcError) as exc:
        foreign.propose(b"evil")
    assert exc.value.code() == grpc.StatusCode.UNAUTHENTICATED  # type: ignore[attr-defined]

    async def open_link() -> grpc.StatusCode:
        async with aio.insecure_channel(h1.address) as ch:
            call = ch.stream_stream(OPEN_METHOD)(metadata=((MD_TOKEN, "nope"), (MD_SENDER, "h2"), (MD_INC, "1")))
            with pytest.raises(aio.AioRpcError) as e:
                await call.read()
            return e.value.code()

    assert asyncio.run(open_link()) == grpc.StatusCode.UNAUTHENTICATED
    assert counter(h1, "rejected_unauthenticated") == before + 3
    assert cluster.all_trusted()
    commit_everywhere(cluster, b"after-foreign-client")


# ---------------------------------------------------------------------------------------------- (d)


def test_a_second_stream_at_a_live_incarnation_is_refused_and_learns_nothing(cluster: LocalCluster) -> None:
    """With the token anybody can open a link as h2 at h2's live incarnation (it is in `cluster status`). It used
    to be accepted and told how far h2's numbering had got (`acked_seq`), so frames sent ahead of it made every
    real message of h2 a duplicate. h2's streams carry its link key; another key at that incarnation is refused
    (`rejected_other_process`) before anything is read, and h2 stays trusted."""
    h1 = cluster["h1"]
    h2_inc = cluster["h2"].status().incarnation
    before = counter(h1, "rejected_other_process")
    async def claim(key: str | None) -> grpc.StatusCode:
        async with aio.insecure_channel(h1.address) as ch:
            md = ((MD_TOKEN, cluster.token), (MD_SENDER, "h2"), (MD_INC, str(h2_inc)))
            if key is not None:
                md += ((MD_HB_KEY, key),)
            call = ch.stream_stream(OPEN_METHOD)(metadata=md)
            with pytest.raises(aio.AioRpcError) as e:
                await call.read()
            return e.value.code()

    assert asyncio.run(claim("cd" * 32)) == grpc.StatusCode.PERMISSION_DENIED
    assert asyncio.run(claim(None)) == grpc.StatusCode.INVALID_ARGUMENT
    assert counter(h1, "rejected_other_process") == before + 1
    assert h1.proc is not None and h1.proc.poll() is None
    assert cluster.all_trusted()
    commit_everywhere(cluster, b"after-second-stream")


# ---------------------------------------------------------------------------------------------- (e)


def test_kill9_suspected_then_restart_is_trusted_again_and_commits(cluster: LocalCluster) -> None:
    h1, h2, h3 = cluster["h1"], cluster["h2"], cluster["h3"]
    old_inc = h3.status().incarnation
    h3.kill9()

    def suspects_h3(h: object) -> bool:
        return any(p.name == "h3" and p.suspected for p in h.status().peers)  # type: ignore[attr-defined]

    wait_for(lambda: suspects_h3(h1) and suspects_h3(h2), 5, "h1 and h2 to suspect h3")
    # the survivors go on without h3 (default participants: the hosts the proposer trusts)
    r = h1.client.propose(b"without-h3", wait=True, timeout=10)
    assert r.committed and sorted(r.participants) == ["h1", "h2"]
    h3.start()
    wait_for(lambda: h3.status().incarnation > old_inc, 15, "h3 to come back")
    cluster.wait_trusted(timeout=15)
    new_inc = h3.status().incarnation
    assert all(p.incarnation == new_inc for h in (h1, h2) for p in h.status().peers if p.name == "h3")
    commit_everywhere(cluster, b"with-new-h3")
    assert h1.status().delivered_hash == h2.status().delivered_hash
    for h in (h1, h2):  # the old incarnation is permanently suspected (excluded, or superseded)
        dead = [e["fields"] for e in h.log_events() if e["event"] == "peer_dead"]
        assert any(f["peer"] == "h3" and f["inc"] == old_inc for f in dead)


# ----------------------------------------------------------------------------------- reincarnation


def test_paused_host_is_excluded_then_reincarnates_and_rejoins(cluster: LocalCluster) -> None:
    h1, h2 = cluster["h1"], cluster["h2"]
    old_inc = h2.status().incarnation
    h2.signal(signal.SIGSTOP)
    try:

        def excluded_by(h: object) -> bool:
            return any(p.name == "h2" and p.excluded for p in h.status().peers)  # type: ignore[attr-defined]

        wait_for(lambda: excluded_by(h1) and excluded_by(cluster["h3"]), EXCLUDE_AFTER + 5, "h2 to be excluded")
    finally:
        h2.signal(signal.SIGCONT)
    wait_for(lambda: h2.status().incarnation > old_inc, 10, "h2 to reincarnate")
    cluster.wait_trusted(timeout=15)
    reinc = [e for e in h2.log_events() if e["event"] == "reincarnate"]
    assert reinc and reinc[-1]["fields"]["old"] == old_inc and reinc[-1]["fields"]["by"] in ("h1", "h3")
    commit_everywhere(cluster, b"after-reincarnation")


# ---------------------------------------------------------------------------------------------- shutdown


def test_sigterm_shuts_down_gracefully(cluster: LocalCluster) -> None:
    final = {n: cluster[n].status().delivered_hash for n in NAMES}
    for n in NAMES:
        assert cluster[n].terminate() == 0
    for n in NAMES:
        events = cluster[n].log_events()
        assert events[-1]["event"] == "shutdown"
        assert events[-1]["fields"]["hash"] == final[n]
        assert all({"ts", "host", "inc", "event", "fields"} <= e.keys() for e in events)
