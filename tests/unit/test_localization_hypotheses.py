"""The multi-hypothesis start-up (mapcontainer.localization.hypotheses and the start-up machine's use of it, rule
``search.accept = "posterior"``, opt-in):
the posterior machinery against closed forms, and the traced cases on the synthetic map of test_localization
(a lone pole with the lanes accepted; a basin ambiguous along the road not accepted until resolved; a GNSS
multipath jump survived; relocalization after a kidnap)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from mapcontainer import geometry as geo
from mapcontainer.localization import CameraFrame, GnssMeasurement, Localizer, LocalizerParams, OdometryMeasurement
from mapcontainer.localization import hypotheses as hyp
from mapcontainer.localization.search import PoseSearchParams, SearchOutcome
from mapcontainer.localization.startup import Phase

from .test_localization import EXACT, HDMAP, pose_error, pose_on, synth_frame

POSTERIOR = dict(search=PoseSearchParams(accept="posterior"))  # the rule under test here (opt-in; default 'landmarks')

# --------------------------------------------------------------------------- closed forms


def test_masses_are_the_exact_posterior_of_linear_gaussian_hypotheses():
    """Hypotheses i: x ~ N(m_i, P_i), z = x + v, v ~ N(0, R). The matcher's score at the optimum (residual plus
    prior chi^2) with the Laplace volume term is the exact -2 log p(z | i) up to a constant common to all i."""
    rng = np.random.default_rng(0)
    R = np.diag([0.04, 0.09, 0.01, 1e-4, 1e-4, 4e-4])
    z = rng.normal(size=6)
    nll, exact = [], []
    for _ in range(4):
        m = z + rng.normal(scale=[1.5, 1.5, 0.2, 0.01, 0.01, 0.05])
        A = rng.normal(size=(6, 6)) * 0.1
        P = np.diag([2.0, 3.0, 0.05, 4e-4, 4e-4, 3e-3]) + A @ A.T * 0.01
        P_post = np.linalg.inv(np.linalg.inv(P) + np.linalg.inv(R))
        x = P_post @ (np.linalg.solve(P, m) + np.linalg.solve(R, z))
        score = (z - x) @ np.linalg.solve(R, z - x) + (x - m) @ np.linalg.solve(P, x - m)
        nll.append(hyp.frame_nll(score, P_post, P))
        exact.append(-2.0 * stats.multivariate_normal(m, P + R).logpdf(z))
    np.testing.assert_allclose(hyp.masses(nll), hyp.masses(exact), rtol=1e-9, atol=1e-12)
    assert np.ptp(np.subtract(nll, exact)) < 1e-9  # one common constant: log det(2 pi R)


def test_student_t_is_the_multivariate_t_density():
    S = np.array([[2.0, 0.3], [0.3, 1.0]])
    for d in ([0.0, 0.0], [1.0, -2.0], [8.0, 3.0]):
        want = -2.0 * stats.multivariate_t(np.zeros(2), S, df=4.0).logpdf(d)
        assert hyp.student_t_nll(np.array(d), S, 4.0) == pytest.approx(want, rel=1e-10)


def test_mixture_moments_and_the_heading_on_the_circle():
    a, b = np.zeros(6), np.zeros(6)
    a[0], b[0] = 0.0, 10.0
    a[5], b[5] = np.radians(179.0), np.radians(-179.0)  # 2 degrees apart across +-180
    P = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    m, C = hyp.mixture([a, b], [P, P], np.array([0.25, 0.75]))
    assert m[0] == pytest.approx(7.5)
    assert C[0, 0] == pytest.approx(0.01 + 0.25 * 7.5**2 + 0.75 * 2.5**2)
    assert geo.wrap_angle(m[5] - np.radians(-179.5)) == pytest.approx(0.0, abs=1e-12)
    assert C[5, 5] == pytest.approx(1e-4 + 0.25 * 0.75 * np.radians(2.0) ** 2)


def test_elsewhere_costs_each_explained_landmark_an_outlier():
    assert hyp.null_increment(10.0, np.array([1.0, 2.0]), 9.21) == pytest.approx(10.0 + 8.21 + 7.21)


# --------------------------------------------------------------------------- the traced cases

V, DT = 10.0, 0.1


def _odo(s):
    rate = geo.wrap_angle(pose_on(s + V * DT)[5] - pose_on(s - V * DT)[5]) / (2 * DT)
    return OdometryMeasurement(V, rate)


def _one_pole(frame: CameraFrame) -> CameraFrame:
    """The frame with its longest pole only, and the lanes: no points."""
    poles = frame.poles_uv
    if len(poles):
        poles = poles[[int(np.argmax(np.hypot(poles[:, 2] - poles[:, 0], poles[:, 3] - poles[:, 1])))]]
    return CameraFrame(frame.intr, frame.T_body_cam, np.zeros((0, 2)), np.zeros(0, np.uint8), poles, frame.lane_mask)


def _run(loc, n, *, s0, seed, frames=lambda f, k: f, gnss_jump=lambda k: np.zeros(2), where=lambda k, s: s, t0=0.0):
    """n steps at 10 Hz from arc length s0; returns [(truth, result)]. ``where(k, s)`` is the true arc length of
    step k (a kidnap moves it), ``gnss_jump(k)`` a multipath offset of its fix, ``frames`` filters its frame."""
    rng = np.random.default_rng(seed)
    bias = rng.normal(0.0, 1.0, 2)
    out = []
    for k in range(n):
        s = where(k, s0 + V * DT * k)
        truth = pose_on(s)
        fix = truth[:3] + np.r_[bias + rng.normal(0, 0.5, 2) + gnss_jump(k), 0.0]
        frame, _ = synth_frame(truth, rng, sigma_px=1.0)
        res = loc.step(t0 + k * DT, frames(frame, k), _odo(s), GnssMeasurement(fix, 2.0, 3.0))
        out.append((truth, res))
    return out


def _err(truth, res) -> float:
    return float(np.hypot(*pose_error(res.pose, truth)[:2]))


def _first_lock(out) -> int | None:
    return next((k for k, (_, r) in enumerate(out) if r.mode == "map_matching"), None)


def test_a_lone_pole_with_the_lanes_is_accepted():
    """The traced urban start (evaluation seed): every frame the search found the true basin from one pole and the
    lane lines and rejected it as 'too few features' (5 constraints and 2 landmarks required), while the vehicle
    published a GNSS-grade fallback 1-2 m off. Seen over a baseline of travel, one pole with the lanes holds the
    posterior mass (each view of the pole counts once per view_baseline_m of travel): accepted, and right."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT, **POSTERIOR))
    out = _run(loc, 30, s0=170.0, seed=3, frames=lambda f, k: _one_pole(f))
    k = _first_lock(out)
    assert k is not None and k <= 20, [r.reason for _, r in out[:21]]  # the first basin at 1.2 s, then 5 m of travel
    after = [_err(t, r) for t, r in out[k:] if r.mode == "map_matching"]
    assert len(after) == len(out) - k and max(after) < 0.5, after  # the pole's bearing fixes along-road over travel
    assert max(after[-10:]) < 0.3, after
    # One frame of one pole is not a lock: its search left the basin ambiguous (elsewhere kept more than epsilon), or
    # had starts left to solve on the next frames (the anytime budget, search.solves_per_frame).
    first = ("search: ambiguous", "search: searching")
    assert any(r.reason.startswith(first) for _, r in out[:k]), [r.reason for _, r in out[:k]]


