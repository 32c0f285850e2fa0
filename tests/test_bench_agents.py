"""Benchmarks of the agent layer: the bench agent types (in-process), and smoke runs of `bench ap4` and
`bench ap3 --real` on 2 real local hosts with 2 samples each (JSON shape and sanity, never timings)."""

from __future__ import annotations

import json
import math
import zlib

import pytest

from haa.lab.experiments.benchagents import STATE_HEAD, BallastAgent, PingerAgent
from haa.pb import agent_pb2 as pb
from haa.sdk.base import AgentContext
from haa.sdk.registry import REGISTRY, load_builtin


def _agent(cls: type, config: dict, epoch: int = 1) -> object:
    init = pb.HostToAgent.Init(agent_id="a-1", name="A1", type_name=cls.TYPE, config=json.dumps(config).encode(),
                               epoch=epoch, host="h1")
    return AgentContext(init, cls, lambda _frame: None).agent


def test_bench_types_are_found_by_the_registry_scan() -> None:
    assert not [e for e in load_builtin() if "benchagents" in e]
    assert REGISTRY["ballast"] is BallastAgent
    assert REGISTRY["pinger"] is PingerAgent


def test_ballast_state_is_the_configured_size_and_survives_a_round_trip() -> None:
    a = _agent(BallastAgent, {"state_bytes": 111_000, "seed": 7})
    a.pings = 5
    data = a.pack_state()
    assert 111_000 < len(data) < 111_000 + 300
    b = _agent(BallastAgent, {"state_bytes": 10, "seed": 1}, epoch=2)
    b.unpack_state(data)
    assert b.blob == a.blob and len(b.blob) == 111_000 and b.pings == 5 and b.thaws == 1
    c = _agent(BallastAgent, {"state_bytes": 10}, epoch=3)
    c.recover(data)
    assert c.blob == a.blob and c.recoveries == 1
    # another seed gives another blob: the state is not a constant the receiver could make up
    assert _agent(BallastAgent, {"state_bytes": 111_000, "seed": 8}).blob != a.blob


def test_ballast_rejects_a_corrupted_state() -> None:
    a = _agent(BallastAgent, {"state_bytes": 1000})
    data = bytearray(a.pack_state())
    data[-1] ^= 0xFF
    b = _agent(BallastAgent, {"state_bytes": 1000})
    with pytest.raises(ValueError, match="corrupted"):
        b.unpack_state(bytes(data))
    with pytest.raises(ValueError, match="bad magic"):
        b.unpack_state(b"XXXX" + bytes(data[4:]))
    assert zlib.crc32(b.blob) == zlib.crc32(a.blob)  # unchanged by the failed loads
    assert STATE_HEAD.size == 8


def test_bad_bench_agent_config_names_the_field() -> None:
    with pytest.raises(ValueError, match=r"config\.state_bytes"):
        _agent(BallastAgent, {"state_bytes": -1})
    with pytest.raises(ValueError, match=r"config\.period"):
        _agent(PingerAgent, {"target": "x", "period": 0})
    with pytest.raises(ValueError, match=r"config\.target"):
        _agent(PingerAgent, {"target": 5})


def test_pinger_report_finds_the_longest_reply_gap_in_the_window() -> None:
    p = _agent(PingerAgent, {"target": "b"})
    t = 1000.0
    # a request every 5 ms answered after 1 ms, except those sent in [t + 0.100, t + 0.180) (the target is
    # frozen): they are answered together right after t + 0.181
    for i in range(60):
        s = t + i * 0.005
        if 20 <= i < 36:
            p.records.append((s, t + 0.181 + i * 1e-5, True))
        else:
            p.records.append((s, s + 0.001, True))
    p.records.append((t + 0.2, 0.0, False))  # a lost request
    rep = p.report(t + 0.05, t + 0.3)
    assert rep["max_gap"] == pytest.approx(0.181 - 0.096, abs=1e-6)  # last reply before -> first after
    assert rep["gap_start"] == pytest.approx(t + 0.096)
    assert rep["max_rtt"] == pytest.approx(0.181 + 20e-5 - 0.100, abs=1e-6)
    assert rep["failed"] == 1 and rep["sent"] == 51
    quiet = p.report(t + 0.25, t + 0.29)
    assert quiet["max_gap"] == pytest.approx(0.005)


@pytest.mark.slow
def test_bench_ap4_smoke_two_hosts(tmp_path) -> None:
    from haa.lab.experiments.ap4 import METRICS, run_ap4
    from haactl import benchtables

    rows = run_ap4((2,), reps=2, root=tmp_path, log=lambda _s: None)
    assert len(rows) == 1
    r = json.loads(json.dumps(rows[0]))
    assert "error" not in r, r.get("error")
    assert r["hosts"] == 2 and r["reps"] == 2 and r["state_bytes"] == 111_000
    # a group of two cannot survive a host crash with an OAC in flight: skipped, with the reason
    assert r["host_crash_skipped"] and r["samples"]["host_crash"] == []
    for kind in ("spawn", "transfer_idle", "transfer", "agent_crash"):
        assert len(r["samples"][kind]) == 2
    for key in ("spawn", "spawn_ready", "freeze", "transfer", "transfer_ready", "transfer_unreachable",
                "freeze_idle", "transfer_idle", "crash_detect", "recovery", "recovery_total", "recovery_unreachable"):
        s = r["summary"][key]
        assert s["n"] == 2 and s["missing"] == 0, key
        assert 0 < s["median"] <= s["p90"] <= s["max"] < 30, key
    for s in r["samples"]["transfer"] + r["samples"]["transfer_idle"]:
        assert s["from"] != s["to"]
        assert s["freezing"] <= s["freeze"] <= s["thawing"] <= s["transfer"]
    for s in r["samples"]["agent_crash"]:
        assert s["from_backup"] is True  # the 111 kB backup made at start
        assert s["crash_detect"] <= s["recovery_total"]
    assert "host_recovery" not in r["summary"]
    assert set(r["summary"]) <= set(METRICS)
    table = benchtables.ap4(rows)
    assert table.count("\n") >= 12 and "| transfer (move request -> thawed) | 2 |" in table
    assert benchtables.ap4_compact(rows).splitlines()[-1].startswith("| 2 |")


@pytest.mark.slow
def test_bench_ap3_real_smoke_two_hosts(tmp_path) -> None:
    from haa.lab.experiments.ap3real import merge_json, run_ap3_real
    from haactl import benchtables

    rows = run_ap3_real((2,), (5,), reps=2, root=tmp_path, log=lambda _s: None)
    assert len(rows) == 1
    r = json.loads(json.dumps(rows[0]))
    assert "error" not in r, r.get("error")
    assert (r["hosts"], r["agents"], r["reps"], r["failed"]) == (2, 5, 2, 0)
    assert r["consensus_ms"]["n"] == 2 and r["allocated_ms"]["n"] == 2
    for s in r["samples"]:
        assert s["ok"] and not math.isnan(s["allocated_s"])
        assert 0 < s["consensus_s"] <= s["allocated_s"] <= s["request_s"]
        assert s["bid_messages"] >= 2  # each of the two hosts sends its bids to the other at least once
        assert s["oac_messages_window"] >= s["oac_messages_session"] == 12  # 2 OACs of 2 participants
    assert "| 2 |" in benchtables.ap3_real(rows)
    path = tmp_path / "ap3.json"
    path.write_text(json.dumps({"mode": "simulated", "rows": [1]}))
    merged = merge_json(path, {"rows": rows})
    assert merged["rows"] == [1] and merged["mode"] == "simulated" and merged["real"]["rows"] == rows
