"""The downlink in process (development seed): no rumour over a minute, no confidence without information.

One 60 s urban run with the downlink on: every vehicle's on-board estimate (its own, with the host's
"what the others know about you" fused) stays consistent (the mean NEES of its horizontal position inside
the chi^2 band of one sample; all four vehicles' means inside the band of four), the downlink is used where the
others see a vehicle, and in every frame a vehicle did not fuse one its on-board covariance is exactly its own
(nothing it was told earlier lingers as confidence).
"""

import numpy as np
import pytest

from mapcontainer.metrics import anees_band
from mapcontainer.pipeline import run_pipeline

pytestmark = pytest.mark.slow

SEED = 7  # development seed
BURNIN_S = 5.0


@pytest.fixture(scope="module")
def run():
    return run_pipeline("paper-urban", seed=SEED, duration_s=60.0, downlink=True)


def test_on_board_nees_stays_in_band_with_the_downlink(run):
    nees: dict[str, list[float]] = {}
    for rec in run.records:
        if rec.t < BURNIN_S:
            continue
        ids = list(rec.truth.vehicle_ids)
        for vid, pose in rec.onboard.items():
            e = pose[:2] - np.asarray(rec.truth.vehicle_pose[ids.index(vid)][:2], float)
            nees.setdefault(vid, []).append(float(e @ np.linalg.solve(rec.onboard_covs[vid][:2, :2], e)))
    means = {v: float(np.mean(x)) for v, x in nees.items()}
    lo1, hi1 = anees_band(2, 1)
    assert all(lo1 <= m <= hi1 for m in means.values()), means
    lo, hi = anees_band(2, len(means))
    assert lo <= np.mean(list(means.values())) <= hi, means


def test_the_downlink_is_used_and_leaves_no_confidence_behind(run):
    used = sum(s in ("fused", "fused_ci") for rec in run.records for s in rec.downlink.values())
    # in the frames where others see it: the others' view is that of the window without the objects (it was used in
    # 31 % of the vehicle frames of this run; more than half while it still came through the objects too, which
    # handed the vehicles their own past: docs/downlink.md)
    assert used > 0.25 * sum(len(rec.downlink) for rec in run.records)
    assert sum(run.rx_bytes.values()) > 0
    for rec in run.records:
        for vid, status in rec.downlink.items():
            if status not in ("fused", "fused_ci"):
                # the prior's covariance as the wire quantises it (float16 sigmas, int16 correlations)
                assert np.allclose(rec.onboard_covs[vid], rec.prior_covs[vid], rtol=2e-3, atol=1e-9), (rec.t, vid)


def test_a_vehicle_the_host_does_not_hear_gets_nothing():
    from mapcontainer.pipeline import View

    res = run_pipeline(
        "paper-urban", seed=SEED, duration_s=4.0, downlink=True, views=(View("c", ("cv0", "cv1", "cv2")),)
    )
    assert res.rx_msgs.get("cv3", 0) == 0
    assert {rec.downlink.get("cv3") for rec in res.records} <= {None, "none"}
