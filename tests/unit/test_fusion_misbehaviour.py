"""Misbehaviour detection: sightings, views, disputes and flags (synthetic sightings; the pipeline below)."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.misbehaviour import MisbehaviourMonitor
from mapcontainer.pipeline import run_pipeline
from mapcontainer.sim import load_scenario
from mapcontainer.sim.errors import with_error_sources, with_traffic

VEHICLE = 2


def see(mon: MisbehaviourMonitor, observer: str, t: float, where: dict[str, tuple[float, float]], truth: dict) -> None:
    """``observer`` detects every other vehicle at its true position; ``where``: what each vehicle reports."""
    others = [v for v in truth if v != observer]
    p = np.array([[*truth[v], 0.0] for v in others])
    reported = {v: np.array([*where[v], 0.0]) for v in where}
    mon.observe(observer, t, p, np.full(len(p), VEHICLE), reported)


def run(bias: dict[str, tuple[float, float]], observers: list[str], seconds: float = 3.0) -> MisbehaviourMonitor:
    """Four vehicles 10 m apart, each seen by ``observers``; ``bias``: what some of them add to their pose
    from t = 1 s on (their detections of the others move with their own bias, as a biased pose's do)."""
    mon = MisbehaviourMonitor(FusionParams())
    truth = {"cv0": (0.0, 0.0), "cv1": (10.0, 0.0), "cv2": (20.0, 0.0), "cv3": (30.0, 0.0)}
    for k in range(int(seconds * 10)):
        t = 0.1 * k
        b = {v: np.array(bias.get(v, (0.0, 0.0))) if t >= 1.0 else np.zeros(2) for v in truth}
        where = {v: tuple(np.array(truth[v]) + b[v]) for v in truth}
        for o in observers:
            seen = {v: tuple(np.array(truth[v]) + b[o]) for v in truth}  # o's detections carry o's bias
            see(mon, o, t, where, seen)
        mon.update(t)
    return mon


def test_honest_vehicles_are_never_flagged_nor_disputed() -> None:
    mon = run({}, ["cv0", "cv1", "cv2", "cv3"])
    assert mon.flagged == {} and mon.disputed == set()


@pytest.mark.parametrize("bias", [(0.0, 1.0), (3.0, 0.0), (0.0, -5.0)])
def test_a_biased_vehicle_is_flagged_and_not_the_ones_it_sees_off(bias) -> None:
    mon = run({"cv1": bias}, ["cv0", "cv1", "cv2", "cv3"])
    assert list(mon.flagged) == ["cv1"], mon.flagged
    assert f"{np.hypot(*bias):.1f} m" in mon.flagged["cv1"]
    assert all("cv1" in pair for pair in mon.disputed)  # cv1 disputes with everyone, nobody else does
    assert mon.flagged_total == 1


def test_two_vehicles_alone_dispute_but_nobody_is_flagged() -> None:
    """cv0 and cv1 see only each other: one of them lies, the host cannot tell which."""
    mon = MisbehaviourMonitor(FusionParams())
    for k in range(30):
        t = 0.1 * k
        b = np.array([0.0, 2.0]) if t >= 1.0 else np.zeros(2)
        where = {"cv0": (0.0, 0.0), "cv1": tuple(np.array([10.0, 0.0]) + b)}
        see(mon, "cv0", t, where, {"cv0": (0.0, 0.0), "cv1": (10.0, 0.0)})
        see(mon, "cv1", t, where, {"cv0": tuple(b), "cv1": (10.0, 0.0)})
        mon.update(t)
    assert mon.flagged == {} and mon.disputed == {frozenset(("cv0", "cv1"))}


def test_a_flag_clears_when_the_vehicle_is_seen_where_it_says_again() -> None:
    mon = run({"cv1": (0.0, 3.0)}, ["cv0", "cv2"], seconds=3.0)
    assert "cv1" in mon.flagged
    truth = {"cv0": (0.0, 0.0), "cv1": (10.0, 0.0), "cv2": (20.0, 0.0), "cv3": (30.0, 0.0)}
    for k in range(30, 60):  # the bias is gone
        t = 0.1 * k
        for o in ("cv0", "cv2"):
            see(mon, o, t, truth, truth)
        mon.update(t)
    assert mon.flagged == {}


@pytest.mark.slow
def test_in_the_pipeline_a_biased_vehicle_is_flagged_within_a_second_and_clean_runs_flag_nobody() -> None:
    """paper-urban, warm start, development seed 101, the recorded case (the simulator's error sources off,
    traffic as listed): cv1 reports its pose 1 m off from t = 2 s. The host flags cv1 (and nobody else)
    within 1 s; without the fault nothing is flagged. Outside the recorded case the detector errs (issue 21
    stays open on it): with the traffic drawn for this seed it flags cv2 beside cv1 from 3.3 s, and with the
    realistic errors on the clean run flags cv2 and cv3 (its fixed dispute distance does not allow for map
    and calibration errors)."""
    sc = load_scenario(
        "paper-urban", {"faults": [{"kind": "pose_bias", "vehicle": "cv1", "bias_m": [0, 1.0], "start_s": 2}]}
    )
    sc = with_traffic(with_error_sources(sc, ()), False)
    res = run_pipeline(sc, seed=101, duration_s=5.0, start="warm")
    flagged = {(round(r.t, 1), v) for r in res.records for v in r.fused["cooperative"].flagged}
    assert {v for _, v in flagged} == {"cv1"}
    assert min(t for t, _ in flagged) <= 3.0
    clean = run_pipeline(
        with_traffic(with_error_sources(load_scenario("paper-urban"), ()), False),
        seed=101,
        duration_s=5.0,
        start="warm",
    )
    assert not any(r.fused["cooperative"].flagged for r in clean.records)
