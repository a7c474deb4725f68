"""The localizer's start-up / recovery state machine (mapcontainer.localization.startup) alone: its phases and
transitions on synthetic cases (the synthetic map and drives of test_localization)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapcontainer.localization import GnssMeasurement, Localizer, LocalizerParams, OdometryMeasurement
from mapcontainer.localization.matcher import MapMatcher
from mapcontainer.localization.search import PoseSearchParams, SearchOutcome
from mapcontainer.localization.startup import Phase, StartupMachine

from .test_localization import EXACT, HDMAP, P_TRACK, _drive, pose_error, pose_on, synth_frame

ODO = OdometryMeasurement(10.0, 0.0)
POSTERIOR = dict(search=PoseSearchParams(accept="posterior"))  # the opt-in start-up rule


def _fix(truth, rng=None, sigma=0.8):
    noise = np.zeros(2) if rng is None else rng.normal(0, sigma, 2)
    return GnssMeasurement(truth[:3] + np.r_[noise, 0.0], 2.0, 3.0)


def _phases(loc, steps):
    """Step loc through (t, frame, odometry, gnss) tuples; the phase after each step."""
    out = []
    for step in steps:
        loc.step(*step)
        out.append(loc.phase)
    return out


def _first_steps(params):
    truth = pose_on(40.0)
    loc = Localizer(HDMAP, params, initial_yaw=truth[5])
    assert loc.phase is Phase.UNINITIALISED
    res = loc.step(0.0, None, ODO, None)
    assert loc.phase is Phase.UNINITIALISED and res.reason == "initialising: no GNSS fix"
    rng = np.random.default_rng(0)
    frame, _ = synth_frame(truth, rng)
    res = loc.step(0.1, frame, ODO, _fix(truth))
    assert res.initialized and loc.stats["initialised"] == 1 and loc.stats["search"] == 1
    return loc, res, truth, rng


def test_initial_yaw_waits_for_gnss_then_tracks():
    loc, res, _, rng = _first_steps(LocalizerParams(**EXACT))
    # The GNSS position is too wide for one local solve: the search runs, and leaves its basins as hypotheses.
    # Its budget (search.solves_per_frame) solves the best start only (its basin a hypothesis); the other two are
    # carried to the next frame (with the budget off, this frame's search rejected the lone basin as 'too few
    # features (3 constraints)': the frames after are the same either way).
    assert loc.phase is Phase.SEARCHING and res.mode == "fallback" and res.reason.startswith("search: ")
    assert res.reason == "search: searching: 2 starts pending" and len(loc.startup.hyps) == 1
    assert len(loc.startup.pending) == 2
    # The lone hypothesis has not won on the next frame: the search runs again for rivals.
    frame, _ = synth_frame(pose_on(41.0), rng)
    res = loc.step(0.2, frame, ODO, _fix(pose_on(41.0)))
    assert loc.phase is Phase.SEARCHING and res.reason == "searching: 1 hypotheses" and loc.stats["search"] == 2
    frame, _ = synth_frame(pose_on(42.0), rng)
    res = loc.step(0.3, frame, ODO, _fix(pose_on(42.0)))
    assert loc.phase is Phase.TRACKING and res.mode == "map_matching"  # the hypothesis won
    assert loc.startup.hyps == [] and np.hypot(*pose_error(res.pose, pose_on(42.0))[:2]) < 0.2


def test_initial_yaw_waits_for_gnss_then_tracks_by_posterior_mass():
    loc, res, truth, rng = _first_steps(LocalizerParams(**EXACT, **POSTERIOR))
    # The GNSS position is too wide for one local solve: the search runs; its budget solves the best start (its basin
    # a hypothesis) and carries the other two to the next frame.
    assert loc.phase is Phase.SEARCHING and res.mode == "fallback" and len(loc.startup.hyps) == 1
    assert res.reason == "search: searching: 2 starts pending"
    # A point and a pole explained again (three constraints on x, y, yaw) and no rival basin: the basin holds the
    # posterior mass, it is taken.
    steps = []
    for k, s in enumerate((41.0, 42.0, 43.0, 44.0)):
        frame, _ = synth_frame(pose_on(s), rng)
        res = loc.step(0.2 + 0.1 * k, frame, ODO, _fix(pose_on(s)))
        steps.append((loc.phase, res.mode))
        e = pose_error(res.pose, pose_on(s))[:2]
        assert e @ np.linalg.solve(res.cov[:2, :2], e) < 13.8  # honest: within its 99.9 % ellipse
        if res.mode == "map_matching":  # the first lock 0.25 m off (along the road, where its sigma is metres)
            assert np.hypot(*e) < 0.3
    # That lock is wide along the road (one point, one pole: about 6 m 1-sigma), so the prediction stays wide and
    # the next frame is searched again: one frame in fallback while its starts are solved, then tracking again.
    assert steps == [
        (Phase.TRACKING, "map_matching"),
        (Phase.SEARCHING, "fallback"),
        (Phase.TRACKING, "map_matching"),
        (Phase.TRACKING, "map_matching"),
    ]


def test_the_phase_is_uninitialised_exactly_while_there_is_no_state():
    """Cold start on a two-way road where the landmarks are sparse: UNINITIALISED while the frames cannot decide
    the heading, then TRACKING."""
    loc2 = Localizer(HDMAP, LocalizerParams(**EXACT))
    rng = np.random.default_rng(13)
    phases, inits = [], []
    for k in range(40):
        truth = pose_on(55.0 + k)
        frame, _ = synth_frame(truth, rng, p_detect=0.9)
        res = loc2.step(0.1 * k, frame, ODO, _fix(truth, rng))
        phases.append(loc2.phase)
        inits.append(res.initialized)
    assert all((ph is Phase.UNINITIALISED) == (not ok) for ph, ok in zip(phases, inits, strict=True))
    assert phases[:5] == [Phase.UNINITIALISED] * 5 and phases[-1] is Phase.TRACKING
    assert loc2.stats["initialising: too few features to search"] >= 5 and loc2.stats["initialised"] == 1
    assert Phase.VERIFYING not in phases


def test_a_known_start_pose_is_verified_then_tracked():
    truth = pose_on(40.0)
    cov = np.diag([0.09, 0.09, 0.01, 1e-4, 1e-4, np.radians(1.0) ** 2])
    start = (truth + [0.2, -0.2, 0.0, 0.0, 0.0, 0.01], cov)
    rng = np.random.default_rng(3)
    steps = [
        (
            0.1 * k,
            synth_frame(pose_on(40.0 + k), rng, p_detect=0.9)[0] if k >= 3 else None,
            ODO,
            _fix(pose_on(40.0 + k)),
        )
        for k in range(12)
    ]
    loc = Localizer(HDMAP, LocalizerParams(**EXACT), initial_pose=start)
    assert _phases(loc, steps[:3]) == [Phase.VERIFYING] * 3  # no camera: nothing to verify with
    assert loc.startup.verify_left == loc.params.verify_start_frames
    assert _phases(loc, steps[3:]) == [Phase.TRACKING] * 9  # the first frame's search accepted the start
    assert loc.stats["start verified"] == 1
    # Not verified (verify_start_frames=0): tracking from the first step, nothing counted.
    loc0 = Localizer(HDMAP, LocalizerParams(verify_start_frames=0, **EXACT), initial_pose=start)
    assert _phases(loc0, steps[:3]) == [Phase.TRACKING] * 3
    assert "start verified" not in loc0.stats


def test_verification_ends_after_its_frames_without_features():
    """Frames without features do not use up the verification; frames with features do, one each."""
    truth = pose_on(40.0)
    cov = np.diag([0.09, 0.09, 0.01, 1e-4, 1e-4, np.radians(1.0) ** 2])
    loc = Localizer(HDMAP, LocalizerParams(verify_start_frames=2, **EXACT), initial_pose=(truth, cov))
    m = loc.startup
    loc.step(0.0, None, OdometryMeasurement(0.0, 0.0), _fix(truth))
    assert loc.phase is Phase.VERIFYING and m.verify_left == 2
    empty, _ = synth_frame(truth, np.random.default_rng(0), empty=True)
    loc.step(0.1, empty, OdometryMeasurement(0.0, 0.0), _fix(truth))
    assert loc.phase is Phase.VERIFYING and m.verify_left == 2
    frame, _ = synth_frame(truth, np.random.default_rng(1))
    loc.step(0.2, frame, OdometryMeasurement(0.0, 0.0), _fix(truth))
    assert loc.phase is Phase.TRACKING and m.verify_left == 0  # the search accepted this frame
    assert loc.stats["start verified"] == 1


def test_reset_and_gnss_divergence_go_back_to_uninitialised():
    rng = np.random.default_rng(9)
    truth = pose_on(40.0)
    wrong = truth + np.r_[20.0 * np.array([np.cos(truth[5] + 1.0), np.sin(truth[5] + 1.0)]), 0, 0, 0, 0]
    cov = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    loc = Localizer(HDMAP, LocalizerParams(verify_start_frames=0), initial_pose=(wrong, cov))
    phases = [_phases(loc, [(0.1 * k, None, OdometryMeasurement(0.0, 0.0), _fix(truth, rng))])[0] for k in range(8)]
    reset_at = phases.index(Phase.UNINITIALISED)
    assert phases[:reset_at] == [Phase.TRACKING] * reset_at
    assert reset_at == 4  # the fifth far fix in a row
    assert loc.stats["gnss_divergence_reset"] == 1 and loc.startup.far == 0
    loc, _ = _drive(5, seed=1)
    assert loc.phase is Phase.TRACKING
    loc.reset()
    assert loc.phase is Phase.UNINITIALISED and not loc.initialized


def test_a_gap_starts_again():
    loc, out = _drive(10, seed=1)
    assert loc.phase is Phase.TRACKING
    truth = pose_on(30.0)
    frame, _ = synth_frame(truth, np.random.default_rng(2))
    res = loc.step(20.0, frame, ODO, _fix(truth))  # 19 s later: the start-up again, without the initial yaw
    assert loc.stats["gap_reset"] == 1
    assert (loc.phase is Phase.UNINITIALISED) == (not res.initialized)


def _machine_tracking_at(s, **params):
    """A tracking localizer's machine on the synthetic map, and a converged match of a frame at s. The vehicle
    stands at s (the same frame each step, zero odometry) until the start-up search, spread over frames by its
    budget (search.solves_per_frame), has found the basin: 4 frames at most."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT, **params), initial_yaw=pose_on(s)[5])
    truth = pose_on(s)
    frame, _ = synth_frame(truth, np.random.default_rng(0))
    for k in range(4):
        loc.step(0.1 * k, frame, OdometryMeasurement(0.0, 0.0), _fix(truth))
        if loc.phase is Phase.TRACKING:
            break
    assert loc.phase is Phase.TRACKING
    match = loc.matcher.match(frame, truth + [0.3, 0.2, 0, 0, 0, 0.01], P_TRACK, None)
    assert match.converged
    return loc, loc.startup, frame, match


