"""The scaling experiment's analysis and outputs on rows of known shape (the runs: tests/integration)."""

from __future__ import annotations

import csv
import json

import pytest

from mapcontainer.experiments.scale import (
    SCALE_COLUMNS,
    analyse,
    fit_exponent,
    scenario_with_connected,
    write_scale_outputs,
)


def _rows() -> list[dict]:
    """Distributed host cost linear in N and no drops; centralized quadratic, dropping from N = 32."""
    rows = []
    for n in (2, 4, 8, 16, 32, 50):
        for mode, cpu, drops in (("distributed", 2.0 * n, 0.0), ("centralized", 0.5 * n * n, 0.2 if n >= 32 else 0.0)):
            row = dict.fromkeys(SCALE_COLUMNS, 0.0)
            row.update(mode=mode, vehicles=n, host_cpu_ms_per_cycle=cpu, fuse_cpu_ms_p50=cpu / 2,
                       bytes_per_s_total=(300.0 if mode == "distributed" else 1400.0) * 10 * (n - 1),
                       dropped_queue_fraction=drops, delivered_fraction=0.985 - drops, scenario="s")  # fmt: skip
            rows.append(row)
    return rows


def test_fit_exponent_recovers_a_power_law_and_skips_what_it_cannot_fit():
    assert fit_exponent([1, 2, 4, 8], [3, 12, 48, 192]) == pytest.approx(2.0)
    assert fit_exponent([1, 2, 4], [5.0, float("nan"), 20.0]) == pytest.approx(1.0)
    assert fit_exponent([1], [1.0]) is None


def test_analysis_names_the_growth_and_the_saturation_of_each_mode():
    a = analyse(_rows())
    assert a["distributed"]["host_cpu_exponent"] == pytest.approx(1.0)
    assert a["centralized"]["host_cpu_exponent"] == pytest.approx(2.0)
    assert a["distributed"]["saturation_vehicles"] is None and a["centralized"]["saturation_vehicles"] == 32
    # 10 Hz: 2 N <= 100 ms everywhere (to 50); 0.5 N^2 <= 100 ms to N = 8 (16 -> 128 ms)
    assert a["distributed"]["realtime_vehicles"] == 50 and a["centralized"]["realtime_vehicles"] == 8


def test_outputs_are_a_table_a_report_with_the_claim_and_two_plots(tmp_path):
    meta = {"scenario": "s", "seed": 1, "duration_s": 10, "warmup_s": 3, "host_compiled": True}
    paths = write_scale_outputs(_rows(), tmp_path, meta)
    with paths["csv"].open() as f:
        table = list(csv.DictReader(f))
    assert len(table) == 12 and list(table[0]) == list(SCALE_COLUMNS)
    md = paths["md"].read_text()
    assert "N^1.00 distributed and N^2.00 centralized" in md
    assert "distributed not within N <= 50, centralized from N = 32" in md
    assert "distributed up to N = 50, centralized up to N = 8; the host's inner loops compiled (numba)" in md
    doc = json.loads(paths["json"].read_text())
    assert doc["analysis"]["centralized"]["saturation_vehicles"] == 32 and len(doc["rows"]) == 12
    for key in ("png_cost", "png_channel"):
        assert paths[key].stat().st_size > 10_000


def test_only_a_sumo_scenario_scales():
    with pytest.raises(ValueError, match="SUMO scenario"):
        scenario_with_connected("paper-urban", 8)


def test_a_sumo_scenario_gets_its_first_n_vehicles_connected():
    pytest.importorskip("sumolib")  # a SUMO preset's map needs the roads extra
    sc = scenario_with_connected("sumo-grid", 7)
    assert sc.n_connected == 7 and sc.sumo.connected.first == 7 and sc.name == "sumo-grid"
