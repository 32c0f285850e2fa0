"""Collectables found by the team's own cameras become identified collectables (Forage; haa.slam.collectables):
the event, association and new ids in the replica, exact checkpoints, the sensor agent on a rendered frame,
and SupervisorSLAM's publication (docs/slam.md "Collectables", docs/team.md "Forage: identified collectables
in the DDB")."""

from __future__ import annotations

import asyncio
import json
import math
from typing import Any

import numpy as np
import pytest
from test_slam_team import FakeCtx, supervisor

from haa.agents import team
from haa.agents.sensor_landmark import AgentSensorLandmark
from haa.core.ddb.ops import decode_value
from haa.pb import slam_pb2 as pb
from haa.slam.collectables import GATE, CollectableMap
from haa.slam.events import (
    MAX_COLLECTABLE_SIGHTINGS,
    AddAvatar,
    EventError,
    Observe,
    Predict,
    Request,
    decode,
    encode,
)
from haa.slam.grid import GridSpec
from haa.slam.motion import DRIFT, Prediction, odometry_prediction
from haa.slam.replica import CheckpointError, SlamReplica
from haa.slam.sensors import CollectablesReading, CooccupancyReading, LandmarkReading, RangeBearing, Sighting
from haa.slam.system import SlamConfig

N = 40
SPEC = GridSpec(18.0, 18.0, 0.1)


def replica(seed: int = 0) -> SlamReplica:
    return SlamReplica(SPEC, SlamConfig(n_particles=N), seed=seed)


def seen(avatar: str, t: float, *rb: tuple[float, float]) -> bytes:
    return encode(Observe(CollectablesReading(avatar, t, tuple(RangeBearing(r, b) for r, b in rb)), "L1"))


def still(avatar: str, t: float) -> bytes:
    """A prediction of an avatar standing still (tiny noise)."""
    return encode(Predict(avatar, Prediction(t, 0.0, 0.0, 0.0, 0.001, 0.0005)))


def run(rep: SlamReplica, items: list[bytes], start: int = 0) -> SlamReplica:
    for i in range(start, len(items)):
        rep.apply(i, items[i])
    return rep


def positions(rep: SlamReplica) -> dict[int, tuple[float, float, int]]:
    return {c.id: (c.x, c.y, c.n) for c in rep.system.collectables.items.values()}


# ----- association -----------------------------------------------------------------------------------------


def test_sightings_are_placed_with_the_estimated_pose_and_associated_within_the_gate() -> None:
    items = [encode(AddAvatar("a", "sweeper", (5.0, 5.0, math.pi / 2))), still("a", 1.0)]
    items.append(seen("a", 0.5, (2.0, 0.0), (2.0, -math.pi / 2)))  # (5, 7) and (7, 5): two new ones
    items.append(seen("a", 0.6, (2.3, 0.0)))  # 0.3 m beyond the first: the same one
    items.append(seen("a", 0.7, (2.0 + 0.9, 0.0)))  # 0.9 m beyond the first sighting, within the gate: it again
    rep = run(replica(), items)
    p = positions(rep)
    assert sorted(p) == [1, 2]
    x1, y1, n1 = p[1]
    assert n1 == 3 and abs(x1 - 5.0) < 0.05 and 7.1 < y1 < 7.6
    assert p[2][2] == 1 and math.hypot(p[2][0] - 7.0, p[2][1] - 5.0) < 0.05
    # just beyond the gate of the first's estimate (towards the avatar): a third one
    rep.apply(len(items), seen("a", 0.8, (y1 - 5.0 - GATE - 0.05, 0.0)))
    p = positions(rep)
    assert sorted(p) == [1, 2, 3] and p[1][2] == 3 and p[3][2] == 1 and abs(p[3][1] - (y1 - GATE - 0.05)) < 0.03
    assert rep.counts["observe.applied"] == 4 and rep.system.processed["collectables"] == 4
    pub = rep.system.collectables.published()
    assert pub["1"]["n"] == 3 and pub["1"]["t_first"] == 0.5 and pub["1"]["t_last"] == 0.7
    assert set(pub["2"]) == {"x", "y", "n", "t_first", "t_last", "std"}


