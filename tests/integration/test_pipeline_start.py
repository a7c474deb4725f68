"""run_pipeline(start=...): warm start from a noisy known pose (deterministic per seed, map matching
from the first frames) (fast: a few frames)."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.evaluation import horizontal_sq_error, vehicle_pose
from mapcontainer.experiments.paper import PaperSettings
from mapcontainer.pipeline import WARM_START_SIGMA, run_pipeline, warm_start_poses
from mapcontainer.sim import World, load_scenario


def _truth0(scenario: str = "paper-urban") -> dict[str, np.ndarray]:
    world = World(load_scenario(scenario), seed=0)
    states = world.states(0.0)
    return {v: np.asarray(states[v].pose, float) for v in world.vehicle_ids}


def test_warm_start_poses_are_seeded_noisy_truth():
    truth = _truth0()
    a, b, c = warm_start_poses(truth, 5), warm_start_poses(truth, 5), warm_start_poses(truth, 6)
    assert list(a) == list(truth)
    for vid, pose in truth.items():
        np.testing.assert_array_equal(a[vid][0], b[vid][0])
        assert not np.array_equal(a[vid][0], c[vid][0])
        np.testing.assert_allclose(a[vid][1], np.diag(WARM_START_SIGMA**2))
        err = a[vid][0] - pose
        err[5] = (err[5] + np.pi) % (2 * np.pi) - np.pi
        assert np.all(np.abs(err) < 6 * WARM_START_SIGMA), (vid, err)
    # the draws have the stated spread (many seeds, one vehicle)
    errs = np.array([warm_start_poses({"v": np.zeros(6)}, s)["v"][0] for s in range(400)])
    np.testing.assert_allclose(errs.std(axis=0), WARM_START_SIGMA, rtol=0.15)
    with pytest.raises(ValueError):
        warm_start_poses(truth, 0, sigma=np.zeros(6))


@pytest.fixture(scope="module")
def warm_runs():
    kw = {"seed": 4, "duration_s": 0.3, "views": (), "start": "warm"}
    return run_pipeline("paper-urban", **kw), run_pipeline("paper-urban", **kw)


def test_warm_start_is_deterministic_and_map_matches_at_once(warm_runs):
    r1, r2 = warm_runs
    assert r1.start == "warm" and len(r1.records) == 3
    for a, b in zip(r1.records, r2.records, strict=True):
        assert a.priors.keys() == b.priors.keys() == {"cv0", "cv1", "cv2", "cv3"}
        for vid in a.priors:
            np.testing.assert_array_equal(a.priors[vid], b.priors[vid])
        assert a.loc_mode == b.loc_mode
    # map matching from the first frame for most vehicles, and for every one within two frames
    first = r1.records[0].loc_mode
    assert sum(m == "map_matching" for m in first.values()) >= 3, first
    for vid in first:
        assert any(rec.loc_mode[vid] == "map_matching" for rec in r1.records[:2]), vid
        assert all(rec.loc_mode[vid] == "map_matching" for rec in r1.records[2:]), vid
    # ... and near the truth: a warm start is 0.3 m (1 sigma) off, GNSS would be metres off
    for rec in r1.records:
        for vid, pose in rec.priors.items():
            assert horizontal_sq_error(pose, vehicle_pose(rec.truth, vid)) < 1.0**2, (rec.t, vid)


def test_cold_start_is_the_default_and_start_is_checked():
    res = run_pipeline("paper-urban", seed=4, duration_s=0.1, views=())
    assert res.start == "cold"
    first = res.records[0].loc_mode
    assert first.keys() == {"cv0", "cv1", "cv2", "cv3"}
    with pytest.raises(ValueError, match="start"):
        run_pipeline("paper-urban", seed=0, duration_s=0.1, views=(), start="hot")
    with pytest.raises(ValueError, match="distributed"):
        run_pipeline("paper-urban", seed=0, duration_s=0.1, views=(), mode="centralized", start="warm")
    assert PaperSettings().start == "cold"
    with pytest.raises(ValueError, match="start"):
        PaperSettings(start="lukewarm")
