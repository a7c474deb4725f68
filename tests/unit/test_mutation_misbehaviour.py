"""mapcontainer.fusion.misbehaviour: the exact sightings, views, thresholds and reasons of the monitor (edges of
every parameter), so a wrong constant or comparison changes a decision a test reads."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.misbehaviour import MisbehaviourMonitor

from .test_fusion_misbehaviour import EAST, KNOWS, look_for, run

I3 = np.eye(3)


def _reported(vids, xy, var=0.01):
    return np.array(vids), np.array([[x, y, 0.0] for x, y in xy]), np.tile(var * I3, (len(vids), 1, 1))


def test_a_sighting_is_the_nearest_vehicle_like_detection_within_the_radius() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    p = np.array([[10.5, 0.2, 0.0], [10.1, 0.0, 0.0], [16.0, 0.0, 0.0], [30.0, 0.0, 0.0], [40.0, 6.0, 0.0]])
    cov = np.stack([k * I3 for k in (0.1, 0.2, 0.3, 0.4, 0.5)])
    cls = np.array([2, 1, 0, 2, 0])  # the one at 10.1 is a pedestrian: not vehicle-like
    rep = _reported(["cv0", "cv1", "cv2", "cv3"], [(0, 0), (10, 0), (30, 0.5), (40, 0)], var=0.01)
    mon.observe("cv0", 1.0, p, cov, cls, rep)
    (s1,) = mon._sightings["cv1"]
    assert (s1.t, s1.observer) == (1.0, "cv0")
    assert s1.offset == pytest.approx(np.array([0.5, 0.2]))
    assert s1.cov == pytest.approx(0.11 * np.eye(2))  # the detection's (0.1) and the vehicle's (0.01)
    (s2,) = mon._sightings["cv2"]
    assert s2.offset == pytest.approx(np.array([0.0, -0.5]))  # 30.0 nearer than 16.0 (class 0 = unknown)
    (s3,) = mon._sightings["cv3"]
    assert s3.offset == pytest.approx(np.array([0.0, 6.0]))  # exactly the 6 m radius: a sighting
    assert "cv0" not in mon._sightings  # nobody sights themself


def test_no_sighting_beyond_the_radius_or_without_vehicle_like_detections() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    rep = _reported(["cv0", "cv1"], [(0, 0), (10, 0)])
    mon.observe("cv0", 1.0, np.array([[16.01, 0.0, 0.0]]), I3[None], np.array([2]), rep)
    mon.observe("cv0", 1.0, np.array([[10.0, 0.0, 0.0]]), I3[None], np.array([1]), rep)  # a pedestrian
    mon.observe("cv0", 1.0, np.array([[10.0, 0.0, 0.0]]), I3[None], np.array([2]), _reported(["cv0"], [(0, 0)]))
    assert mon._sightings == {}


def _views(offsets_by_observer: dict[str, tuple[float, float]], n: int = 4, var: float = 0.01, params=None):
    """cv9 reported at the origin, each observer sees it at ``offset`` n times (0.1 s apart)."""
    mon = MisbehaviourMonitor(params or FusionParams())
    for k in range(n):
        for o, off in offsets_by_observer.items():
            rep = _reported([o, "cv9"], [(50, 50), (0, 0)], var=var / 2)
            mon.observe(o, 0.1 * k, np.array([[off[0], off[1], 0.0]]), (var / 2 * I3)[None], np.array([2]), rep)
    return mon


def test_a_view_needs_min_sightings() -> None:
    mon = _views({"cv1": (3.0, 0.0), "cv2": (3.0, 0.0)}, n=3)
    assert mon.update(0.3) == {} and mon.disputed == set()
    mon = _views({"cv1": (3.0, 0.0), "cv2": (3.0, 0.0)}, n=4)
    assert mon.update(0.3) == {"cv9": "seen 3.0 m from its reported position (+3.0, +0.0) by cv1, cv2 in the last 2 s"}
    assert mon.disputed == {frozenset(("cv1", "cv9")), frozenset(("cv2", "cv9"))}
    assert mon.disputes("cv9", "cv1") and not mon.disputes("cv1", "cv2") and mon.flagged_total == 1


def test_a_view_within_the_offset_floor_agrees_whatever_its_covariance() -> None:
    mon = _views({"cv1": (0.6, 0.0), "cv2": (0.0, 0.6)}, var=1e-6)
    assert mon.update(0.3) == {} and mon.disputed == set()
    mon = _views({"cv1": (0.61, 0.0), "cv2": (0.0, 0.61)}, var=1e-6)
    assert list(mon.update(0.3)) == ["cv9"]


def test_a_view_its_covariance_allows_agrees() -> None:
    """Mahalanobis d^2 = |offset|^2 / var against chi2.ppf(0.999, 2) = 13.8155."""
    gate = 13.815510557964274
    ok = _views({"cv1": (2.0, 0.0), "cv2": (2.0, 0.0)}, var=4.0 / gate + 1e-4)
    assert ok.update(0.3) == {}
    off = _views({"cv1": (2.0, 0.0), "cv2": (2.0, 0.0)}, var=4.0 / gate - 1e-4)
    assert list(off.update(0.3)) == ["cv9"]
    assert MisbehaviourMonitor(FusionParams())._gate == pytest.approx(gate)


def test_a_singular_covariance_disagrees() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    assert mon._agrees(np.array([1.0, 0.0]), np.zeros((2, 2))) is False
    assert mon._agrees(np.array([0.6, 0.0]), np.zeros((2, 2))) is True


def test_the_view_is_the_median_and_its_covariance_the_mean() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    for k, (x, var) in enumerate([(1.0, 0.1), (2.0, 0.2), (5.0, 0.3), (2.5, 0.4)]):
        rep = _reported(["cv1", "cv9"], [(50, 50), (0, 0)], var=0.0)
        mon.observe("cv1", 0.1 * k, np.array([[x, 0.0, 0.0]]), (var * I3)[None], np.array([2]), rep)
    mon.update(0.3)
    assert mon.disputed == {frozenset(("cv1", "cv9"))}  # median 2.25 m, mean covariance 0.25: d^2 = 20.25
    mon2 = MisbehaviourMonitor(FusionParams())
    for k, (x, var) in enumerate([(1.0, 0.1), (2.0, 0.2), (5.0, 0.3), (2.5, 1.0)]):
        rep = _reported(["cv1", "cv9"], [(50, 50), (0, 0)], var=0.0)
        mon2.observe("cv1", 0.1 * k, np.array([[x, 0.0, 0.0]]), (var * I3)[None], np.array([2]), rep)
    mon2.update(0.3)
    assert mon2.disputed == set()  # mean covariance 0.4: d^2 = 12.66 inside the gate


def test_sightings_older_than_the_window_are_dropped() -> None:
    mon = _views({"cv1": (3.0, 0.0), "cv2": (3.0, 0.0)}, n=4)  # sightings at 0.0 .. 0.3
    assert list(mon.update(2.0)) == ["cv9"]  # 0.0 is exactly the window's start: kept
    assert [len(q) for q in mon._sightings.values()] == [8]
    mon.update(2.05)  # the sightings at 0.0 left the window: 3 per observer, no view
    assert [len(q) for q in mon._sightings.values()] == [6] and mon.disputed == set()
    assert list(mon.flagged) == ["cv9"]  # the flag stays until a view of cv9 agrees again
    mon.update(2.35)
    assert mon._sightings == {} and mon.disputed == set()


def test_accusers_must_agree_with_each_other() -> None:
    spread = _views({"cv1": (3.0, 0.0), "cv2": (3.0, 1.0)})  # 1 m apart: each 0.5 m from the median
    assert list(spread.update(0.3)) == ["cv9"]
    apart = _views({"cv1": (3.0, 0.0), "cv2": (3.0, 2.0)})  # each 1.0 m from the median: not below the spread
    assert apart.update(0.3) == {}
    assert apart.disputed == {frozenset(("cv1", "cv9")), frozenset(("cv2", "cv9"))}


def test_one_accuser_is_not_enough_without_corroboration() -> None:
    mon = _views({"cv1": (3.0, 0.0)})
    assert mon.update(0.3) == {} and mon.disputed == {frozenset(("cv1", "cv9"))}
    one = _views({"cv1": (3.0, 0.0)}, params=FusionParams(misbehaviour_min_observers=1))
    assert one.update(0.3) == {"cv9": "seen 3.0 m from its reported position (+3.0, +0.0) by cv1 in the last 2 s"}


def test_a_single_observer_corroborated_now_flags_one_that_is_not() -> None:
    mon = MisbehaviourMonitor(FusionParams())

    def frame(t: float, cv9_off: float) -> None:
        # cv1 sees cv2 where it says (corroborating cv1) and cv9 cv9_off metres off
        rep = _reported(["cv1", "cv2", "cv9"], [(50, 50), (20, 0), (0, 0)])
        mon.observe(
            "cv1",
            t,
            np.array([[20.0, 0.0, 0.0], [cv9_off, 0.0, 0.0]]),
            np.tile(0.01 * I3, (2, 1, 1)),
            np.array([2, 2]),
            rep,
        )

    for k in range(4):
        frame(0.1 * k, 0.0)
    mon.update(0.3)
    assert mon.flagged == {}
    for k in range(4, 30):
        frame(0.1 * k, 3.0)
    flags = mon.update(2.9)
    assert flags == {"cv9": "seen 3.0 m from its reported position (+3.0, +0.0) by cv1 in the last 2 s"}


def test_message_repeats() -> None:
    pp = FusionParams()
    mon = MisbehaviourMonitor(pp)
    mon.message("cv1", 1.0, 1.0, None)
    mon.message("cv1", 5.0, 1.1, "future")  # a future message does not move the newest instant
    mon.message("cv1", 1.0, 1.2, "duplicate")  # t_meas == newest: repeats
    mon.message("cv1", 0.5, 1.3, "stale")
    mon.message("cv1", 0.9, 1.4, "bad_input")  # other refusals do not count
    assert [rep for _, rep in mon._arrivals["cv1"]] == [False, False, True, True, False]
    assert mon._newest["cv1"] == 1.0
    assert mon.update(1.4) == {}  # 2 repeats < clock_min_repeats = 3
    mon.message("cv1", 1.0, 1.5, "stale")
    assert mon.update(1.5) == {
        "cv1": "3 of its 6 messages in the last 2 s repeat instants it had sent (a frozen clock or a replay)"
    }


def test_repeats_must_be_a_fraction_of_the_messages() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(7):
        mon.message("cv1", 1.0 + k, 0.1 * k, None)
    for k in range(3):
        mon.message("cv1", 1.0, 0.8 + 0.1 * k, "duplicate")  # 3 of 10 = 0.3: flagged
    assert list(mon.update(1.0)) == ["cv1"]
    mon2 = MisbehaviourMonitor(FusionParams())
    for k in range(8):
        mon2.message("cv1", 1.0 + k, 0.1 * k, None)
    for k in range(3):
        mon2.message("cv1", 1.0, 0.9 + 0.1 * k, "duplicate")  # 3 of 11 < 0.3
    assert mon2.update(1.1) == {}
    assert mon2.update(3.5) == {} and "cv1" not in mon2._arrivals  # all older than the window: forgotten


def test_a_repeat_flag_holds_while_any_repeat_is_in_the_window() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(3):
        mon.message("cv1", 0.0, 0.1 * k, "duplicate" if k else None)
    mon.message("cv1", 0.0, 0.3, "duplicate")
    assert list(mon.update(0.3)) == ["cv1"]  # 3 of 4
    for k in range(4, 30):
        mon.message("cv1", 0.1 * k, 0.1 * k, None)
    assert list(mon.update(2.2)) == ["cv1"]  # one repeat (at 0.3) still in the window: held
    assert mon.update(2.4) == {}


def test_looks_only_at_what_the_observer_should_see() -> None:
    pp = FusionParams()
    for track_p, occluders, expect in [
        ((2.9, 0.0), (), []),  # nearer than 3 m: not a look
        ((3.0, 0.0), (), [7]),
        ((40.0, 0.0), (), [7]),  # exactly the range
        ((40.0 * np.cos(np.radians(49.9)), 40.0 * np.sin(np.radians(49.9))), (), [7]),  # inside half the 100 deg
        ((20.0 * np.cos(np.radians(50.5)), 20.0 * np.sin(np.radians(50.5))), (), []),
        ((20.0, 0.0), [(1.0, 0.0)], [7]),  # at 1 m along the line: not between
        ((20.0, 0.0), [(19.0, 0.0)], [7]),  # 1 m before the track: not between
        ((20.0, 0.0), [(10.0, 1.5)], [7]),  # 1.5 m beside the line: not on it
        ((20.0, 0.0), [(10.0, 1.49)], []),
    ]:
        mon = MisbehaviourMonitor(pp)
        assert look_for(mon, 0.0, pp.ghost_min_looks, [], track_p, occluders) == expect, (track_p, occluders)


def test_the_gate_and_the_seen_fraction() -> None:
    pp = FusionParams()
    mon = MisbehaviourMonitor(pp)
    assert look_for(mon, 0.0, pp.ghost_min_looks, [[22.5, 0.0, 0.0]]) == []  # 2.5 m: seen
    mon = MisbehaviourMonitor(pp)
    assert look_for(mon, 0.0, pp.ghost_min_looks, [[22.51, 0.0, 0.0]]) == [7]
    mon = MisbehaviourMonitor(pp)  # seen 2 of 8 = 0.25: still denied
    for k in range(pp.ghost_min_looks):
        seen = [[20.0, 0.0, 0.0]] if k in (0, 1) else []
        out = look_for(mon, 0.1 * k, 1, seen)
    assert out == [7]
    mon = MisbehaviourMonitor(pp)
    assert look_for(mon, 0.0, pp.ghost_min_looks - 1, []) == []  # 7 looks: not enough
    mon = MisbehaviourMonitor(pp)  # an observer with 0.5 m sigma exactly: still knows where it is
    assert look_for(mon, 0.0, pp.ghost_min_looks, [], cov=0.5**2 * np.eye(6)) == [7]


def test_a_flagged_observer_denies_nothing() -> None:
    pp = FusionParams()
    mon = MisbehaviourMonitor(pp)
    mon.flagged = {"cv0": "x"}
    for k in range(pp.ghost_min_looks):
        mon.look("cv0", 0.1 * k, EAST, KNOWS, np.zeros((0, 3)), [(7, "cv1")], np.array([[20.0, 0.0]]), np.zeros((0, 2)))
    mon._update_ghosts(0.7)
    assert mon.denied == []


def test_two_denials_flag_only_when_together() -> None:
    pp = FusionParams()
    mon = MisbehaviourMonitor(pp)
    look_for(mon, 0.0, pp.ghost_min_looks, [], tid=7)  # denied at 0.7
    look_for(mon, 0.8, pp.ghost_min_looks, [], tid=8)  # denied at 1.5: 0.8 s later
    assert mon.flagged == {}
    mon = MisbehaviourMonitor(pp)
    look_for(mon, 0.0, pp.ghost_min_looks, [], tid=7)
    mon.look("cv0", 0.8, EAST, KNOWS, np.zeros((0, 3)), [(8, "cv1")], np.array([[20.0, 5.0]]), np.zeros((0, 2)))
    for k in range(1, pp.ghost_min_looks):
        mon.look(
            "cv0", 0.8 + 0.1 * k, EAST, KNOWS, np.zeros((0, 3)), [(8, "cv1")], np.array([[20.0, 5.0]]), np.zeros((0, 2))
        )
    mon.update(1.2)  # denied at 1.2: 0.5 s after the first, exactly ghost_together_s
    assert mon.flagged == {"cv1": "reported 2 objects in 4 s that others should see and did not (#7 by cv0, #8 by cv0)"}
    assert mon.flagged_total == 1


def test_biased_vehicle_reason_names_every_accuser() -> None:
    mon = run({"cv1": (0.0, -5.0)}, ["cv0", "cv2", "cv3"])
    assert mon.flagged == {"cv1": "seen 5.0 m from its reported position (+0.0, +5.0) by cv0, cv2, cv3 in the last 2 s"}


def test_nothing_is_disputed_before_the_first_update() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    assert mon.disputes("cv0", "cv1") is False and mon.flagged == {} and mon.denied == []


def _deny_at(mon: MisbehaviourMonitor, t_end: float, tid: int, observer=EAST, where=(20.0, 0.0)) -> list[int]:
    """cv0 looks at cv1's track ``tid`` 8 times, every 0.125 s up to ``t_end`` (binary-exact times), sees nothing."""
    denied = []
    for k in range(8):
        t = t_end - 0.125 * (7 - k)
        mon.look("cv0", t, observer, KNOWS, np.zeros((0, 3)), [(tid, "cv1")], np.array([where]), np.zeros((0, 2)))
        mon.update(t)
        denied += mon.denied
    return denied


