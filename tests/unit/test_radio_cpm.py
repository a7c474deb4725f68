"""ETSI CPM object inclusion rules on a vehicle's prior (mapcontainer.radio.cpm)."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.radio.cpm import CpmRules
from schemas import LocalizationQuality, ObjectClass, ObjectObservations, VehiclePrior


def _prior(t: float, objects: list[tuple[float, float, int]], x0: float = 0.0) -> VehiclePrior:
    """A vehicle standing at (x0, 0) facing +x that sees objects at map (x, y) of class c."""
    p = np.array([[x - x0, y, 0.0] for x, y, _ in objects]).reshape(-1, 3)
    return VehiclePrior(
        fleet="f",
        sender="cv1",
        seq=int(round(t * 10)),
        t_meas=t,
        t_sent=t,
        pose=np.array([x0, 0, 0, 0, 0, 0.0]),
        pose_cov=(np.diag([0.1, 0.1, 0.05, 0.005, 0.005, 0.005]) ** 2)[np.triu_indices(6)],
        v_map=np.zeros(3),
        quality=LocalizationQuality(mode="map_matching"),
        objects=ObjectObservations.from_metres(
            p, np.tile(np.eye(3) * 0.04, (len(objects), 1, 1)), [c for *_, c in objects]
        ),
    )


def _inclusions(track, seconds=4.0):
    rules = CpmRules()
    times = {}
    for k in range(int(seconds * 10) + 1):
        t = round(0.1 * k, 10)
        out = rules.filter(_prior(t, [o(t) for o in track]))
        for cls in np.asarray(out.objects.cls):
            times.setdefault(int(cls), []).append(t)
    return times, rules


def test_a_standing_car_is_sent_once_a_second_and_a_standing_pedestrian_twice():
    car = lambda t: (20.0, 3.0, int(ObjectClass.VEHICLE))  # noqa: E731
    ped = lambda t: (15.0, -6.0, int(ObjectClass.PEDESTRIAN))  # noqa: E731
    times, rules = _inclusions([car, ped])
    assert times[int(ObjectClass.VEHICLE)] == pytest.approx([0.0, 1.0, 2.0, 3.0, 4.0])
    assert times[int(ObjectClass.PEDESTRIAN)] == pytest.approx([0.5 * k for k in range(9)])
    assert rules.included == 14 and rules.omitted == 82 - 14


def test_a_fast_car_is_sent_when_it_moved_4_m():
    fast = lambda t: (20.0 + 15.0 * t, 3.0, int(ObjectClass.VEHICLE))  # noqa: E731  15 m/s
    times, _ = _inclusions([fast], seconds=3.0)
    gaps = np.diff(times[int(ObjectClass.VEHICLE)])
    # the first inclusions follow the tracker's speed estimate converging (speed change > 0.5 m/s); then every
    # 4 m / 15 m/s = 0.27 s -> each third frame
    assert np.all(gaps[-5:] == pytest.approx(0.3))


def test_a_turning_car_is_sent_on_its_heading_change_and_a_new_one_at_once():
    def turning(t):  # 10 m/s on a circle of 100 m radius: 5.7 deg/s
        a = 0.1 * t
        return (20.0 + 100 * np.sin(a), 3.0 + 100 * (1 - np.cos(a)), int(ObjectClass.VEHICLE))

    rules = CpmRules()
    sent, peds = [], []
    for k in range(60):
        t = round(0.1 * k, 10)
        objs = [turning(t)] + ([(40.0, -3.0, int(ObjectClass.PEDESTRIAN))] if k >= 30 else [])
        cls = np.asarray(rules.filter(_prior(t, objs)).objects.cls)
        sent.append(int((cls == ObjectClass.VEHICLE).sum()))
        peds.append(int((cls == ObjectClass.PEDESTRIAN).sum()))
    assert peds[30] == 1 and peds[31:35] == [0] * 4 and peds[35] == 1, "a new object at once, then its 500 ms"
    assert sent[0] == 1 and 8 <= sum(sent[:30]) <= 15  # 4 m at 10 m/s: every 0.4 s, once the speed settled
