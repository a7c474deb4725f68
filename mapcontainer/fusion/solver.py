"""The solve step of the host's factor graph (:mod:`.graph`): Levenberg-Marquardt and the latest states'
marginal covariances from its Bayes tree.

Levenberg-Marquardt warm-started from the previous solution, starting with no damping (the Gauss-Newton
step, which a warm start almost always accepts) and raising lambda when the cost does not decrease; it
stops when the cost barely moves or the step did what the linear model predicted (one iteration per
cycle in practice). Every iteration eliminates once (multifrontal, COLAMD with the latest state of every
vehicle and track constrained last), so the latest states sit in the root cliques of the Bayes tree and
their covariances come from that elimination: (R^T R)^-1 of the root, and for the few latest keys in
cliques below it the standard top-down recursion (:func:`latest_covariances`) — no extra elimination;
gtsam.Marginals' shortcuts cost ~100 ms per such key here.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.linalg import lapack

from .params import FusionParams

__all__ = ["Solution", "SolveReport", "latest_covariances", "solve"]

_UNIT6 = gtsam.noiseModel.Unit.Create(6)


@dataclass(frozen=True)
class SolveReport:
    iterations: int
    error_before: float
    error_after: float
    factors: int
    variables: int
    cliques_below_root: int  # Bayes-tree cliques below a root visited for the latest covariances
    reweighted: int = 0


@dataclass(frozen=True)
class Solution:
    """What :func:`solve` found: the values, the latest keys' marginal covariances (1e6 I each if the
    system was degenerate), and figures for :class:`SolveReport`."""

    values: gtsam.Values
    covariances: dict[int, np.ndarray]
    iterations: int
    error_before: float
    error_after: float
    cliques_below_root: int  # -1: the system was degenerate
    root_dims: int | None  # size of the largest root clique visited; None: no Bayes tree to visit


def solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, latest: list[int], params: FusionParams) -> Solution:
    """Levenberg-Marquardt on ``graph`` from ``values`` (module docstring), then the marginal covariances
    of the ``latest`` keys (ordered last, so they sit in the root cliques). ``params``: lambda_initial,
    max_iterations, model_tol, relative_error_tol. ``graph`` must have a factor."""
    ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, latest)
    err = None
    lam = params.lambda_initial
    bt = None
    it = 0
    while it < params.max_iterations:
        it += 1
        gfg = graph.linearize(values)
        lin0 = gfg.error(values.zeroVectors())  # the linear model's cost at the current values
        if err is None:  # without GTSAM-robust factors that is the cost itself
            err = err0 = lin0
        if lam > 0:
            for key in values.keys():
                gfg.push_back(gtsam.JacobianFactor(key, np.sqrt(lam) * np.eye(6), np.zeros(6), _UNIT6))
        try:
            tree = gfg.eliminateMultifrontal(ordering)
        except RuntimeError:  # indeterminate: damp and retry
            lam = max(10 * lam, 1.0)
            continue
        delta = tree.optimize()
        new = values.retract(delta)
        new_err = graph.error(new)
        if new_err <= err or not np.isfinite(err):
            if lam == 0:
                bt = tree
            decrease = err - new_err
            # Converged when the cost barely moved, or when the step did what the linear model
            # predicted: it landed on the minimum of an accurate quadratic model. (Robust factors
            # linearise to IRLS quadratics whose values differ from the robust cost by a constant,
            # so compare predicted and actual decrease, not the values.)
            predicted = lin0 - gfg.error(delta)
            model_ok = lam == 0 and abs(predicted - decrease) <= max(params.model_tol * new_err, 1e-3)
            values, err = new, new_err
            lam = lam / 10 if lam > 1e-3 else 0.0
            if decrease <= max(params.relative_error_tol * new_err, 1e-3) or model_ok:
                break
        else:
            lam = max(10 * lam, 1.0)
    try:
        if bt is None:  # no undamped elimination was accepted: one more at the solution
            bt = graph.linearize(values).eliminateMultifrontal(ordering)
    except (RuntimeError, np.linalg.LinAlgError):  # a degenerate system: say so with huge covariances
        covariances, below, root_dims = None, -1, None
    else:
        covariances, below, root_dims = latest_covariances(bt, latest)
    if covariances is None:
        covariances = {k: 1e6 * np.eye(6) for k in latest}
    return Solution(values, covariances, it, float(err0), float(err), below, root_dims)


def latest_covariances(bt: gtsam.GaussianBayesTree, latest: list[int]) -> tuple[dict[int, np.ndarray] | None, int, int]:
    """Marginal covariances of the keys ``latest`` (6-D variables), top-down on the Bayes tree from the roots.

    Each clique on a path from a latest key to its root gets a factor L of its frontal variables,
    as blocks over independent unit noise sources (one per clique), so that
    Cov(x_i, x_j) = sum_s L_i[s] L_j[s]^T: a root R x = d + e has L = R^-1; a clique
    R x_F + S x_S = d + e below has L_F = -R^-1 S L_S plus R^-1 for its own source. With the latest
    states ordered last the roots hold nearly all of them and the paths are short.

    Returns (covariances by key, the number of cliques below a root that were visited, the size of the
    largest root clique visited); a degenerate system (a singular conditional) is not an error: its
    covariances are None, the count -1 and the size that of the roots visited before it.
    """
    wanted = set(latest)
    L: dict[int, dict[int, np.ndarray]] = {}  # clique id -> {source clique id: rows of its frontals}
    where: dict[int, tuple[int, int, int]] = {}  # key -> (clique id, row offset, dim)
    root_dims = 0
    below = 0

    def visit(clique) -> None:
        nonlocal below, root_dims
        c = clique.conditional()
        keys = [int(k) for k in c.keys()]
        cid = keys[0]
        if cid in L:
            return
        R = c.R()
        nf, rows = 0, 0
        while rows < R.shape[0]:
            where[keys[nf]] = (cid, rows, 6)
            rows += 6
            nf += 1
        Rinv, info = lapack.dtrtri(R, lower=0)  # unblocked for small n: no BLAS thread wake-ups
        if info != 0:
            raise np.linalg.LinAlgError(f"singular conditional at {gtsam.DefaultKeyFormatter(cid)}")
        blocks = {cid: Rinv}
        parents = keys[nf:]
        if parents:
            below += 1
            visit(clique.parent())  # visits every ancestor: the separator's keys are frontal there
            G = -Rinv @ c.S()
            sep = [where[k] for k in parents]
            sources = set().union(*(L[w[0]].keys() for w in sep))
            for src in sources:
                cols = next(L[w[0]][src].shape[1] for w in sep if src in L[w[0]])
                LS = np.zeros((G.shape[1], cols))
                off = 0
                for owner, r0, d in sep:
                    if src in L[owner]:
                        LS[off : off + d] = L[owner][src][r0 : r0 + d]
                    off += d
                blocks[src] = G @ LS if src not in blocks else blocks[src] + G @ LS
        else:
            root_dims = max(root_dims, int(R.shape[0]))
        L[cid] = blocks

    def cross(a: int, b: int) -> np.ndarray:
        (ca, ra, da), (cb, rb, db) = where[a], where[b]
        La, Lb = L[ca], L[cb]
        out = np.zeros((da, db))
        for s in La.keys() & Lb.keys():
            out += La[s][ra : ra + da] @ Lb[s][rb : rb + db].T
        return out

    try:
        for key in wanted:
            if key not in where:
                visit(bt[key])
        covariances = {k: 0.5 * (C + C.T) for k in wanted for C in (cross(k, k),)}
    except (RuntimeError, np.linalg.LinAlgError):
        return None, -1, root_dims
    return covariances, below, root_dims
