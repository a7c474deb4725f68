"""Procedural HD maps: a two-way ring road with landmarks, sidewalks and crossings.

The road's reference line is a rounded rectangle centred on the origin, driven
counter-clockwise (CCW) by the outer lanes and clockwise by the inner ones (right-hand traffic).
Offsets are measured outward from the reference line (positive = outside the ring).

Layout across the road (offset, m), for ``lanes_per_direction = 2`` and 3.5 m lanes::

    -9.5 inner sidewalk | -7 solid | -3.5 dashed | 0 solid (centre) | +3.5 dashed | +7 solid | +9.5 outer sidewalk

Landmarks stand at the curb (``curb_offset_m`` beyond the road edge) on both sides.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .model import HDMap, LaneCenterline, LaneLine, PointFeature, PoleFeature, Polyline, WalkableArea

__all__ = ["MapSpec", "generate_map", "ring_line"]


class MapSpec(BaseModel):
    """Parameters of a generated ring-road map (metres unless named otherwise)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = "ring"
    length_m: float = Field(160.0, gt=20, description="extent of the reference line along x")
    width_m: float = Field(80.0, gt=20, description="extent of the reference line along y")
    corner_radius_m: float = Field(18.0, gt=8, description="radius of the reference line at the corners")
    lanes_per_direction: int = Field(2, ge=1, le=4)
    lane_width_m: float = Field(3.5, gt=2)
    dash_m: float = Field(3.0, gt=0, description="painted length of a dashed line")
    gap_m: float = Field(6.0, gt=0, description="blank length of a dashed line")
    lamps: int = Field(14, ge=0, description="lamp posts (pole features), alternating sides")
    lamp_height_m: float = Field(8.0, gt=1)
    traffic_lights: int = Field(4, ge=0, description="traffic lights, in pairs at the crossings")
    traffic_light_height_m: float = Field(5.0, gt=1)
    signs: int = Field(4, ge=0, description="traffic signs")
    sign_height_m: float = Field(2.2, gt=0.5)
    crossings: int = Field(2, ge=0, description="pedestrian crossings on the straight sections")
    sidewalk_width_m: float = Field(3.0, gt=0.5)
    curb_offset_m: float = Field(1.0, ge=0, description="landmark distance beyond the road edge")
    jitter_m: float = Field(4.0, ge=0, description="random shift of landmark positions along the road")
    seed: int = 0


def ring_line(spec: MapSpec, offset: float, spacing: float = 1.0, z: float = 0.0) -> np.ndarray:
    """Points (N, 3), CCW, of the rounded rectangle offset outward by ``offset`` from the reference line."""
    r = spec.corner_radius_m + offset
    if r <= 0.5:
        raise ValueError(f"offset {offset} m collapses the corner radius {spec.corner_radius_m} m")
    hx = spec.length_m / 2 - spec.corner_radius_m
    hy = spec.width_m / 2 - spec.corner_radius_m
    pts = []
    # Start at the middle of the bottom straight, heading +x (east).
    corners = [(hx, -hy, -np.pi / 2), (hx, hy, 0.0), (-hx, hy, np.pi / 2), (-hx, -hy, np.pi)]
    prev_end = np.array([0.0, -hy - r])
    for cx, cy, a0 in corners:
        start = np.array([cx + r * np.cos(a0), cy + r * np.sin(a0)])
        n = max(int(np.linalg.norm(start - prev_end) / spacing), 1)
        pts.extend(prev_end + (start - prev_end) * t for t in np.arange(n) / n)
        n_arc = max(int(np.ceil(r * np.pi / 2 / spacing)), 4)
        for a in a0 + np.arange(n_arc) / n_arc * np.pi / 2:
            pts.append(np.array([cx + r * np.cos(a), cy + r * np.sin(a)]))
        prev_end = np.array([cx + r * np.cos(a0 + np.pi / 2), cy + r * np.sin(a0 + np.pi / 2)])
    end = np.array([0.0, -hy - r])
    n = max(int(np.linalg.norm(end - prev_end) / spacing), 1)
    pts.extend(prev_end + (end - prev_end) * t for t in np.arange(n) / n)
    xy = np.array(pts)
    return np.column_stack([xy, np.full(len(xy), z)])


def _straight_arcs(ref: Polyline, spec: MapSpec) -> list[tuple[float, float]]:
    """Arc-length intervals of the reference line's straight sections (bottom, right, top, left)."""
    hx = spec.length_m / 2 - spec.corner_radius_m
    hy = spec.width_m / 2 - spec.corner_radius_m
    q = spec.corner_radius_m * np.pi / 2
    bottom = (0.0, hx)
    right = (hx + q, hx + q + 2 * hy)
    top = (right[1] + q, right[1] + q + 2 * hx)
    left = (top[1] + q, top[1] + q + 2 * hy)
    last = (left[1] + q, ref.length)
    return [(last[0], last[1] + bottom[1]), right, top, left]


