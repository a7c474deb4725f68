"""Spatial queries on an HD map: landmarks near a point or in a camera's view, lane samples, road height.

:class:`MapIndex` builds k-d trees (``scipy.spatial.cKDTree``) once per map. Distances are
Euclidean in 3-D (map frame, metres) unless a method says otherwise. Results keep the map's
order (ascending index), so they are deterministic.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import CameraIntrinsics, inverse, project_points, transform_points
from .model import HDMap, PointFeature, PoleFeature

__all__ = ["NEAR_PLANE_M", "MapIndex", "segment_distance", "segments_hit_rect"]

NEAR_PLANE_M = 0.1  # camera-frame depth below which nothing counts as in front of the camera


def segment_distance(p, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from point p (3,) to each segment [a_i, b_i] (a, b: (N, 3)).

    d_i = || a_i + t_i (b_i - a_i) - p ||, t_i = clip(((p - a_i) . (b_i - a_i)) / |b_i - a_i|^2, 0, 1).
    """
    p = np.asarray(p, dtype=float)
    d = b - a
    t = np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * d - p, axis=1)


def segments_hit_rect(p0: np.ndarray, p1: np.ndarray, lo, hi) -> np.ndarray:
    """Which 2-D segments [p0_i, p1_i] (N, 2) intersect the closed rectangle lo <= xy <= hi.

    Liang–Barsky clipping: with P(t) = p0 + t D, t in [0, 1], each boundary k gives
    p_k t <= q_k (p = [-Dx, Dx, -Dy, Dy], q = [x0 - xlo, xhi - x0, y0 - ylo, yhi - y0]);
    the segment hits the rectangle iff the resulting interval [t_min, t_max] is not empty.
    """
    p0 = np.asarray(p0, dtype=float).reshape(-1, 2)
    d = np.asarray(p1, dtype=float).reshape(-1, 2) - p0
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    pk = np.stack([-d[:, 0], d[:, 0], -d[:, 1], d[:, 1]], axis=1)
    qk = np.stack([p0[:, 0] - lo[0], hi[0] - p0[:, 0], p0[:, 1] - lo[1], hi[1] - p0[:, 1]], axis=1)
    parallel = pk == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(parallel, 0.0, qk / np.where(parallel, 1.0, pk))
    t_min = np.max(np.where(pk < 0, t, 0.0), axis=1)
    t_max = np.min(np.where(pk > 0, t, 1.0), axis=1)
    outside_parallel = np.any(parallel & (qk < 0), axis=1)
    return (t_min <= t_max) & ~outside_parallel


def _as_point(p_map) -> np.ndarray:
    p = np.asarray(p_map, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"expected a finite map point of shape (3,), got {p_map!r}")
    return p


def _check_radius(radius: float) -> float:
    radius = float(radius)
    if not radius >= 0.0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    return radius


