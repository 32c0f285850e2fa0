"""What the dashboard knows about the DDB, built from one host's mirror stream (no I/O here).

`DdbMirror` is the dashboard's own replica of the DDB (thesis AgentMirror, Table 6.1-1: "an up-to-date copy of
the DDB ... then ... each new DDB update"): `apply(event)` takes one `MirrorEvent` of a host's `Mirror` stream
(a snapshot, an applied batch or a view change) and returns the keys it changed, applying batches with the
same deterministic `haa.core.ddb.ddb.Ddb` the hosts run — so the copy is exactly the host's replica at that seq.

The page's views are plain JSON (or base64 bytes) computed from the replica:

* `map_view` — the published occupancy grid `slam/map` (docs/team.md) as uint8 cells, 0..254 = p(occupied)
  × 254, row 0 the lowest y, with the grid's geometry;
* `overlay_view` — what is drawn over it: estimated poses and their std (`slam/est/<avatar>`), the estimated
  path of each avatar (the poses seen so far, kept here), landmark estimates (`slam/landmarks`), targets
  (`targets/<avatar>`), assignments, planned paths where an agent publishes them (`paths/<avatar>`: a
  `{"points": [[x, y], ...]}`; no agent of the team does today: the planner sends its path to its avatar as a
  message), the particle clouds of the latest SLAM checkpoint (`slam/ckpt/*`, see `checkpoint_particles`),
  the mission status and the newest transcript lines (`mission/events`);
* `ddb_entries` / `object_summary` — the DDB browser: every key with type, size and version, and a readable
  summary of one object (JSON pretty-printed and cut, a log's last items, a map's geometry, a checkpoint's
  parts);
* `avatar_of` — the DDB browser's "by parentage" grouping: an object that belongs to an avatar (its sensor
  readings, estimate, target, bids ...) is shown under that avatar (thesis §6.1.4 item 4: "sensor and particle
  filter objects are placed under their corresponding avatar object").
"""

from __future__ import annotations

import base64
import json
import math
from collections import deque
from typing import Any

import numpy as np

from haa.core.ddb.ddb import Ddb
from haa.core.ddb.objects import DdbError, DdbObject
from haa.pb import control_pb2 as cpb
from haa.pb import ddb_pb2

#: DDB keys and prefixes of docs/team.md that the map overlay is drawn from
K_MAP = "slam/map"
OVERLAY_PREFIXES = ("slam/est/", "slam/estimates", "slam/landmarks", "targets/", "assign/", "avatars/",
                    "mission/status", "mission/params", "paths/", "slam/ckpt/", "mission/events")
#: estimated path points kept per avatar (a point is added when the estimate moved by at least PATH_STEP_M)
PATH_POINTS = 4000
PATH_STEP_M = 0.02
#: particles sent per avatar (a checkpoint holds a few hundred per avatar; every k-th is sent)
MAX_PARTICLES = 300
#: transcript lines sent with the overlay
TRANSCRIPT_LINES = 40
#: a JSON object summary is cut after this many characters
SUMMARY_CHARS = 6000


def batch_keys(payload: bytes) -> set[str]:
    """The keys a `DdbBatch` payload writes (empty if it does not decode)."""
    try:
        batch = ddb_pb2.DdbBatch.FromString(payload)
    except Exception:
        return set()
    out = set()
    for op in batch.ops:
        kind = op.WhichOneof("op")
        if kind:
            out.add(getattr(op, kind).key)
    return out


