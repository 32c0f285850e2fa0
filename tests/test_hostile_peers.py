"""Peers that claim another host's name or incarnation.

With the cluster token anybody can open a host link under any name. These tests do what a hostile or
careless peer would, through a raw `HostLink.Open` client (metadata built by hand) or by starting a second
real `haa-hostd` under a name that is taken, against a live 3-host cluster running a counter pair, and check
after each that every host lives, the group agrees on one view, the DDB replicas are equal, a write commits
within a second and no agent has two live instances (docs/membership.md, "Incarnation claims").

The rules of the receiving transport are also checked in-process (two `Transport`s on loopback): a claim
alone never locks the real host out, and a host displaced by a newer incarnation is told so and rejoins above
it.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from typing import Any

import grpc
import psutil
import pytest
from grpc import aio
from helpers import run, until
from hostilecluster import (
    AGENTS,
    TOKEN,
    Cluster,
    agreed,
    assert_healthy,
    live_instances,
    owner_runs,
    settled,
    start_cluster,
    view,
)

from haa.cluster.hostprocs import MemberHost, free_port
from haa.cluster.hostprocs import wait_for as wait
from haa.core import wire
from haa.core.messages import Heartbeat, Message
from haa.hostd.transport import (
    MD_HB_KEY,
    MD_INC,
    MD_SENDER,
    MD_TOKEN,
    OPEN_METHOD,
    Transport,
    encode_frame,
    envelope_chunk,
    parse_incarnation,
)
from haa.pb import hostlink_pb2 as pb


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = start_cluster(tmp_path_factory.mktemp("hostile"))
    try:
        yield c
    finally:
        c.close()


# ------------------------------------------------------------------------------------------- raw links


def open_link(address: str, sender: str, inc: str, frames: list[bytes] = (),  # type: ignore[assignment]
              key: str = "ab" * 32) -> grpc.StatusCode | bytes:
    """Open `HostLink.Open` as `sender` with incarnation metadata `inc` (as given, unchecked) and link key `key`,
    write `frames`; the handshake's bytes, or the status code the receiver refused with."""
    with grpc.insecure_channel(address) as ch:
        call = ch.stream_stream(OPEN_METHOD)(iter(frames), metadata=((MD_TOKEN, TOKEN), (MD_SENDER, sender),
                                                                      (MD_INC, inc), (MD_HB_KEY, key)), timeout=5)
        try:
            return next(call)
        except grpc.RpcError as e:
            return e.code()


def test_incarnation_metadata_is_parsed_strictly() -> None:
    assert parse_incarnation("1") == 1
    assert parse_incarnation(str(2**64 - 1)) == 2**64 - 1
    for bad in ["", "0", "-1", "+5", " 5", "5 ", "1_000", "0x10", "05", "١٢", str(2**64), str(2**70), "9" * 100]:
        assert parse_incarnation(bad) is None, bad


def test_claims_of_a_live_hosts_name_are_refused_and_change_nothing(cluster: Cluster) -> None:
    """Claims as `h1` on h2's port: incarnation 2**70 (it locked h1 out for good), strings int() accepts, one
    an hour ahead of the clock, one 30 s ahead while h1 lives, and an older one — all refused and counted;
    h1 keeps its incarnation, nobody suspects it, the view does not change."""
    h1, h2 = cluster.hosts["h1"], cluster.hosts["h2"]
    before = view(h2)
    inc1 = h1.status().incarnation
    now = time.time_ns()
    cases = {
        str(2**70): grpc.StatusCode.INVALID_ARGUMENT,
        f"+{inc1 + 1}": grpc.StatusCode.INVALID_ARGUMENT,
        f"{inc1 + 1:_}": grpc.StatusCode.INVALID_ARGUMENT,
        f" {inc1 + 1}": grpc.StatusCode.INVALID_ARGUMENT,
        str(now + 3600 * 10**9): grpc.StatusCode.OUT_OF_RANGE,
        str(2**64 - 1): grpc.StatusCode.OUT_OF_RANGE,
        str(now + 30 * 10**9): grpc.StatusCode.UNAVAILABLE,  # h1 is live here
        str(inc1 - 1): grpc.StatusCode.FAILED_PRECONDITION,  # stale
    }
    got = {inc: open_link(h2.address, "h1", inc) for inc in cases}
    assert got == cases
    counters = h2.status().counters.values
    assert counters["rejected_future_incarnation"] >= 2
    assert counters["rejected_live_incarnation"] >= 1
    assert counters["rejected_bad_metadata"] >= 4
    # for two seconds (h1's stream to h2 would have been cut at its next heartbeat): h1 stays trusted
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        s = h2.status()
        assert "h1" not in s.suspicions, "h2 lost h1"
        time.sleep(0.1)
    assert h1.status().incarnation == inc1
    assert view(h2) == before
    assert_healthy(cluster)


