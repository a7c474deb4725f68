"""A graph's values as arrays: the batched look-ups of many keys at once (one C++ call for every value of a
kind, instead of one ``Values.atVector`` per key, a few microseconds each from Python)."""

from __future__ import annotations

import gtsam
import numpy as np

__all__ = ["vector_table", "vectors"]


def vector_table(values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
    """Every Vector6 of the host's graph (track states ``s``, persistent errors ``b``) at once: (keys,
    rows), keys sorted, for :func:`vectors`."""
    keys = np.array(values.keys(), dtype=np.uint64)  # sorted; a key's symbol character is its top byte
    sym = keys >> np.uint64(56)
    out_k, out_v = [], []
    for c in "bs":  # in key order
        out_k.append(keys[sym == ord(c)])
        out_v.append(gtsam.utilities.extractVectors(values, c).reshape(-1, 6))
    return np.concatenate(out_k), np.concatenate(out_v)


def vectors(table: tuple[np.ndarray, np.ndarray], keys) -> np.ndarray:
    """The rows (N, 6) of ``keys`` (all in the table) in a :func:`vector_table`."""
    k, v = table
    q = np.asarray(keys, dtype=np.uint64).reshape(-1)
    rows = np.searchsorted(k, q)
    found = rows < len(k)
    found[found] = k[rows[found]] == q[found]
    if not found.all():
        raise KeyError(f"not in the table: {[gtsam.DefaultKeyFormatter(int(x)) for x in q[~found]]}")
    return v[rows]
