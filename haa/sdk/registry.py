"""The agent type registry: type name -> AgentBase subclass.

A new agent type is a subclass plus a registry entry, nothing else:

    from haa.sdk.base import AgentBase
    from haa.sdk.registry import register

    @register
    class Pinger(AgentBase):
        TYPE = "pinger"
        ...

(or `REGISTRY["pinger"] = Pinger`, checked the same way when the registry is read). Where types come from
(`load_all`):

1. the entry points of group `haa.agents` of installed distributions — HAA's own team and demo agents
   (pyproject.toml) and third-party agent packages alike. An entry point named after its type and naming a
   class (`counter = "haa.lab.demoagents:CounterAgent"`) is lazy: the name is known at once, the module is
   imported when the type is first asked for (`get`), so that importing the SDK or starting a host imports no
   agent module until an agent of that type is spawned. An entry point naming a module (imported for its
   `@register`s) is imported at once, since its type names are unknown until then;
2. the modules named in the environment variable `HAA_AGENT_MODULES` (comma separated) and the `extra`
   argument (the fork server's `--preload`), imported at once: a host that must not pay an import at its first
   spawn of a type preloads its module this way.

A module that fails to import is reported (the fork server logs it and the host sees it in
`AgentSupervisor.load_errors`) and does not stop the others. The fork server imports a lazy type in its own
process at the first request for it, so the agents it forks later cost a fork, not imports.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import re
from collections.abc import Iterable
from typing import Any, TypeVar

import pydantic

from haa.sdk.base import RECOVERY_STRATEGIES, AgentBase

#: largest AgentBase.MAX_PER_HOST (= haa.core.allocation.specs.MAX_PER_HOST; not imported: agent processes load
#: this module and need nothing of the host daemon)
MAX_PER_HOST = 1000

ENTRY_POINT_GROUP = "haa.agents"
ENV_MODULES = "HAA_AGENT_MODULES"

#: bounds of the resource limits a type may declare (AgentBase.MEMORY_LIMIT_MB, AgentBase.CPU_LIMIT)
MIN_MEMORY_LIMIT_MB = 16
MAX_MEMORY_LIMIT_MB = 1024 * 1024
MIN_CPU_LIMIT = 0.01
MAX_CPU_LIMIT = 1024.0

TYPE_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-]{0,63}$")

REGISTRY: dict[str, type[AgentBase]] = {}
#: types known by name whose class is imported at first use: type name -> its entry point (`catalogue`)
LAZY: dict[str, importlib.metadata.EntryPoint] = {}
_catalogued = False

A = TypeVar("A", bound=type[AgentBase])


class TypeLoadError(LookupError):
    """A type registered by name whose module or class could not be loaded."""


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
        raise TypeError(f"{cls!r} is not a subclass of haa.sdk.base.AgentBase")
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
    """The class of `type_name`, imported now if it is lazy; raises UnknownAgentType (a LookupError) with the
    registered names, or TypeLoadError (a LookupError) if its module or class cannot be loaded."""
    cls = REGISTRY.get(type_name)
    if cls is None:
        if not _catalogued:
            catalogue()
        ep = LAZY.get(type_name)
        if ep is None:
            raise UnknownAgentType(type_name, known())
        cls = _load_lazy(type_name, ep)
    validate(cls, type_name)
    return cls


def types_of(package: str) -> list[str]:
    """The type names of the entry points whose class lives in `package` (e.g. the robot team's, haa.agents),
    without importing them."""
    return sorted(ep.name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
                  if ep.attr and ep.module.startswith(package + "."))


def known() -> list[str]:
    """Every registered type name, imported or not."""
    return sorted({*REGISTRY, *LAZY})


def _load_lazy(type_name: str, ep: importlib.metadata.EntryPoint) -> type[AgentBase]:
    where = f"agent type {type_name!r} ({ep.value})"
    try:
        obj = ep.load()
    except Exception as e:
        raise TypeLoadError(f"{where}: {type(e).__name__}: {e}") from e
    if not (isinstance(obj, type) and issubclass(obj, AgentBase)):
        raise TypeLoadError(f"{where}: not an AgentBase subclass")
    if type_name != obj.TYPE:
        raise TypeLoadError(f"{where}: the class's TYPE is {obj.TYPE!r}, not the entry point's name")
    try:
        if REGISTRY.get(type_name) is not obj:
            register(obj)
    except (TypeError, ValueError) as e:
        raise TypeLoadError(f"{where}: {e}") from e
    LAZY.pop(type_name, None)
    return obj


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


def catalogue() -> list[str]:
    """Read the entry points of group `haa.agents` (module docstring): a class entry point named after a type not
    yet registered becomes lazy, a module entry point is imported now. Returns the error lines."""
    global _catalogued
    _catalogued = True
    errors = []
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.attr:
            if ep.name in REGISTRY:
                continue
            if TYPE_NAME.match(ep.name):
                LAZY.setdefault(ep.name, ep)
            else:
                errors.append(f"entry point {ep.name} = {ep.value}: not a valid agent type name")
            continue
        try:
            ep.load()
        except Exception as e:
            errors.append(f"entry point {ep.name} = {ep.value}: {type(e).__name__}: {e}")
    return errors


def load_builtin() -> list[str]:
    """Import every lazy type now (tests, tools that list every type's details); returns the error lines."""
    if not _catalogued:
        catalogue()
    errors = []
    for name, ep in sorted(LAZY.items()):
        try:
            _load_lazy(name, ep)
        except TypeLoadError as e:
            errors.append(str(e))
    return errors


def load_all(extra: Iterable[str] = ()) -> list[str]:
    """Fill the registry from every source (module docstring); returns the error lines, [] if all loaded."""
    errors = catalogue()
    env = os.environ.get(ENV_MODULES, "")
    errors += load_modules([*env.split(","), *extra])
    for name, cls in list(REGISTRY.items()):  # entries added by assignment are checked here
        try:
            validate(cls, name)
        except (TypeError, ValueError) as e:
            errors.append(f"registry entry {name!r}: {e}")
            del REGISTRY[name]
    return errors
