"""mapcontainer.admission.Admission: its defaults, the edges of its validation, the exact token arithmetic."""

from __future__ import annotations

import pytest

from mapcontainer.admission import Admission


def test_default_burst_is_ten_messages() -> None:
    a = Admission(rate_hz=1.0)
    assert a.burst == 10.0
    assert [a.admit("cv0", 0.0) for _ in range(11)] == [None] * 10 + ["flood"]


def test_default_table_holds_256_senders() -> None:
    a = Admission(rate_hz=1.0)
    assert a.max_senders == 256
    assert all(a.admit(f"s{i}", 0.0) is None for i in range(256))
    assert a.admit("s256", 0.0) == "too_many_senders" and len(a) == 256


def test_validation_edges() -> None:
    assert Admission(rate_hz=1e-9, burst=1.0, max_senders=1).burst == 1.0  # the smallest accepted
    for kwargs in ({"rate_hz": -1.0}, {"rate_hz": 1.0, "burst": 0.999}, {"rate_hz": 1.0, "max_senders": 0}):
        with pytest.raises(ValueError, match="rate_hz must be > 0, burst >= 1 and max_senders >= 1"):
            Admission(**kwargs)
    with pytest.raises(ValueError, match=r"got 1.0, 0.5, 256"):
        Admission(rate_hz=1.0, burst=0.5)
    with pytest.raises(ValueError):
        Admission(rate_hz=float("nan"))


def test_one_sender_table() -> None:
    a = Admission(rate_hz=1.0, burst=1.0, max_senders=1)
    assert a.admit("a", 0.0) is None
    assert a.admit("b", 0.0) == "too_many_senders"
    assert a.admit("a", 0.5) == "flood"  # half a token
    assert a.admit("a", 1.0) is None  # exactly one token back
    assert a.refused() == {"a": 1}  # too_many_senders is not counted against a sender


def test_tokens_refill_at_rate_and_cap_at_burst() -> None:
    a = Admission(rate_hz=2.0, burst=3.0)
    assert [a.admit("x", 0.0) for _ in range(4)] == [None, None, None, "flood"]
    assert a.admit("x", 0.25) == "flood"  # 0.5 token
    assert a.admit("x", 0.5) is None  # 1 token at 0.5 s
    assert [a.admit("x", 100.0) for _ in range(4)] == [None, None, None, "flood"]  # capped at the burst
    assert a.refused() == {"x": 3}


def test_refused_lists_only_senders_that_had_a_refusal() -> None:
    a = Admission(rate_hz=1.0, burst=1.0)
    a.admit("quiet", 0.0)
    a.admit("loud", 0.0)
    a.admit("loud", 0.0)
    assert a.refused() == {"loud": 1} and len(a) == 2
