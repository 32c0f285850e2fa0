"""haa.files: every file a user hands HAA is size-, depth- and node-limited, rejects duplicate keys and fails
with one line; and the CLIs that read them (haa-hostd --config, haa-sim --arena /
--schedule) print exactly that one line and exit 2, quickly, as real processes.

The fuzz test runs `HAA_FUZZ_EXAMPLES` examples (300 by default; `make fuzz` raises it).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from helpers import wait_sync
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from haa import files
from haa.files import FileError, load_json, load_yaml, parse_json, parse_yaml
from haa.sim.arena import ArenaError, builtin_path, load_arena, parse_arena
from haa.sim.schedule import ScheduleError, load_schedule

FUZZ_EXAMPLES = int(os.environ.get("HAA_FUZZ_EXAMPLES", "300"))
HOSTD = [sys.executable, "-m", "haa.hostd.daemon"]
SIM = [sys.executable, "-m", "haa.sim.service"]


def refused(text: str, match: str, **kw: int) -> FileError:
    with pytest.raises(FileError, match=match) as e:
        parse_yaml(text, "t.yaml", **kw)
    assert "\n" not in str(e.value) and str(e.value).startswith("t.yaml: "), str(e.value)
    return e.value


def write(path: Path, data: str | bytes) -> Path:
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return path


# --------------------------------------------------------------------------- the loader
@pytest.mark.parametrize(
    "text",
    [
        "[" * 100_000,
        "[" * 100_000 + "]" * 100_000,
        "a: " + "{a: " * 100_000,
        "- " * 100_000 + "x",
        "x: " + "!!seq [" * 70,
    ],
    ids=["flow-open", "flow-closed", "flow-mappings", "block-sequences", "tagged"],
)
def test_deep_nesting_is_refused_before_composing(text: str) -> None:
    """yaml.safe_load of these raised RecursionError (a 3,000-line traceback from haa-hostd)."""
    t0 = time.monotonic()
    refused(text, r"nested deeper than 64 levels at line 1")
    assert time.monotonic() - t0 < 2.0


def test_depth_limit_is_exact_and_counts_aliases() -> None:
    value: list[object] = []
    for _ in range(63):
        value = [value]
    assert parse_yaml("[" * 64 + "]" * 64, "t") == value
    refused("[" * 65 + "]" * 65, "nested deeper than 64")
    deep = "a: &a " + "[" * 40 + "]" * 40 + "\nb: " + "[" * 30 + "*a" + "]" * 30 + "\n"
    refused(deep, r"nested deeper than 64 levels \(alias \*a\) at line 2")
    assert parse_yaml(deep, "t", max_depth=80)["b"] is not None


def test_devices_are_refused_unopened_and_oversized_files_stop_at_the_limit(tmp_path: Path) -> None:
    t0 = time.monotonic()
    with pytest.raises(FileError, match=r"^/dev/zero: is a character device, not a regular file$"):
        load_yaml("/dev/zero", what="config file")
    with pytest.raises(FileError, match=r"larger than 100 bytes"):
        load_yaml(write(tmp_path / "big.yaml", "a: 1\n" + "#" * 95 + "\n"), max_bytes=100)
    assert load_yaml(write(tmp_path / "ok.yaml", "a: 1\n" + "#" * 94 + "\n"), max_bytes=100) == {"a": 1}
    assert time.monotonic() - t0 < 2.0


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    with pytest.raises(FileError, match=r"fifo: is a FIFO \(a named pipe\), not a regular file"):
        load_yaml(fifo)  # nobody writes to it: an open would block forever
    assert time.monotonic() - t0 < 1.0


def test_missing_unreadable_and_directories(tmp_path: Path) -> None:
    with pytest.raises(FileError, match=r"no such file$") as e:
        load_yaml(tmp_path / "nope.yaml")
    assert e.value.os_errno is not None
    with pytest.raises(FileError, match=r"is a directory, not a file$"):
        load_yaml(tmp_path)
    assert load_yaml("/dev/null") is None


def test_non_utf8_names_the_byte_offset(tmp_path: Path) -> None:
    with pytest.raises(FileError, match=r"not UTF-8 text \(byte 0xff at offset 9\)"):
        load_yaml(write(tmp_path / "a.yaml", b"name: ab\n\xffc\n"))
    assert load_yaml(write(tmp_path / "bom.yaml", b"\xef\xbb\xbfname: x\n")) == {"name": "x"}


def test_duplicate_keys_are_refused_with_both_lines() -> None:
    refused("a: 1\nb: 2\na: 3\n", r"duplicate key 'a' at line 3 \(first at line 1\)")
    refused("m:\n  x: 1\n  y: 2\n  x: 3\n", r"duplicate key 'x' at line 4 \(first at line 2\)")
    refused("- {k: 1, k: 2}\n", r"duplicate key 'k' at line 1")
    refused("1: a\n0x1: b\n", r"duplicate key 1 at line 2")  # the same key once resolved
    refused("? a\n? a\n", "duplicate key 'a'")  # a !!set-like mapping
    # a merge key's entries may be overridden (that is what merging is for)
    assert parse_yaml("b: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n", "t")["c"] == {"x": 3, "y": 2}


def test_billion_laughs_and_cycles_are_refused_early() -> None:
    lol = "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
    for i in range(1, 10):
        prev, name = chr(96 + i), chr(97 + i)
        lol += f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 10) + "]\n"
    assert len(lol) < 1000
    t0 = time.monotonic()
    refused(lol, r"more than 100000 nodes \(counting aliases expanded\) at line 5")
    assert time.monotonic() - t0 < 1.0
    refused("&a [*a]", r"alias \*a refers to a node that contains it")
    refused("a: &a {b: *a}", r"alias \*a refers to a node that contains it")
    small = "a: &a [1, 2]\nb: [*a, *a]\n"  # modest aliasing is fine
    assert parse_yaml(small, "t") == {"a": [1, 2], "b": [[1, 2], [1, 2]]}


def test_node_limit_counts_every_scalar(tmp_path: Path) -> None:
    text = "".join(f"k{i}: {i}\n" for i in range(600))
    assert len(parse_yaml(text, "t", max_nodes=1201)) == 600
    refused(text, "more than 1200 nodes", max_nodes=1200)
    assert len(load_yaml(write(tmp_path / "n.yaml", text), max_nodes=1201)) == 600


def test_a_file_of_one_and_a_half_million_keys_is_refused_fast(tmp_path: Path) -> None:
    """The probe's 27 MB config ran 100 s at 1.6 GB; now it is refused after reading 1 MiB."""
    f = tmp_path / "huge.yaml"
    with f.open("w") as out:
        for start in range(0, 1_500_000, 100_000):
            out.write("".join(f"key{i}: {i}\n" for i in range(start, start + 100_000)))
    assert f.stat().st_size > 20 << 20
    t0 = time.monotonic()
    with pytest.raises(FileError, match="larger than 1 MiB"):
        load_yaml(f)
    assert time.monotonic() - t0 < 1.0


