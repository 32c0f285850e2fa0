"""HostRuntime in-process: the timer wheel, the delivered log and its hash chain, propose outcomes
(commit, abort, timeout), and reincarnation."""

from __future__ import annotations

import asyncio
import hashlib
import time
from collections.abc import Hashable

import pytest
from helpers import run, until

from haa.cluster.hostprocs import free_port
from haa.core.effects import CancelTimer, SetTimer
from haa.core.host.hostcore import CoreConfig
from haa.core.messages import Excluded, TxId
from haa.core.oac.oac import OacError
from haa.core.ufd.qos import QosTargets
from haa.core.ufd.ufd import UfdConfig
from haa.hostd.delivered import GENESIS_HASH, chain_hash
from haa.hostd.outcomes import HostReincarnated, ProposeTimeout, TransactionAborted
from haa.hostd.runtime import HostRuntime, RuntimeConfig

FAST_CORE = CoreConfig(
    ufd=UfdConfig(qos=QosTargets(td_upper=0.3, tmr_lower=3600.0, tm_upper=1.0), initial_period=0.02),
    exclude_after=30.0,
)


def runtimes(names: list[str], no_votes: tuple[bytes, ...] = ()) -> dict[str, HostRuntime]:
    ports = {n: free_port() for n in names}
    return {
        n: HostRuntime(
            RuntimeConfig(
                name=n,
                listen=f"127.0.0.1:{ports[n]}",
                peers={p: f"127.0.0.1:{pp}" for p, pp in ports.items() if p != n},
                token="t",
                core=FAST_CORE,
            ),
            no_votes=no_votes,
        )
        for n in names
    }


def trusted(rts: dict[str, HostRuntime]) -> bool:
    return all(
        not row["suspected"] and row["incarnation"] == rts[row["name"]].incarnation
        for rt in rts.values()
        for row in rt.core.peer_view()  # type: ignore[union-attr]
    )


def test_chain_hash_definition() -> None:
    t = TxId("h1", 7, 3)
    want = hashlib.sha256(GENESIS_HASH.encode() + b"\nh1.7.3\npayload").hexdigest()
    assert chain_hash(GENESIS_HASH, t, b"payload") == want
    assert chain_hash(want, t, b"x") != chain_hash(want, TxId("h1", 7, 4), b"x")
    # no ambiguity between the id and the payload
    assert chain_hash(GENESIS_HASH, TxId("h1", 1, 1), b"2") != chain_hash(GENESIS_HASH, TxId("h1", 1, 12), b"")


def test_timer_wheel_replaces_cancels_and_never_fires_early() -> None:
    async def main() -> None:
        rt = runtimes(["solo"])["solo"]
        await rt.start()
        fired: list[tuple[float, Hashable]] = []
        core = rt.core
        assert core is not None
        core.on_timer = lambda now, key: fired.append((now, key))  # type: ignore[method-assign]
        t = time.monotonic()
        core.out += [
            SetTimer(("x", 1), t + 0.02),
            SetTimer(("x", 1), t + 0.06),  # replaces the first
            SetTimer(("y", 1), t + 0.03),
            SetTimer(("z", 1), t + 0.01),
            CancelTimer(("z", 1)),
        ]
        rt._apply()
        # z was cancelled and the first x replaced: were either to fire, it would come first (t+0.01, t+0.02)
        await until(lambda: len(fired) >= 2, what="two timers")
        assert [k for _n, k in fired] == [("y", 1), ("x", 1)]
        assert fired[0][0] >= t + 0.03 and fired[1][0] >= t + 0.06
        await rt.stop()

    run(main())


def test_single_host_commit_and_abort_and_delivered_log() -> None:
    async def main() -> None:
        rt = runtimes(["solo"], no_votes=(b"veto",))["solo"]
        await rt.start()
        res = await rt.propose(b"a", participants=[])
        assert res.participants == ("solo",) and res.txid.host == "solo"
        with pytest.raises(TransactionAborted) as exc:
            await rt.propose(b"veto", participants=[])
        assert exc.value.txid.seq == res.txid.seq + 1
        res2 = await rt.propose(b"b", participants=[])
        assert [(e.index, e.payload) for e in rt.delivered.entries] == [(0, b"a"), (1, b"b")]
        h = chain_hash(chain_hash(GENESIS_HASH, res.txid, b"a"), res2.txid, b"b")
        assert rt.delivered.hash == h == rt.delivered.entries[-1].chain_hash
        d2d, p2d = rt.proposals.take_latencies(reset=True)
        assert len(d2d) == 2 and len(p2d) == 3
        assert rt.proposals.take_latencies(reset=False) == ([], [])
        st = rt.status()
        assert st["delivered"] == 2 and st["counters"]["oac_aborted"] == 1
        with pytest.raises(OacError):
            rt.propose_nowait(b"x", participants=["ghost"])
        await rt.stop()

    run(main())