def test_the_nearest_within_the_gate_wins_and_ties_go_to_the_lower_id() -> None:
    m = CollectableMap()
    assert m.add(0.0, 0.0, 0.01, 1.0) == 1
    assert m.add(1.5, 0.0, 0.01, 1.0) == 2  # beyond the gate of the first
    assert m.add(0.8, 0.0, 0.01, 2.0) == 2  # 0.8 from 1, 0.7 from 2
    m2 = CollectableMap()
    m2.add(0.0, 0.0, 0.01, 0.0)
    m2.add(1.6, 0.0, 0.01, 0.0)
    assert m2.add(0.8, 0.0, 0.01, 0.0) == 1  # equidistant: the lower id
    full = CollectableMap(limit=2)
    full.add(0.0, 0.0, 0.01, 0.0)
    full.add(5.0, 0.0, 0.01, 0.0)
    assert full.add(10.0, 0.0, 0.01, 0.0) is None and full.full == 1 and len(full) == 2
    assert full.add(5.2, 0.0, 0.01, 0.0) == 2  # a known one is still fused
    with pytest.raises(ValueError, match="gate"):
        CollectableMap(gate=0.0)
    with pytest.raises(ValueError, match="collectable_gate"):
        SlamConfig(collectable_gate=math.nan)


def test_a_reading_is_placed_at_its_own_time_from_the_history() -> None:
    """The avatar drives 1 m/s along x: a reading at t = 0.5 is placed from x = 1.5, not from the newest x."""
    items = [encode(AddAvatar("a", "sweeper", (1.0, 1.0, 0.0)))]
    items += [encode(Predict("a", Prediction(k / 4, 1.0, 0.0, 0.0, 0.0, 0.0))) for k in range(1, 9)]
    items.append(seen("a", 0.5, (1.0, math.pi / 2)))  # 1 m to its left at t = 0.5: (1.5, 2.0)
    rep = run(replica(), items)
    ((x, y, n),) = positions(rep).values()
    assert n == 1 and abs(x - 1.5) < 0.03 and abs(y - 2.0) < 0.03


def test_the_weights_include_the_densities_applied_to_the_block() -> None:
    """Two particles, one at the right pose: once a density says which, the sighting is placed from it."""
    rep = SlamReplica(SPEC, SlamConfig(n_particles=2, initial_spread=(0.0, 0.0, 0.0)))
    rep.apply(0, encode(AddAvatar("a", "sweeper", (2.0, 2.0, 0.0))))
    rep.apply(1, still("a", 1.0))
    pf = rep.system.filter("a")
    b = pf.blocks[-1]
    b.states[: b.length] = np.array([[2.0, 2.0, 0.0], [3.0, 2.0, 0.0]], dtype=b.states.dtype)
    pf.correct(0.5, np.array([0.0, -50.0]))  # the second particle is (almost) ruled out
    rep.apply(2, seen("a", 0.5, (1.0, 0.0)))
    ((x, _, _),) = positions(rep).values()
    assert abs(x - 3.0) < 1e-6  # from the first particle; the block's stale equal weights would say 3.5


def test_collectable_readings_the_history_cannot_serve_are_skipped_and_change_nothing() -> None:
    items = [encode(AddAvatar("a", "sweeper", (5.0, 5.0, 0.0))), still("a", 40.0), encode(Request("a"))]
    rep = run(replica(), items)
    d = rep.state_digest()
    n = rep.next_index
    res = [
        rep.apply(n, seen("a", 1.0, (1.0, 0.0))),  # older than the 30 s horizon
        rep.apply(n + 1, seen("a", 41.0, (1.0, 0.0))),  # not predicted yet
        rep.apply(n + 2, seen("ghost", 40.0, (1.0, 0.0))),
    ]
    assert [r.reason.split(":")[0] for r in res] == ["t=1.000", "t=41.000", "no filter for avatar 'ghost'"]
    assert rep.counts["observe.too_old"] == 1 and rep.counts["observe.not_yet_predicted"] == 1
    assert rep.counts["observe.unknown_avatar"] == 1 and len(rep.system.collectables) == 0
    assert rep.state_digest() != d  # the counters and the index moved; nothing else:
    assert rep.system.collectables.sightings == 0


# ----- events ------------------------------------------------------------------------------------------------


def _bad(avatar: str = "a", t: float = 1.0, **sighting: float) -> bytes:
    s = pb.SlamRangeBearing(**({"range": 1.0, "bearing": 0.0} | sighting))
    return pb.SlamEvent(observe=pb.SlamObserve(collectables=pb.SlamCollectables(avatar=avatar, t=t, sightings=[s])))\
        .SerializeToString()


