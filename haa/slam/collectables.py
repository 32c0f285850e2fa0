"""The team's collectable map (Forage, thesis §6.2.1 Table 6.2-1 scenario 3, §7.1.3): collectables the team's
own cameras found, identified by position, with a map-frame estimate (docs/slam.md "Collectables").

A `CollectablesReading` (haa.slam.sensors: range and bearing of each collectable's centre in one camera
image, from haa.control.collectables) is applied by `SlamSystem.process` like the other readings — on every
replica, in log order — but gives no density and no grid update. Each sighting is placed in the map frame
with the avatar's *estimated* pose at the reading's time: the particles' states there (the filter's history,
as for landmark sightings) each imply a position `x_i + r·(cos, sin)(θ_i + b)`, and the sighting's position
is their mean under the block's weights with the densities already applied to the block folded in (what
`estimate()` would say at that time; read-only, nothing in the filter changes). Its spread is the pose
part of its error.

**Association.** The sighting belongs to the nearest identified collectable whose estimate lies within
`gate` (default `GATE` = 1.0 m); if none, it is a new collectable with the next id (1, 2, ...). Why 1 m:
the arenas place collectables at least 2 m apart (the large arena's nearest pair: 2.02 m). A re-sighting of
collectable A lands within e_s + e_A of A's estimate (e_s: the sighting's map error, e_A: the estimate's);
a first sighting of B, at least 2 m from A, lands at least 2 − e_s − e_A from it. With the gate at half the
spacing both mistakes — a duplicate of A, or B merged into A (never identified, so never collected) — need
e_s + e_A > 1 m, and below that the nearest estimate within the gate is always the right one. The detector
contributes centimetres (range MAE ≤ 3.2 cm, p95 ≤ 6.5 cm up to 4 m, bearing ~1 mrad: docs/control.md
"Collectables"); a heading error δθ adds r·δθ (0.1 m at 4 m for the thesis' 0.024 rad); the rest is the pose
estimate's position error — the thesis' AF-3 0.105 m, our AF-1 runs 0.3-0.8 m — and what matters is its
*difference* between the sightings of one collectable, small for one avatar within seconds and up to the sum
of two avatars' errors otherwise. A smaller gate would split a collectable whenever two avatars' estimates
disagree by a few decimetres; a larger one would merge neighbours.

**Estimate.** The weighted mean of its sightings' positions, each weighted by 1 / (σ_sensor(r)² + σ_pose²)
(σ_sensor = 0.005 + 0.003 r² m: the detector's range error grows with the square of the distance; σ_pose:
the particle spread of the implied positions), with the sighting count, the first and the last sighting's
time; `std` is sqrt(n / Σw) — the typical sighting's σ, not divided by the count: one avatar's sightings
share its pose error. Everything is a deterministic function of the log (Python floats summed in
log order), part of the replica's checkpoint and state digest.

**Bounds.** At most `MAX_COLLECTABLES` identified (a sighting that would make one more is counted in
`full`), so a stream of nonsense cannot make association cost grow without bound; the events' own bounds
(haa.slam.events) limit sightings per image and their range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from haa.slam.sensors import CollectablesReading

#: m: half the arenas' minimum collectable spacing (2 m; see the module docstring)
GATE = 1.0
MAX_COLLECTABLES = 1024


def sensor_sigma(r: float) -> float:
    """σ (m) of a collectable sighting's position from the detector alone, at range r (docs/control.md)."""
    return 0.005 + 0.003 * r * r


@dataclass
class Collectable:
    """One identified collectable: sums of its weighted sightings, count and times."""

    id: int
    sw: float  # Σ w
    swx: float  # Σ w x
    swy: float  # Σ w y
    n: int
    t_first: float
    t_last: float

    @property
    def x(self) -> float:
        return self.swx / self.sw

    @property
    def y(self) -> float:
        return self.swy / self.sw

    @property
    def std(self) -> float:
        """sqrt(n / Σw): the sightings' σ (their weights' harmonic mean), not divided by the count."""
        return math.sqrt(self.n / self.sw)

    def add(self, x: float, y: float, var: float, t: float) -> None:
        w = 1.0 / var
        self.sw += w
        self.swx += w * x
        self.swy += w * y
        self.n += 1
        self.t_first = min(self.t_first, t)
        self.t_last = max(self.t_last, t)


class CollectableMap:
    """Identified collectables by id (see the module docstring)."""

    def __init__(self, gate: float = GATE, limit: int = MAX_COLLECTABLES) -> None:
        if not (math.isfinite(gate) and gate > 0):
            raise ValueError(f"gate: must be a finite distance > 0 m, got {gate}")
        self.gate = float(gate)
        self.limit = int(limit)
        self.items: dict[int, Collectable] = {}
        self.next_id = 1
        self.sightings = 0  # sightings applied
        self.full = 0  # sightings of a new collectable refused: `limit` reached

    def __len__(self) -> int:
        return len(self.items)

    def nearest(self, x: float, y: float) -> Collectable | None:
        """The identified collectable nearest (x, y) within the gate (ties: the lower id)."""
        best, best_d = None, self.gate
        for c in self.items.values():  # in id order (insertion order)
            d = math.hypot(c.x - x, c.y - y)
            if d <= best_d and (best is None or d < best_d):
                best, best_d = c, d
        return best

    def add(self, x: float, y: float, var: float, t: float) -> int | None:
        """One sighting at (x, y) with variance `var` at time t: the id it was given (None: map full)."""
        c = self.nearest(x, y)
        if c is None:
            if len(self.items) >= self.limit:
                self.full += 1
                return None
            c = Collectable(self.next_id, 0.0, 0.0, 0.0, 0, t, t)
            self.items[c.id] = c
            self.next_id += 1
        c.add(x, y, var, t)
        self.sightings += 1
        return c.id

    def apply(self, r: CollectablesReading, states: np.ndarray, weights: np.ndarray) -> list[int | None]:
        """The reading's sightings in turn, from the particle states (N, 3) at its time and their weights."""
        ids = []
        for g in r.sightings:
            phi = states[:, 2] + g.bearing
            px = states[:, 0] + g.range * np.cos(phi)
            py = states[:, 1] + g.range * np.sin(phi)
            mx, my = float(weights @ px), float(weights @ py)
            dx, dy = px - mx, py - my
            pose_var = 0.5 * (float(weights @ (dx * dx)) + float(weights @ (dy * dy)))
            ids.append(self.add(mx, my, sensor_sigma(g.range) ** 2 + pose_var, r.t))
        return ids

    def published(self, ndigits: int = 3) -> dict[str, dict[str, float | int]]:
        """`forage/collectables` (docs/team.md): {id: {"x", "y", "n", "t_first", "t_last", "std"}}."""
        return {
            str(c.id): {
                "x": round(c.x, ndigits),
                "y": round(c.y, ndigits),
                "n": c.n,
                "t_first": round(c.t_first, 3),
                "t_last": round(c.t_last, 3),
                "std": round(c.std, ndigits),
            }
            for c in self.items.values()
        }
