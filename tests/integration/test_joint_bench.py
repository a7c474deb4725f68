"""`mapc bench fusion --host joint`: the centralized host on recorded raw observations, end to end (a fixed
development seed; no wall-clock bounds)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def _mapc(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapcontainer.cli", *args], capture_output=True, text=True, timeout=900, check=False
    )


def test_bench_fusion_joint_prints_timing_phases_accuracy_and_the_yardstick():
    proc = _mapc("bench", "fusion", "--host", "joint", "--vehicles", "2", "--ticks", "40", "--seed", "3")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["host"] == "joint" and r["vehicles"] == 2 and r["scenario"] == "sumo-town"
    assert r["frames_timed"] == 10  # 4 s, timed from 3 s
    for key in ("cycle_ms_p50", "cycle_ms_p99", "cycle_cpu_ms_p50", "yardstick_ms_p50", "cycle_over_yardstick"):
        assert math.isfinite(r[key]) and r[key] > 0, key
    phases = r["phases_cpu_ms_p50"]
    assert {"localize", "condition", "update", "output"} <= phases.keys()
    assert all(math.isfinite(ms) and ms >= 0 for ms in phases.values())
    assert r["vehicle_rmse_m"] < 1.0 and r["vehicle_anees"] < 30.0
    assert r["numerical_failure"] == 0 and r["localizer_failure"] == 0


def test_bench_fusion_joint_refuses_what_it_cannot_do():
    short = _mapc("bench", "fusion", "--host", "joint", "--ticks", "20")
    assert short.returncode == 2 and "--ticks must exceed 30" in short.stderr
    oracle = _mapc("bench", "fusion", "--host", "joint", "--compare-exact")
    assert oracle.returncode == 2 and "--compare-exact" in oracle.stderr
