"""The run's pictures (matplotlib): the bird's-eye view of truth against the fused estimate, and the
error of every vehicle and of the objects over scenario time.

``birdseye.png`` zooms to where the connected vehicles were in the last ``focus_s`` seconds, with an
inset of the whole map; the last seconds are drawn strong and what came before faint. Truth is a wide
pale band, the fused estimate a thin dark line on it, in one colour per vehicle. Covariance ellipses
are 2-sigma, magnified by a stated factor so that decimetre ellipses can be seen on a street-sized view.

``errors.png`` plots each vehicle's horizontal error and the objects' RMSE per fused state against
scenario time (log scale), with the burn-in (the vehicles start cold, from GNSS) shaded.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Ellipse, Rectangle  # noqa: E402
from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter  # noqa: E402

from mapcontainer.hdmap.model import HDMap  # noqa: E402
from schemas import ObjectClass  # noqa: E402
from schemas.arrays import cov_from_upper  # noqa: E402

from .core import Evaluator  # noqa: E402

__all__ = ["ellipse_params", "ellipse_scale", "focus_box", "render_birdseye", "render_errors"]

_VEHICLE_COLORS = ["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]
_OBJECT_COLORS = {int(ObjectClass.PEDESTRIAN): "darkorange", int(ObjectClass.VEHICLE): "navy"}
_NICE = (1, 2, 5, 10, 20, 50, 100, 200, 500)


def ellipse_params(cov2: np.ndarray, n_sigma: float = 2.0) -> tuple[float, float, float]:
    """(width, height, angle_deg) of the n-sigma ellipse of a 2x2 covariance: axes 2 n sqrt(eigenvalues)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov2, float))
    vals = np.clip(vals, 0.0, None)
    angle = float(np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1])))
    return 2 * n_sigma * float(np.sqrt(vals[1])), 2 * n_sigma * float(np.sqrt(vals[0])), angle


def ellipse_scale(widths_m: list[float], view_m: float, target: float = 0.03) -> int:
    """The magnification (1, 2, 5, 10, ...) that draws the median ellipse about ``target`` of the view wide.

    Never below 1: an ellipse that is visible at true size is drawn at true size.
    """
    if not widths_m or view_m <= 0:
        return 1
    want = target * view_m / max(float(np.median(widths_m)), 1e-6)
    return max([k for k in _NICE if k <= want], default=1)


def focus_box(
    xy: np.ndarray, margin_m: float = 15.0, min_size_m: float = 40.0, aspect: float = 1.4
) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the points' bounding box with a margin, at least ``min_size_m`` high, widened or
    heightened to ``aspect`` (width over height) so that it fills the picture."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return (-min_size_m * aspect / 2, min_size_m * aspect / 2, -min_size_m / 2, min_size_m / 2)
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, min_size_m / 2)
    half = np.maximum(half, [half[1] * aspect, half[0] / aspect])
    return (centre[0] - half[0], centre[0] + half[0], centre[1] - half[1], centre[1] + half[1])


def _split(trace, t_from: float) -> tuple[np.ndarray, np.ndarray]:
    """A (t, x, y) trace as (x, y) before and from ``t_from`` (the two parts share their joining point)."""
    a = np.asarray(trace, float).reshape(-1, 3)
    k = int(np.searchsorted(a[:, 0], t_from))
    return a[: k + 1, 1:], a[k:, 1:]


def _draw_map(ax, hdmap: HDMap | None) -> None:
    if hdmap is not None:
        from mapcontainer.sim.render import draw_map

        draw_map(ax, hdmap)


