"""The haa-hostd command line: settings validation (one clear line, exit code 2) and environment fallbacks."""

from __future__ import annotations

import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import pytest

from haa.cluster.hostprocs import free_port, hostd_command
from haa.hostd.daemon import HostSettings, load_settings, parse_peers


@pytest.fixture
def token(tmp_path: Path) -> Path:
    f = tmp_path / "token"
    f.write_text("s3cret\n")
    return f


def base(token: Path, **over: str) -> list[str]:
    opts = {
        "--name": "h1",
        "--listen": "127.0.0.1:7001",
        "--peers": "h2=127.0.0.1:7002,h3=localhost:7003",
        "--token-file": str(token),
        "--data-dir": str(token.parent / "data"),
        **over,
    }
    return [x for k, v in opts.items() if v is not None for x in (k, v)]


def test_valid_settings(token: Path) -> None:
    s = load_settings([*base(token), "--qos-td", "0.5", "--exclude-after", "3"])
    assert isinstance(s, HostSettings)
    assert s.name == "h1" and dict(s.peers) == {"h2": "127.0.0.1:7002", "h3": "localhost:7003"}
    assert s.token.get_secret_value() == "s3cret"
    assert "s3cret" not in repr(s)
    cfg = s.runtime_config()
    assert cfg.peers == {"h2": "127.0.0.1:7002", "h3": "localhost:7003"}
    assert cfg.core.ufd.qos.td_upper == 0.5 and cfg.core.exclude_after == 3.0
    assert cfg.core.ufd.initial_period < 0.5


def test_tiny_detection_bound_keeps_initial_period_below_it(token: Path) -> None:
    cfg = load_settings([*base(token), "--qos-td", "0.04"]).runtime_config()
    assert 0 < cfg.core.ufd.initial_period < 0.04


def test_environment_fallbacks(token: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HAA_NAME", "e1")
    monkeypatch.setenv("HAA_LISTEN", "[::1]:9000")
    monkeypatch.setenv("HAA_PEERS", "e2=10.0.0.2:9000")
    monkeypatch.setenv("HAA_TOKEN_FILE", str(token))
    monkeypatch.setenv("HAA_DATA_DIR", str(token.parent / "d"))
    s = load_settings([])
    assert (s.name, s.listen, dict(s.peers), s.data_dir) == (
        "e1",
        "[::1]:9000",
        {"e2": "10.0.0.2:9000"},
        token.parent / "d",
    )
    assert load_settings(["--name", "e9"]).name == "e9"  # the command line wins


def test_peers_parser() -> None:
    assert parse_peers("") == []
    assert parse_peers(" a=h:1 , b=h:2,") == [("a", "h:1"), ("b", "h:2")]
    with pytest.raises(ValueError, match="NAME=HOST:PORT"):
        parse_peers("a:h:1")


BAD = [
    ("no-name", {"--name": None}, "--name (or HAA_NAME) is required"),
    ("bad-name", {"--name": "h 1"}, "--name:"),
    ("no-port", {"--listen": "127.0.0.1"}, "--listen:"),
    ("port-too-big", {"--listen": "127.0.0.1:70000"}, "bad port"),
    ("port-not-number", {"--listen": "127.0.0.1:http"}, "bad port"),
    ("bad-host", {"--listen": "bad host:80"}, "bad host"),
    ("peer-syntax", {"--peers": "h2:127.0.0.1:7002"}, "--peers: 'h2:127.0.0.1:7002' is not NAME=HOST:PORT"),
    ("peer-port-zero", {"--peers": "h2=127.0.0.1:0"}, "--peers:"),
    ("duplicate-peer", {"--peers": "h2=127.0.0.1:7002,h2=127.0.0.1:7003"}, "duplicate peer name 'h2'"),
    ("own-name", {"--peers": "h1=127.0.0.1:7002"}, "names this host itself"),
    ("no-token-file", {"--token-file": "/nonexistent/token"}, "--token-file: cannot read token file"),
    ("qos-negative", {"--qos-td": "-1"}, "--qos-td:"),
    ("qos-zero", {"--qos-tm": "0"}, "--qos-tm:"),
    ("qos-nan", {"--qos-tmr": "nan"}, "--qos-tmr:"),
    ("exclude-zero", {"--exclude-after": "0"}, "--exclude-after:"),
    ("qos-not-a-number", {"--qos-td": "fast"}, "--qos-td: invalid float value"),
    ("log-level", {"--log-level": "loud"}, "--log-level"),
    # the allocator's bounds (docs/limits.md): an infinite or huge capacity would be refused by every replica
    ("capacity-inf", {"--capacity": "inf"}, "--capacity:"),
    ("capacity-huge", {"--capacity": "1e9"}, "--capacity: Input should be less than or equal to 1000"),
    ("capacity-tiny", {"--capacity": "1e-9"}, "--capacity:"),
]


@pytest.mark.parametrize(("case", "over", "message"), BAD, ids=[b[0] for b in BAD])
def test_bad_settings_exit_2_with_one_line(
    case: str, over: dict[str, str | None], message: str, token: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        load_settings(base(token, **over))  # type: ignore[arg-type]
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("haa-hostd: error: "), err
    assert message in err, err


def test_empty_or_unreadable_token_file(token: Path, capsys: pytest.CaptureFixture[str]) -> None:
    token.write_text("  \n")
    with pytest.raises(SystemExit) as exc:
        load_settings(base(token))
    assert exc.value.code == 2
    assert "is empty" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        load_settings(base(token, **{"--token-file": str(token.parent)}))  # a directory (docker's missing mount)
    err = capsys.readouterr().err
    assert "is a directory, not a file" in err and "make image" in err and err.count("\n") == 1


def test_unknown_option_is_one_line(token: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        load_settings([*base(token), "--frobnicate"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unrecognized arguments: --frobnicate" in err


def test_port_taken_by_another_grpc_server_exits_1(token: Path) -> None:
    """gRPC binds with SO_REUSEPORT by default: without our option two hosts would share one port."""
    port = free_port()
    blocker = grpc.server(ThreadPoolExecutor(1))
    assert blocker.add_insecure_port(f"127.0.0.1:{port}") == port
    blocker.start()
    try:
        args = base(token, **{"--listen": f"127.0.0.1:{port}", "--peers": ""})
        p = subprocess.run([*hostd_command(), *args], capture_output=True, text=True, timeout=30)
    finally:
        blocker.stop(None)
    assert p.returncode == 1, p.stderr
    assert f"haa-hostd: error: cannot listen on 127.0.0.1:{port}" in p.stderr
