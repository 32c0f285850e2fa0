"""Attached missions (`haactl mission start|status|logs|stop`): a mission on a cluster the operator runs.

`start_attached` checks the cluster, checks (or starts) haa-sim and launches the *conductor* as a detached process
(`python -m haa.mission.attached conduct ...`; haa.mission.compose has its own for the compose cluster): `conduct`
runs a MissionRun against the cluster (haa.mission.runner; it leaves the cluster alone and removes only the
mission's agents) and keeps <root>/mission/state.json (the live status: `snapshot`) and transcript.jsonl up to
date. `stop_attached` ends it (SIGTERM: it stops the loop, collects the results, removes the mission's agents)
and stops the haa-sim `start_attached` started; `live_transcript` reads the transcript so far.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import grpc
import psutil

from haa.cluster.queries import alive_hosts, remove_agents
from haa.mission import transcript as tr
from haa.mission.plan import MissionRunError, as_float
from haa.mission.results import rounded
from haa.mission.runner import AVATAR, EXECUTIVE, MissionRun
from haa.mission.schema import Mission
from haa.mission.simproc import SimHandle, check_sim_matches, start_sim

STATE_FILE = "state.json"
SIM_FILE = "sim.json"
TRANSCRIPT_FILE = "transcript.jsonl"
TRANSCRIPT_PERIOD = 3.0


def mission_dir(root: Path) -> Path:
    return Path(root).absolute() / "mission"


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str) + "\n")
    tmp.replace(path)


def process_alive(pid: Any, create_time: Any = None) -> bool:
    if not pid:
        return False
    try:
        p = psutil.Process(int(pid))
        if create_time is not None and abs(p.create_time() - float(create_time)) > 0.5:
            return False
        return p.status() != psutil.STATUS_ZOMBIE
    except (psutil.NoSuchProcess, psutil.AccessDenied, ValueError):
        return False


def conductor_alive(state: dict[str, Any] | None) -> bool:
    return bool(state) and process_alive(state.get("pid"), state.get("create_time"))  # type: ignore[union-attr]


def snapshot(run: MissionRun) -> dict[str, Any]:
    """The live status of a mission (`haactl mission status`): explored share, coverage, accuracy, each
    avatar's supervisor and target, agents per host."""
    st = run.status if isinstance(run.status, dict) else {}
    sc = run.tally.map_scores
    names = {i: (a.name, a.type) for i, a in run.rows.items()}
    avatars = []
    for a in run.spec.avatars:
        agent = run.avatar_agents.get(a.name)
        asg = run.assign.get(a.name)
        if not isinstance(asg, dict):
            asg = {}
        sup = str(asg.get("supervisor", "")) if asg else ""
        sup_name = f"{names[sup][0]} ({tr.class_name(names[sup][1])})" if sup in names else sup[:8]
        tgt = run.targets.get(a.name)
        if isinstance(tgt, dict) and "x" in tgt and "y" in tgt:
            target = f"({as_float(tgt['x'], math.nan):.2f}, {as_float(tgt['y'], math.nan):.2f})"
        else:
            target = json.dumps(tgt) if tgt is not None else ""
        avatars.append({"avatar": a.name, "type": a.type, "in_arena": run.avatar_status.get(a.name, "not yet"),
                        "agent": agent[1] if agent else "", "supervisor": sup_name, "task": asg.get("task", ""),
                        "target": target})
    return {
        "pid": os.getpid(),
        "create_time": psutil.Process().create_time(),
        "updated": time.time(),
        "mission": run.spec.name,
        "state": st.get("state", "starting"),
        "t": round(run.mission_time(), 2),
        "limit": run.spec.complete.time_limit_s,
        "explored": st.get("explored"),
        "target_explored": run.spec.complete.explored,
        "coverage": rounded(sc.coverage) if sc else None,
        "accuracy": rounded(sc.accuracy) if sc else None,
        "position_error_m": rounded(run.tally.loc.position_error()),
        "hosts": run.members,
        "agents_per_host": run.per_host,
        "avatars": avatars,
        "exec": [run.exec_id, run.exec_name],
        "agent_ids": [run.exec_id, *(i for i, _ in run.avatar_agents.values())],
        "sim": run.sim.address if run.sim else "",
        "out_dir": str(run.out_dir),
        "errors": run.errors[-5:],
    }


