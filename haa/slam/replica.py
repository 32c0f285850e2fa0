"""The team's SLAM state rebuilt from the DDB's event log (docs/slam.md "The SLAM state in the DDB").

`SlamReplica(grid, config, seed)` holds a `haa.slam.system.SlamSystem` and applies the items of the log
`slam/log` (haa.slam.events) in index order: `apply(index, data)`. The state is a deterministic function
of the items applied — nothing else moves it (no clock, no estimate taken between events, no dictionary
or set order that depends on the process) — so two replicas that applied the same items are bit-identical
(`state_digest()`), and a replica restored from a checkpoint taken after k items, then given items k..,
is bit-identical to one that applied everything:

* `checkpoint() -> dict[str, bytes]`: the state as a few blobs, each at most `BLOB_LIMIT` (1 MiB, the DDB's
  largest value): `meta` (JSON: format, next index, grid, seed, configuration, avatars, counters, and which
  blobs make the checkpoint with their CRC-32), `grid`, `landmarks`, `collectables` (the identified
  collectables, haa.slam.collectables), `models` (the sensor models' template caches, see below) and
  `filter-<i>` per avatar (its history blocks, its current float64 states and its
  numpy Generator state, so that replay after a restore draws the same noise); a component larger than a
  blob is split into `<name>`, `<name>.1`, `<name>.2`, .... No pickle: arrays are raw little-endian bytes
  with a dtype/shape list in a small JSON header, the whole zlib-compressed (level 1); particle histories
  pass an exactly invertible XOR-and-byte-shuffle filter first (`_xor_shuffle`).
* `SlamReplica.restore(blobs)`: the replica again. Blobs not listed by `meta` are ignored (a previous
  checkpoint's leftovers); a missing or corrupted one raises `CheckpointError`.

Events are applied deterministically whatever they carry: a malformed item, an event for an unknown avatar,
a prediction out of time order, a reading the history cannot serve (`TooOld`, `NotYetPredicted`) is counted
in `counts` and skipped — the same on every replica; an `AddAvatar` of an existing avatar is a no-op.
An index below the next expected one was already applied (skipped, not counted); a gap raises `LogGap`.

**Bounded memory.** The filters keep `horizon` seconds of history (`DEFAULT_HORIZON` = 30 s of simulated
time when the configuration's is infinite): in a mission readings are processed within seconds (mean
delays of 0.5-1.2 s constrained, docs/slam.md), and one older than 30 s is rejected as `TooOld` — FIFO
under constraint reached 34 s mean delays and lost the avatars; applying such readings does not help. Every
`Request` event prunes all filters (deterministically: it is in the log), so a filter holds at most two
horizons of predictions (a block's rows are trimmed once half are older than the horizon) and the closed
blocks within one horizon. The AP-5.2 list of observations per weight update is folded into a counter
(`obs_in_updates`).

**Why the template caches are state.** The sonar and co-occupancy models cache belief templates under a
*rounded* key, but a template is built from the exact arguments of the first reading that missed the cache;
a later reading with the same key uses that template. So the cache's content (and its LRU order: the sonar
cache holds 4,096 templates) changes results in the last bits, and a replica restored with an empty cache
would differ. The checkpoint stores the arguments each cached template was built from (`Template.origin`),
in LRU order, and the restore rebuilds the caches from them.

`estimate(name)` (a read-only event (d): `ParticleFilter.peek`) and `encode_map()` / `decode_map(data)` (the
published `slam/map`: uint8 probabilities, 0..254 ↦ p = q/254 so that 0.5 is exact, zlib-compressed, with a
JSON header) are what SupervisorSLAM publishes between events; neither changes the state.

Determinism holds for one build of numpy and one CPU (SIMD exp/log and BLAS dot products may round
differently on other hardware). Only one replica is authoritative — SupervisorSLAM's, which writes the
checkpoints — so a backup restored on another host continues from the committed checkpoint and log, which
is what matters for losing no committed state.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from haa.slam.collectables import Collectable
from haa.slam.events import (
    AddAvatar,
    EventError,
    Observe,
    Predict,
    RemoveAvatar,
    Request,
    SlamEvent,
    decode,
)
from haa.slam.filter import Block, NotYetPredicted, ParticleFilter, TooOld
from haa.slam.grid import GridSpec
from haa.slam.motion import DriftSpec, wrap_angle
from haa.slam.sensors import (
    Contribution,
    CooccupancyModel,
    FloorModel,
    Landmark,
    LandmarkModel,
    SonarEcho,
    SonarModel,
)
from haa.slam.system import SlamConfig, SlamSystem

DEFAULT_HORIZON = 30.0  # s of simulated time (see the module docstring)
BLOB_LIMIT = 1 << 20  # bytes: the DDB's largest value (haa.core.ddb.objects.MAX_VALUE_BYTES)
FORMAT = 1
_MAGIC = b"HAAS"
MAP_LEVELS = 254  # uint8 0..254 ↦ p = q / 254 (0.5 is exactly 127)


class LogGap(ValueError):
    """`apply` was given an index beyond the next expected one (an item is missing)."""


class CheckpointError(ValueError):
    """The blobs are not a complete, intact checkpoint; the message says which part and why."""


class MapError(ValueError):
    """The bytes are not an encoded map."""


@dataclass(frozen=True)
class ApplyResult:
    """What applying one log item did."""

    index: int
    kind: str  # the event's kind (haa.slam.events: add_avatar, predict, ...), "malformed", or "" (duplicate)
    avatar: str
    outcome: str  # "applied" | "skipped" | "noop" | "duplicate"
    reason: str = ""  # why it was skipped, one line
    resampled: bool = False  # a request that resampled
    n_eff: float = math.nan  # a request's n_eff before resampling


class PoseEstimate(NamedTuple):
    """An avatar's weighted estimate at its newest prediction: std = (σx, σy, σθ) of the particles."""

    t: float
    x: float
    y: float
    theta: float
    std: tuple[float, float, float]


