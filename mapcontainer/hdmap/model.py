"""The vectorized HD map: landmarks, lane geometry and walkable areas, in the map frame (ENU, m).

The map is the paper's "map sensor": point features (traffic lights, signs), line features
(lamp poles, controlled by a base and a top point) and "domain-like" features (lane lines,
matched through a distance transform of the lane mask).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

__all__ = [
    "POINT_CLASSES",
    "POLE_CLASSES",
    "HDMap",
    "JunctionArea",
    "LaneCenterline",
    "LaneLine",
    "PointFeature",
    "PoleFeature",
    "Polyline",
    "WalkableArea",
]

POINT_CLASSES = ("traffic_light", "sign")
POLE_CLASSES = ("lamp",)


def _as_points(a, dim: int = 3) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] != dim or len(a) < 2:
        raise ValueError(f"expected an (N>=2, {dim}) array of points, got shape {a.shape}")
    return a


class Polyline:
    """A 3-D polyline with arc-length parameterisation (open or closed)."""

    def __init__(self, points, closed: bool = False):
        pts = _as_points(points)
        if closed and np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        self.points = pts
        self.closed = closed
        verts = np.vstack([pts, pts[:1]]) if closed else pts
        self._verts = verts
        seg = np.linalg.norm(np.diff(verts, axis=0), axis=1)
        self._s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self._s[-1])

    def _wrap(self, s):
        s = np.asarray(s, dtype=float)
        return np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)

    def point_at(self, s) -> np.ndarray:
        """Point(s) at arc length s (wraps around on a closed line, clamps on an open one)."""
        s = self._wrap(s)
        return np.stack([np.interp(s, self._s, self._verts[:, k]) for k in range(3)], axis=-1)

    def tangent_at(self, s) -> np.ndarray:
        """Unit tangent(s) of the segment containing arc length s."""
        s = self._wrap(s)
        i = np.clip(np.searchsorted(self._s, s, side="right") - 1, 0, len(self._verts) - 2)
        d = self._verts[i + 1] - self._verts[i]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def sample(self, spacing: float) -> np.ndarray:
        """Points every ``spacing`` metres along the line."""
        n = max(int(np.ceil(self.length / spacing)), 1)
        s = np.linspace(0.0, self.length, n, endpoint=self.closed is False)
        return self.point_at(s)

    def project(self, p) -> float:
        """Arc length of the point on the line nearest to p (x, y only)."""
        p = np.asarray(p, dtype=float)[:2]
        a, b = self._verts[:-1, :2], self._verts[1:, :2]
        d = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
        dist = np.linalg.norm(a + t[:, None] * d - p, axis=1)
        i = int(np.argmin(dist))
        return float(self._s[i] + t[i] * (self._s[i + 1] - self._s[i]))


@dataclass(frozen=True)
class PointFeature:
    """A point landmark: its reference point (e.g. a traffic light's housing centre)."""

    id: int
    cls: Literal["traffic_light", "sign"]
    p_map: np.ndarray  # (3,)


@dataclass(frozen=True)
class PoleFeature:
    """A line landmark (lamp post) controlled by its base and top points."""

    id: int
    cls: Literal["lamp"]
    base: np.ndarray  # (3,)
    top: np.ndarray  # (3,)


@dataclass(frozen=True)
class LaneLine:
    """A painted lane line; dashed lines are painted for ``dash_m`` then blank for ``gap_m``."""

    id: int
    points: np.ndarray  # (N, 3)
    kind: Literal["solid", "dashed"]
    closed: bool = False
    dash_m: float = 3.0
    gap_m: float = 6.0
    width_m: float = 0.15

    @property
    def polyline(self) -> Polyline:
        return Polyline(self.points, self.closed)

    def painted_arcs(self, spacing: float) -> np.ndarray:
        """Arc lengths (M,) every ``spacing`` m along the line that fall on painted parts."""
        s = np.arange(0.0, self.polyline.length, spacing)
        if self.kind == "dashed":
            s = s[np.mod(s, self.dash_m + self.gap_m) < self.dash_m]
        return s

    def painted_samples(self, spacing: float) -> np.ndarray:
        """Sample points (M, 3) every ``spacing`` m on the painted parts only."""
        return self.polyline.point_at(self.painted_arcs(spacing))


@dataclass(frozen=True)
class LaneCenterline:
    """The centre of one lane, ordered in the driving direction."""

    id: int
    points: np.ndarray  # (N, 3)
    closed: bool = False
    width_m: float = 3.5

    @property
    def polyline(self) -> Polyline:
        return Polyline(self.points, self.closed)


@dataclass(frozen=True)
class WalkableArea:
    """Where pedestrians may be: a sidewalk or a crossing; ``path`` is its walking centre line."""

    id: int
    kind: Literal["sidewalk", "crossing"]
    polygon: np.ndarray  # (N, 2) map x, y
    path: np.ndarray  # (M, 3)
    closed: bool = False

    @property
    def polyline(self) -> Polyline:
        return Polyline(self.path, self.closed)


@dataclass(frozen=True)
class JunctionArea:
    """The paved area of a junction (intersection), where lanes cross and no lane lines are painted."""

    id: int
    polygon: np.ndarray  # (N, 2) map x, y
    z: float = 0.0


@dataclass
class HDMap:
    """All features of one map. Spatial queries are in :mod:`mapcontainer.hdmap.query`."""

    name: str
    points: list[PointFeature] = field(default_factory=list)
    poles: list[PoleFeature] = field(default_factory=list)
    lane_lines: list[LaneLine] = field(default_factory=list)
    centerlines: list[LaneCenterline] = field(default_factory=list)
    walkable: list[WalkableArea] = field(default_factory=list)
    junctions: list[JunctionArea] = field(default_factory=list)

    def feature_counts(self) -> dict[str, int]:
        """Landmarks by class, e.g. {"lamp": 14, "traffic_light": 4, "sign": 4}."""
        counts = {c: 0 for c in POLE_CLASSES + POINT_CLASSES}
        for f in self.points:
            counts[f.cls] += 1
        for f in self.poles:
            counts[f.cls] += 1
        return counts
