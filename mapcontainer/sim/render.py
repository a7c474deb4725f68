"""Pictures of a simulated episode: a bird's-eye view and a camera view per vehicle."""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from schemas import LandmarkClass, ObjectClass  # noqa: E402

from ..hdmap.model import HDMap  # noqa: E402
from .actors import ActorState  # noqa: E402
from .sensors import CameraObservation  # noqa: E402

__all__ = ["draw_map", "map_extent", "map_mark_sizes", "render_birdseye", "render_camera_view", "render_map"]

_CLS_COLOR = {ObjectClass.PEDESTRIAN: "tab:orange", ObjectClass.VEHICLE: "tab:blue"}


def map_mark_sizes(m_per_pt: float | None) -> tuple[float, float]:
    """(landmark marker size, lane line dot size), in points, for a drawing at ``m_per_pt`` metres per point
    (None: the default sizes, for pictures of a few hundred metres).

    A landmark is drawn about 2 m across and a lane line about 0.6 m wide, each within readable limits: at
    city scale (a metre per point and more) a landmark is no bigger than a lane line, so that a district's
    hundreds of lamps and signs do not cover its roads as one sheet of markers."""
    if m_per_pt is None:
        return 4.0, 0.6
    if not m_per_pt > 0:
        raise ValueError(f"m_per_pt must be positive, got {m_per_pt}")
    lane = float(np.clip(0.6 / m_per_pt, 0.5, 1.5))
    landmark = float(np.clip(2.0 / m_per_pt, 0.5, 5.0))
    return min(landmark, lane) if m_per_pt >= 1.0 else landmark, lane


def draw_map(ax, hdmap: HDMap, m_per_pt: float | None = None) -> None:
    """Junction and walkable areas, lane lines and landmarks on a matplotlib axis (map frame, metres); one artist
    per kind of element (a district's thousands of areas and lines draw in a second, not one artist each).
    ``m_per_pt``: the drawing's scale, which sizes the landmarks and lane lines (:func:`map_mark_sizes`)."""
    landmark_ms, lane_ms = map_mark_sizes(m_per_pt)
    from matplotlib.collections import PolyCollection

    areas = [(j.polygon, "0.93") for j in hdmap.junctions]
    areas += [(w.polygon, "0.85" if w.kind == "sidewalk" else "khaki") for w in hdmap.walkable]
    for color in dict.fromkeys(c for _, c in areas):
        polys = [poly[:, :2] for poly, c in areas if c == color]
        ax.add_collection(PolyCollection(polys, facecolors=color, edgecolors="none", linewidths=0))
    if areas:
        ax.autoscale_view()
    for kind, color in (("solid", "0.2"), ("dashed", "0.5")):
        pts = [ln.painted_samples(0.5)[:, :2] for ln in hdmap.lane_lines if ln.kind == kind]
        if pts:
            p = np.concatenate(pts)
            ax.plot(p[:, 0], p[:, 1], ".", ms=lane_ms, color=color)
    if hdmap.poles:
        b = np.array([f.base for f in hdmap.poles])
        ax.plot(b[:, 0], b[:, 1], "o", ms=landmark_ms, mew=0, color="tab:green", label="lamp")
    for cls, marker, color in (("traffic_light", "^", "tab:red"), ("sign", "s", "tab:purple")):
        p = np.array([f.p_map for f in hdmap.points if f.cls == cls]).reshape(-1, 3)
        if len(p):
            ax.plot(p[:, 0], p[:, 1], marker, ms=landmark_ms * 1.2, mew=0, color=color, label=cls.replace("_", " "))


