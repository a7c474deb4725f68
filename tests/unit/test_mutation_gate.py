"""mapcontainer.fusion.gate.FrameGate: whom it waits for, its defaults and edges, which frame a message joins."""

from __future__ import annotations

import pytest

from mapcontainer.fusion.gate import FRAME_TOLERANCE_S, MAX_WAIT_S, FrameGate


def test_expected_senders_are_those_heard_within_active_s() -> None:
    """Without a list, a sender heard at 5.0 is still expected at 5.1: the frame waits for it."""
    g = FrameGate(None, max_wait_s=1.0, active_s=2.0)
    g.arrived("a", 5.0, now=5.0)
    g.arrived("b", 5.0, now=5.0)
    assert g.due(5.0) == 5.0 and g.complete == 1
    g.arrived("a", 5.1, now=5.1)
    assert g.due(5.1) is None and g.pending == 1  # b was heard 0.1 s ago: expected
    g.arrived("b", 5.1, now=5.15)
    assert g.due(5.15) == pytest.approx(5.1) and (g.complete, g.timed_out) == (2, 0)


def test_a_sender_heard_exactly_active_s_ago_is_still_expected() -> None:
    g = FrameGate(None, max_wait_s=10.0, active_s=2.0)
    g.arrived("b", 1.0, now=1.0)
    assert g.due(1.0) == 1.0
    g.arrived("a", 3.0, now=3.0)
    assert g.due(3.0) is None  # b heard 2.0 s ago: active_s is inclusive
    assert g.due(3.0 + 1e-6) == 3.0  # then b is no longer expected
    assert (g.complete, g.timed_out) == (2, 0)


def test_defaults() -> None:
    g = FrameGate(None)
    assert (g.max_wait_s, g.active_s, g.tolerance_s, g.reference) == (MAX_WAIT_S, 2.0, FRAME_TOLERANCE_S, None)
    assert (MAX_WAIT_S, FRAME_TOLERANCE_S) == (0.1, 0.02)
    assert g.expected is None and g.pending == 0 and (g.complete, g.timed_out) == (0, 0)
    assert g.due(0.0) is None and g.next_deadline() is None
    assert FrameGate(set()).expected is None  # an empty list means: expect the active ones
    assert FrameGate(["a", "b"]).expected == {"a", "b"}


def test_default_active_window_is_two_seconds() -> None:
    g = FrameGate(None, max_wait_s=10.0)
    g.arrived("b", 0.0, now=0.0)
    assert g.due(0.0) == 0.0
    g.arrived("a", 1.9, now=1.9)
    assert g.due(1.9) is None  # b heard 1.9 s ago
    g.arrived("a", 2.5, now=2.5)
    assert g.due(2.5) == 2.5  # b silent for 2.5 s: not waited for; frame 1.9 dropped
    assert (g.complete, g.pending) == (2, 0)


def test_default_tolerance_groups_within_20_ms() -> None:
    g = FrameGate({"a", "b", "c"})
    g.arrived("a", 1.0, now=1.0)
    g.arrived("b", 1.015, now=1.0)  # same frame
    g.arrived("c", 1.025, now=1.0)  # 25 ms from the frame's first: a new frame
    assert g.pending == 2


def test_zero_wait_and_zero_tolerance_are_accepted() -> None:
    g = FrameGate({"a", "b"}, max_wait_s=0.0, tolerance_s=0.0)
    g.arrived("a", 1.0, now=1.0)
    assert g.next_deadline() == 1.0
    assert g.due(1.0) == 1.0 and g.timed_out == 1  # no wait: released at once
    g.arrived("a", 2.0, now=2.0)
    g.arrived("b", 2.001, now=2.0)  # 1 ms apart: two frames with no tolerance
    assert g.pending == 2
    assert FrameGate(None, tolerance_s=0.499).tolerance_s == 0.499
    with pytest.raises(ValueError, match="tolerance_s"):
        FrameGate(None, tolerance_s=-0.001)
    with pytest.raises(ValueError, match=r"active_s must be > 0, got -1"):
        FrameGate(None, active_s=-1.0)
    with pytest.raises(ValueError, match=r"max_wait_s must be >= 0, got -0.1"):
        FrameGate(None, max_wait_s=-0.1)


