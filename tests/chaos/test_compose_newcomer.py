"""A newcomer's raw compose path: `docker-compose up` before `make image` wrote compose/token.

Docker bind-mounts a missing source as a new empty directory, where a host would stop with exit code 2 and a
bare "Is a directory". The image's entrypoint (compose/haa-entrypoint.sh) says what is wrong and what to do,
for the hosts and for haa-sim. Run on a copy of compose/compose.yaml in a temporary directory (no token
there) with `docker-compose run` (no published ports: it cannot collide with a running cluster) under a
project and subnet of its own. Needs docker and the image haa-hostd:latest (`make docker-setup image`).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from chaoslib import docker_problem

from haa.cluster.compose_backend import compose_command

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.docker


def test_a_raw_up_without_the_token_says_run_make_image(tmp_path: Path) -> None:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    shutil.copy(REPO / "compose" / "compose.yaml", tmp_path / "compose.yaml")
    project = f"haanewcomer{os.getpid()}"
    env = {**os.environ, "HAA_SUBNET_PREFIX": f"10.77.{100 + os.getpid() % 100}"}
    base = [*compose_command(), "-f", str(tmp_path / "compose.yaml"), "-p", project]
    try:
        for service, prog in (("h1", "haa-hostd"), ("sim", "haa-sim")):
            r = subprocess.run([*base, "run", "--rm", service], capture_output=True, text=True, timeout=120,
                               cwd=tmp_path, env=env)
            out = r.stdout + r.stderr
            assert r.returncode == 2, out
            assert f"{prog}: error: token file /run/haa/token is a directory" in out, out
            assert "Run `make image`" in out, out
        assert (tmp_path / "token").is_dir()  # what docker made (the reason for the message)
    finally:
        subprocess.run([*base, "down", "-t", "1"], capture_output=True, timeout=120, cwd=tmp_path, env=env)
        with_root = tmp_path / "token"
        if with_root.is_dir():
            with_root.rmdir()
