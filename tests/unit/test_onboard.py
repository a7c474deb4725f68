"""The vehicle's use of the downlink: moved to the present, gated by its own consistency check, fused."""

import numpy as np
import pytest

from mapcontainer.onboard import DownlinkFusion, DownlinkParams
from schemas import PoseDownlink, VehiclePrior, decode, encode
from schemas.arrays import cov_to_upper

OWN_COV = np.diag([0.4, 0.4, 0.1, 0.01, 0.01, 0.02]) ** 2


def downlink(t, xy, sigma=0.1, target="cv1", fleet="f"):
    info = np.diag([sigma**-2, sigma**-2, 0.3**-2, 0, 0, 0])  # a position, nothing about the angles
    return PoseDownlink(fleet=fleet, sender="host", seq=0, t_meas=t, t_sent=t, target=target,
                        pose=np.array([*xy, 0, 0, 0, 0.5], np.float32), pose_info=cov_to_upper(info))  # fmt: skip


def fusion(t_own=1.0, own=(10.0, 5.0)):
    f = DownlinkFusion("cv1", "f", DownlinkParams(seed_search=True))
    f.record(t_own, np.array([*own, 0, 0, 0, 0.5]), OWN_COV)
    return f


def test_a_consistent_downlink_is_fused_and_tightens_the_position_only():
    f = fusion()
    assert f.receive(decode(encode(downlink(1.0, (10.3, 5.0))), PoseDownlink)) is None
    out = f.fuse(1.0, np.array([10.0, 5.0, 0, 0, 0, 0.5]), OWN_COV)
    assert out.status == "fused" and out.used
    # 1-D Kalman per axis: 0.4^2 and 0.1^2 -> mean 10 + 0.3 * 0.16 / 0.17, variance 0.16 * 0.01 / 0.17
    assert out.pose[0] == pytest.approx(10.0 + 0.3 * 0.16 / 0.17, abs=1e-4)
    assert out.cov[0, 0] == pytest.approx(0.16 * 0.01 / 0.17, rel=1e-3)
    np.testing.assert_allclose(out.cov[3:, 3:], OWN_COV[3:, 3:], rtol=1e-6)  # nothing said about the angles
    assert out.pose[5] == pytest.approx(0.5)


def test_a_wrong_host_cannot_drag_a_right_vehicle():
    f = fusion()
    f.receive(downlink(1.0, (14.0, 5.0)))  # 4 m off, claiming 0.1 m
    out = f.fuse(1.0, np.array([10.0, 5.0, 0, 0, 0, 0.5]), OWN_COV)
    assert out.status == "refused" and out.nis > 13.8
    np.testing.assert_array_equal(out.pose[:2], [10.0, 5.0])
    assert f.counts["refused"] == 1


def test_a_downlink_is_moved_by_the_own_motion_since_its_frame_and_expires():
    f = fusion()
    f.record(1.2, np.array([11.6, 5.0, 0, 0, 0, 0.5]), OWN_COV)
    f.receive(downlink(1.0, (10.2, 5.0)))
    z, H, R = f.measurement(1.2, np.array([11.6, 5.0, 0, 0, 0, 0.5]), OWN_COV)
    assert z[0] == pytest.approx(11.8, abs=1e-5)
    assert H.shape == (3, 6) and np.trace(R) > 0.01 + 0.01 + 0.09  # the displacement's error added
    assert f.fuse(2.5, np.array([20.0, 5.0, 0, 0, 0, 0.5]), OWN_COV).status == "stale"


def test_downlinks_for_another_vehicle_or_older_ones_are_refused():
    f = fusion()
    assert f.receive(downlink(1.0, (10, 5), target="cv2")) == "not_for_us"
    assert f.receive(downlink(1.0, (10, 5), fleet="g")) == "fleet"
    assert f.receive(downlink(1.0, (10, 5))) is None
    assert f.receive(downlink(0.9, (10, 5))) == "old"
    assert f.counts["rejected_not_for_us"] == f.counts["rejected_old"] == 1


def test_covariance_intersection_when_correlated_is_no_tighter_than_either_and_conservative():
    f = fusion()
    f.receive(downlink(1.0, (10.3, 5.0)))
    own = np.array([10.0, 5.0, 0, 0, 0, 0.5])
    exact = f.fuse(1.0, own, OWN_COV)
    ci = f.fuse(1.0, own, OWN_COV, correlated=True)
    assert ci.status == "fused_ci"
    assert np.all(np.linalg.eigvalsh(ci.cov - exact.cov) > -1e-12)  # CI never claims more than the exact update
    assert ci.cov[0, 0] >= 0.01 - 1e-9 and ci.cov[0, 0] < OWN_COV[0, 0]


def test_a_searching_vehicle_is_seeded_only_with_a_known_heading():
    f = fusion()
    f.receive(downlink(1.0, (10.3, 5.0)))
    own = np.array([10.0, 5.0, 0, 0, 0, 0.5])
    wide_yaw = OWN_COV.copy()
    wide_yaw[5, 5] = 1.0
    assert f.seed(1.0, own, wide_yaw, 8.0, 1.1) is None and f.counts["seed_no_heading"] == 1
    y, P = f.seed(1.0, own, OWN_COV, 8.0, 1.1)
    assert y[0] == pytest.approx(10.0 + 0.3 * 0.16 / 0.2 + 0.8 * np.cos(0.5), abs=1e-3)  # downlink inflated x4
    assert f.seed(1.5, own, OWN_COV, 8.0, 1.6) is None  # within seed_interval_s
    off = fusion()
    off.params = DownlinkParams(seed_search=False)
    off.receive(downlink(1.0, (10.3, 5.0)))
    assert off.seed(1.0, own, OWN_COV, 8.0, 1.1) is None


def test_a_prior_says_what_the_downlink_did():
    from .test_codec import vehicle_prior

    msg = vehicle_prior(True).model_copy(update={"downlink": "fused"})
    assert decode(encode(msg), VehiclePrior).downlink == "fused"
    assert decode(encode(vehicle_prior(True)), VehiclePrior).downlink is None