class MapIndex:
    """Spatial index over one :class:`HDMap`, built once.

    * point landmarks: a k-d tree of their positions;
    * poles: a k-d tree of segment midpoints, queried with the radius enlarged by the longest
      half-length and then filtered by the exact point-to-segment distance;
    * lane lines: painted samples per spacing (computed on first use, cached) in a k-d tree;
    * road height: samples every ``height_spacing`` m along every lane line (painted or not)
      in a 2-D (x, y) k-d tree.
    """

    def __init__(self, hdmap: HDMap, lane_spacing: float = 0.5, height_spacing: float = 0.25):
        self.hdmap = hdmap
        self._points = list(hdmap.points)
        self._poles = list(hdmap.poles)
        self._p = np.array([f.p_map for f in self._points], dtype=float).reshape(-1, 3)
        self._point_tree = cKDTree(self._p)
        self._base = np.array([f.base for f in self._poles], dtype=float).reshape(-1, 3)
        self._top = np.array([f.top for f in self._poles], dtype=float).reshape(-1, 3)
        self._pole_tree = cKDTree((self._base + self._top) / 2.0)
        half = np.linalg.norm(self._top - self._base, axis=1) / 2.0
        self._pole_reach = float(half.max()) if len(half) else 0.0
        self._lane_cache: dict[float, tuple[np.ndarray, cKDTree]] = {}
        self._lane(lane_spacing)
        if height_spacing <= 0:
            raise ValueError(f"height_spacing must be > 0, got {height_spacing}")
        road = [line.polyline.sample(height_spacing) for line in hdmap.lane_lines]
        self._road = np.vstack(road) if road else np.zeros((0, 3))
        self._road_tree = cKDTree(self._road[:, :2])

    # ------------------------------------------------------------------------- landmarks

    def _points_within(self, p: np.ndarray, radius: float) -> np.ndarray:
        return np.array(sorted(self._point_tree.query_ball_point(p, radius)), dtype=int)

    def _poles_within(self, p: np.ndarray, radius: float) -> np.ndarray:
        cand = np.array(sorted(self._pole_tree.query_ball_point(p, radius + self._pole_reach)), dtype=int)
        if cand.size == 0:
            return cand
        return cand[segment_distance(p, self._base[cand], self._top[cand]) <= radius]

    def landmarks_in_range(self, p_map, radius: float) -> tuple[list[PointFeature], list[PoleFeature]]:
        """Point landmarks within ``radius`` of ``p_map`` and poles whose segment comes that close."""
        p, radius = _as_point(p_map), _check_radius(radius)
        pts = self._points_within(p, radius)
        poles = self._poles_within(p, radius)
        return [self._points[i] for i in pts], [self._poles[i] for i in poles]

    def landmarks_in_view(
        self, intr: CameraIntrinsics, T_map_cam: np.ndarray, max_range: float, margin_px: float = 0.0
    ) -> tuple[list[PointFeature], list[PoleFeature]]:
        """Landmarks a camera at ``T_map_cam`` can see (occlusion is not considered).

        A point counts when it lies within ``max_range`` of the camera centre, in front of the
        camera (z_cam > NEAR_PLANE_M) and projects inside the image shrunk by ``margin_px``
        (``intr.in_image``). A pole counts when its segment comes within ``max_range`` of the camera
        centre and some part of it is visible: the segment is clipped to z_cam >= NEAR_PLANE_M,
        projected, and the projected segment must intersect the (shrunk) image rectangle.
        """
        T_map_cam = np.asarray(T_map_cam, dtype=float)
        if T_map_cam.shape != (4, 4):
            raise ValueError(f"T_map_cam must be 4x4, got shape {T_map_cam.shape}")
        centre = T_map_cam[:3, 3]
        max_range = _check_radius(max_range)
        T_cam_map = inverse(T_map_cam)

        pts = self._points_within(centre, max_range)
        if pts.size:
            uv, z = project_points(intr, T_cam_map, self._p[pts])
            ok = z > NEAR_PLANE_M
            ok[ok] = intr.in_image(uv[ok], margin_px)
            pts = pts[ok]

        poles = self._poles_within(centre, max_range)
        if poles.size:
            a = transform_points(T_cam_map, self._base[poles])
            b = transform_points(T_cam_map, self._top[poles])
            poles = poles[self._segments_visible(intr, a, b, margin_px)]
        return [self._points[i] for i in pts], [self._poles[i] for i in poles]

    @staticmethod
    def _segments_visible(
        intr: CameraIntrinsics, a: np.ndarray, b: np.ndarray, margin_px: float
    ) -> np.ndarray:
        """Camera-frame segments (N, 3) with a part in front of the near plane and inside the image."""
        za, zb = a[:, 2], b[:, 2]
        front = (za >= NEAR_PLANE_M) | (zb >= NEAR_PLANE_M)
        dz = zb - za
        with np.errstate(divide="ignore", invalid="ignore"):
            t_near = np.where(dz != 0.0, (NEAR_PLANE_M - za) / dz, 0.0)
        t0 = np.where(za < NEAR_PLANE_M, t_near, 0.0)
        t1 = np.where(zb < NEAR_PLANE_M, t_near, 1.0)
        d = b - a
        c0 = a + t0[:, None] * d
        c1 = a + t1[:, None] * d
        # Clipped endpoints have z >= NEAR_PLANE_M (up to rounding) where ``front``.
        z0 = np.maximum(c0[:, 2], NEAR_PLANE_M)
        z1 = np.maximum(c1[:, 2], NEAR_PLANE_M)
        uv0 = np.stack([intr.fx * c0[:, 0] / z0 + intr.cx, intr.fy * c0[:, 1] / z0 + intr.cy], axis=1)
        uv1 = np.stack([intr.fx * c1[:, 0] / z1 + intr.cx, intr.fy * c1[:, 1] / z1 + intr.cy], axis=1)
        lo = (margin_px, margin_px)
        hi = (intr.width - 1 - margin_px, intr.height - 1 - margin_px)
        return front & segments_hit_rect(uv0, uv1, lo, hi)

    # ------------------------------------------------------------------------------ lanes

    def _lane(self, spacing: float) -> tuple[np.ndarray, cKDTree]:
        spacing = float(spacing)
        if not spacing > 0:
            raise ValueError(f"spacing must be > 0, got {spacing}")
        if spacing not in self._lane_cache:
            parts = [line.painted_samples(spacing) for line in self.hdmap.lane_lines]
            samples = np.vstack(parts) if parts else np.zeros((0, 3))
            samples.setflags(write=False)
            self._lane_cache[spacing] = (samples, cKDTree(samples))
        return self._lane_cache[spacing]

    def lane_samples(self, spacing: float = 0.5) -> np.ndarray:
        """All painted lane-line samples (M, 3), every ``spacing`` m along each line (read-only)."""
        return self._lane(spacing)[0]

    def lane_samples_in_range(self, p_map, radius: float, spacing: float = 0.5) -> np.ndarray:
        """Painted lane-line samples (M, 3) within ``radius`` of ``p_map`` (3-D distance)."""
        p, radius = _as_point(p_map), _check_radius(radius)
        samples, tree = self._lane(spacing)
        idx = np.array(sorted(tree.query_ball_point(p, radius)), dtype=int)
        return samples[idx].reshape(-1, 3)

    def nearest_lane_height(self, p_map) -> float:
        """Road height under ``p_map``: z of the lane-line sample nearest in (x, y).

        Lane lines are sampled every ``height_spacing`` m including the gaps of dashed lines;
        this is the reference of the paper's soft height constraint.
        """
        p = _as_point(p_map)
        if len(self._road) == 0:
            raise ValueError(f"map {self.hdmap.name!r} has no lane lines to take a height from")
        _, i = self._road_tree.query(p[:2])
        return float(self._road[i, 2])