def render_birdseye(
    path: Path,
    hdmap: HDMap,
    tracks: dict[str, np.ndarray],
    final: dict[str, ActorState],
    connected: list[str],
    fov_deg: float,
    range_m: float,
    title: str,
    classes: dict[str, int] | None = None,
) -> None:
    """Map, every actor's trajectory (tracks: id -> (T, 2)), final boxes and the vehicles' fields of view.

    An actor without a final state (it left the world, as SUMO's do) is drawn by its track alone, in the
    colour of its class in ``classes`` (id -> ObjectClass)."""
    fig, ax = plt.subplots(figsize=(12, 7))
    draw_map(ax, hdmap)
    for aid, xy in tracks.items():
        st = final.get(aid)
        is_cv = aid in connected
        cls = st.cls if st is not None else (classes or {}).get(aid)
        color = "tab:red" if is_cv else _CLS_COLOR.get(cls, "k")
        ax.plot(xy[:, 0], xy[:, 1], "-", lw=2.0 if is_cv else 0.8, color=color, alpha=0.8)
        if st is None:
            continue
        c, s = np.cos(st.yaw), np.sin(st.yaw)
        length, w = st.size[0], st.size[1]
        box = np.array([[length, w], [length, -w], [-length, -w], [-length, w], [length, w]]) / 2
        ax.plot(
            st.p_map[0] + c * box[:, 0] - s * box[:, 1],
            st.p_map[1] + s * box[:, 0] + c * box[:, 1],
            "-",
            color=color,
            lw=1.5,
        )
        if is_cv:
            ang = st.yaw + np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, 30))
            wedge = np.vstack(
                [st.p_map[:2], st.p_map[:2] + range_m * np.column_stack([np.cos(ang), np.sin(ang)]), st.p_map[:2]]
            )
            ax.fill(wedge[:, 0], wedge[:, 1], color="tab:red", alpha=0.08)
            ax.annotate(aid, st.p_map[:2] + [2, 2], color="tab:red", fontsize=9)
    ax.plot([], [], "-", color="tab:red", label="connected vehicle")
    ax.plot([], [], "-", color="tab:blue", label="obstacle vehicle")
    ax.plot([], [], "-", color="tab:orange", label="pedestrian")
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def render_camera_view(path: Path, obs: CameraObservation, title: str) -> None:
    """The camera image: lane mask, detected points (by class) and pole segments (clutter in grey)."""
    h, w = obs.lane_mask.shape
    img = np.full((h, w, 3), 40, np.uint8)
    img[: h // 2] = (90, 60, 50)  # sky above the horizon (camera looks level by default)
    img[obs.lane_mask > 0] = (255, 255, 255)
    for seg, fid in zip(obs.poles_uv, obs.pole_ids, strict=True):
        color = (0, 200, 0) if fid >= 0 else (150, 150, 150)
        p, q = np.rint(seg[:2]).astype(int), np.rint(seg[2:]).astype(int)
        cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), color, 4)
    colors = {LandmarkClass.TRAFFIC_LIGHT: (0, 0, 255), LandmarkClass.SIGN: (200, 0, 200)}
    for uv, cls, fid in zip(obs.points_uv, obs.points_cls, obs.point_ids, strict=True):
        color = colors.get(int(cls), (255, 255, 0)) if fid >= 0 else (150, 150, 150)
        cv2.circle(img, (int(round(uv[0])), int(round(uv[1]))), 9, color, 3)
    cv2.putText(img, title, (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
    legend = "green: lamp pole  red: traffic light  magenta: sign  grey: clutter  white: lane mask"
    cv2.putText(img, legend, (20, h - 20), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (230, 230, 230), 1)
    cv2.imwrite(str(path), img)


def map_extent(hdmap: HDMap) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1): the rectangle the map's lines and areas cover (m)."""
    xy = [ln.points[:, :2] for ln in hdmap.lane_lines] + [w.polygon for w in hdmap.walkable]
    xy += [j.polygon for j in hdmap.junctions] + [c.points[:, :2] for c in hdmap.centerlines]
    pts = np.vstack(xy) if xy else np.zeros((1, 2))
    (x0, y0), (x1, y1) = pts.min(axis=0), pts.max(axis=0)
    return float(x0), float(y0), float(x1), float(y1)


def render_map(
    path: Path,
    hdmap: HDMap,
    title: str,
    bounds: tuple[float, float, float, float] | None = None,
    marks: dict[str, tuple[float, float]] | None = None,
) -> None:
    """A PNG of the map, or of the rectangle ``bounds`` (x0, y0, x1, y1 in m) of it: junctions, walkable
    areas, lane lines (solid dark, dashed grey), lane centre lines with their driving direction (faint
    arrows, below city scale), and the landmarks, sized for the drawing's scale (:func:`map_mark_sizes`).
    ``marks``: labelled points (e.g. the vehicle a view is centred on)."""
    x0, y0, x1, y1 = map_extent(hdmap) if bounds is None else bounds
    span = np.array([x1 - x0, y1 - y0]) + 1.0
    width = 14.0
    fig, ax = plt.subplots(figsize=(width, float(np.clip(width * span[1] / span[0], 4.0, 14.0))))
    m_per_pt = float(max(span[0] / (0.8 * width * 72), span[1] / (0.8 * fig.get_figheight() * 72)))
    for c in hdmap.centerlines:
        ax.plot(c.points[:, 0], c.points[:, 1], "-", lw=0.4, color="tab:cyan", alpha=0.6)
        if m_per_pt < 0.5 and len(c.points) >= 2 and c.polyline.length > 1.0:  # at city scale arrows are clutter
            mid = c.polyline.length / 2
            p, t = c.polyline.point_at(mid), c.polyline.tangent_at(mid)
            ax.annotate("", p[:2] + t[:2], p[:2], arrowprops={"arrowstyle": "->", "color": "tab:cyan", "lw": 0.6})
    draw_map(ax, hdmap, m_per_pt)
    for label, (mx, my) in (marks or {}).items():
        ax.plot([mx], [my], "*", ms=12, color="tab:red")
        ax.annotate(label, (mx, my), xytext=(6, 6), textcoords="offset points", color="tab:red", fontsize=10)
    ax.plot([], [], "-", color="tab:cyan", label="lane centre line")
    if bounds is not None:
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, markerscale=max(1.0, 4.0 / map_mark_sizes(m_per_pt)[0]))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
