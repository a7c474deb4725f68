"""The geometric radio model (mapcontainer.radio): closed forms, geometry, MAC, the channel, validation."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.channel import Channel, load_profile
from mapcontainer.config import ConfigError
from mapcontainer.radio import RadioChannel, RadioProfile, make_channel
from mapcontainer.radio.hashing import directed_keys, link_keys, node_key, normals, uniforms
from mapcontainer.radio.mac import Csma, MacParams, Sps, airtime_s
from mapcontainer.radio.obstacles import Buildings, vehicle_blocked
from mapcontainer.radio.phy import PhyParams, noise_dbm, per
from mapcontainer.radio.propagation import (
    LOS,
    NLOS,
    PropagationParams,
    Shadowing,
    mean_path_loss_db,
    nlosv_loss_db,
)
from mapcontainer.radio.validation import (
    PRR_TOLERANCE,
    SOURCES,
    analytic_cbr,
    published,
    reference_path_loss_db,
    reference_prr,
    simulated_cbr,
    simulated_prr,
)

PAYLOAD = b"p" * 400


def _plain(name: str) -> RadioProfile:
    """A preset in its source's scenario (no vehicle blockage, no background traffic)."""
    from mapcontainer.experiments.radio import source_scenario

    return source_scenario(load_profile(name))


# -- hashing ---------------------------------------------------------------------------------------


def test_counter_based_draws_are_stable_uniform_and_keyed():
    u = uniforms(3, np.arange(20000), 0)
    assert abs(u.mean() - 0.5) < 0.01 and abs(u.var() - 1 / 12) < 0.003 and 0 < u.min() and u.max() < 1
    assert np.array_equal(uniforms(3, 7, np.arange(5)), uniforms(3, 7, np.arange(5)))
    assert not np.array_equal(uniforms(3, 7, np.arange(5)), uniforms(4, 7, np.arange(5)))
    assert not np.array_equal(uniforms(3, 7, 0, np.arange(4))[:2], uniforms(3, 7, 0, np.arange(4))[2:])
    z = normals(1, 5, np.arange(20000))
    assert abs(z.mean()) < 0.03 and abs(z.std() - 1) < 0.02
    a, b = np.uint64(node_key("cv0")), np.uint64(node_key("cv1"))
    assert link_keys(a, b) == link_keys(b, a) and directed_keys(a, b) != directed_keys(b, a)
    assert node_key("cv0") == node_key("cv0") != node_key("cv1")


# -- propagation -----------------------------------------------------------------------------------


def test_winner_b1_los_closed_form_breakpoint_and_free_space_floor():
    p = PropagationParams(frequency_hz=5.89e9, environment_height_m=0.5)
    d_bp = 4 * 1.0 * 1.0 * 5.89e9 / 299_792_458.0  # 78.6 m
    near = 22.7 * np.log10(50) + 27 + 20 * np.log10(5.89)
    far = 40 * np.log10(200) + 7.56 + 2.7 * np.log10(5.89)
    free50 = 20 * np.log10(50) + 46.4 + 20 * np.log10(5.89 / 5)
    got = mean_path_loss_db(p, np.array([50.0, 200.0, 1.0]), LOS)
    assert got[0] == pytest.approx(max(near, free50)) and got[1] == pytest.approx(far)
    assert got[2] == pytest.approx(mean_path_loss_db(p, np.array([3.0]), LOS)[0])  # floored at 3 m
    assert d_bp == pytest.approx(78.6, abs=0.1)


