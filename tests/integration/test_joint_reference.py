"""The centralized reference on a traced failure (slow: a whole centralized run)."""

import math
from functools import cache

import numpy as np
import pytest

from mapcontainer import evaluation as ev
from mapcontainer.pipeline import View, run_pipeline

pytestmark = pytest.mark.slow


@cache
def _urban_objects(seed: int) -> tuple[float, int]:
    """Centralized, paper-urban, 8 s scored from 3 s (test_paper_claims' runs): the objects' horizontal RMSE and
    the frames with a fused object within 1 m of a connected vehicle's true position (a copy of the vehicle)."""
    res = run_pipeline("paper-urban", seed=seed, duration_s=8.0, mode="centralized", views=(View("centralized"),))
    sq, copies = [], 0
    for rec in res.records:
        if rec.t < 3.0:
            continue
        fs = ev.score_frame(rec.fused["centralized"], rec.truth)
        sq.extend(fs.object_sq)
        p_obj = np.asarray(rec.fused["centralized"].object_p_map)[:, :2]
        p_veh = np.asarray(rec.truth.vehicle_pose)[:, :2]
        if len(p_obj) and (np.linalg.norm(p_obj[:, None] - p_veh[None], axis=2) < 1.0).any():
            copies += 1
    return math.sqrt(np.mean(sq)), copies


@cache
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
    cars 5-6 m apart. The joint filter shrank its sigma through the tracks it shared with the other vehicles
    while its detections were of the neighbouring cars; its map matching, started from that, locked on a
    wrong basin: cv0 RMSE 6.66 m (to 11 m), NEES 1,899; all vehicles 3.43 m, ANEES 483. Now its frames correct
    its pose only through sure associations (fusion/joint.py): consistent, cv0 2.44 m / NEES 10.9, all
    vehicles 1.60 m / 8.5."""
    sq, nees = _centralized_scores(1004)
    assert np.mean(nees["cv0"]) < 15.0
    assert np.mean(np.concatenate([nees[v] for v in nees])) < 15.0


@pytest.mark.xfail(
    strict=True, reason="issue 34: a fallback vehicle 5 m off is consistent but not corrected: cv0 2.45 m (bound 1 m)"
)
def test_a_vehicle_in_gnss_fallback_is_corrected_by_the_objects_it_shares():
    """Suburban development seed 1004, centralized: with 'one track alone in the gate' cv0 was corrected by
    lone tracks (0.41 m, all vehicles 0.80 m), among them far detections (45 m) of a track three vehicles saw;
    weighed against the objects not yet tracked around it those associations are not sure (probability
    0.01-0.8), so its frames correct nothing until it map-matches: 2.44 m (NEES 10.9). A density of untracked
    objects that follows the road does not do it (docs/host.md, association, "Tried": 3.83 m at the same scale,
    a collapse again at the scenarios' scale, 6.20 m, NEES 233). What it would take: a smoother that revisits
    the association once the vehicle is localized, on a fallback covariance that covers a multipath jump."""
    sq, nees = _centralized_scores(1004)
    assert math.sqrt(np.mean(sq["cv0"])) < 1.0
    assert math.sqrt(np.mean(np.concatenate([sq[v] for v in sq]))) < 1.2


def test_a_fallback_vehicle_is_not_pinned_by_a_lone_wrong_track():
    """Suburban development seed 1006, centralized: cv0 starts in fallback (sigma 1.9 m); in its first frame
    with detections an object nobody tracked yet lay 7.5 m from a confirmed track alone in its gate (d2 1.5),
    the one update moved it 3.6 m onto the wrong object with sigma 0.6 m, and its localizer, started from
    that, kept shrinking while the error grew: 10 m with sigma 0.6 m at 3 s; cv0 RMSE 8.2 m, NEES 1,337.
    Against the density of objects not yet tracked around it (Tracker.untracked_density) that association
    has probability 0.3 and leaves its pose alone: 0.76 m, NEES 3.2."""
    sq, nees = _centralized_scores(1006)
    assert math.sqrt(np.mean(sq["cv0"])) < 1.0
    assert np.mean(nees["cv0"]) < 15.0
    assert math.sqrt(np.mean(np.concatenate([sq[v] for v in sq]))) < 1.0
    assert np.mean(np.concatenate([nees[v] for v in nees])) < 15.0


def test_the_reference_keeps_no_copy_of_a_connected_vehicle_as_an_object():
    """Urban development seed 1003, centralized: cv0 saw cv2 52 m ahead while the track of the car behind cv2,
    coasting without detections, drifted onto cv2; its detections of cv2 became ambiguous (probability 0.41),
    then left cv2's gate, and started a track: a copy of cv2 that the reference kept for the rest of the run,
    scored as the car behind it 2.3-2.9 m off (objects RMSE 0.73 m, a copy of a vehicle in 27 of 50 frames; the
    distributed host deletes such tracks, Tracker.vehicle_shadows, the reference did not). Now the reference
    deletes them too: 0.58 m, 4 frames (the shadow rule's merge_cycles)."""
    rmse, copies = _urban_objects(1003)
    assert rmse < 0.65
    assert copies <= 8, copies
