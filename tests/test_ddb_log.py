"""The DDB's `log` type (haa.core.ddb, docs/ddb.md "Logs"): log_append / log_trim semantics and indexes, the
bounds, type mismatches, watcher events with indexes, snapshots, the hash, identical rejection of malformed
ops on every replica, the edge check `check_op`, and replica agreement on random op sequences that mix logs
with the other types (hypothesis, against a reference model)."""

import hashlib
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import haa.pb.ddb_pb2 as pb
from haa.core.ddb import ops as D
from haa.core.ddb.ddb import Ddb, DdbEvent
from haa.core.ddb.objects import (
    MAX_KEY,
    MAX_LOG_BYTES,
    MAX_LOG_INDEX,
    MAX_LOG_ITEM_BYTES,
    MAX_LOG_ITEMS,
    MAX_VALUE_BYTES,
    DdbError,
)

KiB = 1024


def run(db: Ddb, *ops, atomic=False):
    return db.apply(D.encode_batch(ops, "t", 0, atomic=atomic))


def reasons(res):
    return [r.reason for r in res.results]


def raw_append(key, items):
    """A log_append op as a peer could propose it, without the client-side checks."""
    return pb.DdbOp(log_append=pb.DdbLogAppend(key=key, items=items))


def log_of(db: Ddb, key: str):
    o = db.get(key)
    assert o is not None and o.type_name == "log"
    return o.value["first"], list(o.value["items"])


# ---------------------------------------------------------------------------------------------- ops


def test_append_creates_the_log_at_zero_and_numbers_items_in_order():
    db = Ddb()
    res = run(db, D.log_append("L", [b"a", b"b"]), D.log_append("L", [b"c"]))
    assert all(r.ok for r in res.results) and [r.version for r in res.results] == [1, 1]
    run(db, D.log_append("L", [b"d", b"e", b"f"]))
    o = db.get("L")
    assert (o.type_name, o.version, o.created, o.size) == ("log", 2, 1, 6)
    assert o.value == {"first": 0, "items": (b"a", b"b", b"c", b"d", b"e", b"f")}
    assert D.decode_log(o.data) == (0, (b"a", b"b", b"c", b"d", b"e", b"f"))


def test_trim_drops_below_upto_and_indexes_never_repeat():
    db = Ddb()
    run(db, D.log_append("L", [b"0", b"1", b"2", b"3"]))
    assert run(db, D.log_trim("L", 2)).ok
    assert log_of(db, "L") == (2, [b"2", b"3"])
    assert db.get("L").size == 2 and db.get("L").version == 2
    run(db, D.log_append("L", [b"4"]))
    assert log_of(db, "L") == (2, [b"2", b"3", b"4"])  # index 4, not 2: trimmed indexes are not given again
    # trimming everything keeps the position: the next item still gets the next index
    assert run(db, D.log_trim("L", 5)).ok
    assert log_of(db, "L") == (5, []) and db.get("L").size == 0
    run(db, D.log_append("L", [b"5"]))
    assert log_of(db, "L") == (5, [b"5"])


def test_trim_at_or_below_first_is_a_no_op_and_beyond_the_end_fails():
    db = Ddb()
    run(db, D.log_append("L", [b"a", b"b", b"c"]))
    run(db, D.log_trim("L", 2))
    before = db.get("L")
    events = []
    db.watch(events.append)
    res = run(db, D.log_trim("L", 2), D.log_trim("L", 0))
    assert [r.ok for r in res.results] == [True, True]
    assert [r.version for r in res.results] == [2, 2]  # nothing written: the version it left
    assert db.get("L") is before and events == []
    res = run(db, D.log_trim("L", 4), D.log_trim("missing", 0))
    assert reasons(res) == ["trim beyond the end: upto 4 > next index 3 of 'L'", "not found: 'missing'"]
    assert db.get("L") is before and events == []


