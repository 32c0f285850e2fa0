"""Experiments AF-1, AF-2 and AF-3 (thesis §7.1.1-7.1.3): N runs of a mission on seeds seed..seed+N-1,
summarised as the thesis' tables do — representative run, mean, RMS and STD (population) per metric — beside
the thesis' values (Tables 7.1-1, 7.1-2 and 7.1-3, L1390-1403, L1514-1527 and L1564-1578).

    summary = run_experiment("af1", runs=10, speed=4)     # bench-results/af1.json

Statistics (thesis guide §3.1, verified on every table): STD is the population standard deviation
(ddof = 0) over the runs and RMS² = mean² + STD². Runs without a value for a metric (None: not measured, or
a run that did not produce it) are left out of that metric's statistics; `n` says how many counted.

Resuming (`resume=True`, `haactl experiment NAME --resume`): an AF-3 run lasts ~29 simulated minutes, so ten
span sessions. The summary JSON is written after every run (`<name>-partial.json` until all are done); a
resumed experiment reads it (or the finished file), keeps its runs when they were made with the same mission
file (its provenance hash), speed, first seed and exploration strategy, and goes on with the next seed. A run
cut off mid-mission is made again from its start.

Representative run (thesis: "figures show one representative run", no rule given): the completed run whose
main metrics (duration, coverage, accuracy, position error) are closest to the means, in units of each
metric's STD (metrics with STD 0 or no values do not count); ties go to the lower seed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from haa.mission.metrics import fmt, rows_for, scaled
from haa.mission.schema import Mission, load_mission

REPO = Path(__file__).resolve().parents[3]
MISSIONS = REPO / "missions"
RESULTS_DIR = REPO / "bench-results"

#: Table 7.1-1 (AF-1) and 7.1-2 (AF-2): title -> (representative run, mean, RMS, STD)
THESIS: dict[str, dict[str, tuple[float, float, float, float]]] = {
    "af1": {
        "Mission Duration [min]": (3.802, 3.871, 3.884, 0.324816),
        "Map Coverage [%]*": (90.38, 91.07, 91.10, 2.247400),
        "Map Accuracy [%]*": (90.64, 91.19, 91.19, 0.793000),
        "Localization Positional Err [m]": (0.07414, 0.05737, 0.05947, 0.015661),
        "Localization Rotational Err [rad]": (0.05221, 0.04665, 0.05290, 0.024944),
        "Landmark Err [m]": (0.07977, 0.07606, 0.07646, 0.007790),
        "Landmark Covariance [m]": (0.40481, 0.40241, 0.41953, 0.118617),
        "Average # Hosts": (4.50, 4.52, 4.52, 0.031171),
        "Average # Agents": (12.83, 13.00, 13.01, 0.396887),
        "Average CPU Usage [%]": (29.64, 28.76, 28.82, 1.771400),
        "DDB Size [MB]": (9.179, 9.475, 9.520, 0.919952),
    },
    "af2": {
        "Mission Duration [min]": (2.974, 3.102, 3.201, 0.788482),
        "Map Coverage [%]*": (57.32, 58.96, 59.18, 4.993000),
        "Map Accuracy [%]*": (78.34, 78.87, 78.89, 1.775000),
        "Localization Positional Err [m]": (0.02808, 0.07489, 0.07899, 0.025108),
        "Localization Rotational Err [rad]": (0.01011, 0.03719, 0.04106, 0.017404),
        "Landmark Err [m]": (0.04999, 0.06436, 0.06577, 0.013556),
        "Landmark Covariance [m]": (0.50794, 0.65200, 0.67516, 0.175332),
        "Average # Hosts": (5.00, 5.00, 5.00, 0.000000),
        "Average # Agents": (12.32, 12.41, 12.41, 0.355753),
        "Average CPU Usage [%]": (16.25, 16.28, 16.41, 2.085000),
        "DDB Size [MB]": (5.973, 5.453, 5.532, 0.928745),
    },
    "af3": {
        "Mission Duration [min]": (28.963, 28.599, 28.683, 2.203573),
        "Map Coverage [%]*": (98.32, 97.83, 97.83, 0.755300),
        "Map Accuracy [%]*": (91.52, 91.15, 91.16, 1.291200),
        "Localization Positional Err [m]": (0.08069, 0.10553, 0.11601, 0.048174),
        "Localization Rotational Err [rad]": (0.01906, 0.02403, 0.02609, 0.010175),
        "Landmark Err [m]": (0.09601, 0.09915, 0.10426, 0.032232),
        "Landmark Covariance [m]": (0.05503, 0.05333, 0.05337, 0.002213),
        "Average # Hosts": (9.00, 9.00, 9.00, 0.000000),
        "Average # Agents": (29.95, 29.48, 29.49, 0.822289),
        "Average CPU Usage [%]": (55.52, 53.84, 53.87, 1.586500),
        "DDB Size [MB]": (26.122, 25.384, 25.420, 1.353034),
        "Cargo Collected": (20.00, 20.00, 20.00, 0.000000),
    },
}
EXPERIMENTS = tuple(THESIS)
#: metrics that choose the representative run
REPRESENTATIVE_KEYS = ("duration_s", "coverage", "accuracy", "position_error_m")


@dataclasses.dataclass(frozen=True)
class Stats:
    n: int
    mean: float | None
    rms: float | None
    std: float | None

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def stats(values: Sequence[float | None]) -> Stats:
    """Mean, RMS and population STD of the values that are there (None and non-finite left out)."""
    xs = [float(v) for v in values if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)]
    if not xs:
        return Stats(0, None, None, None)
    n = len(xs)
    mean = sum(xs) / n
    rms = math.sqrt(sum(x * x for x in xs) / n)
    std = math.sqrt(max(0.0, sum((x - mean) ** 2 for x in xs) / n))
    return Stats(n, mean, rms, std)


def representative(runs: Sequence[dict[str, Any]], keys: Sequence[str] = REPRESENTATIVE_KEYS) -> int | None:
    """Index of the representative run (module docstring); None without runs."""
    if not runs:
        return None
    pool = [i for i, r in enumerate(runs) if r.get("completed")] or list(range(len(runs)))
    st = {k: stats([r.get(k) for r in runs]) for k in keys}

    def distance(i: int) -> tuple[float, int]:
        d = 0.0
        for k, s in st.items():
            v = runs[i].get(k)
            if s.mean is None or not s.std or not isinstance(v, int | float) or isinstance(v, bool):
                continue
            d += abs(float(v) - s.mean) / s.std
        return d, int(runs[i].get("seed", i) or 0)

    return min(pool, key=distance)


def summarize(name: str, runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per table row: the representative run's value, mean, RMS, STD (scaled to the row's unit) and the
    thesis' four values; plus the run count and how many completed."""
    rep = representative(runs)
    thesis = THESIS.get(name, {})
    rows = []
    for title, key, scale in rows_for(runs):
        s = stats([scaled(r, key, scale) for r in runs])
        rows.append({
            "title": title,
            "key": key,
            "representative": scaled(runs[rep], key, scale) if rep is not None else None,
            **s.to_json(),
            "thesis": list(thesis[title]) if title in thesis else None,
        })
    return {
        "experiment": name,
        "runs": len(runs),
        "completed": sum(1 for r in runs if r.get("completed")),
        "representative_run": rep,
        "representative_seed": runs[rep].get("seed") if rep is not None else None,
        "rows": rows,
    }


