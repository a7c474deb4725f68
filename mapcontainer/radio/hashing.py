"""Counter-based random numbers: a value per (seed, key, counter), vectorised and stable everywhere.

The radio model draws per link and per message. A generator object per link would make results
depend on the order links are first seen; instead each draw is a hash of (seed, key, counter, lane)
through SplitMix64's finaliser (Steele, Lea and Flood, "Fast splittable pseudorandom number
generators", OOPSLA 2014), which passes BigCrush on a counter. ``key`` is a 64-bit link or node id
(:func:`node_key`, :func:`link_keys`, hashed from the ids' bytes with BLAKE2b, so it is stable across
processes and Python versions).
"""

from __future__ import annotations

import hashlib

import numpy as np
from scipy.special import ndtri

__all__ = ["directed_keys", "link_keys", "node_key", "normals", "uniforms"]

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def node_key(name: str) -> int:
    """A stable 64-bit key of a node id."""
    return int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little")


def _mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on a uint64 array (arrays wrap silently; numpy scalars would warn)."""
    x = x ^ (x >> np.uint64(30))
    x = x * _M1
    x = x ^ (x >> np.uint64(27))
    x = x * _M2
    return x ^ (x >> np.uint64(31))


def _u64(a) -> np.ndarray:
    return np.atleast_1d(np.asarray(a, dtype=np.uint64))


def link_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unordered link keys from node keys (uint64 arrays): key(a, b) == key(b, a)."""
    a, b = _u64(a), _u64(b)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    return _mix(_mix(lo) ^ (hi * _GOLDEN))


def directed_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Ordered link keys: key(a, b) != key(b, a)."""
    a, b = _u64(a), _u64(b)
    return _mix(_mix(a) + b * _GOLDEN + np.uint64(1))


def uniforms(seed: int, key: np.ndarray, counter: np.ndarray, lane=0) -> np.ndarray:
    """U(0, 1) per (seed, key, counter, lane), open at both ends; key, counter and lane broadcast
    (the result is at least 1-d)."""
    lane = np.atleast_1d(np.asarray(lane, dtype=np.int64)).astype(np.uint64)
    s = _mix(_u64(seed & 0xFFFFFFFFFFFFFFFF) ^ (lane * np.uint64(0x632BE59BD9B4E019)))
    x = _mix(_mix(_u64(key) ^ s) + _u64(counter) * _GOLDEN)
    return ((x >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)


def normals(seed: int, key: np.ndarray, counter: np.ndarray, lane: int = 0) -> np.ndarray:
    """N(0, 1) per (seed, key, counter, lane), by the inverse normal CDF of :func:`uniforms`."""
    return ndtri(uniforms(seed, key, counter, lane))
