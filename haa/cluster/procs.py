"""Starting haa-hostd processes on this machine: a free loopback port, the daemon's command line (membership
mode with a core list, or static mode with a peer list), the cluster token file, and the start itself
(`start_hostd`: a data dir, stderr to a file per start).

Shared by the local cluster backend (haa.cluster.local_backend), the mission runner (haa.mission.runner) and
the experiments' and tests' host processes (haa.cluster.hostprocs).
"""

from __future__ import annotations

import random
import socket
import subprocess
import sys
from pathlib import Path

#: ports this process handed out already (not handed out twice, even when the first taker has not bound yet)
_picked: set[int] = set()


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (the ports bind(0) and outgoing connections get)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def _bindable(port: int) -> bool:
    """Free on loopback for TCP and UDP (haa-hostd takes heartbeat datagrams on its gRPC port number)."""
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def free_port() -> int:
    """A loopback port free now, for a daemon started next. Taken below the kernel's ephemeral range: a port
    from bind(0) is an ephemeral one, which the kernel may give to any outgoing connection (a client socket of
    another host) before the daemon binds it — a benchmark's host once failed to start that way, its port
    taken. Falls back to bind(0) if the range leaves no room below it."""
    low = _ephemeral_low()
    start = max(1024, low // 2)
    rng = random.SystemRandom()
    if len(_picked) > 4096:  # a long sweep: ports handed out long ago are taken or free again by now
        _picked.clear()
    if low - start >= 1000:
        for _ in range(200):
            port = rng.randrange(start, low)
            if port not in _picked and _bindable(port):
                _picked.add(port)
                return port
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def hostd_command() -> list[str]:
    script = Path(sys.executable).parent / "haa-hostd"
    return [str(script)] if script.exists() else [sys.executable, "-m", "haa.hostd.daemon"]


def _command(flag: str, name: str, address: str, hosts: dict[str, str], token_file: Path, data_dir: Path,
             args: list[str] | None) -> list[str]:
    return [*hostd_command(), "--name", name, "--listen", address, flag, ",".join(f"{n}={a}" for n, a in hosts.items()),
            "--token-file", str(token_file), "--data-dir", str(data_dir), *(args or [])]


def member_command(name: str, address: str, core: dict[str, str], token_file: Path, data_dir: Path,
                   args: list[str] | None = None) -> list[str]:
    """The command line of a membership-mode host (Alg. 3): it finds the group through the core list."""
    return _command("--core", name, address, core, token_file, data_dir, args)


def static_command(name: str, address: str, peers: dict[str, str], token_file: Path, data_dir: Path,
                   args: list[str] | None = None) -> list[str]:
    """The command line of a static-mode host: it links to every peer of a fixed list (full mesh)."""
    return _command("--peers", name, address, peers, token_file, data_dir, args)


def write_token(path: Path, token: str, *, private: bool = False) -> None:
    """Write the cluster token file (`private`: readable by its owner only)."""
    path.write_text(token + "\n")
    if private:
        path.chmod(0o600)


def stderr_file(data_dir: Path, start: int) -> Path:
    """Where the `start`-th start of a host writes its stderr (its data dir, one file per start)."""
    return data_dir / f"stderr.{start}.txt"


def start_hostd(cmd: list[str], data_dir: Path, start: int, *, detach: bool = False) -> subprocess.Popen[bytes]:
    """Start a haa-hostd process with command line `cmd`: its data dir is made, stdout discarded, stderr written to
    `stderr_file(data_dir, start)`. `detach`: in a session of its own with no stdin, so that it outlives the command
    that started it and a terminal's interrupt does not reach it (the operator's cluster, haa.cluster.local_backend).
    """
    data_dir.mkdir(parents=True, exist_ok=True)
    with open(stderr_file(data_dir, start), "wb") as err:
        if detach:
            return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                                    start_new_session=True)
        return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
