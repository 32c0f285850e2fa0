"""A mission on the running compose cluster (issue 15 §3), for `haactl mission start|status|logs|stop --compose`.

The agents run in the host containers; haa-sim is the compose file's `sim` service (profile `sim`, same
image): agents reach it as `sim:7100` in the cluster network with the token the containers mount
(/run/haa/token), this machine as its published port (127.0.0.1:17100) with compose/token. `start`:

* uses the `sim` container if it runs (its arena and seed must be the mission's: haa.mission.simproc
  refuses another), else starts it with the mission's arena (the built-in `small` or `large`: the service
  cannot read an arena file of this machine), seed and speed (HAA_SIM_ARENA/SEED/SPEED of compose.yaml) and
  remembers that it did, so that `stop` stops it again; the avatars then join through SimControl at their
  times (haa-sim's own `--schedule` is not used);
* runs the mission conductor of haa.mission.attached (`python -m haa.mission.compose conduct ...`: the
  conductor with a ComposeBackend) in the background, with its state in `.haa/compose-<project>/mission/`
  under the current directory (state.json, transcript.jsonl, the run's results and PNGs in run/).

`status`, `logs` and `stop` read and end that state as they do for a local cluster.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from haa.cluster.backend import ClusterError
from haa.cluster.compose_backend import LABEL_PROJECT, LABEL_SERVICE, ComposeBackend
from haa.mission.attached import read_json, start_attached, stop_attached, write_json
from haa.mission.plan import MissionRunError
from haa.mission.schema import Mission

SIM_SERVICE = "sim"
SIM_PORT = "7100/tcp"
#: haa-sim as the agents in the containers see it
AGENT_SIM = ("sim:7100", "/run/haa/token")
#: in the state directory: the sim container was started by `mission start` (and `stop` stops it)
SIM_STARTED = "compose-sim.json"
SIM_READY_S = 120.0


def state_dir(backend: ComposeBackend) -> Path:
    return Path.cwd().absolute() / ".haa" / f"compose-{backend.project}" / "mission"


def sim_container(backend: ComposeBackend) -> Any:
    found = backend.docker.containers.list(
        all=True, filters={"label": [f"{LABEL_PROJECT}={backend.project}", f"{LABEL_SERVICE}={SIM_SERVICE}"]})
    return found[0] if found else None


def sim_address(c: Any) -> str:
    c.reload()
    bind = (((c.attrs.get("HostConfig") or {}).get("PortBindings") or {}).get(SIM_PORT) or [{}])[0]
    if not bind.get("HostPort"):
        raise ClusterError(f"the {SIM_SERVICE} container publishes no port for {SIM_PORT}")
    host = bind.get("HostIp") or "127.0.0.1"
    return f"{'127.0.0.1' if host == '0.0.0.0' else host}:{bind['HostPort']}"


def ensure_sim(backend: ComposeBackend, mission: Mission, speed: float) -> tuple[str, bool]:
    """(this machine's address of the running `sim` container, whether it was started here)."""
    from haa import files
    from haa.sim.arena import BUILTIN
    from haa.sim.service import SimClient

    if SIM_SERVICE not in backend.other_services:
        raise ClusterError(f"the compose file {backend.file} has no `{SIM_SERVICE}` service (haa-sim)")
    c = sim_container(backend)
    started = False
    if c is None or c.status != "running":
        arena = mission.spec.arena
        if arena not in BUILTIN:
            raise ClusterError(f"arena {arena!r}: the compose `{SIM_SERVICE}` service runs the built-in arenas "
                               f"({', '.join(sorted(BUILTIN))}) only")
        backend.compose("up", "-d", "--no-deps", SIM_SERVICE, env={
            "HAA_SIM_ARENA": arena, "HAA_SIM_SEED": str(mission.spec.seed), "HAA_SIM_SPEED": repr(float(speed))})
        started = True
        c = sim_container(backend)
        if c is None:
            raise ClusterError(f"`compose up {SIM_SERVICE}` made no container")
    address = sim_address(c)
    token = files.read_token(str(backend.token_file))
    deadline = time.monotonic() + SIM_READY_S
    while True:
        try:
            with SimClient(address, token=token, timeout=3.0) as sc:
                sc.wait_ready(3.0)
            return address, started
        except Exception as e:  # grpc errors while it starts
            if time.monotonic() > deadline:
                raise ClusterError(f"haa-sim in the {SIM_SERVICE} container ({address}) is not ready after "
                                   f"{SIM_READY_S:.0f} s: {type(e).__name__}") from None
            time.sleep(0.5)


def stop_sim(backend: ComposeBackend) -> None:
    backend.compose("stop", "--timeout", "5", SIM_SERVICE)
    backend.compose("rm", "-f", SIM_SERVICE)


def start(backend: ComposeBackend, mission: Mission, speed: float | None) -> dict[str, Any]:
    """Start `mission` on the compose cluster (module docstring); the conductor's first status."""
    md = state_dir(backend)
    md.mkdir(parents=True, exist_ok=True)
    sp = float(speed if speed is not None else mission.spec.speed)
    address, started = ensure_sim(backend, mission, sp)
    if started:
        write_json(md / SIM_STARTED, {"started": True, "address": address})
    conductor = [sys.executable, "-m", "haa.mission.compose", "conduct", "--compose-file", str(backend.file),
                 "--project", backend.project]
    try:
        return start_attached(None, mission, speed, address, str(backend.token_file), backend=backend, md=md,
                              conductor=conductor, agent_sim=AGENT_SIM)
    except MissionRunError:
        if started:
            stop_sim(backend)
            (md / SIM_STARTED).unlink(missing_ok=True)
        raise


def stop(backend: ComposeBackend) -> dict[str, Any]:
    """End the mission (as `stop_attached`), and stop the `sim` container if `start` started it."""
    md = state_dir(backend)
    res = stop_attached(None, md=md, backend=backend)
    if read_json(md / SIM_STARTED):
        c = sim_container(backend)
        if c is not None and c.status in ("running", "paused"):
            stop_sim(backend)
            res["sim"] = "stopped"
        (md / SIM_STARTED).unlink(missing_ok=True)
    return res


def conduct_main(argv: list[str]) -> int:
    """`python -m haa.mission.compose conduct --compose-file F --project P <attached conduct args>`."""
    import argparse

    from haa.mission.attached import conduct

    p = argparse.ArgumentParser(prog="python -m haa.mission.compose conduct")
    p.add_argument("--compose-file", type=Path, required=True)
    p.add_argument("--project", required=True)
    a, rest = p.parse_known_args(argv)
    return conduct(rest, backend=ComposeBackend(a.compose_file, a.project))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "conduct":
        sys.exit(conduct_main(sys.argv[2:]))
    print("usage: python -m haa.mission.compose conduct --compose-file F --project P ...", file=sys.stderr)
    sys.exit(2)
