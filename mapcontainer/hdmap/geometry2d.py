"""Plane geometry the map importers share: offset polylines, outlines of strips, principal axes."""

from __future__ import annotations

import numpy as np

__all__ = ["dedup", "is_simple_polygon", "offset_polyline", "principal_axis", "strip_outline"]

_MITER_LIMIT = 4.0  # a corner's offset vertex moves at most this many offsets from the original one


def dedup(points, tol: float = 1e-6) -> np.ndarray:
    """``points`` (N, D) without consecutive vertices closer than ``tol`` (x, y) to the previous kept one."""
    pts = np.asarray(points, dtype=float)
    keep = [0]
    for i in range(1, len(pts)):
        if np.linalg.norm(pts[i, :2] - pts[keep[-1], :2]) > tol:
            keep.append(i)
    return pts[keep]


def offset_polyline(points, d: float) -> np.ndarray:
    """The polyline moved ``d`` metres to its left (negative: right), z kept, by mitred vertex normals.

    Each segment's left normal is n_k = (-t_y, t_x) for its unit tangent t; an inner vertex between
    segments a and b moves by d m with m = (n_a + n_b) / (1 + n_a . n_b), the intersection of the two
    offset segments, its length capped at ``_MITER_LIMIT`` so a hairpin does not shoot off.
    """
    pts = dedup(points)
    if len(pts) < 2:
        raise ValueError(f"a polyline needs 2 distinct vertices to be offset, got {len(pts)}")
    t = np.diff(pts[:, :2], axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.column_stack([-t[:, 1], t[:, 0]])
    m = np.empty((len(pts), 2))
    m[0], m[-1] = n[0], n[-1]
    if len(pts) > 2:
        na, nb = n[:-1], n[1:]
        denom = np.maximum(1.0 + np.einsum("ij,ij->i", na, nb), 1e-9)
        mi = (na + nb) / denom[:, None]
        length = np.linalg.norm(mi, axis=1, keepdims=True)
        m[1:-1] = np.where(length > _MITER_LIMIT, mi / length * _MITER_LIMIT, mi)
    out = pts.copy()
    out[:, :2] += d * m
    return out


def strip_outline(points, width: float) -> np.ndarray:
    """The (N, 2) polygon of a strip ``width`` wide around a centre polyline: left side, then right reversed."""
    left = offset_polyline(points, width / 2)[:, :2]
    right = offset_polyline(points, -width / 2)[:, :2]
    return np.vstack([left, right[::-1]])


def principal_axis(polygon, z: float = 0.0) -> np.ndarray:
    """The (2, 3) segment through a polygon's vertex centroid along its longest principal axis, spanning its extent."""
    xy = np.asarray(polygon, dtype=float)[:, :2]
    c = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - c, full_matrices=False)
    axis = vt[0]
    s = (xy - c) @ axis
    ends = c + np.outer([s.min(), s.max()], axis)
    if np.linalg.norm(ends[1] - ends[0]) < 1e-6:
        raise ValueError("a polygon without extent has no principal axis")
    return np.column_stack([ends, [z, z]])


def is_simple_polygon(polygon) -> bool:
    """Whether the closed ring through ``polygon`` (N, 2) has no repeated vertex and no two non-adjacent edges
    that touch or cross (an O(N^2) orientation test: fine for junction and walking-area outlines)."""
    p = np.asarray(polygon, dtype=float)[:, :2]
    n = len(p)
    if n < 3 or len(np.unique(np.round(p, 9), axis=0)) < n:
        return False

    def orient(a, b, c) -> float:
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        for j in range(i + 1, n):
            if j == i or (j + 1) % n == i or j == (i + 1) % n:
                continue
            c, d = p[j], p[(j + 1) % n]
            o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
            if o1 * o2 <= 0 and o3 * o4 <= 0 and not (o1 == o2 == 0 and not _overlap(a, b, c, d)):
                return False
    return True


def _overlap(a, b, c, d) -> bool:
    """Collinear segments ab and cd share a point (their x, y bounding boxes overlap)."""
    lo1, hi1 = np.minimum(a, b), np.maximum(a, b)
    lo2, hi2 = np.minimum(c, d), np.maximum(c, d)
    return bool(np.all(lo1 <= hi2) and np.all(lo2 <= hi1))