def test_an_atomic_batch_with_a_failing_op_appends_nothing():
    db = Ddb()
    events = []
    db.watch(events.append)
    res = run(db, D.log_append("L", [b"a"]), D.log_trim("L", 5), atomic=True)
    assert not any(r.ok for r in res.results)
    assert reasons(res)[0] == "atomic batch aborted: op 1 failed: trim beyond the end: upto 5 > next index 1 of 'L'"
    assert "L" not in db and events == []
    # the SLAM supervisor's checkpoint: the checkpoint and the trim, all or nothing
    run(db, D.log_append("L", [b"a", b"b"]))
    res = run(db, D.put("ckpt", "blob", b"state@2"), D.log_trim("L", 2), atomic=True)
    assert res.ok and db.get("ckpt").value == b"state@2" and log_of(db, "L") == (2, [])


def test_type_mismatches_and_put_of_a_log():
    db = Ddb()
    run(db, D.put("b", "blob", b"x"), D.add("n", 1), D.log_append("L", [b"a"]))
    res = run(
        db,
        D.log_append("b", [b"a"]),
        D.log_trim("n", 0),
        D.put("L", "blob", b"x"),
        D.append("L", b"x"),
        D.add("L", 1),
        pb.DdbOp(put=pb.DdbPut(key="new", type="log", value=b"")),
        pb.DdbOp(put=pb.DdbPut(key="L", type="log", value=b"")),
        pb.DdbOp(cas=pb.DdbCas(key="L", expected_version=1, type="log", value=b"")),
    )
    cannot = "a log is written only by its own ops, not by put or cas"
    assert reasons(res) == [
        "type mismatch: 'b' is a blob, not a log",
        "type mismatch: 'n' is a counter, not a log",
        "type mismatch: 'L' is a log, not a blob",
        "type mismatch: 'L' is a log, not a list",
        "type mismatch: 'L' is a log, not a counter",
        cannot,
        cannot,
        cannot,
    ]
    assert "new" not in db and log_of(db, "L") == (0, [b"a"])
    with pytest.raises(DdbError, match="written only by its own ops"):
        D.put("k", "log", {"first": 0, "items": []})
    with pytest.raises(DdbError, match="written only by its own ops"):
        D.cas("k", 0, "log", (0, ()))


def test_a_deleted_log_starts_again_at_zero_as_a_new_object():
    db = Ddb()
    run(db, D.log_append("L", [b"a", b"b"]), D.log_trim("L", 1))
    run(db, D.delete("L"))
    run(db, D.log_append("L", [b"c"]))
    o = db.get("L")
    assert o.value == {"first": 0, "items": (b"c",)} and o.created == 3


# ------------------------------------------------------------------------------------------- limits


def test_item_size_limit():
    db = Ddb()
    big = b"x" * (MAX_LOG_ITEM_BYTES + 1)
    with pytest.raises(DdbError, match="MAX_LOG_ITEM_BYTES"):
        D.log_append("L", [b"ok", big])
    res = run(db, raw_append("L", [b"ok", big]))  # a peer that skipped the check: the op fails, whole
    assert reasons(res) == [f"log item 1 too large: {len(big)} bytes > {MAX_LOG_ITEM_BYTES} (MAX_LOG_ITEM_BYTES)"]
    assert "L" not in db
    assert run(db, D.log_append("L", [big[:-1]])).ok  # exactly the limit


def test_total_size_limit_then_trim_makes_room():
    assert MAX_LOG_BYTES == 16 * MAX_LOG_ITEM_BYTES  # (the arithmetic below)
    db = Ddb()
    item = b"y" * MAX_LOG_ITEM_BYTES
    for _ in range(4):  # 4 x 4 items: exactly MAX_LOG_BYTES (a batch stays under MAX_BATCH_BYTES)
        assert run(db, D.log_append("L", [item] * 4)).ok
    assert db.get("L").size == MAX_LOG_BYTES
    res = run(db, D.log_append("L", [b"", b"z"]))
    assert reasons(res) == [
        f"log full: 'L' would hold {MAX_LOG_BYTES + 1} bytes > {MAX_LOG_BYTES} (MAX_LOG_BYTES); trim it first"
    ]
    assert log_of(db, "L")[0] == 0 and len(log_of(db, "L")[1]) == 16  # nothing of the op was appended
    assert run(db, D.log_trim("L", 1), D.log_append("L", [b"z"])).ok
    first, items = log_of(db, "L")
    assert (first, len(items), items[-1]) == (1, 16, b"z")
    # a replica restored from a snapshot holds the full log too
    assert Ddb.restore(db.snapshot()).content_hash() == db.content_hash()


