"""Whether a vehicle knows where it is: the localization part of its health, as a pure rule.

The rule folds the localizer's steps one by one (:func:`advance`, scenario time as an argument) into a
:class:`PoseHealth` and reads it (:func:`verdict`). The pose is *lost* from the first step after

* a gap between steps longer than ``gap_s`` (a frozen or restarted process, frames lost): the
  prediction over it has the odometry of its two ends only (3.1 s across a turn put the pose 15 m
  and 39 degrees off, with a covariance that refused the GNSS fixes),
* a (re)initialisation of the localizer (start-up, a reset by a gap or by GNSS divergence), or
* any phase but TRACKING (uninitialised, verifying a start pose, searching among hypotheses),

until frames map-matched in TRACKING have followed one another for ``relocalized_s``: one
accepted match after a search or a gap is not yet a pose. While lost the vehicle is degraded, except
in its cold start: lost since its first step and never localized yet, for at most ``cold_start_s``
after that step, it is *starting* (the expected search for its pose from GNSS in its first seconds).

While tracking and not lost, frames that are not map-matched (GNSS and odometry only) are allowed
for ``unlocalized_s``, so that single failed matches do not flicker the health; longer, it is
degraded. Frames without a camera (a skipped frame's odometry and GNSS) count for the time and
the phase but are neither a match nor a failed one.
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from .startup import Phase

__all__ = ["PoseHealth", "PoseHealthParams", "advance", "verdict"]

_EPS = 1e-6  # frame times are sums of 0.1 s: 13.6 - 13.1 must count as 0.5

_SEEKING = {
    Phase.UNINITIALISED: "no pose: initialising from GNSS and the camera",
    Phase.VERIFYING: "verifying its start pose",
    Phase.SEARCHING: "searching for its pose",
}


class PoseHealthParams(BaseModel):
    """Thresholds of the rule, in scenario seconds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    gap_s: float = Field(1.0, gt=0, description="a longer gap between the localizer's steps loses the pose")
    relocalized_s: float = Field(
        0.5, ge=0, description="a lost pose is found again after map-matched tracking frames for this long"
    )
    unlocalized_s: float = Field(3.0, gt=0, description="tracking frames not map-matched for longer: degraded")
    cold_start_s: float = Field(
        20.0,
        ge=0,
        description="a vehicle lost since its first step is starting, not degraded, this long after it "
        "(the paper-urban fleet's slowest cold starts took about 17 s)",
    )


@dataclass(frozen=True)
class PoseHealth:
    """The rule's state after the newest step (all times scenario seconds)."""

    t: float | None = None  # the newest step (None: no step yet)
    phase: Phase = Phase.UNINITIALISED  # the localizer's after it
    lost: bool = False  # the pose is not known (see the module doc)
    gap: float | None = None  # while lost: the gap that lost it, if one did
    matched_since: float | None = None  # while lost: the first of the map-matched tracking frames since
    unmatched_since: float | None = None  # not lost: the first of the tracking frames not map-matched since
    t_first: float | None = None  # the first step
    localized: bool = False  # whether the pose was ever known (not lost) since the first step


def advance(
    h: PoseHealth, t: float, phase: Phase, matched: bool | None, restarted: bool, p: PoseHealthParams
) -> PoseHealth:
    """The state after one localizer step at time ``t``: its phase after the step, whether its camera
    frame was map-matched (None: no camera frame) and whether the localizer (re)initialised in it."""
    gap = None if h.t is None else t - h.t
    lost, lost_gap, matched_since, unmatched_since = h.lost, h.gap, h.matched_since, h.unmatched_since
    if gap is not None and gap > p.gap_s:
        lost, lost_gap, matched_since = True, gap, None
    if restarted and not lost:
        lost, matched_since = True, None
    if phase is not Phase.TRACKING:
        lost, matched_since, unmatched_since = True, None, None
    elif matched is True:
        unmatched_since = None
        if lost:
            matched_since = t if matched_since is None else matched_since
            if t - matched_since >= p.relocalized_s - _EPS:
                lost, lost_gap, matched_since = False, None, None
    elif matched is False:
        matched_since = None
        if not lost and unmatched_since is None:
            unmatched_since = t
    if lost:
        unmatched_since = None
    t_first = t if h.t_first is None else h.t_first
    return PoseHealth(t, phase, lost, lost_gap, matched_since, unmatched_since, t_first, h.localized or not lost)


def verdict(h: PoseHealth, p: PoseHealthParams) -> tuple[str, str | None]:
    """("ok", None), ("starting", why) in the cold start's expected period, or ("degraded", why)."""
    if h.t is None:
        return "ok", None
    if h.lost:
        state = "degraded"
        if not h.localized and h.t_first is not None and h.t - h.t_first <= p.cold_start_s + _EPS:
            state = "starting"
        head = "localizing" if h.gap is None else f"relocalizing after a {h.gap:.1f} s gap"
        if h.phase in _SEEKING:
            why = _SEEKING[h.phase] if h.gap is None else f"{head}: {_SEEKING[h.phase]}"
        elif h.matched_since is None:
            why = f"{head}: tracking, not map-matched yet"
        else:
            done = h.t - h.matched_since
            why = f"{head}: tracking, map-matched for {done:.1f} s of the {p.relocalized_s:g} s that confirm it"
        if state == "degraded" and not h.localized:
            why = f"{why} ({h.t - h.t_first:.0f} s after its start: longer than a cold start's {p.cold_start_s:g} s)"
        return state, why
    if h.unmatched_since is not None and h.t - h.unmatched_since > p.unlocalized_s:
        return "degraded", f"not map-matched for {h.t - h.unmatched_since:.1f} s (GNSS-grade priors)"
    return "ok", None
