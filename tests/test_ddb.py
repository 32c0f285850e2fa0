"""The DDB replicated state machine (haa.core.ddb, docs/ddb.md): op semantics and failure reasons, atomic
batches, malformed payloads, limits, hashing, snapshots, watchers, the mirror ring, and replica agreement
on random op sequences (hypothesis, against a small reference model)."""

import ast
import hashlib
import importlib.util
import json
import struct
from pathlib import Path

import pytest
from helpers import parse_source
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import haa.pb.ddb_pb2 as pb
from haa.core.ddb import ops as D
from haa.core.ddb.ddb import Ddb, DdbEvent
from haa.core.ddb.objects import INT64_MAX, INT64_MIN, MAX_BATCH_BYTES, MAX_VALUE_BYTES, DdbError

ROOT = Path(__file__).resolve().parents[1]
MiB = 1024 * 1024


def run(db: Ddb, *ops, atomic=False, origin="t", client_seq=0, meta=None):
    return db.apply(D.encode_batch(ops, origin, client_seq, atomic=atomic), meta)


def raw_put(key, type_name, value: bytes):
    return pb.DdbOp(put=pb.DdbPut(key=key, type=type_name, value=value))


def reasons(res):
    return [r.reason for r in res.results]


# ---------------------------------------------------------------------------------------------- ops


def test_put_each_type_and_read_back():
    db = Ddb()
    res = run(
        db,
        D.put("b", "blob", b"\x00\xff"),
        D.put("j", "json", {"z": [1, 2.5, None, True], "a": "é"}),
        D.put("l", "list", [b"x", b"y"]),
        D.put("c", "counter", -5),
        origin="h1",
        client_seq=9,
        meta="tx-1",
    )
    assert res.ok and res.seq == 1 and res.origin == "h1" and res.client_seq == 9 and res.meta == "tx-1"
    assert [r.version for r in res.results] == [1, 1, 1, 1]
    assert db.get("b").value == b"\x00\xff"
    assert db.get("j").value == {"a": "é", "z": [1, 2.5, None, True]}
    assert db.get("j").data == '{"a":"é","z":[1,2.5,null,true]}'.encode()
    assert db.get("l").value == (b"x", b"y")
    assert db.get("c").value == -5 and db.get("c").data == (-5).to_bytes(8, "big", signed=True)
    assert db.get("missing") is None and "b" in db and db.size == 4 and db.seq == 1


def test_put_overwrites_same_type_keeps_created_and_rejects_other_type():
    db = Ddb()
    run(db, D.put("k", "blob", b"1"))
    run(db, D.put("other", "blob", b"x"))
    res = run(db, D.put("k", "blob", b"2"), D.put("k", "json", 1))
    o = db.get("k")
    assert (o.value, o.version, o.created) == (b"2", 3, 1)
    assert res.results[0].ok and res.results[0].version == 3
    assert res.results[1].reason == "type mismatch: 'k' is a blob, not a json" and res.results[1].version == 0
    run(db, D.delete("k"))
    assert run(db, D.put("k", "json", 1)).ok and db.get("k").created == 5  # a new object after delete


def test_json_value_returned_is_a_fresh_copy():
    db = Ddb()
    run(db, D.put("j", "json", {"a": [1]}))
    db.get("j").value["a"].append(2)
    assert db.get("j").value == {"a": [1]}


@pytest.mark.parametrize(
    ("key", "reason"),
    [
        ("", "invalid key: empty"),
        ("x" * 513, "invalid key: 513 characters > 512"),
        ("a\0b", "invalid key: contains NUL"),
    ],
)
def test_invalid_keys_fail_every_op(key, reason):
    db = Ddb()
    ops = [D.put(key, "blob", b""), D.delete(key), D.append(key, b"i"), D.cas(key, 0, "blob", b""), D.add(key, 1)]
    res = run(db, *ops)
    assert reasons(res) == [reason] * 5 and db.size == 0
    assert run(db, D.put("x" * 512, "blob", b"")).ok  # 512 characters is fine


def test_unknown_type_and_bad_wire_values():
    db = Ddb()
    res = run(
        db,
        D.put("a", "matrix", b"\x01"),
        raw_put("b", "counter", b"\x01\x02"),
        raw_put("c", "list", b"\xff\xff"),
        raw_put("d", "json", b"\xff"),
        raw_put("e", "json", b"{"),
    )
    assert reasons(res) == [
        "unknown type 'matrix'",
        "invalid counter value: expected 8 bytes, got 2",
        "invalid list value: not a DdbListValue",
        "invalid json: not UTF-8 (byte 0)",
        "invalid json: Expecting property name enclosed in double quotes at offset 1",
    ]
    assert db.size == 0 and db.seq == 1


def test_delete():
    db = Ddb()
    run(db, D.put("k", "blob", b"v"))
    res = run(db, D.delete("k"), D.delete("k"))
    assert res.results[0].ok and res.results[1].reason == "not found: 'k'"
    assert db.get("k") is None and db.ls() == []


