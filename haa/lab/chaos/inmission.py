"""A chaos plan inside a mission (docs/chaos.md, "Inside a mission"): the mission extension `chaos` (entry point
of group `haa.mission`, haa.mission.extensions), so that the mission runner and schema use the lab's plans
without importing the lab."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from haa.cluster.backend import Backend
from haa.lab.chaos.inject import Injector
from haa.lab.chaos.plan import Plan, PlanError, load_plan, mission_problems


def load(path: Path) -> Plan:
    """The plan file, validated; ValueError with one line if it cannot run."""
    try:
        return load_plan(path)
    except PlanError as e:
        raise ValueError(str(e)) from None


def problems(plan: Plan, hosts: set[str]) -> list[str]:
    """What the plan asks that a mission with these hosts cannot do, one line each."""
    return mission_problems(plan, hosts)


def injector(plan: Plan, backend: Backend, **options: Any) -> Injector:
    """The injector that runs the plan on the mission's cluster (options: haa.lab.chaos.inject.Injector's)."""
    return Injector(plan, backend, **options)
