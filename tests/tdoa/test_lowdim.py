"""Planar (dim=2) and linear (dim=1) far-field calibration, and the dim="auto" rank test."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.geometry import align
from selfcal.tdoa import farfield_crlb, solve_farfield


def circular(m=16, radius=0.05):
    th = 2 * np.pi * np.arange(m) / m
    Z = radius * np.column_stack([np.cos(th), np.sin(th)])
    return Z - Z[0]


def planar_problem(seed, sigma, m=16, k=24):
    rng = np.random.default_rng(seed)
    Z = circular(m)
    az = rng.uniform(0, 2 * np.pi, k)
    N = np.column_stack([np.cos(az), np.sin(az)])
    D = Z @ N.T + rng.normal(size=k) + sigma * rng.normal(size=(m, k))
    return D, Z, N


def aligned_sq_error(est, true, *, scale=False):
    al = align(est, true, reflection=True, scale=scale)
    return float(np.sum((al.apply(est) - true) ** 2))


@pytest.mark.parametrize("dim", [2, "auto"])
def test_circular_array_in_2d_reaches_the_crlb_blind(dim):
    # 40 seeds, noise level not given to the solver. The ML estimate is asymptotically
    # efficient: the mean aligned squared error over seeds estimates trace(CRLB) with a relative
    # std of about sqrt(2 / (40 * 29)) = 4 % (29 = 2 m - 3 free coordinates per trial), so
    # [0.75, 1.3] is a > 5-sigma band that still fails a 2x-inefficient estimator.
    sigma = 2e-4
    errs, bounds = [], []
    for seed in range(40):
        D, Z, N = planar_problem(seed, sigma)
        res = solve_farfield(D, dim=dim, offsets="free")
        assert res.dim == 2 and res.case == "planar" and res.positions.shape == (16, 2)
        errs.append(aligned_sq_error(res.positions, Z))
        bounds.append(np.trace(farfield_crlb(Z, N, sigma), axis1=1, axis2=2).sum())
    ratio = np.mean(errs) / np.mean(bounds)
    assert 0.75 < ratio < 1.3, ratio


def test_planar_covariance_predicts_the_error():
    # the reported Gauss-Newton covariance (noise estimated from the residual) agrees with the
    # CRLB at the truth to first order: same 4 % Monte-Carlo band reasoning as above
    sigma = 2e-4
    pred, bound = [], []
    for seed in range(10):
        D, Z, N = planar_problem(seed, sigma)
        res = solve_farfield(D, dim=2, offsets="free")
        pred.append(np.trace(res.position_cov, axis1=1, axis2=2).sum())
        bound.append(np.trace(farfield_crlb(Z, N, sigma), axis1=1, axis2=2).sum())
    # position_cov is in the gauge "z_1 = 0, best rotation", the CRLB in "best rigid motion":
    # the first has the translation's share in it (z_1 fixed), so it is larger, never smaller
    assert np.mean(pred) > 0.9 * np.mean(bound)
    assert np.mean(pred) < 4.0 * np.mean(bound)


def linear_problem(seed, sigma, m=8, k=36, spacing=0.03):
    rng = np.random.default_rng(seed)
    x = spacing * np.arange(m)
    th = rng.uniform(0, 2 * np.pi, k)
    u = np.cos(th)
    D = np.outer(x, u) + rng.normal(size=k) + sigma * rng.normal(size=(m, k))
    return D, x, u


def test_linear_array_in_1d_reaches_the_crlb_up_to_scale_blind():
    # positions along the line up to one scale factor (paper 000 sec. 2.2: rank 1); the SVD is
    # the least-squares (ML) fit, so the error after the best scale + translation + sign meets
    # the CRLB with the scale gauge removed; band as in the planar test (m - 2 = 6 free
    # coordinates per trial, 60 seeds: relative std ~ 7 %)
    sigma = 2e-4
    errs, bounds = [], []
    for seed in range(60):
        D, x, u = linear_problem(seed, sigma)
        res = solve_farfield(D, dim="auto", offsets="free")
        assert res.dim == 1 and res.case == "linear" and res.positions.shape == (8, 1)
        errs.append(aligned_sq_error(res.positions, x[:, None], scale=True))
        bounds.append(np.trace(farfield_crlb(x[:, None], u[:, None], sigma), axis1=1, axis2=2).sum())
        # the reported scale is the smallest consistent one: |u_j| <= 1 for the true directions
        # means the true array is at least as long (up to the noise), and no longer than
        # 1 / max|u_j| times it
        length, true_len = np.ptp(res.positions), np.ptp(x)
        assert length <= true_len * (1 + 1e-2)
        assert length >= true_len * np.max(np.abs(u)) * (1 - 1e-2)
    ratio = np.mean(errs) / np.mean(bounds)
    assert 0.6 < ratio < 1.5, ratio


def test_general_3d_array_is_never_called_low_dimensional():
    for seed in range(20):
        rng = np.random.default_rng(seed)
        Z = rng.uniform(-0.5, 0.5, (10, 3))
        Z[:, 2] *= 0.1  # a flat but truly 3-D array: thickness 0.1 >> noise
        Z[0] = 0
        N = rng.normal(size=(20, 3))
        N /= np.linalg.norm(N, axis=1, keepdims=True)
        D = Z @ N.T + rng.normal(size=20) + 1e-3 * rng.normal(size=(10, 20))
        res = solve_farfield(D, dim="auto")
        assert res.dim == 3 and res.case == "spatial"


def test_planar_array_with_sources_off_its_plane_is_refused_in_every_mode():
    rng = np.random.default_rng(1)
    Z = np.column_stack([circular(), np.zeros(16)])
    az, el = rng.uniform(0, 2 * np.pi, 30), rng.uniform(-0.8, 0.8, 30)
    N = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    D = Z @ N.T + 1e-5 * rng.normal(size=(16, 30))
    for dim in (3, 2, "auto"):
        with pytest.raises(DegenerateGeometryError, match="planar-motion") as exc:
            solve_farfield(D, dim=dim)
        assert exc.value.partial.determined.startswith("not determined")


def test_dimension_contradicting_the_data_is_named():
    D, _, _ = planar_problem(0, 1e-4)
    with pytest.raises(InputError, match="dim=1"):
        solve_farfield(D, dim=1)
    rng = np.random.default_rng(0)
    Z = rng.uniform(-0.5, 0.5, (10, 3))
    N = rng.normal(size=(20, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    with pytest.raises(InputError, match="dim=2 but the data are 3-D"):
        solve_farfield(Z @ N.T, dim=2)


def test_planar_directions_on_two_lines_are_refused():
    rng = np.random.default_rng(2)
    Z = circular()
    az = np.repeat([0.3, 1.4], 6) + np.tile([0.0, np.pi], 6)
    N = np.column_stack([np.cos(az), np.sin(az)])
    D = Z @ N.T + 1e-6 * rng.normal(size=(16, 12))
    with pytest.raises(DegenerateGeometryError, match="two lines"):
        solve_farfield(D, dim=2)


def test_planar_result_is_json_and_says_its_case():
    import json

    D, _, _ = planar_problem(3, 1e-4)
    d = solve_farfield(D, dim=2).to_dict()
    json.dumps(d, allow_nan=False)
    assert d["dim"] == 2 and d["case"] == "planar" and "in-plane" in d["determined"]


def test_auto_with_missing_entries_keeps_the_planar_rank():
    # completing the gaps at rank 3 would invent a third component; the rank is chosen on
    # completions of increasing rank instead
    for seed in range(5):
        D, Z, _ = planar_problem(seed, 1e-4)
        D[np.random.default_rng(seed).random(D.shape) < 0.1] = np.nan
        res = solve_farfield(D, dim="auto")
        assert res.case == "planar"
        assert aligned_sq_error(res.positions, Z) / 16 < (5e-4) ** 2


def test_linear_array_covariance_matches_a_dense_numeric_computation():
    # the 1-D covariance (Schur complement over the (u_j, C_j) blocks, scale gauge projected out)
    # against the pseudo-inverse of a finite-difference J^T J over all unknowns
    from selfcal.tdoa.covariance import linear_position_covariance

    rng = np.random.default_rng(3)
    m, k = 8, 25
    x = np.concatenate([[0.0], np.sort(rng.uniform(-0.2, 0.2, m - 1))])
    u = rng.uniform(-1, 1, k)
    C = rng.normal(size=k)
    D = np.outer(x, u) + C + 1e-3 * rng.standard_normal((m, k))
    W = (rng.random((m, k)) > 0.1).astype(float)
    res = solve_farfield(np.where(W > 0, D, np.nan), dim=1)
    xs, us, Cs = res.positions[:, 0], res.directions[:, 0], res.offsets
    cov = linear_position_covariance(D, xs, us, Cs, W)

    def model(p):
        xx = np.concatenate([[0.0], p[: m - 1]])
        return (np.outer(xx, p[m - 1: m - 1 + k]) + p[m - 1 + k:]).ravel()

    p0 = np.concatenate([xs[1:], us, Cs])
    eps = 1e-6
    J = np.stack([(model(p0 + eps * e) - model(p0 - eps * e)) / (2 * eps) for e in np.eye(p0.size)], axis=1)
    Jw = J * np.sqrt(W.ravel())[:, None]
    full = np.linalg.pinv(Jw.T @ Jw, rcond=1e-10, hermitian=True)[: m - 1, : m - 1]
    g = xs[1:] / np.linalg.norm(xs[1:])
    P = np.eye(m - 1) - np.outer(g, g)
    Cls = np.sum(W * (D - np.outer(xs, us)), axis=0) / W.sum(axis=0)  # least-squares offsets
    r = np.where(W > 0, D - np.outer(xs, us) - Cls, 0.0)
    sigma2 = np.sum(r**2) / (W.sum() - (m - 1 + 2 * k - 1))
    ref = sigma2 * np.diag(P @ full @ P)
    assert np.allclose(cov[1:, 0, 0], ref, rtol=1e-5, atol=0)
    assert res.position_cov is not None and np.allclose(res.position_cov[:, 0, 0], cov[:, 0, 0])


@pytest.mark.slow
def test_linear_array_covariance_predicts_the_scatter():
    # over seeds, the reported variances match the scatter of the scale-aligned positions
    rng = np.random.default_rng(11)
    m, k = 8, 60
    x = np.linspace(0, 0.3, m)
    u = rng.uniform(-1, 1, k)
    u[0] = 1.0  # an endfire source: the reported scale (max |u| = 1) is then the true one
    errs, preds, refused = [], [], 0
    for seed in range(200):
        g = np.random.default_rng(seed)
        D = np.outer(x, u) + g.normal(size=k) + 1e-3 * g.standard_normal((m, k))
        try:
            res = solve_farfield(D, dim=1)
        except InputError:
            # the explicit dim=1 is checked by the nested rank test (false-alarm rate RANK_ALPHA =
            # 1e-3 per step, two steps here): a rank-1 draw is refused at that rate, and seed 118
            # is such a draw (s_3 = 0.00924 just above its threshold). Measured on this scene over
            # 20000 draws: 24 refused (1.2e-3: 16 at the rank-2 step, 8 at the rank-3 step), so
            # 200 draws hold one or more with probability ~0.2; more than 3 (P < 1e-3 at the
            # nominal 2e-3) would mean the test's level is wrong
            refused += 1
            continue
        est = res.positions[:, 0]
        a = (est @ x) / (est @ est)  # best scaling about the first position
        errs.append(a * est - x)
        preds.append(res.position_cov[:, 0, 0])
    ratio = np.mean(np.array(errs)[:, 1:] ** 2, axis=0) / np.mean(np.array(preds)[:, 1:], axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio  # 200 draws: each ratio within ~15 % (2 sd)
    assert refused <= 3, refused
