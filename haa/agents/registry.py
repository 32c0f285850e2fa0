"""The agent type registry: type name -> AgentBase subclass.

A new agent type is a subclass plus a registry entry, nothing else:

    from haa.agents.base import AgentBase
    from haa.agents.registry import register

    @register
    class Pinger(AgentBase):
        TYPE = "pinger"
        ...

(or `REGISTRY["pinger"] = Pinger`, checked the same way when the registry is read). Where types come from,
in this order (`load_all`):

1. every module of the `haa.agents` package except the runtime's own (base, channel, registry, runner,
   forkserver, bench, harness) — so an agent module dropped into haa/agents/ is found without editing a list;
2. the entry points of group `haa.agents` of installed distributions (third-party agent packages): an entry
   point names a module (imported for its `@register`s) or an AgentBase subclass (registered if it is not);
3. the modules named in the environment variable `HAA_AGENT_MODULES` (comma separated) and the `extra`
   argument (the fork server's `--preload`).

A module that fails to import is reported (the fork server logs it and the host sees it in
`AgentSupervisor.load_errors`) and does not stop the others. The fork server loads the registry once, before
forking any agent, so spawning a registered type costs a fork, not imports.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import pkgutil
import re
from collections.abc import Iterable
from typing import Any, TypeVar

import pydantic

from haa.agents.base import RECOVERY_STRATEGIES, AgentBase

#: largest AgentBase.MAX_PER_HOST (= haa.core.allocation.MAX_PER_HOST; not imported: agent processes load
#: this module and need nothing of the host daemon)
MAX_PER_HOST = 1000

ENTRY_POINT_GROUP = "haa.agents"
ENV_MODULES = "HAA_AGENT_MODULES"
#: modules of haa.agents that are the runtime, not agent types
RUNTIME_MODULES = frozenset({"base", "channel", "registry", "runner", "forkserver", "bench", "harness"})

#: bounds of the resource limits a type may declare (AgentBase.MEMORY_LIMIT_MB, AgentBase.CPU_LIMIT)
MIN_MEMORY_LIMIT_MB = 16
MAX_MEMORY_LIMIT_MB = 1024 * 1024
MIN_CPU_LIMIT = 0.01
MAX_CPU_LIMIT = 1024.0

TYPE_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-]{0,63}$")

REGISTRY: dict[str, type[AgentBase]] = {}

A = TypeVar("A", bound=type[AgentBase])


class UnknownAgentType(LookupError):
    """No agent type of that name is registered."""

    def __init__(self, type_name: str, known: Iterable[str]) -> None:
        names = ", ".join(sorted(known)) or "none"
        super().__init__(f"unknown agent type {type_name!r} (registered: {names})")
        self.type_name = type_name

    def __str__(self) -> str:
        return str(self.args[0])


def validate(cls: Any, name: str | None = None) -> None:
    """Raise ValueError/TypeError naming the attribute and the reason if `cls` is not a valid agent type."""
    if not (isinstance(cls, type) and issubclass(cls, AgentBase)):
        raise TypeError(f"{cls!r} is not a subclass of haa.agents.base.AgentBase")
    where = f"agent class {cls.__module__}.{cls.__qualname__}"
    type_name = cls.TYPE
    if not isinstance(type_name, str) or not TYPE_NAME.match(type_name):
        raise ValueError(f"{where}: TYPE must match {TYPE_NAME.pattern}, got {type_name!r}")
    if name is not None and name != type_name:
        raise ValueError(f"{where}: registered as {name!r} but its TYPE is {type_name!r}")
    if isinstance(cls.COST, bool) or not isinstance(cls.COST, int | float) or not cls.COST >= 0:
        raise ValueError(f"{where}: COST must be a number >= 0, got {cls.COST!r}")
    if not isinstance(cls.HARDWARE, frozenset) or not all(isinstance(h, str) and h for h in cls.HARDWARE):
        raise ValueError(f"{where}: HARDWARE must be a frozenset of non-empty names, got {cls.HARDWARE!r}")
    p = cls.TRANSFER_PENALTY
    if isinstance(p, bool) or not isinstance(p, int | float) or not 0 <= p <= 1:
        raise ValueError(f"{where}: TRANSFER_PENALTY must be in [0, 1], got {p!r}")
    mph = cls.MAX_PER_HOST
    if isinstance(mph, bool) or not isinstance(mph, int) or not 0 <= mph <= MAX_PER_HOST:
        raise ValueError(f"{where}: MAX_PER_HOST must be an int in [0, {MAX_PER_HOST}] (0 = no limit), got {mph!r}")
    if cls.RECOVERY not in RECOVERY_STRATEGIES:
        raise ValueError(f"{where}: RECOVERY must be one of {sorted(RECOVERY_STRATEGIES)}, got {cls.RECOVERY!r}")
    if cls.CONFIG is not None and not (isinstance(cls.CONFIG, type) and issubclass(cls.CONFIG, pydantic.BaseModel)):
        raise ValueError(f"{where}: CONFIG must be a pydantic model class or None, got {cls.CONFIG!r}")
    m = cls.MEMORY_LIMIT_MB
    if isinstance(m, bool) or not isinstance(m, int) or not MIN_MEMORY_LIMIT_MB <= m <= MAX_MEMORY_LIMIT_MB:
        raise ValueError(f"{where}: MEMORY_LIMIT_MB must be an int in [{MIN_MEMORY_LIMIT_MB}, "
                         f"{MAX_MEMORY_LIMIT_MB}], got {m!r}")
    c = cls.CPU_LIMIT
    if isinstance(c, bool) or not isinstance(c, int | float) or not MIN_CPU_LIMIT <= c <= MAX_CPU_LIMIT:
        raise ValueError(f"{where}: CPU_LIMIT must be a number in [{MIN_CPU_LIMIT}, {MAX_CPU_LIMIT}], got {c!r}")


def register(cls: A) -> A:
    """Class decorator: validate and register an agent type under its TYPE (a second class may not take it)."""
    validate(cls)
    old = REGISTRY.get(cls.TYPE)
    if old is not None and old is not cls and not _same_class(old, cls):
        raise ValueError(
            f"agent type {cls.TYPE!r} is already registered by {old.__module__}.{old.__qualname__}"
        )
    REGISTRY[cls.TYPE] = cls
    return cls


def _same_class(a: type, b: type) -> bool:
    """A module imported twice (as __main__ and by name, or reloaded) defines equal classes again."""
    return a.__qualname__ == b.__qualname__ and a.__module__.split(".")[-1] == b.__module__.split(".")[-1]


def get(type_name: str) -> type[AgentBase]:
    """The class of `type_name`; raises UnknownAgentType (a LookupError) with the registered names."""
    cls = REGISTRY.get(type_name)
    if cls is None:
        raise UnknownAgentType(type_name, REGISTRY)
    validate(cls, type_name)
    return cls


def type_info(cls: type[AgentBase]) -> dict[str, Any]:
    """What a host needs of a type without importing it: cost, hardware, transfer penalty, recovery, whether
    it has a config model (the host then asks the fork server to check a config before a spawn commits) and
    its resource limits."""
    return {
        "type_name": cls.TYPE,
        "cost": float(cls.COST),
        "hardware": sorted(cls.HARDWARE),
        "transfer_penalty": float(cls.TRANSFER_PENALTY),
        "recovery": cls.RECOVERY,
        "module": cls.__module__,
        "has_config": cls.CONFIG is not None,
        "memory_limit_mb": int(cls.MEMORY_LIMIT_MB),
        "cpu_limit": float(cls.CPU_LIMIT),
        "max_per_host": int(cls.MAX_PER_HOST),
    }


def load_modules(names: Iterable[str]) -> list[str]:
    """Import modules by name; returns one error line per module that failed."""
    errors = []
    for name in names:
        name = name.strip()
        if not name:
            continue
        try:
            importlib.import_module(name)
        except Exception as e:
            errors.append(f"module {name}: {type(e).__name__}: {e}")
    return errors


def load_builtin() -> list[str]:
    """Import every agent module of the haa.agents package (see the module docstring)."""
    import haa.agents as pkg

    names = [
        f"{pkg.__name__}.{m.name}"
        for m in pkgutil.iter_modules(pkg.__path__)
        if m.name not in RUNTIME_MODULES and not m.name.startswith(("_", "test"))
    ]
    return load_modules(sorted(names))


def load_entry_points() -> list[str]:
    """Load the `haa.agents` entry points of installed distributions; returns error lines."""
    errors = []
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
            if isinstance(obj, type) and issubclass(obj, AgentBase) and obj.TYPE not in REGISTRY:
                register(obj)
        except Exception as e:
            errors.append(f"entry point {ep.name} = {ep.value}: {type(e).__name__}: {e}")
    return errors


def load_all(extra: Iterable[str] = ()) -> list[str]:
    """Fill the registry from every source (module docstring); returns the error lines, [] if all loaded."""
    errors = load_builtin()
    errors += load_entry_points()
    env = os.environ.get(ENV_MODULES, "")
    errors += load_modules([*env.split(","), *extra])
    for name, cls in list(REGISTRY.items()):  # entries added by assignment are checked here
        try:
            validate(cls, name)
        except (TypeError, ValueError) as e:
            errors.append(f"registry entry {name!r}: {e}")
            del REGISTRY[name]
    return errors
