"""A host's agent types, through its fork server: `AgentTypes` starts the fork server (and a new one when the
old one died), and answers what the host knows of agent types — their names, their `AgentTypeInfo` (cost,
hardware, recovery, config model, limits; a type registered by name is imported at its first request) and
whether a config is valid for its type (haa.hostd.agentproc's docstring, "Config validation"). The host does
not import agent code: the fork server (haa.sdk.forkserver) does.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence
from pathlib import Path

from haa.hostd.logs import log_event
from haa.pb import agent_pb2 as pb
from haa.sdk.forkserver import ForkServer, SpawnError

__all__ = ["VALIDATE_TIMEOUT", "AgentTypes"]

#: how long a config check may wait for the fork server (it answers in milliseconds when it runs)
VALIDATE_TIMEOUT = 2.0


class AgentTypes:
    """The fork server of one host (`on_exit(pid, reason)`: an agent's exit; `on_dead(reason)`: the fork
    server's own) and the agent types it knows."""

    def __init__(self, on_exit: Callable[[int, str], None], on_dead: Callable[[str], None], *,
                 workdir: Path | None, preload: Sequence[str], preload_types: Sequence[str],
                 log: logging.Logger) -> None:
        self.on_exit = on_exit
        self.on_dead = on_dead
        self.workdir = workdir
        self.preload = list(preload)
        self.preload_types = list(preload_types)
        self.log = log
        self._fork: ForkServer | None = None
        self._lock = asyncio.Lock()
        #: counters for the host's stats
        self.restarts = 0
        self.unchecked_configs = 0

    async def ensure(self) -> ForkServer:
        """The running fork server; a new one if there is none yet or the last one died."""
        async with self._lock:
            if self._fork is not None and self._fork.alive:
                return self._fork
            if self._fork is not None:
                await self._fork.close()
                self.restarts += 1
            fs = ForkServer(self.on_exit, on_dead=self.on_dead, workdir=self.workdir,
                            preload=self.preload, preload_types=self.preload_types)
            await fs.start()
            for e in fs.load_errors:
                log_event(self.log, logging.WARNING, "agent_type_load_error", error=e)
            log_event(self.log, logging.INFO, "agent_forkserver_started", pid=fs.pid, types=fs.known(),
                      imported=sorted(fs.types), seconds=round(fs.start_seconds, 3))
            self._fork = fs
            return fs

    async def close(self) -> None:
        if self._fork is not None:
            await self._fork.close()

    def known(self) -> list[str]:
        """The names of every agent type this host can start, imported or not."""
        return self._fork.known() if self._fork is not None else []

    def imported(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's info if the fork server has imported it already (no request needed), else None."""
        return self._fork.types.get(type_name) if self._fork is not None else None

    async def info(self, type_name: str) -> pb.AgentTypeInfo | None:
        """The type's info, imported at this first request if it is registered by name only; None if the type
        is unknown here or its module fails to import (logged once as `agent_type_load_error`)."""
        fs = self._fork
        if fs is None or (type_name not in fs.types and type_name not in fs.lazy):
            return None
        try:
            return await fs.describe(type_name)
        except SpawnError as e:
            log_event(self.log, logging.WARNING, "agent_type_load_error", type=type_name, error=str(e))
            return None

    @property
    def load_errors(self) -> list[str]:
        return list(self._fork.load_errors) if self._fork is not None else []

    @property
    def pid(self) -> int | None:
        return self._fork.pid if self._fork is not None else None

    async def validate(self, type_name: str, config: bytes, timeout: float = VALIDATE_TIMEOUT) -> str:
        """'' when `config` is valid for `type_name`, else the reason (one line); unchecked ('') for a type
        without a config model, unknown here, or when the fork server cannot answer within `timeout`
        (`AgentSupervisor.validate_config` says why)."""
        info = await self.info(type_name)
        if info is None or not info.has_config:
            return ""
        try:
            fs = await self.ensure()
            return await fs.validate(type_name, config, timeout=timeout)
        except (SpawnError, OSError) as e:
            self.unchecked_configs += 1
            log_event(self.log, logging.WARNING, "agent_config_unchecked", type=type_name, bytes=len(config),
                      error=str(e))
            return ""
