"""What stands between two antennas: buildings (from the map) and vehicles (from the world's actors).

Buildings: a raster of the map's ground, ``True`` where a building is. In our generated maps (and
wherever the map has no building outlines) a building is every place that is neither road (lane
centre lines widened to their lane width, junction areas) nor sidewalk or crossing, inside the map's
bounding box grown by ``margin_m``, after the open ground is grown by ``setback_m`` (verges, front
yards, the gap between curb and sidewalk). Outside the raster nothing blocks. Where a SUMO or Lanelet2
map comes with building outlines, :meth:`Buildings.from_polygons` rasterises those instead.

A link is building-blocked (NLOS) when its straight segment crosses a building cell: the segment is
sampled every half cell, so a wall thinner than half a cell can be missed (the default 1 m cells:
nothing thinner than 0.5 m). The metres of building crossed are reported too (Veins' obstacle model
charges a loss per metre inside; 3GPP's NLOS path loss does not, and this model follows 3GPP).

Vehicles: a link is vehicle-blocked (NLOSv) when a vehicle other than its two ends has its footprint
centre within ``half_width_m`` of the segment, between the ends (TR 37.885 §6.2.1 decides NLOSv from
the blocking vehicles' geometry; the footprint is approximated by a disc of the car's half width).
"""

from __future__ import annotations

import cv2
import numpy as np
from matplotlib.path import Path

from ..hdmap.model import HDMap

__all__ = ["Buildings", "vehicle_blocked"]

_SHIFT = 4  # sub-pixel bits of the vertices given to OpenCV


def _pixels(p: np.ndarray, origin: np.ndarray, cell_m: float) -> np.ndarray:
    """Map x, y -> OpenCV fixed-point pixel coordinates (pixel i spans [origin + i cell, origin + (i+1) cell))."""
    return np.round(((np.asarray(p, float)[:, :2] - origin) / cell_m - 0.5) * (1 << _SHIFT)).astype(np.int32)


