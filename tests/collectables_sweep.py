"""Test-only measurement of haa.control.collectables against the simulator's truth (reads ground truth).

`sweep(...)` renders frames from seeded random poses, runs the detector and matches its sightings with the true
collectables; `python tests/collectables_sweep.py` prints the table of docs/control.md ("Collectables").
The detector never sees the truth: only the frames' images, K, mount and max_range.
"""

from __future__ import annotations

import itertools
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from haa.control.collectables import CollectableDetector, CollectableSighting, to_map
from haa.sim.arena import COLLECTABLE_HEIGHT, COLLECTABLE_RADIUS, CollectableSpec, compile_arena, load_arena
from haa.sim.camera import LABEL_AVATAR
from haa.sim.sensors import CAMERAS
from haa.sim.world import World

GATE = 0.3  # m: a sighting within this of a true collectable is that collectable
KINDS = {"basic": "seeker", "enhanced": "enhanced_seeker"}
BINS = (0.0, 1.0, 2.0, 3.0, 4.0)


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def arena_with_collectables(name: str, n: int, seed: int, clearance: float = 0.3, apart: float = 0.5):
    """A built-in arena; when it has no collectables, `n` drawn (seeded) on free floor."""
    arena = load_arena(name)
    if arena.collectables or n == 0:
        return arena
    rng = np.random.default_rng([seed, 77])
    pts: list[tuple[float, float]] = []
    while len(pts) < n:
        x, y = float(rng.uniform(0, arena.width)), float(rng.uniform(0, arena.height))
        if arena.clearance(x, y) >= clearance and all(math.hypot(x - a, y - b) >= apart for a, b in pts):
            pts.append((round(x, 3), round(y, 3)))
    specs = [CollectableSpec(id=f"c{i + 1}", pos=p) for i, p in enumerate(pts)]
    return compile_arena(arena.spec.model_copy(update={"collectables": specs}), f"arena {name}+collectables")


@dataclass
class Tally:
    frames: int = 0
    visible: int = 0  # collectables in range, FOV and line of sight (World.collectable_observations), in the image
    below: int = 0  # ... that are below the image (too near for a horizontal camera): not counted in `visible`
    behind: int = 0  # ... whose centre column the renderer gives to a nearer collectable: not counted
    found: int = 0  # of those, matched by a sighting
    extra_true: int = 0  # sightings of a real collectable the visibility helper does not count
    false: int = 0  # sightings of nothing
    # per matched sighting: (range error, bearing error, true range, partial, edge == "top", crowded)
    errors: list[tuple[float, float, float, bool, bool, bool]] = field(default_factory=list)
    vis_ranges: list[float] = field(default_factory=list)  # true range of each visible collectable
    found_flags: list[bool] = field(default_factory=list)
    seconds: float = 0.0  # CPU time of the detector
    avatar_frames: int = 0  # frames with another avatar (green) in view

    def err(self) -> np.ndarray:
        return np.array(self.errors, dtype=float).reshape(-1, 6)


def _free(w: World, x: float, y: float, r: float = 0.12) -> bool:
    if w.arena.clearance(x, y) < r + 0.05:
        return False
    if any(math.hypot(c.x - x, c.y - y) < r + 0.1 for c in w.collectables.values()):
        return False
    return all(
        math.hypot(a.pose[0] - x, a.pose[1] - y) >= 2 * r + 0.3 for a in w.avatars.values() if a.status == "active"
    )


