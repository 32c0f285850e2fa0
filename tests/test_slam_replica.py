"""The SLAM state as an event log (haa.slam.events) and its replica (haa.slam.replica): determinism, exact
checkpoints at any cut point, skipped events, the published map, and the same estimates as SlamSystem."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest

from haa.pb import slam_pb2 as pb
from haa.slam import replica as replica_mod
from haa.slam.events import (
    AddAvatar,
    EventError,
    Observe,
    Predict,
    RemoveAvatar,
    Request,
    decode,
    encode,
)
from haa.slam.explorer import record
from haa.slam.grid import GridSpec
from haa.slam.motion import DRIFT, Prediction
from haa.slam.recording import recording_events
from haa.slam.replay import calibrate, config_for
from haa.slam.replica import (
    BLOB_LIMIT,
    DEFAULT_HORIZON,
    CheckpointError,
    LogGap,
    MapError,
    SlamReplica,
    decode_map,
    encode_map,
)
from haa.slam.sensors import (
    CooccupancyReading,
    FloorReading,
    LandmarkReading,
    Sighting,
    SonarEcho,
    SonarReading,
)
from haa.slam.strategies import run, strategy
from haa.slam.synthetic import synthetic_recording
from haa.slam.system import SlamConfig, SlamSystem

N = 30  # particles: keep the tests fast


@pytest.fixture(scope="module")
def basic():
    """20 s of the Basic team (4 seekers, small arena): predictions, landmark and co-occupancy readings."""
    return record("basic", 20.0, seed=1)


@pytest.fixture(scope="module")
def synth():
    """Two sweepers in the synthetic room for 40 s: sonar scans too."""
    return synthetic_recording(avatars=2, duration=40.0, seed=4)


class LoggingSystem(SlamSystem):
    """A SlamSystem driven by haa.slam.strategies.run that writes every call it gets as a log event."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.log: list = []

    def predict(self, name, p):
        self.log.append(Predict(name, p))
        super().predict(name, p)

    def process(self, r):
        self.log.append(Observe(r, "logger"))
        return super().process(r)

    def request(self, name):
        self.log.append(Request(name))
        return super().request(name)


def constrained_log(rec, n=N, seed=0):
    """JC-SLAM at constrained capacity (late readings into closed blocks, resamplings): the log it writes
    and the estimates it gave at each request. The system prunes after each request, as the replica does."""
    cfg = dataclasses.replace(config_for(rec, n), horizon=DEFAULT_HORIZON)
    cfg = replica_mod.config_from_json(replica_mod.config_to_json(cfg))
    system = LoggingSystem(rec.grid, cfg, seed=seed)
    for a in rec.avatars:
        system.log.append(AddAvatar(a.name, a.kind, a.start, 0.0, a.drift, a.radius))
        system.add_avatar(a.name, a.start, 0.0)
    estimates = []

    def on_request(avatar, t, est, resampled):
        system.prune()
        estimates.append((avatar, est.pose.copy(), est.n_eff, resampled))

    stats = run(rec.events(1.0), strategy("jcslam"), calibrate(rec, 0.5), system, seed=seed, on_request=on_request)
    return system, system.log, estimates, stats


def rich_stream(rec):
    """The constrained log of `rec`, with sonar bearings jittered below the template cache's rounding (so the
    cache's content matters), floor readings, and the events a replica must skip or ignore."""
    _, log, _, _ = constrained_log(rec)
    rng = np.random.default_rng(7)
    out: list = []
    for ev in log:
        if isinstance(ev, Observe) and isinstance(ev.reading, SonarReading):
            r = ev.reading
            echoes = tuple(SonarEcho(e.bearing + float(rng.uniform(-4e-5, 4e-5)), e.range) for e in r.echoes)
            ev = Observe(dataclasses.replace(r, echoes=echoes), ev.processor)
        out.append(encode(ev))
        if isinstance(ev, Observe) and isinstance(ev.reading, CooccupancyReading) and rng.random() < 0.2:
            poly = ((0.2, -0.3), (1.5, -0.8), (1.5, 0.8), (0.2, 0.3))
            out.append(encode(Observe(FloorReading(ev.reading.avatar, ev.reading.t, poly), "floorfinder")))
    name = rec.avatars[0].name
    extra = [
        b"\xff\x00garbage",  # malformed
        encode(Request("nobody")),  # unknown avatar
        encode(AddAvatar(name, "sweeper", (9.0, 9.0, 0.0))),  # already there: no-op
        encode(Observe(CooccupancyReading(name, -100.0, 0.15))),  # older than the horizon at the end
    ]
    k = len(out) // 3
    out[k:k] = extra[:3]
    out.append(extra[3])
    # an avatar leaves and another joins later (its filter gets a seed of its own)
    k2 = 2 * len(out) // 3
    t = max(p.t for a, p in rec.predictions if a == name and p.t <= 20.0)
    out[k2:k2] = [
        encode(RemoveAvatar(rec.avatars[1].name)),
        encode(AddAvatar("late", "sweeper", (1.0, 1.0, 0.0), t, DRIFT["sweeper"])),
    ]
    return out