def _one_basin(match, reason):
    return SearchOutcome(None, reason, 1, (match,), nll=(0.0,), null_nll=0.0)


@pytest.mark.parametrize("rule", ["landmarks", "posterior"])
def test_hypotheses_enter_and_leave_searching(rule):
    loc, m, frame, match = _machine_tracking_at(170.0, search=PoseSearchParams(accept=rule))
    y, P = loc.y.copy(), loc.P.copy()
    # A search that found nothing converged leaves nothing to track.
    m._spawn(y, P, SearchOutcome(None, "no", 1, (replace(match, converged=False),), nll=(np.inf,)))
    assert m.phase is Phase.TRACKING and m.hyps == []
    m._spawn(y, P, _one_basin(match, "too few features"))
    assert m.phase is Phase.SEARCHING and len(m.hyps) == 1
    # A narrow prediction and a frame with features. Rule 'landmarks': the local match is tried, the hypotheses
    # are dropped (no search). Rule 'posterior': the hypotheses decide (the search runs again for rivals and, the
    # frame rich in landmarks, accepts). Either way the machine tracks again with a match.
    P_narrow = P.copy()
    P_narrow[:6, :6] = P_TRACK
    n_search = loc.stats.get("search", 0)
    got, reason, _, _ = m.match(frame, y, P_narrow, 0.1, ODO, ODO, None)
    assert m.phase is Phase.TRACKING and m.hyps == []
    assert got is not None and reason == ""
    assert loc.stats.get("search", 0) == n_search + (rule == "posterior")
    # A wide prediction with hypotheses: they are advanced with the frame; without features they are kept.
    m._spawn(y, P, _one_basin(match, "too few features"))
    P_wide = P.copy()
    P_wide[0, 0] = P_wide[1, 1] = 4.0
    got, reason, _, _ = m.match(None, y, P_wide, 0.1, ODO, ODO, None)
    assert got is None and reason == "searching: 1 hypotheses" and m.phase is Phase.SEARCHING


