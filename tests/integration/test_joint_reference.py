"""The centralized reference on a traced failure (slow: a whole centralized run)."""

import math

import numpy as np
import pytest

from mapcontainer import evaluation as ev
from mapcontainer.pipeline import View, run_pipeline

pytestmark = pytest.mark.slow


def _centralized_scores(seed: int) -> tuple[dict, dict]:
    """Per vehicle: squared horizontal errors and 6-DoF NEES of the centralized host from 3 s on."""
    res = run_pipeline("paper-suburban", seed=seed, duration_s=10.0, mode="centralized", views=(View("centralized"),))
    sq, nees = {}, {}
    for rec in res.records:
        if rec.t < 3.0:
            continue
        fs = ev.score_frame(rec.fused["centralized"], rec.truth)
        for j, vid in enumerate(fs.vehicle_ids):
            sq.setdefault(vid, []).append(fs.vehicle_sq[j])
            nees.setdefault(vid, []).append(fs.vehicle_nees[j])
    return sq, nees


def test_a_vehicle_in_gnss_fallback_does_not_collapse_through_shared_objects():
    """Suburban development seed 1004, centralized: cv0 starts 5 m off (GNSS multipath) in fallback among
    parked cars 5-6 m apart. The joint filter shrank its sigma through the tracks it shared with the other
    vehicles while its detections were of the neighbouring cars; its map matching, started from that, locked
    on a wrong basin: cv0 RMSE 6.66 m (to 11 m), NEES 1,899; all vehicles 3.43 m, ANEES 483. Now: its
    ambiguous frames leave its pose alone (fusion/joint.py), 0.41 m and 7.0; all vehicles 0.80 m, 8.5."""
    sq, nees = _centralized_scores(1004)
    assert math.sqrt(np.mean(sq["cv0"])) < 1.0
    assert np.mean(nees["cv0"]) < 15.0
    assert math.sqrt(np.mean(np.concatenate([sq[v] for v in sq]))) < 1.2
    assert np.mean(np.concatenate([nees[v] for v in nees])) < 15.0


@pytest.mark.xfail(strict=True, reason="issue 34: a lone track in a fallback vehicle's gate may be the wrong object")
def test_a_fallback_vehicle_is_not_pinned_by_a_lone_wrong_track():
    """Suburban development seed 1006, centralized: cv0 starts 5.5 m off in fallback; frames in which each of
    its detections had one track alone in its gate were of the wrong objects (the right ones had no track
    yet, a neighbour did), so they tightened it (2.7 -> 2.0 m at 1.0 s, 1.4 -> 1.2 m at 1.5 s) and its
    localizer, started from that, kept shrinking while the error grew: 10 m with sigma 0.6 m at 3 s; cv0 RMSE
    8.2 m, NEES 1,337. What it would take: the probability that the lone track is the object against a new
    one (with the density of objects not yet tracked, not only false alarms), or a smoother that revisits
    the association."""
    sq, nees = _centralized_scores(1006)
    assert math.sqrt(np.mean(sq["cv0"])) < 1.0
    assert np.mean(nees["cv0"]) < 15.0