def test_the_default_rule_decides_the_lone_pole_case_as_main_did():
    """The same lone-pole drive under the default rule ('landmarks'): exactly the decisions of main's start-up, traced
    frame by frame from main before the rule became a parameter (the same reasons, the same counters): one pole and
    the lanes are never searched (too few features for min_constraints 5, min_landmarks 2), fallback throughout."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT))
    out = _run(loc, 30, s0=170.0, seed=3, frames=lambda f, k: _one_pole(f))
    assert [r.reason for _, r in out] == ["initialising: no heading yet"] * 13 + ["too few features to search"] * 17
    assert all(r.mode == "fallback" for _, r in out)
    assert dict(loc.stats) == {
        "initialising: too few features to search": 13,
        "initialised": 1,
        "too few features to search": 17,
        "fallback": 17,
    }


def _machine_with_two_basins(offset_m: float, seed: int = 0):
    """A tracking localizer at s = 170 whose machine is handed two basins: the true one and one ``offset_m`` m
    along the road (a lamp spacing), with equal evidence."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT, **POSTERIOR), initial_yaw=pose_on(170.0)[5])
    _run(loc, 12, s0=158.0, seed=seed)
    m = loc.startup
    truth = pose_on(170.0)
    res = m.matcher.match(
        synth_frame(truth, np.random.default_rng(seed), sigma_px=1.0)[0],
        truth,
        np.diag([0.3**2, 0.3**2, 0.05**2, 0.005**2, 0.005**2, np.radians(0.5) ** 2]),
    )
    along = np.r_[np.cos(truth[5]), np.sin(truth[5])] * offset_m
    wrong = replace(res, pose_filtered=res.pose_filtered + np.r_[along, 0, 0, 0, 0])
    y, P = loc.y.copy(), loc.P.copy()
    y[:6] = truth
    P[:2, :2] += np.eye(2) * 9.0
    loc.P = P.copy()  # the localizer's own state is as wide: the hypotheses decide
    m.phase = Phase.SEARCHING
    m.fix = GnssMeasurement(truth[:3] + np.r_[0.5 * along, 0.0], 2.0, 3.0)  # half way: GNSS cannot tell
    m._spawn(y, P, SearchOutcome(None, "ambiguous", 2, (res, wrong), nll=(0.0, 0.0), null_nll=30.0))
    return loc, m, truth


