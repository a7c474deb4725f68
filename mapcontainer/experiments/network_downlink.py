"""The network sweep with the downlink (``mapc experiment network --downlink``): what the link's latency, loss and
capacity do to the downlink's gain.

With the option, every distributed point of the grid runs twice from the same seed: without the host's downlink
and with it (docs/downlink.md). The downlink travels the same emulated link as the uplink (host -> each vehicle:
the point's latency, loss and per-link capacity; signed like the priors), so a late or lost downlink is a stale or
missing one on board. The centralized points have no downlink and run once.

Row keys added to both twins (:func:`downlink_figures`, after ``NETWORK_COLUMNS``):

* ``downlink``: "off" or "on";
* ``onboard_rmse_m``: horizontal RMSE of every vehicle's on-board estimate (its own, with the downlink fused when
  on) over the scored frames; ``onboard_missing``: scored vehicle-frames without an on-board pose (not in it);
* ``onboard_anees_2dof``: the mean NEES of that horizontal position (2 dof: a consistent estimator averages 2);
* ``down_bytes_per_s_per_vehicle``: downlink bytes on the air per second per receiving vehicle (the ego's stays on
  board), signed; ``down_msgs_per_s_per_vehicle``; the uplink's are ``bytes_per_s_per_vehicle``;
* ``downlink_fused_fraction``, ``downlink_refused_fraction``, ``downlink_stale_fraction``: the scored
  vehicle-frames in which the vehicle fused a downlink (also by covariance intersection), refused one (its gate), or
  had only one too old to use.

:func:`section` writes the report's table: per link, the on-board RMSE without and with the downlink and the gain
(without minus with, in metres: positive when the downlink helps).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..evaluation import horizontal_sq_error, rmse_sq, vehicle_pose
from ..jsonout import rounded
from ..metrics import nees
from ..pipeline import PipelineResult

__all__ = ["downlink_figures", "gains", "plot", "point_args", "section", "twins"]


def downlink_figures(res: PipelineResult, warmup_s: float) -> dict[str, Any]:
    """A run's row keys of the module docstring, over its frames from ``warmup_s`` on."""
    sq, nis, statuses = [], [], []
    missing = 0
    for rec in res.records:
        if rec.t < warmup_s - 1e-9:
            continue
        for vid in rec.truth.vehicle_ids:
            p, cov = rec.onboard.get(vid), rec.onboard_covs.get(vid)
            if p is None:
                missing += 1
                continue
            p_true = vehicle_pose(rec.truth, vid)
            sq.append(horizontal_sq_error(p, p_true))
            if cov is not None:
                e = np.asarray(p, float)[:2] - p_true[:2]
                nis.append(float(nees(e, np.asarray(cov, float)[:2, :2])[0]))
            statuses.append(rec.downlink.get(vid, "none"))
    receivers = max(1, len(res.records[0].truth.vehicle_ids) - 1) if res.records else 1  # all but the ego
    seconds = res.duration_s or 1.0
    n = len(statuses)

    def frac(*names: str) -> float:
        return rounded(sum(s in names for s in statuses) / n) if res.downlink and n else float("nan")

    return {
        "downlink": "on" if res.downlink else "off",
        "onboard_rmse_m": rounded(rmse_sq(sq)),
        "onboard_missing": missing,
        "onboard_anees_2dof": rounded(float(np.mean(nis))) if nis else float("nan"),
        "down_bytes_per_s_per_vehicle": rounded(sum(res.rx_bytes.values()) / seconds / receivers, 1),
        "down_msgs_per_s_per_vehicle": rounded(sum(res.rx_msgs.values()) / seconds / receivers, 2),
        "downlink_fused_fraction": frac("fused", "fused_ci"),
        "downlink_refused_fraction": frac("refused"),
        "downlink_stale_fraction": frac("stale"),
    }


def twins(tasks: list[tuple]) -> list[tuple]:
    """The sweep's point tasks with each distributed point twice, from the same seed: without and with the downlink
    (a ninth element); the centralized points once, after them."""
    dist = [t + (on,) for t in tasks if t[3] == "distributed" for on in (False, True)]
    return dist + [t for t in tasks if t[3] != "distributed"]


def point_args(downlink: bool, warmup_s: float) -> dict[str, Any]:
    """:func:`~.network.run_network_point`'s arguments of a twin: the downlink off or on, and its figures."""
    return {"downlink": downlink, "extra": functools.partial(downlink_figures, warmup_s=warmup_s)}


def _link(r: dict) -> tuple[float, float, float]:
    return (-float(r["bandwidth_bps"]), float(r["latency_ms"]), float(r["loss"]))


