"""mapcontainer.metrics: every figure against a closed form or scipy (RMSE, NEES, chi-square bands, percentiles,
the GOSPA assignment's cutoff and order)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mapcontainer import metrics as m


def test_chi2_quantile_is_scipys() -> None:
    assert m.chi2_quantile(0.95, 2) == pytest.approx(stats.chi2.ppf(0.95, 2), rel=1e-12)
    assert m.chi2_quantile([0.025, 0.975], 6) == pytest.approx(stats.chi2.ppf([0.025, 0.975], 6), rel=1e-12)
    assert m.chi2_quantile(0.5, 1) == pytest.approx(0.454936423119572, rel=1e-12)


def test_rmse_of_rows() -> None:
    assert m.rmse([[3.0, 4.0], [0.0, 0.0]]) == pytest.approx(np.sqrt(12.5))  # sqrt(mean(25, 0))
    assert m.rmse([1.0, 3.0]) == pytest.approx(np.sqrt(5.0))  # 1-D: one component per row
    assert m.rmse(np.ones((2, 2, 2))) == pytest.approx(2.0)  # rows flattened: ||e||^2 = 4
    assert np.isnan(m.rmse([])) and np.isnan(m.rmse(np.zeros((0, 3))))


def test_nees_rows_and_one_vector() -> None:
    e = np.array([[1.0, 2.0], [3.0, 0.0]])
    P = np.array([[[1.0, 0.0], [0.0, 4.0]], [[9.0, 0.0], [0.0, 1.0]]])
    assert m.nees(e, P).tolist() == pytest.approx([2.0, 1.0])
    full = np.array([[2.0, 1.0], [1.0, 2.0]])  # e^T P^-1 e with P^-1 = [[2, -1], [-1, 2]] / 3
    assert m.nees([1.0, 1.0], full).tolist() == pytest.approx([2.0 / 3.0])
    assert m.nees([1.0, -1.0], full).shape == (1,) and m.nees([1.0, -1.0], full)[0] == pytest.approx(2.0)


def test_anees_band() -> None:
    lo, hi = m.anees_band(3, 10)
    assert (lo, hi) == pytest.approx(tuple(stats.chi2.ppf([0.025, 0.975], 30) / 10), rel=1e-12)
    lo, hi = m.anees_band(2, 1, confidence=0.9)
    assert (lo, hi) == pytest.approx(tuple(stats.chi2.ppf([0.05, 0.95], 2)), rel=1e-12)
    assert isinstance(lo, float) and isinstance(hi, float)
    for n in (0, -1):
        with pytest.raises(ValueError, match=f"n must be positive, got {n}"):
            m.anees_band(3, n)


def test_percentile() -> None:
    assert m.percentile([1.0, 2.0, 3.0, 4.0, 5.0], 50) == 3.0
    assert m.percentile([0.0, 10.0], 95) == pytest.approx(9.5)
    assert np.isnan(m.percentile([], 50))


def test_match_objects_cutoff_and_order() -> None:
    t = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    e = np.array([[10.5, 0.0, 5.0], [0.0, 2.9, -3.0]])  # heights differ: only x-y counts
    ti, fi = m.match_objects(e, t)
    assert (ti.tolist(), fi.tolist()) == ([0, 1], [1, 0])
    ti, fi = m.match_objects(e, t, gate_m=2.9)  # a pair at exactly the cutoff is no pair
    assert (ti.tolist(), fi.tolist()) == ([1], [0])
    ti, fi = m.match_objects(e, t, gate_m=0.5 + 1e-9)
    assert (ti.tolist(), fi.tolist()) == ([1], [0])
    # order 1 and order 2 choose different pairs: identity costs d = 0 and 4, the cross pairs 2.1 and 2.1;
    # sum d prefers the identity (4 < 4.2), sum d^2 the cross pairs (8.82 < 16)
    ang = 2 * np.arcsin(2.0 / 2.1)
    t2 = np.array([[0.0, 0.0], [2.1, 0.0]])
    e2 = np.array([[0.0, 0.0], [2.1 * np.cos(ang), 2.1 * np.sin(ang)]])
    assert np.linalg.norm(e2[1] - t2[1]) == pytest.approx(4.0)
    ti, fi = m.match_objects(e2, t2, gate_m=10.0, order=1)
    assert (ti.tolist(), fi.tolist()) == ([0, 1], [0, 1])
    ti, fi = m.match_objects(e2, t2, gate_m=10.0)  # order 2 by default
    assert (ti.tolist(), fi.tolist()) == ([0, 1], [1, 0])
    ti, fi = m.match_objects(
        e2, t2, gate_m=3.0
    )  # the cutoff caps the 4 m pair at 9: the identity costs 9, the cross 8.82
    assert (ti.tolist(), fi.tolist()) == ([0, 1], [1, 0])
    ti, fi = m.match_objects(e2, t2, gate_m=2.0)  # cross pairs beyond it: the identity keeps its 0 m pair
    assert (ti.tolist(), fi.tolist()) == ([0], [0])


def test_match_objects_empty_and_bad_arguments() -> None:
    for est, true in ((np.zeros((0, 3)), np.zeros((2, 3))), (np.zeros((2, 3)), np.zeros((0, 3)))):
        ti, fi = m.match_objects(est, true)
        assert (ti.tolist(), fi.tolist()) == ([], []) and ti.dtype.kind == fi.dtype.kind == "i"
    with pytest.raises(ValueError, match="gate_m must be > 0 and order >= 1, got -1.0, 2"):
        m.match_objects(np.zeros((1, 2)), np.zeros((1, 2)), gate_m=-1.0)
    with pytest.raises(ValueError, match="order >= 1"):
        m.match_objects(np.zeros((1, 2)), np.zeros((1, 2)), order=0)
    ti, fi = m.match_objects(np.zeros((1, 2)), np.zeros((1, 2)), order=1)
    assert (ti.tolist(), fi.tolist()) == ([0], [0])


def test_match_objects_default_cutoff_is_three_metres() -> None:
    assert m.match_objects(np.array([[2.99, 0.0]]), np.array([[0.0, 0.0]]))[0].tolist() == [0]
    assert m.match_objects(np.array([[3.0, 0.0]]), np.array([[0.0, 0.0]]))[0].tolist() == []


def test_match_objects_takes_empty_lists() -> None:
    for est, true in (([], [[0.0, 0.0, 0.0]]), ([[0.0, 0.0, 0.0]], [])):
        ti, fi = m.match_objects(est, true)
        assert (ti.tolist(), fi.tolist()) == ([], [])


def test_integer_inputs_are_computed_in_floats() -> None:
    """int16 errors and positions would overflow if squared or subtracted in their own type."""
    assert m.rmse(np.array([[200, 0]], dtype=np.int16)) == 200.0
    far = np.array([[30000, 0]], dtype=np.int16)
    ti, _ = m.match_objects(far, -far, gate_m=1e9)
    assert ti.tolist() == [0]
    ti, _ = m.match_objects(-far, far, gate_m=59999.0)  # 60000 m apart: beyond the cutoff
    assert ti.tolist() == []
