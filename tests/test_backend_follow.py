"""haa.cluster.backend.merged_follow: the container backends' `logs -f` merges one follower thread per host."""

from __future__ import annotations

import queue
import threading

from helpers import wait_sync

from haa.cluster.backend import merged_follow


def test_lines_of_every_host_are_merged_and_closing_stops_the_followers() -> None:
    stopped: list[str] = []

    def follow(name: str, q: queue.Queue[tuple[str, str]], stop: threading.Event) -> None:
        for i in range(3):
            q.put((name, f"{name} line {i}"))
        stop.wait()
        stopped.append(name)

    gen = merged_follow(["h1", "h2"], follow)
    got = [next(gen) for _ in range(6)]
    assert sorted(got) == sorted((h, f"{h} line {i}") for h in ("h1", "h2") for i in range(3))
    assert [ln for h, ln in got if h == "h1"] == [f"h1 line {i}" for i in range(3)]  # each host's order kept
    gen.close()  # the consumer stops: every follower is told to
    wait_sync(lambda: sorted(stopped) == ["h1", "h2"], 5.0, "both followers to stop")
