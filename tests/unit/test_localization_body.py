"""A body that pitches, rolls and heaves about its nominal attitude on the road, as a real car's does.

The r_n soft constraint of the map matcher is centred on the nominal attitude; a real body sits a few
tenths of a degree off it (load, suspension). Cold starts from GNSS, with no heading, must still lock
onto the right basin and track it; fixed seeds on the synthetic frames of test_localization (the
map's landmarks projected from the true, pitched pose). Accuracy is asserted, not time.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer import geometry as geo
from mapcontainer.localization import (
    CameraFrame,
    GnssMeasurement,
    Localizer,
    LocalizerParams,
    MapMatcher,
    MatcherParams,
    OdometryMeasurement,
)
from mapcontainer.localization.search import PoseSearchParams
from mapcontainer.sim import World, load_scenario, with_error_sources, with_traffic
from mapcontainer.vehicle import VehicleAgent, camera_frame

from .test_localization import HDMAP, pose_error, pose_on, synth_frame
from .test_sim import CAR_BODY


def body_pose(s, t, *, heave=0.03, roll_deg=0.3, pitch_deg=0.5, lane=0):
    """The pose at arc length s of a lane with the body heaved (m), rolled and pitched (deg) about nominal,
    plus a suspension motion (1 Hz pitch, 0.7 Hz roll, 1.3 Hz heave)."""
    x = pose_on(s, lane)
    x[2] += heave + 0.01 * np.sin(2 * np.pi * 1.3 * t)
    x[3] += np.radians(roll_deg + 0.2 * np.sin(2 * np.pi * 0.7 * t + 1.0))
    x[4] += np.radians(pitch_deg + 0.25 * np.sin(2 * np.pi * 1.0 * t + 2.0))
    return x


def _drive_body(n, seed, *, s0, v=10.0, **body):
    """A cold start (no heading, GNSS metres off) and n frames at 10 Hz with a moving body."""
    rng = np.random.default_rng(seed)
    loc = Localizer(HDMAP)
    dt = 0.1
    bias = rng.normal(0.0, 1.5, 2)
    out = []
    for k in range(n):
        t = k * dt
        s = s0 + v * t
        truth = body_pose(s, t, **body)
        yaw_rate = geo.wrap_angle(pose_on(s + v * dt)[5] - pose_on(s - v * dt)[5]) / (2 * dt)
        odo = OdometryMeasurement(v + rng.normal(0, 0.05), yaw_rate + rng.normal(0, 0.005))
        gnss = GnssMeasurement(truth[:3] + np.r_[bias + rng.normal(0, 0.8, 2), rng.normal(0, 1.5)], 2.0, 3.0)
        frame, _ = synth_frame(truth, rng, p_detect=0.9)
        out.append((truth, loc.step(t, frame, odo, gnss)))
    return loc, out


@pytest.mark.parametrize(("seed", "s0", "pitch_deg"), [(21, 170.0, 0.5), (22, 190.0, -0.5), (23, 20.0, 0.6)])
def test_cold_start_with_a_pitched_body_locks_and_tracks(seed, s0, pitch_deg):
    loc, out = _drive_body(40, seed, s0=s0, pitch_deg=pitch_deg)
    modes = [r.mode for _, r in out]
    first = modes.index("map_matching")
    assert first <= 5, modes
    assert modes[first:].count("map_matching") >= 0.9 * len(modes[first:])
    errs = np.array([pose_error(r.pose_filtered, truth) for truth, r in out[first:] if r.mode == "map_matching"])
    horiz = np.hypot(errs[:, 0], errs[:, 1])
    assert horiz.max() < 0.5 and np.degrees(np.abs(errs[:, 5]).max()) < 1.0, horiz
    assert np.sqrt(np.mean(horiz**2)) < 0.2
    # The attitude follows the body, not the nominal one r_n is centred on.
    assert np.degrees(np.sqrt(np.mean(errs[5:, 4] ** 2))) < 0.2
    assert loc.stats["initialised"] == 1


# A lamp post 1.6 m ahead of the camera and metres to the side projects thousands of px off the image.
NEAR_POLE_S = 6.0


@pytest.mark.parametrize("seed", [0, 1])
def test_a_landmark_beside_the_camera_does_not_capture_a_far_detection(seed):
    """From a start as wide as the pose search's, a clutter pole in the image must not be associated with
    the lamp post beside the car: linearised at 1.6 m depth its projection's uncertainty is thousands of
    px, so the Mahalanobis gate lets the detection pass, and the LM follows it metres away (the trap is
    real: without the near-landmark rule the same solve ends 8-11 m off)."""
    truth = pose_on(NEAR_POLE_S)
    frame, _ = synth_frame(truth, np.random.default_rng(seed))
    clutter = np.array([[1100.0, 400.0, 1102.0, 250.0]])
    frame = CameraFrame(
        frame.intr,
        frame.T_body_cam,
        frame.points_uv,
        frame.points_cls,
        np.vstack([frame.poles_uv, clutter]),
        frame.lane_mask,
    )
    P = np.diag([0.75**2, 0.75**2, 0.05**2, 0.01**2, 0.01**2, np.radians(2.0) ** 2])
    exact = MatcherParams(landmark_map_sigma_m=0.0)  # the frame comes from the exact map
    res = MapMatcher(HDMAP, exact).match(frame, truth, P)
    assert np.hypot(*pose_error(res.pose_filtered, truth)[:2]) < 0.2
    trapped = MapMatcher(HDMAP, exact.model_copy(update={"near_sigmas": 0.0})).match(frame, truth, P)
    assert np.hypot(*pose_error(trapped.pose_filtered, truth)[:2]) > 3.0


def _as_recorded(sc):
    """The simulated cases below are start-up situations of the localizer found in these scenes: the traffic
    as listed (no per-run variation) and no error source but clutter (the exact map and camera calibration,
    white detector noise, true clocks), so that each seed replays its case. How cold starts fare with the
    realistic error sources is the experiments' question, not these regression tests'."""
    return with_traffic(with_error_sources(sc, ["clutter"]), False)


def _sim_cold_start(scenario: str, seed: int, vid: str, seconds: float):
    """Modes and horizontal errors of one simulated vehicle's filtered pose from a cold start (GNSS only),
    the simulated bodies moving about nominal like a car's (CAR_BODY)."""
    world = World(_as_recorded(load_scenario(scenario, {"sensors": {"body": CAR_BODY}})), seed=seed)
    loc = Localizer(world.hdmap)
    modes, errs, attitude = [], [], []
    for k in range(round(seconds / world.dt)):
        t = k * world.dt
        states = world.states(t)
        obs, _ = world.sense(k, t, vid, states)
        res = loc.step(t, camera_frame(obs), obs.odometry, obs.gnss)
        truth = states[vid].pose
        attitude.append(truth[3:5])
        modes.append(res.mode)
        errs.append(np.inf if res.pose_filtered is None else float(np.hypot(*(res.pose_filtered - truth)[:2])))
    return modes, np.array(errs), np.array(attitude)


