"""V2X channel model: loss, bursts, bandwidth queue, jitter, duplication, shared medium, counters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapcontainer.channel import Channel, Delivery, NetworkProfile, list_profiles, load_profile
from mapcontainer.config import ConfigError

PAYLOAD = b"x" * 100


def _drain(ch: Channel) -> list[Delivery]:
    return ch.deliver(math.inf)


def _loss_pattern(profile: NetworkProfile, n: int, seed: int = 1) -> np.ndarray:
    """True where message i of n (one link, 10 Hz) was dropped."""
    ch = Channel(profile, seed)
    return np.array([not ch.send("a", "b", PAYLOAD, 0.1 * i) for i in range(n)])


def _mean_run(lost: np.ndarray) -> float:
    """Mean length of runs of consecutive losses."""
    padded = np.concatenate([[0], lost.astype(int), [0]])
    starts = np.flatnonzero(np.diff(padded) == 1)
    ends = np.flatnonzero(np.diff(padded) == -1)
    return float(np.mean(ends - starts))


def _check_balance(c: dict) -> None:
    for unit in ("msgs", "bytes"):
        dropped = sum(c[f"dropped_{unit}"].values())
        delivered_once = c[f"delivered_{unit}"] - c[f"duplicated_{unit}"]
        assert c[f"offered_{unit}"] == dropped + delivered_once + c[f"in_flight_{unit}"]


def test_ideal_delivers_everything_at_send_time_in_order():
    ch = Channel(load_profile("ideal"), seed=0)
    times = [0.0, 0.0, 0.05, 0.05, 0.05, 0.1, 0.3]
    for i, t in enumerate(times):
        assert ch.send("v1", "host", bytes([i]), t)
    assert ch.next_arrival() == 0.0
    got: list[Delivery] = []
    for t in sorted(set(times)):
        assert ch.deliver(t - 1e-9) == []
        got += ch.deliver(t)
    assert [d.payload for d in got] == [bytes([i]) for i in range(len(times))]
    assert all(d.t_arrive == d.t_sent and d.latency == 0 and not d.duplicate for d in got)
    assert ch.next_arrival() is None and len(ch) == 0
    s = ch.stats()
    assert s["delivered_msgs"] == s["offered_msgs"] == len(times)
    assert s["links"]["v1->host"]["delivered_bytes"] == len(times)


def test_bernoulli_loss_fraction():
    p, n = 0.2, 20_000
    lost = _loss_pattern(NetworkProfile.custom(loss=p), n)
    assert lost.mean() == pytest.approx(p, abs=0.015)  # 5 sigma = 0.014
    # independent losses: runs are geometric with mean 1 / (1 - p)
    assert _mean_run(lost) == pytest.approx(1 / (1 - p), rel=0.1)


def test_gilbert_elliott_stationary_loss_and_bursts():
    profile = load_profile("lossy")
    p_mean = profile.burst.mean_loss
    assert p_mean == pytest.approx(0.30, abs=0.01)
    n = 50_000
    lost = _loss_pattern(profile, n)
    assert lost.mean() == pytest.approx(p_mean, abs=0.03)
    bernoulli = _loss_pattern(NetworkProfile.custom(loss=p_mean), n)
    assert bernoulli.mean() == pytest.approx(p_mean, abs=0.015)
    # same mean loss, much longer outages: ~1/(1-0.3) = 1.4 for Bernoulli, several for the bursts
    assert _mean_run(bernoulli) < 1.6
    assert _mean_run(lost) > 2.5 * _mean_run(bernoulli)


def test_bandwidth_serialization_spacing():
    n, size, rate, latency_ms = 10, 1000, 1e6, 5.0
    ch = Channel(NetworkProfile.custom(bandwidth_bps=rate, latency_ms=latency_ms, queue_bytes=10**6), 0)
    for i in range(n):
        assert ch.send("a", "b", bytes([i]) * size, 1.0)
    got = _drain(ch)
    t_tx = size * 8 / rate
    arrivals = np.array([d.t_arrive for d in got])
    assert [d.payload[0] for d in got] == list(range(n))  # FIFO
    np.testing.assert_allclose(np.diff(arrivals), t_tx, rtol=1e-9)
    assert arrivals[0] == pytest.approx(1.0 + t_tx + latency_ms / 1000, rel=1e-12)
    assert arrivals[-1] == pytest.approx(1.0 + n * t_tx + latency_ms / 1000, rel=1e-12)


def test_queue_overflow_tail_drops():
    size, rate = 1000, 1e6  # 8 ms per message
    ch = Channel(NetworkProfile.custom(bandwidth_bps=rate, queue_bytes=5 * size), 0)
    accepted = [ch.send("a", "b", bytes([i]) * size, 0.0) for i in range(10)]
    assert accepted == [True] * 5 + [False] * 5  # tail drop: the newest are lost
    assert ch.backlog_bytes(0.0, "a", "b") == pytest.approx(5 * size)
    # after one serialization time one message has left the queue: room for exactly one more
    assert ch.backlog_bytes(0.008, "a", "b") == pytest.approx(4 * size)
    assert ch.send("a", "b", b"\xff" * size, 0.008)
    assert not ch.send("a", "b", b"\xfe" * size, 0.008)
    s = ch.stats()
    assert s["dropped_msgs"] == {"loss": 0, "queue_full": 6}
    assert s["dropped_bytes"]["queue_full"] == 6 * size
    got = _drain(ch)
    assert [d.payload[0] for d in got] == [0, 1, 2, 3, 4, 0xFF]
    assert got[-1].t_arrive == pytest.approx(6 * 0.008)
    # a message larger than the whole queue can never be sent
    assert not ch.send("a", "b", b"z" * (5 * size + 1), 10.0)


def test_jitter_reorders_and_latency_mean():
    latency_ms, jitter_ms, n = 20.0, 5.0, 5000
    ch = Channel(NetworkProfile.custom(latency_ms=latency_ms, jitter_ms=jitter_ms), seed=3)
    for i in range(n):
        ch.send("a", "b", i.to_bytes(4, "little"), 0.001 * i)  # 1 ms apart: jitter spans 10 ms
    got = _drain(ch)
    assert len(got) == n
    arrivals = np.array([d.t_arrive for d in got])
    assert np.all(np.diff(arrivals) >= 0)  # delivered in arrival order
    sent = np.array([d.t_sent for d in got])
    assert np.count_nonzero(np.diff(sent) < 0) > n / 10  # ... which is not the send order
    lat_ms = 1000 * np.array([d.latency for d in got])
    assert lat_ms.min() >= latency_ms and lat_ms.max() <= latency_ms + 2 * jitter_ms
    assert lat_ms.mean() == pytest.approx(latency_ms + jitter_ms, abs=0.15)  # sigma of mean ~0.04 ms
    assert lat_ms.std() == pytest.approx(jitter_ms / math.sqrt(3), rel=0.05)


def test_duplication():
    p_dup, n = 0.3, 10_000
    ch = Channel(NetworkProfile.custom(duplicate=p_dup, latency_ms=10, jitter_ms=2), seed=5)
    for i in range(n):
        ch.send("a", "b", i.to_bytes(4, "little"), 0.01 * i)
    got = _drain(ch)
    dups = [d for d in got if d.duplicate]
    assert len(got) - len(dups) == n  # every original exactly once
    assert len(dups) / n == pytest.approx(p_dup, abs=0.025)
    originals = {d.payload for d in got if not d.duplicate}
    assert {d.payload for d in dups} <= originals and len({d.payload for d in dups}) == len(dups)
    s = ch.stats()
    assert s["duplicated_msgs"] == len(dups) and s["delivered_msgs"] == n + len(dups)
    _check_balance(s)


@pytest.mark.parametrize("shared", [False, True])
def test_shared_medium_halves_capacity(shared):
    n, size, rate = 10, 1000, 1e6
    prof = NetworkProfile.custom(bandwidth_bps=rate, shared_medium=shared, queue_bytes=10**6)
    ch = Channel(prof, seed=0)
    for i in range(n):
        for src in ("v1", "v2"):
            assert ch.send(src, "host", bytes([i]) * size, 0.0)
    got = _drain(ch)
    last = {src: max(d.t_arrive for d in got if d.src == src) for src in ("v1", "v2")}
    t_all = n * size * 8 / rate
    expected = 2 * t_all if shared else t_all
    assert max(last.values()) == pytest.approx(expected)
    if shared:  # interleaved on the one medium, both links finish near the end
        assert min(last.values()) == pytest.approx(expected - size * 8 / rate)
        assert ch.backlog_bytes(0.0) == pytest.approx(2 * n * size)
        assert ch.backlog_bytes(expected) == pytest.approx(0.0, abs=1e-6)


def test_shared_medium_queue_is_shared():
    ch = Channel(NetworkProfile.custom(bandwidth_bps=1e6, shared_medium=True, queue_bytes=3000), 0)
    assert ch.send("v1", "host", b"a" * 1000, 0.0)
    assert ch.send("v2", "host", b"b" * 1000, 0.0)
    assert ch.send("v3", "host", b"c" * 1000, 0.0)
    assert not ch.send("v4", "host", b"d" * 1000, 0.0)
    assert ch.backlog_bytes(0.0) == pytest.approx(3000)
    assert ch.stats()["links"]["v4->host"]["dropped_msgs"]["queue_full"] == 1


def _run(profile: NetworkProfile, seed: int) -> list[Delivery]:
    ch = Channel(profile, seed)
    out: list[Delivery] = []
    for k in range(2000):
        t = 0.01 * k
        for v in ("v1", "v2", "v3"):
            ch.send(v, "host", f"{v}:{k}".encode() * 20, t)
        out += ch.deliver(t)
    return out + _drain(ch)


def test_determinism():
    prof = load_profile("degraded")
    a, b = _run(prof, 42), _run(prof, 42)
    assert a == b and len(a) > 1000
    assert _run(prof, 43) != a


def test_links_have_independent_streams():
    """A link's losses and delays do not depend on traffic on other links (no shared medium)."""
    prof = NetworkProfile.custom(loss=0.3, latency_ms=10, jitter_ms=5)
    alone, busy = Channel(prof, 7), Channel(prof, 7)
    for k in range(500):
        alone.send("v1", "host", PAYLOAD, 0.1 * k)
        busy.send("v2", "host", PAYLOAD, 0.1 * k)
        busy.send("v1", "host", PAYLOAD, 0.1 * k)
    assert _drain(alone) == [d for d in _drain(busy) if d.src == "v1"]


