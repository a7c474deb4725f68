"""Reorder buffer: time order, duplicates, stale and future messages, capacity."""

from dataclasses import dataclass

import pytest

from mapcontainer.fusion.buffer import ReorderBuffer, time_key


@dataclass
class Msg:
    sender: str
    seq: int
    t_meas: float


def test_pops_in_measurement_time_order_up_to_t():
    buf = ReorderBuffer(window_s=1.0)
    arrivals = [Msg("b", 1, 0.2), Msg("a", 0, 0.1), Msg("a", 2, 0.3), Msg("b", 0, 0.1), Msg("a", 1, 0.2)]
    for m in arrivals:
        assert buf.push(m, t_recv=0.35) is None
    out = buf.pop_until(0.2)
    assert [(m.t_meas, m.sender) for m in out] == [(0.1, "a"), (0.1, "b"), (0.2, "a"), (0.2, "b")]
    assert len(buf) == 1
    assert [m.seq for m in buf.pop_until(1.0)] == [2]
    assert buf.accepted == 5 and not buf.rejected


def test_a_second_message_of_a_sender_for_one_instant_is_a_duplicate():
    buf = ReorderBuffer(window_s=1.0)
    assert buf.push(Msg("a", 7, 0.5), 0.5) is None
    assert buf.push(Msg("a", 7, 0.5), 0.6) == "duplicate"  # replayed
    assert buf.push(Msg("a", 8, 0.5004), 0.6) == "duplicate"  # same sender, same instant, new seq
    assert buf.push(Msg("b", 7, 0.5), 0.6) is None  # another sender
    buf.pop_until(0.5)
    assert buf.push(Msg("a", 7, 0.5), 0.7) == "duplicate"  # still remembered after fusing
    assert buf.rejected == {"duplicate": 3}


def test_a_restarted_sender_reusing_sequence_numbers_is_accepted():
    buf = ReorderBuffer(window_s=1.0)
    for k in range(100):  # 10 s of a sender, then it restarts and counts from 0 again
        assert buf.push(Msg("a", k, 0.1 * k), 0.1 * k) is None
        buf.pop_until(0.1 * k)
    for k in range(10):
        assert buf.push(Msg("a", k, 10.0 + 0.1 * k), 10.0 + 0.1 * k) is None
    assert buf.push(Msg("a", 3, 10.3), 10.95) == "duplicate"  # a replay of the new one still is one
    assert buf.accepted == 110 and buf.rejected == {"duplicate": 1}


def test_stale_relative_to_receive_time_and_to_what_was_fused():
    buf = ReorderBuffer(window_s=1.0)
    assert buf.push(Msg("a", 0, 1.0), t_recv=2.5) == "stale"  # arrived 1.5 s late
    assert buf.push(Msg("a", 1, 2.0), t_recv=2.5) is None
    buf.pop_until(5.0)  # the host fused up to 5.0: states before 4.0 are gone
    assert buf.push(Msg("b", 0, 3.5), t_recv=3.6) == "stale"
    assert buf.push(Msg("b", 1, 4.5), t_recv=4.6) is None  # late but within the window: still useful
    assert buf.rejected == {"stale": 2}


def test_future_and_overflow():
    buf = ReorderBuffer(window_s=1.0, future_tolerance_s=0.5, max_pending=2)
    assert buf.push(Msg("a", 0, 10.0), t_recv=1.0) == "future"
    assert buf.push(Msg("a", 1, 1.0), 1.0) is None
    assert buf.push(Msg("a", 2, 1.1), 1.1) is None
    assert buf.push(Msg("a", 3, 1.2), 1.2) == "overflow"
    assert buf.rejected == {"future": 1, "overflow": 1}


def test_duplicate_memory_stays_bounded():
    buf = ReorderBuffer(window_s=1.0)
    for k in range(5000):
        assert buf.push(Msg("a", k, k * 0.1), k * 0.1) is None
        buf.pop_until(k * 0.1)
    assert len(buf._seen) < 1100


def test_time_key_and_bad_window():
    assert time_key(0.1) == 100 and time_key(0.1004) == 100 and time_key(0.1006) == 101
    with pytest.raises(ValueError, match="window_s"):
        ReorderBuffer(window_s=0.0)