def test_long_integers_and_bad_values_are_one_line() -> None:
    refused("x: 1" + ":1" * 100, r"an integer longer than 100 characters at line 1, column 4")  # sexagesimal
    refused("x: !!int " + "9" * 200, "an integer longer than 100")
    assert parse_yaml("x: '" + "1" * 200 + "'", "t") == {"x": "1" * 200}  # a string may be long
    refused("x: 2001-02-30", r"bad value: ValueError: day is out of range for month")
    refused("x: !!timestamp tomorrow", r"'tomorrow' is not a !!timestamp at line 1, column 4")
    refused("x: !!bool maybe", r"'maybe' is not a !!bool")
    refused("x: !!python/object:os.system ls", r"not valid YAML at line 1, column 4: could not determine a constructor")
    refused("x: [1,\n  y: 2\n", r"not valid YAML at line 3, column 1")
    refused("x: \x00", r"not valid YAML: character #x0000 at index 3")
    refused("{[1]: 2}", "found unhashable key")
    refused("a: 1\n---\nb: 2\n", "expected a single document")
    e = refused("k: *undefined\n", "found undefined alias")
    assert "undefined" in e.reason


def test_error_lines_escape_line_breaks_in_paths_and_reasons() -> None:
    e = FileError("a\nb.yaml", "bad\u2028thing\r\nhere")
    assert str(e) == "a\\nb.yaml: bad\\u2028thing\\r\\nhere" and len(str(e).splitlines()) == 1
    assert len(files.one_line("x" * 1000)) == 300


def test_valid_files_load_as_with_pyyaml() -> None:
    for path in (builtin_path("small"), builtin_path("large"), Path(__file__).parents[1] / "compose/compose.yaml"):
        assert load_yaml(path) == yaml.safe_load(path.read_text()), path


