"""DDB values have one decoder, haa.core.ddb.ops.decode_value: a record's canonical bytes -> the value a reader of
the replica sees (`DdbObject.value`), for every type; haa.cluster.values.plain_value (the operator's JSON-able
form: `haactl ddb`) and haa.cluster.queries.ddb_read (the mission runner's reads) build on it."""

from __future__ import annotations

import json

import pytest

from haa.cluster.values import plain_value
from haa.core.ddb import ops as D
from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import TYPES, DdbError


def replica() -> Ddb:
    """One object of every type, written through the ops a client sends."""
    db = Ddb()
    ops = [
        D.put("j", "json", {"b": [1, 2.5, None], "a": "ü"}),
        D.put("b", "blob", b"\x00\xffbytes"),
        D.add("c", -5),
        D.append("l", b"one"),
        D.append("l", b"\xfe"),
        D.log_append("g", [b"first", b"second", b"\xff"]),
        D.log_trim("g", 1),
    ]
    res = db.apply(D.encode_batch(ops, "t", 0))
    assert all(r.ok for r in res.results), [r.reason for r in res.results]
    return db


def test_every_type_decodes_to_what_a_reader_of_the_replica_sees():
    db = replica()
    assert {db.get(k).type_name for k in "jbclg"} == set(TYPES)  # every type is covered
    for key in "jbclg":
        obj = db.get(key)
        assert D.decode_value(obj.type_name, obj.data) == obj.value, key
    assert D.decode_value("json", db.get("j").data) == {"a": "ü", "b": [1, 2.5, None]}
    assert D.decode_value("blob", db.get("b").data) == b"\x00\xffbytes"
    assert D.decode_value("counter", db.get("c").data) == -5
    assert D.decode_value("list", db.get("l").data) == (b"one", b"\xfe")
    assert D.decode_value("log", db.get("g").data) == {"first": 1, "items": (b"second", b"\xff")}


@pytest.mark.parametrize(("type_name", "data", "why"), [
    ("json", b"{bad", "invalid json"),
    ("json", b'{"a": 1, "a": 2}', "duplicate key"),
    ("counter", b"\x01\x02", "expected 8 bytes"),
    ("list", b"\xff\xff", "not a DdbListValue"),
    ("log", b"\xff\xff", "not a DdbLogValue"),
    ("vector", b"", "unknown type"),
])
def test_what_does_not_decode_raises_one_error(type_name, data, why):
    with pytest.raises(DdbError, match=why):
        D.decode_value(type_name, data)


def test_the_operator_sees_every_type_as_json():
    db = replica()
    shown = {k: plain_value(db.get(k).type_name, db.get(k).data) for k in "jbclg"}
    assert shown == {
        "j": {"a": "ü", "b": [1, 2.5, None]},
        "b": "base64:AP9ieXRlcw==",
        "c": -5,
        "l": ["one", "base64:/g=="],
        "g": {"first": 1, "items": ["second", "base64:/w=="]},
    }
    json.dumps(shown)  # JSON-able
    # what does not decode is shown as its bytes
    assert plain_value("counter", b"\x01\x02") == "\x01\x02"
    assert plain_value("vector", b"\xff") == "base64:/w=="
