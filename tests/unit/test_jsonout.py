"""Everything the commands print or write is JSON a strict parser accepts."""

from __future__ import annotations

import json

import numpy as np

from mapcontainer import jsonout


def test_non_finite_figures_become_null() -> None:
    doc = {"rmse": float("nan"), "p99": np.float64("inf"), "rows": [(1.5, -np.inf)], 3: np.int64(4)}
    text = jsonout.dumps(doc)
    assert json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c))) == {
        "rmse": None,
        "p99": None,
        "rows": [[1.5, None]],
        "3": 4,
    }