def sweep(
    arena: str,
    camera: str,
    frames: int,
    seed: int,
    aimed: float = 0.7,
    others: int = 3,
    detector: CollectableDetector | None = None,
    small_collectables: int = 12,
) -> Tally:
    """`frames` frames from seeded random free poses: a share `aimed` look towards a random collectable from
    0.2 m to the range + 0.3 m (heading off by up to the half FOV + 0.15 rad, so some are cut at the border),
    the rest are uniform. `others` avatars stand at random free poses (green occluders)."""
    kind = KINDS[camera]
    spec = CAMERAS[camera]
    w = World(arena_with_collectables(arena, small_collectables, seed), seed=seed)
    det = detector or CollectableDetector()
    rng = np.random.default_rng([seed, 1])
    for _ in range(others):
        while True:
            x, y = rng.uniform(0, w.arena.width), rng.uniform(0, w.arena.height)
            if _free(w, x, y, 0.2):
                w.add_avatar("sweeper", (float(x), float(y), float(rng.uniform(-math.pi, math.pi))))
                break
    cs = list(w.collectables.values())
    t = Tally()
    while t.frames < frames:
        if rng.random() < aimed:
            c = cs[int(rng.integers(len(cs)))]
            d = rng.uniform(0.2, spec.max_range + 0.3)
            phi = rng.uniform(-math.pi, math.pi)
            x, y = c.x - d * math.cos(phi), c.y - d * math.sin(phi)
            th = phi + rng.uniform(-1, 1) * (spec.fov / 2 + 0.15)
        else:
            x, y = rng.uniform(0, w.arena.width), rng.uniform(0, w.arena.height)
            th = rng.uniform(-math.pi, math.pi)
        if not _free(w, float(x), float(y)):
            continue
        aid = w.add_avatar(kind, (float(x), float(y), float(wrap(th))))
        fr = w.capture(aid, labels=True)
        t.avatar_frames += bool((fr.labels == LABEL_AVATAR).any())
        t0 = time.process_time()
        sights = det.sightings(fr)
        t.seconds += time.process_time() - t0
        vis = {o.collectable_id for o in w.collectable_observations(aid)}
        below = {c.id for c in cs if c.id in vis and not in_image_rows(fr, c.x, c.y)}
        behind = {c.id for c in cs if c.id in vis - below and behind_collectable(fr.pose, c, cs)}
        t.below += len(below)
        t.behind += len(behind)
        score(t, fr.pose, sights, cs, vis - below - behind)
        w.retire(aid)
        w.step(0.05)
    return t


def in_image_rows(fr, cx: float, cy: float) -> bool:
    """Is the top of the collectable's near face inside the image (not below its bottom row)? The world's
    visibility helper knows only range, horizontal FOV and line of sight; a horizontal camera 0.3 m up does
    not see the floor within 0.57 m (basic) / 0.24 m (enhanced) of the lens at all."""
    x, y, th = fr.pose
    z = (cx - x) * math.cos(th) + (cy - y) * math.sin(th) - COLLECTABLE_RADIUS  # depth of the near face
    f, v0 = fr.K[1, 1], fr.K[1, 2]
    return z > 0 and v0 + f * (fr.mount[2] - COLLECTABLE_HEIGHT) / z <= fr.height - 0.5


def behind_collectable(pose, c, cs) -> bool:
    """Does another collectable on the floor, nearer, cross the ray to c's centre? haa-sim draws one short
    object per image column (the nearest), so c's centre column shows that one even where, in 3D, c would
    show above it; the world's visibility helper does not count collectables as occluders."""
    x, y, _ = pose
    dx, dy = c.x - x, c.y - y
    R = math.hypot(dx, dy)
    for o in cs:
        if o is c or o.state != "floor":
            continue
        ox, oy = o.x - x, o.y - y
        along = (ox * dx + oy * dy) / R
        if 0 < along < R and abs(ox * dy - oy * dx) / R < COLLECTABLE_RADIUS:
            return True
    return False


def crowded(pose, c, cs) -> bool:
    """Does a nearer collectable on the floor overlap c's columns (also when it is below the image)? The
    renderer then draws the nearer one (or nothing, below the image) in those columns."""
    x, y, _ = pose
    R = math.hypot(c.x - x, c.y - y)
    b = math.atan2(c.y - y, c.x - x)
    for o in cs:
        Ro = math.hypot(o.x - x, o.y - y)
        if o is c or o.state != "floor" or Ro >= R:
            continue
        bo = math.atan2(o.y - y, o.x - x)
        if abs(wrap(b - bo)) < math.asin(COLLECTABLE_RADIUS / R) + math.asin(min(1.0, COLLECTABLE_RADIUS / Ro)):
            return True
    return False


def score(t: Tally, pose, sights: list[CollectableSighting], cs, vis: set[str]) -> None:
    """Match one frame's sightings with the true collectables (Hungarian, within GATE) and tally."""
    x, y, th = pose
    t.frames += 1
    est = np.asarray(to_map(sights, pose)).reshape(-1, 2)
    truth = np.array([[c.x, c.y] for c in cs]).reshape(-1, 2)
    pairs: dict[int, int] = {}
    if len(est) and len(truth):
        cost = np.hypot(est[:, None, 0] - truth[None, :, 0], est[:, None, 1] - truth[None, :, 1])
        ri, ci = linear_sum_assignment(cost)
        pairs = {int(i): int(j) for i, j in zip(ri, ci, strict=True) if cost[i, j] <= GATE}
    matched = set(pairs.values())
    for j, c in enumerate(cs):
        if c.id in vis:
            t.visible += 1
            t.found += j in matched
            t.vis_ranges.append(math.hypot(c.x - x, c.y - y))
            t.found_flags.append(j in matched)
    for i, s in enumerate(sights):
        if i not in pairs:
            t.false += 1
            continue
        c = cs[pairs[i]]
        if c.id not in vis:
            t.extra_true += 1
        tr = math.hypot(c.x - x, c.y - y)
        tb = wrap(math.atan2(c.y - y, c.x - x) - th)
        t.errors.append((s.range - tr, wrap(s.bearing - tb), tr, s.partial, s.edge == "top", crowded(pose, c, cs)))