@pytest.mark.parametrize(
    ("seed", "vid"),
    [
        (0, "cv1"),  # the search's solution in the true basin was not fully solved: a basin 4 m off won
    ],
)
def test_simulated_cold_start_locks_onto_the_true_basin(seed, vid):
    modes, errs, attitude = _sim_cold_start("paper-urban", seed, vid, 3.0)
    assert np.degrees(np.abs(attitude).max()) > 0.3  # the body is pitched or rolled a few tenths of a degree
    matched = np.array(modes) == "map_matching"
    assert matched[:5].any(), modes
    assert matched.mean() > 0.85
    assert errs[matched].max() < 0.5, errs


def test_a_lone_start_up_hypothesis_does_not_stop_the_search():
    """Urban seed 0, cv2 (cold start, course over ground after 1.8 s): the first search sees one pole and finds
    one converged solution, 7 m across and 10 degrees off, too weakly constrained to win. It kept matching its
    pole and the lanes, so it was never dropped, and no search ran again: the vehicle stayed in fallback for the
    whole episode. The search now runs on while the lone hypothesis has not won, and the true basin takes over."""
    modes, errs, _ = _sim_cold_start("paper-urban", 0, "cv2", 4.0)
    matched = np.array(modes) == "map_matching"
    assert matched[:32].any(), modes  # locked by 3.2 s
    first = int(np.argmax(matched))
    assert matched[first:].mean() > 0.9, modes
    assert errs[matched].max() < 0.5, errs


