"""Per-sender admission: a token bucket per sender, a bounded table of senders."""

from __future__ import annotations

import pytest

from mapcontainer.admission import Admission


def test_a_sender_gets_its_burst_then_its_rate() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    assert [a.admit("cv1", 0.0) for _ in range(22)] == [None] * 20 + ["flood", "flood"]
    assert a.admit("cv1", 0.05) is None  # 0.05 s at 20 Hz: one token back
    assert a.admit("cv1", 0.05) == "flood"
    assert a.refused() == {"cv1": 3}


def test_nominal_traffic_is_never_refused() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    assert all(a.admit("cv0", 0.1 * k) is None for k in range(1000))  # 10 Hz for 100 s


def test_a_flood_of_one_sender_costs_only_that_sender() -> None:
    a = Admission(rate_hz=20.0, burst=20.0)
    admitted = {"cv0": 0, "cv9": 0}
    for k in range(10_000):  # cv9: 1,000 messages a second for 10 s; cv0: its 10 Hz
        t = k * 0.001
        admitted["cv9"] += a.admit("cv9", t) is None
        if k % 100 == 0:
            admitted["cv0"] += a.admit("cv0", t) is None
    assert admitted["cv0"] == 100
    assert admitted["cv9"] <= 20 + 20 * 10 + 1  # its burst and its rate, no more


def test_the_table_of_senders_is_bounded() -> None:
    a = Admission(rate_hz=10.0, max_senders=3)
    assert [a.admit(f"s{i}", 0.0) for i in range(5)] == [None, None, None, "too_many_senders", "too_many_senders"]
    assert len(a) == 3 and a.admit("s0", 1.0) is None  # the known ones go on


def test_a_clock_that_goes_back_gives_no_tokens() -> None:
    a = Admission(rate_hz=10.0, burst=1.0)
    assert a.admit("x", 100.0) is None
    assert a.admit("x", 0.0) == "flood"


@pytest.mark.parametrize(
    "kwargs", [{"rate_hz": 0.0}, {"rate_hz": 10.0, "burst": 0.5}, {"rate_hz": 1.0, "max_senders": 0}]
)
def test_bad_parameters_are_refused(kwargs) -> None:
    with pytest.raises(ValueError):
        Admission(**kwargs)
