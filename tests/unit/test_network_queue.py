"""Every point of the network sweep has a queue that holds the largest message either mode sends,
so a drop at the lowest capacity is congestion, not a message too large for the queue."""

from __future__ import annotations

import itertools

import pytest

from mapcontainer.channel import list_profiles, load_profile
from mapcontainer.experiments.bytes import seed_bytes
from mapcontainer.experiments.network import (
    BANDWIDTHS_BPS,
    LATENCIES_MS,
    LOSSES,
    MIN_QUEUE_BYTES,
    QUEUE_S,
    QUICK_GRID,
    sweep_profile,
)

MEASURED_MAX_SIGNED = 2031  # bytes: the largest message over paper-urban seeds 90000-90004, 10 s (module doc)


@pytest.fixture(scope="module")
def largest_message() -> int:
    """The largest signed message of either mode in short runs of both paper scenarios."""
    sizes = [MEASURED_MAX_SIGNED]
    for scenario in ("paper-urban", "paper-suburban"):
        res = seed_bytes(scenario, 90000, 1.0, signing=True)
        sizes += [res[mode]["max_message_bytes_signed"] for mode in ("distributed", "centralized")]
    return max(sizes)


def _points():
    full = itertools.product(LATENCIES_MS, LOSSES, BANDWIDTHS_BPS)
    quick = itertools.product(QUICK_GRID["latencies_ms"], QUICK_GRID["losses"], QUICK_GRID["bandwidths_bps"])
    return sorted(set(full) | set(quick))


def test_every_sweep_point_holds_the_largest_message(largest_message):
    assert MIN_QUEUE_BYTES >= 1.25 * largest_message  # a margin for masks of busier scenes
    for lat, loss, bw in _points():
        profile = sweep_profile(lat, loss, bw)
        assert profile.queue_bytes >= largest_message, (profile.name, profile.queue_bytes)


def test_the_floor_binds_only_where_half_a_second_is_too_small():
    for bw in BANDWIDTHS_BPS:
        q = sweep_profile(0.0, 0.0, bw).queue_bytes
        assert q == max(MIN_QUEUE_BYTES, int(bw * QUEUE_S / 8 + 0.999))
    assert sweep_profile(0.0, 0.0, min(BANDWIDTHS_BPS)).queue_bytes == MIN_QUEUE_BYTES


def test_the_presets_with_a_capacity_hold_it_too(largest_message):
    for name in list_profiles():
        p = load_profile(name)
        if p.bandwidth_bps is not None:
            assert p.queue_bytes >= largest_message, (name, p.queue_bytes)