@pytest.mark.parametrize("rule", ["landmarks", "posterior"])
def test_a_vehicle_that_cannot_keep_up_starts_in_the_true_basin(rule):
    """Urban seed 2, cv2 handling every other frame (as in a fleet on a loaded machine): a search on a frame
    with one pole and the lanes found one basin 35 degrees off, which won on one pole and two lane samples
    and held the vehicle 30-50 m off until GNSS refuted it. Rule 'landmarks' (the default): the first search
    waits for a frame that could decide a start (enough detections for the search's rules, were all of them
    inliers). Rule 'posterior': a basin wins on its posterior mass, a pole counting once per view_baseline_m of
    travel against a basin the search did not reach. Either way the vehicle locks onto the true basin."""
    world = World(_as_recorded(load_scenario("paper-urban")), seed=2)
    params = LocalizerParams(search=PoseSearchParams(accept=rule))
    agent = VehicleAgent(world.hdmap, "cv2", world.fleet, params=params)
    errs, modes = [], []
    for tick in world.run(5.0):
        if round(tick.t / world.dt) % 2 == 0:
            agent.handle(tick.t, tick.frames["cv2"])
            res = agent.last_result
            ok = res.pose_filtered is not None
            errs.append(np.hypot(*(res.pose_filtered - tick.states["cv2"].pose)[:2]) if ok else np.nan)
            modes.append(res.mode)
    matched = np.array(modes) == "map_matching"
    assert matched[:17].any(), modes  # locked by 3.2 s
    first = int(np.argmax(matched))
    assert matched[first:].all() and np.array(errs)[first:].max() < 0.5, (modes, errs)
    if rule == "landmarks":
        assert agent.localizer.stats["initialising: too few features to search"] > 0


def test_a_state_that_gnss_refutes_is_left():
    """A confident state in the wrong place, GNSS fix after fix refused by the gate: farther than GNSS can
    err for 5 fixes in a row, the localizer starts again from GNSS and locks onto the true basin. (Urban
    seed 2, cv2 handling every other frame, once took a wrong basin 35 degrees off this way and stayed 30-50 m
    off for the whole episode; that start is now right (the test above), so here the state is pushed 30 m away
    after the vehicle has locked.)"""
    world = World(_as_recorded(load_scenario("paper-urban")), seed=2)
    agent = VehicleAgent(world.hdmap, "cv2", world.fleet)
    errs, modes = [], []
    for tick in world.run(10.0):
        if abs(tick.t - 4.0) < 1e-9:
            assert agent.last_result.mode == "map_matching"
            agent.localizer.y[:2] += [30.0, 0.0]
        agent.handle(tick.t, tick.frames["cv2"])
        res = agent.last_result
        ok = res.pose_filtered is not None
        errs.append(np.hypot(*(res.pose_filtered - tick.states["cv2"].pose)[:2]) if ok else np.nan)
        modes.append(res.mode)
    errs, matched = np.array(errs), np.array(modes) == "map_matching"
    assert agent.localizer.stats["gnss_divergence_reset"] == 1 and np.nanmax(errs) > 15.0
    assert matched[-20:].mean() >= 0.8 and errs[-20:].max() < 0.3, (modes, errs)  # the last 2 s: the true basin
