"""The stats bundles of a mission run (`haactl mission run -o DIR`, docs/stats.md): the mission extension `bundles`
(entry point of group `haa.mission`, haa.mission.extensions)."""

from __future__ import annotations

from pathlib import Path

from haa.cluster.backend import Backend
from haa.lab.stats.collect import CollectResult, collect_quietly


def collect(backend: Backend, out_dir: Path) -> CollectResult | str:
    """One bundle per host and the cluster summary in `out_dir`: the result, or why it failed (never raises)."""
    return collect_quietly(backend, out_dir)
