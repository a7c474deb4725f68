"""The host container on simulated scenarios, fed with priors synthesised from the simulator's truth
(pose = truth + Gaussian noise of a stated covariance, 0.1 m / 0.3 deg; objects = the sensor frame's
detections as they are, false alarms and misses included), every message through the wire codec.
This isolates the container from the map matcher; the full pipeline is tested elsewhere."""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from mapcontainer.fusion import Container, FusionParams
from mapcontainer.fusion.poses import sym_from_upper
from mapcontainer.fusion.simfeed import OraclePriors
from mapcontainer.metrics import anees_band, rmse
from mapcontainer.sim import World, load_scenario, with_error_sources, with_traffic
from schemas import encode

pytestmark = pytest.mark.integration

WARMUP = 20  # frames before errors count (tracks need birth_hits frames and some history)


def run_views(scenario, seed: int, frames: int, views: dict[str, list[str] | None], params: FusionParams | None = None):
    """One simulated episode fed to one container per view (the senders it hears). Yields per frame
    (tick, {view: FusedState}, {view: Container})."""
    world = World(load_scenario(scenario) if isinstance(scenario, str) else scenario, seed=seed, fleet="t")
    feed = OraclePriors("t", seed=1000 + seed)
    boxes = {name: Container(params or FusionParams(), "t", "cv0") for name in views}
    for k in range(frames):
        tick = world.tick(k)
        priors = feed.priors(tick)
        fused = {}
        for name, senders in views.items():
            for vid, msg in priors.items():
                if senders is None or vid in senders:
                    assert boxes[name].ingest(encode(msg), tick.t).accepted
            fused[name] = boxes[name].fuse(tick.t)
        yield tick, fused, boxes


def obstacle_errors(fused, truth, obstacle: int, gate_m: float = 3.0):
    """(error, covariance) of the fused object nearest to a true obstacle, or None."""
    i = list(truth.obstacle_id).index(obstacle)
    p = truth.obstacle_p_map[i]
    if len(fused.object_id) == 0:
        return None
    d = np.linalg.norm(fused.object_p_map - p, axis=1)
    j = int(np.argmin(d))
    if d[j] > gate_m:
        return None
    return fused.object_p_map[j].astype(float) - p, sym_from_upper(fused.object_cov[j])


@pytest.mark.slow
def test_overlap_fusion_beats_each_vehicle_alone():
    """Both vehicles see obstacle 1: the fused error is near the information-weighted combination of
    the single-vehicle errors, (1/a^2 + 1/b^2)^-1/2, and below either. That bound is for independent
    errors, so the scene runs without the simulator's error sources (calibration and persistent detector
    errors are common to many frames of one vehicle: with them, seed 1-2 gives 0.265 m against 1.1 x
    0.240 m; `mapc experiment paper` reports that setting)."""
    views = {"fused": None, "cv0": ["cv0"], "cv1": ["cv1"]}
    err = {v: [] for v in views}
    nees = []
    scene = with_error_sources(load_scenario("overlap"), ())
    white = FusionParams(detection_persistent_fraction=0.0)  # this scene's detector errors are white
    for seed in (1, 2):
        for k, (tick, fused, _) in enumerate(run_views(scene, seed, 170, views, white)):
            if k < WARMUP:
                continue
            for v in views:
                r = obstacle_errors(fused[v], tick.truth, 1)
                assert r is not None, (v, k)
                err[v].append(r[0])
                if v == "fused" and k % 5 == 0:
                    nees.append(float(r[0] @ np.linalg.solve(r[1], r[0])))
    a, b, f = rmse(err["cv0"]), rmse(err["cv1"]), rmse(err["fused"])
    bound = (a**-2 + b**-2) ** -0.5
    assert f <= 1.1 * bound, (f, a, b, bound)
    assert f < min(a, b) and 0.1 < f < 0.3
    # Consistency: the obstacle drives exactly straight at constant speed, so the white-noise-
    # acceleration model is conservative (ANEES ~2.2-2.5, below the band's lower edge ~2.7): never
    # overconfident. tests/unit/test_fusion_container.py checks the band on data from the model.
    lo, hi = anees_band(3, len(nees))
    assert 1.8 < np.mean(nees) <= hi, (np.mean(nees), lo, hi)


def test_blindspot_obstacle_reaches_the_ego_through_the_connected_vehicle():
    """cv1 drives ahead of the ego (cv0) and hides obstacle 1; only cv1 sees it. The ego's container
    shows it, accurately, and localizes cv1 (which cv0 sees). The first 6 s: the straight before the
    corner, where the ego sees the obstacle past cv1's side (the preset's comment). The container's
    accuracy with ideal detections (oracle priors, white detector noise from its reported covariance,
    the traffic as listed): with every error source on, cv1's fused position is about 0.12 m off."""
    present, errs, cv1_err, cv0_saw = 0, [], [], 0
    box = None
    frames = 60
    sc = with_traffic(with_error_sources(load_scenario("blindspot-occluded"), ["clutter"]), False)
    for k, (tick, fused, boxes) in enumerate(run_views(sc, 3, frames, {"ego": None})):
        box = boxes["ego"]
        cv0_saw += "1" in tick.debug["cv0"].object_truth_ids
        if k < WARMUP:
            continue
        r = obstacle_errors(fused["ego"], tick.truth, 1)
        if r is not None:
            present += 1
            errs.append(r[0])
        i = fused["ego"].vehicle_ids.index("cv1")
        cv1_err.append(fused["ego"].vehicle_pose[i, :3] - tick.states["cv1"].p_map)
    assert cv0_saw == 0
    assert present == frames - WARMUP
    assert rmse(errs) < 0.35
    assert rmse(cv1_err) < 0.1  # prior sigma 0.1 m per axis, fused with cv0's detections of cv1
    assert box.stats()["cross_detections"] > 60 * frames / 90


@pytest.mark.slow
def test_paper_urban_ids_are_stable():
    """4 vehicles, 14 obstacles, 10 s: nearly every true obstacle keeps one id while it is tracked."""
    last, switches, matched, false_objects = {}, 0, 0, 0
    for k, (tick, fused, _) in enumerate(run_views("paper-urban", 1, 100, {"all": None})):
        fs = fused["all"]
        if k < WARMUP or len(fs.object_id) == 0:
            continue
        tp = tick.truth.obstacle_p_map
        D = np.linalg.norm(tp[:, None, :2] - fs.object_p_map[None, :, :2], axis=2)
        rows, cols = linear_sum_assignment(np.where(D < 3.0, D, 1e6))
        pairs = [(r, c) for r, c in zip(rows, cols, strict=True) if D[r, c] < 3.0]
        false_objects += len(fs.object_id) - len(pairs)
        for r, c in pairs:
            oid, fid = int(tick.truth.obstacle_id[r]), int(fs.object_id[c])
            switches += oid in last and last[oid] != fid
            last[oid] = fid
            matched += 1
    assert matched > 400
    assert switches <= 5, switches
    # False tracks: the detector's ghosts persist for about 0.5 s (sim/errors.py), long enough for the
    # host to confirm them: 172 false objects against 514 matched in this run (0.33; 0.02 with the white,
    # one-frame false alarms before). Confirming ghosts is the estimator's to fix (issue 20); this bound
    # catches it getting worse.
    assert false_objects <= 0.4 * matched, (false_objects, matched)
