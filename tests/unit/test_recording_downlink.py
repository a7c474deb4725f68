"""The downlink in recordings, replay and the view: a recording keeps the host's downlink on both keys (to the
channel, and from it to the vehicle) as signed PoseDownlink messages; replay publishes them verified on the target
fleet when asked; the view draws, for the vehicle that received one, the others' estimate of its position with its
uncertainty, coloured by what the vehicle said it did with it (used or refused), and refuses what its host did not
sign or what is about another vehicle."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from mapcontainer.recording import RecordingWriter, info, read_records
from mapcontainer.recording.replay import replay_plan
from mapcontainer.security import Signer, issue, make_ca
from schemas import encode
from schemas.arrays import cov_to_upper
from schemas.codec import decode, peek
from schemas.models import PoseDownlink
from schemas.topics import topic


def downlink(target: str, t: float, xy=(10.0, -4.0), sigma=(0.5, 2.0), yaw: float = 0.0, seq: int = 0) -> PoseDownlink:
    """The others' view of ``target``: position ``xy`` with 1-sigmas ``sigma`` along axes turned by ``yaw``, nothing
    known of the other four numbers."""
    c, s = math.cos(yaw), math.sin(yaw)
    U = np.array([[c, -s], [s, c]])
    info6 = np.zeros((6, 6))
    info6[:2, :2] = U @ np.diag(1.0 / np.square(sigma)) @ U.T
    return PoseDownlink(
        fleet="f", sender="host", seq=seq, t_meas=t, t_sent=t + 0.05, target=target,
        pose=np.array([*xy, 0.0, 0.0, 0.0, 0.3], np.float32), pose_info=cov_to_upper(info6).astype(np.float32),
    )  # fmt: skip


def _recording(tmp_path: Path, frames: int = 4) -> tuple[Path, dict]:
    """A signed fleet's downlink to cv1 on the host's key to the channel and on the channel's key to cv1, and cv1's
    priors saying what it did with it (fused, then refused)."""
    from unit.test_fusion_container import prior

    now = time.time()
    ca = make_ca("ca", now=now - 60)
    signers = {v: Signer(issue(ca, v, 3600, now - 60)) for v in ("host", "cv1")}
    (tmp_path / "ca.cert.json").write_text(ca.certificate.model_dump_json())
    path = tmp_path / "dl.mcap"
    w = RecordingWriter(path, files={"ca.cert.json": (tmp_path / "ca.cert.json").read_bytes()})
    t0 = time.time_ns()
    for k in range(frames):
        t, ns = 0.1 * k, t0 + k * 100_000_000
        signed = signers["host"].sign(encode(downlink("cv1", t, seq=k)), time.time())
        w.add("mc/f/v2x/tx/host/downlink/cv1", signed, None, ns)
        w.add("mc/f/v2x/rx/cv1/host/downlink", signed, None, ns + 20_000_000)
        status = "fused" if k < frames - 1 else "refused"
        p = prior(sender="cv1", seq=k, t=t + 0.1).model_copy(update={"downlink": status})
        w.add("mc/f/v2x/tx/cv1/prior", signers["cv1"].sign(encode(p), time.time()), None, ns + 30_000_000)
    w.close()
    return path, signers


def test_a_recording_keeps_the_downlink_of_both_keys_and_replay_publishes_it_verified(tmp_path: Path) -> None:
    path, _ = _recording(tmp_path)
    channels = {c["topic"]: c for c in info(path)["channels"]}
    for key in ("mc/f/v2x/tx/host/downlink/cv1", "mc/f/v2x/rx/cv1/host/downlink"):
        assert channels[key]["schema"] == "SecuredMessage"
        assert channels[key]["metadata"]["inner_model"] == "PoseDownlink"
    assert sum(topic("downlink_rx").parse(r.key) is not None for r in read_records(path)) == 4

    items, fig = replay_plan(path, "other", topics=("downlink_tx", "downlink_rx"))
    assert fig["signatures_verified"] and fig["refused_signatures"] == 0 and fig["messages"] == 8
    assert {it.key for it in items} == {"mc/other/v2x/tx/host/downlink/cv1", "mc/other/v2x/rx/cv1/host/downlink"}
    for it in items:
        assert "payload" not in peek(it.payload)  # verified and unwrapped
        m = decode(it.payload, PoseDownlink)
        assert m.fleet == "other" and m.target == "cv1" and m.sender == "host"


def test_the_downlink_ellipse_has_the_others_sigmas_at_two_sigma_and_caps_what_they_do_not_know() -> None:
    from mapcontainer.recording.view import DOWNLINK_MAX_SIGMA_M, downlink_ellipse

    centre, half, q = downlink_ellipse(downlink("cv1", 0.0, sigma=(0.5, 2.0), yaw=0.4))
    assert centre == pytest.approx([10.0, -4.0, 0.0])
    assert sorted(half[:2]) == pytest.approx([1.0, 4.0]) and half[2] == pytest.approx(0.05)
    # the long axis (2 sigma = 4 m) points at 0.4 + pi/2 (mod pi): turn the x axis by the quaternion
    x, y, z, w = q
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip
    long_axis = R[:, int(np.argmax(half))]
    assert abs(long_axis[:2] @ [math.cos(0.4 + math.pi / 2), math.sin(0.4 + math.pi / 2)]) == pytest.approx(
        1.0, abs=1e-5
    )
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)
    m = downlink("cv1", 0.0)
    info6 = np.zeros((6, 6))
    info6[0, 0] = 4.0  # x known to 0.5 m, y not at all
    m = m.model_copy(update={"pose_info": cov_to_upper(info6).astype(np.float32)})
    _, half, _ = downlink_ellipse(m)
    assert sorted(half[:2]) == pytest.approx([1.0, 2 * DOWNLINK_MAX_SIGMA_M])


def test_the_view_draws_the_downlink_a_vehicle_received_coloured_by_what_it_did_with_it(tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun", reason="mapc view needs the view extra (rerun-sdk)")
    from mapcontainer.recording.replay import _verifier
    from mapcontainer.recording.view import RerunView

    path, signers = _recording(tmp_path)
    view = RerunView(rr.RecordingStream("test-view-downlink"), _verifier(path))
    seen = []
    for r in read_records(path):
        view.handle(r.key, r.payload, r.log_time_ns)
        seen.append(view.downlink_status.get("cv1"))
    # drawn on each arrival at cv1 (4) and when its prior changed what it did (fused, then refused): the host's key
    # to the channel is not what the vehicle received
    assert view.drawn["downlink"] == 4 + 2 and set(view.downlinks) == {"cv1"} and view.refused == {}
    assert seen[:3] == [None, None, "fused"] and seen[-1] == "refused"

    # a downlink its host did not sign, or one about cv0 on cv1's key: refused, counted, not drawn
    unsigned = encode(downlink("cv1", 1.0, xy=(50.0, 50.0)))
    assert not view.handle("mc/f/v2x/rx/cv1/host/downlink", unsigned, time.time_ns())
    wrong = signers["host"].sign(encode(downlink("cv0", 1.0)), time.time())
    assert not view.handle("mc/f/v2x/rx/cv1/host/downlink", wrong, time.time_ns())
    assert view.refused == {"unsigned": 1, "wrong_target": 1} and view.drawn["downlink"] == 6
    assert view.downlinks["cv1"].pose[0] == pytest.approx(10.0)
