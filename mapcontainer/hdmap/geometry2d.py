"""Plane geometry the map importers share: offset polylines, outlines of strips, principal axes."""

from __future__ import annotations

import numpy as np

__all__ = ["dedup", "distance_to_polyline", "is_simple_polygon", "offset_polyline", "principal_axis", "strip_outline"]

_MITER_LIMIT = 4.0  # a corner's offset vertex moves at most this many offsets from the original one


def dedup(points, tol: float = 1e-6) -> np.ndarray:
    """``points`` (N, D) without consecutive vertices closer than ``tol`` (x, y) to the previous kept one."""
    pts = np.asarray(points, dtype=float)
    keep = [0]
    for i in range(1, len(pts)):
        if np.linalg.norm(pts[i, :2] - pts[keep[-1], :2]) > tol:
            keep.append(i)
    return pts[keep]


def distance_to_polyline(p, line) -> float:
    """Distance (x, y) from point ``p`` to the nearest segment of the polyline ``line`` (N >= 2, 2 or 3 columns).

    min_i | a_i + t_i (b_i - a_i) - p |, t_i = clip(((p - a_i) . (b_i - a_i)) / |b_i - a_i|^2, 0, 1).
    """
    q = np.asarray(p, dtype=float)[:2]
    pts = np.asarray(line, dtype=float)[:, :2]
    a, d = pts[:-1], np.diff(pts, axis=0)
    t = np.clip(np.einsum("ij,ij->i", q - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * d - q, axis=1)))


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
    that touch or cross.

    Edges e_i = [p_i, p_i+1] and e_j cross or touch iff o(e_i, p_j) o(e_i, p_j+1) <= 0 and
    o(e_j, p_i) o(e_j, p_i+1) <= 0, with o(ab, c) = (b - a) x (c - a); collinear pairs (all four zero) count
    only when their extents overlap. Vectorised over j for each i: O(N^2) work, fine for outlines.
    """
    p = np.asarray(polygon, dtype=float)[:, :2]
    n = len(p)
    if n < 3 or len(np.unique(np.round(p, 9), axis=0)) < n:
        return False
    a, b = p, np.roll(p, -1, axis=0)

    def orient(a, b, c) -> np.ndarray:
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])

    idx = np.arange(n)
    for i in range(n):
        others = (idx != i) & (idx != (i + 1) % n) & (idx != (i - 1) % n)
        c, d = a[others], b[others]
        o1, o2 = orient(a[i], b[i], c), orient(a[i], b[i], d)
        o3, o4 = orient(c, d, a[i]), orient(c, d, b[i])
        hit = (o1 * o2 <= 0) & (o3 * o4 <= 0)
        collinear = (o1 == 0) & (o2 == 0)
        if np.any(collinear & hit):
            lo1, hi1 = np.minimum(a[i], b[i]), np.maximum(a[i], b[i])
            lo2, hi2 = np.minimum(c, d), np.maximum(c, d)
            overlap = np.all((lo1 <= hi2) & (lo2 <= hi1), axis=1)
            hit = np.where(collinear, overlap, hit)
        if np.any(hit):
            return False
    return True
