"""The run's pictures: what the evaluator keeps for them, the zoom, the ellipse scale, the files."""

from __future__ import annotations

import numpy as np
import pytest

from mapcontainer.hdmap.generator import generate_map
from mapcontainer.sim.config import load_scenario
from services.evaluator.core import Evaluator
from services.evaluator.plot import ellipse_scale, focus_box, render_birdseye, render_errors

from .test_runtime_roles import _fused, _truth


def _drive(burnin_s: float = 1.0) -> Evaluator:
    """3 s of a vehicle driving east at 10 m/s, 2 m off for the first second, 0.1 m after; one object."""
    ev = Evaluator("f", burnin_s=burnin_s, plot_every_s=0.1)
    for k in range(30):
        t = k * 0.1
        x = 10.0 * t
        off = 2.0 if t < 1.0 else 0.1
        ev.on_truth(_truth(t, (x, 0.0), [(x + 5.0, 3.0)]))
        ev.on_fused(_fused(t, (x + off, 0.0), [(x + 5.0, 3.3)]), None, None, now_wall=100 + t)
    return ev


def test_the_evaluator_keeps_the_error_of_every_fused_state_in_scenario_time() -> None:
    ev = _drive()
    v_err, o_err = ev.vehicle_errors["cv0"].array(), ev.object_errors.array()
    assert list(ev.vehicle_errors) == ["cv0"] and v_err.shape == (30, 2) and o_err.shape == (30, 3)
    t, obj_rmse, coverage = o_err[0]
    assert t == 0.0 and v_err[0, 1] == pytest.approx(2.0, abs=1e-5) and obj_rmse == pytest.approx(0.3, abs=1e-5)
    assert coverage == 1.0
    assert v_err[-1, 1] == pytest.approx(0.1, abs=1e-5)
    truth = np.array(ev.truth_vehicles["cv0"])
    assert truth.shape == (30, 3) and truth[-1, 0] == pytest.approx(2.9) and truth[-1, 1] == pytest.approx(29.0)
    assert list(ev.truth_obstacles) == [1]  # obstacles by their id, apart from the vehicles
    fused_obj = np.array(ev.fused_objects)
    assert fused_obj.shape == (30, 5) and fused_obj[-1, 3] == pytest.approx(34.0)  # t, id, cls, x, y


def test_focus_box_holds_the_points_fills_the_aspect_and_has_a_minimum_size() -> None:
    x0, x1, y0, y1 = focus_box(np.array([[100.0, -50.0], [160.0, -45.0]]), margin_m=10.0, aspect=1.5)
    assert x0 <= 90 and x1 >= 170 and y0 <= -60 and y1 >= -35
    assert (x1 - x0) / (y1 - y0) == pytest.approx(1.5)
    x0, x1, y0, y1 = focus_box(np.array([[0.0, 0.0]]), margin_m=1.0, min_size_m=40.0, aspect=1.0)
    assert (x1 - x0, y1 - y0) == pytest.approx((40.0, 40.0))
    assert np.isfinite(focus_box(np.full((3, 2), np.nan))).all()  # nothing to zoom to: a default view


def test_ellipse_scale_makes_small_ellipses_visible_and_leaves_big_ones_alone() -> None:
    assert ellipse_scale([0.2, 0.3, 0.4], view_m=100.0, target=0.03) == 10  # 3 m wanted, 0.3 m median
    assert ellipse_scale([5.0], view_m=100.0) == 1
    assert ellipse_scale([], view_m=100.0) == 1


def test_the_pictures_are_written(tmp_path) -> None:
    ev = _drive()
    hdmap = generate_map(load_scenario("paper-urban").map)
    render_birdseye(tmp_path / "birdseye.png", ev, hdmap, "test")
    render_errors(tmp_path / "errors.png", ev, "test")
    for name in ("birdseye.png", "errors.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000, name
    empty = Evaluator("f")  # a run that fused nothing still gets its pictures
    render_birdseye(tmp_path / "empty.png", empty, None, "test")
    render_errors(tmp_path / "empty-errors.png", empty, "test")
    assert (tmp_path / "empty.png").stat().st_size > 0 and (tmp_path / "empty-errors.png").stat().st_size > 0
