"""Experiment R-1, Agent Failure (thesis §7.3.1, L1782-1830; Table 7.3-1; issue 18 §5).

Mapping and Exploration in the small arena, three hosts, four seekers, 95 % of the reachable cells explored
(missions/r1.yaml). Four failure rates, each a chaos plan run inside the mission (docs/chaos.md, "Inside a
mission"): every agent draws a failure time uniformly in its life-expectancy window, counted from when it is
first seen active; then its event loop blocks for `HANG_S` simulated seconds (a stuck computation, which its
host finds by the missing heartbeats and kills) — "injected failures hang 30 s first" (thesis guide, gap 5) —
and a recovered instance draws again:

    none       no failure
    moderate   1-10 min     (MTF, the window's midpoint: 5.5 min)
    high       1-3 min      (2 min)
    extreme    0.5-1.5 min  (1 min)

Every level runs the same seeds (seed..seed+N-1). Per level the table has the mean and the population STD of
every row of Table 7.1-1 (haa.lab.experiments.af.summarize), beside Table 7.3-1. The duration model of
eq. 7.3-1, ΔD = (MTF + k) / MTF with ΔD = mean duration / mean duration without failures, is fitted by least
squares through the origin in x = 1/MTF, y = ΔD - 1 (k = Σxy / Σx²); the thesis measured +10 / +27 / +52 %
and k = 0.55 min.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import yaml

from haa.lab.experiments.af import MISSIONS, RESULTS_DIR, stats, summarize, with_seed
from haa.mission.schema import Mission, load_mission

#: (level, life-expectancy window in simulated seconds or None)
LEVELS: tuple[tuple[str, tuple[float, float] | None], ...] = (
    ("none", None),
    ("moderate", (60.0, 600.0)),
    ("high", (60.0, 180.0)),
    ("extreme", (30.0, 90.0)),
)
#: simulated seconds a failing agent's loop stays blocked (it is killed as hung before, by its host)
HANG_S = 30.0
#: Table 7.3-1 (L1793-1806): title -> (means none, moderate, high, extreme), (STDs in the same order)
THESIS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "Mission Duration [min]": ((2.573, 2.842, 3.261, 3.900), (0.2606, 0.3476, 0.4108, 0.4927)),
    "Map Coverage [%]*": ((88.00, 88.88, 88.49, 87.80), (2.3483, 1.5553, 1.9932, 1.9850)),
    "Map Accuracy [%]*": ((90.58, 90.43, 90.27, 89.86), (0.8154, 0.3783, 0.9082, 0.9449)),
    "Localization Positional Err [m]": ((0.0602, 0.0676, 0.0774, 0.1016), (0.0203, 0.0192, 0.0261, 0.0377)),
    "Localization Rotational Err [rad]": ((0.0370, 0.0576, 0.0394, 0.0828), (0.0095, 0.0257, 0.0204, 0.0412)),
    "Landmark Err [m]": ((0.0801, 0.0933, 0.0860, 0.1136), (0.0159, 0.0201, 0.0190, 0.0483)),
    "Landmark Covariance [m]": ((0.4445, 0.4133, 0.3578, 0.3739), (0.1318, 0.1528, 0.0804, 0.0831)),
    "Average # Hosts": ((4.00, 4.00, 4.00, 4.00), (0.0, 0.0, 0.0, 0.0)),
    "Average # Agents": ((14.20, 14.32, 15.14, 16.37), (0.2970, 0.3454, 0.5694, 0.4536)),
    "Average CPU Usage [%]": ((40.60, 38.99, 35.67, 28.79), (1.7048, 1.9236, 2.4381, 2.2266)),
    "DDB Size [MB]": ((8.434, 9.075, 9.304, 9.225), (0.9787, 1.0661, 0.9106, 0.8870)),
}
#: the thesis' duration increases (moderate, high, extreme) and k of eq. 7.3-1 [min]
THESIS_INCREASE = (0.10, 0.27, 0.52)
THESIS_K_MIN = 0.55


def mtf_min(window: tuple[float, float] | None) -> float | None:
    """Mean time to failure [min] of a uniform life-expectancy window [s]: its midpoint."""
    return None if window is None else (window[0] + window[1]) / 2 / 60


def fit_k(points: Sequence[tuple[float, float]]) -> float | None:
    """k of eq. 7.3-1 from (MTF [min], ΔD) pairs: least squares of ΔD - 1 = k / MTF through the origin."""
    xs = [(1.0 / m, d - 1.0) for m, d in points if m > 0]
    sxx = sum(x * x for x, _ in xs)
    return sum(x * y for x, y in xs) / sxx if sxx > 0 else None


def plan_for(level: str, window: tuple[float, float] | None, seed: int) -> dict[str, Any] | None:
    """The chaos plan of a failure level (module docstring); None for no failure."""
    if window is None:
        return None
    return {"name": f"r1-{level}", "seed": seed,
            "faults": [{"life_s": list(window), "action": "hang", "target": "agents", "hang_s": HANG_S}]}


def with_plan(mission: Mission, plan: dict[str, Any] | None, folder: Path) -> Mission:
    """The mission running `plan` (written to folder/plan.yaml), or without chaos."""
    if plan is None:
        return dataclasses.replace(mission, spec=mission.spec.model_copy(update={"chaos": None}))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "plan.yaml"
    path.write_text(yaml.safe_dump(plan, sort_keys=False))
    return dataclasses.replace(mission, spec=mission.spec.model_copy(update={"chaos": str(path.absolute())}))


def summarize_r1(by_level: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Per level the AF table summary; the duration increases against no failure and the fitted k."""
    levels = {name: summarize("r1", runs) for name, runs in by_level.items() if runs}
    base = stats([r.get("duration_s") for r in by_level.get("none", [])]).mean
    increase: dict[str, float | None] = {}
    points = []
    for name, window in LEVELS:
        runs = by_level.get(name) or []
        m = stats([r.get("duration_s") for r in runs]).mean
        if window is None or not runs or m is None or not base:
            continue
        d = m / base
        increase[name] = d - 1.0
        points.append((mtf_min(window) or 0.0, d))
    failures = {name: stats([r.get("agent_failures") for r in runs]).to_json() for name, runs in by_level.items()}
    return {
        "experiment": "r1",
        "levels": levels,
        "increase": increase,
        "k_min": fit_k(points),
        "failures": failures,
        "thesis": {"table": {t: {"mean": list(v[0]), "std": list(v[1])} for t, v in THESIS.items()},
                   "increase": dict(zip(("moderate", "high", "extreme"), THESIS_INCREASE, strict=True)),
                   "k_min": THESIS_K_MIN},
    }