class DdbMirror:
    """A replica of the DDB fed by `MirrorEvent`s; remembers the estimated path of every avatar."""

    def __init__(self) -> None:
        self.ddb: Ddb | None = None
        self.view: dict[str, Any] = {}  # the latest view change: members, leader, view
        self.snapshots = 0
        self.batches = 0
        self.paths: dict[str, deque[tuple[float, float]]] = {}
        self._particles_key: tuple[Any, ...] | None = None
        self._particles: dict[str, Any] = {}

    @property
    def seq(self) -> int:
        return self.ddb.seq if self.ddb is not None else 0

    def apply(self, ev: cpb.MirrorEvent) -> set[str] | None:
        """Apply one mirror event; the keys it changed, None for "everything" (a snapshot replaced the replica).
        A batch that does not follow the replica's seq raises `DdbError` (the caller resubscribes)."""
        kind = ev.WhichOneof("event")
        if kind == "snapshot":
            self.ddb = Ddb.restore(ev.snapshot.SerializeToString(), mirror_capacity=0)
            self.snapshots += 1
            self._track_paths(None)
            return None
        if kind == "batch":
            if self.ddb is None:
                raise DdbError("a batch before the first snapshot")
            if ev.batch.ddb_seq != self.ddb.seq + 1:
                raise DdbError(f"batch #{ev.batch.ddb_seq} after #{self.ddb.seq}")
            self.ddb.apply(ev.batch.payload)
            self.batches += 1
            keys = batch_keys(ev.batch.payload)
            self._track_paths(keys)
            return keys
        if kind == "view":
            v = ev.view
            self.view = {"view": v.view, "leader": v.leader, "members": [m.name for m in v.members],
                         "added": list(v.added), "removed": list(v.removed)}
            return set()
        return set()

    # ------------------------------------------------------------------ reading
    def get(self, key: str) -> DdbObject | None:
        return self.ddb.get(key) if self.ddb is not None else None

    def json(self, key: str) -> Any:
        o = self.get(key)
        if o is None or o.type_name != "json":
            return None
        try:
            return o.value
        except ValueError:
            return None

    def json_under(self, prefix: str) -> dict[str, Any]:
        """{rest of the key: parsed value} of the JSON objects under `prefix`."""
        if self.ddb is None:
            return {}
        return {o.key[len(prefix):]: o.value for o in self.ddb.items(prefix) if o.type_name == "json"}

    def _track_paths(self, keys: set[str] | None) -> None:
        if self.ddb is None:
            return
        names = [k for k in keys if k.startswith("slam/est/")] if keys is not None else self.ddb.ls("slam/est/")
        for k in names:
            est = self.json(k)
            if not isinstance(est, dict):
                continue
            try:
                x, y = float(est["x"]), float(est["y"])
            except (KeyError, TypeError, ValueError):
                continue
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            path = self.paths.setdefault(k[len("slam/est/"):], deque(maxlen=PATH_POINTS))
            if not path or math.hypot(x - path[-1][0], y - path[-1][1]) >= PATH_STEP_M:
                path.append((round(x, 3), round(y, 3)))

    # ------------------------------------------------------------------ views
    def map_view(self) -> dict[str, Any] | None:
        """The published occupancy grid for the page, or None (no map yet, or one that does not decode)."""
        o = self.get(K_MAP)
        if o is None or o.type_name != "blob":
            return None
        return map_view(o.value, o.version)

    def overlay_view(self) -> dict[str, Any]:
        est = {a: e for a, e in self.json_under("slam/est/").items() if isinstance(e, dict)}
        lms = self.json("slam/landmarks")
        events = self.get("mission/events")
        lines: list[Any] = []
        if events is not None and events.type_name == "log":
            for item in list(events.value["items"])[-TRANSCRIPT_LINES:]:
                try:
                    lines.append(json.loads(item))
                except ValueError:
                    lines.append({"text": item[:200].decode("utf-8", "replace")})
        planned = {a: p.get("points") for a, p in self.json_under("paths/").items()
                   if isinstance(p, dict) and isinstance(p.get("points"), list)}
        return {
            "seq": self.seq,
            "estimates": est,
            "paths": {a: list(p) for a, p in self.paths.items()},
            "planned": planned,
            "landmarks": lms if isinstance(lms, dict) else {},
            "targets": {a: t for a, t in self.json_under("targets/").items() if isinstance(t, dict)},
            "assign": self.json_under("assign/"),
            "avatars": self.json_under("avatars/"),
            "status": self.json("mission/status"),
            "mission": _mission_summary(self.json("mission/params")),
            "particles": self.particles(),
            "transcript": lines,
        }

    def particles(self) -> dict[str, Any]:
        """{avatar: {"t": checkpoint index, "points": [[x, y], ...]}} from the latest complete checkpoint."""
        if self.ddb is None:
            return {}
        meta = self.get("slam/ckpt/meta")
        if meta is None:
            return {}
        key = (meta.version,)
        if key != self._particles_key:
            self._particles_key = key
            blobs = {o.key[len("slam/ckpt/"):]: o.value for o in self.ddb.items("slam/ckpt/") if o.type_name == "blob"}
            try:
                self._particles = checkpoint_particles(blobs)
            except Exception:  # a checkpoint half written or of another format: no particles, not an error
                self._particles = {}
        return self._particles

    def ddb_entries(self) -> list[list[Any]]:
        """[key, type, size, version] of every object, in key order."""
        if self.ddb is None:
            return []
        return [[o.key, o.type_name, o.size, o.version] for o in self.ddb.items("")]

    def entry(self, key: str) -> list[Any] | None:
        o = self.get(key)
        return None if o is None else [o.key, o.type_name, o.size, o.version]

    def object_summary(self, key: str) -> dict[str, Any]:
        o = self.get(key)
        if o is None:
            return {"key": key, "missing": True}
        return object_summary(o)


# ---------------------------------------------------------------------------------------------- pure helpers


