"""The graph's values as arrays (mapcontainer.fusion.values) against GTSAM's own look-ups."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, S, X

from mapcontainer.fusion.values import vector_table, vectors


def test_vectors_are_the_values_of_their_keys_whatever_else_the_values_hold():
    values = gtsam.Values()
    rng = np.random.default_rng(0)
    keys = [S(7), B(1), S(0), S(300), B(0)]
    for k in keys:
        values.insert(k, rng.normal(size=6))
    values.insert(X(3), gtsam.Pose3())  # poses are not in the table
    table = vector_table(values)
    want = [S(300), B(0), S(0), S(0), B(1), S(7)]
    np.testing.assert_array_equal(vectors(table, want), np.array([values.atVector(k) for k in want]))
    assert vectors(table, []).shape == (0, 6)
    with pytest.raises(KeyError, match="x3"):
        vectors(table, [S(0), X(3)])
    assert vector_table(gtsam.Values())[1].shape == (0, 6)
