"""The vehicle agent on simulated frames: accuracy, message size and the centralized payload."""

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer import lanemask
from mapcontainer.metrics import rmse
from mapcontainer.sim import World, load_scenario, with_error_sources, with_traffic
from mapcontainer.vehicle import FrameBacklog, VehicleAgent
from schemas import ObjectObservations, RawObservations, VehiclePrior, decode, encode
from schemas.arrays import cov_from_upper


def as_recorded(name: str):
    """The scene as these tests were written for: the traffic as listed, no error source but clutter (the
    exact map and camera calibration, white detector noise, true clocks). They check the agent's localizer
    and its input handling under ideal sensing; how it fares with the realistic error sources is the
    experiments' figure (paper-urban seed 0 with every source on: map-matched in about half of the frames
    after 3 s)."""
    return with_traffic(with_error_sources(load_scenario(name), ["clutter"]), False)


@pytest.fixture(scope="module")
def urban_run():
    world = World(as_recorded("paper-urban"), seed=0)
    agents = {v: VehicleAgent(world.hdmap, v, world.fleet) for v in world.vehicle_ids}
    out = []
    for tick in world.run(8.0):
        for vid, frame in tick.frames.items():
            out.append((tick, vid, frame, agents[vid].handle(tick.t, frame)))
    return out


def test_self_localization_accuracy_and_consistency(urban_run):
    err, nees, matched = [], [], []
    for tick, vid, frame, prior in urban_run:
        assert isinstance(prior, VehiclePrior) and prior.sender == vid and prior.t_meas == frame.t_meas
        if tick.t < 3.0:  # initialisation from GNSS first
            continue
        e = np.asarray(prior.pose, float) - tick.states[vid].pose
        e[3:] = geo.wrap_angle(e[3:])
        nees.append(e @ np.linalg.solve(cov_from_upper(prior.pose_cov), e))  # honest in fallback too
        matched.append(prior.quality.mode == "map_matching")
        if matched[-1]:
            err.append(e[:2])
    assert rmse(err) < 0.3
    assert np.mean(matched) > 0.9
    assert 1.0 < np.mean(nees) < 15.0


def test_prior_carries_this_frames_detections_and_is_compact(urban_run):
    _, _, frame, prior = urban_run[-1]
    np.testing.assert_array_equal(prior.objects.p_body_cm, frame.objects.p_body_cm)
    # With 14 observed objects a prior still encodes to <= 600 bytes (an ETSI CPM with 14 objects ~540 B).
    rng = np.random.default_rng(0)
    p = rng.uniform([-5, -30, -0.5], [60, 30, 0.5], (14, 3))
    cov = np.array([np.diag(rng.uniform(0.01, 0.4, 3)) for _ in range(14)])
    big = prior.model_copy(
        update={
            "objects": ObjectObservations.from_metres(p, cov, np.ones(14, np.uint8)),
            "seq": 123456,
            "fleet": "fleet-01",
        }
    )
    payload = encode(big)
    assert len(payload) <= 600, len(payload)
    back = decode(payload, VehiclePrior)
    assert isinstance(back, VehiclePrior) and len(back.objects) == 14


def test_centralized_mode_forwards_the_raw_observations():
    world = World(load_scenario("overlap"), seed=0)
    agent = VehicleAgent(world.hdmap, "cv1", world.fleet, mode="centralized")
    tick = world.tick(0)
    raw = agent.handle(0.05, tick.frames["cv1"])
    assert isinstance(raw, RawObservations) and raw.sender == "cv1" and raw.t_sent == 0.05
    # the lane mask pooled to the width the host's matcher uses (tests/unit/test_lane_mask_resolution.py)
    assert raw.lane_mask_png == b"" and raw.lane_mask_pooled_png == lanemask.pool_png(
        tick.frames["cv1"].lane_mask_png, agent.localizer.params.matcher.lane_dt_max_width_px
    )
    assert len(encode(raw)) > 3 * 400
    with pytest.raises(ValueError, match="given a frame from cv0"):
        agent.handle(0.0, tick.frames["cv0"])


def test_frames_without_time_to_match_still_carry_the_heading_through_a_turn():
    """A vehicle that falls behind skips frames; their odometry must still reach the localizer.

    Urban seed 0, cv2 turns at 35 degrees/s until 8.9 s and then drives straight. With the frames of
    8.3-9.2 s lost, the prediction over the gap averaged 35 and 0 degrees/s into a heading 11 degrees
    off, and the matches that followed confirmed it (4 m off at 10.9 s). Skipped, they keep it.
    """
    world = World(as_recorded("paper-urban"), seed=0)
    agent = VehicleAgent(world.hdmap, "cv2", world.fleet)
    turning, after = [], []
    for tick in world.run(10.5):
        frame, truth = tick.frames["cv2"], tick.states["cv2"]
        if 8.25 < tick.t < 9.25:
            assert agent.skip(tick.t, frame) is None
            turning.append(abs(truth.yaw_rate))
            continue
        prior = agent.handle(tick.t, frame)
        if tick.t > 9.25:
            e = np.asarray(prior.pose, float) - truth.pose
            after.append((np.hypot(*e[:2]), abs(geo.wrap_angle(e[5])), prior.quality.mode))
    assert max(turning) > np.radians(30.0) and min(turning) < np.radians(1.0)  # the gap spans the turn's end
    err, yaw, mode = zip(*after, strict=True)
    assert max(err) < 0.3 and max(yaw) < np.radians(1.0)
    assert mode.count("map_matching") >= 0.8 * len(mode)
    with pytest.raises(ValueError, match="frame from cv1"):
        agent.skip(tick.t, tick.frames["cv1"])