def map_view(data: bytes, version: int = 0) -> dict[str, Any] | None:
    """An encoded `slam/map` (haa.slam.replica.encode_map) -> {w, h, res, x0, y0, version, cells (base64 uint8,
    row 0 = lowest y, 0..254 = p × 254)}; None if it does not decode."""
    try:
        from haa.slam.replica import MapError, decode_map
    except ImportError:  # pragma: no cover - the SLAM package is part of haa
        return None
    try:
        spec, prob = decode_map(data)
    except MapError:
        return None
    q = np.rint(np.clip(prob, 0.0, 1.0) * 254.0).astype(np.uint8)
    rows, cols = q.shape
    return {"w": cols, "h": rows, "res": spec.resolution, "x0": spec.x0, "y0": spec.y0, "version": version,
            "cells": base64.b64encode(np.ascontiguousarray(q).tobytes()).decode()}


def checkpoint_particles(blobs: dict[str, bytes], limit: int = MAX_PARTICLES) -> dict[str, Any]:
    """The current particle states of every filter of a SLAM checkpoint (haa.slam.replica: blob `meta` lists
    the parts; `filter-<i>` holds a filter's `current` states, x, y, theta per particle, and its avatar's name),
    at most `limit` per avatar."""
    from haa.slam.replica import _unpack  # the checkpoint's own blob reader (no public one reads a single part)

    meta = json.loads(blobs["meta"])
    out: dict[str, Any] = {}
    for name, (nparts, _size, _crc) in meta["parts"].items():
        if not name.startswith("filter-"):
            continue
        data = b"".join(bytes(blobs[name if k == 0 else f"{name}.{k}"]) for k in range(nparts))
        head, arrays = _unpack(data, name)
        cur = np.asarray(arrays["current"], dtype=np.float64)
        if cur.ndim != 2 or cur.shape[1] < 2:
            continue
        step = max(1, math.ceil(len(cur) / limit))
        pts = np.round(cur[::step, :2], 3)
        out[str(head.get("name", name))] = {"index": meta.get("next_index"), "points": pts.tolist()}
    return out


def _mission_summary(params: Any) -> dict[str, Any] | None:
    if not isinstance(params, dict):
        return None
    m = params.get("mission")
    if not isinstance(m, dict):
        m = {}
    return {"name": m.get("name"), "scenario": m.get("scenario"), "arena": m.get("arena"),
            "speed": params.get("speed"), "sim": params.get("sim"), "map_resolution": m.get("map_resolution")}


def avatar_of(key: str, avatars: set[str]) -> str:
    """The avatar an object belongs to ('' for none): the first path component after the first one that names a
    registered avatar (`slam/raw/s1/00000017` -> s1, `avatars/s1` -> s1, `bids/s2/<id>` -> s2)."""
    parts = key.split("/")
    for p in parts[1:]:
        if p in avatars:
            return p
    return ""


def object_summary(o: DdbObject) -> dict[str, Any]:
    """A readable summary of one DDB object for the DDB browser."""
    out: dict[str, Any] = {"key": o.key, "type": o.type_name, "size": o.size, "version": o.version,
                           "created": o.created}
    t = o.type_name
    if t == "json":
        text = json.dumps(o.value, indent=1, sort_keys=True)
        out["text"] = text if len(text) <= SUMMARY_CHARS else text[:SUMMARY_CHARS] + "\n..."
    elif t == "counter":
        out["text"] = str(o.value)
    elif t == "log":
        v = o.value
        items = list(v["items"])
        out["text"] = f"log: items {v['first']}..{v['first'] + len(items) - 1} ({len(items)} kept)"
        tail = []
        for it in items[-8:]:
            try:
                tail.append(json.dumps(json.loads(it), sort_keys=True)[:300])
            except ValueError:
                tail.append(f"{len(it)} bytes: {bytes(it[:24]).hex()}...")
        out["items"] = tail
    elif t == "list":
        items = list(o.value)
        out["text"] = f"list of {len(items)} items"
    else:  # blob
        data = o.value
        mv = map_view(data, o.version) if o.key == K_MAP else None
        if mv is not None:
            cells = np.frombuffer(base64.b64decode(mv["cells"]), dtype=np.uint8)
            known = float(np.mean(np.abs(cells.astype(np.int16) - 127) > 24)) if cells.size else 0.0
            out["text"] = (f"occupancy grid {mv['w']} x {mv['h']} cells of {mv['res']} m from ({mv['x0']}, "
                           f"{mv['y0']}); {100 * known:.1f} % of the cells known (p < 0.4 or p > 0.6)")
        elif o.key == "slam/ckpt/meta":
            try:
                meta = json.loads(data)
                out["text"] = (f"SLAM checkpoint at log index {meta.get('next_index')}: parts "
                               + ", ".join(f"{k} ({v[1]} B)" for k, v in meta.get("parts", {}).items()))
            except (ValueError, AttributeError):
                out["text"] = f"{len(data)} bytes"
        else:
            try:
                text = bytes(data).decode("utf-8")
                out["text"] = text[:SUMMARY_CHARS] if text.isprintable() or "\n" in text else f"{len(data)} bytes"
            except UnicodeDecodeError:
                out["text"] = f"{len(data)} bytes: {bytes(data[:32]).hex()}..."
    return out
