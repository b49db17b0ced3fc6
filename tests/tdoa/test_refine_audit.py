"""Audit of the far-field refinement (issue 4): is LM the ML estimator, and how close to the bound?

The Fig. 3-4 reproductions showed LM not lowering the position error of the initialisation.
These tests pin down the explanation: LM minimises the right cost (checked against an
independent ``scipy.optimize.least_squares``), the ML estimate is efficient at low noise
(it meets the Cramer-Rao bound) and lowers the error of the initialisation there, and the
loss at sigma = 0.1 with m = k = 10 is an outward scale bias of ML that vanishes with more
columns.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from selfcal.experiments.farfield import FINDING, fig3_trial, fig4_trial
from selfcal.geometry import align
from selfcal.tdoa import farfield_crlb, refine_lm
from selfcal.tdoa.initialize import initialize_farfield


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def aligned_mse(est: np.ndarray, true: np.ndarray) -> float:
    al = align(est, true, reflection=True)
    return float(np.mean(np.sum((al.apply(est) - true) ** 2, axis=1)))


def geometry(seed: int, m: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    Z = rng.uniform(0, 1, (m, 3))
    Z -= Z[0]
    return Z, unit(rng.normal(size=(k, 3)))


def start(D: np.ndarray):
    k = D.shape[1]
    return initialize_farfield(np.vstack([np.zeros((1, k)), D[1:] - D[0]]))


def scipy_ml(D: np.ndarray, Z0: np.ndarray, N0: np.ndarray, C0: np.ndarray) -> tuple[np.ndarray, float]:
    """Independent ML fit: directions as free 3-vectors normalised inside the model."""
    m, k = D.shape

    def fun(x: np.ndarray) -> np.ndarray:
        Z = np.vstack([np.zeros(3), x[: 3 * (m - 1)].reshape(m - 1, 3)])
        N = unit(x[3 * (m - 1) : 3 * (m - 1) + 3 * k].reshape(k, 3))
        return (D - Z @ N.T - x[3 * (m - 1) + 3 * k :]).ravel()

    x0 = np.concatenate([Z0[1:].ravel(), N0.ravel(), C0])
    sol = least_squares(fun, x0, method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    Z = np.vstack([np.zeros(3), sol.x[: 3 * (m - 1)].reshape(m - 1, 3)])
    return Z, 2.0 * sol.cost


def test_lm_reaches_the_same_ml_minimum_as_scipy_least_squares():
    Z, N = geometry(0, 8, 9)
    rng = np.random.default_rng(10)
    for sigma in (0.01, 0.1):
        D = Z @ N.T + 0.5 + sigma * rng.normal(size=Z.shape[:1] + N.shape[:1])
        init = start(D)
        lm = refine_lm(D, init.positions, init.directions, D[0].copy(), free_offsets=True)
        Zs, cost_s = scipy_ml(D, init.positions, init.directions, D[0].copy())
        init_cost = float(np.sum((D - init.positions @ init.directions.T - D[0]) ** 2))
        assert lm.cost <= init_cost
        assert np.isclose(lm.cost, cost_s, rtol=1e-6)
        assert aligned_mse(lm.positions, Zs) < 1e-8 * aligned_mse(Zs, Z)


def test_ml_refinement_meets_the_crlb_and_beats_the_initialisation_at_low_noise():
    # 200 draws: the Monte-Carlo MSE is known to ~5 %, the bound is exact
    Z, N = geometry(0, 8, 10)
    sigma = 1e-3
    rng = np.random.default_rng(1)
    e_init, e_ml = [], []
    for _ in range(200):
        D = Z @ N.T + 0.3 + sigma * rng.normal(size=(8, 10))
        init = start(D)
        ml = refine_lm(D, init.positions, init.directions, D[0].copy(), free_offsets=True)
        e_init.append(aligned_mse(init.positions, Z))
        e_ml.append(aligned_mse(ml.positions, Z))
    bound = np.trace(farfield_crlb(Z, N, sigma), axis1=1, axis2=2).mean()
    assert 0.8 < np.mean(e_ml) / bound < 1.25
    # the initialisation is above the bound, so refinement has something to gain
    assert np.mean(e_ml) < np.mean(e_init)


def test_crlb_is_invariant_to_the_gauge_and_scales_with_the_noise():
    Z, N = geometry(2, 6, 8)
    R = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    a = farfield_crlb(Z, N, 0.01)
    b = farfield_crlb((Z + [1.0, -2.0, 0.5]) @ R.T, N @ R.T, 0.01)
    assert np.isclose(np.trace(a, axis1=1, axis2=2).sum(), np.trace(b, axis1=1, axis2=2).sum(), rtol=1e-8)
    assert np.allclose(farfield_crlb(Z, N, 0.02), 4.0 * a)
    # unknown offsets can only add uncertainty
    pinned = farfield_crlb(Z, N, 0.01, free_offsets=False)
    assert np.trace(pinned, axis1=1, axis2=2).sum() <= np.trace(a, axis1=1, axis2=2).sum() * (1 + 1e-9)


def test_reproductions_report_the_ml_refinement_and_the_bound():
    row = fig4_trial({"distance": 1e7, "sigma": 1e-3, "batch": 6}, seed=0)
    assert len(row["ml_rms"]) == len(row["crlb_rms"]) == 6
    ms = np.mean(np.square(row["ml_rms"])) / np.mean(np.square(row["crlb_rms"]))
    assert 0.3 < ms < 3.0  # 6 draws: loose, the tight check is the Monte-Carlo test above
    row3 = fig3_trial({"m": 10, "k": 10, "sigma": 0.01, "length": 40}, seed=0)
    for key in ("ml_error", "ml_rms", "crlb_rms", "init_scale", "ml_scale"):
        assert np.isfinite(row3[key])
    assert "least_squares" in FINDING and "CRLB" in FINDING


def test_ml_scale_bias_at_high_noise_shrinks_with_more_columns():
    """The documented cause of Fig. 3 (sigma = 0.1): ML inflates the array, less so for large k."""
    rng = np.random.default_rng(4)

    def median_scale(k: int, draws: int) -> float:
        out = []
        for _ in range(draws):
            Z = rng.uniform(0, 1, (10, 3))
            Z -= Z[0]
            N = unit(rng.normal(size=(k, 3)))
            D = Z @ N.T + 0.1 * rng.normal(size=(10, k))
            init = start(D)
            ml = refine_lm(D, init.positions, init.directions, D[0].copy(), free_offsets=True)
            e, t = ml.positions - ml.positions.mean(0), Z - Z.mean(0)
            out.append(np.linalg.norm(e) / np.linalg.norm(t))
        return float(np.median(out))

    few, many = median_scale(10, 40), median_scale(80, 20)
    assert few > 1.08
    assert many < few - 0.05


def test_ml_at_sigma_0p1_can_collapse_towards_coplanar_directions():
    """The heavy tail of Fig. 3 (sigma = 0.1, m = k = 10) is in the likelihood, not the solver.

    Where the ML estimate lands far from the truth, its directions are nearly coplanar (the
    coplanar-directions failure mode, whose out-of-plane scale is free) and LM started at the
    TRUE geometry typically slides to a solution of the same or higher cost.
    """
    rng = np.random.default_rng(0)
    far, truth_not_better = 0, 0
    for _ in range(40):
        Z = rng.uniform(0, 1, (10, 3))
        Z -= Z[0]
        N = unit(rng.normal(size=(10, 3)))
        D = Z @ N.T + 0.1 * rng.normal(size=(10, 10))
        init = start(D)
        if not init.b_positive_definite:
            continue
        ml = refine_lm(D, init.positions, init.directions, D[0].copy(), free_offsets=True, max_iter=300)
        if np.sqrt(aligned_mse(ml.positions, Z)) < 0.5:
            continue
        far += 1
        sv = np.linalg.svd(ml.directions, compute_uv=False)
        assert sv[-1] / sv[0] < 0.2
        tr = refine_lm(D, Z, N, (D - Z @ N.T).mean(0), free_offsets=True, max_iter=300)
        truth_not_better += int(ml.cost <= tr.cost * (1 + 1e-6))
    assert far >= 3
    assert truth_not_better >= far / 2


def test_solver_flags_every_collapsed_high_noise_solution_and_no_low_noise_one():
    """solve_farfield warns (``directions-collapsed``) instead of silently returning the
    stretched arrays of the test above: at sigma = 0.1 every estimate off by more than the
    array size (1 m) carries the warning; at sigma = 0.01 none does."""
    import warnings

    from selfcal.errors import ConvergenceWarning
    from selfcal.tdoa import solve_farfield

    rng = np.random.default_rng(0)
    wrong, flagged_wrong = 0, 0
    for _ in range(40):
        Z = rng.uniform(0, 1, (10, 3))
        Z -= Z[0]
        N = unit(rng.normal(size=(10, 3)))
        D = Z @ N.T + 0.1 * rng.normal(size=(10, 10))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            r = solve_farfield(D, method="lm", check_degeneracy=False)
        if np.sqrt(aligned_mse(r.positions, Z)) > 1.0:
            wrong += 1
            flagged_wrong += any(w.startswith("directions-collapsed") for w in r.warnings)
    assert wrong >= 3
    assert flagged_wrong == wrong
    for _ in range(20):
        Z = rng.uniform(0, 1, (10, 3))
        N = unit(rng.normal(size=(10, 3)))
        r = solve_farfield(Z @ N.T + 0.01 * rng.normal(size=(10, 10)), method="lm")
        # (a few low-redundancy entries may be reported as uncheckable for gross errors: the
        # small-matrix screen assumes t_3 tails, issue 31; that is not a collapse warning)
        assert not any(w.startswith("directions-collapsed") for w in r.warnings)
