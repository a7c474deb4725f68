"""An erroneous copy of an HD map: what a vehicle carries when the world has moved on from the survey.

Error model (every length in metres, horizontal sigmas per axis):

* a smooth displacement field d(x, y) shared by every feature (survey-trajectory drift), each of its
  three components a Gaussian random field with covariance ``sigma^2 exp(-|p - q|^2 / (2 l^2))``,
  drawn as random Fourier features: ``d(p) = sigma sqrt(2 / K) sum_k a_k cos(w_k . p + b_k)`` with
  ``a_k ~ N(0, 1)``, ``w_k ~ N(0, I / l^2)``, ``b_k ~ U(0, 2 pi)`` (Rahimi & Recht 2007);
* for each lane line a field of its own (``line_sigma_m`` over ``line_length_m``): lines move
  smoothly, correlated along the line rather than white per vertex;
* for each landmark an independent offset (poles move rigidly: base and top together);
* landmarks missing from the map (present in the world) and extra ones (in the map, not in the world).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .model import HDMap, PointFeature, PoleFeature, Polyline

__all__ = ["MapError", "SmoothField", "perturb_map"]

_FEATURES = 64  # random Fourier features per field component


class SmoothField:
    """A smooth random displacement field R^2 -> R^3 (module docstring) for one draw of ``rng``."""

    def __init__(self, sigma_h: float, sigma_v: float, length_m: float, rng: np.random.Generator):
        if length_m <= 0:
            raise ValueError(f"length_m must be positive, got {length_m}")
        self.sigma = np.array([sigma_h, sigma_h, sigma_v], dtype=float)
        self.w = rng.normal(0.0, 1.0 / length_m, (3, _FEATURES, 2))
        self.b = rng.uniform(0.0, 2 * np.pi, (3, _FEATURES))
        self.a = rng.normal(0.0, 1.0, (3, _FEATURES))

    def __call__(self, p) -> np.ndarray:
        """Displacements (N, 3) at points p (N, >=2) (their x, y)."""
        xy = np.asarray(p, dtype=float).reshape(-1, np.shape(p)[-1])[:, :2]
        phase = np.einsum("ckj,nj->cnk", self.w, xy) + self.b[:, None, :]
        d = np.sqrt(2.0 / _FEATURES) * np.einsum("ck,cnk->nc", self.a, np.cos(phase))
        return d * self.sigma


@dataclass(frozen=True)
class MapError:
    """The error model's parameters (module docstring); all zero: an exact copy."""

    field_sigma_m: tuple[float, float] = (0.0, 0.0)  # horizontal per axis, vertical
    field_length_m: float = 50.0
    line_sigma_m: float = 0.0  # horizontal per axis
    line_length_m: float = 15.0
    landmark_sigma_m: tuple[float, float] = (0.0, 0.0)  # horizontal per axis, vertical
    p_missing: float = 0.0
    p_extra: float = 0.0  # extra landmarks: Poisson(p_extra x landmarks)
    extra_shift_m: tuple[float, float] = (10.0, 30.0)  # along the road from the landmark an extra one copies