# ----- blobs: small JSON header + raw arrays, zlib ---------------------------------------------------------


_UINT = {2: np.uint16, 4: np.uint32, 8: np.uint64}
_MAX_BODY = 256 << 20  # bytes a blob may decompress to


def _xor_shuffle(a: np.ndarray) -> bytes:
    """Exactly invertible filter for particle states: each row XOR the previous one (as unsigned integers:
    a particle's coordinates change in their low bits from prediction to prediction), then the bytes grouped
    by significance — zlib then compresses the history ~20 % better than the raw floats."""
    u = a.reshape(a.shape[0], -1).view(_UINT[a.dtype.itemsize])
    x = u.copy()
    x[1:] ^= u[:-1]
    return x.view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


def _xor_unshuffle(data: bytes, dtype: np.dtype, shape: list[int]) -> np.ndarray:
    b = np.frombuffer(data, dtype=np.uint8).reshape(dtype.itemsize, -1).T.copy()
    x = b.view(_UINT[dtype.itemsize]).reshape(shape[0], -1)
    u = np.bitwise_xor.accumulate(x, axis=0)
    return u.view(dtype).reshape(shape)


def _pack(header: dict[str, Any], arrays: list[tuple[str, np.ndarray]], shuffle: frozenset[str] = frozenset()) -> bytes:
    """Blob: magic, format byte, zlib(u32 header length, JSON header with the arrays' names, little-endian
    dtypes, shapes and codecs, then the arrays' bytes). Arrays named in `shuffle` are XOR-shuffled."""
    specs = []
    chunks = []
    for name, a in arrays:
        a = np.ascontiguousarray(a)
        a = a.astype(a.dtype.newbyteorder("<"), copy=False) if a.dtype.byteorder == ">" else a
        codec = "xs" if name in shuffle and a.ndim >= 1 and a.shape[0] > 1 and a.dtype.itemsize in _UINT else ""
        specs.append([name, a.dtype.str, list(a.shape), codec])
        chunks.append(_xor_shuffle(a) if codec else a.tobytes())
    head = json.dumps({**header, "arrays": specs}, separators=(",", ":"), sort_keys=True).encode()
    body = struct.pack("<I", len(head)) + head + b"".join(chunks)
    return _MAGIC + bytes([FORMAT]) + zlib.compress(body, 1)