def test_an_ambiguity_along_the_road_is_published_wide_and_not_accepted_until_resolved():
    loc, m, truth = _machine_with_two_basins(6.0)
    assert len(m.hyps) == 2 and m.mass[:2] == pytest.approx([0.5, 0.5], abs=0.02)
    # The published pose is the mixture: its along-road variance covers both basins.
    pose, cov = m.mixture(loc.y, loc.P)
    heading = np.r_[np.cos(truth[5]), np.sin(truth[5])]
    assert heading @ cov[:2, :2] @ heading >= 3.0**2 * 0.9

    # Frames with the lanes only (they repeat along the road) do not resolve it: searching, published wide.
    # Then frames with landmarks do: the wrong basin explains them worse, the true one wins.
    def lanes_only(f, k):
        return (
            _one_pole(f)
            if k >= 3
            else CameraFrame(
                f.intr, f.T_body_cam, np.zeros((0, 2)), np.zeros(0, np.uint8), np.zeros((0, 4)), f.lane_mask
            )
        )

    out = _run(loc, 10, s0=171.0, seed=1, t0=1.2, frames=lanes_only)
    k = _first_lock(out)
    assert k is not None and k >= 3, [r.reason for _, r in out]
    for i, (t, r) in enumerate(out[:k]):
        assert r.mode == "fallback" and r.reason == "searching: 2 hypotheses"
        heading = np.r_[np.cos(t[5]), np.sin(t[5])]
        var_along = heading @ r.cov_filtered[:2, :2] @ heading
        if i < 3:  # lanes only: both basins inside (the fixes favour the true one)
            assert var_along >= 1.5**2
        # once the pole is in view the mass moves to the true basin over the views (each worth the travel since the
        # last one over view_baseline_m): the published mixture narrows with it, and stays honest
        assert abs(heading @ pose_error(r.pose_filtered, t)[:2]) < 3.0 * np.sqrt(var_along)
    assert all(_err(t, r) < 0.3 for t, r in out[k:] if r.mode == "map_matching")