def gains(rows: Sequence[dict]) -> list[dict[str, Any]]:
    """Per distributed link with both twins: the link, the twins' figures side by side and the gain
    ``onboard_gain_m`` = on-board RMSE without minus with the downlink (positive: it helps), in the rows' order."""
    twins: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        if r.get("mode") == "distributed" and r.get("downlink") in ("off", "on"):
            twins.setdefault(_link(r), {})[r["downlink"]] = r
    out = []
    for link in sorted(twins):
        t = twins[link]
        if set(t) != {"off", "on"}:
            continue
        off, on = t["off"], t["on"]
        out.append(
            {
                "latency_ms": off["latency_ms"],
                "loss": off["loss"],
                "bandwidth_bps": off["bandwidth_bps"],
                "onboard_rmse_off_m": off["onboard_rmse_m"],
                "onboard_rmse_on_m": on["onboard_rmse_m"],
                "onboard_gain_m": rounded(off["onboard_rmse_m"] - on["onboard_rmse_m"]),
                "onboard_anees_off": off["onboard_anees_2dof"],
                "onboard_anees_on": on["onboard_anees_2dof"],
                "vehicle_rmse_off_m": off["vehicle_rmse_m"],
                "vehicle_rmse_on_m": on["vehicle_rmse_m"],
                "object_rmse_off_m": off["object_rmse_m"],
                "object_rmse_on_m": on["object_rmse_m"],
                "up_bytes_per_s_per_vehicle_off": off["bytes_per_s_per_vehicle"],
                "up_bytes_per_s_per_vehicle_on": on["bytes_per_s_per_vehicle"],
                "down_bytes_per_s_per_vehicle": on["down_bytes_per_s_per_vehicle"],
                "downlink_fused_fraction": on["downlink_fused_fraction"],
                "downlink_refused_fraction": on["downlink_refused_fraction"],
                "downlink_stale_fraction": on["downlink_stale_fraction"],
            }
        )
    return out


def section(rows: Sequence[dict], cell, bw_label) -> list[str]:
    """The report's section "The downlink" (nothing without twins); ``cell`` and ``bw_label`` format numbers and
    capacities as the rest of the report does."""
    g = gains(rows)
    if not g:
        return []
    L = [
        "## The downlink",
        "",
        "Each distributed point twice from the same seed, without and with the host's downlink (it crosses the same "
        "link, host -> vehicle: the point's latency, loss and capacity). *On board* = every vehicle's own estimate "
        "(with the downlink fused when on), horizontal RMSE over the scored frames; gain = without minus with "
        "(positive: the downlink helps). ANEES of the on-board horizontal position (2 dof; 2 when consistent). "
        "Bytes per second per vehicle on the air, signed: up (vehicle -> host, without / with) and down (host -> "
        "vehicle). Downlink frames: the fraction of scored vehicle-frames in which the vehicle fused one, refused "
        "one (its gate), or had only one too old to use.",
        "",
        "| latency (ms) | loss | capacity | on-board RMSE off (m) | on (m) | gain (m) | ANEES off / on | fused "
        "vehicle RMSE off / on (m) | object RMSE off / on (m) | up B/s/veh off / on | down B/s/veh | fused / "
        "refused / stale |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in g:
        L.append(
            f"| {cell(x['latency_ms'])} | {cell(x['loss'])} | {bw_label(x['bandwidth_bps'])} | "
            f"{cell(x['onboard_rmse_off_m'])} | {cell(x['onboard_rmse_on_m'])} | {cell(x['onboard_gain_m'])} | "
            f"{cell(x['onboard_anees_off'])} / {cell(x['onboard_anees_on'])} | "
            f"{cell(x['vehicle_rmse_off_m'])} / {cell(x['vehicle_rmse_on_m'])} | "
            f"{cell(x['object_rmse_off_m'])} / {cell(x['object_rmse_on_m'])} | "
            f"{cell(x['up_bytes_per_s_per_vehicle_off'])} / {cell(x['up_bytes_per_s_per_vehicle_on'])} | "
            f"{cell(x['down_bytes_per_s_per_vehicle'])} | {cell(x['downlink_fused_fraction'])} / "
            f"{cell(x['downlink_refused_fraction'])} / {cell(x['downlink_stale_fraction'])} |"
        )
    return [*L, "", "![the downlink's gain](network_downlink.png)", ""]


def plot(rows: Sequence[dict], out: Path, banner) -> dict[str, Path]:
    """The gain against latency, one line per loss, at the highest capacity (nothing without twins); ``banner`` lays
    the figure out as the sweep's other figures."""
    g = gains(rows)
    if not g:
        return {}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bw_top = max(x["bandwidth_bps"] for x in g)
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for loss in sorted({x["loss"] for x in g}):
        pts = sorted((x["latency_ms"], x) for x in g if x["loss"] == loss and x["bandwidth_bps"] == bw_top)
        lat = [p[0] for p in pts]
        ax[0].plot(lat, [p[1]["onboard_gain_m"] for p in pts], "o-", label=f"loss {100 * loss:g} %")
        ax[1].plot(lat, [p[1]["onboard_rmse_on_m"] for p in pts], "o-", label=f"with, loss {100 * loss:g} %")
        ax[1].plot(lat, [p[1]["onboard_rmse_off_m"] for p in pts], "x:", color=ax[1].lines[-1].get_color())
    cap = "unlimited" if not math.isfinite(bw_top) else f"{bw_top / 1e6:g} Mbit/s"
    ax[0].axhline(0.0, color="k", lw=0.8)
    ax[0].set(xlabel="latency (ms)", ylabel="on-board RMSE without - with (m)", title=f"the downlink's gain, {cap}")
    ax[1].set(xlabel="latency (ms)", ylabel="on-board RMSE (m)", title="with (o) and without (x) the downlink")
    for a in ax:
        a.legend(fontsize=7)
    path = out / "network_downlink.png"
    banner(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return {"png_downlink": path}
