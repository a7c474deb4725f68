"""The solve step of the host's factor graph (:mod:`.graph`): Levenberg-Marquardt and the latest states'
marginal covariances from its Bayes tree.

Levenberg-Marquardt warm-started from the previous solution, starting with no damping (the Gauss-Newton
step, which a warm start almost always accepts) and raising lambda when the cost does not decrease; it
stops when the cost barely moves or the step did what the linear model predicted (one iteration per
cycle in practice). Every iteration eliminates once (multifrontal), and the latest states' covariances
come from the last undamped elimination by the top-down recursion over the Bayes tree's cliques
(:func:`latest_covariances`): no extra elimination; gtsam.Marginals' shortcuts cost ~100 ms per key here.

The elimination order (FusionParams.solver): ``"sparse"`` is COLAMD over the whole window. A track is
conditionally independent of the other tracks given its observers' frames, and vehicles couple only
through the objects they share, so its cliques stay as large as a neighbourhood of the scene, and
elimination and recursion grow with the detections, not with the fleet. ``"exact"`` orders the latest
state of every vehicle and track last, so their covariances come from one dense root clique of
6 x (vehicles + tracks) dimensions, factored and inverted every cycle: cubic in the scene's size, and the
cheaper order for a small window ("sparse" uses it up to ``DENSE_ROOT_KEYS`` latest states). Both
solve the same linear systems exactly (the covariances agree to ~1e-12); "exact" is the simpler order,
kept as the test oracle.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.linalg import lapack

from .laps import Laps
from .params import FusionParams

__all__ = ["Solution", "SolveReport", "latest_covariances", "solve"]

_UNIT6 = gtsam.noiseModel.Unit.Create(6)

# With this few latest states "sparse" orders them last too: one dense root of at most 6 x 24 dimensions costs
# less than the recursion over more, smaller cliques (4 vehicles / 14 objects: 15.4 against 18.1 ms a cycle).
DENSE_ROOT_KEYS = 24


@dataclass(frozen=True)
class SolveReport:
    iterations: int
    error_before: float
    error_after: float
    factors: int
    variables: int
    cliques_below_root: int  # Bayes-tree cliques below a root visited for the latest covariances
    reweighted: int = 0
    phases_ms: dict[str, float] | None = None  # wall time by phase (Solution.phases_ms and the reweighting)


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
    phases_ms: dict[
        str, float
    ]  # wall time: ordering, linearize, eliminate, step (back-substitution, errors), covariances


def solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, latest: list[int], params: FusionParams) -> Solution:
    """Levenberg-Marquardt on ``graph`` from ``values`` (module docstring), then the marginal covariances
    of the ``latest`` keys. ``params``: solver (the elimination order), lambda_initial, max_iterations,
    model_tol, relative_error_tol. ``graph`` must have a factor."""
    laps = Laps()
    if params.solver == "exact" or len(latest) <= DENSE_ROOT_KEYS:
        ordering = gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, latest)
    else:
        ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    laps.mark("ordering")
    err = None
    lam = params.lambda_initial
    bt = None
    it = 0
    while it < params.max_iterations:
        it += 1
        gfg = graph.linearize(values)
        laps.mark("linearize")
        lin0 = gfg.error(values.zeroVectors())  # the linear model's cost at the current values
        if err is None:  # without GTSAM-robust factors that is the cost itself
            err = err0 = lin0
        if lam > 0:
            for key in values.keys():
                gfg.push_back(gtsam.JacobianFactor(key, np.sqrt(lam) * np.eye(6), np.zeros(6), _UNIT6))
        laps.mark("step")
        try:
            tree = gfg.eliminateMultifrontal(ordering)
        except RuntimeError:  # indeterminate: damp and retry
            lam = max(10 * lam, 1.0)
            laps.mark("eliminate")
            continue
        laps.mark("eliminate")
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
        laps.mark("step")
    try:
        if bt is None:  # no undamped elimination was accepted: one more at the solution
            bt = graph.linearize(values).eliminateMultifrontal(ordering)
            laps.mark("eliminate")
    except (RuntimeError, np.linalg.LinAlgError):  # a degenerate system: say so with huge covariances
        covariances, below, root_dims = None, -1, None
    else:
        covariances, below, root_dims = latest_covariances(bt, latest)
    if covariances is None:
        covariances = {k: 1e6 * np.eye(6) for k in latest}
    laps.mark("covariances")
    return Solution(values, covariances, it, float(err0), float(err), below, root_dims, laps.ms)


def latest_covariances(bt: gtsam.GaussianBayesTree, latest: list[int]) -> tuple[dict[int, np.ndarray] | None, int, int]:
    """Marginal covariances of the keys ``latest`` (6-D variables), top-down on the Bayes tree from the roots.

    A clique's conditional R x_F + S x_S = d + e (unit noise) gives the joint covariance of its frontal
    and separator variables from the separator's, which its parent's joint holds: with G = -R^-1 S,
    Cov(x_F, x_S) = G Cov(x_S) and Cov(x_F) = R^-1 R^-T + G Cov(x_S) G^T; a root has Cov(x_F) = R^-1 R^-T.
    Only the cliques on the paths from the latest keys to their roots are visited; a clique's whole
    joint is formed only when a visited clique hangs below it, otherwise just its latest keys' blocks.
    The cost follows the cliques' sizes, (frontal + separator)^3 each, not the number of keys.

    Returns (covariances by key, the number of cliques below a root that were visited, the size of the
    largest root clique visited); a degenerate system (a singular conditional) is not an error: its
    covariances are None, the count -1 and the size that of the roots visited before it.
    """
    wanted = list(dict.fromkeys(latest))
    # pass 1: the cliques on the paths, by their first frontal key, and which of them have a child there
    cliques: dict[int, tuple] = {}  # id -> (keys, R, S or None, parent id or None)
    mine: dict[int, list[tuple[int, int]]] = {}  # clique id -> its latest keys (position among its frontals, key)
    inner: set[int] = set()
    for key in wanted:
        clique = bt[key]
        c = clique.conditional()
        keys = c.keys()
        cid = keys[0]
        mine.setdefault(cid, []).append((keys.index(key), key))
        while cid not in cliques:
            R = c.R()
            if len(keys) == R.shape[0] // 6:  # no separator: a root
                cliques[cid] = (keys, R, None, None)
                break
            parent = clique.parent()
            pc = parent.conditional()
            pkeys = pc.keys()
            cliques[cid] = (keys, R, c.S(), pkeys[0])
            inner.add(pkeys[0])
            clique, c, keys, cid = parent, pc, pkeys, pkeys[0]
    # pass 2: top down
    joint: dict[int, tuple[dict[int, int], np.ndarray]] = {}  # inner clique id -> (offset by key, joint)
    blocks: dict[int, np.ndarray] = {}
    below, root_dims = 0, 0
    six = np.arange(6)

    def visit(cid: int) -> None:
        nonlocal below, root_dims
        keys, R, S, parent = cliques[cid]
        n = R.shape[0]
        Rinv, info = lapack.dtrtri(R, lower=0)  # unblocked for small n: no BLAS thread wake-ups
        if info != 0:
            raise np.linalg.LinAlgError(f"singular conditional at {gtsam.DefaultKeyFormatter(cid)}")
        latest_here = mine.get(cid, ())
        if parent is None:
            root_dims = max(root_dims, n)
            J = Rinv @ Rinv.T
        else:
            below += 1
            if parent not in joint:
                visit(parent)
            at, Jp = joint[parent]
            idx = (np.array([at[k] for k in keys[n // 6 :]])[:, None] + six).ravel()
            Sss = Jp.take(idx, axis=0).take(idx, axis=1)
            if cid in inner:
                G = -Rinv @ S
                Sfs = G @ Sss
                J = np.empty((n + len(idx), n + len(idx)))
                J[:n, :n] = Rinv @ Rinv.T + Sfs @ G.T
                J[:n, n:] = Sfs
                J[n:, :n] = Sfs.T
                J[n:, n:] = Sss
            else:  # a leaf of the visited tree: only its latest keys' blocks
                rows = (6 * np.array([i for i, _ in latest_here])[:, None] + six).ravel()
                Ri = Rinv[rows]
                Gr = -Ri @ S
                C = Ri @ Ri.T + Gr @ Sss @ Gr.T
                for j, (_, k) in enumerate(latest_here):
                    blocks[k] = C[6 * j : 6 * j + 6, 6 * j : 6 * j + 6]
                return
        for i, k in latest_here:
            blocks[k] = J[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]
        if cid in inner:
            joint[cid] = ({k: 6 * i for i, k in enumerate(keys)}, J)

    try:
        for cid, here in mine.items():
            if here[0][1] not in blocks:  # not visited on the way to another
                visit(cid)
    except (RuntimeError, np.linalg.LinAlgError):
        return None, -1, root_dims
    return {k: 0.5 * (blocks[k] + blocks[k].T) for k in wanted}, below, root_dims