def test_a_token_holder_cannot_take_over_a_live_hosts_link_or_forge_its_heartbeats(cluster: Cluster) -> None:
    """The reliability probe, as a token holder: a stream as h1 at h1's live incarnation was accepted and told
    `acked_seq`, and 200,000 envelopes numbered from there made every real message of h1 a duplicate (puts
    timed out for minutes, one `reject_invalid` in the log); 200 heartbeat datagrams forged as h2 under the
    token's MAC key got h2 removed. Now a stream at a live incarnation must carry the link key of the process
    that opened the first one (refused before anything is read or told), and heartbeat datagrams are MACed with
    that key, which never leaves the link."""
    import hashlib
    import hmac as hm
    import socket

    h1, h2 = cluster.hosts["h1"], cluster.hosts["h2"]
    before = view(h2)
    inc1, inc2 = h1.status().incarnation, h2.status().incarnation
    frames = [frame_from("h1", inc1, seq, Heartbeat(10**9 + seq, 0.05, 1.0)) for seq in range(1, 50)]
    assert open_link(h2.address, "h1", str(inc1), frames, key="cd" * 32) == grpc.StatusCode.PERMISSION_DENIED
    assert h2.status().counters.values["rejected_other_process"] >= 1
    # heartbeats forged as h2 to h1's datagram port (the gRPC port's number), under the key the token used to give
    token_key = hashlib.sha256(b"haa-heartbeat\0" + TOKEN.encode()).digest()
    rejected = h1.status().counters.values["hb_rejected_unauthenticated"]
    port = int(h1.address.rsplit(":", 1)[1])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        for i in range(200):
            body = b"HAAhb1" + wire.encode("h2", inc2, 0, Heartbeat(10**9 + i, 0.05, 1e-3)).SerializeToString()
            udp.sendto(body + hm.new(token_key, body, hashlib.sha256).digest()[:16], ("127.0.0.1", port))
    wait(lambda: h1.status().counters.values["hb_rejected_unauthenticated"] >= rejected + 150, 10,
         "the forged heartbeats refused")
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        assert "h1" not in h2.status().suspicions and "h2" not in h1.status().suspicions
        time.sleep(0.1)
    assert view(h2) == before
    assert_healthy(cluster)


def frame_from(sender: str, inc: int, seq: int, msg: Message) -> bytes:
    return encode_frame(seq, [envelope_chunk(wire.encode(sender, inc, 0, msg).SerializeToString())])


def test_a_second_daemon_under_a_live_name_is_refused(cluster: Cluster) -> None:
    """`haa-hostd --name h2` with the core list while h2 lives is refused by every member (accepted, it would
    join and recover h2's agents while h2 still runs them); the group does not change. Nor does the impostor
    form a group of its own once its formation timeout (5 s) has passed (it did, a one-host group beside the
    real one, e.g. with a copied certificate): it logs `name_in_use` and keeps applying."""
    before = view(cluster.hosts["h1"])
    imp = cluster.second("h2", "impostor")
    imp.start()
    others = [cluster.hosts["h1"], cluster.hosts["h3"]]
    wait(lambda: view(cluster.hosts["h1"]) != before
         or all(h.status().counters.values["rejected_live_incarnation"] >= 1 for h in others), 20,
         "the impostor refused by h1 and h3 (or accepted)")
    deadline = time.monotonic() + 7.0  # past the formation timeout: the view stays, the impostor is no member
    while time.monotonic() < deadline:
        assert view(cluster.hosts["h1"]) == before
        s = imp.status()
        assert not s.member and not s.members, list(s.members)
        time.sleep(0.2)
    assert any(e.get("event") == "name_in_use" for e in imp.events(0))
    assert not [a.name for a in imp.client.agent_list().agents if a.local_phase]
    assert_healthy(cluster, [imp])
    imp.kill()
    assert view(cluster.hosts["h1"]) == before
    assert_healthy(cluster)


