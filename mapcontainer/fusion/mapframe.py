"""Detections in the map frame and their distances to candidates (the association's geometry).

A body-frame detection z (covariance S_z) seen from a pose [x, y, z, roll, pitch, yaw] (covariance S_pose)
is, to first order,

    m = R z + t,     S_m = R S_z R^T + J S_pose J^T,     J = d m / d [x, y, z, roll, pitch, yaw]
                                                            = [I, dR/droll z, dR/dpitch z, dR/dyaw z],

and its distance to a candidate c (covariance S_c) is d^2 = (m - c)^T (S_m + S_c)^-1 (m - c).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtri

from .. import geometry as geo

__all__ = ["RoadArea", "mahalanobis_logdet", "mahalanobis_matrix", "observations_to_map", "rotated_to_map"]


def observations_to_map(pose, pose_cov, p_body, cov_body) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame positions (N, 3) and covariances (N, 3, 3) of body-frame detections.

    ``pose`` = [x, y, z, roll, pitch, yaw] with covariance ``pose_cov`` (6, 6); ``p_body`` (N, 3) with
    covariances ``cov_body`` (N, 3, 3). First-order propagation of both uncertainties (module docstring).
    """
    pose = np.asarray(pose, dtype=float)
    return rotated_to_map(pose, geo.rpy_to_matrix_jac(*pose[3:]), pose_cov, p_body, cov_body)