def test_two_hosts_commit_then_timeout_when_the_peer_is_gone() -> None:
    async def main() -> None:
        rts = runtimes(["a", "b"])
        for rt in rts.values():
            await rt.start()
        await until(lambda: trusted(rts))
        res = await rts["a"].propose(b"both", participants=["a", "b"])
        assert res.participants == ("a", "b")
        await until(lambda: len(rts["b"].delivered.entries) == 1)
        assert rts["a"].delivered.hash == rts["b"].delivered.hash
        await rts["b"].stop()
        # with two participants nothing can be decided without b: the proposer times out
        with pytest.raises(ProposeTimeout) as exc:
            await rts["a"].propose(b"alone", participants=["a", "b"], timeout=0.3)
        assert exc.value.participants == ("a", "b")
        await rts["a"].stop()

    run(main())


def test_reincarnation_on_exclusion_notice() -> None:
    async def main() -> None:
        rts = runtimes(["a", "b"])
        for rt in rts.values():
            await rt.start()
        await until(lambda: trusted(rts))
        a, b = rts["a"], rts["b"]
        old = a.incarnation
        open_tx = asyncio.create_task(a.propose(b"pending", participants=["a", "b"], timeout=5))
        await asyncio.sleep(0)
        n_timers = len(a.timers)
        assert n_timers > 0
        # b tells a that its incarnation has been excluded
        a._on_envelopes("b", b.incarnation, [(old, Excluded(old))])
        assert a.incarnation > old
        assert a.transport.incarnation == a.incarnation
        assert a.counters["reincarnations"] == 1
        with pytest.raises(HostReincarnated):
            await open_tx
        await until(lambda: trusted(rts))
        res = await a.propose(b"again", participants=["a", "b"])
        assert res.txid.inc == a.incarnation
        for rt in rts.values():
            await rt.stop()

    run(main())


def test_concurrent_proposals_commit_and_close_everything() -> None:
    """Regression: the wire codec once dropped OacDecide.delivered, so every rebroadcast counted for the
    l. 41 closing gate and late 'delivered' messages re-created closed transactions as placeholders that
    blocked the l. 37 gate for good. Concurrent proposers on real runtimes hit it within a few
    transactions."""

    async def main() -> None:
        rts = runtimes(["h1", "h2", "h3"])
        for rt in rts.values():
            await rt.start()
        await until(lambda: trusted(rts), 10)
        jobs = [
            asyncio.wait_for(rts[p].propose(f"{p}{i}".encode(), participants=list(rts)), 10)
            for i in range(15)
            for p in rts
        ]
        results = await asyncio.gather(*jobs)
        assert len(results) == 45
        await until(lambda: all(not rt.core.oac.txs for rt in rts.values()), 5)  # type: ignore[union-attr]
        assert len({rt.delivered.hash for rt in rts.values()}) == 1
        assert all(len(rt.delivered.entries) == 45 for rt in rts.values())
        for rt in rts.values():
            await rt.stop()

    run(main())


def test_delivered_log_is_bounded_and_the_chain_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    import haa.hostd.delivered as delivered_mod

    monkeypatch.setattr(delivered_mod, "MAX_DELIVERED", 4)

    async def main() -> None:
        rt = runtimes(["solo"])["solo"]
        await rt.start()
        h = GENESIS_HASH
        for i in range(10):
            res = await rt.propose(f"p{i}".encode(), participants=[])
            h = chain_hash(h, res.txid, f"p{i}".encode())
        log_ = rt.delivered
        assert log_.count == 10 and rt.status()["delivered"] == 10
        assert len(log_.entries) <= 4 and log_.entries[0].index == log_.base
        assert [e.index for e in log_.entries] == list(range(log_.base, 10))
        assert log_.hash == h == log_.entries[-1].chain_hash
        await rt.stop()

    run(main())
