"""Starting haa-hostd processes on this machine: a free loopback port, the daemon's command line.

Shared by the local cluster backend (haa.cluster.local_backend), the mission runner (haa.mission.runner) and
the experiments' and tests' host processes (haa.cluster.hostprocs).
"""

from __future__ import annotations

import socket
import sys
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def hostd_command() -> list[str]:
    script = Path(sys.executable).parent / "haa-hostd"
    return [str(script)] if script.exists() else [sys.executable, "-m", "haa.hostd.daemon"]


def member_command(
    name: str,
    address: str,
    core: dict[str, str],
    token_file: Path,
    data_dir: Path,
    args: list[str] | None = None,
) -> list[str]:
    """The command line of a membership-mode host (Alg. 3): it finds the group through the core list."""
    return [
        *hostd_command(),
        "--name",
        name,
        "--listen",
        address,
        "--core",
        ",".join(f"{n}={a}" for n, a in core.items()),
        "--token-file",
        str(token_file),
        "--data-dir",
        str(data_dir),
        *(args or []),
    ]