def test_silent_host_is_superseded_in_bounded_time_and_rejoins_by_itself(cluster: Cluster) -> None:
    """A host restarted elsewhere while the old process is frozen (SIGSTOP: its streams stay open, silent):
    the new process is accepted within the live window + reconnect backoff and joins; the old one, resumed,
    learns it was superseded, kills its agent instances and rejoins as a newer incarnation once the new one is
    gone (it stayed cut off for good before)."""
    old = cluster.hosts["h2"]
    assert old.proc is not None
    assert settled(cluster) and owner_runs(cluster, "A1") == "h2"
    pids = [a.pid for a in old.client.agent_list().agents if a.local_phase and a.pid > 0]
    assert pids
    old.proc.send_signal(signal.SIGSTOP)
    try:
        new = cluster.second("h2", "restarted")
        t0 = time.monotonic()
        new.start()
        trio = [cluster.hosts["h1"], new, cluster.hosts["h3"]]
        wait(lambda: agreed(trio), 30, "the new h2 in every view")
        took = time.monotonic() - t0
        assert took < 15.0, f"the new h2 took {took:.1f} s to supersede the silent one and join"
        wait(lambda: all(owner_runs_among(trio, n) for n in AGENTS), 30, "h2's agents recovered")
    finally:
        old.proc.send_signal(signal.SIGCONT)
    # the old process learns it is out — superseded (a link refused it with the newer incarnation) or excluded
    # (a member's removal notice, Excluded, reached it first: which one comes first is a race) — and becomes a
    # new incarnation, its agent instances killed
    wait(lambda: not any(_alive(p) for p in pids), 15, "the displaced host's agent processes gone")
    wait(lambda: any(e.get("event") == "reincarnate" for e in old.events(0)), 10, "the displaced host reincarnated")
    twice = {n: w for n, w in live_instances([*trio, old]).items() if len(w) > 1}
    assert not twice, twice
    assert not old.status().member
    # the new process goes away: the displaced one rejoins by itself
    new.kill()
    wait(lambda: agreed(cluster.members()), 30, "the displaced h2 back in every view")
    wait(lambda: settled(cluster), 30, "agents active again")
    assert_healthy(cluster)


def owner_runs_among(hs: list[MemberHost], name: str) -> bool:
    rec = {a.name: a for a in hs[0].client.agent_list().agents}.get(name)
    if rec is None or rec.status != "active":
        return False
    runners = [(h.name, a.local_phase) for h in hs for a in h.client.agent_list().agents
               if a.name == name and a.local_phase]
    return runners == [(rec.owner, "active")]


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


# ------------------------------------------------------------------------------------------- in-process


class Node:
    """A Transport with its own server, recording what it receives and who superseded it."""

    def __init__(self, name: str, inc: int, port: int, peers: dict[str, int], **kw: Any) -> None:
        self.got: list[tuple[str, int, Message]] = []
        self.superseded: list[tuple[str, int]] = []
        self.t = Transport(name, TOKEN, {p: f"127.0.0.1:{pp}" for p, pp in peers.items()},
                           on_envelopes=self._on_envelopes, on_superseded=self._on_superseded,
                           min_backoff=0.01, max_backoff=0.1, handshake_timeout=1.0, **kw)
        self.t.incarnation = inc
        self.port = port
        self.server: aio.Server | None = None

    def _on_envelopes(self, src: str, src_inc: int, items: list[tuple[int, Message]]) -> None:
        self.got += [(src, src_inc, m) for _d, m in items]

    def _on_superseded(self, peer: str, newer: int) -> None:
        self.superseded.append((peer, newer))
        self.t.set_incarnation(newer + 1)  # what HostRuntime does: reincarnate above it

    async def serve(self) -> None:
        self.server = aio.server(options=Transport.server_options())
        self.t.add_to_server(self.server)
        self.server.add_insecure_port(f"127.0.0.1:{self.port}")
        await self.server.start()

    async def close(self) -> None:
        await self.t.stop()
        if self.server is not None:
            await self.server.stop(0)