def table(summary: dict[str, Any], which: str = "mean") -> list[tuple[str, ...]]:
    """Rows of Table 7.3-1's shape: title, our `which` (mean | std) per level, the thesis' per level."""
    from haa.mission.metrics import fmt

    names = [n for n, _ in LEVELS]
    titles = [r["title"] for r in next(iter(summary["levels"].values()))["rows"]] if summary["levels"] else []
    out = []
    for title in titles:
        ours = []
        for n in names:
            lv = summary["levels"].get(n)
            row = next((r for r in lv["rows"] if r["title"] == title), None) if lv else None
            ours.append(fmt(row[which], title) if row else "")
        th = THESIS.get(title)
        theirs = [fmt(v, title) for v in th[0 if which == "mean" else 1]] if th else [""] * 4
        out.append((title, *ours, *theirs))
    return out


def run_r1(
    runs: int = 10,
    speed: float | None = None,
    out_dir: Path | None = None,
    json_out: Path | None = None,
    mission: Mission | None = None,
    levels: Sequence[str] | None = None,
    run_fn: Callable[..., dict[str, Any]] | None = None,
    on_run: Callable[[str, int, dict[str, Any]], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run R-1 (module docstring): `runs` seeds per level, the levels one after the other, the summary
    written to `json_out` (default bench-results/r1.json) after every run and returned."""
    if run_fn is None:
        from haa.mission.runner import run_mission

        run_fn = run_mission
    known = [n for n, _ in LEVELS]
    chosen = list(levels) if levels else known
    bad = [n for n in chosen if n not in known]
    if bad:
        raise ValueError(f"levels: unknown {', '.join(bad)} (known: {', '.join(known)})")
    m = mission or load_mission(MISSIONS / "r1.yaml")
    out_dir = (out_dir or Path("mission-runs") / "r1").absolute()
    path = json_out or RESULTS_DIR / "r1.json"
    t0 = time.time()
    by_level: dict[str, list[dict[str, Any]]] = {n: [] for n in chosen}
    doc: dict[str, Any] = {}
    for name, window in LEVELS:
        if name not in chosen:
            continue
        for k in range(runs):
            seed = m.spec.seed + k
            folder = out_dir / name / f"seed{seed}"
            if log:
                log(f"r1 {name} run {k + 1}/{runs}: seed {seed}")
            run_m = with_plan(with_seed(m, seed), plan_for(name, window, seed), folder)
            r = run_fn(run_m, speed=speed, out_dir=folder, log=log)
            r["level"] = name
            by_level[name].append(r)
            if on_run:
                on_run(name, k, r)
            doc = _write(path, m, runs, speed, t0, by_level, chosen)
    return doc


def _write(path: Path, m: Mission, runs: int, speed: float | None, t0: float,
           by_level: dict[str, list[dict[str, Any]]], chosen: list[str]) -> dict[str, Any]:
    from haa.mission.results import provenance

    done = sum(len(v) for v in by_level.values())
    doc = {
        **summarize_r1(by_level),
        "mission": m.spec.name,
        "seeds": [m.spec.seed + k for k in range(runs)],
        "runs_planned": runs * len(chosen),
        "runs_done": done,
        "partial": done < runs * len(chosen),
        "speed": speed if speed is not None else m.spec.speed,
        "hang_s": HANG_S,
        "windows_s": {n: list(w) if w else None for n, w in LEVELS if n in chosen},
        "wall_s": round(time.time() - t0, 1),
        "provenance": provenance(m),
        "results": by_level,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    doc["json"] = str(path)
    return doc