def test_item_count_limit():
    db = Ddb()
    assert run(db, D.log_append("L", [b""] * MAX_LOG_ITEMS)).ok
    res = run(db, D.log_append("L", [b""]))
    assert reasons(res) == [
        f"log full: 'L' would hold {MAX_LOG_ITEMS + 1} items > {MAX_LOG_ITEMS} (MAX_LOG_ITEMS); trim it first"
    ]
    with pytest.raises(DdbError, match="MAX_LOG_ITEMS"):
        D.log_append("M", [b""] * (MAX_LOG_ITEMS + 1))


def test_index_overflow_is_refused():
    top = MAX_LOG_INDEX
    snap = pb.DdbSnapshot(format=1, seq=1)
    value = pb.DdbLogValue(first=top - 1, items=[b"a"]).SerializeToString()
    snap.objects.add(key="L", type="log", value=value, version=1, created=1)
    db = Ddb.restore(snap.SerializeToString())
    assert log_of(db, "L") == (top - 1, [b"a"])
    res = run(db, D.log_append("L", [b"b"]))
    assert reasons(res) == [f"log index overflow: 'L' would reach index {top + 1}"]
    assert run(db, D.log_trim("L", top)).ok and log_of(db, "L") == (top, [])


def test_client_constructor_errors():
    for bad, match in [
        (lambda: D.log_append("L", b"abc"), "iterable of bytes items"),
        (lambda: D.log_append("L", "abc"), "iterable of bytes items"),
        (lambda: D.log_append("L", []), "no items"),
        (lambda: D.log_append("L", [b"a", "b"]), "log item 1 must be bytes"),
        (lambda: D.log_trim("L", -1), "upto must be an int"),
        (lambda: D.log_trim("L", 2**64), "upto must be an int"),
        (lambda: D.log_trim("L", True), "upto must be an int"),
        (lambda: D.decode_log(b"\xff\xff"), "not a DdbLogValue"),
    ]:
        with pytest.raises(DdbError, match=match):
            bad()
    assert D.decode_log(b"") == (0, ())
    op = D.log_append("L", (bytearray(b"a"), memoryview(b"b")))
    assert list(op.log_append.items) == [b"a", b"b"]


def test_check_op_refuses_what_needs_no_replica_to_refuse():
    big = b"x" * (MAX_LOG_ITEM_BYTES + 1)
    cases = {
        "": [D.log_append("L", [b"a"]), D.log_trim("L", 3), D.put("k", "json", {"a": 1}), D.add("n", 1)],
        "invalid key: empty": [D.log_append("", [b"a"]), D.log_trim("", 0)],
        "invalid key: contains NUL": [D.put("a\0", "blob", b"")],
        "unknown type 'nope'": [pb.DdbOp(put=pb.DdbPut(key="k", type="nope"))],
        "a log is written only by its own ops": [pb.DdbOp(cas=pb.DdbCas(key="k", type="log"))],
        "log_append with no items": [pb.DdbOp(log_append=pb.DdbLogAppend(key="L"))],
        "log item 0 too large": [raw_append("L", [big])],
        "value too large": [pb.DdbOp(put=pb.DdbPut(key="k", type="blob", value=b"v" * (MAX_VALUE_BYTES + 1)))],
        "op has no operation set": [pb.DdbOp()],
    }
    for reason, ops in cases.items():
        for op in ops:
            got = D.check_op(op)
            assert got.startswith(reason) if reason else got == "", (op, got)


# -------------------------------------------------------------------------------- events, snapshots


