"""haa-sim as a container: the `sim` service of compose/compose.yaml, run from haa-hostd:latest, talked to over
gRPC through its published port.

The container is started with the docker SDK from the service's own definition (image, entrypoint, command
with its `${VAR:-default}`s expanded), on the default bridge with a random published port and a token of
its own, so that it never touches a compose project that others may be running (project `haa`, h1..h10).
Skipped without docker or the image (`make docker-setup image`); failed instead when HAA_REQUIRE_DOCKER=1.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml
from chaoslib import docker_problem
from helpers import wait_sync

from haa.pb import sim_pb2 as pb
from haa.sim.service import SimClient, decode_frame

pytestmark = pytest.mark.docker

REPO = Path(__file__).resolve().parents[2]
TOKEN = "sim-container-test-token"


def sim_service() -> dict[str, Any]:
    spec = yaml.safe_load((REPO / "compose" / "compose.yaml").read_text())
    return spec["services"]["sim"]


def expand(arg: str, env: dict[str, str]) -> str:
    """compose's ${VAR:-default} substitution."""
    return re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: env.get(m.group(1)) or m.group(2), str(arg))


@pytest.fixture(scope="module")
def container(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, str]]:
    problem = docker_problem()
    if problem:
        if os.environ.get("HAA_REQUIRE_DOCKER") == "1":
            pytest.fail(f"HAA_REQUIRE_DOCKER=1 but {problem}")
        pytest.skip(problem)
    import docker

    svc = sim_service()
    env = {"HAA_SIM_ARENA": "small", "HAA_SIM_SEED": "4", "HAA_SIM_SPEED": "10"}
    command = [expand(a, env) for a in svc["command"]]
    token_dir = tmp_path_factory.mktemp("simtoken")
    (token_dir / "token").write_text(TOKEN + "\n")
    token_dir.chmod(0o755)
    (token_dir / "token").chmod(0o644)
    client = docker.from_env(version="auto", timeout=30)
    c = client.containers.run(
        svc["image"],
        command=command,
        entrypoint=svc["entrypoint"],
        init=True,
        detach=True,
        name=f"haa-simtest-{os.getpid()}",
        labels={"io.haa.test": "sim-container"},
        ports={"7100/tcp": ("127.0.0.1", None)},
        volumes={str(token_dir / "token"): {"bind": "/run/haa/token", "mode": "ro"}},
    )
    try:
        def listening() -> str | None:
            """The published port once haa-sim listens; fails at once if it exited."""
            c.reload()
            if c.status == "exited":
                raise AssertionError(f"haa-sim exited: {c.logs().decode()[-2000:]}")
            binding = (c.attrs["NetworkSettings"]["Ports"] or {}).get("7100/tcp")
            return binding[0]["HostPort"] if binding and b'"event": "listening"' in c.logs() else None

        try:
            port = wait_sync(listening, 30, "haa-sim to listen", interval=0.2)
        except AssertionError as e:
            raise AssertionError(f"{e}: {c.logs().decode()[-2000:]}") from None
        yield c, f"127.0.0.1:{port}"
    finally:
        try:
            c.stop(timeout=5)
            c.reload()
            code = c.attrs["State"]["ExitCode"]
            logs = c.logs().decode()
        finally:
            c.remove(force=True)
            client.close()
        assert code == 0, logs[-2000:]
        assert '"event": "stopped"' in logs


def test_sim_container_serves_the_avatar_and_ground_truth_apis(container: tuple[Any, str]) -> None:
    _, address = container
    with SimClient(address, token="wrong") as bad:
        with pytest.raises(grpc.RpcError) as e:
            bad.info()
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with SimClient(address, token=TOKEN, timeout=10) as c:
        info = c.wait_ready(20)
        assert info.arena == "small" and info.mode == "realtime" and info.speed == 10 and info.seed == 4
        aid = c.register("sweeper").avatar.avatar_id
        events = c.events(replay=True, timeout=30)
        assert next(events).avatar_id == aid
        odo = c.odometry(aid, period=0.5, timeout=30)
        sonar = c.sonar(aid, timeout=30)
        updates = list(c.act(pb.ActionRequest(avatar_id=aid, move_by=pb.MoveBy(distance=0.8)), timeout=30))
        assert updates[-1].status == pb.ACTION_STATUS_SUCCEEDED, updates[-1]
        readings = [next(odo) for _ in range(4)]
        assert readings[-1].time > readings[0].time
        scan = next(sonar)
        assert len(scan.readings) == 5
        img = decode_frame(c.capture(aid))
        assert img.shape == (480, 640, 3)
        det = c.detect(aid)
        assert det.landmarks
        occ, explorable, g = c.grid(0.1)
        assert occ.shape == explorable.shape == (72, 34) and g.explorable_area == pytest.approx(24.2, abs=0.2)
        t0 = c.info().time
        time.sleep(0.5)  # wall time passes: the simulated clock must run 10x as fast
        assert c.info().time > t0 + 1.0  # 10x: the clock runs in the container
        c.crash(aid)
        assert next(events).kind == "crashed"
        for stream in (odo, sonar, events):
            stream.cancel()