def render_birdseye(path: Path, ev: Evaluator, hdmap: HDMap | None, title: str, focus_s: float = 10.0) -> None:
    """Truth against the fused estimate at the end of the run, zoomed to the vehicles' last ``focus_s`` s."""
    fig = plt.figure(figsize=(13, 8))
    grid = fig.add_gridspec(2, 2, width_ratios=[3.2, 1], height_ratios=[1, 1.3], wspace=0.08, hspace=0.12)
    ax = fig.add_subplot(grid[:, 0])
    inset = fig.add_subplot(grid[0, 1])
    key = fig.add_subplot(grid[1, 1])
    key.axis("off")
    t_end = ev.t_meas if ev.t_meas is not None else 0.0
    t_from = t_end - focus_s
    colors = {vid: _VEHICLE_COLORS[i % len(_VEHICLE_COLORS)] for i, vid in enumerate(sorted(ev.truth_vehicles))}
    for vid in ev.tracks_fused:
        colors.setdefault(vid, _VEHICLE_COLORS[len(colors) % len(_VEHICLE_COLORS)])

    # the zoom: where the connected vehicles were (truth and estimate) in the last focus_s seconds
    recent = [_split(tr, t_from)[1] for tr in ev.truth_vehicles.values()]
    recent += [_split(tr, t_from)[1] for tr in ev.tracks_fused.values()]
    box = focus_box(np.vstack(recent) if recent else np.zeros((0, 2)))
    view_m = max(box[1] - box[0], box[3] - box[2])

    for a in (ax, inset):
        _draw_map(a, hdmap)
    for tr in ev.truth_obstacles.values():
        old, new = _split(tr, t_from)
        ax.plot(old[:, 0], old[:, 1], ":", lw=0.8, color="0.6", alpha=0.5)
        ax.plot(new[:, 0], new[:, 1], ":", lw=1.4, color="0.3")
    for vid, tr in ev.truth_vehicles.items():
        old, new = _split(tr, t_from)
        c = colors[vid]
        ax.plot(old[:, 0], old[:, 1], "-", lw=7, color=c, alpha=0.08, solid_capstyle="round")
        ax.plot(new[:, 0], new[:, 1], "-", lw=7, color=c, alpha=0.28, solid_capstyle="round")
        whole = np.asarray(tr, float).reshape(-1, 3)
        inset.plot(whole[:, 1], whole[:, 2], "-", lw=1.2, color=c)
    for vid, tr in ev.tracks_fused.items():
        old, new = _split(tr, t_from)
        ax.plot(old[:, 0], old[:, 1], "-", lw=0.8, color=colors[vid], alpha=0.3)
        ax.plot(new[:, 0], new[:, 1], "-", lw=1.4, color=colors[vid])

    # fused objects: their tracks over the last focus_s seconds
    obj = np.asarray(ev.fused_objects, float).reshape(-1, 5)
    obj = obj[obj[:, 0] >= t_from]
    for oid in np.unique(obj[:, 1]):
        rows = obj[obj[:, 1] == oid]
        ax.plot(rows[:, 3], rows[:, 4], "-", lw=0.9, color=_OBJECT_COLORS.get(int(rows[0, 2]), "k"), alpha=0.7)

    # the last fused state and the truth of the same instant: markers, ids and magnified ellipses
    fused, truth = ev.last_fused, ev.last_truth
    ellipses = []  # (x, y, 2x2 cov, colour)
    if truth is not None:
        v = np.asarray(truth.vehicle_pose, float).reshape(-1, 6)
        for vid, pose in zip(truth.vehicle_ids, v, strict=True):
            c = colors.get(vid, "k")
            ax.plot(pose[0], pose[1], "s", ms=9, mfc="none", mec=c, mew=1.8)
            ax.annotate(vid, pose[:2], xytext=(8, 8), textcoords="offset points", color=c, fontsize=10, weight="bold")
        o = np.asarray(truth.obstacle_p_map, float).reshape(-1, 3)
        ax.plot(o[:, 0], o[:, 1], "o", ms=6, mfc="none", mec="0.3", mew=1.2)
    if fused is not None:
        for vid, pose, cov in zip(fused.vehicle_ids, fused.vehicle_pose, fused.vehicle_pose_cov, strict=True):
            c = colors.get(vid, "k")
            ax.plot(pose[0], pose[1], "+", ms=11, mew=2, color=c)
            ellipses.append((float(pose[0]), float(pose[1]), cov_from_upper(np.asarray(cov, float))[:2, :2], c))
        for oid, cls, p, cov in zip(
            fused.object_id, fused.object_cls, fused.object_p_map, fused.object_cov, strict=True
        ):
            c = _OBJECT_COLORS.get(int(cls), "k")
            ax.plot(p[0], p[1], "x", ms=6, mew=1.5, color=c)
            if box[0] <= p[0] <= box[1] and box[2] <= p[1] <= box[3]:
                ax.annotate(str(int(oid)), p[:2], xytext=(4, -10), textcoords="offset points", color=c, fontsize=7)
            ellipses.append((float(p[0]), float(p[1]), cov_from_upper(np.asarray(cov, float))[:2, :2], c))
    params = [(x, y, ellipse_params(cov), c) for x, y, cov, c in ellipses]
    scale = ellipse_scale([w for *_, (w, _h, _a), _c in params], view_m)
    for x, y, (w, h, ang), c in params:
        ax.add_patch(Ellipse((x, y), w * scale, h * scale, angle=ang, fill=False, color=c, lw=1.3))

    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[2], box[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(f"{title}\nt = {t_end:.1f} s; strong: the last {focus_s:g} s, faint: before", fontsize=10)
    inset.add_patch(Rectangle((box[0], box[2]), box[1] - box[0], box[3] - box[2], fill=False, color="k", lw=1.2))
    inset.set_aspect("equal", adjustable="datalim")
    inset.set_title("whole map (box: the view)", fontsize=8)
    inset.tick_params(labelsize=6)

    handles = [
        plt.Line2D([], [], lw=7, color="0.4", alpha=0.3, label="vehicle truth (colour per vehicle)"),
        plt.Line2D([], [], lw=1.4, color="0.2", label="vehicle fused pose"),
        plt.Line2D([], [], ls="none", marker="s", mfc="none", mec="0.2", ms=9, label="true pose now, with id"),
        plt.Line2D([], [], ls="none", marker="+", mew=2, color="0.2", ms=11, label="fused pose now"),
        plt.Line2D([], [], ls=":", lw=1.4, color="0.3", label="obstacle truth"),
        plt.Line2D([], [], ls="none", marker="o", mfc="none", mec="0.3", label="obstacle true position now"),
        plt.Line2D([], [], lw=0.9, color=_OBJECT_COLORS[int(ObjectClass.PEDESTRIAN)], label="fused pedestrian, id"),
        plt.Line2D([], [], lw=0.9, color=_OBJECT_COLORS[int(ObjectClass.VEHICLE)], label="fused vehicle object, id"),
        plt.Line2D(
            [], [], ls="none", marker="o", ms=12, mfc="none", mec="0.2", label=f"2-sigma ellipse, drawn x{scale}"
        ),
    ]
    if hdmap is not None:
        handles += [
            plt.Line2D([], [], ls="none", marker="o", color="tab:green", ms=5, label="lamp"),
            plt.Line2D([], [], ls="none", marker="^", color="tab:red", ms=5, label="traffic light"),
            plt.Line2D([], [], ls="none", marker="s", color="tab:purple", ms=5, label="sign"),
        ]
    key.legend(handles=handles, loc="upper left", fontsize=8, frameon=False)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def render_errors(path: Path, ev: Evaluator, title: str) -> None:
    """Each vehicle's horizontal error and the objects' RMSE per fused state over scenario time."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 7), sharex=True)
    steady = ev.summary()
    for i, vid in enumerate(sorted(ev.vehicle_errors)):
        te = ev.vehicle_errors[vid].array()
        s = steady["vehicle_rmse_steady_by_id_m"].get(vid)
        label = f"{vid} (steady RMSE {s:.3f} m)" if s is not None else vid
        top.plot(te[:, 0], te[:, 1], "-", lw=1.0, color=_VEHICLE_COLORS[i % len(_VEHICLE_COLORS)], label=label)
    t, obj, cover = ev.object_errors.array().T
    s = steady["object_rmse_steady_m"]
    bottom.plot(t, obj, "-", lw=1.0, color="navy", label="objects RMSE" + (f" (steady {s:.3f} m)" if s else ""))
    twin = bottom.twinx()
    twin.plot(t, cover, "-", lw=0.8, color="darkorange", alpha=0.7, label="coverage of true obstacles")
    twin.set_ylim(0, 1.05)
    twin.set_ylabel("coverage")
    for a in (top, bottom):
        if len(t):
            a.axvspan(
                min(t.min(), 0.0), ev.burnin_s, color="0.85", zorder=0, label=f"burn-in (cold start, {ev.burnin_s:g} s)"
            )
        if a.has_data() and len(t):  # log scale: decimetres and metres on one axis
            a.set_yscale("log")
            a.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))  # labels within one decade too
            a.yaxis.set_major_formatter(FormatStrFormatter("%g"))
            a.yaxis.set_minor_formatter(NullFormatter())
        a.grid(True, which="both", alpha=0.3)
    top.set_ylabel("vehicle error (m)")
    bottom.set_ylabel("object RMSE (m)")
    bottom.set_xlabel("scenario time (s)")
    top.set_title(f"{title}: horizontal error of the fused estimate per fused state", fontsize=10)
    if not len(t):
        top.text(0.5, 0.5, "no fused state was scored", transform=top.transAxes, ha="center")
    else:
        top.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
        (h1, l1), (h2, l2) = bottom.get_legend_handles_labels(), twin.get_legend_handles_labels()
        bottom.legend(h1 + h2, l1 + l2, loc="center left", bbox_to_anchor=(1.08, 0.5), fontsize=8, frameon=False)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
