"""haa.cluster.procs.free_port: ports for daemons started next, outside the kernel's ephemeral range."""

from __future__ import annotations

import socket

import pytest

from haa.cluster import procs


def test_ports_are_below_the_ephemeral_range_distinct_and_free() -> None:
    low = procs._ephemeral_low()
    ports = [procs.free_port() for _ in range(50)]
    assert len(set(ports)) == 50
    assert all(1024 <= p < low for p in ports)
    for p in ports[:5]:
        with socket.socket() as s:
            s.bind(("127.0.0.1", p))


def test_a_taken_port_is_not_handed_out(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        assert not procs._bindable(port)
        monkeypatch.setattr(procs, "_ephemeral_low", lambda: port + 1)
        monkeypatch.setattr(procs.random.SystemRandom, "randrange", lambda self, a, b: port)
        got = procs.free_port()  # every try hits the taken one: bind(0)
        assert got != port


def test_no_room_below_the_range_falls_back_to_an_ephemeral_port(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(procs, "_ephemeral_low", lambda: 1500)
    assert procs.free_port() >= 1500
