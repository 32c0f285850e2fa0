"""ExecutiveAvatar (thesis App. III L3041-3045; Table 4.2-1 item 2): who controls which avatar.

"Controls the distribution of avatar resources using a bidding algorithm. Task supervisors place bids for
resources and the ExecutiveAvatar assigns resources to the highest bidders. Resource assignments are stored in
the DDB so that they are independent of agent failures." In the thesis' experiments it was rolled into
ExecutiveMission (L1264); here it is its own agent, a child of ExecutiveMission.

* Registry: avatar agents register under `avatars/<name>` (status active | retired).
* Bids: `bids/<avatar>/<supervisor id>` = {"priority": p, "task": ...}; a supervisor withdraws by deleting.
* Assignment: for every active avatar, the highest priority wins; ties go to the lower supervisor id (a
  deterministic rule; the thesis gives none, gap 6). Written to `assign/<avatar>` only when it changes; an
  avatar with no bids or no longer active loses its assignment. Bid scale (docs/team.md): SupervisorExplore
  bids 1 (the low default of L1510), SupervisorCongregate 10.

Everything it decides from is in the DDB, so it keeps no state of its own: RECOVERY = "restart" ("Restore
configuration"), and it recomputes on start, on every registry or bid change (coalesced) and every
`period_s`.
"""

from __future__ import annotations

import json
from typing import Any

import pydantic

from haa.agents import team
from haa.core.ddb import ops as ddbops
from haa.sdk.registry import register


class ExecutiveAvatarConfig(team.TeamConfig):
    period_s: float = pydantic.Field(2.0, gt=0, le=600)


def decide(registry: dict[str, dict[str, Any]],
           bids: dict[str, dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """avatar → winning bid {"supervisor", "priority", "task"} for every active avatar with bids."""
    out: dict[str, dict[str, Any]] = {}
    for a, reg in registry.items():
        if reg.get("status") != "active" or not bids.get(a):
            continue
        sup, bid = min(bids[a].items(), key=lambda kv: (-float(kv[1].get("priority", 0)), kv[0]))
        out[a] = {"supervisor": sup, "priority": float(bid.get("priority", 0)), "task": bid.get("task", "")}
    return out


@register
class ExecutiveAvatar(team.TeamAgent):
    TYPE = "executive_avatar"
    CONFIG = ExecutiveAvatarConfig
    COST = 0.01
    RECOVERY = "restart"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.cfg: ExecutiveAvatarConfig
        self.pending = False

    async def begin(self, how: str) -> None:
        self.watch(team.K_AVATARS, self._changed)
        self.watch(team.K_BIDS, self._changed)
        self.every(self.cfg.period_s, self.assign)
        await self.assign()

    def _changed(self, kind: str, key: str, value: bytes | None) -> None:
        if not self.pending:
            self.pending = True
            self.call_later(0.05, self.assign)

    async def assign(self) -> None:
        self.pending = False
        registry = {k[len(team.K_AVATARS):]: json.loads(v) for k, v in (await self.ddb_scan(team.K_AVATARS)).items()}
        bids: dict[str, dict[str, dict[str, Any]]] = {}
        for k, v in (await self.ddb_scan(team.K_BIDS)).items():
            avatar, _, sup = k[len(team.K_BIDS):].partition("/")
            bids.setdefault(avatar, {})[sup] = json.loads(v)
        current = {k[len(team.K_ASSIGN):]: json.loads(v) for k, v in (await self.ddb_scan(team.K_ASSIGN)).items()}
        want = decide(registry, bids)
        ops = []
        changes = []
        for a, w in want.items():
            cur = current.get(a)
            if cur is None or cur.get("supervisor") != w["supervisor"]:
                ops.append(team.op_put_json(team.K_ASSIGN + a, {**w, "t": round(self.now(), 3)}))
                changes.append(f"{a} to {w['task'] or w['supervisor'][:8]}")
        for a in current:
            if a not in want:
                ops.append(ddbops.delete(team.K_ASSIGN + a))
                changes.append(f"{a} released")
        if ops:
            await self.ddb_write(ops)
            await team.transcript(self, "assigned " + ", ".join(changes))