class Buildings:
    """A building raster: ``mask[row, col]`` for the cell with lower-left corner ``origin + (col, row) * cell_m``."""

    def __init__(self, mask: np.ndarray, origin: np.ndarray, cell_m: float) -> None:
        mask = np.asarray(mask, dtype=bool)
        if mask.ndim != 2:
            raise ValueError(f"building mask must be 2-D, got shape {mask.shape}")
        if not cell_m > 0:
            raise ValueError(f"cell_m must be positive, got {cell_m}")
        self.mask = mask
        self.origin = np.asarray(origin, dtype=float).reshape(2)
        self.cell_m = float(cell_m)

    @classmethod
    def empty(cls) -> Buildings:
        return cls(np.zeros((1, 1), bool), np.zeros(2), 1.0)

    @classmethod
    def from_map(cls, hdmap: HDMap, cell_m: float = 1.0, margin_m: float = 60.0, setback_m: float = 2.0) -> Buildings:
        """Buildings wherever the map has neither road nor sidewalk (module docstring)."""
        pts = [c.points[:, :2] for c in hdmap.centerlines]
        pts += [w.polygon[:, :2] for w in hdmap.walkable] + [j.polygon[:, :2] for j in hdmap.junctions]
        if not pts:
            return cls.empty()
        allp = np.vstack(pts)
        origin = allp.min(axis=0) - margin_m
        size = np.ceil((allp.max(axis=0) + margin_m - origin) / cell_m).astype(int) + 1
        open_ = np.zeros((size[1], size[0]), np.uint8)

        def px(p: np.ndarray) -> np.ndarray:
            return _pixels(p, origin, cell_m)

        for c in hdmap.centerlines:
            thick = max(1, int(round(c.width_m / cell_m)))
            cv2.polylines(open_, [px(c.points)], bool(c.closed), 1, thickness=thick, shift=_SHIFT)
        polys = [px(w.polygon) for w in hdmap.walkable] + [px(j.polygon) for j in hdmap.junctions]
        if polys:
            cv2.fillPoly(open_, polys, 1, shift=_SHIFT)
        r = int(round(setback_m / cell_m))
        if r > 0:
            open_ = cv2.dilate(open_, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        return cls(open_ == 0, origin, cell_m)

    @classmethod
    def from_polygons(cls, polygons: list[np.ndarray], cell_m: float = 1.0) -> Buildings:
        """Buildings from outlines (each (N, 2) map x, y), e.g. a SUMO ``.poly.xml``'s buildings."""
        if not polygons:
            return cls.empty()
        allp = np.vstack([np.asarray(p, float)[:, :2] for p in polygons])
        origin = allp.min(axis=0) - cell_m
        size = np.ceil((allp.max(axis=0) + cell_m - origin) / cell_m).astype(int) + 1
        mask = np.zeros((size[1], size[0]), bool)
        for poly in polygons:  # exact: a cell is a building when its centre is inside an outline
            poly = np.asarray(poly, float)[:, :2]
            lo = np.floor((poly.min(axis=0) - origin) / cell_m).astype(int)
            hi = np.ceil((poly.max(axis=0) - origin) / cell_m).astype(int)
            cols, rows = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
            centres = origin + (np.stack([cols, rows], axis=-1) + 0.5) * cell_m
            inside = Path(poly).contains_points(centres.reshape(-1, 2)).reshape(cols.shape)
            mask[rows[inside], cols[inside]] = True
        return cls(mask, origin, cell_m)

    def at(self, p: np.ndarray) -> np.ndarray:
        """True where points p (..., 2) are inside a building."""
        ij = np.floor((np.asarray(p, float) - self.origin) / self.cell_m).astype(np.int64)
        h, w = self.mask.shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
        out = np.zeros(ij.shape[:-1], dtype=bool)
        out[inside] = self.mask[ij[..., 1][inside], ij[..., 0][inside]]
        return out

    def crossed_m(self, a: np.ndarray, b: np.ndarray, max_samples: int = 2048) -> np.ndarray:
        """Metres of building along each segment a[i] -> b[i] ((n, 2) each), sampled every half cell."""
        a = np.asarray(a, float).reshape(-1, 2)
        b = np.asarray(b, float).reshape(-1, 2)
        n = len(a)
        out = np.zeros(n)
        if n == 0 or not self.mask.any():
            return out
        length = np.hypot(*(b - a).T)
        steps = np.clip(np.ceil(length / (0.5 * self.cell_m)).astype(int), 1, max_samples)
        order = np.argsort(steps)
        # group segments by their sample count (powers of two) to keep the arrays rectangular
        for s in np.unique(2 ** np.ceil(np.log2(steps)).astype(int)):
            idx = order[(2 ** np.ceil(np.log2(steps[order])).astype(int)) == s]
            f = (np.arange(s) + 0.5) / s
            p = a[idx, None, :] + f[None, :, None] * (b[idx] - a[idx])[:, None, :]
            out[idx] = self.at(p).mean(axis=1) * length[idx]
        return out


def vehicle_blocked(
    a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray, blockers: np.ndarray, half_width_m: float = 0.9
) -> np.ndarray:
    """True for segments a[i] -> b[i] passing within ``half_width_m`` of a blocker centre other than
    their own ends (indices ``ia``/``ib`` into ``blockers``, -1 for an end that is not a blocker),
    strictly between the ends (projection parameter in (0, 1))."""
    a = np.asarray(a, float).reshape(-1, 2)
    b = np.asarray(b, float).reshape(-1, 2)
    blockers = np.asarray(blockers, float).reshape(-1, 2)
    if len(a) == 0 or len(blockers) == 0:
        return np.zeros(len(a), dtype=bool)
    ab = b - a
    l2 = np.maximum((ab**2).sum(axis=1), 1e-12)
    ap = blockers[None, :, :] - a[:, None, :]
    t = (ap * ab[:, None, :]).sum(axis=2) / l2[:, None]
    closest = a[:, None, :] + np.clip(t, 0, 1)[..., None] * ab[:, None, :]
    d2 = ((blockers[None, :, :] - closest) ** 2).sum(axis=2)
    hit = (d2 < half_width_m**2) & (t > 0) & (t < 1)
    m = np.arange(len(blockers))[None, :]
    hit &= (m != np.asarray(ia)[:, None]) & (m != np.asarray(ib)[:, None])
    return hit.any(axis=1)
