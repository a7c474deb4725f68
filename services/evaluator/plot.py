"""The run's bird's-eye picture: truth vs fused estimates, with covariance ellipses (matplotlib)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

from mapcontainer.hdmap.model import HDMap  # noqa: E402

from .core import Evaluator  # noqa: E402

__all__ = ["ellipse_params", "render_run"]


def ellipse_params(cov2: np.ndarray, n_sigma: float = 2.0) -> tuple[float, float, float]:
    """(width, height, angle_deg) of the n-sigma ellipse of a 2x2 covariance: axes 2 n sqrt(eigenvalues)."""
    vals, vecs = np.linalg.eigh(np.asarray(cov2, float))
    vals = np.clip(vals, 0.0, None)
    angle = float(np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1])))
    return 2 * n_sigma * float(np.sqrt(vals[1])), 2 * n_sigma * float(np.sqrt(vals[0])), angle


def render_run(path: Path, ev: Evaluator, hdmap: HDMap | None, title: str) -> None:
    fig, ax = plt.subplots(figsize=(12, 7))
    if hdmap is not None:
        from mapcontainer.sim.render import draw_map

        draw_map(ax, hdmap)
    for aid, pts in ev.tracks_truth.items():
        xy = np.asarray(pts)
        is_vehicle = not aid.startswith("o")
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            "-",
            lw=2.0 if is_vehicle else 0.8,
            color="tab:red" if is_vehicle else "0.35",
            alpha=0.8,
            label=None,
        )
    truth = ev.last_truth  # at the last fused state's t_meas: markers and ellipses are simultaneous
    if truth is not None:
        v = np.asarray(truth.vehicle_pose, float).reshape(-1, 6)
        o = np.asarray(truth.obstacle_p_map, float).reshape(-1, 3)
        ax.plot(v[:, 0], v[:, 1], "s", ms=5, color="tab:red")
        ax.plot(o[:, 0], o[:, 1], "o", ms=4, color="0.35")
    for _vid, pts in ev.tracks_fused.items():
        xy = np.asarray(pts)
        ax.plot(xy[:, 0], xy[:, 1], "--", lw=1.2, color="tab:blue", alpha=0.9)
    if ev.fused_objects:
        o = np.asarray(ev.fused_objects)
        ax.plot(o[:, 0], o[:, 1], ".", ms=1.0, color="tab:cyan", alpha=0.4)
    for x, y, cov in ev.ellipses():
        w, h, ang = ellipse_params(cov)
        ax.add_patch(Ellipse((x, y), max(w, 0.05), max(h, 0.05), angle=ang, fill=False, color="tab:blue", lw=1.2))
        ax.plot(x, y, "+", color="tab:blue", ms=6)
    ax.plot([], [], "-", color="tab:red", lw=2, label="connected vehicles (truth)")
    ax.plot([], [], "-", color="0.35", lw=0.8, label="obstacles (truth)")
    ax.plot([], [], "--", color="tab:blue", label="fused vehicle poses")
    ax.plot([], [], ".", color="tab:cyan", label="fused objects")
    ax.plot([], [], "o", mfc="none", color="tab:blue", label="last fused state, 2-sigma ellipses")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, map east)")
    ax.set_ylabel("y (m, map north)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