def test_a_lone_well_constrained_hypothesis_wins_at_once():
    """Rule 'landmarks': a lone hypothesis has no rival to beat: matched again on a frame rich in landmarks it wins
    (no new search); the machine goes back to TRACKING with the winner's prediction and match."""
    loc, m, frame, match = _machine_tracking_at(170.0)
    y, P = loc.y.copy(), loc.P.copy()
    m._spawn(y, P, _one_basin(match, "too few features"))
    hyp = m.hyps[0]
    P_wide = P.copy()
    P_wide[0, 0] = P_wide[1, 1] = 4.0
    n_search = loc.stats.get("search", 0)
    got, reason, y_pred, P_pred = m.match(frame, y, P_wide, 0.0, ODO, ODO, None)
    assert loc.stats.get("search", 0) == n_search
    assert got is hyp.last and m.attempt is got and reason == ""
    assert y_pred is hyp.y_pred and P_pred is hyp.P_pred
    assert m.phase is Phase.TRACKING and m.hyps == []
    assert np.hypot(*pose_error(got.pose_filtered, pose_on(170.0))[:2]) < 0.2


@pytest.mark.parametrize(
    "budget",
    [
        None,
        pytest.param(
            PoseSearchParams().solves_per_frame,
            marks=pytest.mark.xfail(
                strict=True,
                reason="known limitation of the anytime search under the posterior rule: a vehicle standing still "
                "with a lone hypothesis never localizes. A search spread over frames cannot accept (its parts' basins "
                "are not solved on one frame), and the same view again is no new evidence for the hypotheses, so "
                "the lone basin stays at about half of the mass against elsewhere (docs/localization.md, Real time)",
            ),
        ),
    ],
)
def test_a_lone_hypothesis_wins_by_posterior_mass_only_on_new_evidence(budget):
    """Rule 'posterior': a lone hypothesis has no rival but *elsewhere*: the same frame again from the same place is
    no new evidence, so the search runs again on it and, the frame rich in landmarks, accepts its basin (within 3
    frames); the machine goes back to TRACKING with the winner's match."""
    loc, m, frame, match = _machine_tracking_at(
        170.0, search=PoseSearchParams(accept="posterior", solves_per_frame=budget)
    )
    y, P = loc.y.copy(), loc.P.copy()
    m._spawn(y, P, _one_basin(match, "ambiguous"))
    P_wide = P.copy()
    P_wide[0, 0] = P_wide[1, 1] = 4.0
    n_search = loc.stats.get("search", 0)
    for k in range(3):
        got, reason, _, _ = m.match(frame, y, P_wide, 0.0, ODO, ODO, None)
        assert loc.stats.get("search", 0) == n_search + k + 1  # the search runs on every frame until one wins
        if got is not None:
            break
        assert m.phase is Phase.SEARCHING and reason.startswith("searching")
    assert got is not None and m.attempt is got and reason == ""
    assert m.phase is Phase.TRACKING and m.hyps == [] and m.pending == []
    assert np.hypot(*pose_error(got.pose_filtered, pose_on(170.0))[:2]) < 0.2


