"""Sparse (Schur) far-field covariance and LM steps against their dense references."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.tdoa.refine import _lm_step, _normal_equations, position_covariance, refine_lm


def _problem(seed, m, k, d, sigma=1e-3):
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-0.5, 0.5, (m, d))
    Z[0] = 0
    N = rng.normal(size=(k, d))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    C = rng.normal(size=k)
    D = Z @ N.T + C + sigma * rng.normal(size=(m, k))
    return D, Z, N, C


# both Schur sides: positions eliminated (d m > p k) and directions eliminated
@pytest.mark.parametrize("m,k,d", [(10, 30, 3), (30, 10, 3), (40, 12, 3), (8, 40, 2), (40, 8, 2)])
@pytest.mark.parametrize("seed", range(3))
def test_sparse_covariance_equals_dense_pinv(seed, m, k, d):
    D, Z, N, C = _problem(seed, m, k, d)
    out = refine_lm(D, Z, N, C, free_offsets=True, covariance=False)
    W = np.ones((m, k))
    W[np.random.default_rng(seed).random((m, k)) < 0.1] = 0.0  # missing entries too
    W[:, :] = np.where(W.sum(1, keepdims=True) >= d + 1, W, 1.0)
    args = (D, out.positions, out.directions, out.offsets, W)
    dense = position_covariance(*args, free_offsets=True, method="dense")
    sparse = position_covariance(*args, free_offsets=True, method="schur")
    assert dense.shape == (m, d, d)
    assert np.abs(sparse - dense).max() <= 1e-9 * np.abs(dense).max()


@pytest.mark.parametrize("m,k,d", [(12, 30, 3), (30, 9, 3), (20, 7, 2)])
def test_lm_step_is_the_same_from_either_side(m, k, d):
    D, Z, N, C = _problem(7, m, k, d, sigma=1e-2)
    Hzz, Hzn, Hnn, gz, gn, _, _ = _normal_equations(D, Z, N, C + 0.01, np.ones((m, k)), True)
    a = _lm_step(Hzz, Hzn, Hnn, gz, gn, 0.1, side="directions")
    b = _lm_step(Hzz, Hzn, Hnn, gz, gn, 0.1, side="positions")
    for x, y in zip(a, b, strict=True):
        assert np.allclose(x, y, rtol=1e-8, atol=1e-12 * np.abs(x).max())


def test_cg_step_matches_the_direct_step():
    # the conjugate-gradient step used when both sides are large solves the same damped system
    D, Z, N, C = _problem(3, 30, 40, 3, sigma=1e-2)
    Hzz, Hzn, Hnn, gz, gn, _, _ = _normal_equations(D, Z, N, C + 0.01, np.ones((30, 40)), True)
    a = _lm_step(Hzz, Hzn, Hnn, gz, gn, 0.1, side="directions")
    b = _lm_step(Hzz, Hzn, Hnn, gz, gn, 0.1, side="cg")
    for x, y in zip(a, b, strict=True):
        assert np.abs(x - y).max() <= 1e-8 * np.abs(x).max()


def test_truncated_svd_equals_full_svd():
    from selfcal.tdoa.degeneracy import top_svd

    rng = np.random.default_rng(0)
    X = rng.normal(size=(400, 350)) + 10 * rng.normal(size=(400, 3)) @ rng.normal(size=(3, 350))
    U, s, Vt = top_svd(X, 4)
    s_full = np.linalg.svd(X, compute_uv=False)
    assert np.allclose(s, s_full[:4], rtol=1e-10)
    assert np.allclose(np.abs(np.sum(U * (X @ Vt.T), axis=0)), s, rtol=1e-10)


def test_matrix_free_cg_step_matches_the_direct_step():
    D, Z, N, C = _problem(4, 25, 35, 3, sigma=1e-2)
    W = np.ones((25, 35))
    full = _normal_equations(D, Z, N, C + 0.01, W, True)
    fac = _normal_equations(D, Z, N, C + 0.01, W, True, coupling=False)
    a = _lm_step(*full[:5], 0.1, side="directions")
    b = _lm_step(*fac[:5], 0.1, side="cg")
    for x, y in zip(a, b, strict=True):
        assert np.abs(x - y).max() <= 1e-8 * np.abs(x).max()
