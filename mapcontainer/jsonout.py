"""JSON that strict parsers accept: NaN and infinity (a figure with nothing to measure) become null."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

__all__ = ["dumps", "finite_or_null", "rounded"]


def finite_or_null(o: Any) -> Any:
    """``o`` with every non-finite float (also inside dicts, lists and numpy scalars) replaced by None."""
    if isinstance(o, dict):
        return {str(k): finite_or_null(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [finite_or_null(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def dumps(o: Any, **kw: Any) -> str:
    """``json.dumps`` of :func:`finite_or_null` (``NaN`` is not JSON: jq and most parsers reject it)."""
    return json.dumps(finite_or_null(o), allow_nan=False, **kw)


def rounded(x: float | None, nd: int = 4) -> float:
    """A figure for a table: ``x`` rounded to ``nd`` decimals; NaN when there is none (None, NaN, infinite)."""
    return float(round(x, nd)) if x is not None and math.isfinite(x) else float("nan")
