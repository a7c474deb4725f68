"""The solve step alone (mapcontainer.fusion.solver): the latest keys' covariances from the Bayes tree
against a dense inverse of the same linear system, and Levenberg-Marquardt against GTSAM's own."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import S, X

from mapcontainer.fusion import FusionParams
from mapcontainer.fusion.solver import latest_covariances, solve

UNIT6 = gtsam.noiseModel.Unit.Create(6)


def _linear_system(n: int, links: list[tuple[int, int]], seed: int = 0):
    """A Gaussian factor graph over n 6-D keys S(0..n-1): a unary factor on each and a binary factor per
    link, random dense blocks; returns it and its dense Jacobian A (columns key by key)."""
    rng = np.random.default_rng(seed)
    graph = gtsam.GaussianFactorGraph()
    rows = []
    for i in range(n):
        Ai = rng.normal(size=(6, 6)) + 3 * np.eye(6)
        graph.push_back(gtsam.JacobianFactor(S(i), Ai, rng.normal(size=6), UNIT6))
        row = np.zeros((6, 6 * n))
        row[:, 6 * i : 6 * i + 6] = Ai
        rows.append(row)
    for i, j in links:
        Ai, Aj = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
        graph.push_back(gtsam.JacobianFactor(S(i), Ai, S(j), Aj, rng.normal(size=6), UNIT6))
        row = np.zeros((6, 6 * n))
        row[:, 6 * i : 6 * i + 6], row[:, 6 * j : 6 * j + 6] = Ai, Aj
        rows.append(row)
    return graph, np.vstack(rows)


def _ordering(keys) -> gtsam.Ordering:
    o = gtsam.Ordering()
    for k in keys:
        o.push_back(k)
    return o


def test_latest_covariances_match_a_dense_inverse():
    """A chain of 6 keys eliminated in chain order: the root clique holds the last keys, the first keys
    sit in cliques below it, reached by the top-down recursion; every block equals (A^T A)^-1's."""
    n = 6
    graph, A = _linear_system(n, [(i, i + 1) for i in range(n - 1)] + [(0, 3)])
    bt = graph.eliminateMultifrontal(_ordering([S(i) for i in range(n)]))
    cov = np.linalg.inv(A.T @ A)
    wanted = [S(0), S(2), S(5)]
    covariances, below, root_dims = latest_covariances(bt, wanted)
    assert set(covariances) == set(wanted)
    for k in wanted:
        i = gtsam.Symbol(k).index()
        np.testing.assert_allclose(covariances[k], cov[6 * i : 6 * i + 6, 6 * i : 6 * i + 6], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(covariances[k], covariances[k].T)
    assert below >= 2  # S(0) and S(2) are below the root
    root = bt[S(n - 1)].conditional()  # eliminated last: in the root clique
    assert len(root.keys()) * 6 == root.R().shape[0] == root_dims >= 12


def test_latest_covariances_with_several_roots():
    """Two unconnected components: two roots; each key's covariance is that of its own component."""
    graph, A = _linear_system(5, [(0, 1), (1, 2), (3, 4)], seed=1)
    bt = graph.eliminateMultifrontal(_ordering([S(i) for i in range(5)]))
    cov = np.linalg.inv(A.T @ A)
    assert np.all(cov[:18, 18:] == pytest.approx(0.0, abs=1e-15))
    covariances, below, _ = latest_covariances(bt, [S(2), S(4), S(0)])
    for i in (0, 2, 4):
        np.testing.assert_allclose(covariances[S(i)], cov[6 * i : 6 * i + 6, 6 * i : 6 * i + 6], rtol=1e-9, atol=1e-12)
    assert below >= 1


def test_latest_covariances_of_the_root_alone_visit_nothing_below():
    graph, A = _linear_system(4, [(0, 1), (1, 2), (2, 3)], seed=2)
    bt = graph.eliminateMultifrontal(_ordering([S(i) for i in range(4)]))
    covariances, below, root_dims = latest_covariances(bt, [S(3)])
    assert below == 0 and root_dims >= 6
    np.testing.assert_allclose(covariances[S(3)], np.linalg.inv(A.T @ A)[18:, 18:], rtol=1e-9, atol=1e-12)


def _tree_system(seed: int = 3):
    """60 keys in 6 loosely coupled chains tied to 3 shared hub keys (the vehicles' persistent errors of
    the host's graph), eliminated in COLAMD's order: a Bayes tree with a root, inner cliques and leaves,
    several wanted keys in one clique; its latest keys (every chain's last) and its dense covariance."""
    rng = np.random.default_rng(seed)
    n, hubs = 60, [57, 58, 59]
    links = [(i, i + 1) for i in range(57) if (i + 1) % 10]  # chains 0-9, 10-19, ...
    links += [(i, hubs[rng.integers(3)]) for i in range(0, 57, 4)]
    graph, A = _linear_system(n, links, seed=seed)
    bt = graph.eliminateMultifrontal(gtsam.Ordering.ColamdGaussianFactorGraph(graph))
    return bt, [S(i) for i in (9, 19, 29, 39, 49, 56, 58, 8, 18)], np.linalg.inv(A.T @ A)


def test_latest_covariances_of_a_branching_tree_match_a_dense_inverse():
    bt, wanted, cov = _tree_system()
    covariances, below, root_dims = latest_covariances(bt, wanted)
    assert below >= 5 and root_dims >= 6
    for k in wanted:
        i = gtsam.Symbol(k).index()
        np.testing.assert_allclose(covariances[k], cov[6 * i : 6 * i + 6, 6 * i : 6 * i + 6], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("compiled", [pytest.param(True, marks=pytest.mark.slow), False])  # slow: numba compiles
def test_clique_recursion_says_which_conditional_is_singular(compiled):
    """GTSAM's elimination refuses a singular system; the recursion still checks each R's diagonal and
    names the first clique with a zero there (the solve then reports huge covariances)."""
    from mapcontainer.fusion.compiled import clique_recursion

    R_root, R_leaf = np.eye(6), np.eye(6)
    R_leaf[2, 2] = 0.0
    i64 = lambda *v: np.array(v, dtype=np.int64)  # noqa: E731
    blocks, failed = clique_recursion(
        i64(6, 6), i64(0, 6), i64(-1, 0), np.array([True, False]),
        np.concatenate([R_root.ravel(), R_leaf.ravel()]), i64(0, 36, 72),
        np.zeros(36), i64(0, 0, 36), np.arange(6, dtype=np.int64), i64(0, 0, 6),
        i64(0, 0), i64(0, 1), i64(0, 1, 2), 2, compiled=compiled,
    )  # fmt: skip
    assert failed == 1
    np.testing.assert_array_equal(blocks[0], np.eye(6))  # the root's, before it


_INTERPRETED = """
import sys
sys.modules["numba"] = None  # as if the fast extra were not installed
import numpy as np
from tests.unit.test_fusion_solver import _tree_system
from mapcontainer.fusion import compiled
from mapcontainer.fusion import solver
from mapcontainer.fusion.solver import latest_covariances
assert not compiled.COMPILED
solver.COMPILE_FROM_CLIQUES = 0  # would compile, if it could
bt, wanted, _ = _tree_system()
covariances, below, root_dims = latest_covariances(bt, wanted)
np.save(sys.argv[1], np.array([covariances[k] for k in wanted]))
print(below, root_dims)
"""


@pytest.mark.slow  # numba compiles the kernel (seconds) unless a previous run left it in its cache
def test_compiled_and_interpreted_recursions_agree(monkeypatch):
    """The clique recursion compiled by numba and the same code interpreted give the same covariances,
    to rounding (the solver picks one by the tree's size: here both, forced)."""
    pytest.importorskip("numba")
    from mapcontainer.fusion import solver

    bt, wanted, _ = _tree_system()
    got = {}
    for compiled, threshold in ((True, 0), (False, 10**9)):
        monkeypatch.setattr(solver, "COMPILE_FROM_CLIQUES", threshold)
        got[compiled] = latest_covariances(bt, wanted)
    assert got[True][1:] == got[False][1:]
    for k in wanted:
        np.testing.assert_allclose(got[True][0][k], got[False][0][k], rtol=1e-12, atol=1e-15)


@pytest.mark.slow  # a second Python process importing gtsam
def test_without_numba_the_same_covariances(tmp_path, monkeypatch):
    """Without the fast extra (a process that cannot import numba) the module runs, interpreted, and gives
    what this process gives, compiled if it can."""
    import subprocess
    import sys
    from pathlib import Path

    from mapcontainer.fusion import solver

    monkeypatch.setattr(solver, "COMPILE_FROM_CLIQUES", 0)
    out = tmp_path / "interpreted.npy"
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "-c", _INTERPRETED, str(out)], cwd=root, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    bt, wanted, _ = _tree_system()
    covariances, below, root_dims = latest_covariances(bt, wanted)
    assert run.stdout.split() == [str(below), str(root_dims)]
    np.testing.assert_allclose(np.array([covariances[k] for k in wanted]), np.load(out), rtol=1e-12, atol=1e-15)


def _nonlinear_problem():
    """Three Pose3 with priors and odometry, and two Vector6 tied to each other and to nothing else but
    unary priors: a small, well-posed nonlinear graph, its values perturbed from the optimum."""
    rng = np.random.default_rng(4)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    sig = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.02, 0.1, 0.1, 0.2]))
    truth = [gtsam.Pose3(gtsam.Rot3.Ypr(0.1 * i, 0.0, 0.02), np.array([2.0 * i, 0.5, 0.0])) for i in range(3)]
    for i, T in enumerate(truth):
        noisy = T.retract(rng.normal(0, [0.01, 0.01, 0.02, 0.1, 0.1, 0.2]))
        graph.add(gtsam.PriorFactorPose3(X(i), noisy, sig))
        values.insert(X(i), T.retract(rng.normal(0, 0.05, 6)))
        if i:
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), truth[i - 1].between(T), sig))
    for i in range(2):
        graph.add(gtsam.PriorFactorVector(S(i), rng.normal(size=6), gtsam.noiseModel.Isotropic.Sigma(6, 0.5)))
        values.insert(S(i), np.zeros(6))
    graph.add(gtsam.BetweenFactorVector(S(0), S(1), np.ones(6), gtsam.noiseModel.Isotropic.Sigma(6, 0.2)))
    return graph, values