def test_tr37885_formulas_and_nlos_above_los():
    urban = PropagationParams(family="tr37885_urban", frequency_hz=5.9e9)
    hw = PropagationParams(family="tr37885_highway", frequency_hz=5.9e9)
    assert mean_path_loss_db(urban, np.array([100.0]), LOS)[0] == pytest.approx(38.77 + 33.4 + 18.2 * np.log10(5.9))
    assert mean_path_loss_db(hw, np.array([100.0]), LOS)[0] == pytest.approx(32.4 + 40 + 20 * np.log10(5.9))
    nlos = mean_path_loss_db(urban, np.array([100.0]), NLOS)[0]
    assert nlos == pytest.approx(36.85 + 60 + 18.9 * np.log10(5.9))
    d = np.linspace(3, 1000, 200)
    for fam in ("winner_b1", "tr37885_urban", "tr37885_highway"):
        prm = PropagationParams(family=fam)
        assert np.all(mean_path_loss_db(prm, d, NLOS) >= mean_path_loss_db(prm, d, LOS))
        assert np.all(np.diff(mean_path_loss_db(prm, d, LOS)) >= 0)


def test_nlosv_blockage_loss_has_the_tables_mean_and_spread():
    p = PropagationParams()  # 1.5 m antennas below a 1.6 m car: mean 9 + max(0, 15 log10 d - 41), sigma 4.5
    u = uniforms(0, np.arange(200000), 0)
    for d, mu in ((50.0, 9.0), (1000.0, 9.0 + 15 * 3 - 41)):
        x = nlosv_loss_db(p, np.full(len(u), d), u)
        assert x.mean() == pytest.approx(mu, rel=0.01) and x.std() == pytest.approx(4.5, rel=0.03)
    assert np.all(nlosv_loss_db(PropagationParams(antenna_height_m=2.0), np.array([50.0]), np.array([0.5])) == 0)


def test_shadowing_is_stable_reciprocal_and_decorrelates_with_motion():
    p = PropagationParams()
    n = 4000
    keys = link_keys(np.arange(n, dtype=np.uint64), np.arange(n, dtype=np.uint64) + np.uint64(n))
    sh = Shadowing(p, seed=5)
    s0 = sh.update(keys, np.zeros(n), np.full(n, LOS))
    assert s0.std() == pytest.approx(3.0, rel=0.05)
    assert np.array_equal(sh.update(keys, np.zeros(n), np.full(n, LOS)), s0)  # a standing link keeps its value
    s1 = sh.update(keys, np.full(n, 10.0), np.full(n, LOS))  # moved one decorrelation distance
    assert np.corrcoef(s0, s1)[0, 1] == pytest.approx(np.exp(-1), abs=0.05)
    assert s1.std() == pytest.approx(3.0, rel=0.05)
    again = Shadowing(p, seed=5)  # the same seed draws the same values whatever the order of the links
    assert np.array_equal(again.update(keys[::-1], np.zeros(n), np.full(n, LOS))[::-1], s0)
    nlos = Shadowing(p, seed=5).update(keys, np.zeros(n), np.full(n, NLOS))
    assert np.allclose(nlos, s0 * 4.0 / 3.0)


# -- obstacles -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ring_map():
    from mapcontainer.sim import World, load_scenario

    return World(load_scenario("blindspot-occluded"), seed=0).hdmap


