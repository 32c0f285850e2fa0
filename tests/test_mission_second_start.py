"""A second `haactl mission start` on the same local cluster runs a mission of its own: the first mission's
`mission/status = complete` (and its map, estimates, ...) stays in the DDB after it ended, and a start that
read it would finish at once. The runner clears the team's keys (haa.mission.runner.TEAM_PREFIXES) before it
spawns the new executive. Stand-in team agents (test_mission_runner_fakes: complete after FAKE_DURATION_S
simulated seconds, at speed 4 about 6 s); ≈ 40 s."""

from __future__ import annotations

from pathlib import Path

from helpers import wait_sync, wait_value
from test_mission_runner import FAKE_MISSION, fake_team, mission_file, our_processes
from test_mission_runner_fakes import FAKE_DURATION_S

from haa.cluster import queries
from haa.cluster.local_backend import LocalBackend
from haa.mission import attached, load_mission
from haa.mission import runner as rn


def wait_state(root: Path, pred, timeout: float, what: str) -> dict:
    """The mission's state file once `pred` holds for it."""
    state = attached.mission_dir(root) / attached.STATE_FILE
    return wait_value(lambda: attached.read_json(state) or {}, pred, timeout, what, interval=0.3)


def test_a_second_start_gets_a_fresh_mission(tmp_path, monkeypatch):
    types = fake_team(monkeypatch)
    root = tmp_path / "cluster"
    b = LocalBackend(root)
    b.up(2, 2)
    try:
        wait_sync(lambda: b.formation(["h1", "h2"]).done, 60, "h1 and h2 in one group", interval=0.2)
        m = load_mission(mission_file(tmp_path, FAKE_MISSION))
        durations = []
        for _ in range(2):
            st = attached.start_attached(root, m, agent_types=types)
            assert st["mission"] == "fake"
            st = wait_state(root, lambda s: s.get("state") == "running", 30, "the mission to run")
            st = wait_state(root, lambda s: s.get("state") in ("finished", "failed"), 60, "the mission to end")
            res = st["results"]
            assert res["completed"] is True, res
            durations.append(float(res["duration_s"]))
            # the conductor stopped the haa-sim `start` started for the mission: no `mission stop` needed
            # before the next start (its avatars used to stay, and the second start was refused)
            assert not (attached.mission_dir(root) / attached.SIM_FILE).exists()
        # each mission ran its own FAKE_DURATION_S: the second did not inherit the first's `complete`
        assert all(d >= 0.8 * FAKE_DURATION_S for d in durations), durations
        values = queries.ddb_read(b, keys=[rn.K_STATUS])
        assert values is not None and values[1][rn.K_STATUS]["state"] == "complete"
    finally:
        attached.stop_attached(root)
        b.down(grace=1.0)
    assert not our_processes(str(tmp_path))
