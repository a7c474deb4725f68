"""What stands between two antennas: buildings (from the map) and vehicles (from the world's actors).

Buildings: a raster of the map's ground, ``True`` where a building is. In our generated maps (and
wherever the map has no building outlines) a building is every place that is neither road (lane
centre lines widened to their lane width, junction areas) nor sidewalk or crossing, inside the map's
bounding box grown by ``margin_m``, after the open ground is grown by ``setback_m`` (verges, front
yards, the gap between curb and sidewalk). Outside the raster nothing blocks. Where a SUMO or Lanelet2
map comes with building outlines, :meth:`Buildings.from_polygons` rasterises those instead.

A link is building-blocked (NLOS) when its straight segment crosses a building cell: the segment is
sampled every cell, so a building corner clipped by less than a cell can be missed (1 m cells by
default). The metres of building crossed are reported too (Veins' obstacle model
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

    @classmethod
    def from_sumo(cls, path, cell_m: float = 1.0) -> Buildings:
        """Buildings from a SUMO additional file's polygons whose type starts with "building" (what
        ``polyconvert`` writes for OpenStreetMap buildings), in the network's x, y (the map frame of a
        SUMO map). Needs sumolib (the roads extra)."""
        from ..hdmap.errors import MapFileError, require

        require("sumolib", "Reading building polygons of a SUMO additional file")
        from sumolib.shapes.polygon import read as read_polygons

        try:
            polys = read_polygons(str(path))
        except OSError as exc:
            raise MapFileError(f"{path}: {exc}") from None
        shapes = [np.asarray(p.shape, float)[:, :2] for p in polys if (p.type or "").startswith("building")]
        return cls.from_polygons([s for s in shapes if len(s) >= 3], cell_m)

    def at(self, p: np.ndarray) -> np.ndarray:
        """True where points p (..., 2) are inside a building."""
        p = np.asarray(p, float)
        return self._at_xy(p[..., 0], p[..., 1])

    def _at_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        h, w = self.mask.shape
        col = np.floor((x - self.origin[0]) / self.cell_m).astype(np.int64)
        row = np.floor((y - self.origin[1]) / self.cell_m).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        flat = np.where(inside, row * w + col, 0)
        return self.mask.ravel()[flat] & inside

    def crossed_m(self, a: np.ndarray, b: np.ndarray, max_samples: int = 4096) -> np.ndarray:
        """Metres of building along each segment a[i] -> b[i] ((n, 2) each), sampled every cell."""
        a = np.asarray(a, float).reshape(-1, 2)
        b = np.asarray(b, float).reshape(-1, 2)
        out = np.zeros(len(a))
        if len(a) == 0 or not self.mask.any():
            return out
        seg, x, y, steps, length = sample_segments(a, b, self.cell_m, max_samples)
        return np.bincount(seg, weights=self._at_xy(x, y), minlength=len(a)) / steps * length


def sample_segments(a: np.ndarray, b: np.ndarray, step_m: float, max_samples: int = 4096):
    """Points every ``step_m`` (at most ``max_samples``) along each segment, at the centres of equal parts:
    (segment index per point, x, y (float32), samples per segment, segment lengths)."""
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    steps = np.clip(np.ceil(length / step_m).astype(np.int64), 1, max_samples)
    seg = np.repeat(np.arange(len(a), dtype=np.int32), steps)
    first = (np.cumsum(steps) - steps).astype(np.float32)
    f = (np.arange(len(seg), dtype=np.float32) - np.repeat(first, steps) + np.float32(0.5)) / np.repeat(
        steps.astype(np.float32), steps
    )
    x = np.repeat(a[:, 0].astype(np.float32), steps) + f * np.repeat(d[:, 0].astype(np.float32), steps)
    y = np.repeat(a[:, 1].astype(np.float32), steps) + f * np.repeat(d[:, 1].astype(np.float32), steps)
    return seg, x, y, steps, length


def vehicle_blocked(
    a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray, blockers: np.ndarray, half_width_m: float = 0.9
) -> np.ndarray:
    """True for segments a[i] -> b[i] passing within ``half_width_m`` of a blocker centre other than
    their own ends (indices ``ia``/``ib`` into ``blockers``, -1 for an end that is not a blocker),
    strictly between the ends (projection parameter in (0, 1)). Float32, one (segments x blockers) pass."""
    a = np.asarray(a, np.float32).reshape(-1, 2)
    b = np.asarray(b, np.float32).reshape(-1, 2)
    q = np.asarray(blockers, np.float32).reshape(-1, 2)
    if len(a) == 0 or len(q) == 0:
        return np.zeros(len(a), dtype=bool)
    dx, dy = (b[:, 0] - a[:, 0])[:, None], (b[:, 1] - a[:, 1])[:, None]
    length = np.maximum(np.sqrt(dx * dx + dy * dy), np.float32(1e-6))
    ux, uy = dx / length, dy / length
    rx = q[None, :, 0] - a[:, 0:1]
    ry = q[None, :, 1] - a[:, 1:2]
    along = rx * ux + ry * uy  # metres along the segment
    hit = np.abs(rx * uy - ry * ux) < half_width_m
    hit &= (along > 0) & (along < length)
    m = np.arange(len(q))[None, :]
    hit &= (m != np.asarray(ia)[:, None]) & (m != np.asarray(ib)[:, None])
    return hit.any(axis=1)
