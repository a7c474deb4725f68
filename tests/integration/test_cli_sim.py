"""`mapc sim` end to end: a short episode on disk, its summary, its pictures, and reading it back."""

import json
import subprocess
import sys

import numpy as np

from mapcontainer.hdmap.io import load_map
from mapcontainer.sim.episode import read_episode
from schemas import GroundTruth, SensorFrame, encode


def test_mapc_sim_writes_a_readable_episode(tmp_path):
    out = tmp_path / "episode"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapcontainer.cli",
            "sim",
            "paper-urban",
            "--seed",
            "1",
            "--duration",
            "1.0",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["scenario"] == "paper-urban" and summary["seed"] == 1
    assert summary["frames"] == 10 and summary["vehicles"] == 4
    assert summary["obstacles"] == {"vehicle": 6, "pedestrian": 8}
    assert summary["map_features"] == {"lamp": 14, "traffic_light": 4, "sign": 4}
    assert summary["sensor_frame_bytes_mean"] > 0
    for name in ["birdseye.png", "camera_cv0.png", "camera_cv3.png", "map.geojson", "map_true.geojson", "summary.json"]:
        assert (out / name).stat().st_size > 0, name

    records = list(read_episode(out))
    truths = [m for _, _, m in records if isinstance(m, GroundTruth)]
    frames = [m for _, _, m in records if isinstance(m, SensorFrame)]
    assert len(truths) == 10 and len(frames) == 40
    assert {f.sender for f in frames} == {"cv0", "cv1", "cv2", "cv3"}
    assert summary["sensor_frame_bytes_mean"] == round(float(np.mean([len(encode(f)) for f in frames])), 1)
    assert load_map(out / "map_true.geojson").feature_counts() == summary["map_features"]  # the world's
    assert load_map(out / "map.geojson").feature_counts() == summary["published_map_features"]  # the vehicles' map


def test_mapc_scenario_list_and_bad_scenario():
    proc = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", "scenario", "list", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    names = {row["name"] for row in json.loads(proc.stdout)}
    assert "paper-urban" in names and "blindspot-beyond" in names
    bad = subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", "sim", "nope", "--out", "/tmp/never"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "unknown scenario" in bad.stderr
