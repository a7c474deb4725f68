"""anees_summary's split of the 3-D NEES into horizontal (dof 2) and vertical-given-horizontal (dof 1)."""

import numpy as np

from mapcontainer.experiments.paper import anees_summary


def _runs(rng, n_runs: int, z_var_scale: float, bad_seed: int | None = None) -> list[dict]:
    """Runs of 3-D errors e ~ N(0, P) with correlated random P; the estimator reports P with its
    vertical variance multiplied by ``z_var_scale`` (< 1: overconfident in height). The run with seed
    ``bad_seed`` has 5x larger vertical errors (a heavy tail of one run)."""
    out = []
    for seed in range(n_runs):
        rows = []
        for k in range(10):
            for i in range(3):
                A = rng.normal(size=(3, 3)) * [0.3, 0.3, 0.05]
                P = A.T @ A + np.diag([0.02, 0.02, 0.002])
                e = np.linalg.cholesky(P) @ rng.normal(size=3)
                if seed == bad_seed:
                    e[2] *= 5.0
                Pr = P.copy()
                Pr[2, :] *= np.sqrt(z_var_scale)
                Pr[:, 2] *= np.sqrt(z_var_scale)
                n3 = float(e @ np.linalg.solve(Pr, e))
                n2 = float(e[:2] @ np.linalg.solve(Pr[:2, :2], e[:2]))
                rows.append((k, i, n3, n2))
        out.append({"seed": seed, "nees": rows})
    return out


def test_vertical_anees_is_chi2_one_for_a_consistent_estimator():
    rs = _runs(np.random.default_rng(1), 60, 1.0)
    v3, v2, v1 = (anees_summary(rs, dof=d) for d in (3, 2, 1))
    assert v3["inside"] and v2["inside"] and v1["inside"]
    assert abs(v1["value"] - 1.0) < 0.1
    assert abs(v3["value"] - (v2["value"] + v1["value"])) < 1e-3  # NEES_3 = NEES_2 + NEES_z|xy


def test_vertical_anees_flags_an_overconfident_height_and_names_the_worst_run():
    rs = _runs(np.random.default_rng(2), 60, 0.25)  # reported height variance 4x too small
    assert anees_summary(rs, dof=2)["inside"]  # the horizontal part does not see it
    v1 = anees_summary(rs, dof=1)
    assert not v1["inside"] and 3.0 < v1["value"] < 5.0
    tail = anees_summary(_runs(np.random.default_rng(3), 60, 1.0, bad_seed=17), dof=1)
    assert tail["worst_runs"][0][0] == 17 and tail["worst_runs"][0][1] > 10.0