def rotated_to_map(pose, jac, pose_cov, p_body, cov_body, rowwise: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`observations_to_map` with the pose's rotation and its derivatives ``jac`` given
    (:func:`mapcontainer.geometry.rpy_to_matrix_jac`), for a caller that has them already. ``rowwise``: each
    row's Jacobian as one (1, 3) product, the numbers of N calls with one row each to the last bit (BLAS
    rounds an (N, 3) product's rows differently)."""
    p_body = np.asarray(p_body, dtype=float).reshape(-1, 3)
    cov_body = np.asarray(cov_body, dtype=float).reshape(-1, 3, 3)
    R, dR_r, dR_p, dR_y = jac
    m = p_body @ R.T + pose[:3]
    J = np.empty((len(p_body), 3, 6))
    J[:, :, :3] = np.eye(3)
    rows = p_body[:, None, :] if rowwise else p_body
    J[:, :, 3] = (rows @ dR_r.T).reshape(-1, 3)
    J[:, :, 4] = (rows @ dR_p.T).reshape(-1, 3)
    J[:, :, 5] = (rows @ dR_y.T).reshape(-1, 3)
    S = R @ cov_body @ R.T + J @ np.asarray(pose_cov, dtype=float) @ J.transpose(0, 2, 1)
    return m, 0.5 * (S + S.transpose(0, 2, 1))


def mahalanobis_matrix(m, S_m, c, S_c) -> np.ndarray:
    """d2[i, j] = (m_i - c_j)^T (S_m_i + S_c_j)^-1 (m_i - c_j) for (N, 3) / (K, 3) points and their covariances."""
    return mahalanobis_logdet(m, S_m, c, S_c)[0]


def mahalanobis_logdet(m, S_m, c, S_c) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mahalanobis_matrix` and ln det(S_m_i + S_c_j) of every pair (inf where not positive definite)."""
    m = np.asarray(m, dtype=float).reshape(-1, 3)
    c = np.asarray(c, dtype=float).reshape(-1, 3)
    if len(m) == 0 or len(c) == 0:
        return np.zeros((len(m), len(c))), np.zeros((len(m), len(c)))
    diff = m[:, None, :] - c[None, :, :]
    S = np.asarray(S_m, dtype=float)[:, None] + np.asarray(S_c, dtype=float)[None, :]
    return _quad_inv3(S, diff, logdet=True)


def _quad_inv3(S: np.ndarray, d: np.ndarray, logdet: bool = False):
    """d^T S^-1 d for stacks of symmetric positive definite 3x3 S (..., 3, 3) and vectors d (..., 3), by
    the adjugate (closed form; a batched LAPACK solve costs ~1 us of overhead per matrix); with ``logdet``
    also ln det S."""
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    e, f, i = S[..., 1, 1], S[..., 1, 2], S[..., 2, 2]
    A00, A01, A02 = e * i - f * f, c * f - b * i, b * f - c * e
    A11, A12, A22 = a * i - c * c, b * c - a * f, a * e - b * b
    det = a * A00 + b * A01 + c * A02
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    q = A00 * x * x + A11 * y * y + A22 * z * z + 2.0 * (A01 * x * y + A02 * x * z + A12 * y * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(det > 0, q / det, np.inf)
        if logdet:
            return out, np.where(det > 0, np.log(np.where(det > 0, det, 1.0)), np.inf)
    return out


class RoadArea:
    """Where road users can be, from the host's map: its lanes (each centre line widened to its lane width),
    walkable areas (sidewalks, crossings) and junctions, rasterised once on a grid of ``cell_m`` cells.

    :meth:`fraction` is the share of a detection's horizontal uncertainty that lies there,

        f(m, S) = P[x on road or sidewalk],  x ~ N(m_xy, S_xy),

    over ``strata`` x ``strata`` points of equal mass (the standard normal's quantiles at the middles of equal
    strata along each axis, through the Cholesky factor of S_xy): the mask's value where the Gaussian is narrower
    than a cell, the mass on each side of a road's edge to about 1 / strata where it is wide. A map without
    lanes or walkable areas is all road (f = 1): the host then knows nothing about where objects can be.
    """

    def __init__(self, hdmap, cell_m: float = 0.5, strata: int = 12):
        if cell_m <= 0 or strata < 1:
            raise ValueError(f"cell_m must be positive and strata at least 1, got {cell_m}, {strata}")
        self.cell_m = float(cell_m)
        u = ndtri((np.arange(strata) + 0.5) / strata)
        self._nodes = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
        strips = [(np.asarray(c.points, float)[:, :2], float(c.width_m), c.closed) for c in hdmap.centerlines]
        polygons = [np.asarray(a.polygon, float)[:, :2] for a in [*hdmap.walkable, *hdmap.junctions]]
        self.empty = not strips and not polygons
        if self.empty:
            self.origin, self.mask = np.zeros(2), np.ones((1, 1), dtype=bool)
            return
        pts = np.vstack([s for s, _, _ in strips] + polygons)
        pad = max([w for _, w, _ in strips], default=0.0) + 2 * self.cell_m
        self.origin = pts.min(axis=0) - pad
        shape = np.ceil((pts.max(axis=0) + pad - self.origin) / self.cell_m).astype(int)
        self.mask = np.zeros(shape, dtype=bool)  # [ix, iy]
        centres = self.origin + (np.indices(shape).reshape(2, -1).T + 0.5) * self.cell_m
        for line, width, closed in strips:
            self._fill_strip(centres, line, width, closed)
        for poly in polygons:
            self._fill_polygon(poly)

    def _fill_strip(self, centres: np.ndarray, line: np.ndarray, width: float, closed: bool) -> None:
        """Cells whose centre is within width / 2 of the polyline (sampled every cell_m / 4)."""
        if closed:
            line = np.vstack([line, line[:1]])
        seg = np.diff(line, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / (self.cell_m / 4)), 1).astype(int)
        samples = np.vstack([a + np.outer(np.arange(k) / k, d) for a, d, k in zip(line[:-1], seg, n, strict=True)])
        samples = np.vstack([samples, line[-1:]])
        lo, hi = samples.min(axis=0) - width, samples.max(axis=0) + width
        box = np.all((centres >= lo) & (centres <= hi), axis=1)
        d, _ = cKDTree(samples).query(centres[box], distance_upper_bound=width / 2)
        flat = self.mask.reshape(-1)
        flat[np.flatnonzero(box)[np.isfinite(d)]] = True

    def _fill_polygon(self, poly: np.ndarray) -> None:
        """Cells whose centre is inside the polygon (even-odd rule, one scan line per grid column)."""
        a, b = poly, np.roll(poly, -1, axis=0)
        xs = self.origin[0] + (np.arange(self.mask.shape[0]) + 0.5) * self.cell_m
        for ix in np.flatnonzero((xs >= poly[:, 0].min()) & (xs <= poly[:, 0].max())):
            x = xs[ix]
            cross = (a[:, 0] <= x) != (b[:, 0] <= x)
            if not cross.any():
                continue
            ya, yb, xa, xb = a[cross, 1], b[cross, 1], a[cross, 0], b[cross, 0]
            y = np.sort(ya + (x - xa) * (yb - ya) / (xb - xa))
            iy = np.ceil((y - self.origin[1]) / self.cell_m - 0.5).astype(int)  # first cell centre above y
            for lo, hi in zip(iy[0::2], iy[1::2], strict=False):
                self.mask[ix, max(lo, 0) : max(hi, 0)] = True

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Whether each map point (..., >= 2) lies on a lane, walkable area or junction (outside the grid: no)."""
        if self.empty:
            return np.ones(np.shape(p)[:-1], dtype=bool)
        idx = np.floor((np.asarray(p, float)[..., :2] - self.origin) / self.cell_m).astype(int)
        inside = np.all((idx >= 0) & (idx < self.mask.shape), axis=-1)
        out = np.zeros(idx.shape[:-1], dtype=bool)
        out[inside] = self.mask[idx[inside][:, 0], idx[inside][:, 1]]
        return out

    def fraction(self, m: np.ndarray, S: np.ndarray) -> np.ndarray:
        """f(m_i, S_i) (class docstring) for map positions m (N, 3) and their covariances S (N, 3, 3)."""
        m = np.asarray(m, float).reshape(-1, 3)
        if self.empty or not len(m):
            return np.ones(len(m))
        S2 = np.asarray(S, float).reshape(-1, 3, 3)[:, :2, :2]
        L = np.linalg.cholesky(S2 + 1e-12 * np.eye(2))
        x = m[:, None, :2] + np.einsum("nij,kj->nki", L, self._nodes)
        return self.contains(x).mean(axis=1)