def test_events_carry_each_item_and_its_index_and_trims_the_new_first():
    db = Ddb()
    events: list[DdbEvent] = []
    db.watch(events.append)
    run(db, D.log_append("L", [b"a", b"b"]), D.log_append("L", [b"c"]))
    run(db, D.log_trim("L", 2), D.log_trim("L", 1), D.log_append("L", [b"d"]), D.delete("L"))
    assert [(e.kind, e.key, e.type_name, e.version, e.value, e.trimmed, e.index) for e in events] == [
        ("add", "L", "log", 1, {"first": 0, "items": ()}, 0, 0),
        ("append", "L", "log", 1, b"a", 0, 0),
        ("append", "L", "log", 1, b"b", 0, 1),
        ("append", "L", "log", 1, b"c", 0, 2),
        ("trim", "L", "log", 2, 2, 2, 2),
        ("append", "L", "log", 2, b"d", 0, 3),
        ("remove", "L", "log", 2, {"first": 2, "items": (b"c", b"d")}, 0, 0),
    ]
    # filters know the new kind
    trims = []
    db.watch(trims.append, events=["trim"])
    run(db, D.log_append("M", [b"1", b"2"]), D.log_trim("M", 1))
    assert [(e.kind, e.value, e.index) for e in trims] == [("trim", 1, 1)]


def test_snapshot_restore_round_trip_then_continue():
    a = Ddb()
    run(a, D.log_append("L", [b"1", b"2", b"3"]), D.put("j", "json", [1]), D.log_append("E", [b"x"]))
    run(a, D.log_trim("L", 2), D.log_trim("E", 1))
    b = Ddb.restore(a.snapshot())
    assert list(b.items()) == list(a.items()) and b.content_hash() == a.content_hash()
    assert b.snapshot() == a.snapshot()
    rec = next(r for r in pb.DdbSnapshot.FromString(a.snapshot()).objects if r.key == "L")
    assert D.decode_log(rec.value) == (2, (b"3",))
    more = [
        D.encode_batch([D.log_append("L", [b"4"]), D.log_trim("E", 0), D.log_trim("L", 9)]),
        D.encode_batch([D.log_trim("L", 4), D.delete("E"), D.log_append("E", [b"y"])]),
    ]
    for p in more:
        assert a.apply(p).results == b.apply(p).results
    assert a.content_hash() == b.content_hash() and list(a.items()) == list(b.items())
    assert log_of(b, "L") == (4, []) and log_of(b, "E") == (0, [b"y"])


def test_restore_rejects_bad_log_values():
    def snap(value: bytes) -> bytes:
        s = pb.DdbSnapshot(format=1, seq=1)
        s.objects.add(key="L", type="log", value=value, version=1, created=1)
        return s.SerializeToString()

    big = b"x" * (MAX_LOG_ITEM_BYTES + 1)
    cases = {
        "not a DdbLogValue": b"\xff\xff",
        "log item 0 too large": pb.DdbLogValue(items=[big]).SerializeToString(),
        "log too long": pb.DdbLogValue(items=[b""] * (MAX_LOG_ITEMS + 1)).SerializeToString(),
        "log too large": pb.DdbLogValue(items=[big[:-1]] * 17).SerializeToString(),
        "log index overflow": pb.DdbLogValue(first=MAX_LOG_INDEX, items=[b"a"]).SerializeToString(),
    }
    for message, value in cases.items():
        with pytest.raises(DdbError, match=message):
            Ddb.restore(snap(value))


def test_content_hash_known_answer_for_a_log():
    """Pins the canonical encoding of a log (a DdbLogValue): replicas of different builds must agree on it."""
    db = Ddb()
    run(db, D.log_append("ev", [b"a", b"bc"]))
    run(db, D.log_trim("ev", 1))

    k, t = b"ev", b"log"
    value = b"\x08\x01" + b"\x12\x02bc"  # first = 1 (field 1, varint), items = [b"bc"] (field 2, bytes)
    d = hashlib.sha256(
        b"haa.ddb.obj\0" + struct.pack(">I", len(k)) + k + struct.pack(">I", len(t)) + t
        + struct.pack(">QQQ", 2, 1, len(value)) + value
    ).digest()  # fmt: skip
    expected = hashlib.sha256(b"haa.ddb.v1\0" + struct.pack(">QQ", 2, 1) + d).hexdigest()
    assert db.get("ev").data == value
    assert db.content_hash() == expected
    assert expected == "73d8f2fd01b902265ca07a7d5065fbe03eb89dd4209a885a2f81ca53078e5d4e"