def test_json_variant(tmp_path: Path) -> None:
    assert load_json(write(tmp_path / "a.json", '{"a": [1, 2, {"b": null}]}')) == {"a": [1, 2, {"b": None}]}
    for text, match in (
        ('{"a": 1, "a": 2}', "duplicate key 'a'"),
        ("[" * 100_000, "nested deeper than 64 levels"),
        ('{"a": NaN}', "NaN is not JSON"),
        ('{"a": 1', "not valid JSON at line 1"),
        ("[" + ",".join(["1"] * 2000) + "]", "more than 1000 nodes"),
    ):
        with pytest.raises(FileError, match=match) as e:
            parse_json(text, "t.json", max_nodes=1000)
        assert "\n" not in str(e.value)
    assert parse_json('["[[[[", "\\"{{{{"]', "t", max_depth=1) == ["[[[[", '"{{{{']  # brackets in strings


# --------------------------------------------------------------------------- fuzz
SEEDS = [
    builtin_path("small").read_text(),
    "name: h1\nlisten: 127.0.0.1:7001\ncore: [h1=a:1, h2=b:2]\nmembership: {c_f: 1, discovery: 0.5}\n",
    "schedule:\n  - {at: 0, join: {type: seeker, id: s1}}\n  - {at: 120, retire: s1}\n",
    "a: &a [1, 2]\nb: *a\nc: {<<: {x: 1}, y: !!float 2}\nd: |\n  text\n",
]
TOKENS = [
    "[", "]", "{", "}", "&a ", "*a", "&b ", "*b", ": ", "- ", "\n", "\t", "  ", "? ", "<<: ", "'", '"', "\\",
    "!!int ", "!!float ", "!!binary ", "!!set ", "!!omap ", "!!timestamp ", "!!python/name:os.system ", "!x ",
    "%YAML 1.1\n", "%TAG ! tag:x:\n", "---\n", "...\n", "|", ">-", "#", "1:2:3", "0x", "1e999", "2001-02-30",
    "\x00", "\ufeff", "\u2028", "~", "null", ".nan", "9" * 120,
]  # fmt: skip


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    data = bytearray(draw(st.sampled_from(SEEDS)).encode())
    for _ in range(draw(st.integers(1, 8))):
        pos = draw(st.integers(0, len(data)))
        op = draw(st.sampled_from(["insert", "delete", "replace", "repeat", "byte"]))
        token = draw(st.sampled_from(TOKENS)).encode()
        if op == "insert":
            data[pos:pos] = token
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 20))]
        elif op == "replace":
            data[pos : pos + len(token)] = token
        elif op == "repeat":
            data[pos:pos] = token * draw(st.integers(2, 200))
        else:
            data[pos:pos] = bytes([draw(st.integers(0, 255))])
    return bytes(data)


def check_only_file_errors(data: bytes) -> None:
    try:
        parse_yaml(files.decode(data, "f.yaml"), "f.yaml", max_nodes=5000)
    except FileError as e:
        assert "\n" not in str(e) and len(str(e).splitlines()) == 1, str(e)
        assert str(e).startswith("f.yaml: ")


@settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(mutated(), st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_fuzz_only_file_error_escapes(data: bytes) -> None:
    check_only_file_errors(data)


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**30), 10**30) | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner, max_size=5),
    max_leaves=30,
)