def test_the_denial_window_keeps_a_denial_exactly_its_length_ago() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    assert _deny_at(mon, 1.0, 7) == [7] and _deny_at(mon, 3.0, 8) == [8]
    assert mon.flagged == {}
    assert _deny_at(mon, 5.0, 9) == [9]  # the first denial is exactly ghost_denial_window_s (4 s) ago: three
    assert mon.flagged == {
        "cv1": "reported 3 objects in 4 s that others should see and did not (#7 by cv0, #8 by cv0, #9 by cv0)"
    }


def test_two_denials_exactly_ghost_together_s_apart_flag() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    _deny_at(mon, 1.0, 7)
    _deny_at(mon, 1.5, 8, where=(20.0, 5.0))
    assert list(mon.flagged) == ["cv1"]
    mon = MisbehaviourMonitor(FusionParams())
    _deny_at(mon, 1.0, 7)
    _deny_at(mon, 1.625, 8, where=(20.0, 5.0))
    assert mon.flagged == {}


def test_looks_from_an_observer_away_from_the_origin_heading_west() -> None:
    """Observer at (100, 50) heading 3.0 rad; a track 20 m away at bearing -3.0 rad (6 rad apart unwrapped,
    0.28 rad wrapped): in view."""
    west = np.array([100.0, 50.0, 0.0, 0.0, 0.0, 3.0])
    where = (100.0 + 20.0 * np.cos(-3.0), 50.0 + 20.0 * np.sin(-3.0))
    assert _deny_at(MisbehaviourMonitor(FusionParams()), 1.0, 7, observer=west, where=where) == [7]
    behind = (100.0 + 20.0, 50.0)
    assert _deny_at(MisbehaviourMonitor(FusionParams()), 1.0, 7, observer=west, where=behind) == []