def test_a_multipath_jump_does_not_decide_between_basins():
    """A fix 12 m off (a multipath jump on top of the receiver's bias), right on a wrong basin 12 m along: the
    Student-t likelihood gives it a bounded weight and the camera's evidence keeps the true basin ahead; a
    Gaussian of the same scale would let the jump decide."""
    loc, m, truth = _machine_with_two_basins(12.0)
    m.hyps[1].nll += 12.0  # the camera's evidence: the true basin explained a few frames better
    along = np.r_[np.cos(truth[5]), np.sin(truth[5])]
    m.fix = GnssMeasurement(truth[:3] + np.r_[12.0 * along, 0.0], 2.0, 3.0)
    mass = m._masses()
    assert mass[0] > 0.8, mass
    p = loc.params
    var = p.gnss_bias_sigma_m**2 + 0.5**2 + p.init_extra_sigma_m**2  # the scale the t uses (white: 0.5 m)
    gauss = hyp.masses([m.hyps[0].nll + 12.0**2 / var, m.hyps[1].nll])
    assert gauss[0] < 0.1, gauss


def test_a_multipath_jump_while_searching_keeps_the_published_pose_honest():
    """The traced start: a 7 m multipath jump during the search dragged the GNSS-grade fallback 5.4 m off with a
    NEES of 38 while the rejected lone hypothesis sat 0.1 m from the truth. Now the lone pole and lanes win through
    the jump, and every published pose before is honest."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT, **POSTERIOR))
    jump = np.array([5.0, -5.0])
    out = _run(loc, 25, s0=170.0, seed=4, frames=lambda f, k: _one_pole(f), gnss_jump=lambda k: jump if k < 20 else 0)
    k = _first_lock(out)
    assert k is not None and k <= 20
    assert all(_err(t, r) < 0.5 for t, r in out[k:] if r.mode == "map_matching")
    for t, r in out[:k]:
        if r.cov_filtered is not None:
            e = pose_error(r.pose_filtered, t)[[0, 1, 5]]
            assert e @ np.linalg.solve(r.cov_filtered[np.ix_([0, 1, 5], [0, 1, 5])], e) < 16.3  # chi^2 3 dof, 99.9 %


def test_relocalization_after_a_kidnap():
    """Tracking, then the vehicle is carried 40 m along the road (frames and fixes from there, the odometry does
    not know): the fixes disagree, the localizer starts again and the same machinery finds it within a second.
    Until the fixes have disagreed long enough, only the lanes match (they look the same 40 m along): no landmark
    confirms the old place, and the vehicle says its lock is lateral only."""
    loc = Localizer(HDMAP, LocalizerParams(**EXACT, **POSTERIOR), initial_yaw=pose_on(150.0)[5])
    out = _run(loc, 40, s0=150.0, seed=6, where=lambda k, s: s + (40.0 if k >= 20 else 0.0))
    assert all(r.mode == "map_matching" and _err(t, r) < 0.3 for t, r in out[5:20])
    after = out[20:]
    wrong = [r for t, r in after if r.mode == "map_matching" and _err(t, r) > 0.5]
    assert all(r.lock == "lateral" for r in wrong), [(r.n_points, r.n_poles) for r in wrong]  # it says so
    assert len(wrong) <= loc.params.gnss_divergence_fixes
    assert loc.stats.get("gnss_divergence_reset", 0) == 1
    k = next(i for i, (t, r) in enumerate(after) if r.n_points + r.n_poles > 0 and r.mode == "map_matching")
    assert k <= 10 and all(_err(t, r) < 0.3 for t, r in after[k:] if r.mode == "map_matching")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("rule", "budget"), [("landmarks", None), ("landmarks", PoseSearchParams().solves_per_frame), ("posterior", None)]
)
def test_the_traced_urban_start_locks_on_a_lone_pole_and_the_lanes(rule, budget):
    """Development seed 1 of paper-urban, every error source on, cv2 from a cold start: the search found the true
    basin from one pole and the lanes at 2.0 s (0.3 m along, 0.2 m across) and rejected it as 'too few features
    (3 constraints)'; the vehicle published a GNSS-grade fallback 1.1-1.3 m off until 3.0 s. Rule 'landmarks' (the
    default) still does exactly that (main's decisions, traced frame by frame: first lock at 3.0 s, 0.11 m off).
    By its posterior mass (rule 'posterior') it locks at 0.5 s (0.5 m along at 1.5 sigma) and is within 0.3 m 0.2 s
    later. These decisions are checked with the search's budget off (every start solved in its frame). With the
    default anytime budget (search.solves_per_frame) the landmark rule locks one frame later, at 3.1 s: the search
    that finds the basin at 1.9 s solves its best start first (not the true basin), and the starts it carries are
    solved on later frames."""
    from mapcontainer.sim import World, load_scenario
    from mapcontainer.vehicle import VehicleAgent

    with World(load_scenario("paper-urban"), seed=1) as world:
        params = LocalizerParams(search=PoseSearchParams(accept=rule, solves_per_frame=budget))
        agent = VehicleAgent(world.hdmap, "cv2", world.fleet, params=params)
        rows = []
        for tick in world.run(3.5):
            agent.handle(tick.t, tick.frames["cv2"])
            r = agent.last_result
            err = np.hypot(*(r.pose_filtered - tick.states["cv2"].pose)[:2]) if r.pose_filtered is not None else np.inf
            rows.append((tick.t, r.mode, err, r.reason))
    first = next(t for t, mode, _, _ in rows if mode == "map_matching")
    if rule == "landmarks" and budget is not None:
        assert first == pytest.approx(3.1), rows
    elif rule == "landmarks":
        assert first == pytest.approx(3.0), rows
        assert sum(reason == "too few features to search" for *_, reason in rows) == 7, rows
        assert all(reason == "searching: 1 hypotheses" for t, *_, reason in rows if 2.0 - 1e-9 < t < first), rows
    else:
        assert first <= 1.0, rows
    assert all(mode == "map_matching" and err < 0.6 for t, mode, err, _ in rows if t >= first), rows
    assert all(err < 0.3 for t, _, err, _ in rows if t >= first + 0.3), rows  # the pole's bearing, over travel


def _suburban_seed10_cv0(seconds: float, map_errors: str = "independent") -> np.ndarray:
    """Development seed 10 of paper-suburban, every error source on, cv0 from a cold start under rule 'posterior'
    (and the tracker's ``map_errors``): rows [t, |lateral error|, |along-road error|, lateral PL, longitudinal PL,
    along-road sigma, wheel-speed scale] of the frames it claims integrity (map matched, a protection level stated)."""
    from mapcontainer.sim import World, load_scenario
    from mapcontainer.vehicle import VehicleAgent

    with World(load_scenario("paper-suburban"), seed=10) as world:
        params = LocalizerParams(**POSTERIOR, map_errors=map_errors)
        agent = VehicleAgent(world.hdmap, "cv0", world.fleet, params=params)
        rows = []
        for tick in world.run(seconds):
            agent.handle(tick.t, tick.frames["cv0"])
            r, truth = agent.last_result, tick.states["cv0"].pose
            if r.protection_level is None:
                continue
            R = geo.rot_z(truth[5]).T[:2, :2]
            e_along, e_across = R @ (r.pose_filtered[:2] - truth[:2])
            sigma_along = float(np.sqrt((R @ r.cov_filtered[:2, :2] @ R.T)[0, 0]))
            rows.append((tick.t, abs(e_across), abs(e_along), *r.protection_level, sigma_along, agent.localizer.y[6]))
    return np.array(rows)


@pytest.mark.slow
def test_a_one_pole_basin_is_accepted_with_an_honest_along_road_sigma():
    """The traced suburban start (development seed 10, cv0): the basins of one pole lie on a ridge along the road
    (the search returned four, 1 m apart), and each view of the pole was folded into the hypotheses as independent
    at 10 frames a second: the basin accepted at 4.8 s was 1.82 m off along the road at an along-road sigma of
    0.43 m (4.2 sigma, beyond its protection level). A view is now worth the travel since the hypothesis' last one
    over view_baseline_m: accepted at 4.2 s, 1.55 m off at 0.73 m (2.1 sigma), inside its protection level."""
    a = _suburban_seed10_cv0(4.5)
    assert len(a) and a[0, 0] < 4.5, a  # it locks
    t, e_lat, e_along, pl_lat, pl_lon, sigma_along, _ = a[0]
    assert e_along <= pl_lon and e_lat <= pl_lat and e_along < 3.0 * sigma_along, a[0]


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="known limitation: with the landmarks' map errors as consider states (map_errors='consider'; with the "
    "default 'independent' 18 HMI frames, the scale at 1.043) the lock's along-road error no "
    "longer outruns its sigma (1 frame of HMI in the first 1.6 s, 10 before), but the pole's correction still turns "
    "into a wheel-speed scale error (1.032 at 6.4 s, truth 0.999) and the pose drifts 0.5-0.7 m along the road at "
    "a longitudinal PL of 0.52-0.62 m (12 frames of HMI, 13 of 78 in all, 18 before). With the camera's rotation "
    "calibration error off the same start has none (|k - 1| <= 1.4 %; docs/localization.md, Along-road rivals)",
)
def test_a_basin_accepted_off_along_the_road_tracks_honestly():
    """The same start after the lock, the tracker keeping the landmarks' map errors as consider states: every frame
    the vehicle claims integrity, its errors are inside its protection levels, and the wheel-speed scale estimate
    stays within 3 % of 1."""
    a = _suburban_seed10_cv0(12.0, "consider")
    assert np.all(a[:, 1] <= a[:, 3]) and np.all(a[:, 2] <= a[:, 4]), a
    assert np.all(np.abs(a[:, 6] - 1.0) < 0.03), a


def test_a_one_pole_basin_has_rivals_one_pole_spacing_along_the_road():
    """Rule 'posterior': a basin whose only landmark is one pole gets along-road copies that put the neighbouring
    poles of the same row (one ahead, one behind) where that pole is seen, with its evidence so far; a basin with
    a second landmark, poles of another row and rule 'landmarks' get none."""
    loc, m, truth = _machine_with_two_basins(6.0)
    h = m.hyps[0]
    j = h.last.pole_pairs[0, 0]
    heading = np.r_[np.cos(h.y[5]), np.sin(h.y[5])]
    lateral = np.r_[-heading[1], heading[0]]
    p0 = m._pole_xy[j].copy()
    row = np.array([p0 - 25.0 * heading, p0 + 31.0 * heading, p0 + 12.0 * heading + 4.0 * lateral, p0 - 70 * heading])
    m._pole_xy = np.vstack([m._pole_xy, row])
    one_pole = replace(h.last, point_pairs=h.last.point_pairs[:0], pole_pairs=h.last.pole_pairs[:1])
    one_pole = replace(one_pole, pair_chi2=np.r_[1.0])
    h.last = one_pole
    copies = m._aliases(h, [h])
    offsets = sorted(float(heading @ (c.y[:2] - h.y[:2])) for c in copies)
    assert offsets == pytest.approx([-25.0, 31.0], abs=1e-6)
    assert all(c.alias and c.nll == h.nll and np.array_equal(c.P, h.P) for c in copies)
    two = replace(one_pole, pair_chi2=np.r_[1.0, 1.0], pole_pairs=np.r_[one_pole.pole_pairs, [[j + 1, 0]]])
    h.last = two
    assert m._aliases(h, [h]) == []
    loc.params = loc.params.model_copy(update={"search": PoseSearchParams(accept="landmarks")})
    m.params = loc.params
    h.last = one_pole
    assert m._aliases(h, [h]) == []