def test_loss_sweeps_share_random_numbers():
    """Same seed, higher loss: the lost messages are a superset (common random numbers)."""
    low = _loss_pattern(NetworkProfile.custom(loss=0.1), 2000, seed=9)
    high = _loss_pattern(NetworkProfile.custom(loss=0.2), 2000, seed=9)
    assert np.all(high[low]) and high.sum() > low.sum()


def test_stats_balance():
    prof = NetworkProfile.custom(
        latency_ms=50, jitter_ms=30, loss=0.1, duplicate=0.2, bandwidth_bps=2e5, queue_bytes=4000
    )
    ch = Channel(prof, seed=11)
    rng = np.random.default_rng(0)
    for k in range(3000):
        t = 0.005 * k
        ch.send(f"v{k % 3}", "host", b"p" * int(rng.integers(50, 800)), t)
        if k % 7 == 0:
            ch.deliver(t)
    s = ch.stats()
    assert s["in_flight_msgs"] > 0 and all(s["dropped_msgs"].values()) and s["duplicated_msgs"] > 0
    _check_balance(s)
    for c in s["links"].values():
        _check_balance(c)
    assert sum(c["offered_msgs"] for c in s["links"].values()) == s["offered_msgs"] == 3000
    _drain(ch)
    s = ch.stats()
    assert s["in_flight_msgs"] == 0
    _check_balance(s)
    ch.reset_stats()
    s = ch.stats()
    assert s["offered_msgs"] == s["delivered_msgs"] == 0 and s["dropped_msgs"]["loss"] == 0


