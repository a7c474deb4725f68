"""``mapc view`` in a real browser: headless Chromium loads the page Rerun's wheel serves and draws the map
and the vehicles, which move as a recording plays at its pace."""

from __future__ import annotations

import contextlib
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun", reason="mapc view needs the view extra (rerun-sdk)")
pytest.importorskip("playwright", reason="the browser test needs the browser extra (playwright)")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [
    pytest.mark.integration,
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine (.ci/run installs Debian's)"),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _recording(path: Path) -> None:
    from mapcontainer.fusion.hostcore import fused_state
    from mapcontainer.recording import RecordingWriter
    from schemas import GroundTruth, HealthStatus, encode

    w = RecordingWriter(path, metadata={"fleet": "f", "scenario": "paper-urban"})
    t0 = time.time_ns()
    pose_cov = np.diag([0.5, 0.5, 0.1, 0.01, 0.01, 0.02])
    for k in range(150):
        t, ns = 0.1 * k, t0 + k * 100_000_000
        poses = np.array([[-60 + 8 * t, -40, 0, 0, 0, 0], [60 - 8 * t, 40, 0, 0, 0, np.pi]])
        env = dict(fleet="f", seq=k, t_meas=t, t_sent=t)
        v = np.zeros((2, 3), np.float32)
        truth = GroundTruth(**env, sender="world", vehicle_ids=["cv0", "cv1"], vehicle_pose=poses, vehicle_v_map=v)
        w.add("mc/f/sim/truth", encode(truth), None, ns)
        est = poses + [0.5, 0.3, 0, 0, 0, 0]
        obj, obj_cov = [[0.0, -30.0 + 2 * t, 0.0]], [np.diag([1.0, 0.5, 0.1])]
        fused = fused_state("f", "host", k + 1, t, ["cv0", "cv1"], est, [pose_cov] * 2, [7], [1], obj, [[0, 2, 0]],
                            obj_cov, 10, [])  # fmt: skip
        w.add("mc/f/host/host/fused", encode(fused), None, ns + 50_000_000)
        if k % 10 == 0:
            h = HealthStatus(fleet="f", sender="host", seq=k, t_meas=t, t_sent=t, role="host", state="ok", uptime_s=t)
            w.add("mc/f/health/host/host", encode(h), None, ns)
    w.close()


def _mask(img: np.ndarray, kind: str) -> np.ndarray:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    if kind == "lane":  # COLORS["lane"], teal
        return (r < 60) & (g > 100) & (b > 100) & (np.abs(g - b) < 40)
    if kind == "truth":  # green boxes
        return (g > 140) & (r < 110) & (b < 110) & (g - r > 60)
    if kind == "fused":  # orange boxes
        return (r > 190) & (g > 70) & (g < 180) & (b < 80)
    raise ValueError(kind)


@contextlib.contextmanager
def _view_page(tmp_path: Path, spawn, wait_for, rec: Path, *flags: str):
    """``mapc view --file rec *flags`` and headless Chromium on its page: yields (page, shoot, shots, the view's
    process); ``shoot()`` takes a screenshot (its file appended to ``shots``) and returns its 3-D view as RGB."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    web, grpc = _free_port(), _free_port()
    proc = spawn("services.cli", "view", "--file", str(rec), *flags, "--web-port", str(web), "--grpc-port",
                 str(grpc), "--exit-after", "120")  # fmt: skip
    line = wait_for(lambda: next((x for x in proc.log_path.read_text().splitlines() if "open http" in x), None), 60,
                    "the view's address")  # fmt: skip
    url = line.split("open ", 1)[1].split()[0]
    shots: list[Path] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        )
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.set_default_timeout(90_000)  # a software-rendered page on a loaded machine
        page.goto(url)

        def shoot() -> np.ndarray:
            path = tmp_path / f"shot-{len(shots)}.png"
            page.screenshot(path=str(path))
            shots.append(path)
            return np.asarray(Image.open(path).convert("RGB"))[60:760, : int(1280 * 0.72)]  # the 3-D view

        try:
            yield page, shoot, shots, proc
        finally:
            browser.close()


def test_the_view_draws_the_map_and_vehicles_that_move(tmp_path, spawn, wait_for) -> None:
    rec = tmp_path / "rec.mcap"
    _recording(rec)
    with _view_page(tmp_path, spawn, wait_for, rec, "--paced") as (page, shoot, shots, _):

        def scene() -> tuple[np.ndarray] | None:
            img = shoot()
            return (img,) if _mask(img, "lane").sum() > 200 and _mask(img, "truth").sum() > 10 else None

        (first,) = wait_for(scene, 60, "the map and the vehicles on the page", every=1.0)
        time.sleep(3.0)
        second = (scene() or (None,))[0]
        title = page.title()
    assert second is not None, f"the scene went away: {shots[-1]}"
    assert "rerun" in title.lower()
    for img in (first, second):
        assert _mask(img, "lane").sum() > 200 and _mask(img, "truth").sum() > 10 and _mask(img, "fused").sum() > 10

    def centroid(img: np.ndarray) -> np.ndarray:
        return np.argwhere(_mask(img, "truth")).mean(axis=0)

    moved = np.linalg.norm(centroid(second) - centroid(first))
    assert moved > 2.0, f"the true vehicles did not move on the page ({moved:.1f} px): {shots[-2]}, {shots[-1]}"


def _downlink_recording(path: Path) -> None:
    """Two parked vehicles 60 m apart, each receiving the host's downlink (the others' view of its position, 3 m
    good): cv0's priors say its gate refused it, cv1's that it fused it. No map: nothing else red or cyan."""
    from unit.test_fusion_container import prior

    from mapcontainer.recording import RecordingWriter
    from schemas import GroundTruth, encode
    from schemas.arrays import cov_to_upper
    from schemas.models import PoseDownlink

    w = RecordingWriter(path, metadata={"fleet": "f"})
    t0 = time.time_ns()
    poses = np.array([[-30.0, 0, 0, 0, 0, 0], [30.0, 0, 0, 0, 0, 0]])
    info6 = np.zeros((6, 6))
    info6[:2, :2] = np.eye(2) / 9.0
    for k in range(20):
        t, ns = 0.1 * k, t0 + k * 100_000_000
        env = dict(fleet="f", seq=k, t_meas=t, t_sent=t)
        v = np.zeros((2, 3), np.float32)
        truth = GroundTruth(**env, sender="world", vehicle_ids=["cv0", "cv1"], vehicle_pose=poses, vehicle_v_map=v)
        w.add("mc/f/sim/truth", encode(truth), None, ns)
        for i, (vid, status) in enumerate((("cv0", "refused"), ("cv1", "fused"))):
            dl = PoseDownlink(**env, sender="host", target=vid, pose=poses[i] + [0, 8, 0, 0, 0, 0],
                              pose_info=cov_to_upper(info6).astype(np.float32))  # fmt: skip
            w.add(f"mc/f/v2x/rx/{vid}/host/downlink", encode(dl), None, ns + 10_000_000)
            p = prior(sender=vid, seq=k, t=t, pose=poses[i]).model_copy(update={"downlink": status})
            w.add(f"mc/f/v2x/tx/{vid}/prior", encode(p), None, ns + 20_000_000)
    w.close()


def _downlink_mask(img: np.ndarray, kind: str) -> np.ndarray:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    if kind == "used":  # COLORS["downlink_used"], cyan: blue above green, little red
        return (r < 90) & (b > 150) & (b - g > 25) & (g > 90)
    if kind == "refused":  # COLORS["downlink_refused"], red
        return (r > 150) & (g < 70) & (b < 70)
    raise ValueError(kind)


def test_the_view_draws_each_vehicles_downlink_used_or_refused(tmp_path, spawn, wait_for) -> None:
    rec = tmp_path / "downlink.mcap"
    _downlink_recording(rec)
    with _view_page(tmp_path, spawn, wait_for, rec) as (_, shoot, shots, proc):

        def scene() -> tuple[np.ndarray] | None:
            img = shoot()
            ok = all(_downlink_mask(img, k).sum() > 30 for k in ("used", "refused")) and _mask(img, "truth").sum() > 10
            return (img,) if ok else None

        (img,) = wait_for(scene, 60, "both vehicles' downlinks on the page", every=1.0)
    drawn = wait_for(lambda: next((x for x in proc.log_path.read_text().splitlines() if x.startswith("drawn: ")), None),
                     30, "what the view drew")  # fmt: skip
    assert '"downlink": 42' in drawn, drawn  # 40 arrivals and the first prior of each vehicle recolouring it

    # the refused ellipse is cv0's (at x = -30 m: left of cv1's on the page, as the true boxes are)
    def cx(mask: np.ndarray) -> float:
        return float(np.argwhere(mask)[:, 1].mean())

    truth = np.argwhere(_mask(img, "truth"))[:, 1]
    mid = 0.5 * (truth.min() + truth.max())  # between the two boxes (60 m apart; the nearer one is larger)
    left, right = truth[truth < mid].mean(), truth[truth >= mid].mean()
    assert cx(_downlink_mask(img, "refused")) < cx(_downlink_mask(img, "used")), shots[-1]
    assert abs(cx(_downlink_mask(img, "refused")) - left) < abs(cx(_downlink_mask(img, "refused")) - right), shots[-1]