def start_attached(root: Path | None, mission: Mission, speed: float | None = None, sim_address: str | None = None,
                   sim_token_file: str = "", wait: float = 60.0,
                   agent_types: tuple[str, str] = (EXECUTIVE, AVATAR), backend: Any = None,
                   md: Path | None = None, conductor: Sequence[str] = (),
                   agent_sim: tuple[str, str] = ("", "")) -> dict[str, Any]:
    """`haactl mission start`: check the cluster, check or start haa-sim, launch the conductor; returns its
    first status snapshot. MissionRunError when anything is wrong (nothing is left running then).

    The local cluster at `root` by default; another cluster (compose) comes as `backend` with its state
    directory `md`, `conductor` (the command that runs `conduct` with that backend, haa.mission.compose)
    and `agent_sim` (haa-sim's address and token file as the agents see them)."""
    from haa.cluster.backend import ClusterError
    from haa.cluster.local_backend import LocalBackend

    if mission.path is None:
        raise MissionRunError("mission start needs a mission file")
    try:
        backend = backend if backend is not None else LocalBackend(Path(root or "."))
        backend.require_hosts()
    except ClusterError as e:
        raise MissionRunError(str(e)) from None
    if not alive_hosts(backend):
        raise MissionRunError(f"no host is alive in the {backend.describe()}")
    md = md or mission_dir(backend.root)
    md.mkdir(parents=True, exist_ok=True)
    state = read_json(md / STATE_FILE)
    if conductor_alive(state) and state is not None and state.get("state") in ("finished", "failed"):
        deadline = time.monotonic() + 10.0  # the mission is over; its conductor is on its way out
        while conductor_alive(state) and time.monotonic() < deadline:
            time.sleep(0.1)
    if conductor_alive(state):
        raise MissionRunError(f"mission {state.get('mission')} is running on this cluster (pid {state.get('pid')}): "  # type: ignore[union-attr]
                              "haactl mission stop first")
    speed = float(speed if speed is not None else mission.spec.speed)
    rec = read_json(md / SIM_FILE)
    handle = SimHandle.from_json(rec) if rec else None
    if handle is not None and handle.started_here and not handle.alive():
        handle = None
    if sim_address:
        handle = SimHandle(sim_address, sim_token_file, agent_address=agent_sim[0], agent_token_file=agent_sim[1])
    fresh = False
    if handle is not None:
        try:
            with handle.client(3.0) as c:
                info = c.info()
                ids = {a.avatar_id for a in c.poses().avatars}
        except grpc.RpcError as e:
            raise MissionRunError(f"haa-sim at {handle.address} does not answer: {e.code().name}") from None
        check_sim_matches(info, mission)
        clash = sorted(ids & {a.name for a in mission.spec.avatars})
        if clash:
            raise MissionRunError(f"the running haa-sim already has avatar{'s' if len(clash) > 1 else ''} "
                                  f"{', '.join(clash)}: stop it first (haactl mission stop)")
        if info.mode == "realtime" and info.speed and abs(info.speed - speed) > 1e-9:
            speed = float(info.speed)  # the agents' clocks must follow the haa-sim that runs
        if sim_address:  # the conductor finds it there
            write_json(md / SIM_FILE, handle.to_json())
    else:
        handle = start_sim(mission, speed, md, schedule=True, detached=True)
        fresh = True
        write_json(md / SIM_FILE, handle.to_json())
    (md / TRANSCRIPT_FILE).unlink(missing_ok=True)
    where = ["--state-dir", str(md)] if conductor else ["--root", str(backend.root)]
    cmd = [*(conductor or [sys.executable, "-m", "haa.mission.attached", "conduct"]), *where, "--mission",
           str(Path(mission.path).absolute()), "--speed", repr(speed), "--out", str(md / "run")]
    if fresh:
        cmd.append("--fresh-sim")
    if agent_types != (EXECUTIVE, AVATAR):
        cmd += ["--agent-types", ",".join(agent_types)]
    write_json(md / STATE_FILE, {"state": "launching", "mission": mission.spec.name})
    with open(md / "conductor.log", "wb") as logf:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT,
                             start_new_session=True)
    deadline = time.monotonic() + wait
    while True:
        st = read_json(md / STATE_FILE) or {}
        if st.get("state") == "failed" or p.poll() is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(10)
            if fresh:
                handle.stop()
                (md / SIM_FILE).unlink(missing_ok=True)
            raise MissionRunError(str(st.get("error") or f"the mission conductor exited (log: {md / 'conductor.log'})"))
        if st.get("pid") and st.get("state") not in ("launching", "starting"):
            return st
        if st.get("pid") and st.get("exec", ["", ""])[0]:
            return st
        if time.monotonic() > deadline:
            return st
        time.sleep(0.2)


