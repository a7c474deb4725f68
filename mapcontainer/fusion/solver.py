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

from .compiled import clique_recursion
from .laps import Laps
from .params import FusionParams

__all__ = ["Solution", "SolveReport", "latest_covariances", "solve"]

_UNIT6 = gtsam.noiseModel.Unit.Create(6)

# The compiled clique recursion from this many cliques on the paths: below it the interpreted one costs a few
# ms at most, and a small window (tests, a few vehicles) never waits for numba's compile (see .compiled).
COMPILE_FROM_CLIQUES = 256

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
                laps.mark("step")
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

    Here the paths are gathered from the tree (its conditionals' R and S, parents first); the recursion
    itself is :func:`.compiled.clique_recursion` (compiled with numba when installed).

    Returns (covariances by key, the number of cliques below a root that were visited, the size of the
    largest root clique visited); a degenerate system (a singular conditional) is not an error: its
    covariances are None, the count -1 and the size that of the roots visited before it.
    """
    wanted = list(dict.fromkeys(latest))
    # the cliques on the paths, by their first frontal key; each path climbs until a clique already
    # listed, so its cliques reversed, list after list, put every parent before its children
    cliques: dict[int, int] = {}  # first frontal key -> position in `order`
    order: list[tuple] = []  # (keys, R, S or None, parent's first key or None)
    wants: list[tuple[int, int, int]] = []  # (clique's first key, block row among its frontals, output row)
    for out_row, key in enumerate(wanted):
        clique = bt[key]
        c = clique.conditional()
        keys = c.keys()
        cid = keys[0]
        wants.append((cid, keys.index(key), out_row))
        path = []
        while cid not in cliques:
            R = c.R()
            if len(keys) == R.shape[0] // 6:  # no separator: a root
                path.append((keys, R, None, None))
                break
            parent = clique.parent()
            pc = parent.conditional()
            pkeys = pc.keys()
            path.append((keys, R, c.S(), pkeys[0]))
            clique, c, keys, cid = parent, pc, pkeys, pkeys[0]
        for item in reversed(path):
            cliques[item[0][0]] = len(order)
            order.append(item)
    # depth-first preorder (the recursion keeps one path's joints: .compiled.clique_recursion)
    nc = len(order)
    up = [-1 if it[3] is None else cliques[it[3]] for it in order]
    children: list[list[int]] = [[] for _ in range(nc)]
    for c, p in enumerate(up):
        if p >= 0:
            children[p].append(c)
    pre: list[int] = []
    stack = [c for c in reversed(range(nc)) if up[c] < 0]
    while stack:
        c = stack.pop()
        pre.append(c)
        stack.extend(reversed(children[c]))
    rank = np.empty(nc, dtype=np.int64)
    rank[pre] = np.arange(nc)
    order = [order[c] for c in pre]
    parent = np.array([-1 if up[c] < 0 else rank[up[c]] for c in pre], dtype=np.int64)
    nf = np.array([it[1].shape[0] for it in order], dtype=np.int64)
    ns = np.array([0 if it[2] is None else it[2].shape[1] for it in order], dtype=np.int64)
    inner = np.zeros(nc, dtype=np.bool_)
    inner[parent[parent >= 0]] = True
    sep_blocks: list[int] = []  # each separator key's position among its parent's keys
    slots: dict[int, dict[int, int]] = {}
    for it, p in zip(order, parent, strict=True):
        if p >= 0:
            at = slots.get(p)
            if at is None:
                at = slots[p] = {k: i for i, k in enumerate(order[p][0])}
            sep_blocks.extend(at[k] for k in it[0][it[1].shape[0] // 6 :])
    sep_pos = (6 * np.array(sep_blocks, dtype=np.int64)[:, None] + np.arange(6)).ravel()
    want_clique = rank[[cliques[w[0]] for w in wants]]
    by_clique = np.argsort(want_clique, kind="stable")
    blocks, failed = clique_recursion(
        nf,
        ns,
        parent,
        inner,
        np.concatenate([it[1].ravel(order="F") for it in order]),  # GTSAM's matrices are column-major: views
        _offsets(nf * nf),
        np.concatenate([np.zeros(0)] + [it[2].ravel(order="F") for it in order if it[2] is not None]),
        _offsets(nf * ns),
        sep_pos,
        _offsets(ns),
        np.array([w[1] for w in wants], dtype=np.int64)[by_clique],
        np.array([w[2] for w in wants], dtype=np.int64)[by_clique],
        np.searchsorted(want_clique[by_clique], np.arange(nc + 1)).astype(np.int64),
        len(wanted),
        compiled=nc >= COMPILE_FROM_CLIQUES,
    )
    roots = parent < 0
    if failed >= 0:
        return None, -1, int(nf[:failed][roots[:failed]].max(initial=0))
    below = int(np.count_nonzero(~roots))
    blocks = 0.5 * (blocks + blocks.transpose(0, 2, 1))
    return dict(zip(wanted, blocks, strict=True)), below, int(nf[roots].max(initial=0))


def _offsets(sizes: np.ndarray) -> np.ndarray:
    """Start of each item in a flat buffer, and the total: [0, s0, s0 + s1, ...] (int64)."""
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
