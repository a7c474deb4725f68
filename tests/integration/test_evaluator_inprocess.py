"""The evaluator service's core scores a pipeline run exactly as the in-process code does."""

from __future__ import annotations

import pytest

from mapcontainer.evaluation import Totals, score_frame
from mapcontainer.pipeline import View, run_pipeline
from services.evaluator.core import SCORE_KEYS, Evaluator, steady_name


@pytest.fixture(scope="module")
def run():
    return run_pipeline("paper-urban", seed=5, duration_s=1.5, start="warm", views=(View("cooperative"),))


def test_the_live_evaluator_and_the_in_process_scoring_agree(run):
    ev = Evaluator("f", burnin_s=0.75)
    whole, steady = Totals(), Totals()
    for k, rec in enumerate(run.records):
        fused = rec.fused["cooperative"]
        ev.on_truth(rec.truth)
        ev.on_fused(fused, None, None, now_wall=float(k))
        s = score_frame(fused, rec.truth)  # at the truth of the frame it was fused for
        whole.add(s)
        if fused.t_meas >= 0.75:
            steady.add(s)
    summ = ev.summary()
    assert summ["evaluated"] == len(run.records) == 15 and summ["no_truth"] == 0
    for key in SCORE_KEYS:
        name = "object_coverage" if key == "coverage" else key
        assert summ[name] == whole.summary()[key], key  # the same code on the same states: equal, not close
        assert summ[steady_name(name)] == steady.summary()[key], key
    assert summ["frames_steady"] == 7
    # the figures the fleet report and the live experiment read keep their names
    kept = ("vehicle_rmse_steady_m", "vehicle_rmse_steady_by_id_m", "object_rmse_steady_m", "object_coverage_steady")
    for key in (*kept, "false_track_fraction_steady", "vehicle_rmse_m", "object_rmse_m"):
        assert summ[key] is not None, key
    assert summ["vehicle_nees_steady"]["cells"] == 28  # 4 vehicles x 7 frames (at the first, the vehicles whose
    # clocks run ahead of the ego's have no estimate yet: the host solves at the ego's clock)
    assert len(ev.frames) == 15 and ev.frames[-1]["vehicle_pairs"] == 4
