"""The one host loop (mapcontainer.host): its set-up, build_host, the HostCore protocol both cores implement,
and the loop's receive / step / timeouts / fuse on a clock given as an argument."""

import argparse

import numpy as np
import pytest
from pydantic import ValidationError

from mapcontainer.config import ConfigError
from mapcontainer.fusion.container import Container
from mapcontainer.fusion.hostcore import HostCore
from mapcontainer.fusion.joint import JointHost
from mapcontainer.hdmap.generator import generate_map
from mapcontainer.hdmap.io import save_map
from mapcontainer.host import HostSetup, add_host_args, build_host, host_setup_from_args
from mapcontainer.sim.config import load_scenario
from schemas import FusedState, decode, encode

from .test_fusion_container import prior


def _args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_host_args(p)
    return p.parse_args(list(argv))


def test_build_host_makes_either_core_behind_the_gate_and_the_map_comes_as_a_map(tmp_path) -> None:
    loop = build_host(HostSetup(fleet="f", known_senders=("cv0",), local=("cv0",), max_wait_s=0.2))
    assert isinstance(loop.core, Container) and isinstance(loop.core, HostCore)
    assert loop.gate.expected == {"cv0"} and loop.gate.reference == "cv0" and loop.gate.max_wait_s == 0.2
    with pytest.raises(ValueError, match="HD map"):
        build_host(HostSetup(fleet="f", mode="centralized"))
    hdmap = generate_map(load_scenario("overlap").map)
    path = save_map(hdmap, tmp_path / "m.geojson")
    from_file = build_host(HostSetup(fleet="f", mode="centralized", map_file=str(path)))
    given = build_host(HostSetup(fleet="f", mode="centralized"), hdmap)
    for loop in (from_file, given):
        assert isinstance(loop.core, JointHost) and isinstance(loop.core, HostCore)
    assert len(from_file.core.hdmap.lane_lines) == len(hdmap.lane_lines) and given.core.hdmap is hdmap


def test_the_loop_solves_a_frame_once_every_known_sender_is_in_and_lists_its_inputs() -> None:
    loop = build_host(HostSetup(fleet="f", known_senders=("cv0", "cv1"), local=("cv0",)))
    r = loop.receive(encode(prior("cv1", seq=1, t=0.003, pose=(0, 8, 0, 0, 0, 0))), t_recv=0.05, now=10.0)
    assert r.accepted and loop.step(10.0) is None  # cv0's message is missing
    assert not loop.receive(encode(prior("cv9", seq=4, t=0.0)), 0.05, now=10.01).accepted  # unknown: no frame
    assert not loop.receive(b"\x00garbage", 0.05, now=10.01).accepted
    loop.receive(encode(prior("cv0", seq=1, t=0.001)), t_recv=0.06, now=10.02)
    f = loop.step(10.02)
    assert f is not None and f.t == pytest.approx(0.001) and f.released == 10.02  # cv0's clock times the frame
    assert f.inputs == [["cv1", 1, 0.05], ["cv9", 4, 0.05], ["cv0", 1, 0.06]]  # all it received, in order
    assert isinstance(decode(f.payload(), FusedState), FusedState) and list(f.state.vehicle_ids) == ["cv0", "cv1"]
    assert loop.step(10.03) is None and loop.gate.complete == 1
    stats = loop.stats()
    assert stats["accepted"] == 2 and stats["rejected"]["unknown_sender"] == 1 and sum(stats["rejected"].values()) == 2
    assert stats["frames_complete"] == 1 and stats["frames_timed_out"] == 0


def test_a_frame_missing_a_sender_is_solved_when_it_times_out() -> None:
    loop = build_host(HostSetup(fleet="f", known_senders=("cv0", "cv1"), max_wait_s=0.1))
    loop.receive(encode(prior("cv0", seq=1, t=0.1)), 0.1)
    loop.receive(encode(prior("cv0", seq=2, t=0.2)), 0.2)
    assert loop.next_deadline() == pytest.approx(0.2)
    assert loop.timeouts(0.15) == []
    out = loop.timeouts(0.3)  # frame 0.1 times out at 0.2; frame 0.2 (first heard at 0.2) at 0.3
    assert [round(f.t, 3) for f in out] == [0.1, 0.2] and [round(f.released, 3) for f in out] == [0.2, 0.3]
    assert loop.next_deadline() is None and loop.gate.timed_out == 2


def test_fusing_at_a_given_time_is_what_re_fusion_does_and_the_gate_forgets_that_frame() -> None:
    loop = build_host(HostSetup(fleet="f", known_senders=("cv0", "cv1")))
    for k in range(3):
        loop.receive(encode(prior("cv0", seq=k, t=0.1 * k, pose=(0.5 * k, 0, 0, 0, 0, 0))), 0.1 * k)
    f = loop.fuse(0.1, tolerance_s=0.02)
    assert f.t == 0.1 and f.tolerance_s == 0.02 and f.released is None and len(f.inputs) == 3
    assert loop.gate.pending == 1  # frames 0.0 and 0.1 are done; 0.2 still waits for cv1
    # the same inputs and times through a fresh loop: the same bytes (what replay relies on)
    again = build_host(HostSetup(fleet="f", known_senders=("cv0", "cv1")))
    for k in range(3):
        again.receive(encode(prior("cv0", seq=k, t=0.1 * k, pose=(0.5 * k, 0, 0, 0, 0, 0))), 0.1 * k)
    assert again.fuse(0.1, 0.02).payload() == f.payload()
    assert np.allclose(f.state.vehicle_pose[0, :2], [0.5, 0.0], atol=0.05)


