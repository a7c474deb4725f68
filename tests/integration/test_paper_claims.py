"""The paper experiment's figures with teeth: a short but steady-state configuration of its own runs
(paper-urban, 4 development seeds, cold start, 8 s scored from 3 s, every realistic error source on)
checked against bounds a missing fusion step or a broken estimator would fail. The claims the
estimators do not earn yet are strict xfails naming the issue that owns them: when they start to
hold, the test says so."""

from __future__ import annotations

from dataclasses import asdict

import pytest

from mapcontainer.experiments.executors import Executor
from mapcontainer.experiments.paper import PaperSettings
from mapcontainer.experiments.paper.figures import sim_figures
from mapcontainer.experiments.paper.runs import describe, run_task
from mapcontainer.experiments.runner import run_all

pytestmark = pytest.mark.slow

SETTINGS = PaperSettings(runs=4, seed=1000, duration_s=8.0, burnin_s=3.0)


@pytest.fixture(scope="module")
def urban() -> dict:
    s = SETTINGS
    tasks = [("sim", "urban", "paper-urban", "all", s.seed + i, asdict(s)) for i in range(s.runs)]
    runs = run_all(run_task, tasks, "paper runs", describe, Executor(workers=2), progress=False).results
    return sim_figures(runs, s.burnin_s)


def test_map_matching_beats_gnss_by_an_order_of_magnitude(urban):
    # seeds 1000-1003: GNSS 1.79 m, on-board 0.13 m, per-frame map matching 0.13 m (ego)
    e = urban["ego_rmse_m"]
    assert e["gnss"] > 1.0 and e["onboard"] < 0.25 and e["map_matching"] < 0.25
    assert urban["runs"] == 4 and urban["objects"]["cooperative"]["frames"] == 4 * 50


def test_cooperation_sees_more_targets_and_places_them_better(urban):
    """A host that ignored the other vehicles would equal the ego-only view: coverage 0.58 against 0.48,
    GOSPA 3.5 against 4.1 m, rms2 on the targets both views estimate 0.48 against 0.51 m."""
    coop, ego = urban["objects"]["cooperative"], urban["objects"]["ego_only"]
    assert coop["coverage"] > ego["coverage"] + 0.05
    assert coop["gospa_m"] < ego["gospa_m"] - 0.2
    assert urban["target_rmse_common_m"]["cooperative"] < urban["target_rmse_common_m"]["ego_only"]
    assert urban["target_rmse_m"]["cooperative"] < 0.7


def test_cooperation_never_hurts_a_vehicle(urban):
    # seeds 1000-1003, fused against on board: cv0 0.149 / 0.154, cv1 0.175 / 1.255, cv2 0.250 / 0.375,
    # cv3 0.133 / 0.133 m; cv3 was 0.159 while the host moved a frame of the instant by the gap between the
    # vehicles' clocks (docs/host.md, "a vehicle's own echo")
    for vid, f in urban["per_vehicle_rmse_m"].items():
        assert f["cooperative"] <= 1.05 * f["onboard"], (vid, f)


def test_fused_vehicle_poses_are_consistent(urban):
    # seeds 1000-1003: fused 6-DoF ANEES 5.47 (band 3.1-9.8); it was 51 before the vehicles reported the
    # error their every frame repeats and the host used each vehicle's filtered estimate once
    c = urban["consistency"]["vehicles_cooperative_6dof"]
    assert c["dof"] == 6 and c["runs"] == 4
    assert c["inside"], c


def test_the_centralized_joint_estimator_costs_bytes_and_keeps_its_vehicles(urban):
    """The same runs in centralized mode (one joint filter over every vehicle's raw observations) send several
    times the bytes of the distributed priors, and keep every vehicle localized (held to 0.3 m)."""
    eff = urban["efficiency"]
    assert eff["runs"] == 4
    assert eff["bytes_ratio"] > 5.0, eff
    assert urban["vehicles_rmse_m"]["centralized"] < 0.3


def test_the_centralized_joint_estimator_is_the_accuracy_reference(urban):
    """Efficiency = centralized MSE / distributed MSE <= 1 for the objects and the targets (0.679 and 0.680 on these
    runs; 1.089 and 1.132 while the reference kept copies of connected vehicles as objects, test_joint_reference;
    0.853 and 0.890 before the distributed host took a searching vehicle's detections by their association
    probability, which costs it objects accuracy on seed 1003, docs/host.md 'The cold start'). Not claimed for the
    vehicles: on these runs the distributed host's vehicles are the more accurate (efficiency 1.21)."""
    eff = urban["efficiency"]
    assert eff["objects"] <= 1.0 and eff["targets"] <= 1.05, eff