@settings(max_examples=max(50, FUZZ_EXAMPLES // 3), deadline=None)
@given(JSONISH)
def test_fuzz_valid_data_round_trips(value: object) -> None:
    """What PyYAML dumps, the loader reads back unchanged (the limits refuse nothing ordinary)."""
    assert parse_yaml(yaml.safe_dump(value), "t") == value


# --------------------------------------------------------------------------- schemas
def test_arena_lists_are_bounded() -> None:
    base = "name: t\nsize: [4, 4]\nstart_poses: [[1, 1, 0]]\n"
    many = base.replace("start_poses: [[1, 1, 0]]", "start_poses: [" + ", ".join(["[1, 1, 0]"] * 101) + "]")
    with pytest.raises(ArenaError, match=r"start_poses: List should have at most 100 items"):
        parse_arena(many, "arena t.yaml")
    poly = "[" + ", ".join(f"[{1 + 0.5 * (k % 2)}, {1 + 0.01 * k}]" for k in range(17)) + "]"
    with pytest.raises(ArenaError, match=r"obstacles\[0\].polygon: List should have at most 16 items"):
        parse_arena(base + f"obstacles: [{{id: o, polygon: {poly}}}]\n", "arena t.yaml")
    with pytest.raises(ArenaError, match=r"size\[0\]: Input should be less than or equal to 100"):
        parse_arena(base.replace("[4, 4]", "[1e9, 4]"), "arena t.yaml")
    with pytest.raises(ArenaError, match=r"start_poses\[0\]\[0\]: Input should be a finite number"):
        parse_arena(base.replace("[[1, 1, 0]]", "[[.nan, 1, 0]]"), "arena t.yaml")
    with pytest.raises(ArenaError, match=r"name: String should have at most 64 characters"):
        parse_arena(base.replace("name: t", "name: " + "t" * 65), "arena t.yaml")


def test_arena_and_schedule_files_get_one_line(tmp_path: Path) -> None:
    with pytest.raises(ArenaError, match=r"^arena .*/d.yaml: duplicate key 'size' at line 3 \(first at line 2\)$"):
        load_arena(write(tmp_path / "d.yaml", "name: t\nsize: [4, 4]\nsize: [5, 5]\nstart_poses: [[1, 1, 0]]\n"))
    with pytest.raises(ArenaError, match=r"^arena /dev/zero: is a character device"):
        load_arena("/dev/zero")
    with pytest.raises(ArenaError, match=r"no such file \(built-in arenas: small, large\)"):
        load_arena(tmp_path / "none.yaml")
    with pytest.raises(ScheduleError, match=r"^schedule s.yaml: not UTF-8 text \(byte 0xfe at offset 10\)$"):
        load_schedule(write(tmp_path / "s.yaml", b"schedule: \xfe"), 3)
    entries = "schedule:\n" + "".join(f"  - {{at: {i}, join: {{type: seeker}}}}\n" for i in range(1001))
    with pytest.raises(ScheduleError, match=r"schedule: more than 1000 entries"):
        load_schedule(write(tmp_path / "many.yaml", entries), 3)


# --------------------------------------------------------------------------- real processes
def run(cmd: list[str], timeout: float = 60) -> tuple[int, str, float]:
    """Run a command: (exit code, stderr, CPU seconds it used). CPU time, not wall time, says "quickly":
    the machine may be busy with other tests."""
    with subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as p:
        assert p.stderr is not None
        t = threading.Timer(timeout, p.kill)
        t.start()
        try:
            err = p.stderr.read()
            _, status, usage = os.wait4(p.pid, 0)
        finally:
            t.cancel()
        p.returncode = os.waitstatus_to_exitcode(status)
        return p.returncode, err, usage.ru_utime + usage.ru_stime


def assert_one_line_exit_2(cmds: list[list[str]], expect: list[str]) -> None:
    for cmd, text in zip(cmds, expect, strict=True):
        code, err, cpu = run(cmd)
        assert code == 2, (cmd[3:], err[-2000:])
        assert err.count("\n") == 1 and len(err.splitlines()) == 1, err[-2000:]
        assert text in err, err
        assert cpu < 5, (cmd[3:], cpu)  # ~1 s is the import


def test_hostd_bad_config_files_exit_2_with_one_line(tmp_path: Path) -> None:
    token = write(tmp_path / "token", "s3cret\n")
    million = tmp_path / "million.yaml"
    with million.open("w") as f:
        f.write("core:\n")
        for start in range(0, 1_000_000, 100_000):
            f.write("".join(f"  - h{i}=127.0.0.1:{20000 + i % 40000}\n" for i in range(start, start + 100_000)))
    cases = {
        "deep": ("core: " + "[" * 100_000, "nested deeper than 64 levels"),
        "million": (None, "million.yaml: larger than 256 KiB (config file limit)"),
        "1001": ("core:\n" + "".join(f"  h{i}: a:{20000 + i}\n" for i in range(1001)), "--core: more than 1000"),
        "dup": ("name: h1\nmembership:\n  c_f: 1\n  c_f: 2\n", "duplicate key 'c_f' at line 4 (first at line 3)"),
        "zero": (None, "/dev/zero: is a character device, not a regular file"),
    }
    cmds, expect = [], []
    for name, (content, text) in cases.items():
        path = {"million": str(million), "zero": "/dev/zero"}.get(name)
        if path is None:
            path = str(write(tmp_path / f"{name}.yaml", content))  # type: ignore[arg-type]
        cmds.append([*HOSTD, "--name", "h0", "--listen", "127.0.0.1:0", "--token-file", str(token),
                     "--data-dir", str(tmp_path / "d"), "--config", path])  # fmt: skip
        expect.append(text)
    cmds.append([*HOSTD, "--name", "h0", "--listen", "127.0.0.1:0", "--token-file", "/dev/zero"])
    expect.append("--token-file: cannot read token file /dev/zero: is a character device, not a regular file")
    assert_one_line_exit_2(cmds, expect)


def test_hostd_with_the_most_core_entries_still_stops_on_sigterm(tmp_path: Path) -> None:
    """A million core entries kept the event loop busy creating failure detectors for minutes, with the
    SIGTERM handler waiting behind it; at the 1,000 allowed the daemon starts and leaves promptly."""
    token = write(tmp_path / "token", "s3cret\n")
    core = ",".join(f"h{i}=127.0.0.1:{20000 + i}" for i in range(1000))
    p = subprocess.Popen(
        [*HOSTD, "--name", "h0", "--listen", "127.0.0.1:0", "--token-file", str(token), "--core", core,
         "--data-dir", str(tmp_path / "d"), "--no-agents", "--leave-timeout", "0.5"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        log = tmp_path / "d" / "h0.jsonl"

        def started() -> bool:
            assert p.poll() is None, p.stderr.read() if p.stderr else ""
            return log.exists() and '"startup"' in log.read_text(errors="replace")

        wait_sync(started, 20, "the daemon's startup line", interval=0.1)
        time.sleep(0.5)  # on purpose: SIGTERM while the 1,000 peers' failure detectors are at work
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=20)
        assert time.monotonic() - t0 < 10
        assert p.returncode == 0, p.stderr.read() if p.stderr else ""
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_sim_bad_arena_and_schedule_files_exit_2_with_one_line(tmp_path: Path) -> None:
    deep = write(tmp_path / "deep.yaml", "name: " + "[" * 100_000)
    cmds = [
        [*SIM, "--arena", str(deep)],
        [*SIM, "--arena", str(write(tmp_path / "latin1.yaml", "name: caf\xe9\n".encode("latin-1")))],
        [*SIM, "--schedule", str(write(tmp_path / "dups.yaml", "schedule:\n  - {at: 1, at: 2, crash: x}\n"))],
    ]
    expect = [
        f"haa-sim: error: arena {deep}: nested deeper than 64 levels at line 1",
        f"haa-sim: error: arena {tmp_path}/latin1.yaml: not UTF-8 text (byte 0xe9 at offset 9)",
        "haa-sim: error: schedule dups.yaml: duplicate key 'at' at line 2",
    ]
    assert_one_line_exit_2(cmds, expect)


ARENA_SEED = builtin_path("small").read_text()
ARENA_TOKENS = [*TOKENS, "-1", "0", "1e308", "-1e308", ".inf", "[0, 0]", "[1, 1, 1]", "{}", "[]", "999", "0.0001"]


@st.composite
def mutated_arena(draw: st.DrawFn) -> str:
    text = ARENA_SEED
    for _ in range(draw(st.integers(1, 6))):
        pos = draw(st.integers(0, len(text)))
        token = draw(st.sampled_from(ARENA_TOKENS))
        if draw(st.booleans()):
            text = text[:pos] + token + text[pos:]
        else:
            text = text[:pos] + token + text[pos + len(token) :]
    return text


@settings(max_examples=max(50, FUZZ_EXAMPLES // 3), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated_arena())
def test_fuzz_arena_files_only_arena_error_escapes(text: str) -> None:
    try:
        parse_arena(text, "arena f.yaml")
    except ArenaError as e:
        assert len(str(e).splitlines()) == 1 and str(e).startswith("arena f.yaml"), str(e)


# ------------------------------------------------------------------ files HAA writes itself


def test_a_corrupt_known_hosts_file_is_ignored_with_a_warning(tmp_path: Path) -> None:
    """haa-hostd reads `<data-dir>/known_hosts.json` at start: a huge, deep or broken one is ignored (the host
    starts without the hint), never read without limit."""
    from haa.hostd.datadir import HostDataDir

    data = HostDataDir("h1", tmp_path)
    f = tmp_path / "known_hosts.json"
    assert data.known_hosts_file == f
    for text in ("[" * 100_000, '{"members": 5}', "\xff", " " * (2 << 20), '{"members": [["h1", "a"], ["h1", "a"]]'):
        f.write_text(text, errors="surrogateescape")
        assert data.load_known_hosts() == []
    f.write_text('{"members": [["h1", "127.0.0.1:1"], ["h2", "127.0.0.1:2"]]}')
    assert data.load_known_hosts() == [("h2", "127.0.0.1:2")]


def test_a_broken_cluster_state_file_is_one_clear_error(tmp_path: Path) -> None:
    from haa.cluster.backend import ClusterError
    from haa.cluster.local_backend import STATE_FILE, LocalBackend

    b = LocalBackend(tmp_path)
    for text in ("[" * 100_000, "[1, 2]", '{"a": 1, "a": 2}'):
        (tmp_path / STATE_FILE).write_text(text)
        with pytest.raises(ClusterError, match="broken state file") as e:
            b.load()
        assert "\n" not in str(e.value)