def test_append_creates_appends_and_trims_from_the_front():
    db = Ddb()
    assert run(db, D.append("q", b"a")).ok
    o = db.get("q")
    assert (o.type_name, o.value, o.version, o.created, o.size) == ("list", (b"a",), 1, 1, 1)
    run(db, D.append("q", b"bb"), D.append("q", b"ccc"))
    assert db.get("q").value == (b"a", b"bb", b"ccc") and db.get("q").version == 2
    run(db, D.append("q", b"d", max_len=2))
    o = db.get("q")
    assert o.value == (b"ccc", b"d") and o.size == 4 and o.created == 1
    run(db, D.append("q", b"e"))  # max_len belongs to the op, not to the list
    assert db.get("q").value == (b"ccc", b"d", b"e")
    run(db, D.put("b", "blob", b""), D.put("c", "counter", 0))
    res = run(db, D.append("b", b"x"), D.append("c", b"x"))
    assert reasons(res) == ["type mismatch: 'b' is a blob, not a list", "type mismatch: 'c' is a counter, not a list"]


def test_cas():
    db = Ddb()
    res = run(db, D.cas("k", 0, "blob", b"1"), D.cas("k", 0, "blob", b"2"))
    assert res.results[0].ok and res.results[1].reason == "version mismatch: expected absent, found 1"
    res = run(db, D.cas("k", 7, "blob", b"3"), D.cas("k", 1, "json", 3), D.cas("new", 4, "blob", b""))
    assert reasons(res) == [
        "version mismatch: expected 7, found 1",
        "type mismatch: 'k' is a blob, not a json",
        "version mismatch: expected 4, found absent",
    ]
    res = run(db, D.cas("k", 1, "blob", b"4"))
    assert res.ok and db.get("k").value == b"4" and db.get("k").version == 3 and db.get("k").created == 1
    assert not run(db, D.cas("k", 1, "blob", b"5")).ok  # the old version no longer matches


def test_counter_add():
    db = Ddb()
    run(db, D.add("n", 5))
    assert db.get("n").value == 5 and db.get("n").type_name == "counter"
    run(db, D.add("n", -7), D.add("n", 0))
    assert db.get("n").value == -2 and db.get("n").version == 2
    run(db, D.put("n", "counter", INT64_MAX - 1))
    res = run(db, D.add("n", 1), D.add("n", 1))
    assert res.results[0].ok and res.results[1].reason == (f"counter overflow: {INT64_MAX} + 1 is outside int64")
    assert db.get("n").value == INT64_MAX
    run(db, D.put("b", "blob", b""))
    assert reasons(run(db, D.add("b", 1))) == ["type mismatch: 'b' is a blob, not a counter"]


def test_ops_in_a_batch_apply_in_order_and_failures_are_per_op():
    db = Ddb()
    res = run(db, D.put("a", "blob", b"1"), D.delete("zzz"), D.delete("a"), D.put("a", "json", [1]))
    assert [r.ok for r in res.results] == [True, False, True, True]
    assert [r.op for r in res.results] == ["put", "delete", "delete", "put"]
    assert db.get("a").value == [1] and db.get("a").created == 1


def test_seq_counts_batches_even_when_every_op_fails():
    db = Ddb()
    run(db, D.delete("x"))
    assert db.seq == 1 and db.size == 0
    run(db, D.put("k", "blob", b""))
    assert db.get("k").version == 2


# ------------------------------------------------------------------------------------------ atomic


def test_atomic_batch_all_or_nothing():
    db = Ddb()
    assert run(db, D.put("a", "blob", b"1"), D.add("n", 1), atomic=True).ok
    before = db.content_hash()
    events = []
    db.watch(events.append)
    res = run(
        db, D.put("a", "blob", b"2"), D.append("l", b"x"), D.cas("a", 1, "blob", b"3"), D.add("n", 1), atomic=True
    )
    why = "atomic batch aborted: op 2 failed: version mismatch: expected 1, found 2"
    assert reasons(res) == [why] * 4 and not any(r.ok for r in res.results) and res.atomic
    assert db.get("a").value == b"1" and db.get("l") is None and db.get("n").value == 1
    assert events == [] and db.seq == 2 and db.content_hash() != before  # the batch still took a seq
    assert db.mirror_since(1)[-1].results == res.results


def test_atomic_batch_ops_see_each_other():
    db = Ddb()
    res = run(db, D.cas("k", 0, "blob", b"1"), D.cas("k", 1, "blob", b"2"), atomic=True)
    assert res.ok and db.get("k").value == b"2"


# ---------------------------------------------------------------------------------------- malformed