def generate_map(spec: MapSpec) -> HDMap:
    """A deterministic ring-road map for ``spec`` (same spec, same map)."""
    rng = np.random.default_rng(spec.seed)
    n, w = spec.lanes_per_direction, spec.lane_width_m
    edge = n * w
    hd = HDMap(name=spec.name)
    fid = iter(range(1, 1_000_000))

    # Lane lines: edges and centre solid, lane dividers dashed.
    for k in range(-n, n + 1):
        kind = "solid" if k in (-n, 0, n) else "dashed"
        hd.lane_lines.append(
            LaneLine(next(fid), ring_line(spec, k * w), kind, closed=True, dash_m=spec.dash_m, gap_m=spec.gap_m)
        )
    # Lane centre lines: outer lanes CCW, inner lanes CW (reversed).
    for k in range(n):
        off = (k + 0.5) * w
        hd.centerlines.append(LaneCenterline(next(fid), ring_line(spec, off), closed=True, width_m=w))
        hd.centerlines.append(LaneCenterline(next(fid), ring_line(spec, -off)[::-1].copy(), closed=True, width_m=w))

    # Sidewalks on both sides.
    side_off = edge + spec.curb_offset_m + spec.sidewalk_width_m / 2
    for sign in (+1, -1):
        inner = ring_line(spec, sign * (side_off - spec.sidewalk_width_m / 2), spacing=2.0)
        outer = ring_line(spec, sign * (side_off + spec.sidewalk_width_m / 2), spacing=2.0)
        poly = np.vstack([outer[:, :2], inner[::-1, :2]])
        hd.walkable.append(
            WalkableArea(next(fid), "sidewalk", poly, ring_line(spec, sign * side_off, spacing=2.0), closed=True)
        )

    ref = Polyline(ring_line(spec, 0.0), closed=True)
    straights = _straight_arcs(ref, spec)

    # Crossings at the middle of straight sections (bottom first, then top, right, left).
    crossing_s = []
    for k in [0, 2, 1, 3][: spec.crossings]:
        a, b = straights[k]
        s = (a + b) / 2
        crossing_s.append(s)
        c, t = ref.point_at(s), ref.tangent_at(s)
        nrm = np.array([t[1], -t[0], 0.0])  # outward normal of a CCW loop
        half = 2.0
        path = np.stack([c - nrm * side_off, c + nrm * side_off])
        poly = np.array(
            [
                (c - nrm * side_off + t * half)[:2],
                (c + nrm * side_off + t * half)[:2],
                (c + nrm * side_off - t * half)[:2],
                (c - nrm * side_off - t * half)[:2],
            ]
        )
        hd.walkable.append(WalkableArea(next(fid), "crossing", poly, path, closed=False))

    curb = edge + spec.curb_offset_m

    def place(s: float, side: int, height: float):
        c, t = ref.point_at(s), ref.tangent_at(s)
        nrm = np.array([t[1], -t[0], 0.0])
        base = c + nrm * side * curb
        base[2] = 0.0
        return base, base + np.array([0.0, 0.0, height])

    # Traffic lights: a pair at each crossing, one on each side, a few metres before the stripes.
    for i in range(spec.traffic_lights):
        s = crossing_s[(i // 2) % len(crossing_s)] if crossing_s else ref.length * i / spec.traffic_lights
        side = +1 if i % 2 == 0 else -1
        _, top = place(s - side * 6.0, side, spec.traffic_light_height_m)
        hd.points.append(PointFeature(next(fid), "traffic_light", top))

    # Lamps evenly spread, alternating sides; signs offset between them.
    def spread(count: int, phase: float) -> np.ndarray:
        s = (np.arange(count) + phase) / max(count, 1) * ref.length
        return s + rng.uniform(-spec.jitter_m, spec.jitter_m, count)

    for i, s in enumerate(spread(spec.lamps, 0.25)):
        base, top = place(s, +1 if i % 2 == 0 else -1, spec.lamp_height_m)
        hd.poles.append(PoleFeature(next(fid), "lamp", base, top))
    for i, s in enumerate(spread(spec.signs, 0.6)):
        _, top = place(s, -1 if i % 2 == 0 else +1, spec.sign_height_m)
        hd.points.append(PointFeature(next(fid), "sign", top))
    return hd