@pytest.fixture(scope="module")
def stream(synth):
    return rich_stream(synth)


def fresh(rec, n=N, seed=0):
    return SlamReplica(rec.grid, config_for(rec, n), seed=seed)


def apply_all(rep, items, start=0):
    for i in range(start, len(items)):
        rep.apply(i, items[i])
    return rep


# ----- events ------------------------------------------------------------------------------------------------


def test_events_round_trip(basic):
    evs = recording_events(basic)
    floor = Observe(FloorReading("seeker-1", 3.0, ((0.1, 0.0), (1.0, -0.5), (1.0, 0.5))), "ff")
    sonar = Observe(SonarReading("a1", 2.0, (SonarEcho(0.0, 1.2), SonarEcho(0.5, None))), "sonar-1")
    evs += [floor, sonar, RemoveAvatar("seeker-2")]
    kinds = {type(e).__name__ for e in evs}
    assert kinds == {"AddAvatar", "Predict", "Observe", "Request", "RemoveAvatar"}
    for e in evs:
        assert decode(encode(e)) == e
    # sizes: what the log costs per event
    assert len(encode(evs[10])) < 100


def bad(m: pb.SlamEvent) -> bytes:
    return m.SerializeToString()


def _pred(**kw):
    d = dict(avatar="a", t=1.0, vx=0.1, vy=0.0, omega=0.0, sigma_xy=0.01, sigma_theta=0.01)
    d.update(kw)
    return pb.SlamEvent(predict=pb.SlamPrediction(**d))


@pytest.mark.parametrize(
    "data, reason",
    [
        (b"\xff\xff\xff", "not a SlamEvent"),
        (b"", "no event set"),
        (bad(_pred(t=math.nan)), "prediction.t: must be finite"),
        (bad(_pred(sigma_xy=math.inf)), "prediction.sigma_xy: must be finite"),
        (bad(_pred(avatar="")), "predict.avatar: must be a non-empty string"),
        (bad(pb.SlamEvent(request=pb.SlamRequest(avatar=""))), "request.avatar"),
        (bad(pb.SlamEvent(observe=pb.SlamObserve(processor="x"))), "observe: no reading set"),
        (
            bad(pb.SlamEvent(observe=pb.SlamObserve(floor=pb.SlamFloor(avatar="a", t=1, xs=[0, 1, 1], ys=[0, 1])))),
            "2 ys",
        ),
        (
            bad(
                pb.SlamEvent(observe=pb.SlamObserve(floor=pb.SlamFloor(avatar="a", t=1, xs=[0, 1e3, 1], ys=[0, 0, 1])))
            ),
            "beyond 20",
        ),
        (
            bad(
                pb.SlamEvent(
                    observe=pb.SlamObserve(
                        sonar=pb.SlamSonar(
                            avatar="a", t=1, fov=0.3, max_range=2, echoes=[pb.SlamEcho(bearing=0, range=5)]
                        )
                    )
                )
            ),
            "range: must be in [0, max_range=2.0]",
        ),
        (
            bad(
                pb.SlamEvent(
                    observe=pb.SlamObserve(
                        landmark=pb.SlamLandmark(
                            avatar="a", t=1, sightings=[pb.SlamSighting(landmark_id=1, range=-1, bearing=0)]
                        )
                    )
                )
            ),
            "range: must be > 0",
        ),
        (
            bad(
                pb.SlamEvent(
                    add_avatar=pb.SlamAddAvatar(
                        avatar=pb.SlamAvatarInfo(name="a", x=math.nan, radius=0.1, drift_inflate=1), t0=0
                    )
                )
            ),
            "add_avatar.pose[0]: must be finite",
        ),
        (bad(pb.SlamEvent(remove_avatar=pb.SlamRemoveAvatar(name="x" * 200))), "longer than 128"),
        (b"\n" + bytes([0x80] * 9), "not a SlamEvent"),
    ],
)
def test_malformed_events_are_refused(data, reason):
    with pytest.raises(EventError) as e:
        decode(data)
    assert reason in e.value.reason
    assert "\n" not in e.value.reason