def test_a_core_defect_in_ingest_propagates_but_the_payload_counts_for_the_next_solve(monkeypatch) -> None:
    loop = build_host(HostSetup(fleet="f", known_senders=("cv0",)))

    def broken(payload, t_recv):
        raise OverflowError("a defect")

    monkeypatch.setattr(loop.core, "ingest", broken)
    with pytest.raises(OverflowError):
        loop.receive(encode(prior("cv0", seq=3, t=0.0)), 0.0)
    monkeypatch.undo()
    loop.receive(encode(prior("cv0", seq=4, t=0.1)), 0.1)
    f = loop.step(0.1)
    assert f is not None and [i[1] for i in f.inputs] == [3, 4]


def test_the_host_flags_make_the_setup_and_a_bad_params_file_is_a_config_error(tmp_path) -> None:
    (tmp_path / "p.yaml").write_text("window_s: 2.0\n")
    s = host_setup_from_args(
        _args("--mode", "centralized", "--map", "m.osm", "--local", "cv0", "--known-senders", "cv0,cv1,",
              "--max-wait", "0.3", "--params", str(tmp_path / "p.yaml")),  # fmt: skip
        "fl",
        "h1",
    )
    assert (s.fleet, s.host_id, s.mode, s.map_file, s.local, s.known_senders, s.max_wait_s) == (
        "fl", "h1", "centralized", "m.osm", ("cv0",), ("cv0", "cv1"), 0.3
    )  # fmt: skip
    assert s.params.window_s == 2.0 and s.reference == "cv0"
    (tmp_path / "bad.yaml").write_text("track_lag_s: -1\n")
    with pytest.raises(ConfigError, match="track_lag_s"):
        host_setup_from_args(_args("--params", str(tmp_path / "bad.yaml")), "fl", "h1")
    with pytest.raises(ValidationError):
        HostSetup(fleet="f", max_wait_s=-1.0)


def test_the_host_service_needs_a_map_file_in_centralized_mode_only(tmp_path) -> None:
    from services.host.app import parse_args

    assert parse_args(["--fleet", "f"]).host.map_file is None  # distributed: no map
    with pytest.raises(ValidationError, match="--map"):
        parse_args(["--fleet", "f", "--mode", "centralized"])
    with pytest.raises(ValidationError, match="no such file"):
        parse_args(["--fleet", "f", "--mode", "centralized", "--map", str(tmp_path / "none.geojson")])
    path = save_map(generate_map(load_scenario("overlap").map), tmp_path / "m.geojson")
    s = parse_args(["--fleet", "f", "--id", "h", "--mode", "centralized", "--map", str(path), "--local", "cv0"])
    assert (s.host.fleet, s.host.host_id, s.host.map_file, s.host.local) == ("f", "h", str(path), ("cv0",))


def test_the_observers_repeated_error_is_added_to_an_objects_covariance_with_its_share() -> None:
    """observer_bias: a translation bias S of the only observer adds S; a yaw bias sigma adds (r sigma)^2
    across the line of sight at range r; two observers with half the detections each add a quarter each."""
    from mapcontainer.fusion.hostcore import observer_bias, observer_weights

    S_t = np.diag([0.1, 0.2, 0.05, 0.0, 0.0, 0.0]) ** 2
    pose = np.array([5.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(observer_bias([25.0, 1.0, 0.0], [(pose, S_t, 1.0)]), S_t[:3, :3], atol=1e-15)
    S_yaw = np.diag([0, 0, 0, 0, 0, 0.01]) ** 2
    np.testing.assert_allclose(observer_bias([25.0, 1.0, 0.0], [(pose, S_yaw, 1.0)]), np.diag([0, 0.2**2, 0]), atol=1e-12)
    two = observer_bias([25.0, 1.0, 0.0], [(pose, S_t, 0.5), (pose + [0, 3, 0, 0, 0, 0], S_t, 0.5)])
    np.testing.assert_allclose(two, 0.5 * S_t[:3, :3], atol=1e-15)
    w = observer_weights({("cv0", 1): 0.1, ("cv0", 2): 0.2, ("cv1", 2): 0.2, ("cv1", -5): -0.5}, t_min=0.0)
    assert w == {"cv0": 2 / 3, "cv1": 1 / 3}


def test_the_persistent_part_of_an_observers_detection_error_is_added_rotated_to_the_map() -> None:
    """The part of a detection's error that persists (detector.errors.persistent_fraction of the sensor profile)
    does not average out over one observer's detections: observer_bias adds w^2 R D R^T, D its body-frame
    covariance; persistent_share is f times the variance of the mean of a Gauss-Markov process over the window
    (the whole of it for a window much shorter than its correlation time, nothing for a much longer one)."""
    from mapcontainer.fusion import FusionParams
    from mapcontainer.fusion.hostcore import observer_bias, persistent_share

    pose = np.array([5.0, 1.0, 0.0, 0.0, 0.0, np.pi / 2])  # heading north: body x is map y
    D = np.diag([0.3, 0.1, 0.05]) ** 2
    got = observer_bias([5.0, 21.0, 0.0], [(pose, np.zeros((6, 6)), 0.5, D)])
    np.testing.assert_allclose(got, 0.25 * np.diag([0.1, 0.3, 0.05]) ** 2, atol=1e-15)
    assert persistent_share(FusionParams(window_s=0.01, detection_persistence_s=100.0)) == pytest.approx(0.5, rel=1e-3)
    assert persistent_share(FusionParams(window_s=100.0, detection_persistence_s=0.01)) < 1e-3
    assert persistent_share(FusionParams(detection_persistent_fraction=0.0)) == 0.0
    x = 1.0 / 2.0
    assert persistent_share(FusionParams(window_s=1.0, detection_persistence_s=2.0)) == pytest.approx(
        0.5 * 2 * (x - 1 + np.exp(-x)) / x**2
    )
