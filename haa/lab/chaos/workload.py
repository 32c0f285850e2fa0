"""Workloads that give a chaos run something to lose, without a mission (plan key `workload`).

* `ddb-writes`: `agents` writer agents (type `chaos_writer`, defined here). Every `period_s` a writer
  appends one item `{"w": name, "e": epoch, "n": seq}` to its own DDB log `chaos/log/<name>` (an append, so
  an overwrite cannot hide a loss and a repeat shows as a duplicate) and, once the write is committed (its
  host answered ""), logs `chaos_ack` with the same fields: the ack lands in its host's JSON-lines log in the
  host's data dir, where the checks read it. A writer stops writing at `until` (unix time, from its
  config) or once the key `chaos/stop` exists (the runner writes it when the faults end), so the replicas can
  converge before they are read. Writes go through the agent's host, fenced by
  the instance's epoch: what an older instance writes after a newer one started must not be committed.
* `counters`: `agents` pairs of the demo `counter` agents (haa.lab.demoagents), each checking the numbered
  stream of its peer and writing its counters to `demo/<name>`.

The hosts find `chaos_writer` through `HAA_AGENT_MODULES` (`WORKLOAD_MODULE`), which the chaos runner sets
in the environment of the hosts it starts.
"""

from __future__ import annotations

import json
import time
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from haa.core.ddb import ops as ddbmod
from haa.sdk.base import AgentBase, HostError
from haa.sdk.registry import register

#: module the hosts must load for the `ddb-writes` workload
WORKLOAD_MODULE = "haa.lab.chaos.workload"
WRITER_TYPE = "chaos_writer"
#: the writers' DDB logs
LOG_PREFIX = "chaos/log/"
#: event a writer logs for each committed write
ACK_EVENT = "chaos_ack"
#: once this key exists (the runner writes it when the chaos ends) writers stop writing
STOP_KEY = "chaos/stop"


class WriterConfig(BaseModel):
    """Config of `chaos_writer`."""

    model_config = ConfigDict(extra="forbid", strict=True)

    period: float = Field(0.2, ge=0.01, le=60)
    #: stop writing at this unix time (0: never)
    until: float = Field(0.0, ge=0)


def log_key(writer_name: str) -> str:
    return LOG_PREFIX + writer_name


def item_bytes(name: str, epoch: int, n: int) -> bytes:
    return json.dumps({"w": name, "e": epoch, "n": n}, separators=(",", ":")).encode()


@register
class ChaosWriter(AgentBase):
    """Appends numbered items to its DDB log and logs each committed one (module docstring)."""

    TYPE = "chaos_writer"
    RECOVERY = "backup"
    CONFIG = WriterConfig

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.n = 0  # next sequence number of this instance's writes
        self.stopped = False

    async def on_start(self) -> None:
        await self._arm()

    async def on_resume(self, how: str) -> None:
        await self._arm()

    async def _arm(self) -> None:
        self.watch(STOP_KEY, self._on_stop_key)
        self.stopped = await self.ddb_get(STOP_KEY) is not None
        self.every(self.cfg.period, self._tick)

    def _on_stop_key(self, event: str, key: str, value: bytes | None) -> None:
        if key == STOP_KEY and value is not None:
            self.stopped = True

    def pack_state(self) -> bytes:
        return json.dumps({"n": self.n}).encode()

    def unpack_state(self, data: bytes) -> None:
        self.n = int(json.loads(data)["n"])

    def recover(self, backup: bytes | None) -> None:
        # a new epoch: the items are told apart by (epoch, n), so numbering may start again
        self.n = 0

    async def _tick(self) -> None:
        if self.stopped or (self.cfg.until and time.time() >= self.cfg.until):
            return
        n = self.n
        self.n += 1
        op = ddbmod.log_append(log_key(self.name), [item_bytes(self.name, self.epoch, n)])
        try:
            reasons = await self.ddb_write([op], timeout=10.0)
        except (HostError, TimeoutError) as e:
            self.log("chaos_write_failed", level="warning", w=self.name, e=self.epoch, n=n, error=str(e))
            return
        if reasons == [""]:
            self.log(ACK_EVENT, w=self.name, e=self.epoch, n=n)
        else:
            self.log("chaos_write_failed", level="warning", w=self.name, e=self.epoch, n=n, error=reasons[0])
