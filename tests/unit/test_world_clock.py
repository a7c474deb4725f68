"""The world's adaptive clock (--time-scale auto): who it waits for, and its pauses."""

from __future__ import annotations

import threading
import time

import pytest

from services.launcher.manifest import FleetParams
from services.world.core import Pacer, Progress

VIDS = ["cv0", "cv1", "cv2"]


def test_a_frame_is_done_when_every_vehicle_sent_it_and_the_host_is_within_its_slack() -> None:
    p = Progress(VIDS, dt=0.1, host_slack_s=0.5)
    assert p.behind(0.0, host=True) == VIDS  # nothing yet; the host is not awaited in the first slack
    for v in VIDS:
        p.sent(v, 0.0)
    assert p.behind(0.0) == []
    p.sent("cv1", 0.097)  # a vehicle's clock a few ms off still counts for the frame at 0.1
    p.sent("cv0", 0.1)
    assert p.behind(0.1, host=False) == ["cv2"]
    p.sent("cv2", 0.1)
    assert p.behind(0.6) == ["cv0", "cv1", "cv2", "host"]  # no fused state yet past the slack
    for v in VIDS:
        p.sent(v, 0.6)
    p.fused(0.1)
    assert p.behind(0.6) == []  # 0.5 s behind: within the slack
    assert p.behind(0.7, vehicles={"cv0"}) == ["cv0", "host"]  # only the vehicles alive are awaited
    assert p.behind(0.7, vehicles=set(), host=False) == []
    p.sent("cv9", 5.0)  # not ours: ignored
    p.sent("cv0", 0.2)  # older than what it sent: ignored
    assert p.behind(0.6, host=False) == []
    with pytest.raises(ValueError):
        Progress(VIDS, dt=0.0)


def test_wait_for_returns_when_the_last_one_is_done_or_says_who_is_late() -> None:
    p = Progress(["cv0", "cv1"], dt=0.1)
    p.sent("cv0", 1.0)
    threading.Timer(0.1, p.sent, ("cv1", 1.0)).start()
    t0 = time.monotonic()
    assert p.wait_for(1.0, 5.0, lambda: None, lambda: False) == []
    assert time.monotonic() - t0 < 4.0  # woken by the message, not by the timeout
    assert p.wait_for(1.1, 0.05, lambda: None, lambda: False) == ["cv0", "cv1"]


def test_the_clock_pauses_rather_than_drops_a_frame() -> None:
    pacer = Pacer(epoch_wall_ns=10**12, dt=0.1, time_scale=1.0)
    due = pacer.due_wall_ns(5)
    assert pacer.pause(5, due - 1000) == 0 and pacer.due_wall_ns(5) == due  # not late: no pause
    assert pacer.pause(5, due + 30_000_000) == 30_000_000
    assert pacer.due_wall_ns(5) == due + 30_000_000 and pacer.due_wall_ns(6) == due + 130_000_000
    assert pacer.first_k_at(due + 30_000_000) == 5  # frame 5 is now the one due


def test_fleet_time_scale_is_auto_by_default_and_the_other_services_get_slope_1() -> None:
    p = FleetParams()
    assert p.time_scale == "auto" and p.clock_scale == 1.0
    assert FleetParams(time_scale=0.25).clock_scale == 0.25
    for bad in (0.0, 1000.0, "fast"):
        with pytest.raises(ValueError):
            FleetParams(time_scale=bad)


def test_a_service_clock_does_not_run_ahead_of_a_paused_world() -> None:
    """While the world's clock pauses, a message received is stamped no later than the next frame's time:
    the host refused messages stamped seconds ahead as stale."""
    from services.runtime import SimClock

    epoch = 10**18
    c = SimClock()
    assert c.update({"epoch_wall_ns": epoch, "time_scale": 1.0, "t_next": 0.5})  # frame 4 out, 0.5 next
    assert c.now(epoch + 300_000_000) == pytest.approx(0.3)
    assert c.now(epoch + 3_000_000_000) == 0.5  # 3 s of wall time into a pause: still before frame 5
    c.update({"epoch_wall_ns": epoch + 2_500_000_000, "time_scale": 1.0, "t_next": 0.6})  # frame 5, 2.5 s late
    assert c.now(epoch + 3_000_000_000) == pytest.approx(0.5)
    c.update({"epoch_wall_ns": epoch, "time_scale": 1.0, "t_next": 0.5})  # a late relay of an older frame
    assert c.epoch_wall_ns == epoch + 2_500_000_000 and c.t_next == 0.6  # the newest clock is kept
    assert c.fields() == {"epoch_wall_ns": epoch + 2_500_000_000, "time_scale": 1.0, "t_next": 0.6}
