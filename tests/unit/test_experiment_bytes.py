"""The byte figures are those of the messages a run really sends."""

from __future__ import annotations

import json

import pytest

from mapcontainer.experiments.bytes import VARIANTS, measure_bytes, seed_bytes
from mapcontainer.pipeline import run_pipeline

SEED = 90000


@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_the_bytes_are_those_run_pipeline_offers_to_the_link(mode):
    """seed_bytes runs the vehicles' side itself (to encode each frame in every variant): its totals
    must stay those of run_pipeline, which offers the same messages to the channel."""
    mine = seed_bytes("paper-urban", SEED, 1.0, signing=True)[mode]
    res = run_pipeline("paper-urban", seed=SEED, duration_s=1.0, mode=mode, views=(), signing=True)
    assert mine["messages"] == sum(res.tx_msgs.values())
    assert mine["bytes"] == sum(res.tx_message_bytes.values())
    assert mine["bytes_signed"] == pytest.approx(sum(res.tx_bytes.values()), abs=2 * mine["messages"])


def test_measure_bytes_reports_both_modes_and_the_ratios_with_and_without_the_lane_mask():
    res = measure_bytes("paper-urban", seeds=[SEED], duration_s=0.5, signing=True)
    json.dumps(res, allow_nan=False)  # JSON-able as it is
    v = res["variants"]
    assert set(v) == set(VARIANTS)
    assert v["distributed"]["msgs_per_s_per_vehicle"] == pytest.approx(10.0)
    assert v["centralized"]["lane_mask_px"] == [[640, 360]]
    assert v["centralized_camera_resolution"]["lane_mask_px"] == [[1280, 720]]
    assert v["centralized_no_lane_mask"]["lane_mask_bytes_per_message"] == 0.0
    d, c, n = v["distributed"], v["centralized"], v["centralized_no_lane_mask"]
    assert d["bytes_per_message"] < n["bytes_per_message"] < c["bytes_per_message"]
    assert c["bytes_per_message"] < v["centralized_camera_resolution"]["bytes_per_message"]
    for key in ("bytes_per_message", "bytes_per_message_signed"):
        # the mask, its tag and its bin header (and, signed, perhaps a longer bin header of the payload)
        assert c[key] - n[key] == pytest.approx(c["lane_mask_bytes_per_message"], abs=6)
    r = res["ratio"]
    assert r["with_lane_mask_per_message"] == pytest.approx(c["bytes_per_message"] / d["bytes_per_message"], abs=0.01)
    assert r["without_lane_mask_per_s_signed"] == pytest.approx(
        n["bytes_per_s_per_vehicle_signed"] / d["bytes_per_s_per_vehicle_signed"], abs=0.01
    )
    assert 1.0 < r["without_lane_mask_per_message"] < r["with_lane_mask_per_message"]
    assert r["with_lane_mask_per_message_signed"] < r["with_lane_mask_per_message"]  # signing adds the same bytes
    unsigned = measure_bytes("paper-urban", seeds=[SEED], duration_s=0.2, signing=False)
    assert "bytes_per_message_signed" not in unsigned["variants"]["centralized"]
    assert not any(k.endswith("_signed") for k in unsigned["ratio"])
