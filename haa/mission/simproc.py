"""haa-sim as the mission runner uses it: `SimHandle` (an haa-sim this machine can reach — its address and token
file, and its process when we started it; saved as JSON by an attached mission), `start_sim` (start one for a
mission: its arena, seed, speed and avatar schedule, on a free loopback port with a fresh token) and
`check_sim_matches` (refuse a running haa-sim of another arena or seed).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

from haa.cluster import procs
from haa.mission.plan import MissionRunError, schedule_yaml
from haa.mission.schema import Mission, resolve

#: how the runner names itself to haa-sim (its ground-truth calls are counted apart from the agents')
RUNNER_CALLER = "mission-runner"


@dataclass
class SimHandle:
    """An haa-sim this machine can reach: its address, token file, and — if we started it — its process."""

    address: str
    token_file: str = ""
    pid: int | None = None
    create_time: float | None = None
    log: str = ""
    started_here: bool = False
    proc: subprocess.Popen[bytes] | None = field(default=None, repr=False)
    #: where the agents reach it, when not at `address` (compose: sim:7100 and the token in the containers)
    agent_address: str = ""
    agent_token_file: str = ""
    #: its Prometheus endpoint (docs/metrics.md), "" when it serves none
    metrics_url: str = ""

    def client(self, timeout: float = 5.0) -> Any:
        from haa import files
        from haa.sim.service import SimClient

        token = files.read_token(self.token_file) if self.token_file else None
        return SimClient(self.address, token=token, timeout=timeout, caller=RUNNER_CALLER)

    def alive(self) -> bool:
        if self.proc is not None:
            return self.proc.poll() is None
        if not self.pid:
            return False
        try:
            p = psutil.Process(self.pid)
            if self.create_time is not None and abs(p.create_time() - self.create_time) > 0.5:
                return False
            return p.status() != psutil.STATUS_ZOMBIE
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            return False

    def stop(self, grace: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after `grace` s (only a process we started; reaps it)."""
        if not self.started_here or not self.pid:
            return
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
            deadline = time.monotonic() + grace
            while self.alive() and time.monotonic() < deadline:
                time.sleep(0.05)
            if self.alive():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
        if self.proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(5)
        else:
            with contextlib.suppress(ChildProcessError, OSError):
                os.waitpid(self.pid, os.WNOHANG)

    def to_json(self) -> dict[str, Any]:
        return {"address": self.address, "token_file": self.token_file, "pid": self.pid,
                "create_time": self.create_time, "log": self.log, "started_here": self.started_here,
                "agent_address": self.agent_address, "agent_token_file": self.agent_token_file,
                "metrics_url": self.metrics_url}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SimHandle:
        return cls(str(d["address"]), str(d.get("token_file") or ""), d.get("pid"), d.get("create_time"),
                   str(d.get("log") or ""), bool(d.get("started_here")),
                   agent_address=str(d.get("agent_address") or ""),
                   agent_token_file=str(d.get("agent_token_file") or ""),
                   metrics_url=str(d.get("metrics_url") or ""))


def sim_command() -> list[str]:
    script = Path(sys.executable).parent / "haa-sim"
    return [str(script)] if script.exists() else [sys.executable, "-m", "haa.sim.service"]


def arena_argument(mission: Mission) -> str:
    from haa.sim.arena import BUILTIN

    a = mission.spec.arena
    if a in BUILTIN:
        return a
    base = Path(mission.path).parent if mission.path is not None else None
    return str(resolve(base, a).absolute())


def start_sim(mission: Mission, speed: float, workdir: Path, schedule: bool = True, detached: bool = False,
              timeout: float = 30.0) -> SimHandle:
    """Start haa-sim for the mission (arena, seed, speed; the avatar schedule unless `schedule` is False) on a
    free loopback port with a fresh token, its Prometheus /metrics on another (`SimHandle.metrics_url`); wait
    until it listens. `detached`: it outlives this process."""
    workdir.mkdir(parents=True, exist_ok=True)
    token_file = workdir / "sim.token"
    token_file.write_text(secrets.token_hex(24) + "\n")
    token_file.chmod(0o600)
    cmd = [*sim_command(), "--arena", arena_argument(mission), "--listen", "127.0.0.1:0",
           "--seed", str(mission.spec.seed), "--speed", repr(float(speed)), "--token-file", str(token_file),
           "--drift", mission.spec.drift, "--metrics-port", str(procs.free_port())]
    if schedule:
        sched = workdir / "sim-schedule.yaml"
        sched.write_text(schedule_yaml(mission))
        cmd += ["--schedule", str(sched)]
    log_path = workdir / "sim.log"
    with open(log_path, "wb") as err:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True)
    try:
        ct = psutil.Process(p.pid).create_time()
    except psutil.NoSuchProcess:
        ct = None
    h = SimHandle("", str(token_file), p.pid, ct, str(log_path), True, None if detached else p)
    deadline = time.monotonic() + timeout
    while True:
        for line in log_path.read_text(errors="replace").splitlines():
            with contextlib.suppress(ValueError):
                rec = json.loads(line)
                if isinstance(rec, dict) and rec.get("event") == "listening":
                    h.address = str(rec["address"])
                    h.metrics_url = str(rec.get("metrics") or "")
                    return h
        code = p.poll()
        if code is not None:
            lines = [ln for ln in log_path.read_text(errors="replace").splitlines() if ln.strip()]
            raise MissionRunError(f"haa-sim exited at start with code {code}: {lines[-1] if lines else '(no output)'}")
        if time.monotonic() > deadline:
            h.stop(1.0)
            raise MissionRunError(f"haa-sim did not start listening within {timeout:.0f} s (log: {log_path})")
        time.sleep(0.05)


def check_sim_matches(info: Any, mission: Mission) -> None:
    """Refuse an haa-sim that runs another arena or seed than the mission's (one clear line)."""
    from haa.sim.arena import load_arena

    want_seed = mission.spec.seed
    want_arena = mission.arena.name if mission.arena is not None else load_arena(arena_argument(mission)).name
    problems = []
    if info.arena != want_arena:
        problems.append(f"arena {info.arena!r} (the mission wants {want_arena!r})")
    if int(info.seed) != int(want_seed):
        problems.append(f"seed {info.seed} (the mission wants {want_seed})")
    if problems:
        raise MissionRunError("the running haa-sim has " + " and ".join(problems) +
                              ": stop it first (haactl mission stop) or change the mission file")