def test_the_hash_covers_first_and_items():
    def h(first, items):
        snap = pb.DdbSnapshot(format=1, seq=2)
        value = pb.DdbLogValue(first=first, items=items).SerializeToString()
        snap.objects.add(key="L", type="log", value=value, version=2, created=1)
        return Ddb.restore(snap.SerializeToString()).content_hash()

    base = h(1, [b"b"])
    others = {h(0, [b"b"]), h(2, [b"b"]), h(1, [b"c"]), h(1, [b"b", b""]), h(1, [])}
    assert base not in others and len(others) == 5
    # the same state reached by different histories hashes the same (a dropped item leaves no trace)
    a, b = Ddb(), Ddb()
    run(a, D.log_append("L", [b"x", b"b"]))
    run(b, D.log_append("L", [b"a", b"b"]))
    run(a, D.log_trim("L", 1))
    run(b, D.log_trim("L", 1))
    assert a.content_hash() == b.content_hash() == base


# ----------------------------------------------------------------------- malformed and hostile input


def test_malformed_log_ops_are_refused_identically_on_every_replica():
    replicas = [Ddb(), Ddb(mirror_capacity=1)]
    for db in replicas:
        run(db, D.put("b", "blob", b"x"), D.log_append("L", [b"a"]))
    bad_ops = [
        raw_append("", [b"a"]),
        raw_append("L", []),
        raw_append("b", [b"a"]),
        raw_append("x" * (MAX_KEY + 1), [b"a"]),
        raw_append("L", [b"z" * (MAX_LOG_ITEM_BYTES + 1)]),
        pb.DdbOp(log_trim=pb.DdbLogTrim(key="L", upto=2**64 - 1)),
        pb.DdbOp(log_trim=pb.DdbLogTrim(key="\0")),
        pb.DdbOp(put=pb.DdbPut(key="L", type="log", value=pb.DdbLogValue(first=0).SerializeToString())),
    ]
    payload = pb.DdbBatch(ops=bad_ops, origin="evil").SerializeToString()
    outcomes = [db.apply(payload).results for db in replicas]
    assert outcomes[0] == outcomes[1] and not any(r.ok for r in outcomes[0])
    # a payload whose op has no operation set (e.g. an unknown op kind) is refused whole, taking no seq
    unknown = pb.DdbBatch(ops=[D.log_append("L", [b"b"]), pb.DdbOp()]).SerializeToString()
    for db in replicas:
        with pytest.raises(DdbError, match="op 1 has no operation set"):
            db.apply(unknown)
    # bytes flipped or cut anywhere: every replica decides the same way
    good = D.encode_batch([D.log_append("L", [b"bb", b"cc"]), D.log_trim("L", 1)])
    for i in range(len(good)):
        for variant in (good[:i], good[:i] + bytes([good[i] ^ 0x5A]) + good[i + 1 :]):
            got = []
            for db in replicas:
                try:
                    got.append(db.apply(variant).results)
                except DdbError as e:
                    got.append(str(e))
            assert got[0] == got[1], (i, variant)
    assert replicas[0].content_hash() == replicas[1].content_hash()


# ------------------------------------------------------------------------------ replicas (property)


class Model:
    """A naive reference: logs as (first, [items]), counters as ints, blobs as bytes; key -> [type, value]."""

    def __init__(self):
        self.objs: dict[str, list] = {}

    def apply(self, ops: list[tuple], atomic: bool) -> list[bool]:
        saved = {k: [v[0], (v[1][0], list(v[1][1])) if v[0] == "log" else v[1]] for k, v in self.objs.items()}
        oks = [self.op(*op) for op in ops]
        if atomic and not all(oks):
            self.objs = saved
            return [False] * len(ops)
        return oks

    def op(self, kind, key, *args) -> bool:
        cur = self.objs.get(key)
        if kind == "log_append":
            (items,) = args
            if cur and cur[0] != "log":
                return False
            if not cur:
                cur = self.objs[key] = ["log", (0, [])]
            cur[1][1].extend(items)
        elif kind == "log_trim":
            (upto,) = args
            if not cur or cur[0] != "log":
                return False
            first, items = cur[1]
            if upto > first + len(items):
                return False
            if upto > first:
                cur[1] = (upto, items[upto - first :])
        elif kind == "put":
            if cur and cur[0] != "blob":
                return False
            self.objs[key] = ["blob", args[0]]
        elif kind == "add":
            if cur and cur[0] != "counter":
                return False
            self.objs[key] = ["counter", (cur[1] if cur else 0) + args[0]]
        elif kind == "delete":
            if not cur:
                return False
            del self.objs[key]
        return True

    def public(self):
        return {k: {"first": v[1][0], "items": tuple(v[1][1])} if v[0] == "log" else v[1] for k, v in self.objs.items()}