def table_rows(summary: dict[str, Any]) -> list[tuple[str, ...]]:
    """(title, rep, mean, RMS, STD, thesis rep, thesis mean, thesis RMS, thesis STD) as text, for printing."""
    out = []
    for r in summary["rows"]:
        th = r["thesis"] or [None] * 4
        out.append((r["title"], *(fmt(r[k], r["title"]) for k in ("representative", "mean", "rms", "std")),
                    *(fmt(v, r["title"]) if v is not None else "" for v in th)))
    return out


def mission_for(name: str, path: Path | None = None) -> Mission:
    """missions/<name>.yaml (or `path`)."""
    return load_mission(path if path is not None else MISSIONS / f"{name}.yaml")


def with_seed(mission: Mission, seed: int) -> Mission:
    return dataclasses.replace(mission, spec=mission.spec.model_copy(update={"seed": seed}))


def with_exploration(mission: Mission, exploration: str | None) -> Mission:
    """The mission with SupervisorExplore's strategy set (`em` | `frontier`), to compare them on the same seeds."""
    if exploration is None:
        return mission
    if exploration not in ("em", "frontier"):
        raise ValueError(f"exploration: 'em' or 'frontier', got {exploration!r}")
    return dataclasses.replace(mission, spec=mission.spec.model_copy(update={"exploration": exploration}))


