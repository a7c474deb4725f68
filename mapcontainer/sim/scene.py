"""Range indexes the sensors cull against: every actor's box at one instant, and a camera's map features.

A World builds one :class:`ActorBoxes` per tick and every vehicle's camera and detector share it. A
sensor asks :meth:`ActorBoxes.near` for the actors that can matter within its range (the targets it
may see, the boxes that may hide something from it), and a camera asks its :class:`RangeIndex` of the
map's landmarks and lane segments for those within its range; the projection and occlusion work is done
on those alone, so a frame's cost follows what its camera can see, not how many actors the world holds
or how large its map is.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from .actors import ActorState

__all__ = ["ActorBoxes", "RangeIndex"]

_MARGIN_M = 0.01  # a candidate query reaches this much farther than asked: its callers' exact tests decide


class RangeIndex:
    """Points in the plane (N, 2) with a k-d tree: which lie within a radius of a point. ``index`` False
    (or no points): no tree, every point is a candidate (the brute force)."""

    def __init__(self, xy, index: bool = True):
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        self.n = len(xy)
        self._tree = cKDTree(xy) if index and self.n else None

    def near(self, xy, radius_m: float) -> np.ndarray:
        """Indices (ascending) of the points within ``radius_m`` of ``xy`` (its first two coordinates).
        A superset (by ``_MARGIN_M``): callers keep their exact test."""
        if self._tree is None or not np.isfinite(radius_m):
            return np.arange(self.n)
        idx = self._tree.query_ball_point(np.asarray(xy, float)[:2], radius_m + _MARGIN_M)
        return np.sort(np.asarray(idx, dtype=int))


class ActorBoxes:
    """Actor boxes (oriented, standing on the ground) as arrays: ``p_map`` (A, 3) footprint centres,
    ``yaw`` (A,), ``size`` (A, 3) length, width, height, ``cls`` (A,), ``ids`` (A,).

    ``reach_m`` is the largest horizontal distance from a box's centre to its edge (half its diagonal):
    a box reaches within r of a point only if its centre is within r + reach_m. ``z_range_m``: the
    lowest and highest footprint centre (0 included). ``index`` False: no range index, :meth:`near`
    returns every actor (the brute force that culling is checked against).
    """

    def __init__(self, states: Sequence[ActorState], index: bool = True):
        n = len(states)
        self.ids = np.array([s.id for s in states], dtype=object)
        self.p_map = np.array([s.p_map for s in states], dtype=float).reshape(n, 3)
        self.yaw = np.array([s.yaw for s in states], dtype=float)
        self.size = np.array([s.size for s in states], dtype=float).reshape(n, 3)
        self.cls = np.array([s.cls for s in states], dtype=np.uint8)
        self.reach_m = float(np.hypot(self.size[:, 0], self.size[:, 1]).max(initial=0.0) / 2)
        self.z_range_m = (float(self.p_map[:, 2].min(initial=0.0)), float(self.p_map[:, 2].max(initial=0.0)))
        self._index = {aid: i for i, aid in enumerate(self.ids)}
        self._range = RangeIndex(self.p_map[:, :2], index)

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, actor_id: str) -> int:
        """The position of actor ``actor_id`` (KeyError for an actor not there)."""
        return self._index[actor_id]

    def near(self, xy, radius_m: float, skip: int | None = None) -> np.ndarray:
        """Indices (ascending) of the actors whose footprint centre is within ``radius_m`` of ``xy``
        horizontally, ``skip`` left out. A superset (by ``_MARGIN_M``): callers keep their exact test."""
        idx = self._range.near(xy, radius_m)
        return idx if skip is None else idx[idx != skip]

    def corners(self, idx: np.ndarray) -> np.ndarray:
        """The 8 corners (K, 8, 3) of the boxes ``idx`` in the map frame (:func:`~.actors.box_corners` each)."""
        length, w, h = self.size[idx, 0, None], self.size[idx, 1, None], self.size[idx, 2, None]
        x = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * length / 2
        y = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * w / 2
        z = np.array([0, 0, 0, 0, 1, 1, 1, 1]) * h
        c, s = np.cos(self.yaw[idx])[:, None], np.sin(self.yaw[idx])[:, None]
        return np.stack([c * x - s * y, s * x + c * y, z], axis=2) + self.p_map[idx, None, :]


def as_boxes(actors: ActorBoxes | Sequence[ActorState]) -> ActorBoxes:
    """``actors`` as :class:`ActorBoxes` (a list of states is indexed once here)."""
    return actors if isinstance(actors, ActorBoxes) else ActorBoxes(actors)