def test_buildings_from_the_map_fill_what_is_neither_road_nor_sidewalk(ring_map):
    b = Buildings.from_map(ring_map)
    road = np.array([c.points[len(c.points) // 3, :2] for c in ring_map.centerlines])
    assert not b.at(road).any()
    assert b.at(np.array([[0.0, 0.0]]))[0], "the block inside the ring is a building"
    # across the block from the bottom straight to the top straight: NLOS; along the bottom straight: LOS
    crossed = b.crossed_m(np.array([[0.0, -52.0], [-100.0, -52.0]]), np.array([[0.0, 52.0], [100.0, -52.0]]))
    assert 50 < crossed[0] < 100 and crossed[1] == 0


def test_buildings_from_polygons_and_vehicle_blockage():
    b = Buildings.from_polygons([np.array([[10, -5], [12, -5], [12, 5], [10, 5]])])
    assert b.crossed_m(np.array([[0.0, 0.0]]), np.array([[20.0, 0.0]]))[0] == pytest.approx(2.0, abs=0.6)
    assert b.crossed_m(np.array([[0.0, 10.0]]), np.array([[20.0, 10.0]]))[0] == 0
    a, e = np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[20.0, 0.0], [20.0, 0.0]])
    blockers = np.array([[0.0, 0.0], [20.0, 0.0], [10.0, 0.5], [10.0, 3.0]])
    assert vehicle_blocked(a, e, np.array([0, 0]), np.array([1, 1]), blockers).all()
    assert not vehicle_blocked(a[:1], e[:1], np.array([0]), np.array([1]), blockers[[0, 1, 3]]).any()


# -- PHY and MAC -----------------------------------------------------------------------------------


def test_per_tables_and_the_802_11p_eb_n0_offset():
    p = PhyParams()
    assert per(p, np.array([-20.0]))[0] == 1.0 and per(p, np.array([60.0]))[0] == pytest.approx(1e-3)
    # 6 Mbit/s in 10 MHz: Eb/N0 = SINR + 2.22 dB; the table gives 0.4 at Eb/N0 = 10 dB
    assert per(p, np.array([10.0 - 10 * np.log10(10 / 6)]))[0] == pytest.approx(0.4)
    lte = PhyParams(per_curve="ltev2x_qpsk_0.7", sensing_dbm=-90.5, resource_blocks=10)
    assert per(lte, np.array([6.0]))[0] == pytest.approx(0.4)
    assert np.all(np.diff(per(lte, np.linspace(-5, 25, 100))) <= 0)


def test_csma_cbr_is_the_sensed_load_and_collisions_grow_with_hidden_load():
    phy, mac = PhyParams(), MacParams()
    csma = Csma(mac, phy)
    # three nodes: 0 and 1 hear each other, 2 is heard by 1 only
    P = np.array([[23.0, -70.0, -100.0], [-70.0, 23.0, -70.0], [-100.0, -70.0, 23.0]])
    rate, air = np.array([10.0, 20.0, 5.0]), np.array([1e-3, 1e-3, 2e-3])
    assert np.allclose(csma.cbr(P, rate, air), [0.03, 0.04, 0.03])
    noise = 10 ** (-9.5)
    assert csma.collision_free(0, 1, P, np.array([10.0, 0.0, 0.0]), air, np.zeros(3), noise) == 1.0
    lo = csma.collision_free(0, 1, P, np.array([10.0, 10.0, 10.0]), air, np.zeros(3), noise)
    hi = csma.collision_free(0, 1, P, np.array([10.0, 10.0, 100.0]), air, np.zeros(3), noise)
    assert 1.0 > lo > hi  # node 2 is hidden from 0 and loud at 1
    assert airtime_s(190, 6e6) == pytest.approx(40e-6 + 8 * 220 / 6e6)


def test_sps_keeps_a_reservation_for_5_to_15_transmissions():
    sps = Sps(MacParams(access="sps"), PhyParams(sensing_dbm=-90.5), seed=1)
    P = np.array([[23.0]])
    res = [sps.transmit("a", 150, 0.1 * k, ["a"], P) for k in range(200)]
    runs, n = [], 1
    for r0, r1 in zip(res, res[1:], strict=False):
        if r1 == r0:
            n += 1
        else:
            runs.append(n)
            n = 1
    assert runs and min(runs) >= 5 and max(runs) <= 30  # a reselection may draw the same resource again
    assert all(0 <= r[0] < 100 and r[2] == 1 for r in res)
    assert sps.width(500) == 3 and sps.width(5000) == 4


def test_sps_avoids_a_decoded_neighbours_resource():
    sps = Sps(MacParams(access="sps", subchannels=1), PhyParams(sensing_dbm=-90.5), seed=2)
    P = np.array([[23.0, -60.0], [-60.0, 23.0]])
    same = 0
    for k in range(300):
        ra = sps.transmit("a", 100, 0.1 * k, ["a", "b"], P)
        rb = sps.transmit("b", 100, 0.1 * k, ["a", "b"], P)
        same += ra[0] == rb[0]
    assert same == 0


# -- the channel -----------------------------------------------------------------------------------


def _balance(st):
    dropped = sum(st["dropped_msgs"].values())
    assert st["offered_msgs"] == dropped + st["delivered_msgs"] + st["in_flight_msgs"]
    assert sum(st["radio_drops"].values()) == st["dropped_msgs"]["loss"]


def test_radio_profiles_load_and_refuse_a_loss_of_their_own(tmp_path):
    for name in ("its-g5", "its-g5-dcc", "cv2x-mode4"):
        p = load_profile(name)
        assert isinstance(p, RadioProfile) and p.description
        assert p.radio.dcc.enabled == (name == "its-g5-dcc")
        assert isinstance(make_channel(p, 0), RadioChannel)
    assert isinstance(make_channel(load_profile("dsrc"), 0), Channel)
    bad = tmp_path / "bad.yaml"
    bad.write_text("loss: 0.1\nradio: {mac: {access: csma}}\n")
    with pytest.raises(ConfigError, match="radio model"):
        load_profile(bad)
    bad.write_text("radio: {mac: {access: aloha}}\n")
    with pytest.raises(ConfigError, match="access"):
        load_profile(bad)


def _run(profile, seed=0, steps=50):
    ch = RadioChannel(profile, seed)
    ch.place("host", "a")
    out = []
    for k in range(steps):
        t = 0.1 * k
        ch.observe(t, {"a": (0.0, 0.0), "b": (150.0 + k, 0.0), "c": (260.0, 3.0)}, {"7": (75.0, 0.2)})
        ch.on_air("a", PAYLOAD, t)
        for src in ("b", "c"):
            out.append(ch.send(src, "host", PAYLOAD, t))
        out.extend((d.src, round(d.t_arrive, 9)) for d in ch.deliver(t))
    return ch, out


@pytest.mark.parametrize("name", ["its-g5", "cv2x-mode4"])
def test_radio_channel_is_reproducible_and_balanced(name):
    prof = load_profile(name)
    ch, out = _run(prof)
    _, again = _run(prof)
    assert out == again
    st = ch.stats()
    _balance(st)
    assert st["link_states"]["nlosv"] > 0, "the vehicle at x = 75 m blocks a -> b"
    assert set(st["cbr"]) == {"a", "b", "c"} and all(0 < v["mean"] <= 1 for v in st["cbr"].values())
    assert "7" in ch.cbr(), "the other vehicle sends background CAMs"
    lat = [d for d in out if isinstance(d, tuple)]
    assert lat, "some messages arrive"


def test_unlocated_nodes_and_onboard_receivers():
    ch = RadioChannel(_plain("its-g5"), 0)
    assert ch.send("x", "host", PAYLOAD, 0.0)  # nobody is located yet
    ch.observe(0.1, {"a": (0.0, 0.0)})
    ch.place("host", "a")
    assert ch.send("a", "host", PAYLOAD, 0.1)  # on board: no radio
    st = ch.stats()
    assert st["unlocated_msgs"] == 1 and st["offered_msgs"] == 2 and len(ch) == 2


def test_a_broadcast_is_one_transmission_however_many_receivers():
    ch = RadioChannel(_plain("its-g5"), 0)
    for k in range(11):
        t = 0.1 * k
        ch.observe(t, {"a": (0.0, 0.0), "b": (50.0, 0.0), "c": (0.0, 50.0)})
        for dst in ("b", "c"):
            ch.send("a", dst, PAYLOAD, t)
    cbr = ch.cbr()
    assert cbr["b"] == pytest.approx(10 * airtime_s(len(PAYLOAD), 6e6))


def test_the_corner_of_the_ring_is_nlos(ring_map):
    prof = load_profile("its-g5")
    ch = make_channel(prof, 0, ring_map)
    ch.place("host", "a")
    # a on the bottom straight before the corner, b on the right straight after it: the block is between
    ch.observe(0.0, {"a": (150.0, -52.0), "b": (201.0, 0.0)})
    i, j = ch.names.index("a"), ch.names.index("b")
    assert ch.state[i, j] == NLOS
    ch.observe(0.1, {"a": (150.0, -52.0), "b": (190.0, -52.0)})
    assert ch.state[i, j] == LOS


# -- validation against the sources' closed forms -------------------------------------------------


@pytest.mark.parametrize("name", ["its-g5", "cv2x-mode4"])
@pytest.mark.parametrize("state", [LOS, NLOS])
def test_prr_against_the_published_model_at_three_distances(name, state):
    prof = _plain(name)
    d = np.array([50.0, 100.0, 300.0]) if state == NLOS else np.array([100.0, 275.0, 450.0])
    a = reference_prr(SOURCES[name], d, state)
    s = simulated_prr(prof, d, state, n=300, seed=3)
    assert np.all(np.abs(a - s) <= 0.09), (a, s)  # 3.1 binomial sigmas at p = 0.5 for 300 messages


@pytest.mark.slow
@pytest.mark.parametrize("name", ["its-g5", "cv2x-mode4"])
@pytest.mark.parametrize("state", [LOS, NLOS])
def test_prr_against_the_published_model_every_25_m(name, state):
    from mapcontainer.experiments.radio import DISTANCES_M

    prof = _plain(name)
    d = np.asarray(DISTANCES_M)
    a = reference_prr(SOURCES[name], d, state)
    s = simulated_prr(prof, d, state, n=1000, seed=0)
    assert np.all(np.abs(a - s) <= PRR_TOLERANCE), np.round(a - s, 3)


def test_cbr_against_the_802_11p_load_closed_form():
    prof = _plain("its-g5")
    for beta in (0.02, 0.06):
        sim, per_vehicle = simulated_cbr(prof, beta)
        assert sim == pytest.approx(analytic_cbr(prof, beta, 10.0, 190), rel=0.06)
        assert per_vehicle.min() < sim  # the road's ends hear fewer vehicles


def test_the_reference_prr_has_the_published_models_shape():
    a = reference_prr("gonzalez2019_cv2x", np.array([10.0]), LOS)
    assert a[0] == pytest.approx((1 - 0.01) * (1 - 1e-3), abs=1e-3)  # half duplex lambda / 1000, BLER floor
    assert reference_prr("sepulcre2021_80211p", np.array([10.0]), LOS)[0] == pytest.approx(1 - 1e-3, abs=1e-4)
    assert reference_prr("sepulcre2021_80211p", np.array([2000.0]), LOS)[0] < 1e-6
    far = reference_prr("sepulcre2021_80211p", np.array([150.0, 300.0]), NLOS)
    assert np.all(far < reference_prr("sepulcre2021_80211p", np.array([150.0, 300.0]), LOS))


def test_the_path_loss_matches_ns3s_published_tr37885_vectors():
    from mapcontainer.experiments.radio import ns3_path_loss_check

    rows = ns3_path_loss_check()
    assert len(rows) == 12 and all(r["within_tolerance"] for r in rows), rows
    ref, nl = published()["ns3_tr37885_pathloss"], published()["tr37885_nlos"]
    for d, pl in ref["urban"]["NLOS"]:  # the reference's NLOS coefficients reproduce them too
        assert nl["a"] + nl["b"] * np.log10(d) + nl["c"] * np.log10(ref["frequency_hz"] / 1e9) == pytest.approx(
            pl, abs=ref["tolerance_db"]
        )


@pytest.mark.parametrize("name", ["its-g5", "cv2x-mode4"])
def test_the_presets_carry_the_published_models_numbers(name):
    src, r = published()[SOURCES[name]], load_profile(name).radio
    w = src["winner_b1"]
    assert r.propagation.frequency_hz == w["frequency_hz"] and r.phy.tx_power_dbm == src["tx_power_dbm"]
    assert r.propagation.environment_height_m == w["environment_height_m"]
    assert r.phy.sensing_dbm == src["sensing_dbm"] and noise_dbm(r.phy) == pytest.approx(src["noise_dbm"], abs=1e-3)
    x = np.asarray(src["per_x_db"], dtype=float)
    if "data_rate_bps" in src:  # the model's 802.11p table is in Eb/N0: back to SINR
        x = x - 10 * np.log10(src["bandwidth_hz"] / src["data_rate_bps"])
    assert per(r.phy, x) == pytest.approx(src["per_y"])
    # the model's WINNER+ B1 against the authors' get_PL_SH.m (c = 3e8 there: 0.07 % off the breakpoint)
    d = np.array([3.0, 20.0, 60.0, 120.0, 500.0])
    assert mean_path_loss_db(r.propagation, d, LOS) == pytest.approx(
        reference_path_loss_db(SOURCES[name], d, LOS)[0], abs=0.01
    )


# -- DCC ---------------------------------------------------------------------------------------------


def test_reactive_dcc_rises_on_sustained_load_and_falls_on_sustained_quiet():
    from mapcontainer.radio.dcc import DccParams, ReactiveDcc

    d = ReactiveDcc(DccParams(enabled=True))
    t = 0.0
    for _ in range(5):  # a single high sample does not raise it while the last second held lower ones
        t += 0.1
        d.update(t, 0.1)
    assert d.update(t + 0.1, 0.5) == 0
    t += 0.1
    for _ in range(11):
        t += 0.1
        d.update(t, 0.5)
    assert d.state == 4 and d.interval_s == pytest.approx(0.34)  # 0.43 <= 0.5 < 0.51: Active 4
    for _ in range(20):  # 2 s of quiet: the last 5 s still held 0.5
        t += 0.1
        d.update(t, 0.05)
    assert d.state == 4
    for _ in range(31):
        t += 0.1
        d.update(t, 0.05)
    assert d.state == 0
    assert d.allow(10.0) and not d.allow(10.05) and d.allow(10.06) and d.gated == 1
    with pytest.raises(ValueError, match="intervals_s"):
        DccParams(thresholds=(0.2,), intervals_s=(0.1,))


def test_dcc_on_every_sender_cuts_the_load_of_a_dense_road():
    prof = _plain("its-g5")
    dense = prof.model_copy(update={"radio": prof.radio.model_copy(update={"background_rate_hz": 20.0})})
    from mapcontainer.radio.dcc import DccParams

    gated = dense.model_copy(update={"radio": dense.radio.model_copy(update={"dcc": DccParams(enabled=True)})})
    out = {}
    for name, p in (("off", dense), ("on", gated)):
        ch = RadioChannel(p, 0)
        ch.place("host", "a")
        others = {str(k): (4.0 * k, 3.5 * (k % 2)) for k in range(1, 100)}
        for k in range(40):
            t = 0.1 * k
            ch.observe(t, {"a": (0.0, 0.0), "b": (60.0, 0.0)}, others)
            ch.send("b", "host", PAYLOAD, t)
        out[name] = (ch.cbr()["a"], ch.stats())
    assert out["on"][0] < 0.8 * out["off"][0]
    st = out["on"][1]
    _balance(st)
    assert st["radio_drops"]["dcc"] > 0 and max(ch.dcc_states().values()) > 0


def test_buildings_from_a_sumo_additional_file(tmp_path):
    pytest.importorskip("sumolib")
    f = tmp_path / "city.poly.xml"
    f.write_text(
        "<additional>\n"
        '  <poly id="b1" type="building" color="red" fill="1" layer="-1" shape="10,-5 12,-5 12,5 10,5 10,-5"/>\n'
        '  <poly id="p1" type="natural.water" color="blue" fill="1" layer="-1" shape="30,-5 40,-5 40,5 30,5"/>\n'
        "</additional>\n"
    )
    b = Buildings.from_sumo(f)
    assert b.crossed_m(np.array([[0.0, 0.0]]), np.array([[20.0, 0.0]]))[0] == pytest.approx(2.0, abs=0.6)
    assert b.crossed_m(np.array([[25.0, 0.0]]), np.array([[45.0, 0.0]]))[0] == 0  # water does not block
    prof = load_profile("its-g5")
    prof = prof.model_copy(update={"radio": prof.radio.model_copy(update={"building_file": str(f)})})
    assert make_channel(prof, 0).buildings.mask.any()
