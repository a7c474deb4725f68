"""``mapc experiment network --live``: one profile on the live fleet, its rows and the side-by-side."""

from __future__ import annotations

import csv
import json

import pytest

from mapcontainer.experiments.network import NETWORK_COLUMNS
from services.launcher.live_experiment import COMPARE_METRICS

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _csv(path):
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return rows


def test_live_network_one_profile_writes_the_sweep_table_and_the_comparison(tmp_path, mapc):
    out = tmp_path / "live"
    proc = mapc(
        "experiment", "network", "--live", "--out", str(out), "--profiles", "ideal", "--mode", "distributed",
        "--duration", "6", "--vehicles", "2", "--quiet",
        timeout=400,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {
        "out": str(out),
        "live_points": 1,
        "inprocess_points": 1,
    }
    for name in ("network.csv", "network.md", "results.json", "network_latency.png", "network_bandwidth.png"):
        assert (out / name).is_file(), name
    for name in ("live_vs_inprocess.csv", "live_vs_inprocess.md", "live_vs_inprocess.png"):
        assert (out / name).is_file(), name

    rows = _csv(out / "network.csv")
    assert len(rows) == 1
    assert set(NETWORK_COLUMNS) <= set(rows[0]) and {"e2e_latency_ms_p50", "e2e_latency_ms_p99"} <= set(rows[0])
    r = rows[0]
    assert (r["source"], r["profile"], r["mode"]) == ("live", "ideal", "distributed")
    assert float(r["bytes_per_s_per_vehicle"]) > 0
    assert float(r["vehicle_rmse_m"]) >= 0 and float(r["e2e_latency_ms_p50"]) > 0
    assert 0.9 <= float(r["delivered_fraction"]) <= 1.0  # ideal link

    cmp_rows = _csv(out / "live_vs_inprocess.csv")
    assert len(cmp_rows) == 1 and (cmp_rows[0]["profile"], cmp_rows[0]["mode"]) == ("ideal", "distributed")
    for k, _ in COMPARE_METRICS:
        assert {f"{k}_live", f"{k}_inprocess"} <= set(cmp_rows[0])
        assert cmp_rows[0][f"{k}_inprocess"] != ""
    assert "| ideal | distributed |" in (out / "live_vs_inprocess.md").read_text()


def test_live_network_rejects_an_unknown_profile(tmp_path, mapc):
    proc = mapc("experiment", "network", "--live", "--out", str(tmp_path), "--profiles", "nope", timeout=60)
    assert proc.returncode == 2 and "unknown network profile" in proc.stderr