def test_an_occluder_beside_a_diagonal_line_of_sight() -> None:
    """Line of sight at 45 deg to (20, 20); an occluder at (10, 12) is 1.41 m off it: hides; at (10, 12.2) 1.56 m."""
    pp = FusionParams()
    for occ, expect in (((10.0, 12.0), []), ((10.0, 12.2), [7])):
        mon = MisbehaviourMonitor(pp)
        assert look_for(mon, 0.0, pp.ghost_min_looks, [], (20.0, 20.0), [occ]) == expect, occ


def test_a_corroborated_accuser_is_named_alone_when_the_accusers_disagree() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(30):
        t = 0.1 * k
        # cv1 sees cv2 where it says (cv1 is corroborated); cv1 and cv3 see cv9 off, 2 m apart from each other
        rep = _reported(["cv1", "cv2", "cv3", "cv9"], [(50, 50), (20, 0), (-50, -50), (0, 0)])
        mon.observe(
            "cv1",
            t,
            np.array([[20.0, 0.0, 0.0], [3.0, 0.0, 0.0]]),
            np.tile(0.01 * I3, (2, 1, 1)),
            np.array([2, 2]),
            rep,
        )
        if k >= 4:
            mon.observe("cv3", t, np.array([[3.0, 2.0, 0.0]]), (0.01 * I3)[None], np.array([2]), rep)
        mon.update(t)
    # the median of both views, named by the corroborated one only
    assert mon.flagged == {"cv9": "seen 3.2 m from its reported position (+3.0, +1.0) by cv1 in the last 2 s"}