def test_a_message_joins_the_nearest_of_two_candidate_frames() -> None:
    g = FrameGate({"a", "b"}, max_wait_s=1.0, tolerance_s=0.02)
    g.arrived("a", 1.00, now=1.00)
    g.arrived("a", 1.03, now=1.03)
    assert g.pending == 2
    g.arrived("b", 1.02, now=1.04)  # within 20 ms of both; 10 ms from 1.03
    assert g.pending == 2
    assert g.due(1.04) == pytest.approx(1.03) and (g.complete, g.timed_out) == (1, 0)
    assert g.pending == 0  # 1.00 dropped with it


def test_a_message_joins_a_frame_whose_first_is_after_it() -> None:
    g = FrameGate({"a", "b"}, max_wait_s=1.0)
    g.arrived("a", 1.01, now=1.0)
    g.arrived("b", 0.995, now=1.0)  # 15 ms earlier than the first: same frame
    assert g.pending == 1 and g.due(1.0) == pytest.approx(1.01)


def test_the_timeout_is_reached_at_first_plus_max_wait() -> None:
    g = FrameGate({"a", "b"}, max_wait_s=0.25)
    g.arrived("a", 1.0, now=1.5)
    assert g.next_deadline() == 1.75
    assert g.due(1.7499) is None
    assert g.due(1.75) == 1.0 and (g.complete, g.timed_out) == (0, 1)


def test_released_frames_and_those_within_the_tolerance_of_them_are_ignored() -> None:
    g = FrameGate({"a"}, max_wait_s=1.0)
    g.arrived("a", 1.0, now=1.0)
    assert g.due(1.0) == 1.0
    g.arrived("a", 1.015, now=1.1)  # within tolerance of the released frame
    g.arrived("a", 0.5, now=1.1)  # older than it
    assert g.pending == 0
    g.arrived("a", 1.05, now=1.1)
    assert g.pending == 1 and g.due(1.1) == 1.05


def test_the_reference_senders_time_is_kept_after_release() -> None:
    """Released at the reference's 1.012 (later than the first's 1.0): a message at 1.025 is within the
    tolerance of the reference's time, so it is late for that frame, not a new one."""
    g = FrameGate({"r", "a"}, reference="r", max_wait_s=1.0)
    g.arrived("a", 1.0, now=1.0)
    g.arrived("r", 1.012, now=1.0)
    assert g.due(1.0) == 1.012
    g.arrived("a", 1.025, now=1.1)
    assert g.pending == 0


def test_of_two_timed_out_frames_the_newest_is_released() -> None:
    g = FrameGate({"a", "b"}, max_wait_s=0.5)
    g.arrived("a", 1.0, now=1.0)
    g.arrived("a", 1.25, now=1.25)
    assert g.due(2.0) == 1.25 and (g.complete, g.timed_out, g.pending) == (0, 1, 0)


def test_a_message_exactly_the_tolerance_away_joins_the_frame() -> None:
    """Binary-exact times: 1.25 - 1.0 == tolerance_s, which counts as the same frame (and as late)."""
    g = FrameGate({"a", "b"}, max_wait_s=1.0, tolerance_s=0.25)
    g.arrived("a", 1.0, now=1.0)
    g.arrived("b", 1.25, now=1.0)
    assert g.pending == 1 and g.due(1.0) == 1.0 and g.complete == 1
    g.arrived("a", 1.25, now=1.5)  # exactly the tolerance after the released frame: late, ignored
    assert g.pending == 0


def test_a_short_active_window_is_accepted() -> None:
    g = FrameGate(None, active_s=0.5, max_wait_s=10.0)
    g.arrived("b", 0.0, now=0.0)
    assert g.due(0.0) == 0.0
    g.arrived("a", 0.75, now=0.75)
    assert g.due(0.75) == 0.75  # b silent for 0.75 s > 0.5 s
