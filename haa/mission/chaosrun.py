"""A mission's chaos plan (mission file `chaos: FILE`; docs/chaos.md, "Inside a mission"): run by the lab's
chaos extension (haa.mission.extensions) on a thread of its own, from mission time 0 until the mission ends or
the plan's `duration_s`. Its times and `hang_s` are simulated seconds; every fault it injects (or skips) goes on
the mission's transcript; `summary` goes into the results, `to_json` is chaos.json of the run folder.
haa.mission.runner.MissionRun keeps one when the mission names a plan.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from haa.mission.extensions import extension
from haa.mission.schema import Mission, resolve

#: a transcript line: (text, event, host, t=mission time) — MissionRun.line
LineFn = Callable[..., None]

#: how a chaos action is said on the transcript
SAID = {"hang": "hangs", "kill": "killed", "pause": "paused", "resume": "resumed", "restart": "restarted"}


class ChaosRun:
    """The plan of `plan_file`, loaded through the lab's extension (ExtensionMissing without the lab; the mission
    schema has checked the plan). Its faults go on the transcript through `line`; a failure of the plan is
    appended to `errors` (the mission goes on without it)."""

    def __init__(self, plan_file: Path, line: LineFn, errors: list[str]) -> None:
        self.ext = extension("chaos")
        self.plan = self.ext.load(plan_file)
        self.line = line
        self.errors = errors
        self.done = threading.Event()
        self.thread: threading.Thread | None = None
        self.injector: Any = None

    @classmethod
    def of(cls, mission: Mission, line: LineFn, errors: list[str]) -> ChaosRun | None:
        """The mission's chaos plan, None if it names none."""
        if mission.spec.chaos is None:
            return None
        return cls(resolve(mission.path.parent if mission.path else None, mission.spec.chaos), line, errors)

    @property
    def started(self) -> bool:
        return self.thread is not None

    def start(self, backend: Any, clock: Callable[[], float], speed: float, limit_s: float) -> None:
        """Run the plan on `backend` (an object of its own: the plan runs on its own thread) against the mission
        clock `clock` (simulated seconds) at `speed`, for the plan's `duration_s` or else `limit_s`."""
        plan = self.plan
        self.injector = self.ext.injector(plan, backend, on_fault=self.fault_line, clock=clock,
                                          sleep=lambda s: self.done.wait(max(0.0, s) / speed),
                                          duration=plan.duration_s or limit_s, wall_per_s=1.0 / speed)
        self.line(f"chaos plan {plan.name}: {len(plan.faults)} fault lines (seed {plan.seed})", "fault")

        def chaos() -> None:
            try:
                self.injector.run(stop=self.done.is_set, t0=0.0)
            except Exception as e:  # the mission goes on without its chaos; said in the results
                msg = f"chaos plan {plan.name} stopped: {e}"
                self.errors.append(msg)
                self.line(msg, "error")

        self.thread = threading.Thread(target=chaos, name="mission-chaos", daemon=True)
        self.thread.start()

    def stop(self, wait: float = 30.0) -> None:
        """End the chaos (pauses it holds are ended); waits up to `wait` s for its thread (0: not at all)."""
        self.done.set()
        if self.thread is not None and wait > 0:
            self.thread.join(wait)

    def fault_line(self, rec: Any) -> None:
        """One injected (or skipped) fault on the transcript."""
        what = SAID.get(rec.action, rec.action)
        text = (f"{rec.target} {what} by chaos: {rec.detail}" if rec.ok
                else f"chaos {rec.action} {rec.target} not done: {rec.detail}")
        self.line(text, "fault", rec.target if rec.target.startswith("h") and rec.target[1:].isdigit() else "",
                   t=rec.t)

    def summary(self) -> dict[str, Any] | None:
        """The plan's name and what it did (every record is in chaos.json of the run folder); None if it never
        started."""
        if self.injector is None:
            return None
        recs = list(self.injector.injected)
        by: dict[str, int] = {}
        for r in recs:
            if r.ok:
                by[r.action] = by.get(r.action, 0) + 1
        return {"plan": self.plan.name, "seed": self.plan.seed, "injected": sum(by.values()),
                "skipped": sum(1 for r in recs if not r.ok), "by_action": by}

    def to_json(self) -> dict[str, Any] | None:
        """chaos.json: the plan and every fault record; None if it never started."""
        if self.injector is None:
            return None
        return {"plan": self.plan.model_dump(mode="json"), "faults": [r.to_json() for r in self.injector.injected]}
