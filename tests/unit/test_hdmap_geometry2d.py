"""Plane geometry of the map importers: offset polylines, strips, simple polygons, principal axes."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.hdmap.geometry2d import (
    dedup,
    distance_to_polyline,
    is_simple_polygon,
    offset_polyline,
    principal_axis,
    strip_outline,
)


def test_offset_of_a_right_angle_keeps_the_distance_on_both_legs() -> None:
    line = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 1.0], [10.0, 10.0, 1.0]])  # east, then north: a left turn
    left = offset_polyline(line, 2.0)
    assert np.allclose(left, [[0, 2, 1], [8, 2, 1], [8, 10, 1]])  # the corner is the legs' intersection
    right = offset_polyline(line, -2.0)
    assert np.allclose(right, [[0, -2, 1], [12, -2, 1], [12, 10, 1]])
    for p in np.linspace(left[0], left[1], 5):
        assert distance_to_polyline(p, line) == pytest.approx(2.0)


def test_a_hairpin_mitre_is_capped() -> None:
    line = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.1, 0.0]])
    out = offset_polyline(line, 1.0)
    assert np.linalg.norm(out[1, :2] - line[1, :2]) <= 4.0 + 1e-9


def test_repeated_vertices_are_dropped_and_a_point_is_refused() -> None:
    assert len(dedup([[0, 0, 0], [0, 0, 0], [1, 0, 0]])) == 2
    with pytest.raises(ValueError, match="2 distinct vertices"):
        offset_polyline([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]], 1.0)


def test_strip_outline_is_a_rectangle_for_a_straight_line() -> None:
    poly = strip_outline(np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]), 2.0)
    assert np.allclose(poly, [[0, 1], [4, 1], [4, -1], [0, -1]])
    assert is_simple_polygon(poly)


@pytest.mark.parametrize(
    ("polygon", "simple"),
    [
        ([[0, 0], [1, 0], [1, 1], [0, 1]], True),
        ([[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]], True),  # concave
        ([[0, 0], [1, 1], [1, 0], [0, 1]], False),  # a bow tie
        ([[0, 0], [2, 0], [1, 0], [1, 1]], False),  # an edge doubling back on the previous one
        ([[0, 0], [1, 0], [0, 0], [0, 1]], False),  # a repeated vertex
        ([[0, 0], [1, 0]], False),
    ],
)
def test_is_simple_polygon(polygon, simple: bool) -> None:
    assert is_simple_polygon(polygon) is simple


def test_principal_axis_spans_a_long_rectangle() -> None:
    axis = principal_axis([[0, 0], [10, 0], [10, 2], [0, 2]], z=0.5)
    assert np.allclose(sorted(axis[:, 0]), [0, 10]) and np.allclose(axis[:, 1], 1) and np.allclose(axis[:, 2], 0.5)
    with pytest.raises(ValueError, match="extent"):
        principal_axis([[1, 1], [1, 1], [1, 1]])
