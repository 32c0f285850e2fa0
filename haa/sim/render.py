"""Top-down pictures of an arena, and of a world's true state (`haactl sim show`).

Drawn with OpenCV at `scale` pixels per metre, north (+y) up: outer walls and walls grey, obstacles blue,
the congregation post yellow, landmarks as small squares on their faces with their ids, collection regions
green, collectables red, start poses as numbered arrows, avatars (when a World is given) as circles with a
heading tick and their ids (red when crashed), plus a 1 m scale bar and a title line with the arena's counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from haa.sim.arena import OBSTACLE, OUTER_WALL, POST, WALL, Arena
from haa.sim.groundtruth import explorable_area

if TYPE_CHECKING:
    from haa.sim.world import CollectableState, World


@dataclass
class AvatarView:
    id: str
    status: str
    x: float
    y: float
    theta: float
    radius: float
    carrying: bool = False


@dataclass
class TruthView:
    """What a picture of the true state needs (from a World, or from haa-sim's ground-truth API)."""

    time: float
    avatars: list[AvatarView] = field(default_factory=list)
    collectables: list[CollectableState] = field(default_factory=list)


def truth_of(world: World) -> TruthView:
    avatars = [
        AvatarView(a.id, a.status, *a.pose, a.spec.radius, bool(a.carrying))
        for a in world.avatars.values()
        if a.status != "retired"
    ]
    return TruthView(world.time, avatars, world.collectable_states())


BGR = {
    "floor": (236, 240, 244),
    OUTER_WALL: (90, 90, 90),
    WALL: (120, 120, 120),
    OBSTACLE: (158, 108, 72),
    POST: (58, 196, 222),
    "landmark": (30, 30, 30),
    "region": (150, 220, 150),
    "collectable": (30, 36, 214),
    "start": (200, 120, 40),
    "avatar": (70, 150, 46),
    "crashed": (40, 40, 200),
    "text": (20, 20, 20),
}
MARGIN = 40
TITLE = 30


def render_topdown(
    arena: Arena, truth: TruthView | World | None = None, scale: float | None = None, labels: bool = True
) -> np.ndarray:
    """BGR image of the arena (and of the true state's avatars and collectables when given)."""
    from haa.sim.world import World

    world = truth_of(truth) if isinstance(truth, World) else truth
    if scale is None:
        scale = max(20.0, min(120.0, 900.0 / max(arena.width, arena.height)))
    Wpx = math.ceil(arena.width * scale) + 2 * MARGIN
    Hpx = math.ceil(arena.height * scale) + 2 * MARGIN + TITLE
    img = np.full((Hpx, Wpx, 3), 255, dtype=np.uint8)

    def px(x: float, y: float) -> tuple[int, int]:
        return (round(MARGIN + x * scale), round(TITLE + MARGIN + (arena.height - y) * scale))

    def poly(points: list[tuple[float, float]]) -> np.ndarray:
        return np.array([px(x, y) for x, y in points], dtype=np.int32)

    cv2.rectangle(img, px(0, arena.height), px(arena.width, 0), BGR["floor"], -1)
    for rid, r in arena.regions.items():
        cv2.fillPoly(img, [poly(r)], BGR["region"])
        if labels:
            cx = sum(p[0] for p in r) / len(r)
            cy = sum(p[1] for p in r) / len(r)
            _text(img, rid, px(cx, cy), 0.4, center=True)
    for s in arena.structures:
        cv2.fillPoly(img, [poly(s.polygon)], BGR[s.kind], lineType=cv2.LINE_AA)
    fs = 0.3 if scale < 60 else 0.35
    for m in arena.markers:
        nx, ny = m.normal
        ux, uy = -ny, nx
        h = m.plate / 2
        q = [(m.center[0] + ux * h, m.center[1] + uy * h), (m.center[0] - ux * h, m.center[1] - uy * h)]
        q += [(q[1][0] + nx * 0.06, q[1][1] + ny * 0.06), (q[0][0] + nx * 0.06, q[0][1] + ny * 0.06)]
        cv2.fillPoly(img, [poly(q)], BGR["landmark"])
        if labels and m.id != arena.congregation_id:
            off = 0.06 + 10 / scale
            _text(img, str(m.id), px(m.center[0] + nx * off, m.center[1] + ny * off), fs, center=True)
    if arena.congregation_id is not None and labels:
        cx, cy = arena.landmarks[arena.congregation_id]
        _text(img, f"congregation ({arena.congregation_id})", px(cx, cy - 0.25 - 12 / scale), fs, center=True)
    for i, (x, y, th) in enumerate(arena.start_poses):
        a, b = px(x, y), px(x + 0.2 * math.cos(th), y + 0.2 * math.sin(th))
        cv2.circle(img, a, max(2, int(0.05 * scale)), BGR["start"], 1, cv2.LINE_AA)
        cv2.arrowedLine(img, a, b, BGR["start"], 1, cv2.LINE_AA, tipLength=0.4)
        if labels:
            _text(img, str(i), px(x - 0.12, y - 0.12), fs, colour=BGR["start"])
    if world is None:
        for cid, (x, y) in arena.collectables.items():
            cv2.circle(img, px(x, y), max(2, int(0.05 * scale)), BGR["collectable"], -1, cv2.LINE_AA)
            if labels:
                _text(img, cid, px(x + 0.08, y + 0.08), fs, colour=BGR["collectable"])
    else:
        for c in world.collectables:
            if c.state == "deposited":
                colour = (60, 120, 60)
            else:
                colour = BGR["collectable"]
            if c.state != "carried":
                cv2.circle(img, px(c.x, c.y), max(2, int(0.05 * scale)), colour, -1, cv2.LINE_AA)
        for av in world.avatars:
            if av.status == "retired":
                continue
            x, y, th = av.x, av.y, av.theta
            colour = BGR["crashed"] if av.status == "crashed" else BGR["avatar"]
            r = max(3, int(av.radius * scale))
            cv2.circle(img, px(x, y), r, colour, 2, cv2.LINE_AA)
            tip = px(x + av.radius * math.cos(th), y + av.radius * math.sin(th))
            cv2.line(img, px(x, y), tip, colour, 2, cv2.LINE_AA)
            if av.carrying:
                cv2.circle(img, px(x, y), max(2, r // 3), BGR["collectable"], -1, cv2.LINE_AA)
            if labels:
                _text(img, av.id, px(x + av.radius, y + av.radius), fs, colour=colour)
    # scale bar
    x0, y0 = MARGIN, Hpx - 12
    cv2.line(img, (x0, y0), (x0 + int(scale), y0), BGR["text"], 2)
    _text(img, "1 m", (x0 + int(scale) + 6, y0 + 4), 0.4)
    n_lm = len(arena.landmarks) - (arena.congregation_id is not None)
    title = (
        f"{arena.name}: {arena.width:g} x {arena.height:g} m, {len(arena.obstacles)} obstacles, {n_lm} landmarks"
        + (", congregation point" if arena.congregation_id is not None else "")
        + (f", {len(arena.collectables)} collectables, {len(arena.regions)} regions" if arena.collectables else "")
        + f", explorable {explorable_area(arena):.1f} m2"
    )
    if world is not None:
        title += f"  t={world.time:.1f} s"
    _text(img, title, (8, 20), 0.45)
    return img


def _text(
    img: np.ndarray,
    s: str,
    at: tuple[int, int],
    size: float,
    colour: tuple[int, int, int] = BGR["text"],
    center: bool = False,
) -> None:
    x, y = at
    if center:
        (w, h), _ = cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, size, 1)
        x, y = x - w // 2, y + h // 2
    cv2.putText(img, s, (x, y), cv2.FONT_HERSHEY_SIMPLEX, size, colour, 1, cv2.LINE_AA)


def save_png(img: np.ndarray, path: str | Path) -> Path:
    p = Path(path)
    if not cv2.imwrite(str(p), img):
        raise OSError(f"cannot write {p}")
    return p