def test_solve_reaches_gtsams_optimum_and_marginals():
    """Warm-started from its previous solution, as the graph calls it every cycle, the solve step reaches
    GTSAM's optimum (one Gauss-Newton step per call here), and its covariances are gtsam.Marginals' at its
    solution."""
    graph, values = _nonlinear_problem()
    latest = [X(2), S(1)]
    params = FusionParams()
    first = sol = solve(graph, values, latest, params)
    assert first.error_before == pytest.approx(graph.error(values), rel=1e-9)
    assert first.error_after < first.error_before and first.iterations >= 1
    for _ in range(5):
        sol = solve(graph, sol.values, latest, params)
        assert sol.error_after <= sol.error_before
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(1e-12)
    lm.setAbsoluteErrorTol(1e-12)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, values, lm).optimize()
    assert sol.error_after == pytest.approx(graph.error(ref), rel=1e-9)
    np.testing.assert_allclose(sol.values.atVector(S(1)), ref.atVector(S(1)), atol=1e-9)
    np.testing.assert_allclose(sol.values.atPose3(X(2)).matrix(), ref.atPose3(X(2)).matrix(), atol=1e-6)
    m = gtsam.Marginals(graph, sol.values)
    assert set(sol.covariances) == set(latest)
    for k in latest:
        np.testing.assert_allclose(sol.covariances[k], m.marginalCovariance(k), rtol=1e-6, atol=1e-12)
    assert sol.cliques_below_root >= 0 and sol.root_dims is not None and sol.root_dims >= 6
    assert values.atVector(S(1)) == pytest.approx(np.zeros(6))  # the input values are not modified


def test_solve_says_degenerate_with_huge_covariances():
    """A variable only half constrained: damped steps go through, the undamped elimination does not;
    the covariances say so (1e6 I), the Bayes-tree count is -1, and there is no root size."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    values.insert(S(0), np.zeros(6))
    A = np.hstack([np.eye(3), np.zeros((3, 3))])
    jf = gtsam.JacobianFactor(S(0), A, np.ones(3), gtsam.noiseModel.Unit.Create(3))
    graph.add(gtsam.LinearContainerFactor(jf, values))
    sol = solve(graph, values, [S(0)], FusionParams(max_iterations=3))
    assert sol.cliques_below_root == -1 and sol.root_dims is None
    np.testing.assert_array_equal(sol.covariances[S(0)], 1e6 * np.eye(6))
    assert sol.iterations == 3