def test_repeated_jumps_distrust_the_prediction_and_search():
    """Converged matches rejected as jumps jump_reset_after times in a row: the prediction is widened and the
    search decides; the jump counter starts again and the track is back on the road."""
    loc, _ = _drive(10, seed=1)
    m = loc.startup
    n_search = loc.stats["search"]
    loc.y[:2] += 2.0 * np.array([np.cos(loc.y[5] + np.pi / 2), np.sin(loc.y[5] + np.pi / 2)])  # 2 m sideways
    loc.P[:6, :6] = np.diag([0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5])  # and confident
    rng = np.random.default_rng(7)
    jumps, phases, res = [], [], None
    for k in range(10, 25):
        truth = pose_on(10.0 + k)
        frame, _ = synth_frame(truth, rng, p_detect=0.9)
        res = loc.step(0.1 * k, frame, ODO, GnssMeasurement(truth[:3], 2.0, 3.0))
        jumps.append(m.jumps)
        phases.append(loc.phase)
    n = loc.params.jump_reset_after
    assert jumps[: n - 1] == list(range(1, n)) and jumps[n - 1] == 0
    assert loc.stats["match_jump"] == n and loc.stats["jump_reset"] == 1
    assert loc.stats["search"] == n_search + 1
    assert phases[-1] is Phase.TRACKING and res.mode == "map_matching"
    assert np.hypot(*pose_error(res.pose, truth)[:2]) < 0.2


@pytest.mark.parametrize("verify", [0, 3])
def test_constructor_states(verify):
    params = LocalizerParams(verify_start_frames=verify)
    m = StartupMachine(HDMAP, params, MapMatcher(HDMAP, params.matcher), None, lambda key: None, lambda x: None)
    assert m.phase is Phase.UNINITIALISED and m.hyps == [] and m.verify_left == 0 and m.jumps == m.far == 0
    truth = pose_on(40.0)
    state = m.try_initialise(None, _fix(truth), 0.0, None, None)
    assert state is None  # a two-way road, no frame, no course yet
    m.reset(None, (truth, np.diag([0.01] * 6)))
    y, P = m.try_initialise(None, _fix(truth), 0.0, None, None)
    np.testing.assert_array_equal(y[:6], truth)
    assert m.phase is (Phase.VERIFYING if verify else Phase.TRACKING) and m.verify_left == verify
    assert m.initial_pose is None  # used once