def _state(db):
    return db.seq, db.content_hash(), list(db.items()), db.mirror_since(0)


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"\xff\xff\xff", "does not decode"),
        (b"", "no operations"),
        (pb.DdbBatch(origin="x").SerializeToString(), "no operations"),
        (pb.DdbBatch(ops=[pb.DdbOp()]).SerializeToString(), "op 0 has no operation set"),
        (pb.DdbBatch(ops=[D.put("a", "blob", b""), pb.DdbOp()]).SerializeToString(), "op 1 has no operation"),
        (b"\x0a\x05\x0a\x03\x0a\x01\xff", "does not decode"),  # invalid UTF-8 in a string field
        (b"\x00" * (MAX_BATCH_BYTES + 1), "batch too large"),
    ],
)
def test_malformed_payload_is_rejected_and_changes_nothing(payload, message):
    db = Ddb()
    run(db, D.put("a", "blob", b"1"))
    calls = []
    db.watch(calls.append)
    before = _state(db)
    with pytest.raises(DdbError, match=message):
        db.apply(payload)
    assert _state(db) == before and calls == []
    assert run(db, D.put("b", "blob", b"")).seq == 2  # no seq was consumed


# ----------------------------------------------------------------------------------------- limits


def test_value_size_limits():
    db = Ddb()
    big = b"x" * (MAX_VALUE_BYTES + 1)
    with pytest.raises(DdbError, match="value too large"):
        D.put("k", "blob", big)
    with pytest.raises(DdbError, match="value too large"):
        D.append("k", big)
    # (one op per batch: two values over the limit are more than a batch may hold)
    res = run(db, raw_put("k", "blob", big))
    assert reasons(res) == [f"value too large: {MAX_VALUE_BYTES + 1} bytes > {MAX_VALUE_BYTES}"]
    res = run(db, pb.DdbOp(append=pb.DdbAppend(key="l", item=big)))
    assert reasons(res) == [f"value too large: item of {MAX_VALUE_BYTES + 1} bytes > {MAX_VALUE_BYTES}"]
    assert run(db, D.put("k", "blob", b"x" * MAX_VALUE_BYTES)).ok
    # a list's items count together; trimming can keep it under the limit
    half = b"y" * (MAX_VALUE_BYTES // 2)
    assert run(db, D.append("l", half), D.append("l", half)).ok
    res = run(db, D.append("l", b"z"))
    assert reasons(res) == [f"value too large: list would hold {MAX_VALUE_BYTES + 1} bytes > {MAX_VALUE_BYTES}"]
    assert run(db, D.append("l", b"z", max_len=2)).ok and db.get("l").size == len(half) + 1


def test_batch_size_limit_on_encode():
    chunk = b"x" * (MAX_VALUE_BYTES - 64)
    with pytest.raises(DdbError, match=r"batch of \d+ bytes > 2097152 \(MAX_BATCH_BYTES\)"):
        D.encode_batch([D.put(f"k{i}", "blob", chunk) for i in range(MAX_BATCH_BYTES // MAX_VALUE_BYTES + 1)])
    with pytest.raises(DdbError, match="empty batch"):
        D.encode_batch([])
    # the bound is on the encoded batch, so whatever the edge accepts every replica's apply takes
    ops = [D.put("k0", "blob", chunk), D.put("k1", "blob", chunk), D.put("k2", "blob", b"y" * 200)]
    refused = 0
    while True:
        try:
            payload = D.encode_batch(ops, origin="h1")
            break
        except DdbError:
            refused += 1
            ops[2] = D.put("k2", "blob", ops[2].put.value[:-1])
    assert refused > 0 and MAX_BATCH_BYTES - 2 <= len(payload) <= MAX_BATCH_BYTES and Ddb().apply(payload).ok


def test_constructor_errors():
    with pytest.raises(DdbError, match="int64"):
        D.put("c", "counter", 2**63)
    with pytest.raises(DdbError, match="json value cannot be encoded"):
        D.put("j", "json", float("nan"))
    with pytest.raises(DdbError, match="json value cannot be encoded"):
        D.put("j", "json", {"a": object()})
    with pytest.raises(DdbError, match="must be bytes"):
        D.put("b", "blob", "text")
    with pytest.raises(DdbError, match="list items must be bytes"):
        D.put("l", "list", ["a"])
    with pytest.raises(DdbError, match="invalid add"):
        D.add("c", 2**63)
    with pytest.raises(DdbError, match="invalid cas"):
        D.cas("c", -1, "blob", b"")
    with pytest.raises(DdbError, match="unknown type"):
        D.put("x", "matrix", [1])


# -------------------------------------------------------------------------------------------- json


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        (b"NaN", "invalid json: NaN is not allowed"),
        (b"[-Infinity]", "invalid json: -Infinity is not allowed"),
        (b"1e999", "invalid json: number 1e999 is out of range"),
        (b'{"a":1,"a":2}', "invalid json: duplicate key 'a'"),
        (b'"\\ud800"', "invalid json: lone surrogate in a string"),
        (b"[" * 101 + b"]" * 101, "invalid json: nested deeper than 100"),
        (b"1 2", "invalid json: Extra data at offset 2"),
    ],
)
def test_json_rejections(text, reason):
    db = Ddb()
    assert reasons(run(db, raw_put("j", "json", text))) == [reason]


def test_json_depth_limit_is_exact_and_ignores_brackets_in_strings():
    db = Ddb()
    deep = b"[" * 100 + b"]" * 100
    in_string = json.dumps(["[{" * 500]).encode()
    assert run(db, raw_put("a", "json", deep), raw_put("b", "json", in_string)).ok


def test_json_is_stored_canonically_so_key_order_and_spacing_do_not_change_the_hash():
    a, b, c = Ddb(), Ddb(), Ddb()
    run(a, D.put("j", "json", {"a": 1, "b": {"y": [1.5, "é"], "x": None}}))
    run(b, D.put("j", "json", {"b": {"x": None, "y": [1.5, "é"]}, "a": 1}))
    run(c, raw_put("j", "json", b' { "b" : { "x":null , "y":[ 15e-1, "\\u00e9" ] },\n"a": 1 } '))
    assert a.get("j").data == b.get("j").data == c.get("j").data == '{"a":1,"b":{"x":null,"y":[1.5,"é"]}}'.encode()
    assert a.content_hash() == b.content_hash() == c.content_hash()


# ----------------------------------------------------------------------------------------- hashing


def test_content_hash_covers_seq_and_every_field():
    def h(*ops, batches=1):
        db = Ddb()
        for _ in range(batches - 1):
            run(db, D.delete("nothing"))
        run(db, *ops)
        return db.content_hash()

    base = h(D.put("k", "blob", b"v"))
    assert base == h(D.put("k", "blob", b"v"))
    others = {
        h(D.put("k", "blob", b"w")),
        h(D.put("k2", "blob", b"v")),
        h(D.put("k", "list", [b"v"])),
        h(D.put("k", "blob", b"v"), batches=2),  # seq (and version, created)
        h(D.put("k", "blob", b"v"), D.put("k2", "blob", b"v")),
    }
    assert base not in others and len(others) == 5
    # writing the same value twice in one batch gives the same version, hence the same state
    assert h(D.put("k", "blob", b"v"), D.put("k", "blob", b"v")) == base
    empty = Ddb()
    assert empty.content_hash() != Ddb.restore(pb.DdbSnapshot(format=1, seq=1).SerializeToString()).content_hash()


def test_content_hash_known_answer():
    """Pins the canonical encoding: replicas of different builds must agree on it."""
    db = Ddb()
    run(db, D.put("hosts/h1", "json", {"addr": "10.0.0.1", "cpu": 4}), D.add("n", 3), D.append("q", b"a"))
    run(db, D.put("blob", "blob", b"\x00"), D.delete("n"))

    # the documented encoding, recomputed independently
    def digest(key, type_name, value, version, created):
        k, t = key.encode(), type_name.encode()
        return hashlib.sha256(
            b"haa.ddb.obj\0" + struct.pack(">I", len(k)) + k + struct.pack(">I", len(t)) + t
            + struct.pack(">QQQ", version, created, len(value)) + value
        ).digest()  # fmt: skip

    objs = [
        digest("blob", "blob", b"\x00", 2, 2),
        digest("hosts/h1", "json", b'{"addr":"10.0.0.1","cpu":4}', 1, 1),
        digest("q", "list", b"\x0a\x01a", 1, 1),
    ]
    expected = hashlib.sha256(b"haa.ddb.v1\0" + struct.pack(">QQ", 2, 3) + b"".join(objs)).hexdigest()
    assert db.content_hash() == expected
    assert expected == "4152391a8a6ea082ea57ccf1a91f4523d2562757f490376b39185505e61391cf"


def test_content_hash_cache_is_invalidated_by_apply():
    db = Ddb()
    run(db, D.append("q", b"a"))
    h1 = db.content_hash()
    assert db.content_hash() == h1
    run(db, D.append("q", b"b"))
    fresh = Ddb.restore(db.snapshot())
    assert db.content_hash() != h1 and db.content_hash() == fresh.content_hash()


# -------------------------------------------------------------------------------------- snapshots


def test_snapshot_restore_round_trip_then_continue():
    a = Ddb()
    run(a, D.put("j", "json", {"b": 1, "a": [True]}), D.append("q", b"1"), D.add("n", 2), D.put("b", "blob", b""))
    run(a, D.append("q", b"2"), D.delete("b"))
    b = Ddb.restore(a.snapshot())
    assert b.seq == a.seq and list(b.items()) == list(a.items()) and b.content_hash() == a.content_hash()
    assert b.snapshot() == a.snapshot()
    more = [D.encode_batch([D.append("q", b"3", max_len=2), D.add("n", -1), D.cas("j", 1, "json", 0)])]
    more.append(D.encode_batch([D.put("new", "counter", 1), D.delete("q")]))
    for p in more:
        ra, rb = a.apply(p), b.apply(p)
        assert ra.results == rb.results
    assert a.content_hash() == b.content_hash() and list(a.items()) == list(b.items())


def test_restore_rejects_bad_snapshots():
    good = pb.DdbObjectRecord(key="a", type="blob", value=b"", version=1, created=1)
    cases = {
        "does not decode": b"\xff\xff",
        "unknown snapshot format 2": pb.DdbSnapshot(format=2),
        "invalid key: empty": pb.DdbSnapshot(format=1, seq=1, objects=[pb.DdbObjectRecord(version=1, created=1)]),
        "strictly increasing": pb.DdbSnapshot(format=1, seq=1, objects=[good, good]),
        "created <= version <= seq": pb.DdbSnapshot(
            format=1, seq=1, objects=[pb.DdbObjectRecord(key="a", type="blob", version=2, created=1)]
        ),
        "unknown type 'x'": pb.DdbSnapshot(
            format=1, seq=1, objects=[pb.DdbObjectRecord(key="a", type="x", version=1, created=1)]
        ),
        "invalid counter value": pb.DdbSnapshot(
            format=1, seq=1, objects=[pb.DdbObjectRecord(key="a", type="counter", version=1, created=1)]
        ),
    }
    for message, snap in cases.items():
        data = snap if isinstance(snap, bytes) else snap.SerializeToString()
        with pytest.raises(DdbError, match=message):
            Ddb.restore(data)


# ---------------------------------------------------------------------------------------- watchers


def test_watcher_event_kinds_and_values():
    db = Ddb()
    events: list[DdbEvent] = []
    db.watch(events.append)
    run(db, D.put("b", "blob", b"1"), D.put("b", "blob", b"2"), D.append("q", b"x"), D.add("n", 4))
    run(db, D.append("q", b"y", max_len=1), D.add("n", -1), D.delete("b"), D.put("j", "json", {"k": 1}))
    assert [(e.kind, e.key, e.type_name, e.version, e.value, e.delta, e.trimmed) for e in events] == [
        ("add", "b", "blob", 1, b"1", 0, 0),
        ("write", "b", "blob", 1, b"2", 0, 0),
        ("add", "q", "list", 1, (), 0, 0),
        ("append", "q", "list", 1, b"x", 0, 0),
        ("add", "n", "counter", 1, 0, 0, 0),
        ("increment", "n", "counter", 1, 4, 4, 0),
        ("append", "q", "list", 2, b"y", 0, 1),
        ("increment", "n", "counter", 2, 3, -1, 0),
        ("remove", "b", "blob", 2, b"2", 0, 0),
        ("add", "j", "json", 2, {"k": 1}, 0, 0),
    ]


def test_failed_ops_emit_nothing():
    db = Ddb()
    events = []
    db.watch(events.append)
    run(db, D.delete("x"), D.cas("y", 3, "blob", b""), D.put("", "blob", b""))
    assert events == []


def test_watcher_filters():
    db = Ddb()
    got: dict[str, list[tuple[str, str]]] = {n: [] for n in ("key", "prefix", "type", "events", "all_of")}

    def rec(name):
        return lambda e: got[name].append((e.kind, e.key))

    db.watch(rec("key"), key="agents/a1/state")
    db.watch(rec("prefix"), prefix="agents/")
    db.watch(rec("type"), type_name="counter")
    db.watch(rec("events"), events=["remove", "increment"])
    db.watch(rec("all_of"), prefix="agents/", type_name="list", events="append")
    run(
        db,
        D.put("agents/a1/state", "blob", b"s"),
        D.append("agents/a1/queue", b"m"),
        D.add("agents/count", 1),
        D.add("hosts/count", 1),
        D.delete("agents/a1/state"),
        D.append("hosts/h1/log", b"l"),
    )
    assert got["key"] == [("add", "agents/a1/state"), ("remove", "agents/a1/state")]
    assert got["prefix"] == [
        ("add", "agents/a1/state"),
        ("add", "agents/a1/queue"),
        ("append", "agents/a1/queue"),
        ("add", "agents/count"),
        ("increment", "agents/count"),
        ("remove", "agents/a1/state"),
    ]
    assert got["type"] == [
        ("add", "agents/count"),
        ("increment", "agents/count"),
        ("add", "hosts/count"),
        ("increment", "hosts/count"),
    ]
    assert got["events"] == [("increment", "agents/count"), ("increment", "hosts/count"), ("remove", "agents/a1/state")]
    assert got["all_of"] == [("append", "agents/a1/queue")]
    with pytest.raises(DdbError, match="unknown event kind"):
        db.watch(print, events=["changed"])


def test_notification_order_isolation_and_unwatch():
    db = Ddb()
    log = []

    def boom(e):
        log.append(("boom", e.key))
        raise RuntimeError("watcher bug")

    def first(e):
        log.append(("first", e.key))

    def last(e):
        log.append(("last", e.key, db.get("b") is not None))  # sees the whole batch applied

    db.watch(first)
    w_boom = db.watch(boom)
    db.watch(last)
    res = run(db, D.put("a", "blob", b""), D.put("b", "blob", b""))
    assert res.ok and db.size == 2
    assert log == [
        ("first", "a"), ("boom", "a"), ("last", "a", True),
        ("first", "b"), ("boom", "b"), ("last", "b", True),
    ]  # fmt: skip
    assert db.watcher_errors == 2 and isinstance(db.last_watcher_error, RuntimeError)
    assert db.unwatch(w_boom) and not db.unwatch(w_boom)
    log.clear()
    run(db, D.delete("a"))
    assert log == [("first", "a"), ("last", "a", True)]


def test_unwatch_and_reentrant_apply_inside_a_callback():
    db = Ddb()
    seen = []
    errors = []

    def once(e):
        seen.append(e.key)
        db.unwatch(wid)
        try:
            run(db, D.put("inner", "blob", b""))
        except DdbError as err:
            errors.append(str(err))

    wid = db.watch(once)
    run(db, D.put("a", "blob", b""), D.put("b", "blob", b""))
    assert seen == ["a"] and errors == ["apply called from a watcher callback"]
    assert db.get("inner") is None and db.seq == 1
    assert run(db, D.put("c", "blob", b"")).seq == 2  # apply works again afterwards


def test_watchers_do_not_affect_state():
    ops = [D.put("a", "json", [1]), D.append("q", b"1"), D.add("n", 1), D.delete("a")]
    plain, watched = Ddb(), Ddb()

    def bad(e):
        raise ValueError("x")

    watched.watch(bad)
    for db in (plain, watched):
        run(db, *ops)
    assert plain.content_hash() == watched.content_hash() and watched.watcher_errors == 6


# ------------------------------------------------------------------------------------------ mirror


def test_mirror_since_coverage_and_replay():
    db = Ddb(mirror_capacity=3)
    payloads = [D.encode_batch([D.add("n", i)], "h", i) for i in range(1, 6)]
    snap_at_2 = None
    for i, p in enumerate(payloads, 1):
        db.apply(p, meta=f"m{i}")
        if i == 2:
            snap_at_2 = db.snapshot()
    assert db.mirror_since(5) == []
    assert [e.seq for e in db.mirror_since(2)] == [3, 4, 5]
    assert [e.seq for e in db.mirror_since(4)] == [5]
    assert db.mirror_since(1) is None and db.mirror_since(0) is None  # evicted: needs a fresh snapshot
    entry = db.mirror_since(4)[0]
    assert entry.payload == payloads[4] and entry.meta == "m5" and entry.results[0].ok
    with pytest.raises(DdbError, match="at seq 5"):
        db.mirror_since(6)
    # a subscriber: snapshot, then every applied batch, reaches the same state
    sub = Ddb.restore(snap_at_2)
    for e in db.mirror_since(sub.seq):
        sub.apply(e.payload)
    assert sub.content_hash() == db.content_hash()
    assert sub.mirror_since(2) == [e for e in sub.mirror_since(2)] and sub.mirror_since(1) is None


def test_mirror_ignores_malformed_payloads_and_respects_bounds():
    db = Ddb(mirror_capacity=0)
    run(db, D.add("n", 1))
    assert db.mirror_since(1) == [] and db.mirror_since(0) is None
    size = len(D.encode_batch([D.put("k0", "blob", b"x" * 40)], "t"))
    db = Ddb(mirror_max_bytes=2 * size + 1)
    for i in range(5):
        run(db, D.put(f"k{i}", "blob", b"x" * 40))
    assert [e.seq for e in db.mirror_since(3)] == [4, 5] and db.mirror_since(2) is None
    with pytest.raises(DdbError):
        db.apply(b"\xff")
    assert [e.seq for e in db.mirror_since(3)] == [4, 5]
    run(db, D.put("big", "blob", b"x" * 500))  # larger than the byte bound: still kept alone
    assert [e.seq for e in db.mirror_since(5)] == [6]


# ----------------------------------------------------------------------------------------- reads


def test_ls_and_items_in_key_order_with_prefix():
    db = Ddb()
    keys = ["b", "a/2", "a/1", "a", "ab", "a/1/x", "é", "Z"]
    run(db, *[D.put(k, "blob", k.encode()) for k in keys])
    assert db.ls() == sorted(keys)
    assert db.ls("a/") == ["a/1", "a/1/x", "a/2"]
    assert db.ls("a") == ["a", "a/1", "a/1/x", "a/2", "ab"]
    assert db.ls("c") == [] and db.ls("é") == ["é"]
    assert [o.value for o in db.items("a/1")] == [b"a/1", b"a/1/x"]
    run(db, D.delete("a/1"), D.delete("Z"))
    assert db.ls() == sorted(set(keys) - {"a/1", "Z"})


# ------------------------------------------------------------------------------ replicas (property)


class Model:
    """A deliberately naive reference for the op semantics (key -> [type, value, version, created])."""

    def __init__(self):
        self.objs: dict[str, list] = {}
        self.seq = 0

    def apply(self, ops: list[tuple], atomic: bool) -> list[bool]:
        self.seq += 1
        saved = {k: list(v) for k, v in self.objs.items()}
        oks = [self.op(*op) for op in ops]
        if atomic and not all(oks):
            self.objs = saved
            return [False] * len(ops)
        return oks

    def op(self, kind, key, *args) -> bool:
        cur = self.objs.get(key)
        if kind == "put" or kind == "cas":
            if kind == "cas":
                exp, type_name, value = args
                if (cur[2] if cur else 0) != exp:
                    return False
            else:
                type_name, value = args
            if cur and cur[0] != type_name:
                return False
            if type_name == "list":
                value = tuple(value)
            self.objs[key] = [type_name, value, self.seq, cur[3] if cur else self.seq]
        elif kind == "delete":
            if not cur:
                return False
            del self.objs[key]
        elif kind == "append":
            item, max_len = args
            if cur and cur[0] != "list":
                return False
            items = (*cur[1], item) if cur else (item,)
            if max_len:
                items = items[-max_len:]
            self.objs[key] = ["list", items, self.seq, cur[3] if cur else self.seq]
        elif kind == "add":
            (delta,) = args
            if cur and cur[0] != "counter":
                return False
            new = (cur[1] if cur else 0) + delta
            if not INT64_MIN <= new <= INT64_MAX:
                return False
            self.objs[key] = ["counter", new, self.seq, cur[3] if cur else self.seq]
        return True


KEYS = st.sampled_from(["a", "a/b", "b", "q", "n"])
JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=6,
)
VALUES = st.one_of(
    st.tuples(st.just("blob"), st.binary(max_size=4)),
    st.tuples(st.just("json"), JSON),
    st.tuples(st.just("list"), st.lists(st.binary(max_size=3), max_size=3)),
    st.tuples(st.just("counter"), st.integers(INT64_MIN, INT64_MAX) | st.integers(-3, 3)),
)
OPS = st.one_of(
    st.builds(lambda k, tv: ("put", k, *tv), KEYS, VALUES),
    st.builds(lambda k: ("delete", k), KEYS),
    st.builds(lambda k, i, m: ("append", k, i, m), KEYS, st.binary(max_size=3), st.integers(0, 3)),
    st.builds(lambda k, v, tv: ("cas", k, v, *tv), KEYS, st.integers(0, 6), VALUES),
    st.builds(lambda k, d: ("add", k, d), KEYS, st.integers(-5, 5) | st.integers(INT64_MIN, INT64_MAX)),
)
BATCHES = st.lists(st.tuples(st.lists(OPS, min_size=1, max_size=4), st.booleans()), min_size=1, max_size=12)


def to_op(t):
    kind, key, *args = t
    return {"put": D.put, "delete": D.delete, "append": D.append, "cas": D.cas, "add": D.add}[kind](key, *args)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batches=BATCHES, cut=st.integers(0, 12))