def perturb_map(hdmap: HDMap, err: MapError, seed: np.random.SeedSequence) -> HDMap:
    """A copy of ``hdmap`` with the errors of ``err`` drawn from ``seed`` (deterministic).

    Each part draws from its own child stream (field, lines, landmarks, missing, extra), so changing one
    parameter leaves the other parts' draws as they were. Feature ids are kept; extra landmarks get new
    ids above the largest one.
    """
    ss_field, ss_lines, ss_marks, ss_missing, ss_extra = seed.spawn(5)
    field = SmoothField(*err.field_sigma_m, err.field_length_m, np.random.default_rng(ss_field))
    rng_lines = np.random.default_rng(ss_lines)
    rng_marks = np.random.default_rng(ss_marks)
    rng_missing = np.random.default_rng(ss_missing)
    rng_extra = np.random.default_rng(ss_extra)

    lane_lines = []
    for line in hdmap.lane_lines:
        own = SmoothField(err.line_sigma_m, 0.0, err.line_length_m, rng_lines)
        lane_lines.append(replace(line, points=line.points + field(line.points) + own(line.points)))
    centerlines = [replace(c, points=c.points + field(c.points)) for c in hdmap.centerlines]
    walkable = [
        replace(w, polygon=w.polygon + field(w.polygon)[:, :2], path=w.path + field(w.path)) for w in hdmap.walkable
    ]

    sh, sv = err.landmark_sigma_m
    own_sigma = np.array([sh, sh, sv])
    points = [
        replace(f, p_map=f.p_map + field(f.p_map)[0] + rng_marks.normal(size=3) * own_sigma) for f in hdmap.points
    ]
    poles = []
    for f in hdmap.poles:
        d = field(f.base)[0] + rng_marks.normal(size=3) * own_sigma
        poles.append(replace(f, base=f.base + d, top=f.top + d))

    keep_pt = rng_missing.random(len(points)) >= err.p_missing
    keep_pole = rng_missing.random(len(poles)) >= err.p_missing
    points = [f for f, k in zip(points, keep_pt, strict=True) if k]
    poles = [f for f, k in zip(poles, keep_pole, strict=True) if k]

    extra_pts, extra_poles = _extra_landmarks(hdmap, err, rng_extra, field)
    return HDMap(
        name=hdmap.name,
        points=points + extra_pts,
        poles=poles + extra_poles,
        lane_lines=lane_lines,
        centerlines=centerlines,
        walkable=walkable,
        junctions=list(hdmap.junctions),
    )


def _extra_landmarks(hdmap: HDMap, err: MapError, rng: np.random.Generator, field: SmoothField):
    """Landmarks that are in the map but not in the world: copies of real ones moved along the road."""
    marks = [*hdmap.points, *hdmap.poles]
    n = int(rng.poisson(err.p_extra * len(marks))) if marks else 0
    if n == 0 or not hdmap.centerlines:
        return [], []
    road = Polyline(hdmap.centerlines[0].points, hdmap.centerlines[0].closed)
    next_id = 1 + max(
        [f.id for f in marks]
        + [x.id for x in hdmap.lane_lines]
        + [x.id for x in hdmap.centerlines]
        + [x.id for x in hdmap.walkable]
    )
    points, poles = [], []
    for i in range(n):
        src = marks[int(rng.integers(len(marks)))]
        shift = rng.uniform(*err.extra_shift_m) * rng.choice([-1.0, 1.0])
        ref = src.p_map if isinstance(src, PointFeature) else src.base
        move = _along_road(road, ref, shift)
        fid = next_id + i
        if isinstance(src, PointFeature):
            p = move(src.p_map)
            points.append(PointFeature(fid, src.cls, p + field(p)[0]))
        else:
            base, top = move(src.base), move(src.top)
            d = field(base)[0]
            poles.append(PoleFeature(fid, src.cls, base + d, top + d))
    return points, poles


def _along_road(road: Polyline, ref: np.ndarray, shift_m: float):
    """A function moving points near ``ref`` by ``shift_m`` along ``road``, keeping their offset from it
    in the road's (tangent, normal) frame."""
    s = road.project(ref)
    c0, t0 = road.point_at(s), road.tangent_at(s)
    c1, t1 = road.point_at(s + shift_m), road.tangent_at(s + shift_m)
    t0, t1 = t0 * [1, 1, 0], t1 * [1, 1, 0]
    n0 = np.array([-t0[1], t0[0], 0.0])
    n1 = np.array([-t1[1], t1[0], 0.0])

    def move(p: np.ndarray) -> np.ndarray:
        d = np.asarray(p, dtype=float) - c0
        return c1 + t1 * (d[:2] @ t0[:2]) + n1 * (d[:2] @ n0[:2]) + np.array([0.0, 0.0, d[2]])

    return move
