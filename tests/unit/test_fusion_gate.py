"""mapcontainer.fusion.gate.FrameGate: the solve policy of the live host and the pipeline (time is an argument)."""

from __future__ import annotations

import pytest

from mapcontainer.fusion.gate import MAX_WAIT_S, FrameGate


def test_waits_for_every_known_sender_and_releases_once() -> None:
    g = FrameGate({"cv0", "cv1"}, max_wait_s=0.1)
    g.arrived("cv0", 0.1, now=0.1)
    assert g.due(0.15) is None and g.pending == 1  # cv1 missing
    g.arrived("cv1", 0.1, now=0.17)
    assert g.due(0.17) == pytest.approx(0.1) and (g.complete, g.timed_out) == (1, 0)
    assert g.due(0.18) is None
    g.arrived("cv1", 0.1, now=0.2)  # a late duplicate of a released frame is ignored
    assert g.pending == 0 and g.next_deadline() is None


def test_times_out_max_wait_after_the_first_message() -> None:
    g = FrameGate({"cv0", "cv1"})
    assert g.max_wait_s == MAX_WAIT_S
    t3, t4 = 3 * 0.1, 4 * 0.1  # frame times as the world makes them: t4 - t3 < 0.1 in floats
    g.arrived("cv0", t3, now=t3)
    assert g.next_deadline() == pytest.approx(0.4)
    assert g.due(t3 + MAX_WAIT_S * 0.99) is None
    assert g.due(t4) == pytest.approx(0.3) and g.timed_out == 1  # due at the next frame time


def test_a_complete_newer_frame_drops_the_older_incomplete_one() -> None:
    g = FrameGate({"cv0", "cv1"}, max_wait_s=0.5)
    g.arrived("cv0", 0.1, now=0.1)
    g.arrived("cv0", 0.2, now=0.2)
    g.arrived("cv1", 0.2, now=0.22)
    assert g.due(0.22) == pytest.approx(0.2)  # newest ready; 0.1 is dropped, not released later
    g.arrived("cv1", 0.1, now=0.25)
    assert g.due(0.7) is None and (g.complete, g.timed_out) == (1, 0)


def test_times_out_and_skips_to_the_newest() -> None:
    g = FrameGate({"cv0", "cv1"}, max_wait_s=0.1)
    g.arrived("cv0", 0.1, now=0.0)
    g.arrived("cv0", 0.2, now=0.1)
    assert g.due(0.15) == pytest.approx(0.1)  # frame 0.1 timed out; 0.2 still waits
    assert g.due(0.21) == pytest.approx(0.2) and g.timed_out == 2


def test_without_a_sender_list_expects_the_active_ones() -> None:
    g = FrameGate(None, max_wait_s=1.0, active_s=2.0)
    g.arrived("a", 0.0, now=0.0)
    assert g.due(0.0) == 0.0  # only a was heard of
    g.arrived("b", 0.1, now=0.1)
    g.arrived("a", 0.2, now=0.2)
    assert g.due(0.2) is None  # a and b are both active now: frames 0.1 (b) and 0.2 (a) wait
    g.arrived("b", 0.2, now=0.25)
    assert g.due(0.25) == pytest.approx(0.2)
    g.arrived("a", 3.0, now=3.0)  # b silent for more than active_s: no longer expected
    assert g.due(3.0) == pytest.approx(3.0)


def test_refuses_bad_settings() -> None:
    with pytest.raises(ValueError, match="max_wait_s"):
        FrameGate({"a"}, max_wait_s=-0.1)
    with pytest.raises(ValueError, match="active_s"):
        FrameGate(None, active_s=0.0)


def test_groups_messages_stamped_by_clocks_a_few_ms_apart() -> None:
    g = FrameGate({"cv0", "cv1", "cv2"}, reference="cv0")
    g.arrived("cv1", 1.004, now=1.0)
    g.arrived("cv2", 0.997, now=1.0)
    assert g.due(1.0) is None and g.pending == 1  # one frame, cv0 missing
    g.arrived("cv0", 1.002, now=1.01)
    assert g.due(1.01) == pytest.approx(1.002) and g.complete == 1  # solved at the reference's time
    g.arrived("cv1", 1.0, now=1.02)  # late for the released frame: ignored
    g.arrived("cv1", 1.104, now=1.1)  # the next frame
    assert g.pending == 1 and g.due(1.1 + MAX_WAIT_S) == pytest.approx(1.104)  # no reference: the first's time


def test_frames_further_apart_than_the_tolerance_stay_apart() -> None:
    g = FrameGate({"cv0", "cv1"}, tolerance_s=0.02)
    g.arrived("cv0", 1.0, now=1.0)
    g.arrived("cv1", 1.03, now=1.0)
    assert g.pending == 2
    with pytest.raises(ValueError, match="tolerance_s"):
        FrameGate(None, tolerance_s=0.5)
