"""Size limits and memory bounds (docs/limits.md, "Sizes and memory").

Unit tests: the byte bounds of the delivered log, the DDB mirror ring and a mirror subscriber's queue, the
JSON bounds of a DDB batch, the agent table's config / backup / queue bounds. Real processes (a 4-host
group with agents): over-limit requests through a raw control-API stub are refused cleanly and change no
view; the largest accepted ones commit without a view change; a few seconds of maximum-size traffic keep
every host's RSS bounded.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import grpc
import psutil
import pytest

from haa.cluster.hostprocs import MemberHost
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import agenttable as at
from haa.core.ddb import ops as ddb
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import MAX_BATCH_BYTES, MAX_JSON_VALUE_BYTES, MAX_VALUE_BYTES, DdbError
from haa.core.messages import TxId
from haa.hostd.delivered import DeliveredLog
from haa.hostd.mirrors import MirrorSub
from haa.hostd.resources import LoopWatch
from haa.hostd.transport import LINK_PIECE, MAX_MESSAGE, MAX_REQUEST, Transport
from haa.lab.experiments import memory as membench
from haa.pb import agenttx_pb2 as apb
from haa.pb import control_pb2 as cpb
from haa.pb import control_pb2_grpc
from haa.sdk.channel import MAX_AGENT_MESSAGE

MiB = 1 << 20
#: what the memory budget of a host allows each of the byte-bounded buffers to hold (docs/limits.md)
BUFFER_BUDGET = 16 * MiB
#: the largest agent config, and the payload bytes one queue of a frozen agent may hold
CONFIG_BUDGET = MiB
QUEUE_BUDGET = 4 * MiB


# ----------------------------------------------------------------------------------------- unit: bounds


def test_delivered_log_is_bounded_in_bytes_and_keeps_counting() -> None:
    log_ = DeliveredLog()
    payload = b"p" * MiB
    n = 3 * BUFFER_BUDGET // MiB
    for i in range(n):
        log_.append(TxId("h2", 1, i + 1), i + 1, payload)
    kept = sum(len(e.payload) for e in log_.entries)
    assert kept == log_.bytes <= BUFFER_BUDGET
    assert log_.count == n and log_.entries[-1].index == n - 1
    assert log_.base + len(log_.entries) == n
    # many small entries: the count bound still applies, bytes stay exact
    for i in range(50):
        log_.append(TxId("h2", 1, n + i + 1), n + i + 1, b"x")
    assert log_.bytes == sum(len(e.payload) for e in log_.entries)


def test_mirror_ring_is_bounded_in_bytes() -> None:
    db = Ddb()
    ops = membench.max_blob_batch("k")
    for _ in range(3 * BUFFER_BUDGET // MAX_BATCH_BYTES + 1):
        db.apply(ddb.encode_batch(ops))
    ring = db.mirror_since(db.seq - 1)
    assert ring is not None and len(ring) == 1  # the newest batch is always there
    assert db._mirror_bytes <= BUFFER_BUDGET
    assert db.mirror_since(0) is None  # the oldest batches are gone: a subscriber that far behind resyncs


def test_mirror_subscriber_queue_is_bounded_in_bytes() -> None:
    async def main() -> None:
        sub = MirrorSub(views=False)
        for seq in range(1, 40):
            sub.push(("batch", seq, b"b" * MiB, seq))
            assert sub.bytes <= BUFFER_BUDGET
        items = []
        while sub.queue:
            item = await sub.get()
            assert item is not None
            items.append(item)
        assert ("resync",) in items and sub.bytes == 0

    asyncio.run(main())


def test_json_bounds_are_checked_before_parsing() -> None:
    text = b"[" + b"{}," * (MAX_JSON_VALUE_BYTES // 3) + b"{}]"
    big = ddb._op(put=ddb.pb.DdbPut(key="j", type="json", value=text))
    assert "MAX_JSON_VALUE_BYTES" in ddb.check_json_sizes([big])
    with pytest.raises(DdbError, match="MAX_JSON_VALUE_BYTES"):
        ddb.encode_batch([big])
    # a committed batch over the bound (from a peer that skipped the edge check) is refused identically
    raw = ddb.pb.DdbBatch(ops=[big]).SerializeToString()
    db = Ddb()
    with pytest.raises(DdbError, match="MAX_JSON_VALUE_BYTES"):
        db.apply(raw)
    assert db.seq == 0
    # the largest accepted JSON batch of the costliest kind applies
    res = db.apply(ddb.encode_batch(membench.max_json_batch()))
    assert all(r.ok for r in res.results)
    with pytest.raises(DdbError):
        ddb.encode_value("json", ["x" * MAX_JSON_VALUE_BYTES])


def test_agent_table_size_bounds() -> None:
    c = apb.AgentCreate(id="a", type="probe", host="h1", recovery="backup", config=b"x" * (CONFIG_BUDGET + 1))
    assert "MAX_CONFIG" in at.check_create(c)
    c.config = b"x" * at.MAX_CONFIG
    assert at.check_create(c) == ""
    t = at.AgentTable()
    tx = apb.AgentTx()
    tx.create.CopyFrom(c)
    assert t.apply(tx.SerializeToString()).ok
    # a frozen agent's queue keeps at most MAX_QUEUE_BYTES of payload; the rest is counted as dropped
    r = t.records["a"]
    r.status = at.CRASHED
    push = apb.AgentTx()
    push.push.id, push.push.queue = "a", 2
    for _ in range(2 * QUEUE_BUDGET // MiB):
        push.push.msgs.add(dst="a", payload=b"m" * MiB)
    assert t.apply(push.SerializeToString()).ok
    assert sum(len(m.payload) for m in r.queue2) <= QUEUE_BUDGET
    assert r.dropped == len(push.push.msgs) - len(r.queue2) > 0


def test_loop_watch_counts_stalls() -> None:
    c: Counter[str] = Counter()

    async def main() -> None:
        w = LoopWatch(c, tick=0.01)
        w.start()
        await asyncio.sleep(0.05)  # the watch ticks on an idle loop ...
        time.sleep(0.3)  # a callback that keeps the loop busy
        await asyncio.sleep(0.05)  # ... and after the stall, when it measures it
        w.stop()

    asyncio.run(main())
    assert 250 <= c["loop_lag_max_ms"] < 2000 and c["loop_stalls_over_250ms"] == 1


def test_grpc_limits_are_set_on_purpose() -> None:
    opts = dict(Transport.server_options())
    assert opts["grpc.max_receive_message_length"] == MAX_REQUEST < MAX_MESSAGE
    assert opts["grpc.max_send_message_length"] == MAX_MESSAGE  # a joiner's snapshot, a large reply
    assert opts["grpc.max_concurrent_streams"] > 0
    # every request a client may send is below the server's limit, so the handlers' checks refuse it cleanly
    assert max(MAX_BATCH_BYTES, at.MAX_CONFIG, at.MAX_STATE) * 4 <= MAX_REQUEST
    assert MAX_AGENT_MESSAGE + 64 * 1024 <= MAX_REQUEST
    # a host-link frame above it goes in pieces that fit
    assert LINK_PIECE + 64 <= MAX_REQUEST


# ----------------------------------------------------------------------------------------- real processes


@pytest.fixture(scope="module")
def group(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, MemberHost]]:
    root: Path = tmp_path_factory.mktemp("limits")
    hs = membench.start_group(root, "limits-test-token")
    try:
        yield hs
    finally:
        for h in hs.values():
            h.kill()


def _stub(h: MemberHost) -> tuple[control_pb2_grpc.HostControlStub, tuple[tuple[str, str], ...], grpc.Channel]:
    ch = grpc.insecure_channel(h.address, options=[("grpc.max_send_message_length", -1)])
    return control_pb2_grpc.HostControlStub(ch), (("x-haa-token", "limits-test-token"),), ch


def _views(hs: dict[str, MemberHost]) -> dict[str, tuple[int, int, tuple[str, ...]]]:
    out = {}
    for n, h in hs.items():
        st = h.status()
        out[n] = (st.view, st.incarnation, tuple(sorted(st.members)))
    return out


def test_over_limit_requests_are_refused_cleanly_and_expel_nobody(group: dict[str, MemberHost]) -> None:
    before = _views(group)
    stub, md, ch = _stub(group["h2"])
    try:
        # a 50 MB config (the one that got h2 expelled: gRPC read it whole on the event loop, 1-5 s): above
        # MAX_REQUEST, refused by gRPC unread
        with pytest.raises(grpc.RpcError) as e:
            stub.AgentSpawn(cpb.AgentSpawnRequest(type="probe", config=b"x" * (50 * 1000 * 1000)), metadata=md,
                            timeout=30)
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        # over MAX_CONFIG but within MAX_REQUEST: decoded, refused by the handler before anything is proposed
        r = stub.AgentSpawn(cpb.AgentSpawnRequest(type="probe", config=b"x" * (MAX_REQUEST - 4096)), metadata=md,
                            timeout=30)
        assert not r.ok and "MAX_CONFIG" in r.reason, r
        r = stub.AgentSpawn(cpb.AgentSpawnRequest(type="probe", config=b"x" * (at.MAX_CONFIG + 1)), metadata=md,
                            timeout=30)
        assert not r.ok and "MAX_CONFIG" in r.reason, r
        # beyond the gRPC limit: refused by gRPC before it is decoded
        with pytest.raises(grpc.RpcError) as e:
            stub.AgentSpawn(cpb.AgentSpawnRequest(type="probe", config=b"x" * (MAX_REQUEST + 1)), metadata=md,
                            timeout=30)
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        # DDB: a batch over MAX_BATCH_BYTES, and JSON over its bound
        big = [ddb.put(f"lim/{i}", "blob", b"b" * MAX_VALUE_BYTES) for i in range(3)]
        with pytest.raises(grpc.RpcError) as e:
            stub.DdbWrite(cpb.DdbWriteRequest(ops=big), metadata=md, timeout=30)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "MAX_BATCH_BYTES" in e.value.details()
        text = b"[" + b"0," * MAX_JSON_VALUE_BYTES + b"0]"
        js = [ddb._op(put=ddb.pb.DdbPut(key="lim/j", type="json", value=text))]
        with pytest.raises(grpc.RpcError) as e:
            stub.DdbWrite(cpb.DdbWriteRequest(ops=js), metadata=md, timeout=30)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "MAX_JSON_VALUE_BYTES" in e.value.details()
    finally:
        ch.close()
    time.sleep(1.5)  # a host expelled by a stall would be removed within ~1-2 s
    assert _views(group) == before
    assert not any(a.type == "probe" for a in group["h1"].client.agent_list().agents)


def test_largest_accepted_requests_commit_without_a_view_change(group: dict[str, MemberHost]) -> None:
    before = _views(group)
    stub, md, ch = _stub(group["h3"])
    try:
        r = stub.AgentSpawn(cpb.AgentSpawnRequest(type="probe", config=membench.max_config(), transfer_penalty=-1.0),
                            metadata=md, timeout=30)
        assert r.ok, r
        w = stub.DdbWrite(cpb.DdbWriteRequest(ops=membench.max_blob_batch()), metadata=md, timeout=30)
        assert w.committed, w
        w = stub.DdbWrite(cpb.DdbWriteRequest(ops=membench.max_json_batch()), metadata=md, timeout=30)
        assert w.committed, w
        wait(lambda: any(a.id == r.id and a.status == "active" for a in group["h1"].client.agent_list().agents), 20,
             "the probe active")
        rem = stub.AgentRemove(cpb.AgentRef(ref=r.id), metadata=md, timeout=30)
        assert rem.ok, rem
    finally:
        ch.close()
    time.sleep(1.5)  # a host expelled by a stall would be removed within ~1-2 s
    assert _views(group) == before


def test_maximum_size_traffic_keeps_memory_bounded(group: dict[str, MemberHost]) -> None:
    """A short version of `haactl bench memory`: ~12 s of the largest accepted requests (DDB batches, spawn
    with the largest config, messages, state and backup of MAX_STATE, a transfer); every host stays a member
    and its RSS stays within 250 MiB."""
    before = _views(group)
    sampler = membench.Sampler(group, 0.2)
    sampler.start()
    traffic = membench.Traffic(group, log=lambda _s: None)
    t_end = time.monotonic() + 12
    try:
        while time.monotonic() < t_end:
            traffic.round()
    finally:
        sampler.halt.set()
        sampler.join()
    failed = [s for s in traffic.steps if not s["ok"]]
    assert not failed, failed[:3]
    kinds = {s["step"] for s in traffic.steps}
    assert {"ddb", "ddb_json", "spawn", "message", "set_state", "backup", "transfer", "remove"} <= kinds, kinds
    peaks = {n: max(r for _, r in s) / MiB for n, s in sampler.samples.items()}
    assert all(p <= 250 for p in peaks.values()), peaks
    for n, h in group.items():
        p = psutil.Process(h.proc.pid)  # type: ignore[union-attr]
        assert p.memory_info().rss <= 250 * MiB, n
    assert _views(group) == before
    st = group["h1"].status().counters.values
    print(json.dumps({"peaks_mib": peaks, "loop_lag_max_ms": st.get("loop_lag_max_ms", 0)}))