def _unpack(data: bytes, what: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    if not isinstance(data, (bytes, bytearray, memoryview)) or bytes(data[:4]) != _MAGIC or len(data) < 6:
        raise CheckpointError(f"{what}: not a replica blob (no {_MAGIC!r} header)")
    if data[4] != FORMAT:
        raise CheckpointError(f"{what}: format {data[4]}, this code reads {FORMAT}")
    try:
        d = zlib.decompressobj()
        body = d.decompress(bytes(data[5:]), _MAX_BODY)
        if d.unconsumed_tail or not d.eof:
            raise ValueError("truncated, or larger than 256 MiB decompressed")
        (n,) = struct.unpack_from("<I", body)
        header = json.loads(body[4 : 4 + n])
        arrays: dict[str, np.ndarray] = {}
        off = 4 + n
        for name, dt, shape, codec in header.pop("arrays"):
            dtype = np.dtype(dt)
            if dtype.hasobject or not all(isinstance(k, int) and k >= 0 for k in shape):
                raise ValueError(f"array {name}: bad dtype or shape")
            count = math.prod(shape)
            size = dtype.itemsize * count
            if off + size > len(body):
                raise ValueError(f"array {name}: truncated")
            if codec == "xs":
                arrays[name] = _xor_unshuffle(body[off : off + size], dtype, shape)
            elif codec == "":
                arrays[name] = np.frombuffer(body, dtype=dtype, count=count, offset=off).reshape(shape).copy()
            else:
                raise ValueError(f"array {name}: unknown codec {codec!r}")
            off += size
        if off != len(body):
            raise ValueError(f"{len(body) - off} bytes after the last array")
    except CheckpointError:
        raise
    except (zlib.error, struct.error, ValueError, TypeError, KeyError) as e:
        raise CheckpointError(f"{what}: {e}") from None
    return header, arrays


def _crc(data: bytes) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


# ----- configuration as JSON (fresh model instances: a replica never shares template caches) -----------------


def _model_fields(m: object) -> dict[str, Any]:
    return {f.name: getattr(m, f.name) for f in dataclasses.fields(m) if not f.name.startswith("_")}  # type: ignore[arg-type]


def config_to_json(c: SlamConfig) -> dict[str, Any]:
    """A SlamConfig as JSON-able data (infinities as the strings "inf"/"-inf")."""

    def enc(v: Any) -> Any:
        if isinstance(v, float) and math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if isinstance(v, tuple):
            return [enc(x) for x in v]
        return v

    out: dict[str, Any] = {}
    for f in dataclasses.fields(c):
        v = getattr(c, f.name)
        out[f.name] = {k: enc(x) for k, x in _model_fields(v).items()} if dataclasses.is_dataclass(v) else enc(v)
    return out


def config_from_json(d: Mapping[str, Any]) -> SlamConfig:
    def dec(v: Any) -> Any:
        if v == "inf":
            return math.inf
        if v == "-inf":
            return -math.inf
        return v

    models = {"sonar": SonarModel, "landmark": LandmarkModel, "cooccupancy": CooccupancyModel, "floor": FloorModel}
    kw: dict[str, Any] = {}
    for k, v in d.items():
        if k in models:
            kw[k] = models[k](**{a: dec(b) for a, b in v.items()})
        elif k == "initial_spread":
            kw[k] = tuple(dec(x) for x in v)
        else:
            kw[k] = dec(v)
    return SlamConfig(**kw)


def _grid_json(g: GridSpec) -> dict[str, float]:
    return {"width": g.width, "height": g.height, "resolution": g.resolution, "x0": g.x0, "y0": g.y0}


def _avatar_json(ev: AddAvatar) -> dict[str, Any]:
    d = ev.drift
    return {
        "name": ev.name,
        "kind": ev.kind,
        "pose": list(ev.pose),
        "t0": ev.t0,
        "drift": [d.linear_m_per_10m, d.angular_rad_per_10rot, d.inflate],
        "radius": ev.radius,
    }


def _avatar_from_json(d: Mapping[str, Any]) -> AddAvatar:
    return AddAvatar(d["name"], d["kind"], tuple(d["pose"]), d["t0"], DriftSpec(*d["drift"]), d["radius"])


# the attributes each checkpoint knows; `checkpoint()` refuses an object with others (a field added to the
# library later must be added to the checkpoint, or restore would silently lose it)
_FILTER_ATTRS = frozenset(
    {
        "n", "name", "horizon", "forward_propagation", "rng", "_dtype", "_current", "blocks", "_starts", "marker",
        "corrections", "weight_updates", "weight_requests", "resamples", "pending_obs", "obs_per_update",
    }
)  # fmt: skip
_SYSTEM_ATTRS = frozenset({"config", "grid", "landmarks", "collectables", "filters", "seed", "processed"})
_GRID_ATTRS = frozenset(
    {"spec", "map_particles", "rows", "cols", "clamp", "prow", "_lo", "_p", "_border", "updates", "_df", "_df_version"}
)
_LANDMARKS_ATTRS = frozenset({"window", "gate", "gated", "landmarks", "_n"})
_COLLECTABLES_ATTRS = frozenset({"gate", "limit", "items", "next_id", "sightings", "full"})
_COLLECTABLE_FIELDS = ("id", "sw", "swx", "swy", "n", "t_first", "t_last")


def _check_attrs(obj: object, known: frozenset[str], what: str) -> None:
    extra = set(vars(obj)) - known
    if extra:
        raise CheckpointError(f"{what}: attributes the checkpoint does not know: {sorted(extra)}")


# ----- the replica ------------------------------------------------------------------------------------------


class SlamReplica:
    """The SLAM state of the team as a function of the event log (see the module docstring)."""

    def __init__(self, grid: GridSpec, config: SlamConfig | None = None, seed: int = 0) -> None:
        cj = config_to_json(config if config is not None else SlamConfig(n_particles=100))
        if cj["horizon"] == "inf":
            cj["horizon"] = DEFAULT_HORIZON
        self.grid_spec = grid
        self.seed = int(seed)
        self.system = SlamSystem(grid, config_from_json(cj), seed=self.seed)  # sets the models' resolution
        self.config = self.system.config
        self.next_index = 0
        self.avatars: dict[str, AddAvatar] = {}  # the current avatars, in filter order
        self.added = 0  # avatars ever added (their filters' seeds)
        self.counts: dict[str, int] = {}  # "<kind>.<outcome or reason>" -> items
        self.obs_in_updates = 0  # AP-5.2: observations folded into weight updates (ParticleFilter.obs_per_update)

    # ----- applying the log ---------------------------------------------------------------------------------
    def _count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def apply(self, index: int, data: bytes) -> ApplyResult:
        """Apply log item `index` (the next expected one; lower ones are skipped as applied, a gap raises)."""
        if index < self.next_index:
            return ApplyResult(index, "", "", "duplicate")
        if index > self.next_index:
            raise LogGap(f"index {index}: the next expected log item is {self.next_index}")
        self.next_index = index + 1
        try:
            ev = decode(data)
        except EventError as e:
            self._count("malformed")
            return ApplyResult(index, "malformed", "", "skipped", e.reason)
        return self.apply_event(index, ev)

    def apply_event(self, index: int, ev: SlamEvent) -> ApplyResult:
        """Apply an already decoded event (`apply` without the index bookkeeping)."""
        kind = ev.KIND
        if isinstance(ev, AddAvatar):
            if ev.name in self.system.filters:
                self._count("add_avatar.noop")
                return ApplyResult(index, kind, ev.name, "noop", "already has a filter")
            self.system.add_avatar(ev.name, ev.pose, ev.t0, seed=self.seed * 1009 + self.added)
            self.added += 1
            self.avatars[ev.name] = ev
            return self._done(index, kind, ev.name)
        name = ev.name if isinstance(ev, RemoveAvatar) else ev.avatar
        pf = self.system.filters.get(name)
        if pf is None:
            return self._skip(index, kind, name, "unknown_avatar", f"no filter for avatar {name!r}")
        try:
            if isinstance(ev, Predict):
                if not ev.prediction.t > pf.time:
                    return self._skip(index, kind, name, "out_of_order", f"t={ev.prediction.t} not after t={pf.time}")
                pf.predict(ev.prediction)
            elif isinstance(ev, Observe):
                self.system.process(ev.reading)
            elif isinstance(ev, Request):
                est, resampled = self.system.request(name)
                self._after_request()
                self._count("request.applied")
                if resampled:
                    self._count("request.resampled")
                return ApplyResult(index, kind, name, "applied", "", resampled, est.n_eff)
            else:
                del self.system.filters[name]
                del self.avatars[name]
        except TooOld as e:
            return self._skip(index, kind, name, "too_old", e.reason)
        except NotYetPredicted as e:
            return self._skip(index, kind, name, "not_yet_predicted", e.reason)
        except MemoryError:
            raise
        except Exception as e:  # deterministic too: the same code fails the same way on every replica
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            return self._skip(index, kind, name, "failed", msg)
        return self._done(index, kind, name)

    def _done(self, index: int, kind: str, name: str) -> ApplyResult:
        self._count(f"{kind}.applied")
        return ApplyResult(index, kind, name, "applied")

    def _skip(self, index: int, kind: str, name: str, why: str, reason: str) -> ApplyResult:
        self._count(f"{kind}.{why}")
        return ApplyResult(index, kind, name, "skipped", reason)

    def _after_request(self) -> None:
        """Pruning and the AP-5.2 list, on every request (so at the same items on every replica)."""
        for pf in self.system.filters.values():
            pf.prune()
            if pf.obs_per_update:
                self.obs_in_updates += sum(pf.obs_per_update)
                pf.obs_per_update.clear()

    # ----- reading the state (changes nothing) ------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return list(self.system.filters)

    def estimate(self, name: str) -> PoseEstimate:
        """Avatar `name`'s weighted estimate at its newest prediction (KeyError naming it if unknown)."""
        pf = self.system.filter(name)
        est = pf.peek()
        states = pf.last.states_at(est.t)
        w = est.weights
        x, y, th = (float(v) for v in est.pose)
        sx = math.sqrt(max(float(w @ (states[:, 0] - x) ** 2), 0.0))
        sy = math.sqrt(max(float(w @ (states[:, 1] - y) ** 2), 0.0))
        st = math.sqrt(max(float(w @ np.asarray(wrap_angle(states[:, 2] - th)) ** 2), 0.0))
        return PoseEstimate(est.t, x, y, th, (sx, sy, st))

    def encode_map(self) -> bytes:
        """The occupancy grid as `slam/map` (see `encode_map`)."""
        return encode_map(self.grid_spec, self.system.grid.prob())

    def memory_bytes(self) -> int:
        """Bytes held by the state's arrays: histories, grid, landmark map, template caches."""
        s = self.system
        g = s.grid
        n = s.memory_bytes() + g._lo.nbytes + g._p.nbytes + (0 if g._df is None else g._df.nbytes)
        n += sum(pf._current.nbytes for pf in s.filters.values())
        n += sum(100 + 7 * 8 * len(lm.sources) for lm in s.landmarks.landmarks.values())
        n += 120 * len(s.collectables)
        for cache in (self.config.sonar._cache, self.config.cooccupancy._cache):
            n += sum(t.points.nbytes + np.asarray(t.p).nbytes for t in cache.values())
        return n

    # ----- checkpoints -----------------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, bytes]:
        """The state as blobs, each at most BLOB_LIMIT bytes (names and contents: the module docstring)."""
        s = self.system
        _check_attrs(s, _SYSTEM_ATTRS, "SlamSystem")
        _check_attrs(s.grid, _GRID_ATTRS, "OccupancyGrid")
        _check_attrs(s.landmarks, _LANDMARKS_ATTRS, "LandmarkMap")
        _check_attrs(s.collectables, _COLLECTABLES_ATTRS, "CollectableMap")
        components: dict[str, bytes] = {}
        g = s.grid
        components["grid"] = _pack({"updates": g.updates}, [("lo", g._lo), ("p", g._p)])
        components["landmarks"] = self._landmarks_blob()
        components["collectables"] = self._collectables_blob()
        components["models"] = self._models_blob()
        for i, pf in enumerate(s.filters.values()):
            components[f"filter-{i}"] = self._filter_blob(pf)
        out: dict[str, bytes] = {}
        parts: dict[str, list[int]] = {}
        for name, data in components.items():
            chunks = [data[k : k + BLOB_LIMIT] for k in range(0, len(data), BLOB_LIMIT)] or [b""]
            for k, c in enumerate(chunks):
                out[name if k == 0 else f"{name}.{k}"] = c
            parts[name] = [len(chunks), len(data), _crc(data)]
        meta = {
            "format": FORMAT,
            "next_index": self.next_index,
            "grid": _grid_json(self.grid_spec),
            "seed": self.seed,
            "config": config_to_json(self.config),
            "avatars": [_avatar_json(self.avatars[n]) for n in s.filters],
            "added": self.added,
            "counts": self.counts,
            "obs_in_updates": self.obs_in_updates,
            "processed": s.processed,
            "parts": parts,
        }
        out["meta"] = json.dumps(meta, separators=(",", ":")).encode()
        assert all(len(v) <= BLOB_LIMIT for v in out.values())
        return out

    def _filter_blob(self, pf: ParticleFilter) -> bytes:
        _check_attrs(pf, _FILTER_ATTRS, f"ParticleFilter {pf.name!r}")
        blocks = []
        arrays: list[tuple[str, np.ndarray]] = [("current", pf._current)]
        for b in pf.blocks:
            blocks.append([b.index, b.length, b.has_fwd, b.parents is not None])
            arrays += [
                (f"{b.index}.times", b.times[: b.length]),
                (f"{b.index}.states", b.states[: b.length]),
                (f"{b.index}.weights", b.weights),
                (f"{b.index}.log_acc", b.log_acc),
                (f"{b.index}.log_fwd", b.log_fwd),
            ]
            if b.parents is not None:
                arrays.append((f"{b.index}.parents", b.parents))
        arrays.append(("obs_per_update", np.asarray(pf.obs_per_update, dtype=np.int64)))
        shuffle = frozenset(f"{b.index}.states" for b in pf.blocks)
        head = {
            "name": pf.name,
            "n": pf.n,
            "horizon": "inf" if math.isinf(pf.horizon) else pf.horizon,
            "forward_propagation": pf.forward_propagation,
            "dtype": np.dtype(pf._dtype).str,
            "rng": pf.rng.bit_generator.state,
            "marker": pf.marker,
            "counters": [pf.corrections, pf.weight_updates, pf.weight_requests, pf.resamples, pf.pending_obs],
            "blocks": blocks,
        }
        return _pack(head, arrays, shuffle)

    def _landmarks_blob(self) -> bytes:
        lms = self.system.landmarks
        ids, means, covs, sightings = [], [], [], []
        src_lm, src_key, src_av, src_vals = [], [], [], []
        names: dict[str, int] = {}
        for k, (lid, lm) in enumerate(lms.landmarks.items()):
            ids.append(lid)
            means.append(lm.mean)
            covs.append(lm.cov)
            sightings.append(lm.sightings)
            for (av, key), c in lm.sources.items():
                src_lm.append(k)
                src_key.append(key)
                src_av.append(names.setdefault(av, len(names)))
                src_vals.append([getattr(c, f.name) for f in dataclasses.fields(Contribution)])
        head = {"gated": lms.gated, "n": lms._n, "sources": list(names)}
        return _pack(
            head,
            [
                ("ids", np.asarray(ids, dtype=np.int64)),
                ("means", np.asarray(means, dtype=np.float64).reshape(-1, 2)),
                ("covs", np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2)),
                ("sightings", np.asarray(sightings, dtype=np.int64)),
                ("src_lm", np.asarray(src_lm, dtype=np.int64)),
                ("src_key", np.asarray(src_key, dtype=np.int64)),
                ("src_avatar", np.asarray(src_av, dtype=np.int64)),
                ("src_vals", np.asarray(src_vals, dtype=np.float64).reshape(-1, len(dataclasses.fields(Contribution)))),
            ],
        )

    def _collectables_blob(self) -> bytes:
        cm = self.system.collectables
        items = list(cm.items.values())
        if any(set(vars(c)) != set(_COLLECTABLE_FIELDS) for c in items):
            raise CheckpointError("Collectable: attributes the checkpoint does not know")
        head = {"next_id": cm.next_id, "sightings": cm.sightings, "full": cm.full}
        return _pack(
            head,
            [
                ("ids", np.asarray([c.id for c in items], dtype=np.int64)),
                ("n", np.asarray([c.n for c in items], dtype=np.int64)),
                ("sums", np.asarray([[c.sw, c.swx, c.swy] for c in items], dtype=np.float64).reshape(-1, 3)),
                ("times", np.asarray([[c.t_first, c.t_last] for c in items], dtype=np.float64).reshape(-1, 2)),
            ],
        )

    def _models_blob(self) -> bytes:
        def origins(cache: Mapping[Any, Any], width: int) -> np.ndarray:
            rows = []
            for tpl in cache.values():
                if tpl.origin is None or len(tpl.origin) != width:
                    raise CheckpointError("template cache: a template without its origin")
                rows.append(tpl.origin)
            return np.asarray(rows, dtype=np.float64).reshape(-1, width)

        return _pack(
            {},
            [
                ("sonar", origins(self.config.sonar._cache, 4)),
                ("cooccupancy", origins(self.config.cooccupancy._cache, 1)),
            ],
        )

    @classmethod
    def restore(cls, blobs: Mapping[str, bytes]) -> SlamReplica:
        """The replica a checkpoint was taken of (CheckpointError if the blobs are not a complete one)."""
        if "meta" not in blobs:
            raise CheckpointError("meta: missing")
        try:
            meta = json.loads(blobs["meta"])
            if meta.get("format") != FORMAT:
                raise CheckpointError(f"meta: format {meta.get('format')!r}, this code reads {FORMAT}")
            comps: dict[str, bytes] = {}
            for name, (nparts, size, crc) in meta["parts"].items():
                keys = [name if k == 0 else f"{name}.{k}" for k in range(nparts)]
                missing = [k for k in keys if k not in blobs]
                if missing:
                    raise CheckpointError(f"{missing[0]}: missing")
                data = b"".join(bytes(blobs[k]) for k in keys)
                if len(data) != size or _crc(data) != crc:
                    raise CheckpointError(f"{name}: size or CRC does not match meta (a blob of another checkpoint?)")
                comps[name] = data
            grid = GridSpec(**meta["grid"])
            rep = cls(grid, config_from_json(meta["config"]), meta["seed"])
            rep.next_index = int(meta["next_index"])
            rep.added = int(meta["added"])
            rep.counts = {str(k): int(v) for k, v in meta["counts"].items()}
            rep.obs_in_updates = int(meta["obs_in_updates"])
            s = rep.system
            s.processed = {str(k): int(v) for k, v in meta["processed"].items()}
            head, arr = _unpack(comps["grid"], "grid")
            if arr["lo"].shape != s.grid._lo.shape or arr["p"].shape != s.grid._p.shape:
                raise CheckpointError("grid: shape does not match the grid spec")
            s.grid._lo[:] = arr["lo"]
            s.grid._p[:] = arr["p"]
            s.grid.updates = int(head["updates"])
            rep._restore_landmarks(comps["landmarks"])
            if "collectables" in comps:  # (a checkpoint written before the collectable map has none)
                rep._restore_collectables(comps["collectables"])
            rep._restore_models(comps["models"])
            for i, a in enumerate(meta["avatars"]):
                ev = _avatar_from_json(a)
                rep.avatars[ev.name] = ev
                s.filters[ev.name] = rep._restore_filter(comps[f"filter-{i}"], ev, f"filter-{i}")
        except CheckpointError:
            raise
        except (KeyError, ValueError, TypeError, IndexError, AttributeError) as e:
            raise CheckpointError(f"checkpoint: {type(e).__name__}: {e}") from None
        return rep

    def _restore_filter(self, data: bytes, av: AddAvatar, what: str) -> ParticleFilter:
        head, arr = _unpack(data, what)
        if head["name"] != av.name:
            raise CheckpointError(f"{what}: holds avatar {head['name']!r}, meta says {av.name!r}")
        horizon = math.inf if head["horizon"] == "inf" else float(head["horizon"])
        dtype = np.dtype(head["dtype"]).type
        pf = ParticleFilter(
            int(head["n"]),
            av.pose,
            av.t0,
            seed=0,
            horizon=horizon,
            forward_propagation=bool(head["forward_propagation"]),
            store_dtype=dtype,
            name=av.name,
        )
        pf.rng.bit_generator.state = head["rng"]
        pf._current = arr["current"]
        blocks = []
        for index, length, has_fwd, has_parents in head["blocks"]:
            times, states = arr[f"{index}.times"], arr[f"{index}.states"]
            if times.shape != (length,) or states.shape != (length, pf.n, 3):
                raise CheckpointError(f"{what}: block {index} has the wrong shape")
            b = Block(index, float(times[0]), states[0], arr[f"{index}.parents"] if has_parents else None, dtype)
            b.times, b.states, b.length = times, states, length
            b.weights, b.log_acc, b.log_fwd = arr[f"{index}.weights"], arr[f"{index}.log_acc"], arr[f"{index}.log_fwd"]
            b.has_fwd = bool(has_fwd)
            blocks.append(b)
        if not blocks:
            raise CheckpointError(f"{what}: no blocks")
        pf.blocks = blocks
        pf._starts = [b.start for b in blocks]
        pf.marker = None if head["marker"] is None else int(head["marker"])
        pf.corrections, pf.weight_updates, pf.weight_requests, pf.resamples, pf.pending_obs = (
            int(v) for v in head["counters"]
        )
        pf.obs_per_update = [int(v) for v in arr["obs_per_update"]]
        return pf

    def _restore_landmarks(self, data: bytes) -> None:
        head, arr = _unpack(data, "landmarks")
        lms = self.system.landmarks
        lms.gated, lms._n = int(head["gated"]), int(head["n"])
        names = head["sources"]
        lms.landmarks = {}
        order = []
        for k, lid in enumerate(arr["ids"]):
            lm = Landmark(arr["means"][k].copy(), arr["covs"][k].copy(), int(arr["sightings"][k]), {})
            lms.landmarks[int(lid)] = lm
            order.append(lm)
        for k in range(arr["src_lm"].shape[0]):
            vals = [float(v) for v in arr["src_vals"][k]]
            key = (names[int(arr["src_avatar"][k])], int(arr["src_key"][k]))
            order[int(arr["src_lm"][k])].sources[key] = Contribution(*vals)

    def _restore_collectables(self, data: bytes) -> None:
        head, arr = _unpack(data, "collectables")
        cm = self.system.collectables
        cm.next_id, cm.sightings, cm.full = int(head["next_id"]), int(head["sightings"]), int(head["full"])
        cm.items = {}
        for k, cid in enumerate(arr["ids"]):
            sw, swx, swy = (float(v) for v in arr["sums"][k])
            t_first, t_last = (float(v) for v in arr["times"][k])
            cm.items[int(cid)] = Collectable(int(cid), sw, swx, swy, int(arr["n"][k]), t_first, t_last)

    def _restore_models(self, data: bytes) -> None:
        _, arr = _unpack(data, "models")
        sonar, cooc = self.config.sonar, self.config.cooccupancy
        sonar._cache.clear()
        cooc._cache.clear()
        for rng, bearing, fov, max_range in arr["sonar"]:  # in LRU order: rebuilding keeps the order
            sonar.echo_template(
                SonarEcho(float(bearing), None if math.isnan(rng) else float(rng)), float(fov), float(max_range)
            )
        for (radius,) in arr["cooccupancy"]:
            cooc.template(float(radius))

    # ----- the state digest ------------------------------------------------------------------------------
    def state_digest(self) -> str:
        """SHA-256 over everything that makes the state (computed from the live objects, not the checkpoint)."""
        h = hashlib.sha256()

        def put(*vals: Any) -> None:
            for v in vals:
                if isinstance(v, np.ndarray):
                    h.update(f"{v.dtype.str}{v.shape}".encode())
                    h.update(np.ascontiguousarray(v).tobytes())
                else:
                    h.update(repr(v).encode())
                h.update(b"|")

        s = self.system
        put(self.next_index, sorted(self.counts.items()), self.seed, self.added, self.obs_in_updates)
        put(json.dumps(config_to_json(self.config), sort_keys=True), sorted(s.processed.items()))
        put([_avatar_json(a) for a in self.avatars.values()])
        for name, pf in s.filters.items():
            put(name, pf.n, pf.horizon, pf.forward_propagation, json.dumps(pf.rng.bit_generator.state, sort_keys=True))
            put(pf._current, pf.marker, pf._starts, pf.obs_per_update)
            put(pf.corrections, pf.weight_updates, pf.weight_requests, pf.resamples, pf.pending_obs)
            for b in pf.blocks:
                put(b.index, b.length, b.has_fwd, b.times[: b.length], b.states[: b.length])
                put(b.weights, b.log_acc, b.log_fwd, b.parents if b.parents is not None else "root")
        put(s.grid._lo, s.grid._p, s.grid.updates)
        put(s.landmarks.gated, s.landmarks._n)
        for lid, lm in s.landmarks.landmarks.items():
            put(lid, lm.mean, lm.cov, lm.sightings)
            for key, c in lm.sources.items():
                put(key, dataclasses.astuple(c))
        cm = s.collectables
        put(cm.gate, cm.limit, cm.next_id, cm.sightings, cm.full)
        for cid, col in cm.items.items():
            put(cid, dataclasses.astuple(col))
        for cache in (self.config.sonar._cache, self.config.cooccupancy._cache):
            for key, tpl in cache.items():
                put(key, tpl.points, np.asarray(tpl.p), tpl.origin)
        return h.hexdigest()