def test_a_frame_from_the_future_or_with_bad_odometry_is_refused_and_changes_nothing():
    """A broken clock once moved the localizer 1e6 s ahead: every later frame went "backwards", and the
    vehicle kept sending its frozen pose with fresh times (46 m off after 8 s). Refused frames now send
    nothing and leave the localizer where it was."""
    world = World(as_recorded("paper-urban"), seed=0)
    agent = VehicleAgent(world.hdmap, "cv0", world.fleet)
    out = []
    for k, tick in enumerate(world.run(6.0)):
        frame = tick.frames["cv0"]
        if k == 25:
            out.append(agent.handle(tick.t, frame.model_copy(update={"t_meas": frame.t_meas + 1e6})))
            assert agent.skip(tick.t, frame.model_copy(update={"t_meas": frame.t_meas + 1e6})).reason == "future"
        if k == 35:
            bad = frame.model_copy(update={"odometry": frame.odometry.model_copy(update={"speed": float("inf")})})
            out.append(agent.handle(tick.t, bad))
        out.append(agent.handle(tick.t, frame))
        truth = tick.states["cv0"].pose
    refused = [m for m in out if not isinstance(m, VehiclePrior)]
    assert [(r.reason, r.detail.split(":")[0]) for r in refused] == [
        ("future", "frame measured at 1000002.500 s handled at 2.500 s"),
        ("bad_input", "odometry not finite"),
    ]
    priors = [m for m in out if isinstance(m, VehiclePrior)]
    assert len(priors) == 60 and priors[-1].quality.mode == "map_matching"
    assert np.hypot(*(np.asarray(priors[-1].pose[:2], float) - truth[:2])) < 0.3


def _behind(world, duration_s: float, work_s) -> dict[str, list]:
    """Vehicles whose every matched frame takes ``work_s(solves)`` seconds (time as an argument: a function of the
    matcher's solves in the frame, not of this machine's speed), fed at the world's 10 Hz: frames that arrive while
    a vehicle works wait in its FrameBacklog; when it is free it skips the stale ones (their odometry and GNSS kept)
    and matches the newest, as the vehicle service does. Per vehicle, rows (t, the matched frame's age, prior,
    true pose, health) of its matched frames, and its agent last."""
    out = {}
    for vid in world.vehicle_ids:
        out[vid] = ([], VehicleAgent(world.hdmap, vid, world.fleet), FrameBacklog(), [0.0])
    for tick in world.run(duration_s):
        for vid, (rows, agent, backlog, free_at) in out.items():
            backlog.put((tick, tick.frames[vid]))
            if tick.t < free_at[0] - 1e-9:  # still working on an earlier frame
                continue
            stale, (newest, frame) = backlog.take(0.0)
            for _, f in stale:
                assert agent.skip(tick.t, f) is None
            solves0 = agent.localizer.matcher.solves
            prior = agent.handle(tick.t, frame)
            free_at[0] = tick.t + work_s(agent.localizer.matcher.solves - solves0)
            rows.append((tick.t, tick.t - newest.t, prior, newest.states[vid].pose, agent.health()[0]))
    return {vid: (rows, agent) for vid, (rows, agent, _, _) in out.items()}


@pytest.mark.slow
def test_a_vehicle_that_falls_behind_drops_stale_frames_and_keeps_its_lock():
    """Every frame's work costs 50 ms plus 40 ms per matcher solve (a tracking frame of 1-2 solves: 90-130 ms, more
    than the 100 ms frame period; a search frame of 6-10 solves: 290-450 ms), so the vehicles fall behind from
    the start and stay behind: each matches under two thirds of the frames, always the newest one, and skips the
    rest. Urban, every error source on, development seed 3, against the same vehicles matching every frame: every
    vehicle localizes within 8 s, never re-initialises, is map matched and healthy after its lock as often (the
    blind stretches of the road are the same), and its error after the lock is as small."""
    duration = 15.0
    behind = _behind(World(load_scenario("paper-urban"), seed=3), duration, lambda solves: 0.05 + 0.04 * solves)
    every = _behind(World(load_scenario("paper-urban"), seed=3), duration, lambda solves: 0.0)

    def after_lock(rows):
        """(map matched, healthy, horizontal error) of the rows from a second after the first map match."""
        matched = [p.quality.mode == "map_matching" for _, _, p, _, _ in rows]
        lock = matched.index(True)
        t_lock = rows[lock][0]
        assert t_lock < 8.0, t_lock  # behind, a cold start searches fewer frames: cv2 locks at 5.9 s, not 2.4 s
        out = [
            (m, h == "ok", float(np.hypot(*(np.asarray(p.pose[:2], float) - x[:2]))))
            for (t, _, p, x, h), m in zip(rows, matched, strict=True)
            if t >= t_lock + 1.0
        ]
        return np.array(out, dtype=float).T

    for vid, (rows, agent) in behind.items():
        t, age, *_ = zip(*rows, strict=True)
        assert len(rows) < 0.65 * duration * 10, (vid, len(rows))  # it fell behind ...
        assert max(age) < 1e-9  # ... and the frame it matched was always the newest there was
        stats = agent.localizer.stats
        assert stats.get("initialised") == 1 and not stats.get("gap_reset") and not stats.get("jump_reset"), stats
        matched, ok, err = after_lock(rows)
        ref_matched, ref_ok, ref_err = after_lock(every[vid][0])
        assert matched.mean() >= ref_matched.mean() - 0.05 and ok.mean() >= ref_ok.mean() - 0.05, (vid, matched, ok)
        assert rmse(err[matched > 0]) < max(0.2, 1.25 * rmse(ref_err[ref_matched > 0])), (vid, err, ref_err)
