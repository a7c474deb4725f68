"""The host's inner loops, compiled with numba when it is installed (the ``fast`` extra), else run as the
same numpy code in the interpreter: one algorithm, two ways to run it.

``COMPILED`` says whether numba is there. The kernels take flat arrays (no Python objects), so that
numba can compile them; the callers (:mod:`.solver`) gather those arrays. Compiled kernels are cached
on disk (numba's ``cache=True``): the first process that needs one compiles it (seconds, more on a busy
machine), later ones load it (under a second). So a caller uses the compiled kernel only for work large
enough to need it (:func:`clique_recursion`'s ``compiled``), and a small window (the unit tests, a
handful of vehicles) never waits for numba. Compiled and interpreted results agree to rounding (the
triangular inverse is a compiled loop against LAPACK's ``dtrtri``; the matrix products go to BLAS in
both: at 50 vehicles / 500 objects the covariances differ by 1e-15 of their size).
"""

from __future__ import annotations

import types

import numpy as np
from scipy.linalg import lapack

try:
    import numba
except ImportError:  # the fast extra is not installed: the same kernels, interpreted
    numba = None

__all__ = ["COMPILED", "clique_recursion"]

COMPILED = numba is not None


def _upper_inverse_lapack(R: np.ndarray) -> np.ndarray:
    """R^-1 of an upper-triangular R with non-zero diagonal (LAPACK dtrtri, unblocked for small n)."""
    Rinv, _ = lapack.dtrtri(R, lower=0)
    return Rinv


def _upper_inverse_loops(R: np.ndarray) -> np.ndarray:
    """R^-1 of an upper-triangular R with non-zero diagonal, row by row from the last (contiguous rows):
    X[i, i] = 1 / R[i, i], X[i, i+1:] = -(R[i, i+1:] / R[i, i]) X[i+1:, i+1:]."""
    n = R.shape[0]
    X = np.zeros((n, n))
    for i in range(n - 1, -1, -1):
        d = 1.0 / R[i, i]
        X[i, i] = d
        for k in range(i + 1, n):
            f = -R[i, k] * d
            if f != 0.0:
                for j in range(k, n):
                    X[i, j] += f * X[k, j]
    return X