@pytest.mark.parametrize(
    "data, reason",
    [
        (_bad(range=-1.0), "CollectablesReading.sightings[0].range: must be > 0"),
        (_bad(range=0.0), "range: must be > 0"),
        (_bad(bearing=math.nan), "sightings[0].bearing: must be finite"),
        (_bad(range=math.inf), "range: must be > 0"),
        (_bad(range=25.0), "observe.collectables.range: must be <= 20.0 m"),
        (_bad(t=math.nan), "CollectablesReading.t: must be finite"),
        (_bad(avatar=""), "observe.reading.avatar: must be a non-empty string"),
        (
            pb.SlamEvent(observe=pb.SlamObserve(collectables=pb.SlamCollectables(
                avatar="a", t=1.0, sightings=[pb.SlamRangeBearing(range=1.0)] * (MAX_COLLECTABLE_SIGHTINGS + 1))))
            .SerializeToString(),
            f"more than {MAX_COLLECTABLE_SIGHTINGS}",
        ),
    ],
)
def test_bad_collectable_events_are_refused_with_one_line(data: bytes, reason: str) -> None:
    with pytest.raises(EventError) as e:
        decode(data)
    assert reason in e.value.reason and "\n" not in e.value.reason
    rep = replica()
    res = rep.apply(0, data)
    assert res.outcome == "skipped" and res.kind == "malformed" and reason in res.reason
    assert rep.counts == {"malformed": 1}


def test_collectable_events_round_trip_and_encode_refuses_what_decode_refuses() -> None:
    r = CollectablesReading("s1", 3.25, (RangeBearing(1.5, 0.1), RangeBearing(3.8, -0.4)))
    data = encode(Observe(r, "L1"))
    assert decode(data) == Observe(r, "L1") and len(data) < 64
    with pytest.raises(EventError, match="range: must be <= 20"):
        Observe(CollectablesReading("s1", 0.0, (RangeBearing(21.0, 0.0),)))
    with pytest.raises(EventError, match=f"more than {MAX_COLLECTABLE_SIGHTINGS}"):
        Observe(CollectablesReading("s1", 0.0, (RangeBearing(1.0, 0.0),) * (MAX_COLLECTABLE_SIGHTINGS + 1)))
    with pytest.raises(ValueError, match="range: must be > 0"):
        CollectablesReading("s1", 0.0, (RangeBearing(-1.0, 0.0),))


# ----- determinism and checkpoints ---------------------------------------------------------------------------


def stream() -> list[bytes]:
    """Two avatars driving, seeing landmarks (densities: resampling), collectables (some from both) and
    co-occupancy."""
    rng = np.random.default_rng(3)
    items = [encode(AddAvatar("a", "sweeper", (3.0, 3.0, 0.0))), encode(AddAvatar("b", "seeker", (9.0, 4.0, 1.0)))]
    truth = [(6.0, 3.5), (8.0, 7.0), (11.0, 6.5), (4.5, 9.0)]
    marks = {1: (7.0, 2.0), 2: (10.0, 9.0), 3: (5.0, 7.0)}
    pose = {"a": np.array([3.0, 3.0, 0.0]), "b": np.array([9.0, 4.0, 1.0])}
    for k in range(1, 121):
        t = k * 0.25
        for av, (v, w) in (("a", (0.3, 0.05)), ("b", (0.25, -0.04))):
            items.append(encode(Predict(av, Prediction(t, v, 0.0, w, 0.02, 0.01))))
            p = pose[av]
            p[2] += w * 0.25
            p[0] += v * 0.25 * math.cos(p[2])
            p[1] += v * 0.25 * math.sin(p[2])
            if k % 3 == 0:
                rb = []
                for cx, cy in truth:
                    r = math.hypot(cx - p[0], cy - p[1])
                    if r < 4.5:
                        b = math.atan2(cy - p[1], cx - p[0]) - p[2] + float(rng.normal(0, 0.003))
                        rb.append((r + float(rng.normal(0, 0.01)), b))
                if rb:
                    items.append(seen(av, t - 0.1, *rb))
            if k % 2 == 0:
                lms = tuple(
                    Sighting(i, math.hypot(mx - p[0], my - p[1]) * (1 + float(rng.normal(0, 0.03))),
                             math.atan2(my - p[1], mx - p[0]) - p[2] + float(rng.normal(0, 0.02)))
                    for i, (mx, my) in marks.items()
                )
                items.append(encode(Observe(LandmarkReading(av, t - 0.2, lms), "L1")))
            if k % 5 == 0:
                items.append(encode(Observe(CooccupancyReading(av, t - 0.05, 0.15))))
        if k % 4 == 0:
            items += [encode(Request("a")), encode(Request("b"))]
    return items