def test_next_arrival():
    ch = Channel(NetworkProfile.custom(latency_ms=100), 0)
    assert ch.next_arrival() is None
    ch.send("a", "b", PAYLOAD, 1.0)
    ch.send("a", "b", PAYLOAD, 0.5)
    assert ch.next_arrival() == pytest.approx(0.6)
    assert len(ch.deliver(0.6)) == 1 and ch.next_arrival() == pytest.approx(1.1)


def test_bad_arguments_raise():
    ch = Channel(load_profile("ideal"), 0)
    with pytest.raises(TypeError, match="payload"):
        ch.send("a", "b", "text", 0.0)
    with pytest.raises(ValueError, match="finite"):
        ch.send("a", "b", b"", float("nan"))
    with pytest.raises(ValueError, match="seed"):
        Channel(load_profile("ideal"), -1)


def test_expected_presets_exist():
    assert {"ideal", "dsrc", "congested", "lossy", "degraded"} <= set(list_profiles())


@pytest.mark.parametrize("name", list_profiles())
def test_every_profile_loads(name):
    prof = load_profile(name)
    assert prof.name == name and prof.description
    ch = Channel(prof, seed=0)
    for k in range(100):
        ch.send("v1", "host", PAYLOAD, 0.1 * k)
    _check_balance(ch.stats())


def test_dsrc_profile_values():
    p = load_profile("dsrc")
    assert p.shared_medium and p.bandwidth_bps == 6e6
    assert 0.01 <= p.mean_loss <= 0.02 and 0.015 <= p.mean_latency_s <= 0.025


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("name: bad\nloss: 1.5\n", "loss"),
        ("name: bad\nlatency_ms: -3\n", "latency_ms"),
        ("name: bad\nlatncy_ms: 3\n", "latncy_ms"),
        ("name: bad\nburst: {p_good_to_bad: 0.1}\n", "burst.p_bad_to_good"),
        ("name: bad\nloss: 0.1\nburst: {p_good_to_bad: 0.1, p_bad_to_good: 0.2}\n", "loss"),
        ("name: bad\nshared_medium: true\n", "bandwidth_bps"),
        ("name: bad\nqueue_bytes: 0\n", "queue_bytes"),
        ("name: bad\nlatency_ms: .inf\n", "latency_ms"),  # the link would never deliver
        ("name: bad\njitter_ms: .nan\n", "jitter_ms"),
    ],
)
def test_bad_profile_file_names_the_field(tmp_path, text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")) as err:
        load_profile(path)
    assert str(path) in str(err.value)


def test_unknown_or_unreadable_profile(tmp_path):
    with pytest.raises(ConfigError, match="unknown network profile 'nope'.*dsrc"):
        load_profile("nope")
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_profile(path)


def test_profile_name_defaults_to_file_stem(tmp_path):
    path = tmp_path / "mylink.yaml"
    path.write_text("latency_ms: 30  # ms\n")
    assert load_profile(path).name == "mylink"


def test_custom_validates():
    assert NetworkProfile.custom(latency_ms=5).latency_ms == 5
    with pytest.raises(ValueError, match="duplicate"):
        NetworkProfile.custom(duplicate=2)
