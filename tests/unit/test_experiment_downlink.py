"""The downlink on/off experiment's figures from synthetic runs."""

import math

import pytest

from mapcontainer.experiments.downlink import markdown, summarize


def _run(errs, nees, rx=0):
    rows = {"cv0": [[0.1 * k, e, n] for k, (e, n) in enumerate(zip(errs, nees, strict=True))]}
    return {
        "rows": rows,
        "tx_bytes": 1000,
        "rx_bytes": rx,
        "duration_s": 0.1 * len(errs),
        "downlink_counts": {"fused": 3},
    }


def test_summary_scores_after_the_burnin_and_counts_frames_without_a_pose():
    errs = [math.nan, 5.0] + [0.2] * 20
    f = summarize([_run(errs, [math.nan, 50.0] + [2.0] * 20, rx=500)], burnin_s=0.15)
    assert f["onboard_rmse_m"] == pytest.approx(0.2)
    assert f["frames_without_pose"] == 0 and f["onboard_anees_2dof"] == pytest.approx(2.0)
    assert f["time_to_localize_s"]["p50"] == pytest.approx(0.2) and f["time_to_localize_s"]["never"] == 0
    assert f["downlink_bytes_per_s"] == pytest.approx(500 / 2.2) and f["downlink"] == {"fused": 3}
    table = markdown({"paper-urban": {"off": f, "on": f}})
    assert table.count("\n") == 3 and "| paper-urban | on | 0.200 |" in table