# ----- the published map ------------------------------------------------------------------------------------


def encode_map(spec: GridSpec, prob: np.ndarray) -> bytes:
    """`slam/map`: p(C) per cell (rows = y) quantised to uint8 q = round(254 p) (error ≤ 1/508), zlib, JSON header."""
    prob = np.asarray(prob)
    if prob.shape != spec.shape:
        raise MapError(f"prob: shape must be {spec.shape}, got {prob.shape}")
    q = np.rint(np.clip(prob, 0.0, 1.0) * MAP_LEVELS).astype(np.uint8)
    return _pack({"kind": "map", "grid": _grid_json(spec), "levels": MAP_LEVELS}, [("q", q)])


def decode_map(data: bytes) -> tuple[GridSpec, np.ndarray]:
    """(grid spec, p(C) float32 (rows, cols)) of an encoded map; MapError if the bytes are not one."""
    try:
        head, arr = _unpack(data, "map")
        if head.get("kind") != "map" or head.get("levels") != MAP_LEVELS:
            raise MapError("map: not an encoded map")
        spec = GridSpec(**head["grid"])
        q = arr["q"]
        if q.dtype != np.uint8 or q.shape != spec.shape or int(q.max(initial=0)) > MAP_LEVELS:
            raise MapError("map: cells do not match the grid")
    except MapError:
        raise
    except (CheckpointError, KeyError, TypeError, ValueError) as e:
        raise MapError(f"map: {e}") from None
    return spec, (q.astype(np.float32) / np.float32(MAP_LEVELS))