async def claim(port: int, sender: str, inc: int, heartbeat: bool) -> aio.StreamStreamCall:
    """A raw stream claiming to be `sender`#`inc`, with one valid heartbeat envelope or none; left open."""
    ch = aio.insecure_channel(f"127.0.0.1:{port}")
    call = ch.stream_stream(OPEN_METHOD)(metadata=((MD_TOKEN, TOKEN), (MD_SENDER, sender), (MD_INC, str(inc)),
                                                   (MD_HB_KEY, "ab" * 32)))
    reply = pb.LinkReply.FromString(await call.read())
    assert reply.receiver == "b"
    if heartbeat:
        env = wire.encode(sender, inc, 0, Heartbeat(1, 0.05, 1.0)).SerializeToString()
        await call.write(encode_frame(1, [envelope_chunk(env)]))
    call._haa_channel = ch  # type: ignore[attr-defined]
    return call


def test_a_claim_alone_never_locks_the_real_host_out() -> None:
    """A stream claiming a newer incarnation of `a` that carries no valid message (made while `a` was
    not connected) is forgotten once it is gone; the real `a` connects (it was refused as stale for good)."""
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        b = Node("b", 5, pb_, {"a": pa})
        await b.serve()
        fake = await claim(pb_, "a", time.time_ns() + 10**9, heartbeat=False)
        fake.cancel()
        a = Node("a", time.time_ns(), pa, {"b": pb_})
        a.t.start()
        await until(lambda: a.t.connected("b"), what="the real a connected")
        a.t.send("b", 5, Heartbeat(1, 0.05, 1.0))
        await until(lambda: b.got, what="a's heartbeat delivered")
        assert b.t.counters["rx_claim_forgotten"] == 1 and not a.superseded
        await a.close()
        await b.close()

    run(main())


def test_a_displaced_host_is_told_and_rejoins_above_the_newer_incarnation() -> None:
    """A newer incarnation of `a` that spoke (a valid heartbeat) while the real `a` was silent
    displaces it; the real `a` is refused as stale with the newer incarnation, reincarnates above it and
    is accepted once the newer one is gone — never locked out for good."""
    async def main() -> None:
        pa, pb_ = free_port(), free_port()
        b = Node("b", 5, pb_, {"a": pa})
        await b.serve()
        forged = time.time_ns() + 20 * 10**9  # within MAX_INCARNATION_AHEAD
        fake = await claim(pb_, "a", forged, heartbeat=True)
        await until(lambda: b.got, what="the claim's heartbeat")
        a = Node("a", time.time_ns(), pa, {"b": pb_})
        a.t.start()
        await until(lambda: a.superseded == [("b", forged)], what="a told it was superseded")
        assert b.t.counters["rejected_stale_incarnation"] >= 1
        assert a.t.incarnation == forged + 1
        fake.cancel()
        await until(lambda: a.t.connected("b"), what="a (above the claim) connected")
        a.t.send("b", 5, Heartbeat(2, 0.05, 2.0))
        await until(lambda: any(i == forged + 1 for _s, i, _m in b.got), what="a's heartbeat delivered")
        await a.close()
        await b.close()

    run(main())


# ------------------------------------------------------------------------------------------- hearsay


def test_hearsay_never_supersedes_a_peer_we_hear_from() -> None:
    """Incarnation claims through the messages of a member: an OAC participant list or a relayed introduction naming
    (h1, 2**64 - 1) made every host treat the live h1 as restarted (its real incarnation dead, locked out for
    good: the transport refuses an incarnation that far ahead). Hearsay is believed only while no incarnation
    of the peer is trusted; a peer that really restarted is suspected first, then believed."""
    from haa.core.host.hostcore import HostCore

    core = HostCore("h2", 5, ["h1", "h2", "h3"])
    core.start(0.0)
    core.on_message(0.01, "h1", 7, 0, Heartbeat(0, 0.05, 0.0))
    core.drain()
    p = core.peers["h1"]
    assert p.inc == 7 and not p.suspected
    core._learn_participants((("h1", 2**64 - 1), ("h3", 9)))  # h3 was never heard from: believed
    core.add_peer(0.02, "h1", 2**64 - 2, hearsay=True)
    assert p.inc == 7 and ("h1", 7) not in core.dead
    assert core.peers["h3"].inc == 9
    assert core.counters["hearsay_incarnation_ignored"] == 2
    # h1 falls silent and is suspected: now a mention of its new incarnation is believed
    fresh = p.observer.freshness
    core.on_timer(fresh, ("fd", "h1"))
    core.drain()
    assert p.suspected
    core._learn_participants((("h1", 8),))
    assert p.inc == 8
    # the new incarnation's own word (the handshake) is believed at once, suspected or not
    core.on_peer_info(fresh + 0.1, "h1", 9)
    assert p.inc == 9