def test_replicas_agree_with_each_other_and_the_model(batches, cut):
    payloads = [D.encode_batch([to_op(o) for o in ops], "h", i, atomic=at) for i, (ops, at) in enumerate(batches)]
    a, b = Ddb(), Ddb(mirror_capacity=2)
    model = Model()
    shadow: dict = {}  # rebuilt from the events alone: they must describe every change

    def on(e: DdbEvent):
        if e.kind in ("add", "write", "increment"):
            shadow[e.key] = e.value
        elif e.kind == "remove":
            del shadow[e.key]
        elif e.kind == "append":
            items = (*shadow[e.key], e.value)
            shadow[e.key] = items[e.trimmed :]

    a.watch(on)
    c = None
    for i, ((ops, atomic), p) in enumerate(zip(batches, payloads, strict=True)):
        if i == cut:
            c = Ddb.restore(a.snapshot())
        ra, rb = a.apply(p), b.apply(p)
        assert ra.results == rb.results
        assert [r.ok for r in ra.results] == model.apply(ops, atomic)
        if c is not None:
            assert c.apply(p).results == ra.results
    if c is None:
        c = Ddb.restore(a.snapshot())
    expected = {k: tuple(v) for k, v in model.objs.items()}
    got = {o.key: (o.type_name, o.value, o.version, o.created) for o in a.items()}
    assert got == expected
    assert list(a.items()) == list(b.items()) == list(c.items())
    assert a.content_hash() == b.content_hash() == c.content_hash() == Ddb.restore(b.snapshot()).content_hash()
    assert shadow == {o.key: o.value for o in a.items()}


