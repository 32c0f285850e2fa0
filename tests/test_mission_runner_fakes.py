"""Stand-ins for the two top-level team agents, so that the mission runner is tested on real processes
independently of the robot team (tests/test_mission_runner.py loads this module into the hosts through
HAA_AGENT_MODULES and runs the runner with `agent_types=(FAKE_EXEC, FAKE_AVATAR)`).

They speak the runner's side of docs/team.md and nothing more: `fake_executive_mission` takes the executive's
config and writes `mission/status` (running, then complete after `FAKE_DURATION_S` simulated seconds, the
explored share growing linearly), `slam/map` and the `stats/*` counters; `fake_avatar_simulation` takes an
avatar's config and writes `slam/est/<avatar>` — its true pose from haa-sim's ground truth plus a fixed
0.05 m offset (a stand-in may look; the real agents may not). No test functions here.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from haa.sdk.base import AgentBase
from haa.sdk.registry import register

FAKE_EXEC = "fake_executive_mission"
FAKE_AVATAR = "fake_avatar_simulation"
FAKE_DURATION_S = 24.0
EST_OFFSET_M = 0.05


def _sim_time(cfg: dict[str, Any]) -> float:
    return float(cfg["sim0"]) + (time.time() - float(cfg["wall0"])) * float(cfg["speed"])


def _encode_map(width: float, height: float, resolution: float, prob: Any) -> bytes:
    from haa.mission.metrics import fallback_decode_map, fallback_encode_map, map_decoder
    from haa.slam.grid import GridSpec

    spec = GridSpec(width, height, resolution)
    if map_decoder() is fallback_decode_map:
        return fallback_encode_map(spec, prob)
    from haa.slam.replica import encode_map  # type: ignore[import-not-found,unused-ignore]

    return encode_map(spec, prob)  # type: ignore[no-any-return,unused-ignore]


@register
class FakeExecutive(AgentBase):
    TYPE = FAKE_EXEC
    RECOVERY = "restart"

    async def on_start(self) -> None:
        self.cfg_ = self.config_json()
        self.started = _sim_time(self.cfg_)
        self.done = False
        self.every(0.25, self.tick, first=0.0)

    def pack_state(self) -> bytes:
        return json.dumps({"started": self.started, "done": self.done}).encode()

    def unpack_state(self, data: bytes) -> None:
        self.cfg_ = self.config_json()
        d = json.loads(data) if data else {"started": _sim_time(self.cfg_), "done": False}
        self.started, self.done = float(d["started"]), bool(d["done"])

    async def on_resume(self, how: str) -> None:
        if not hasattr(self, "cfg_"):
            self.unpack_state(b"")
        self.every(0.25, self.tick, first=0.0)

    async def tick(self) -> None:
        if self.done:
            return
        import numpy as np

        t = _sim_time(self.cfg_)
        share = min(1.0, (t - self.started) / FAKE_DURATION_S)
        status: dict[str, Any] = {"state": "running", "t": t, "explored": share, "reason": "",
                                  "started_t": self.started, "finished_t": None}
        if share >= 1.0:
            status.update(state="complete", finished_t=t, reason=f"explored {100 * share:.0f} % (fake)")
            self.done = True
        m = self.cfg_["mission"]
        res = float(m.get("map_resolution", 0.1))
        width, height = 3.4, 7.2  # the small arena
        rows, cols = round(height / res), round(width / res)
        prob = np.full((rows, cols), 0.5, dtype=np.float32)
        prob[: int(rows * share)] = 0.1  # "free", growing northwards
        await self.ddb_put("slam/map", _encode_map(width, height, res, prob))
        await self.ddb_put_json("mission/status", status)
        n = max(0, int(10 * (t - self.started)))
        for key, v in (("readings_generated", n), ("readings_processed", n), ("processings", 2 * n)):
            await self.ddb_put_json(f"stats/{key}", v)  # (the team uses counters; the runner reads numbers)


@register
class FakeAvatar(AgentBase):
    TYPE = FAKE_AVATAR
    RECOVERY = "restart"

    async def on_start(self) -> None:
        self.cfg_ = self.config_json()
        self.every(0.3, self.tick, first=0.0)

    async def on_resume(self, how: str) -> None:
        await self.on_start()

    async def tick(self) -> None:
        from haa.sim.service import SimClient

        tf = self.cfg_.get("sim_token_file")
        token = Path(tf).read_text().strip() if tf else None
        with SimClient(self.cfg_["sim"], token=token, timeout=3.0) as c:
            r = c.poses()
        for a in r.avatars:
            if a.avatar_id == self.cfg_["avatar"] and a.status == "active":
                est = {"t": r.time, "x": a.pose.x + EST_OFFSET_M, "y": a.pose.y, "theta": a.pose.theta,
                       "std": [0.1, 0.1, 0.05]}
                await self.ddb_put("slam/est/" + self.cfg_["avatar"], json.dumps(est).encode(), "json")
