"""FrameBacklog (mapcontainer.vehicle): the newest frame waiting is matched, the ones before it are stale."""

import threading

import pytest

from mapcontainer.vehicle import FrameBacklog


def test_take_returns_every_frame_waiting_in_order_the_newest_apart():
    b = FrameBacklog()
    assert b.take(0.0) is None  # nothing waiting
    b.put(1)
    assert b.take(0.0) == ([], 1)  # a vehicle that keeps up: no stale frame
    for k in (2, 3, 4):
        b.put(k)
    assert len(b) == 3 and b.take(0.0) == ([2, 3], 4) and len(b) == 0


def test_a_flood_drops_the_oldest_whole_and_counts_them():
    b = FrameBacklog(max_waiting=3)
    for k in range(7):
        b.put(k)
    assert b.pop_dropped() == 4 and b.pop_dropped() == 0
    assert b.take(0.0) == ([4, 5], 6)
    with pytest.raises(ValueError, match="max_waiting"):
        FrameBacklog(max_waiting=0)


def test_take_waits_for_a_frame_from_another_thread():
    b = FrameBacklog()
    threading.Timer(0.05, b.put, args=("frame",)).start()
    assert b.take(5.0) == ([], "frame")
