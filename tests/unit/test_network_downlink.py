"""mapcontainer.experiments.network_downlink: the sweep's twins (each distributed point without and with the
downlink), the gain per link and its section of the report, on synthetic rows."""

from __future__ import annotations

import math

from mapcontainer.experiments.network import _bw_label, _cell, write_network_outputs
from mapcontainer.experiments.network_downlink import gains, section, twins


def _row(mode: str, latency_ms: float, loss: float, downlink: str | None, onboard: float) -> dict:
    r = {
        "mode": mode,
        "latency_ms": latency_ms,
        "loss": loss,
        "bandwidth_bps": 6e6,
        "vehicle_rmse_m": 0.3,
        "object_rmse_m": 0.4,
        "bytes_per_s_per_vehicle": 3300.0,
        "delivered_fraction": 1.0 - loss,
    }
    if downlink is not None:
        r.update(
            downlink=downlink,
            onboard_rmse_m=onboard,
            onboard_anees_2dof=2.0,
            down_bytes_per_s_per_vehicle=2000.0 * (1 - loss) if downlink == "on" else 0.0,
            downlink_fused_fraction=0.8 if downlink == "on" else math.nan,
            downlink_refused_fraction=0.1 if downlink == "on" else math.nan,
            downlink_stale_fraction=0.05 if downlink == "on" else math.nan,
        )
    return r


def test_twins_run_each_distributed_point_without_and_with_the_downlink_from_the_same_seed() -> None:
    tasks = [
        (0.0, 0.0, 6e6, "distributed", 3, 2.5, "paper-urban", 1.0),
        (0.0, 0.0, 6e6, "centralized", 3, 2.5, "x", 1.0),
    ]
    assert twins(tasks) == [(*tasks[0], False), (*tasks[0], True), tasks[1]]


def test_the_gain_per_link_is_without_minus_with(tmp_path) -> None:
    rows = [
        _row("distributed", 0.0, 0.0, "off", 0.40),
        _row("distributed", 0.0, 0.0, "on", 0.25),
        _row("distributed", 200.0, 0.5, "off", 0.40),
        _row("distributed", 200.0, 0.5, "on", 0.35),
        _row("distributed", 500.0, 0.5, "off", 0.40),  # no twin: not in the table
        _row("centralized", 0.0, 0.0, None, math.nan),
    ]
    g = gains(rows)
    assert [(x["latency_ms"], x["loss"], x["onboard_gain_m"]) for x in g] == [(0.0, 0.0, 0.15), (200.0, 0.5, 0.05)]
    assert g[1]["down_bytes_per_s_per_vehicle"] == 1000.0 and g[0]["downlink_refused_fraction"] == 0.1
    text = section(rows, _cell, _bw_label)
    assert text[0] == "## The downlink"
    table = [line for line in text if line.startswith("| 0 |") or line.startswith("| 200 |")]
    assert table[0].startswith("| 0 | 0 | 6 Mbit/s | 0.4 | 0.25 | 0.15 | 2 / 2 |")
    assert table[1].startswith("| 200 | 0.5 | 6 Mbit/s | 0.4 | 0.35 | 0.05 |") and "| 1000 |" in table[1]
    assert section([r for r in rows if r.get("downlink") != "on"], _cell, _bw_label) == []

    paths = write_network_outputs(rows, tmp_path, {"seed": 3})
    md = paths["md"].read_text()
    assert "## The downlink" in md and "| mode | downlink |" in md
    assert paths["png_downlink"].read_bytes()[:4] == b"\x89PNG"
    # the summary is of the points without the downlink: one distributed row at the best link
    summary = md.split("## Key comparison")[1].split("## All points")[0]
    assert summary.count("| distributed |") == 1


def test_without_the_downlink_the_outputs_have_no_downlink_section(tmp_path) -> None:
    rows = [_row("distributed", 0.0, 0.0, None, math.nan), _row("centralized", 0.0, 0.0, None, math.nan)]
    paths = write_network_outputs(rows, tmp_path, {"seed": 3})
    md = paths["md"].read_text()
    assert "downlink" not in md and "png_downlink" not in paths