# ---------------------------------------------------------------------------------------- sans-I/O


@pytest.mark.parametrize("module", ["objects", "ddb", "ops"])
def test_ddb_module_is_sans_io(module):
    """The DDB's modules (haa/core/ddb/: objects.py, ddb.py, ops.py) import only the standard library's pure
    modules, protobuf, its generated messages and each other."""
    spec = importlib.util.spec_from_file_location("_sans_io", ROOT / "tests/test_sans_io.py")
    sans_io = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sans_io)
    path = ROOT / f"haa/core/ddb/{module}.py"
    assert not sans_io._imports(path) & sans_io.FORBIDDEN
    tree = parse_source(path)
    haa = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names if a.name.startswith("haa")}
    haa |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("haa")}
    assert "haa.pb.ddb_pb2" in haa
    assert haa <= {"haa.pb.ddb_pb2", "haa.core.ddb.objects", "haa.core.ddb.ops"}
    src = path.read_text()
    assert "import grpc" not in src and "ddb_pb2_grpc" not in src


# ------------------------------------------------------------------------------------------------ work bounds


def test_a_batch_of_more_than_max_batch_ops_is_refused_at_the_edge_and_on_apply():
    from haa.core.ddb.objects import MAX_BATCH_OPS

    ops = [D.delete(f"k{i}") for i in range(MAX_BATCH_OPS + 1)]  # ~130 KB: bytes would not stop it
    with pytest.raises(DdbError, match=rf"batch of {MAX_BATCH_OPS + 1} ops > {MAX_BATCH_OPS} \(MAX_BATCH_OPS\)"):
        D.encode_batch(ops)
    db = Ddb()
    raw = pb.DdbBatch(ops=ops).SerializeToString()  # a peer that skipped the edge: refused, nothing applied
    with pytest.raises(DdbError, match="MAX_BATCH_OPS"):
        db.apply(raw)
    assert db.seq == 0
    assert len(run(db, *ops[:MAX_BATCH_OPS]).results) == MAX_BATCH_OPS  # the bound itself is accepted


