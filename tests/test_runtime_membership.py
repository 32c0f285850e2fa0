"""haa-hostd in membership mode (`--core`, Alg. 3) with real processes on loopback.

One 5-host cluster (h1-h3 core) is shared by the tests of this module, in order: formation, DDB writes
through several hosts and the mirror stream, the leader crashing, a crashed host restarting as a new
incarnation, a paused host, a graceful leave by SIGTERM. Configuration errors are checked on the command
line (exit code 2, one line naming the option).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from helpers import run, until

from haa.cluster.hostprocs import MemberGroup, MemberHost, free_port, hostd_command
from haa.cluster.hostprocs import wait_for as wait
from haa.core.ddb import ops as ddb
from haa.core.ddb.ddb import Ddb
from haa.hostd.control import ControlClient

TOKEN = "membership-test-token"
NAMES = ["h1", "h2", "h3", "h4", "h5"]
CORE = ["h1", "h2", "h3"]


def views(hosts: list[MemberHost]) -> dict[str, tuple[tuple[str, ...], int, str]]:
    out = {}
    for h in hosts:
        s = h.status()
        out[h.name] = (tuple(s.members), s.view, s.ddb_hash)
    return out


def agree(hosts: list[MemberHost], members: list[str] | None = None) -> bool:
    """Every listed host is a member of the same view (with exactly `members`, if given) and DDB hash."""
    v = views(hosts)
    if len(set(v.values())) != 1:
        return False
    mem = next(iter(v.values()))[0]
    want = set(members) if members is not None else {h.name for h in hosts}
    return set(mem) == want


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, MemberHost]]:
    root = tmp_path_factory.mktemp("membership")
    group = MemberGroup(root, NAMES, core=CORE, token=TOKEN)
    group.start()
    try:
        yield group.hosts
    finally:
        group.close()


def test_group_forms_with_the_first_core_process_as_leader(cluster: dict[str, MemberHost]) -> None:
    hosts = list(cluster.values())
    wait(lambda: agree(hosts, NAMES), 20, "all five hosts in one view")
    for h in hosts:
        s = h.status()
        assert s.mode == "membership" and s.member and s.group_correct
        assert s.leader == "h1" and s.members[0] == "h1"
        assert s.rank == list(s.members).index(h.name)
        assert not s.suspicions
        assert s.ddb_size == 0


def test_ddb_writes_through_any_host_and_the_mirror_stream(cluster: dict[str, MemberHost]) -> None:
    hosts = list(cluster.values())
    events: list[Any] = []
    stream = cluster["h5"].client.mirror(views=True)

    def follow() -> None:
        try:
            for e in stream:
                events.append(e)
        except grpc.RpcError:
            pass

    t = threading.Thread(target=follow, daemon=True)
    t.start()
    wait(lambda: events, 10, "the mirror snapshot")
    for i, h in enumerate(hosts * 4):
        r = h.client.ddb_write([ddb.put(f"k/{i}", "json", {"i": i, "by": h.name})])
        assert r.committed, r.reason
        assert r.results[0].ok and r.results[0].version == r.ddb_seq
    r = cluster["h2"].client.ddb_write([ddb.append("log", b"a"), ddb.add("n", 3), ddb.delete("missing")])
    assert r.committed and [o.ok for o in r.results] == [True, True, False]
    assert r.results[2].reason
    r = cluster["h3"].client.ddb_write([ddb.cas("k/0", 999, "json", 1)], atomic=True)
    assert r.committed and not r.results[0].ok
    wait(lambda: agree(hosts), 10, "equal replicas")
    got = cluster["h4"].client.ddb_get(prefix="k/")
    assert len(got.objects) == 20
    assert cluster["h4"].client.ddb_get(keys=["k/3"]).objects[0].value == b'{"by":"h4","i":3}'
    # replay the mirror stream into a replica of our own: it must end equal to the hosts'
    final = cluster["h1"].status().ddb_hash
    wait(lambda: events and events[-1].ddb_hash == final, 10, "the mirror to catch up")
    stream.cancel()
    kinds = [e.WhichOneof("event") for e in events]
    assert kinds[0] == "snapshot" and kinds.count("batch") == 22
    replica = Ddb.restore(events[0].snapshot.SerializeToString())
    for e in events[1:]:
        if e.WhichOneof("event") == "batch":
            assert e.batch.ddb_seq == replica.seq + 1
            replica.apply(e.batch.payload)
            assert replica.content_hash() == e.ddb_hash
    assert replica.content_hash() == final


def test_leader_crash_is_removed_from_every_view(cluster: dict[str, MemberHost]) -> None:
    h1 = cluster["h1"]
    assert h1.proc is not None
    h1.proc.kill()
    t0 = time.monotonic()
    h1.proc.wait(10)
    rest = [cluster[n] for n in NAMES if n != "h1"]
    wait(lambda: agree(rest, NAMES[1:]), 15, "h1 removed everywhere")
    took = time.monotonic() - t0
    assert took < 5.0, f"crash to removal took {took:.2f} s"
    for h in rest:
        s = h.status()
        assert s.leader == s.members[0] != "h1"
    r = cluster["h4"].client.ddb_write([ddb.put("after-crash", "blob", b"x")])
    assert r.committed


def test_restarted_host_rejoins_with_an_equal_replica(cluster: dict[str, MemberHost]) -> None:
    h1 = cluster["h1"]
    old_inc = max(int(x) for x in (h1.data_dir / "incarnation").read_text().split())
    assert (h1.data_dir / "known_hosts.json").exists()
    h1.start()
    hosts = list(cluster.values())
    wait(lambda: agree(hosts, NAMES), 20, "h1 back in every view")
    s = h1.status()
    assert s.incarnation > old_inc
    assert s.members[-1] == "h1"  # a new member is appended at the end of the list
    assert s.ddb_size == cluster["h2"].status().ddb_size == 23


def test_paused_host_is_removed_and_comes_back_as_a_new_incarnation(cluster: dict[str, MemberHost]) -> None:
    h4 = cluster["h4"]
    assert h4.proc is not None
    inc = h4.status().incarnation
    h4.proc.send_signal(signal.SIGSTOP)
    try:
        others = [cluster[n] for n in NAMES if n != "h4"]
        wait(lambda: agree(others, [n for n in NAMES if n != "h4"]), 15, "h4 removed")
        # the group keeps working without it
        assert cluster["h2"].client.ddb_write([ddb.put("while-paused", "blob", b"p")]).committed
    finally:
        h4.proc.send_signal(signal.SIGCONT)
    hosts = list(cluster.values())
    wait(lambda: agree(hosts, NAMES), 20, "h4 back")
    assert h4.status().incarnation > inc
    assert cluster["h4"].client.ddb_get(keys=["while-paused"]).objects


def test_sigterm_is_a_graceful_leave(cluster: dict[str, MemberHost]) -> None:
    h5 = cluster["h5"]
    assert h5.proc is not None
    h5.proc.send_signal(signal.SIGTERM)
    assert h5.proc.wait(10) == 0
    rest = [cluster[n] for n in NAMES if n != "h5"]
    # a leave needs no failure detection: the view without h5 is committed before it exits
    assert all("h5" not in h.status().members for h in rest)
    assert not (h5.data_dir / "known_hosts.json").exists()
    log = (h5.data_dir / "h5.jsonl").read_text()
    assert '"event":"left"' in log


def _hostd(args: list[str], env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*hostd_command(), *args],
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, **(env or {})},
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--peers", "h2=127.0.0.1:1", "--core", "h1=127.0.0.1:2"], "--core: give either --peers"),
        (["--core", "h1=127.0.0.1:2,h1=127.0.0.1:3"], "duplicate core process"),
        (["--core", "h1=nowhere"], "is not HOST:PORT"),
        (["--core", "h1=127.0.0.1:2", "--advertise", "x"], "--advertise"),
    ],
)
def test_bad_settings_exit_2_naming_the_option(tmp_path: Path, args: list[str], message: str) -> None:
    (tmp_path / "t").write_text("tok\n")
    r = _hostd(["--name", "h1", "--listen", "127.0.0.1:0", "--token-file", str(tmp_path / "t"), *args])
    assert r.returncode == 2, r.stderr
    assert message in r.stderr and r.stderr.count("\n") == 1


def test_yaml_file_and_environment(tmp_path: Path) -> None:
    (tmp_path / "t").write_text("tok\n")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: h1\ncore: [h1=127.0.0.1:2\n")
    r = _hostd(["--config", str(bad), "--listen", "127.0.0.1:0", "--token-file", str(tmp_path / "t")])
    assert r.returncode == 2 and "not valid YAML at line" in r.stderr
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("name: h1\ncores: h1=127.0.0.1:2\n")
    r = _hostd(["--config", str(unknown), "--listen", "127.0.0.1:0", "--token-file", str(tmp_path / "t")])
    assert r.returncode == 2 and "unknown option 'cores'" in r.stderr
    sizes = tmp_path / "sizes.yaml"
    sizes.write_text("name: h1\ncore: {h1: '127.0.0.1:2', h2: '127.0.0.1:3'}\nmembership: {c_f: 1}\n")
    r = _hostd(["--config", str(sizes), "--listen", "127.0.0.1:0", "--token-file", str(tmp_path / "t")])
    assert r.returncode == 2 and "c_f = 1 violates c_f < c/2" in r.stderr
    # the environment fills what the file and the command line leave out, and is validated the same way
    r = _hostd(
        ["--config", str(sizes), "--token-file", str(tmp_path / "t")],
        env={"HAA_LISTEN": "127.0.0.1:0", "HAA_FORGET_GROUP": "maybe"},
    )
    assert r.returncode == 2 and "HAA_FORGET_GROUP" in r.stderr


def test_a_single_core_process_forms_a_group_of_one_and_serves_the_ddb(tmp_path: Path) -> None:
    (tmp_path / "t").write_text(TOKEN + "\n")
    port = free_port()
    yaml_file = tmp_path / "h.yaml"
    yaml_file.write_text(
        f"name: solo\nlisten: 127.0.0.1:{port}\ncore: solo=127.0.0.1:{port}\nmembership:\n  discovery: 0.1\n"
    )
    proc = subprocess.Popen(
        [*hostd_command(), "--config", str(yaml_file), "--data-dir", str(tmp_path / "d")],
        env={**os.environ, "HAA_TOKEN_FILE": str(tmp_path / "t")},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    c = ControlClient(f"127.0.0.1:{port}", TOKEN)
    try:
        s = wait(lambda: (st := c.status()).member and st, 15, "the group of one")
        assert list(s.members) == ["solo"] and s.leader == "solo" and s.group_correct
        assert c.ddb_write([ddb.put("a", "counter", 1)]).committed
        with pytest.raises(grpc.RpcError) as e:
            ControlClient(f"127.0.0.1:{port}", "wrong").status()
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        reply = c.leave(exit=True)
        assert reply.left
        assert proc.wait(10) == 0
    finally:
        c.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert sys.executable  # keep the interpreter import used by hostd_command's fallback


def test_concurrent_writes_each_keep_their_own_results(tmp_path: Path) -> None:
    """In-process single-host group: concurrent `ddb_write`s through the sequencer, each request gets exactly
    its own ops' results, later ops see earlier ones, an atomic request is all or none over its own ops."""
    import asyncio

    from haa.core.membership.membership import NodeConfig
    from haa.hostd.runtime import HostRuntime, RuntimeConfig

    port = free_port()
    addr = f"127.0.0.1:{port}"

    async def main() -> None:
        rt = HostRuntime(
            RuntimeConfig(
                name="solo",
                listen=addr,
                peers={},
                token=TOKEN,
                data_dir=tmp_path / "solo",
                core_processes=[("solo", addr)],
                node=NodeConfig(discovery=0.05),
            )
        )
        await rt.start()
        try:
            await until(lambda: rt.status()["member"], what="a group of one")
            # one core process: c_f = 0, so its group of one is a correct group and takes writes
            writes = [rt.writes.ddb_write([ddb.put(f"k{i}", "counter", i), ddb.add(f"k{i}", 100)]) for i in range(30)]
            writes.append(rt.writes.ddb_write([ddb.cas("k0", 999, "counter", 7)], atomic=True))  # stale version
            writes.append(rt.writes.ddb_write([ddb.delete("k1"), ddb.delete("nope")]))
            res = await asyncio.gather(*writes)
            for i, r in enumerate(res[:30]):
                assert [o.key for o in r.results] == [f"k{i}", f"k{i}"] and all(o.ok for o in r.results)
            assert not res[30].results[0].ok
            assert [o.ok for o in res[31].results] == [True, False]
            assert rt.mnode is not None
            db = rt.mnode.state.ddb
            assert db.get("k5").value == 105 and db.get("k1") is None
            c = rt.counters
            assert c["ddb_writes"] == 32 and c["writes_submitted"] == 32
            # one DDB batch per request: 32 distinct DDB seqs, in submission order
            assert [r.ddb_seq for r in res] == sorted(r.ddb_seq for r in res) and len({r.ddb_seq for r in res}) == 32
        finally:
            await rt.stop()

    run(main())


def test_one_daemon_per_data_dir(tmp_path: Path) -> None:
    (tmp_path / "t").write_text(TOKEN + "\n")
    port = free_port()
    args = ["--name", "solo", "--listen", f"127.0.0.1:{port}", "--core", f"solo=127.0.0.1:{port}"]
    args += ["--token-file", str(tmp_path / "t"), "--data-dir", str(tmp_path / "d")]
    first = subprocess.Popen([*hostd_command(), *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        c = ControlClient(f"127.0.0.1:{port}", TOKEN)
        wait(lambda: c.status(), 15, "the first daemon")
        c.close()
        second = _hostd([*args[:3], f"127.0.0.1:{free_port()}", *args[4:]])
        assert second.returncode == 1 and "is in use by another haa-hostd" in second.stderr
    finally:
        first.kill()
        first.wait()
