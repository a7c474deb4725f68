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
    with np.errstate(over="ignore"):
        x = x ^ (x >> np.uint64(30))
        x = x * _M1
        x = x ^ (x >> np.uint64(27))
        x = x * _M2
        return x ^ (x >> np.uint64(31))


def link_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unordered link keys from node keys (uint64 arrays): key(a, b) == key(b, a)."""
    a = np.asarray(a, dtype=np.uint64)
    b = np.asarray(b, dtype=np.uint64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    with np.errstate(over="ignore"):
        return _mix(_mix(lo) ^ (hi * _GOLDEN))


def directed_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Ordered link keys: key(a, b) != key(b, a)."""
    a = np.asarray(a, dtype=np.uint64)
    b = np.asarray(b, dtype=np.uint64)
    with np.errstate(over="ignore"):
        return _mix(_mix(a) + b * _GOLDEN + np.uint64(1))


def uniforms(seed: int, key: np.ndarray, counter: np.ndarray, lane: int = 0) -> np.ndarray:
    """U(0, 1) per (seed, key, counter, lane), open at both ends, broadcast over key and counter."""
    key = np.asarray(key, dtype=np.uint64)
    counter = np.asarray(counter, dtype=np.uint64)
    s = _mix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ np.uint64((lane * 0x632BE59BD9B4E019) & 0xFFFFFFFFFFFFFFFF))
    with np.errstate(over="ignore"):
        x = _mix(_mix(key ^ s) + counter * _GOLDEN)
    return ((x >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)


def normals(seed: int, key: np.ndarray, counter: np.ndarray, lane: int = 0) -> np.ndarray:
    """N(0, 1) per (seed, key, counter, lane), by the inverse normal CDF of :func:`uniforms`."""
    return ndtri(uniforms(seed, key, counter, lane))