def _footprint(db: Ddb) -> tuple[int, int]:
    return db.size, sum(len(o.key) + o.size for o in db.items())


def test_the_replica_bounds_its_keys_and_bytes_and_an_op_over_them_fails_alone(monkeypatch):
    import haa.core.ddb.ddb as ddbmod

    monkeypatch.setattr(ddbmod, "MAX_DDB_KEYS", 3)
    monkeypatch.setattr(ddbmod, "MAX_DDB_BYTES", 100)
    db = Ddb()
    res = run(db, *[D.put(k, "blob", str(i).encode()) for i, k in enumerate("abcd", 1)])
    assert [r.ok for r in res.results] == [True, True, True, False]
    assert reasons(res)[3] == "ddb full: 4 keys > 3 (MAX_DDB_KEYS)"
    assert db.ls() == ["a", "b", "c"] and db.footprint == 6 == _footprint(db)[1]
    # deleting makes room; replacing a value in place needs no new key
    res = run(db, D.delete("a"), D.put("d", "blob", b"4"), D.put("b", "blob", b"x" * 60))
    assert [r.ok for r in res.results] == [True, True, True] and db.ls() == ["b", "c", "d"]
    # bytes (key characters + values: b 61, c 2, d 2): growing "c" by 39 takes the replica to 104 > 100 and
    # fails, only that op; a later smaller growth still applies
    res = run(db, D.put("c", "blob", b"y" * 40), D.put("d", "blob", b"z" * 30))
    assert [r.ok for r in res.results] == [False, True]
    assert reasons(res)[0] == "ddb full: 104 bytes > 100 (MAX_DDB_BYTES); delete or trim first", reasons(res)
    assert db.footprint == _footprint(db)[1] == 61 + 2 + 31
    # atomic: the op over the bound aborts the whole batch
    before = db.content_hash()
    res = run(db, D.delete("b"), D.put("e", "blob", b"1"), D.put("f", "blob", b"1"), atomic=True)
    assert not any(r.ok for r in res.results) and "ddb full" in res.results[0].reason
    assert db.ls() == ["b", "c", "d"] and db.content_hash() != before  # (a new seq, nothing else changed)
    # a snapshot carries its footprint
    assert Ddb.restore(db.snapshot()).footprint == db.footprint


def test_many_new_keys_in_one_batch_keep_the_index_sorted():
    import random

    rng = random.Random(5)
    db = Ddb()
    keys = [f"k/{rng.randrange(10**9)}/{i}" for i in range(3000)]
    run(db, *[D.put(k, "blob", b"") for k in keys[:1000]])  # a merge (more than 256 new keys)
    run(db, *[D.put(k, "blob", b"") for k in keys[1000:1010]])  # inserts one by one
    run(db, *[D.put(k, "blob", b"") for k in keys[1010:]], *[D.delete(k) for k in keys[:500]])
    assert db.ls() == sorted(keys[500:]) and db.ls("k/1") == sorted(k for k in keys[500:] if k.startswith("k/1"))
    assert Ddb.restore(db.snapshot()).content_hash() == db.content_hash()
    assert db.footprint == _footprint(db)[1]
