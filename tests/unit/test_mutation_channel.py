"""mapcontainer.channel: exact figures and pinned seeded outcomes (tests that a mutation of the model fails).

The per-link random streams are part of the contract (the class docstring: reproducible for a seed, stable across
runs and Pythons, a link's outcomes independent of other links), so seeded outcomes are pinned here: a change to
how a link's stream is seeded or consumed must change these numbers on purpose.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from mapcontainer.channel import Channel, GilbertElliott, NetworkProfile

# Seed 7, link cv1->host, 10 messages of 10 bytes at 10 Hz: loss 0.3, latency 10 ms, jitter 5 ms, duplicate 0.2.
PINNED_PROFILE = {"loss": 0.3, "latency_ms": 10, "jitter_ms": 5, "duplicate": 0.2}
PINNED_SENT = [True, False, True, True, False, True, True, True, True, True, False, False]
PINNED_ARRIVALS = [  # (t_arrive, duplicate) in arrival order
    (0.01403804, False),
    (0.216368311, False),
    (0.31052819, False),
    (0.510265376, False),
    (0.619961107, False),
    (0.715299149, False),
    (0.717204716, True),
    (0.81328643, False),
    (0.912579193, True),
    (0.916845686, False),
]
# Seed 3, link a->b, Gilbert-Elliott 0.2 / 0.3 (loss 0 good, 1 bad): X lost, . delivered.
PINNED_BURST = "XX...............X....X..X...X.........X"


def test_a_links_seeded_outcomes_are_pinned() -> None:
    ch = Channel(NetworkProfile.custom(**PINNED_PROFILE), seed=7)
    assert [ch.send("cv1", "host", b"x" * 10, 0.1 * k) for k in range(12)] == PINNED_SENT
    got = [(d.t_arrive, d.duplicate) for d in ch.deliver(math.inf)]
    assert [dup for _, dup in got] == [dup for _, dup in PINNED_ARRIVALS]
    assert [t for t, _ in got] == pytest.approx([t for t, _ in PINNED_ARRIVALS], abs=1e-9)


def test_the_stream_is_the_links_own() -> None:
    """Another link of the same seed draws other numbers; the same link of another channel the same ones."""
    prof = NetworkProfile.custom(**PINNED_PROFILE)
    other = Channel(prof, seed=7)
    assert [other.send("cv2", "host", b"x" * 10, 0.1 * k) for k in range(12)] == [True] * 12
    reversed_link = Channel(prof, seed=7)
    assert [reversed_link.send("host", "cv1", b"x" * 10, 0.1 * k) for k in range(12)] != PINNED_SENT
    other_seed = Channel(prof, seed=8)
    assert [other_seed.send("cv1", "host", b"x" * 10, 0.1 * k) for k in range(12)] != PINNED_SENT


def test_a_gilbert_elliott_links_seeded_bursts_are_pinned() -> None:
    prof = NetworkProfile.custom(burst=GilbertElliott(p_good_to_bad=0.2, p_bad_to_good=0.3))
    ch = Channel(prof, seed=3)
    assert "".join("." if ch.send("a", "b", b"x", 0.1 * k) else "X" for k in range(40)) == PINNED_BURST
    assert ch.stats()["dropped_msgs"] == {"loss": PINNED_BURST.count("X"), "queue_full": 0}


def test_gilbert_elliott_stationary_figures_are_exact() -> None:
    ge = GilbertElliott(p_good_to_bad=0.1, p_bad_to_good=0.3, loss_good=0.05, loss_bad=0.8)
    assert ge.p_bad == pytest.approx(0.25, abs=1e-15)
    assert ge.mean_loss == pytest.approx(0.75 * 0.05 + 0.25 * 0.8, abs=1e-15)  # 0.2375
    default = GilbertElliott(p_good_to_bad=0.1, p_bad_to_good=0.4)  # loss 0 when good, 1 when bad
    assert (default.loss_good, default.loss_bad, default.mean_loss) == (0.0, 1.0, pytest.approx(0.2, abs=1e-15))
    assert NetworkProfile.custom(burst=ge).mean_loss == pytest.approx(0.2375, abs=1e-15)
    assert NetworkProfile.custom(loss=0.125).mean_loss == 0.125


def test_a_chain_that_never_moves_is_refused_but_one_that_moves_one_way_is_accepted() -> None:
    with pytest.raises(ValidationError, match="both 0"):
        GilbertElliott(p_good_to_bad=0.0, p_bad_to_good=0.0)
    assert GilbertElliott(p_good_to_bad=0.0, p_bad_to_good=0.5).p_bad == 0.0
    assert GilbertElliott(p_good_to_bad=0.5, p_bad_to_good=0.0).p_bad == 1.0


def test_profile_defaults_are_an_ideal_link() -> None:
    p = NetworkProfile.custom()
    assert p.name == "custom" and p.description == ""
    assert (p.latency_ms, p.jitter_ms, p.loss, p.burst, p.bandwidth_bps) == (0.0, 0.0, 0.0, None, None)
    assert (p.queue_bytes, p.duplicate, p.shared_medium) == (65536, 0.0, False)
    assert NetworkProfile.custom(latency_ms=20, jitter_ms=5).mean_latency_s == pytest.approx(0.025, abs=1e-15)


def test_profile_consistency_rules() -> None:
    ge = GilbertElliott(p_good_to_bad=0.1, p_bad_to_good=0.3)
    with pytest.raises(ValidationError, match="ignored when burst is set"):
        NetworkProfile.custom(loss=0.1, burst=ge)
    assert NetworkProfile.custom(loss=0.0, burst=ge).burst == ge
    with pytest.raises(ValidationError, match="shared_medium needs"):
        NetworkProfile.custom(shared_medium=True)
    assert NetworkProfile.custom(shared_medium=True, bandwidth_bps=1e6).shared_medium


def test_backlog_bytes() -> None:
    # 8000 bit/s = 1000 B/s: 500 B sent at 0 leave the queue at 0.5 s
    ch = Channel(NetworkProfile.custom(bandwidth_bps=8000.0), seed=0)
    ch.send("a", "b", b"x" * 500, 0.0)
    assert ch.backlog_bytes(0.0, "a", "b") == pytest.approx(500.0)
    assert ch.backlog_bytes(0.25, "a", "b") == pytest.approx(250.0)
    assert ch.backlog_bytes(0.5, "a", "b") == 0.0 and ch.backlog_bytes(2.0, "a", "b") == 0.0
    assert ch.backlog_bytes(0.0, "b", "a") == 0.0  # a link that never sent
    assert ch.backlog_bytes(0.0, "x", "y") == 0.0
    unlimited = Channel(NetworkProfile.custom(), seed=0)
    unlimited.send("a", "b", b"x" * 500, 0.0)
    assert unlimited.backlog_bytes(0.0, "a", "b") == 0.0
    shared = Channel(NetworkProfile.custom(bandwidth_bps=8000.0, shared_medium=True), seed=0)
    shared.send("a", "b", b"x" * 500, 0.0)
    shared.send("c", "d", b"x" * 300, 0.0)
    assert shared.backlog_bytes(0.0) == pytest.approx(800.0)  # one queue for the medium
    assert shared.backlog_bytes(0.3, "x", "y") == pytest.approx(500.0)


def test_serialization_latency_and_jitter_figures() -> None:
    """t_arrive = max(t, F) + 8 b / R + L + u * 2 J: exact with no jitter, inside [L, L + 2 J] with it."""
    ch = Channel(NetworkProfile.custom(bandwidth_bps=8000.0, latency_ms=20), seed=0)
    ch.send("a", "b", b"x" * 100, 1.0)  # 0.1 s on the air
    ch.send("a", "b", b"x" * 100, 1.0)  # queued behind it
    assert [d.t_arrive for d in ch.deliver(math.inf)] == pytest.approx([1.12, 1.22], abs=1e-12)
    jit = Channel(NetworkProfile.custom(latency_ms=20, jitter_ms=10), seed=4)
    for k in range(200):
        jit.send("a", "b", b"x", float(k))
    lat = np.array([d.latency for d in jit.deliver(math.inf)])
    assert lat.min() >= 0.020 and lat.max() <= 0.040 and lat.max() > 0.038 and lat.min() < 0.022


def test_the_queue_bound_counts_bytes_exactly() -> None:
    ch = Channel(NetworkProfile.custom(bandwidth_bps=8000.0, queue_bytes=1000), seed=0)
    assert ch.send("a", "b", b"x" * 600, 0.0)
    assert ch.send("a", "b", b"x" * 400, 0.0)  # 600 + 400 = 1000: fits exactly
    assert not ch.send("a", "b", b"x", 0.0)  # 1001: tail drop
    assert ch.send("a", "b", b"x", 0.6)  # 400 left, room again
    s = ch.stats()
    assert s["dropped_msgs"] == {"loss": 0, "queue_full": 1} and s["dropped_bytes"]["queue_full"] == 1
    assert (s["offered_msgs"], s["offered_bytes"], s["in_flight_msgs"], s["in_flight_bytes"]) == (4, 1002, 3, 1001)


def test_duplicates_are_counted_and_not_in_flight() -> None:
    ch = Channel(NetworkProfile.custom(duplicate=1.0, latency_ms=5), seed=0)
    ch.send("a", "b", b"xyz", 0.0)
    assert len(ch) == 2
    s = ch.stats()
    assert (s["in_flight_msgs"], s["in_flight_bytes"]) == (1, 3)
    out = ch.deliver(1.0)
    assert sorted(d.duplicate for d in out) == [False, True]
    s = ch.stats()
    assert (s["delivered_msgs"], s["delivered_bytes"], s["duplicated_msgs"], s["duplicated_bytes"]) == (2, 6, 1, 3)
    assert s["links"]["a->b"]["duplicated_msgs"] == 1 and out[0].link == "a->b"
    assert [d.t_sent for d in out] == [0.0, 0.0] and all(0.005 <= d.latency for d in out)


def test_stats_are_a_copy() -> None:
    ch = Channel(NetworkProfile.custom(loss=1.0), seed=0)
    ch.send("a", "b", b"xy", 0.0)
    s = ch.stats()
    s["links"]["a->b"]["dropped_msgs"]["loss"] = 99
    s["dropped_msgs"]["loss"] = 99
    again = ch.stats()
    assert again["dropped_msgs"] == {"loss": 1, "queue_full": 0}
    assert again["links"]["a->b"]["dropped_msgs"] == {"loss": 1, "queue_full": 0}
    assert again["links"]["a->b"]["dropped_bytes"] == {"loss": 2, "queue_full": 0}


def test_arguments_are_checked() -> None:
    ch = Channel(NetworkProfile.custom(), seed=0)
    with pytest.raises(TypeError, match="src and dst must be str, got str, int"):
        ch.send("a", 1, b"", 0.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="src and dst must be str, got float, str"):
        ch.send(1.0, "b", b"", 0.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="payload must be bytes, got str"):
        ch.send("a", "b", "text", 0.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        ch.send("a", "b", b"", math.inf)
    with pytest.raises(TypeError, match="profile must be a NetworkProfile, got dict"):
        Channel({"name": "x"}, 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="seed"):
        Channel(NetworkProfile.custom(), True)  # type: ignore[arg-type]
    assert Channel(NetworkProfile.custom(), np.int64(5)).seed == 5
    assert ch.send("a", "b", bytearray(b"ab"), 0.0) and ch.send("a", "b", memoryview(b"cd"), 0.0)
    assert [d.payload for d in ch.deliver(0.0)] == [b"ab", b"cd"]
