"""A vehicle process frozen (SIGSTOP) and resumed on a live fleet: its health says degraded until it has
relocalized, and once it says ok again its published pose is right.

The world and one vehicle run as processes on a loopback rendezvous (fixtures in conftest.py); the test
reads the vehicle's priors, its periodic health status and the world's ground truth.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time

import numpy as np
import pytest

from mapcontainer.localization.health import PoseHealthParams
from mapcontainer.security import inner_payload
from schemas import GroundTruth, HealthStatus, VehiclePrior, decode
from schemas.topics import topic

pytestmark = [pytest.mark.integration, pytest.mark.slow]

FREEZE_S = 5.0
# The freeze starts once the vehicle has published a prior this late (scenario s), so that it resumes near
# 11.7 s: a cold start of paper-urban seed 0 (two vehicles) between about 10.6 and 13.2 s finds the right
# pose, while one from 13.3 s, or from parts of 17-19 s, locks into a wrong basin 4-14 m off with a
# confident covariance -- a defect of the start-up, not of the health this test is about.
FREEZE_AT_S = 6.5
GOOD_M = 0.5  # horizontal error of a relocalized pose (a wrong basin or a prediction over the gap: metres)
WATCH_S = 3.0  # scenario seconds of priors checked once the health is ok again


class Recorder:
    """Priors, health statuses (with their arrival times) and the truth of one vehicle."""

    def __init__(self, session, fleet: str, vid: str):
        self.vid = vid
        self.lock = threading.Lock()
        self.events: list[tuple[float, str, object]] = []  # (monotonic arrival, "prior" | "health", message)
        self.truth: dict[int, np.ndarray] = {}  # frame index (t_meas / 0.1) -> true pose
        self._subs = [
            session.declare_subscriber(topic("truth").key(fleet=fleet), self._on_truth),
            session.declare_subscriber(topic("prior_tx").key(fleet=fleet, src=vid), self._on("prior", VehiclePrior)),
            session.declare_subscriber(
                topic("health").key(fleet=fleet, role="vehicle", id=vid), self._on("health", HealthStatus)
            ),
        ]

    def _on_truth(self, sample) -> None:
        g = decode(inner_payload(sample.payload.to_bytes()), GroundTruth)  # signed by the world
        if g and self.vid in g.vehicle_ids:
            with self.lock:
                self.truth[round(g.t_meas * 10)] = np.asarray(g.vehicle_pose[g.vehicle_ids.index(self.vid)], float)

    def _on(self, kind: str, model):
        def cb(sample) -> None:
            msg = decode(sample.payload.to_bytes(), model)
            if msg:
                with self.lock:
                    self.events.append((time.monotonic(), kind, msg))

        return cb

    def since(self, t0: float) -> list[tuple[float, str, object]]:
        with self.lock:
            return [e for e in self.events if e[0] >= t0]

    def error_m(self, prior: VehiclePrior) -> float | None:
        with self.lock:
            truth = self.truth.get(round(prior.t_meas * 10))
        return None if truth is None else float(np.hypot(*(np.asarray(prior.pose[:2], float) - truth[:2])))

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def relocalized(events) -> tuple[int, int] | None:
    """(index of the first status that says relocalizing after a gap, index of the first ok status after it)."""
    health = [i for i, (_, kind, _) in enumerate(events) if kind == "health"]
    first = next((i for i in health if "relocalizing after a" in (events[i][2].last_error or "")), None)
    if first is None:
        return None
    ok = next((i for i in health if i > first and events[i][2].state == "ok"), None)
    return None if ok is None else (first, ok)


def test_a_frozen_vehicle_is_degraded_until_it_relocalizes(rendezvous, fleet_name, spawn, watch_liveliness, stop):
    session, endpoint = rendezvous
    alive = watch_liveliness(session, topic("alive").pattern(fleet=fleet_name))
    rec = Recorder(session, fleet_name, "cv0")
    common = ["--fleet", fleet_name, "--connect", endpoint]
    vehicle = spawn("services.vehicle", *common, "--id", "cv0", "--health-period", "0.1")
    alive.wait_alive(topic("alive").key(fleet=fleet_name, role="vehicle", id="cv0"), timeout=60)
    world = spawn("services.world", *common, "--vehicles", "2", "--wait-subscribers", "1")
    try:

        def tracking_late_enough() -> bool:
            ev = rec.since(0.0)
            last_health = next((m for _, k, m in reversed(ev) if k == "health"), None)
            late = any(k == "prior" and m.t_meas >= FREEZE_AT_S for _, k, m in ev)
            return late and last_health is not None and last_health.state == "ok"

        deadline = time.monotonic() + 90
        while not tracking_late_enough():
            assert time.monotonic() < deadline, f"cv0 never tracked: {rec.since(0.0)[-3:]}"
            time.sleep(0.02)
        os.kill(vehicle.pid, signal.SIGSTOP)
        try:
            time.sleep(FREEZE_S)  # the freeze itself
        finally:
            os.kill(vehicle.pid, signal.SIGCONT)
        t_resume = time.monotonic()

        def done():  # relocalized, and WATCH_S of priors after the first ok status since
            ev = rec.since(t_resume)
            found = relocalized(ev)
            if found is None:
                return None
            after = [m for _, k, m in ev[found[1] :] if k == "prior"]
            return (ev, found) if after and after[-1].t_meas - after[0].t_meas >= WATCH_S else None

        deadline = time.monotonic() + 90
        while (got := done()) is None:
            assert time.monotonic() < deadline, [(k, getattr(m, "last_error", None)) for _, k, m in rec.since(t_resume)]
            time.sleep(0.05)
    finally:
        rec.close()
        codes = {"world": stop(world), "vehicle": stop(vehicle)}
    assert codes == {"world": 0, "vehicle": 0}, (
        world.log_path.read_text()[-3000:],
        vehicle.log_path.read_text()[-3000:],
    )

    events, (first, ok) = got
    gap = float(re.search(r"after a ([0-9.]+) s gap", events[first][2].last_error).group(1))
    # scenario seconds without a frame: fewer than the wall seconds frozen when the world is behind its
    # clock (a loaded machine), but a gap the pose does not survive
    assert gap > PoseHealthParams().gap_s, events[first][2].last_error
    # Degraded from the first frame after the gap (``first``) until ``ok``; once ok, the vehicle knows where
    # it is: every prior since is right. A prior is put after the frame that changed the health, so one
    # from before the relocalization cannot arrive after the ok status.
    after = [(m, rec.error_m(m)) for _, k, m in events[ok:] if k == "prior"]
    assert len(after) >= 10 and after[0][0].quality.mode == "map_matching", after[:3]
    bad = [(m.t_meas, m.quality.mode, e) for m, e in after if e is None or e > GOOD_M]
    assert not bad, bad
