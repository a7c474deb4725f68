"""Protection levels: from the filter's covariance, in the vehicle frame, withheld on a detected fault, carried by
the prior the schema way (optional fields; a message without them still decodes)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from mapcontainer.localization import GnssMeasurement, Localizer, LocalizerParams
from schemas import VehiclePrior, decode, encode

from .test_codec import vehicle_prior
from .test_localization import EXACT, HDMAP, pose_on
from .test_localization_hypotheses import _run


def test_protection_levels_are_k_sigma_across_and_along_the_heading():
    loc = Localizer(HDMAP, LocalizerParams(**EXACT))
    out = _run(loc, 12, s0=150.0, seed=2)
    res = out[-1][1]
    assert res.mode == "map_matching" and res.protection_level is not None
    yaw = res.pose_filtered[5]
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    C = R.T @ res.cov_filtered[:2, :2] @ R  # along, across
    k = 3.2905  # two-sided Gaussian quantile of 1e-3
    np.testing.assert_allclose(res.protection_level, k * np.sqrt([C[1, 1], C[0, 0]]), rtol=1e-4)


def test_a_fix_the_gate_refuses_while_map_matched_withholds_the_protection_level():
    loc = Localizer(HDMAP, LocalizerParams(**EXACT), initial_yaw=pose_on(150.0)[5])
    _run(loc, 12, s0=150.0, seed=2)
    far = GnssMeasurement(pose_on(161.2)[:3] + np.r_[30.0, 0.0, 0.0], 2.0, 3.0)
    from .test_localization import synth_frame
    from .test_localization_hypotheses import _odo

    res = loc.step(1.2, synth_frame(pose_on(162.0), np.random.default_rng(0))[0], _odo(162.0), far)
    assert res.mode == "map_matching" and res.protection_level is None
    assert res.reason.startswith("integrity") and loc.stats["integrity fault"] == 1


def test_the_prior_carries_protection_levels_optionally():
    old = vehicle_prior(True)
    assert decode(encode(old), VehiclePrior).protection_level_m is None  # a message without them decodes
    new = VehiclePrior(**{**old.model_dump(), "protection_level_m": [0.4, 1.2], "integrity_risk": 1e-3})
    got = decode(encode(new), VehiclePrior)
    np.testing.assert_allclose(got.protection_level_m, [0.4, 1.2])
    assert got.integrity_risk == 1e-3
    with pytest.raises(ValidationError):
        VehiclePrior(**{**old.model_dump(), "protection_level_m": [0.4, 1.2]})  # no risk stated
    with pytest.raises(ValidationError):
        VehiclePrior(**{**old.model_dump(), "protection_level_m": [-0.4, 1.2], "integrity_risk": 1e-3})


def test_lanes_alone_are_a_lateral_lock_tight_across_and_wide_along():
    """Tracking, then frames with the lane lines only: the mode stays map matching, the lock says 'lateral', and
    the covariance is tight across the road and wide along it (the along-road position is GNSS and odometry's)."""
    from mapcontainer.localization import CameraFrame

    def lanes_only(f, k):
        if k < 15:
            return f
        return CameraFrame(f.intr, f.T_body_cam, np.zeros((0, 2)), np.zeros(0, np.uint8), np.zeros((0, 4)), f.lane_mask)

    loc = Localizer(HDMAP, LocalizerParams(**EXACT), initial_yaw=pose_on(150.0)[5])
    out = _run(loc, 35, s0=150.0, seed=2, frames=lanes_only)
    assert out[14][1].lock == "full"
    for _truth, res in out[20:]:
        assert res.mode == "map_matching" and res.lock == "lateral"
        pl_lat, pl_lon = res.protection_level
        assert pl_lon > 2.0 * pl_lat
    first, last = out[15][1].protection_level, out[-1][1].protection_level
    assert last[1] > first[1]  # along the road the uncertainty grows with the distance driven on odometry
