"""The mission runner's pictures: the estimated map beside the ideal one with the true paths (`plot_maps`,
map.png of a run folder) and the agents per host over mission time (`plot_timeline`, allocation.png).
matplotlib (Agg) is imported when a picture is drawn; without it they raise ImportError.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from haa.mission import metrics as mm
from haa.mission import transcript as tr


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_maps(path: Path, ideal: np.ndarray | None, explorable: np.ndarray | None, prob: np.ndarray | None,
              res: float, scores: mm.MapScores | None, paths: dict[str, mm.PoseHistory],
              errors: dict[str, list[tuple[float, float, float]]], title: str) -> Path:
    """The estimated map `prob` beside the `ideal` one (north up; cells of `res` m), the true `paths` on the
    ideal map, each avatar's mean position error (of `errors`, as LocalizationLog keeps them) on the map."""
    plt = _plt()
    occ = ideal if ideal is not None else np.zeros((1, 1))
    ex = explorable if explorable is not None else np.zeros_like(occ)
    est = prob if prob is not None else np.full(occ.shape, 0.5, dtype=np.float32)
    extent = (0.0, occ.shape[1] * res, 0.0, occ.shape[0] * res)
    fig, axes = plt.subplots(1, 2, figsize=(10, 10 * occ.shape[0] / max(1, 2 * occ.shape[1]) + 1.2), dpi=110)
    left = "estimated map (slam/map)" if prob is not None else "estimated map (none published)"
    if scores is not None:
        left += (f"\ncoverage {100 * scores.coverage:.1f} %, accuracy {100 * scores.accuracy:.1f} %, "
                 f"explored {100 * scores.explored:.1f} %")
    axes[0].imshow(1.0 - est, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent)
    axes[0].set_title(left, fontsize=9)
    shade = np.where(occ > 0, 0.0, np.where(ex > 0, 1.0, 0.75))
    axes[1].imshow(shade, cmap="gray", vmin=0, vmax=1, origin="lower", extent=extent)
    axes[1].set_title(f"ideal map (haa-sim, {int(ex.sum())} reachable cells) and true paths", fontsize=9)
    for i, (name, h) in enumerate(sorted(paths.items())):
        if not h.t:
            continue
        xy = np.array([(p[0], p[1]) for p in h.poses])
        color = f"C{i % 10}"
        axes[1].plot(xy[:, 0], xy[:, 1], lw=0.8, color=color, label=name)
        errs = errors.get(name)
        if errs:
            axes[0].plot([], [], color=color, label=f"{name}: {np.mean([e[1] for e in errs]):.3f} m")
    for ax in axes:
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
    if paths:
        axes[1].legend(fontsize=7, loc="upper right")
    if errors:
        axes[0].legend(fontsize=7, loc="upper right", title="mean position error", title_fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_timeline(path: Path, samples: mm.Samples, members: Iterable[str], lines: Iterable[tr.Line],
                  name: str) -> Path:
    """Agents per host over simulated mission time (from polling), with the group size; a line at every host
    event of the runner's `lines`."""
    plt = _plt()
    s = samples
    hosts = sorted({h for _, c in s.per_host for h in c} | set(members),
                   key=lambda n: (len(n), n))
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6), dpi=110, sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    ts = [t for t, _ in s.per_host]
    for i, h in enumerate(hosts):
        ax.step(ts, [c.get(h, 0) for _, c in s.per_host], where="post", lw=1.2, color=f"C{i % 10}", label=h)
    if s.agents:
        ax.step([t for t, _ in s.agents], [v for _, v in s.agents], where="post", color="k", lw=1.5, ls="--",
                label="all agents")
    ax.set_ylabel("active agents")
    ax.set_title(f"mission {name}: agent allocation (agents per host)", fontsize=10)
    if hosts:
        ax.legend(fontsize=7, ncol=min(6, len(hosts) + 1), loc="upper left")
    if s.hosts:
        ax2.step([t for t, _ in s.hosts], [v for _, v in s.hosts], where="post", color="C3", label="hosts")
    ax2.set_ylabel("hosts")
    ax2.set_xlabel("simulated mission time [s]")
    for ln in lines:
        if ln.event == "host":
            ax2.axvline(ln.t, color="0.7", lw=0.6)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