def summary_row(arena: str, camera: str, t: Tally) -> str:
    e = t.err()
    return (
        f"| {arena} | {camera} | {t.frames} | {t.avatar_frames} | {t.visible} | {t.found} | "
        f"{t.found / max(t.visible, 1):.3f} | {t.below} / {t.behind} | {t.extra_true} | {t.false} | "
        f"{int(e[:, 3].sum())} / {int(e[:, 4].sum())} | {1000 * t.seconds / t.frames:.1f} |"
    )


def error_rows(camera: str, tallies: list[Tally]) -> list[str]:
    """Per true-distance bin, both arenas pooled: detection rate and errors (crowded sightings left out)."""
    e = np.concatenate([t.err() for t in tallies])
    e = e[e[:, 5] == 0]
    vr = np.concatenate([np.array(t.vis_ranges) for t in tallies])
    ff = np.concatenate([np.array(t.found_flags, dtype=bool) for t in tallies])
    out = []
    for lo, hi in [*itertools.pairwise(BINS), (0.0, 4.0)]:
        vm = (vr >= lo) & (vr <= hi if hi == 4 else vr < hi)
        em = (e[:, 2] >= lo) & (e[:, 2] <= hi if hi == 4 else e[:, 2] < hi)
        dr, db = e[em, 0], e[em, 1]
        name = f"{lo:.0f}-{hi:.0f} m" if (lo, hi) != (0.0, 4.0) else "all"
        rate = f"{ff[vm].mean():.3f} ({ff[vm].sum()}/{vm.sum()})" if vm.sum() else "–"
        if not em.any():
            out.append(f"| {camera} | {name} | {rate} | 0 | | | | | | |")
            continue
        out.append(
            f"| {camera} | {name} | {rate} | {em.sum()} | {100 * dr.mean():+.1f} cm | "
            f"{100 * np.abs(dr).mean():.1f} cm | "
            f"{100 * np.percentile(np.abs(dr), 95):.1f} cm | {100 * np.abs(dr).max():.1f} cm | "
            f"{1000 * np.abs(db).mean():.1f} mrad | {1000 * np.percentile(np.abs(db), 95):.1f} mrad |"
        )
    return out


def main(argv: list[str]) -> None:
    frames = int(argv[1]) if len(argv) > 1 else 1000
    seed = int(argv[2]) if len(argv) > 2 else 11
    res: dict[tuple[str, str], Tally] = {}
    for arena in ("small", "large"):
        for camera in ("basic", "enhanced"):
            res[arena, camera] = sweep(arena, camera, frames, seed=seed)
    print(
        "| arena | camera | frames | with an avatar in view | collectables in view | found | detection rate | "
        "left out: below the image / behind another | found beyond the helper's view | false | partial / top-edge "
        "sightings | ms / frame |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (arena, camera), t in res.items():
        print(summary_row(arena, camera, t))
    print()
    print(
        "| camera | true range | detection rate | sightings | range bias | range MAE | range p95 | range max | "
        "bearing MAE | bearing p95 |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for camera in ("basic", "enhanced"):
        print("\n".join(error_rows(camera, [res["small", camera], res["large", camera]])))
    for (arena, camera), t in res.items():
        e = t.err()
        cr, clean = e[e[:, 5] == 1], e[e[:, 5] == 0]
        for name, part in (("whole", clean[clean[:, 3] == 0]), ("partial", clean[clean[:, 3] == 1])):
            db = np.abs(part[:, 1])
            print(
                f"{arena}/{camera} {name}: {len(part)}, range MAE {100 * np.abs(part[:, 0]).mean():.1f} cm, "
                f"bearing MAE {1000 * db.mean():.1f} mrad, max {1000 * db.max(initial=0):.1f} mrad, "
                f"> 5 mrad: {(db > 0.005).sum()}"
            )
        print(f"{arena}/{camera} crowded: {len(cr)}, bearing max {1000 * np.abs(cr[:, 1]).max(initial=0):.1f} mrad")


if __name__ == "__main__":
    main(sys.argv)