def test_an_observer_unsure_along_one_axis_does_not_look() -> None:
    """Its position 1-sigma is 1 m along x (0.1 m along y): the largest, not the smallest, decides."""
    pp = FusionParams()
    cov = np.diag([1.0, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    assert look_for(MisbehaviourMonitor(pp), 0.0, pp.ghost_min_looks, [], cov=cov) == []


def test_the_field_of_view_is_about_the_observers_heading() -> None:
    north = np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    assert _deny_at(MisbehaviourMonitor(FusionParams()), 1.0, 7, observer=north, where=(0.0, 20.0)) == [7]
    assert _deny_at(MisbehaviourMonitor(FusionParams()), 1.0, 7, observer=north, where=(20.0, 0.0)) == []


def test_occluders_are_taken_relative_to_an_observer_away_from_the_origin() -> None:
    o = np.array([100.0, 50.0, 0.0, 0.0, 0.0, 0.0])
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(8):
        t = 0.125 * k
        mon.look(
            "cv0", t, o, KNOWS, np.zeros((0, 3)), [(7, "cv1")], np.array([[120.0, 50.0]]), np.array([[110.0, 50.0]])
        )
        mon.update(t)
        assert mon.denied == []  # the vehicle at (110, 50) hides it


def test_a_ghost_flag_holds_exactly_ghost_hold_s() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    _deny_at(mon, 1.0, 7)
    _deny_at(mon, 1.5, 8, where=(20.0, 5.0))  # two at once: flagged at 1.5
    mon.update(6.5)
    assert list(mon.flagged) == ["cv1"]  # exactly 5 s after the last denial
    mon.update(6.625)
    assert mon.flagged == {}


def test_two_reasons_are_joined() -> None:
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(4):
        mon.message("cv1", 0.0, 0.125 * k, "duplicate" if k else None)
    _deny_at(mon, 1.0, 7)
    _deny_at(mon, 1.5, 8, where=(20.0, 5.0))
    assert mon.flagged == {
        "cv1": "reported 2 objects in 4 s that others should see and did not (#7 by cv0, #8 by cv0); "
        "3 of its 4 messages in the last 2 s repeat instants it had sent (a frozen clock or a replay)"
    }
