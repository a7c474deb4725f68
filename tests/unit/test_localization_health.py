"""The pose-health rule (mapcontainer.localization.health) on hand-made step sequences."""

from __future__ import annotations

import pytest

from mapcontainer.localization.health import PoseHealth, PoseHealthParams, advance, verdict
from mapcontainer.localization.startup import Phase

P = PoseHealthParams(gap_s=1.0, relocalized_s=0.5, unlocalized_s=3.0)
T, U, S, V = Phase.TRACKING, Phase.UNINITIALISED, Phase.SEARCHING, Phase.VERIFYING


def run(steps, h: PoseHealth | None = None, p: PoseHealthParams = P):
    """Fold (t, phase, matched[, restarted]) steps; the verdict after each and the final state."""
    h = h or PoseHealth()
    out = []
    for step in steps:
        t, phase, matched, restarted = (*step, False) if len(step) == 3 else step
        h = advance(h, t, phase, matched, restarted, p)
        out.append(verdict(h, p))
    return out, h


def tracked(t0: float = 0.0, n: int = 10):
    """A vehicle map-matched in tracking from its start: (steps, state)."""
    steps = [(t0, U, False)] + [(t0 + 0.1 * k, T, True, k == 1) for k in range(1, n)]
    return run(steps)


def test_no_step_yet_is_ok():
    assert verdict(PoseHealth(), P) == ("ok", None)


def test_start_up_is_starting_until_matched_in_tracking_for_relocalized_s():
    out, h = tracked(n=8)
    assert out[0] == ("starting", "no pose: initialising from GNSS and the camera")
    assert out[1] == ("starting", "localizing: tracking, map-matched for 0.0 s of the 0.5 s that confirm it")
    assert [s for s, _ in out[1:6]] == ["starting"] * 5  # 0.1 .. 0.5: 0.4 s matched so far
    assert out[6:] == [("ok", None)] * 2  # 0.6: 0.5 s since the first match
    assert not h.lost and h.localized


def test_first_step_already_tracking_after_an_initialisation_is_not_ok():
    out, _ = run([(0.0, T, True, True)])
    assert out[0][0] == "starting"


def test_a_cold_start_longer_than_cold_start_s_is_degraded():
    p = PoseHealthParams(gap_s=1.0, relocalized_s=0.5, unlocalized_s=3.0, cold_start_s=10.0)
    steps = [(0.0, U, False)] + [(0.1 * k, S, False) for k in range(1, 121)]  # searching until 12.0 s
    out, h = run(steps, p=p)
    assert out[100] == ("starting", "searching for its pose")  # 10.0 s: still the expected period
    assert out[101] == ("degraded", "searching for its pose (10 s after its start: longer than a cold start's 10 s)")
    assert out[-1][0] == "degraded" and not h.localized


def test_a_pose_lost_after_the_start_is_degraded_even_early():
    _, h = tracked()  # localized by 0.6 s
    out, _ = run([(1.0, S, False)], h)
    assert out == [("degraded", "searching for its pose")]


def test_a_gap_loses_the_pose_until_relocalized():
    _, h = tracked()
    out, h = run([(6.0, T, False), (6.1, T, True), (6.2, T, True), (6.3, T, True), (6.4, T, True)], h)
    assert out[0] == ("degraded", "relocalizing after a 5.1 s gap: tracking, not map-matched yet")
    assert out[1][1].startswith("relocalizing after a 5.1 s gap: tracking, map-matched for 0.0 s")
    assert out[-1][0] == "degraded"
    out, h = run([(6.5, T, True), (6.6, T, True)], h)
    assert out == [("degraded", out[0][1]), ("ok", None)]  # 6.1 .. 6.6


def test_a_gap_then_a_reset_and_a_search_say_which():
    _, h = tracked()
    out, _ = run([(3.0, U, False), (3.1, S, False), (3.2, S, None)], h)
    assert out[0] == ("degraded", "relocalizing after a 2.1 s gap: no pose: initialising from GNSS and the camera")
    assert out[1] == ("degraded", "relocalizing after a 2.1 s gap: searching for its pose")
    assert out[2] == out[1]


def test_a_gap_up_to_gap_s_changes_nothing():
    _, h = tracked()
    out, _ = run([(1.9, T, True)], h)  # 1.0 s after 0.9
    assert out == [("ok", None)]


def test_a_failed_match_while_confirming_starts_the_confirmation_again():
    _, h = tracked()
    steps = [(3.0, T, True), (3.1, T, True), (3.2, T, True), (3.3, T, False)]
    steps += [(3.4 + 0.1 * k, T, True) for k in range(6)]  # 3.4 .. 3.9
    out, _ = run(steps, h)
    assert [s for s, _ in out[:-1]] == ["degraded"] * 9 and out[-1] == ("ok", None)


def test_frames_without_camera_neither_confirm_nor_fail():
    _, h = tracked()
    steps = [(3.0, T, True), (3.1, T, None), (3.2, T, None), (3.3, T, True), (3.4, T, None), (3.5, T, True)]
    out, _ = run(steps, h)
    assert out[-2][0] == "degraded" and out[-1] == ("ok", None)  # 3.0 .. 3.5 matched in tracking


def test_single_fallback_frames_while_tracking_do_not_flicker():
    _, h = tracked()
    steps = [(1.0 + 0.1 * k, T, k % 3 != 0) for k in range(60)]  # every third frame not map-matched
    out, _ = run(steps, h)
    assert set(out) == {("ok", None)}


def test_not_map_matched_while_tracking_for_unlocalized_s():
    _, h = tracked()
    out, h = run([(1.0 + 0.1 * k, T, False) for k in range(32)], h)  # 1.0 .. 4.1
    assert out[30] == ("ok", None)  # 3.0 s
    assert out[31] == ("degraded", "not map-matched for 3.1 s (GNSS-grade priors)")
    out, _ = run([(4.2, T, True)], h)  # the pose was never lost: one match is enough
    assert out == [("ok", None)]


@pytest.mark.parametrize(("phase", "why"), [(S, "searching for its pose"), (V, "verifying its start pose")])
def test_leaving_tracking_loses_the_pose(phase, why):
    _, h = tracked()
    out, h = run([(1.0, phase, False), (1.1, phase, True)], h)
    assert out == [("degraded", why)] * 2
    out, _ = run([(1.2 + 0.1 * k, T, True) for k in range(6)], h)
    assert out[-2][0] == "degraded" and out[-1] == ("ok", None)


def test_a_reinitialisation_within_one_step_while_tracking_loses_the_pose():
    """A reset by GNSS divergence whose re-initialisation succeeds in the same step: still tracking, but a new pose."""
    _, h = tracked()
    out, _ = run([(1.0, T, True, True)], h)
    assert out == [("degraded", "localizing: tracking, map-matched for 0.0 s of the 0.5 s that confirm it")]


def test_parameters_are_checked():
    with pytest.raises(ValueError, match="gap_s"):
        PoseHealthParams(gap_s=0.0)