def run_experiment(
    name: str,
    runs: int = 10,
    speed: float | None = None,
    out_dir: Path | None = None,
    json_out: Path | None = None,
    mission: Mission | None = None,
    run_fn: Callable[..., dict[str, Any]] | None = None,
    on_run: Callable[[int, dict[str, Any]], None] | None = None,
    log: Callable[[str], None] | None = None,
    exploration: str | None = None,
    resume: bool = False,
) -> dict[str, Any]:
    """Run the experiment's mission `runs` times on seeds seed..seed+runs-1 (each in its own local cluster
    and haa-sim, one after the other), write the summary JSON (default bench-results/<name>.json) and
    return it. `run_fn` (default haa.mission.runner.run_mission) is how one run is made (tests). `resume`:
    go on from the runs already in the JSON (module docstring)."""
    if run_fn is None:
        from haa.mission.runner import run_mission

        run_fn = run_mission
    m = with_exploration(mission or mission_for(name), exploration)
    out_dir = (out_dir or Path("mission-runs") / name).absolute()
    t0 = time.time()
    results: list[dict[str, Any]] = resumed(name, m, speed, json_out, log) if resume else []
    for k in range(len(results), runs):
        seed = m.spec.seed + k
        if log:
            log(f"{name} run {k + 1}/{runs}: seed {seed}")
        r = run_fn(with_seed(m, seed), speed=speed, out_dir=out_dir / f"seed{seed}", log=log)
        results.append(r)
        if on_run:
            on_run(k, r)
        if k + 1 < runs:  # after every run, so that an interrupted experiment keeps what it measured
            _write(name, m, runs, speed, t0, results, json_out, partial=True)
    return _write(name, m, runs, speed, t0, results, json_out, partial=False)


def resumed(name: str, m: Mission, speed: float | None, json_out: Path | None,
            log: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """The runs an earlier, interrupted (or shorter) call of the same experiment left in its JSON: [] when there
    is none or it was made with another mission file, speed or first seed (then it is said why)."""
    from haa.mission.results import provenance

    path = json_out or RESULTS_DIR / f"{name}.json"
    for p in (path.with_name(path.stem + "-partial" + path.suffix), path):
        try:
            doc = json.loads(p.read_text())
        except (OSError, ValueError):
            continue
        want = {"mission file": provenance(m).get("mission_sha256"), "speed": speed if speed is not None
                else m.spec.speed, "first seed": m.spec.seed, "exploration": m.spec.exploration}
        got = {"mission file": (doc.get("provenance") or {}).get("mission_sha256"), "speed": doc.get("speed"),
               "first seed": (doc.get("seeds") or [None])[0], "exploration": doc.get("exploration")}
        differ = [k for k in want if got[k] != want[k]]
        if differ:
            if log:
                log(f"not resuming from {p}: its {', '.join(differ)} differ{'s' if len(differ) == 1 else ''}")
            return []
        runs = [r for r in doc.get("results", []) if isinstance(r, dict)]
        if log:
            log(f"resuming from {p}: {len(runs)} run(s) done (seeds {doc.get('seeds')})")
        return runs
    return []


def _write(name: str, m: Mission, runs: int, speed: float | None, t0: float, results: list[dict[str, Any]],
           json_out: Path | None, partial: bool) -> dict[str, Any]:
    """The summary of the runs so far as JSON (`partial`: fewer than `runs` done; the file name gets
    `-partial`)."""
    from haa.mission.results import provenance

    doc = {
        **summarize(name, results),
        "mission": m.spec.name,
        "exploration": m.spec.exploration,
        "seeds": [m.spec.seed + k for k in range(len(results))],
        "runs_planned": runs,
        "partial": partial,
        "speed": speed if speed is not None else m.spec.speed,
        "wall_s": round(time.time() - t0, 1),
        "provenance": provenance(m),
        "results": results,
    }
    path = json_out or RESULTS_DIR / f"{name}.json"
    if partial:
        path = path.with_name(path.stem + "-partial" + path.suffix)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    if not partial:
        path.with_name(path.stem + "-partial" + path.suffix).unlink(missing_ok=True)
    doc["json"] = str(path)
    return doc