def stop_attached(root: Path | None, timeout: float = 90.0, md: Path | None = None,
                  backend: Any = None) -> dict[str, Any]:
    """`haactl mission stop`: end the conductor (it collects the results and removes the mission's agents),
    or remove the agents itself if the conductor is gone; stop the haa-sim `start` started. Returns
    {"results": ... or None, "removed": [...], "sim": "stopped" | "left running" | ""}. The local cluster at
    `root`, or `backend` with its state directory `md` (compose)."""
    from haa.cluster.local_backend import LocalBackend

    md = md or mission_dir(Path(root or "."))
    state = read_json(md / STATE_FILE)
    out: dict[str, Any] = {"results": None, "removed": [], "sim": "", "was_running": False}
    rec = read_json(md / SIM_FILE)  # (a conductor that ends stops the haa-sim `start` started, and forgets it)
    if conductor_alive(state):
        out["was_running"] = True
        assert state is not None
        os.kill(int(state["pid"]), signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while conductor_alive(state) and time.monotonic() < deadline:
            time.sleep(0.2)
        if conductor_alive(state):
            os.kill(int(state["pid"]), signal.SIGKILL)
    elif state and state.get("agent_ids") and state.get("state") not in ("finished", "failed"):
        with contextlib.suppress(Exception):
            backend = backend if backend is not None else LocalBackend(Path(root or "."))
            out["removed"] = remove_agents(backend, [i for i in state["agent_ids"] if i])
    if rec:
        out["sim"] = _stop_started_sim(md)
        h = SimHandle.from_json(rec)
        if not out["sim"] and h.started_here and out["was_running"] and not h.alive():
            out["sim"] = "stopped"  # by the conductor, on its way out
        (md / SIM_FILE).unlink(missing_ok=True)
    out["results"] = read_json(md / "run" / "results.json")
    return out


def _stop_started_sim(md: Path) -> str:
    """Stop the haa-sim recorded in `md` if `mission start` started it (not one the operator gave with --sim);
    "stopped" if it did. A finished mission's haa-sim used to step on (3 % of a core) after the mission and
    `cluster down`, and the next `mission start` was refused (its avatars still there) until `mission stop`."""
    rec = read_json(md / SIM_FILE)
    if not rec:
        return ""
    h = SimHandle.from_json(rec)
    if not h.started_here:
        return ""
    done = ""
    if h.alive():
        h.stop()
        done = "stopped"
    (md / SIM_FILE).unlink(missing_ok=True)
    return done


def live_transcript(root: Path | None, md: Path | None = None) -> list[dict[str, Any]]:
    path = (md or mission_dir(Path(root or "."))) / TRANSCRIPT_FILE
    out = []
    with contextlib.suppress(OSError):
        for line in path.read_text().splitlines():
            with contextlib.suppress(ValueError):
                out.append(json.loads(line))
    return out


def conduct(argv: Sequence[str] | None = None, backend: Any = None) -> int:
    """The detached process behind `haactl mission start` (see above): on the local cluster `--root`, or on
    `backend` with its state directory `--state-dir` (haa.mission.compose for the compose cluster)."""
    import argparse

    from haa.cluster.local_backend import LocalBackend
    from haa.mission.schema import MissionError, load_mission

    p = argparse.ArgumentParser(prog="python -m haa.mission.attached conduct")
    p.add_argument("--root", type=Path)
    p.add_argument("--state-dir", type=Path, help="the mission state directory (default <root>/mission)")
    p.add_argument("--mission", type=Path, required=True)
    p.add_argument("--speed", type=float, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--fresh-sim", action="store_true")
    p.add_argument("--agent-types", default=f"{EXECUTIVE},{AVATAR}", help="stand-ins of the two top-level types")
    a = p.parse_args(argv)
    exec_type, _, avatar_type = a.agent_types.partition(",")
    if a.root is None and (backend is None or a.state_dir is None):
        p.error("--root, or a backend and --state-dir")
    md = a.state_dir.absolute() if a.state_dir is not None else mission_dir(a.root)
    me = psutil.Process()
    base = {"pid": me.pid, "create_time": me.create_time()}
    try:
        mission = load_mission(a.mission)
        rec = read_json(md / SIM_FILE)
        if rec is None:
            raise MissionRunError(f"no haa-sim recorded in {md / SIM_FILE}")
        sim = SimHandle.from_json(rec)
        sim.started_here = False  # `haactl mission stop` stops it, not the conductor
        last_tr = [0.0]

        def on_poll(run: MissionRun) -> None:
            write_json(md / STATE_FILE, snapshot(run))
            if time.monotonic() - last_tr[0] > TRANSCRIPT_PERIOD:
                last_tr[0] = time.monotonic()
                with contextlib.suppress(Exception):
                    lines, _ = run.transcript(events=run.read_events())
                    tmp = md / (TRANSCRIPT_FILE + ".tmp")
                    tmp.write_text("".join(json.dumps(ln.to_json()) + "\n" for ln in lines))
                    tmp.replace(md / TRANSCRIPT_FILE)

        write_json(md / STATE_FILE, {**base, "state": "starting", "mission": mission.spec.name})
        run = MissionRun(mission, a.speed, a.out, backend=backend if backend is not None else LocalBackend(a.root),
                         sim=sim, fresh_sim=a.fresh_sim,
                         on_poll=on_poll, log=lambda text: print(text, flush=True),
                         agent_types=(exec_type, avatar_type))
        signal.signal(signal.SIGTERM, lambda *_: run.stop_flag.set())
        signal.signal(signal.SIGINT, lambda *_: run.stop_flag.set())
        try:
            results = run.run()
        finally:
            if a.fresh_sim:  # the mission is over: the haa-sim `start` started for it goes too
                _stop_started_sim(md)
        lines = [json.loads(x) for x in (a.out / "transcript.jsonl").read_text().splitlines() if x.strip()]
        (md / TRANSCRIPT_FILE).write_text("".join(json.dumps(x) + "\n" for x in lines))
        write_json(md / STATE_FILE, {**snapshot(run), "state": "finished", "results": results})
        return 0 if results.get("completed") else 1
    except (MissionRunError, MissionError) as e:
        write_json(md / STATE_FILE, {**base, "state": "failed", "error": str(e)})
        print(f"error: {e}", flush=True)
        return 2
    except Exception as e:
        write_json(md / STATE_FILE, {**base, "state": "failed", "error": f"{type(e).__name__}: {e}"})
        raise


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "conduct":
        sys.exit(conduct(sys.argv[2:]))
    print("usage: python -m haa.mission.attached conduct --root DIR --mission FILE --speed X --out DIR",
          file=sys.stderr)
    sys.exit(2)
