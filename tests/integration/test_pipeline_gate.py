"""run_pipeline solves each view's frames when the host's FrameGate releases them, as the live host does."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.channel import NetworkProfile
from mapcontainer.pipeline import View, run_pipeline

VIEWS = (View("cooperative"), View("ego_only", ("cv0",)))


def _run(profile, max_wait_s=0.1):
    return run_pipeline("paper-urban", seed=3, duration_s=1.0, start="warm", views=VIEWS, network=profile,
                        max_wait_s=max_wait_s)  # fmt: skip


def test_ideal_channel_releases_every_frame_at_its_time_complete():
    res = _run("ideal")
    assert len(res.records) == 10
    for rec in res.records:
        for name in ("cooperative", "ego_only"):
            assert rec.released[name] == rec.t
            assert abs(rec.fused[name].t_meas - rec.t) < 0.02  # the ego's clock: a few ms off t_k
    assert res.gate_stats == {v.name: {"complete": 10, "timed_out": 0} for v in VIEWS}


def test_a_frame_waits_for_its_late_senders():
    res = _run(NetworkProfile.custom(latency_ms=40.0))
    rel = np.array([r.released["cooperative"] - r.t for r in res.records])
    assert rel == pytest.approx(0.04, abs=1e-9)  # the remote vehicles' messages arrive 40 ms after t_k
    assert all(r.released["ego_only"] == r.t for r in res.records)  # the ego's own arrives on board
    assert res.gate_stats["cooperative"] == {"complete": 10, "timed_out": 0}
    # everything of frame k is in: the same fused state as on an ideal link
    ideal = _run("ideal")
    for a, b in zip(res.records, ideal.records, strict=True):
        assert np.array_equal(a.fused["cooperative"].vehicle_pose, b.fused["cooperative"].vehicle_pose)


def test_a_frame_whose_senders_are_lost_times_out_max_wait_after_the_first():
    res = _run(NetworkProfile.custom(loss=1.0), max_wait_s=0.07)
    assert [r.released["cooperative"] - r.t for r in res.records] == pytest.approx([0.07] * 10)
    assert res.gate_stats["cooperative"] == {"complete": 0, "timed_out": 10}
    assert all(r.fused["cooperative"].vehicle_ids == ["cv0"] for r in res.records)