def test_the_collectable_map_is_deterministic_and_checkpoints_exactly_at_any_cut() -> None:
    items = stream()
    full = run(replica(seed=5), items)
    assert run(replica(seed=5), items).state_digest() == full.state_digest()
    assert len(full.system.collectables) >= 3 and full.counts.get("request.resampled", 0) > 0
    for k in (0, 1, len(items) // 3, len(items) // 2 + 1, len(items) - 1, len(items)):
        part = run(replica(seed=5), items[:k])
        blobs = part.checkpoint()
        assert "collectables" in blobs
        again = SlamReplica.restore(blobs)
        assert again.state_digest() == part.state_digest()
        assert again.system.collectables.published() == part.system.collectables.published()
        run(again, items, start=k)
        assert again.state_digest() == full.state_digest()
        assert again.system.collectables.published() == full.system.collectables.published()
        assert again.system.collectables.next_id == full.system.collectables.next_id


def test_the_digest_and_the_checkpoint_see_the_collectable_map() -> None:
    items = stream()
    rep = run(replica(), items[: len(items) // 2])
    d = rep.state_digest()
    c = next(iter(rep.system.collectables.items.values()))
    c.swx += 1e-9
    assert rep.state_digest() != d
    c.swx -= 1e-9
    rep.system.collectables.next_id += 1
    assert rep.state_digest() != d
    rep.system.collectables.next_id -= 1
    assert rep.state_digest() == d
    blobs = rep.checkpoint()
    broken = dict(blobs)
    broken["collectables"] = blobs["collectables"][:-3]
    with pytest.raises(CheckpointError, match="collectables"):
        SlamReplica.restore(broken)
    rep.system.collectables.something_new = 1  # type: ignore[attr-defined]
    with pytest.raises(CheckpointError, match="something_new"):
        rep.checkpoint()


# ----- the sensor agent on a rendered frame, end to end --------------------------------------------------------


class FrameCtx(FakeCtx):
    """FakeCtx plus the avatar agent's answer to a frame request (the encoded camera frames, by number)."""

    def __init__(self, config: dict[str, Any], frames: dict[int, bytes]) -> None:
        super().__init__(config, agent_id="L1", name="A6.2.1")
        self.frames = frames

    async def request(self, to: str, payload: bytes, timeout: float) -> bytes:
        return self.frames[json.loads(payload)["n"]]


def process_frames(frames: list[tuple[str, Any]], collectables: bool) -> list[bytes]:
    """Each (avatar, haa.sim CameraFrame) through AgentSensorLandmark's processing (frame request, detection,
    the atomic batch): the Observe events it appended to slam/log, in order."""
    from haa.pb import sim_pb2 as spb
    from haa.sim.arena import load_arena
    from haa.sim.convert import encode_frame

    arena = load_arena("large")
    enc = {n: encode_frame(f, spb.IMAGE_ENCODING_RAW_RGB).SerializeToString() for n, (_, f) in enumerate(frames)}
    cfg = {"supervisor": "sup", "marker_dictionary": arena.marker_dictionary, "marker_size": arena.marker_size,
           "landmark_ids": sorted(arena.landmarks)}
    if collectables:
        cfg["collectables"] = True
    ctx = FrameCtx(cfg, enc)
    agent = AgentSensorLandmark(ctx)

    async def go() -> None:
        for n, (av, f) in enumerate(frames):
            rec = {"avatar": av, "agent": f"av-{av}", "kind": "camera", "t": f.time, "n": n, "frame": n}
            await agent.on_message("sup", team.dumps(
                {"op": "process", "key": f"slam/raw/{av}/{n}", "proc": "sensor_landmark", "reading": rec}))
            await asyncio.gather(*agent.jobs)

    asyncio.run(go())
    done = [m for _, m in ctx.sent if m.get("op") == "done"]
    assert len(done) == len(frames) and all(m["ok"] and m["wrote"] for m in done)
    return [bytes(item) for ops in ctx.writes for op in ops if op.HasField("log_append")
            for item in op.log_append.items]


def test_collectables_in_rendered_frames_become_identified_collectables_near_the_truth() -> None:
    """haa-sim's large arena: sweeper s1 drives north towards c7 (and sees c8 farther on), s2 looks at c8
    from the west. The avatars' predictions come from their odometry, their start poses are the known ones;
    the frames go through the sensor agent; the replica identifies two collectables, c8 seen by both."""
    from haa.sim.world import World

    w = World.from_arena("large", seed=1)
    truth = w.arena.collectables
    starts = {"s1": (17.28, 3.3, math.pi / 2), "s2": (15.21, 7.3, 0.0)}
    ids = {av: w.add_avatar("sweeper", pose, av) for av, pose in starts.items()}
    log = [encode(AddAvatar(av, "sweeper", pose, w.time, DRIFT["sweeper"])) for av, pose in starts.items()]
    odo = {av: (w.time, w.odometry(ids[av])) for av in starts}
    frames = []
    w.set_velocity(ids["s1"], 0.3, 0.0)
    for k in range(1, 13):
        w.step(0.25)
        for av in starts:
            t0, p0 = odo[av]
            p1 = w.odometry(ids[av])
            log.append(encode(Predict(av, odometry_prediction(t0, p0, w.time, p1, DRIFT["sweeper"]))))
            odo[av] = (w.time, p1)
        if k % 4 == 0:
            frames += [(av, w.capture(ids[av])) for av in starts]
    assert frames[-1][1].time == pytest.approx(3.0)

    # with the flag off the agent writes what it wrote before: no collectables reading
    off = [decode(d) for d in process_frames(frames, collectables=False)]
    assert not any(isinstance(e.reading, CollectablesReading) for e in off)  # type: ignore[union-attr]

    obs = process_frames(frames, collectables=True)
    evs = [decode(d) for d in obs]
    assert sum(isinstance(e.reading, CollectablesReading) for e in evs) == len(frames)  # type: ignore[union-attr]
    assert [e for e in evs if not isinstance(e.reading, CollectablesReading)] == off  # type: ignore[union-attr]
    rep = run(replica(), log + obs)
    assert rep.counts.get("observe.applied") == len(evs)
    cols = rep.system.collectables.items
    assert len(cols) == 2
    for cid, name, n in ((1, "c7", 3), (2, "c8", 6)):  # c8: 3 frames of s1 and 3 of s2, one collectable
        c = cols[cid]
        err = math.hypot(c.x - truth[name][0], c.y - truth[name][1])
        assert err < 0.3, (name, err)
        assert c.n == n
    assert cols[1].t_first == pytest.approx(1.0) and cols[2].t_first == pytest.approx(1.0)


# ----- SupervisorSLAM: the flag and the publication ----------------------------------------------------------


def test_supervisor_passes_the_flag_and_publishes_the_estimates_only_when_they_changed() -> None:
    off, off_ctx = supervisor()
    on, on_ctx = supervisor(collectables=True)

    async def go() -> None:
        for sup in (off, on):
            sup._spawn("sensor_landmark")
            await asyncio.gather(*sup.tasks)
        assert "collectables" not in off_ctx.spawned[0][1]  # explore/congregate: the config as before
        assert on_ctx.spawned[0][1]["collectables"] is True

        on.replica = replica()
        items = [encode(AddAvatar("a", "sweeper", (5.0, 5.0, 0.0))), still("a", 1.0)]
        run(on.replica, items)

        def published() -> list[Any]:
            return [decode_value("json", op.put.value) for ops in on_ctx.writes for op in ops
                    if op.HasField("put") and op.put.key == team.K_FORAGE_COLLECTABLES]

        async def publish() -> None:
            on.dirty = True
            await on._publish()
            await asyncio.gather(*on.tasks)

        await publish()
        assert published() == []  # nothing identified yet: no key
        on.replica.apply(2, seen("a", 0.5, (2.0, 0.0)))
        await publish()
        assert len(published()) == 1 and published()[0]["1"]["n"] == 1
        await publish()  # the map, the estimates again; the collectables unchanged: not rewritten
        assert len(published()) == 1
        on.replica.apply(3, seen("a", 0.6, (2.05, 0.0)))
        await publish()
        assert len(published()) == 2
        keys = {op.put.key for ops in on_ctx.writes for op in ops if op.HasField("put")}
        assert not any(k.startswith(team.K_FORAGE_STATE) for k in keys)

    asyncio.run(go())