def _gather_loops(J: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """J[idx][:, idx] in one pass."""
    k = len(idx)
    out = np.empty((k, k))
    for a in range(k):
        row = J[idx[a]]
        for b in range(k):
            out[a, b] = row[idx[b]]
    return out


def _gather_numpy(J: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """J[idx][:, idx]."""
    return J[np.ix_(idx, idx)]


if COMPILED:
    _upper_inverse = numba.njit(cache=True)(_upper_inverse_loops)
    _gather = numba.njit(cache=True)(_gather_loops)
else:
    _upper_inverse, _gather = _upper_inverse_lapack, _gather_numpy


def _clique_recursion(
    nf: np.ndarray,
    ns: np.ndarray,
    parent: np.ndarray,
    inner: np.ndarray,
    R_flat: np.ndarray,
    R_off: np.ndarray,
    S_flat: np.ndarray,
    S_off: np.ndarray,
    sep_pos: np.ndarray,
    sep_off: np.ndarray,
    want_row: np.ndarray,
    want_out: np.ndarray,
    want_off: np.ndarray,
    n_out: int,
) -> tuple[np.ndarray, int]:
    """The top-down recursion of :func:`.solver.latest_covariances` over cliques in depth-first preorder.

    Clique c has ``nf[c]`` frontal and ``ns[c]`` separator dimensions, its conditional's R (nf x nf,
    column-major, as GTSAM holds it, at ``R_flat[R_off[c]:]``) and S (nf x ns, column-major at
    ``S_flat[S_off[c]:]``), ``parent[c]`` (an
    earlier clique, -1 for a root), its separator's dimensions' positions in the parent's joint
    (``sep_pos[sep_off[c]:sep_off[c] + ns[c]]``), and whether a clique of the list hangs below it
    (``inner[c]``: its whole joint is formed). Its wanted 6 x 6 frontal blocks: the block rows
    ``want_row[want_off[c]:want_off[c + 1]]`` go to the output rows ``want_out[...]``. Returns
    (blocks (n_out, 6, 6), -1), or (partial blocks, c) when clique c's conditional is singular (a zero
    on R's diagonal).

    In preorder, every clique listed between a clique's parent and it belongs to a finished subtree,
    so the joints live on a stack: a clique's right after its parent's. The stack holds one path's
    joints (a few MB at 50 vehicles / 500 objects, against ~50 MB for every inner clique's), which
    stay in cache and are not page-faulted in afresh each cycle.
    """
    nc = len(nf)
    size = np.where(inner, (nf + ns) * (nf + ns), 0)
    J_off = np.zeros(nc, dtype=np.int64)
    top = 0
    for c in range(nc):
        J_off[c] = 0 if parent[c] < 0 else J_off[parent[c]] + size[parent[c]]
        top = max(top, J_off[c] + size[c])
    J_flat = np.empty(top)
    out = np.zeros((n_out, 6, 6))
    for c in range(nc):
        n, s = nf[c], ns[c]
        R = np.ascontiguousarray(R_flat[R_off[c] : R_off[c] + n * n].reshape(n, n).T)
        for i in range(n):
            if R[i, i] == 0.0:
                return out, c
        Rinv = _upper_inverse(R)
        rows = want_row[want_off[c] : want_off[c + 1]]
        outs = want_out[want_off[c] : want_off[c + 1]]
        p = parent[c]
        if p < 0:
            m = n
            J = J_flat[J_off[c] : J_off[c] + m * m].reshape(m, m) if inner[c] else np.empty((m, m))
            J[:, :] = Rinv @ Rinv.T
        else:
            mp = nf[p] + ns[p]
            Jp = J_flat[J_off[p] : J_off[p] + mp * mp].reshape(mp, mp)
            Sss = _gather(Jp, sep_pos[sep_off[c] : sep_off[c] + s])
            S = S_flat[S_off[c] : S_off[c] + n * s].reshape(s, n).T
            if inner[c]:
                m = n + s
                J = J_flat[J_off[c] : J_off[c] + m * m].reshape(m, m)
                G = -(Rinv @ S)
                Sfs = G @ Sss
                J[:n, :n] = Rinv @ Rinv.T + Sfs @ G.T
                J[:n, n:] = Sfs
                J[n:, :n] = Sfs.T
                J[n:, n:] = Sss
            else:  # a leaf of the visited tree: only its wanted blocks' rows
                k = len(rows)
                sel = np.empty(6 * k, dtype=np.int64)
                for j in range(k):
                    for d in range(6):
                        sel[6 * j + d] = 6 * rows[j] + d
                Ri = np.ascontiguousarray(Rinv[sel])
                Gr = -(Ri @ S)
                C = Ri @ Ri.T + Gr @ Sss @ Gr.T
                for j in range(k):
                    out[outs[j]] = C[6 * j : 6 * j + 6, 6 * j : 6 * j + 6]
                continue
        for j in range(len(rows)):
            r = 6 * rows[j]
            out[outs[j]] = J[r : r + 6, r : r + 6]
    return out, -1


# the same code with the numpy helpers, whether or not numba compiled the module's
_interpreted = types.FunctionType(
    _clique_recursion.__code__,
    {**_clique_recursion.__globals__, "_upper_inverse": _upper_inverse_lapack, "_gather": _gather_numpy},
    "_clique_recursion",
)
_compiled = numba.njit(cache=True)(_clique_recursion) if COMPILED else None


def clique_recursion(*args, compiled: bool = True) -> tuple[np.ndarray, int]:
    """:func:`_clique_recursion` (its arguments), compiled if numba is installed and ``compiled``, else
    interpreted."""
    return (_compiled if COMPILED and compiled else _interpreted)(*args)