def test_encode_refuses_what_decode_refuses():
    with pytest.raises(EventError, match=r"add_avatar\.radius"):
        AddAvatar("a", "seeker", (0, 0, 0), radius=0.0)
    with pytest.raises(EventError, match="more than 256 vertices"):
        Observe(FloorReading("a", 0.0, tuple((math.cos(k), math.sin(k)) for k in range(300))))
    with pytest.raises(EventError, match="max_range"):
        Observe(SonarReading("a", 0.0, (SonarEcho(0.0, None),), max_range=100.0))
    with pytest.raises(EventError, match="more than 1024"):
        Observe(LandmarkReading("a", 0.0, tuple(Sighting(k, 1.0, 0.0) for k in range(1025))))


# ----- the replica: determinism, skipping, checkpoints --------------------------------------------------------


def test_two_replicas_agree_and_the_digest_notices_a_difference(stream, synth):
    a = apply_all(fresh(synth), stream)
    b = apply_all(fresh(synth), stream)
    assert a.state_digest() == b.state_digest()
    assert a.counts == b.counts
    # the digest sees a different noise seed, and one item left out
    assert apply_all(fresh(synth, seed=1), stream).state_digest() != a.state_digest()
    c = fresh(synth)
    for i, d in enumerate(stream):
        c.apply(i, d if i != len(stream) // 2 else encode(Request("nobody")))
    assert c.state_digest() != a.state_digest()


def test_skipped_events_are_counted_and_change_nothing(stream, synth):
    rep = apply_all(fresh(synth), stream)
    c = rep.counts
    assert c["malformed"] == 1
    # the removed avatar's later events are for an unknown avatar too
    gone = synth.avatars[1].name
    evs = [decode(d) if d[:1] != b"\xff" else None for d in stream]
    cut = next(i for i, e in enumerate(evs) if isinstance(e, RemoveAvatar))
    later = [type(e).__name__ for e in evs[cut:] if e is not None and getattr(e, "avatar", None) == gone]
    assert c["request.unknown_avatar"] == 1 + later.count("Request")
    assert c.get("predict.unknown_avatar", 0) == later.count("Predict") > 0
    unknown_observe = later.count("Observe")
    assert c["add_avatar.noop"] == 1
    assert c["observe.too_old"] == 1
    assert c["remove_avatar.applied"] == 1 and c["add_avatar.applied"] == 3
    assert rep.names == [synth.avatars[0].name, "late"]
    # a skipped item changes nothing but the counters and the next index
    name = synth.avatars[0].name
    pf = rep.system.filter(name)
    before = (rep.system.grid._lo.copy(), pf.last.weights.copy(), pf.last.log_acc.copy(), len(pf.blocks))
    n = rep.next_index
    results = [
        rep.apply(n, encode(Observe(CooccupancyReading(name, pf.time - DEFAULT_HORIZON - 1.0)))),
        rep.apply(n + 1, encode(Observe(CooccupancyReading(name, pf.time + 5.0)))),
        rep.apply(n + 2, encode(Observe(CooccupancyReading("ghost", pf.time)))),
        rep.apply(n + 3, encode(Predict(name, Prediction(pf.time, 0.1, 0, 0, 0.01, 0.01)))),
        rep.apply(n + 4, b"\x08"),
    ]
    assert [r.outcome for r in results] == ["skipped"] * 5
    assert [r.reason.split(":")[0] for r in results[:2]] == [
        f"t={pf.time - DEFAULT_HORIZON - 1.0:.3f}",
        f"t={pf.time + 5.0:.3f}",
    ]
    assert "older than the history horizon" in results[0].reason
    assert (
        c["observe.too_old"] == 2
        and c["observe.not_yet_predicted"] == 1
        and c["observe.unknown_avatar"] == unknown_observe + 1
    )
    assert c["predict.out_of_order"] == 1 and c["malformed"] == 2
    after = (rep.system.grid._lo, pf.last.weights, pf.last.log_acc, len(pf.blocks))
    for x, y in zip(before[:3], after[:3], strict=True):
        np.testing.assert_array_equal(x, y)
    assert before[3] == after[3]


def test_indexes_duplicates_and_gaps(synth, stream):
    rep = fresh(synth)
    rep.apply(0, stream[0])
    d = rep.state_digest()
    assert rep.apply(0, stream[0]).outcome == "duplicate"
    assert rep.state_digest() == d
    with pytest.raises(LogGap, match="index 2: the next expected log item is 1"):
        rep.apply(2, stream[2])
    assert rep.state_digest() == d


@pytest.mark.parametrize("cut", [0, 1, 0.25, 0.5, 0.77, 1.0])
def test_checkpoint_is_exact_at_any_cut(stream, synth, cut):
    k = cut if isinstance(cut, int) else round(cut * len(stream))
    full = apply_all(fresh(synth), stream)
    part = fresh(synth)
    for i in range(k):
        part.apply(i, stream[i])
    blobs = part.checkpoint()
    assert set(blobs) >= {"meta", "grid", "landmarks", "models"}
    assert all(len(v) <= BLOB_LIMIT for v in blobs.values())
    again = SlamReplica.restore(blobs)
    assert again.state_digest() == part.state_digest()
    assert again.next_index == k
    apply_all(again, stream, start=k)
    assert again.state_digest() == full.state_digest()
    for name in full.names:
        assert again.estimate(name) == full.estimate(name)


def test_checkpoint_exact_on_the_basic_team(basic):
    """A real case: 20 s of Basic, 30 particles, cut at several points."""
    items = [encode(e) for e in recording_events(basic)]
    full = apply_all(SlamReplica(basic.grid, config_for(basic, N), seed=2), items)
    for k in (5, len(items) // 3, 2 * len(items) // 3 + 1):
        part = SlamReplica(basic.grid, config_for(basic, N), seed=2)
        for i in range(k):
            part.apply(i, items[i])
        again = apply_all(SlamReplica.restore(part.checkpoint()), items, start=k)
        assert again.state_digest() == full.state_digest()


def test_restore_needs_the_rng_state_and_the_template_caches(stream, synth):
    """The exactness test can fail: a restore that loses the noise generator's state, or the sonar
    templates' origins (the cache is keyed by rounded bearings), diverges."""
    k = len(stream) // 2
    full = apply_all(fresh(synth), stream)
    part = fresh(synth)
    for i in range(k):
        part.apply(i, stream[i])
    blobs = part.checkpoint()

    lost_rng = SlamReplica.restore(blobs)
    for pf in lost_rng.system.filters.values():
        pf.rng = np.random.default_rng(0)
    apply_all(lost_rng, stream, start=k)
    assert lost_rng.state_digest() != full.state_digest()

    lost_cache = SlamReplica.restore(blobs)
    lost_cache.config.sonar._cache.clear()
    apply_all(lost_cache, stream, start=k)
    assert not np.array_equal(lost_cache.system.grid._lo, full.system.grid._lo)


def test_large_checkpoints_are_split_into_blobs(stream, synth, monkeypatch):
    monkeypatch.setattr(replica_mod, "BLOB_LIMIT", 4096)
    k = len(stream) // 2
    part = fresh(synth)
    for i in range(k):
        part.apply(i, stream[i])
    blobs = part.checkpoint()
    assert any("." in name for name in blobs)
    assert all(len(v) <= 4096 for v in blobs.values())
    again = SlamReplica.restore(blobs)
    assert again.state_digest() == part.state_digest()


def test_restore_refuses_broken_checkpoints_and_ignores_leftovers(synth, stream):
    part = apply_all(fresh(synth), stream[:200])
    blobs = part.checkpoint()
    other = apply_all(fresh(synth), stream[:300]).checkpoint()
    assert SlamReplica.restore({**blobs, "filter-7": b"old", "grid.3": b"x"}).state_digest() == part.state_digest()
    with pytest.raises(CheckpointError, match="meta: missing"):
        SlamReplica.restore({k: v for k, v in blobs.items() if k != "meta"})
    with pytest.raises(CheckpointError, match="filter-1: missing"):
        SlamReplica.restore({k: v for k, v in blobs.items() if k != "filter-1"})
    with pytest.raises(CheckpointError, match="grid: size or CRC"):
        SlamReplica.restore({**blobs, "grid": other["grid"]})
    with pytest.raises(CheckpointError):
        SlamReplica.restore({**blobs, "meta": b"{not json"})


def test_checkpoint_knows_every_attribute(synth, stream):
    """A field added to the filter later must be added to the checkpoint too, or restores would lose it."""
    rep = apply_all(fresh(synth), stream[:100])
    pf = next(iter(rep.system.filters.values()))
    pf.something_new = 1
    with pytest.raises(CheckpointError, match="something_new"):
        rep.checkpoint()


def test_pruning_bounds_the_history(synth, stream):
    rep = apply_all(fresh(synth), stream)
    for pf in rep.system.filters.values():
        assert pf.horizon == DEFAULT_HORIZON
        assert pf.blocks[0].start >= pf.time - 2 * DEFAULT_HORIZON - 1.0
        assert not pf.obs_per_update  # folded into the replica's counter
    assert rep.obs_in_updates > 0
    # an infinite horizon is replaced; a finite one is kept
    assert SlamReplica(synth.grid, SlamConfig(n_particles=5, horizon=12.0)).config.horizon == 12.0
    assert SlamReplica(synth.grid, SlamConfig(n_particles=5)).config.horizon == DEFAULT_HORIZON


def test_replicas_never_share_template_caches(synth):
    cfg = config_for(synth, N)
    a, b = SlamReplica(synth.grid, cfg), SlamReplica(synth.grid, cfg)
    assert a.config.sonar is not b.config.sonar and a.config.sonar is not cfg.sonar


# ----- the same JC-SLAM as SlamSystem ------------------------------------------------------------------------


def test_baseline_replay_through_the_log_equals_slamsystem(basic):
    """The replica (horizon 30 s, pruning at every request) gives bit-identical estimates to a SlamSystem
    driven directly by haa.slam.strategies.run (Baseline, infinite horizon, no pruning)."""
    direct: list = []
    system = SlamSystem(basic.grid, config_for(basic, N), seed=5)
    for a in basic.avatars:
        system.add_avatar(a.name, a.start, 0.0)
    run(basic.events(1.0), strategy("baseline"), None, system, on_request=lambda a, t, e, r: direct.append((a, e, r)))
    rep = SlamReplica(basic.grid, config_for(basic, N), seed=5)
    got = []
    for i, data in enumerate(encode(e) for e in recording_events(basic)):
        res = rep.apply(i, data)
        assert res.outcome == "applied", res
        if res.kind == "request":
            got.append((res.avatar, res.n_eff, res.resampled))
    assert len(got) == len(direct) > 50
    assert sum(r for _, _, r in got) > 3  # resamplings happened
    for (a, n_eff, res), (a2, e2, r2) in zip(got, direct, strict=True):
        assert (a, n_eff, res) == (a2, e2.n_eff, r2)
    np.testing.assert_array_equal(rep.system.grid.prob(), system.grid.prob())
    for name, pf in system.filters.items():
        e = pf.peek()
        assert rep.estimate(name)[:4] == (e.t, *(float(v) for v in e.pose))


def test_constrained_jcslam_through_the_log_equals_slamsystem(synth):
    """Late readings into closed blocks and forward propagation: the logged run and its replay agree bitwise."""
    system, log, estimates, stats = constrained_log(synth)
    assert stats.out_of_order > 0 and stats.resamples > 0
    rep = SlamReplica(synth.grid, system.config, seed=0)
    got = []
    for i, ev in enumerate(log):
        res = rep.apply(i, encode(ev))
        if res.kind == "request":
            got.append((res.avatar, res.n_eff, res.resampled))
    assert got == [(a, n, r) for a, _, n, r in estimates]
    np.testing.assert_array_equal(rep.system.grid._lo, system.grid._lo)
    for name, pf in system.filters.items():
        np.testing.assert_array_equal(rep.system.filter(name).last.weights, pf.last.weights)


def test_peek_is_estimate_without_side_effects(synth):
    """ParticleFilter.peek equals estimate() bitwise — also with densities still to propagate through
    resamplings and to fold — and changes nothing; SlamReplica.estimate reports it."""
    cfg = config_for(synth, N)
    system = SlamSystem(synth.grid, cfg, seed=0)
    for a in synth.avatars:
        system.add_avatar(a.name, a.start, 0.0)
    rep = SlamReplica(synth.grid, cfg)
    checked = {"pending_forward": 0, "pending_fold": 0, "all": 0}

    def check(r, t_done):
        if checked["all"] >= 40 or system.filter(r.avatar).resamples == 0:
            return
        pf = system.filter(r.avatar)
        checked["all"] += 1
        checked["pending_forward"] += pf.marker is not None and pf.marker < pf.last.index
        checked["pending_fold"] += bool(np.any(pf.last.log_acc))
        twin = copy.deepcopy(pf)
        before = (pf.last.weights.copy(), pf.last.log_acc.copy(), pf.marker, pf.weight_requests, pf.pending_obs)
        p = pf.peek()
        e = twin.estimate()
        np.testing.assert_array_equal(p.weights, e.weights)
        np.testing.assert_array_equal(p.pose, e.pose)
        assert (p.t, p.n_eff, p.block) == (e.t, e.n_eff, e.block)
        np.testing.assert_array_equal(before[0], pf.last.weights)
        np.testing.assert_array_equal(before[1], pf.last.log_acc)
        assert before[2:] == (pf.marker, pf.weight_requests, pf.pending_obs)
        rep.system.filters[r.avatar] = pf
        t, x, y, th, std = rep.estimate(r.avatar)
        assert (t, x, y, th) == (e.t, *(float(v) for v in e.pose))
        assert math.hypot(std[0], std[1]) == pytest.approx(e.std_xy, rel=1e-9)

    run(synth.events(1.0), strategy("jcslam"), calibrate(synth, 0.5), system, on_processed=check)
    assert checked["all"] == 40 and checked["pending_forward"] > 0 and checked["pending_fold"] > 0, checked


# ----- the published map -------------------------------------------------------------------------------------


@pytest.mark.parametrize("spec", [GridSpec(3.4, 7.2, 0.1), GridSpec(18.0, 18.0, 0.1, -1.0, 2.0)])
def test_map_round_trip_within_quantisation(spec):
    rng = np.random.default_rng(3)
    p = rng.uniform(0.0, 1.0, spec.shape)
    p[0, :5] = [0.0, 0.5, 1.0, 0.001, 0.999]
    data = encode_map(spec, p)
    spec2, q = decode_map(data)
    assert spec2 == spec and q.dtype == np.float32 and q.shape == spec.shape
    assert np.max(np.abs(q - p)) <= 1 / 508 + 1e-7
    assert q[0, 1] == 0.5 and q[0, 0] == 0.0 and q[0, 2] == 1.0
    assert len(data) < spec.shape[0] * spec.shape[1] + 200
    # an explored-looking map compresses well
    half = np.full(spec.shape, 0.5)
    assert len(encode_map(spec, half)) < 600


def test_map_errors():
    spec = GridSpec(3.4, 7.2, 0.1)
    with pytest.raises(MapError, match="shape"):
        encode_map(spec, np.zeros((3, 3)))
    with pytest.raises(MapError):
        decode_map(b"HAAS\x01garbage")
    with pytest.raises(MapError):
        decode_map(b"nope")
    data = encode_map(spec, np.full(spec.shape, 0.5))
    rep_blob = SlamReplica(spec).checkpoint()["grid"]
    with pytest.raises(MapError, match="not an encoded map"):
        decode_map(rep_blob)
    assert decode_map(data)[0] == spec


def test_replica_map_and_memory(basic):
    rep = apply_all(SlamReplica(basic.grid, config_for(basic, N)), [encode(e) for e in recording_events(basic)])
    spec, p = decode_map(rep.encode_map())
    assert spec == basic.grid
    assert np.max(np.abs(p - rep.system.grid.prob())) <= 1 / 508 + 1e-7
    assert (p != 0.5).sum() > 100  # something was mapped
    m = rep.memory_bytes()
    assert rep.system.memory_bytes() < m < 10 * 1024 * 1024


def test_blob_arrays_round_trip_bit_exactly():
    """The blob container (and its XOR-shuffle filter for particle histories) keeps every bit: -0.0, NaN
    payloads, infinities, one-row and empty arrays."""
    rng = np.random.default_rng(1)
    states = rng.normal(2.0, 1.0, (57, 13, 3)).astype(np.float32)
    states.view(np.uint32)[3, 4, 1] = 0x7FC01234  # a NaN with a payload
    states[5, 0, 0], states[6, 1, 2] = -0.0, np.inf
    arrays = [
        ("s", states),
        ("one", states[:1]),
        ("empty", np.zeros((0, 3), dtype=np.float32)),
        ("w", rng.random(13)),
        ("i", np.arange(5, dtype=np.int64)),
    ]
    blob = replica_mod._pack({"x": 1}, arrays, frozenset({"s", "one", "empty", "w"}))
    head, got = replica_mod._unpack(blob, "t")
    assert head == {"x": 1}
    for name, a in arrays:
        assert got[name].dtype == a.dtype and got[name].shape == a.shape
        assert got[name].tobytes() == a.tobytes(), name
    with pytest.raises(CheckpointError, match="t: "):
        replica_mod._unpack(blob[:-3], "t")