LKEYS = st.sampled_from(["L", "M", "n"])
LOPS = st.one_of(
    st.builds(lambda k, i: ("log_append", k, i), LKEYS, st.lists(st.binary(max_size=2), min_size=1, max_size=3)),
    st.builds(lambda k, u: ("log_trim", k, u), LKEYS, st.integers(0, 9)),
    st.builds(lambda k, v: ("put", k, v), LKEYS, st.binary(max_size=2)),
    st.builds(lambda k, d: ("add", k, d), LKEYS, st.integers(-3, 3)),
    st.builds(lambda k: ("delete", k), LKEYS),
)
LBATCHES = st.lists(st.tuples(st.lists(LOPS, min_size=1, max_size=4), st.booleans()), min_size=1, max_size=12)


def to_op(t):
    kind, key, *args = t
    if kind == "put":
        return D.put(key, "blob", args[0])
    return {"log_append": D.log_append, "log_trim": D.log_trim, "add": D.add, "delete": D.delete}[kind](key, *args)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batches=LBATCHES, cut=st.integers(0, 12))
def test_replicas_with_logs_agree_with_each_other_the_model_and_their_events(batches, cut):
    payloads = [D.encode_batch([to_op(o) for o in ops], "h", i, atomic=at) for i, (ops, at) in enumerate(batches)]
    a, b = Ddb(), Ddb(mirror_capacity=2)
    model = Model()
    shadow: dict = {}  # rebuilt from the events alone: they must describe every change of a log

    def on(e: DdbEvent):
        if e.kind in ("add", "write", "increment"):
            shadow[e.key] = e.value
        elif e.kind == "remove":
            del shadow[e.key]
        elif e.kind == "append":
            log = shadow[e.key]
            assert e.index == log["first"] + len(log["items"])  # the next index, in order
            shadow[e.key] = {"first": log["first"], "items": (*log["items"], e.value)}
        elif e.kind == "trim":
            log = shadow[e.key]
            assert e.trimmed == e.index - log["first"] > 0 and e.value == e.index
            shadow[e.key] = {"first": e.index, "items": log["items"][e.trimmed :]}

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
    assert {o.key: o.value for o in a.items()} == model.public() == shadow
    assert list(a.items()) == list(b.items()) == list(c.items())
    assert a.content_hash() == b.content_hash() == c.content_hash() == Ddb.restore(b.snapshot()).content_hash()


# ---------------------------------------------------------------------------------------- haactl


def test_haactl_ddb_get_shows_a_log_by_index_with_its_newest_items_cut():
    from haa.cluster.values import plain_value
    from haactl.ddbcli import LOG_ITEM_CHARS, LOG_SHOW_ITEMS, show_log

    db = Ddb()
    run(db, D.log_append("L", [f"line {i}".encode() for i in range(LOG_SHOW_ITEMS + 3)]))
    run(db, D.log_append("L", [b"x" * 200, b"two\nlines", b"\xff"]), D.log_trim("L", 2))
    value = plain_value("log", db.get("L").data)
    assert value["first"] == 2 and len(value["items"]) == LOG_SHOW_ITEMS + 4 and value["items"][-1] == "base64:/w=="
    lines = show_log(value).splitlines()
    assert lines[:3] == [f"log: first 2, {LOG_SHOW_ITEMS + 4} items, next {LOG_SHOW_ITEMS + 6}", "... 4 older items",
                         "[6] line 6"]  # fmt: skip
    assert lines[-3:] == ["[13] " + "x" * (LOG_ITEM_CHARS - 1) + "…", "[14] two\\nlines", "[15] base64:/w=="]
    assert len(lines) == 2 + LOG_SHOW_ITEMS
