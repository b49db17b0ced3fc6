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


# ----------------------------------------------------------------------------- units (m vs mm)

def _start_near(Z, N, C, rng, spread=0.05):
    Z0 = Z + spread * rng.normal(size=Z.shape)
    Z0[0] = 0
    N0 = N + spread * rng.normal(size=N.shape)
    N0 /= np.linalg.norm(N0, axis=1, keepdims=True)
    return Z0, N0, C + spread * rng.normal(size=C.shape)


@pytest.mark.parametrize("free_offsets", [True, False])
@pytest.mark.parametrize("seed", range(6))
def test_lm_fit_is_invariant_under_a_change_of_units(seed, free_offsets):
    """The same data in kilometres and in millimetres: the fit scales, the directions do not move.

    The LM step is Marquardt-damped (lambda diag(J^T J)) with a ridge relative to each kind of
    unknown's largest diagonal entry, the cost test is relative and the step test compares
    lengths with the array's extent and angles with sqrt(k), so the runs agree to rounding
    (1e-8 of the array). The absolute 1e-12 ridge used before moved km-scale fits by up to
    2e-4 of the array (seeds 1, 5, 7) and the old step test mixed metres with radians.
    """
    m, k = (4, 7) if seed % 2 else (9, 12)
    D, Z, N, C = _problem(seed, m, k, 3, sigma=1e-3)
    Z0, N0, C0 = _start_near(Z, N, C, np.random.default_rng(100 + seed))
    if not free_offsets:
        C0 = C  # known offsets
    kw = dict(free_offsets=free_offsets, covariance=False)
    a = refine_lm(D, Z0, N0, C0, **kw)
    assert a.converged
    size = np.abs(a.positions).max()
    for s in (1e-3, 1e3):
        b = refine_lm(s * D, s * Z0, N0, s * C0, **kw)
        assert b.converged and abs(b.iterations - a.iterations) <= 1  # the last step may round either way
        assert np.abs(b.positions / s - a.positions).max() <= 1e-8 * size
        assert np.abs(b.directions - a.directions).max() <= 1e-8
        assert np.abs(b.offsets / s - a.offsets).max() <= 1e-8 * max(np.abs(a.offsets).max(), size)
        assert b.cost / s**2 == pytest.approx(a.cost, rel=1e-8)


def test_step_test_is_unit_free():
    from selfcal.tdoa.lm import _small_step

    rng = np.random.default_rng(0)
    Z, C = rng.normal(size=(6, 3)), rng.normal(size=9)
    dz, dn = 1e-11 * rng.normal(size=(5, 3)), 1e-11 * rng.normal(size=(9, 3))
    for s in (1e-3, 1.0, 1e3, 1e6):
        dn_s = dn.copy()
        dn_s[:, 2] *= s  # the offset column is a length; the two tangent columns are angles
        assert _small_step(s * dz, dn_s, s * Z, s * C, 2, 1e-10) == _small_step(dz, dn, Z, C, 2, 1e-10)
    # a step that is small in metres but large in kilometres-as-metres is not "small" any more
    assert _small_step(dz, dn, Z, C, 2, 1e-10)
    assert not _small_step(dz, dn, 1e-3 * Z, 1e-3 * C, 2, 1e-10)
