"""The Schur LM engine's direct step (small reduced systems) against its CG step."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa.engine import model, nls
from selfcal.toa.engine import schur_lm as sl

CASES = [  # (I, J, offsets, dim, fraction missing)
    (12, 6, "both", 3, 0.0),
    (8, 10, "none", 2, 0.0),
    (10, 14, "receivers", 3, 0.1),
    (20, 20, "sources", 3, 0.0),
    (14, 9, "both", 2, 0.1),
]


def _problem(I: int, J: int, offsets: str, d: int, miss: float, seed: int) -> tuple:
    g = np.random.default_rng(seed)
    r = g.uniform(0, 1.5, (I, d))
    s = 0.75 + g.normal(0, 2, (J, d))
    dr, os_ = g.uniform(0, 3, I), g.uniform(0, 30, J)
    hr, hs = nls._flags(offsets)
    Y = nls.toa_model(r, s, dr if hr else None, os_ if hs else None) + g.normal(0, 0.007, (I, J))
    if miss:
        Y[g.uniform(size=Y.shape) < miss] = np.nan
    r0, s0 = r + g.normal(0, 0.1, r.shape), s + g.normal(0, 0.1, s.shape)
    th0 = nls._pack(r0, s0, dr + g.normal(0, 0.1, I) if hr else None, os_ + g.normal(0, 0.1, J) if hs else None)
    lay = nls._make_layout(r0, s0, offsets)

    def gauge(t: np.ndarray) -> np.ndarray:
        return nls.gauge_basis(*model._unpack(t, I, J, d, offsets)[:2], offsets)

    return th0, Y, lay, gauge


@pytest.mark.parametrize("case", CASES, ids=[f"{c[0]}x{c[1]}-{c[2]}-{c[3]}d" for c in CASES])
def test_direct_step_gives_the_iterates_of_an_exact_cg_step(case: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """Both paths solve the same damped reduced system S x = rhs; with the CG forcing term at
    1e-13 the CG iterates are the exact ones, so after 1, 3, 10 iterations and at convergence
    the direct path must give the same parameters (to round-off amplified by cond(S), ~1e-9)
    and the same iteration count (the accept / reject sequence of the damping is identical);
    25 iterations is convergence for all but the ill-conditioned 12 x 6 (cap, still compared)."""
    monkeypatch.setattr(sl, "CG_RTOL", (1e-13, 1e-13))
    for seed in (0,) if case[2] == "both" else (0, 1):  # exact CG steps are slow on 'both'
        th0, Y, lay, gauge = _problem(*case, seed=seed)
        for nfev in (1, 5, 25):
            a = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, nfev, 1e-10, gauge, step="reduced")
            b = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, nfev, 1e-10, gauge, step="cg")
            assert a[2] == b[2] and a[1] == b[1]
            np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-8 * np.abs(b[0]).max())


def test_direct_step_on_observed_pairs_equals_the_dense_grid() -> None:
    """The observed-pairs storage (selfcal.toa.sparse's path) forms the same reduced matrix
    (to round-off) and reaches the same minimum. The iterates themselves agree only to
    round-off times cond(S) (~3e5 on this both-offsets network), so the minimum is compared
    by its cost (to 1e-9) and its parameters to 1e-5 of their scale."""
    th0, Y, lay, gauge = _problem(10, 14, "both", 3, 0.2, seed=3)
    i, j = np.nonzero(np.isfinite(Y))
    a = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, None, 1e-10, gauge, step="reduced")
    b = sl.solve_schur_lm(th0, Y[i, j], lay, "linear", 1.0, None, 1e-10, gauge, pairs=(i, j), step="reduced")
    assert a[1] and b[1]
    ca = float(np.sum(nls.toa_residuals(a[0], Y, 3, "both") ** 2))
    cb = float(np.sum(nls.toa_residuals(b[0], Y, 3, "both") ** 2))
    assert abs(ca - cb) <= 1e-9 * ca
    np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-5 * np.abs(a[0]).max())
    ori = sl._Oriented(lay)
    xK, xE, _, _ = ori.split(a[0])
    obs = np.isfinite(Y)
    Ug, _ = sl.directions(xK, xE, sl.Grid(*obs.shape))
    Up, _ = sl.directions(xK, xE, sl.Pairs(i, j, *obs.shape))
    Sg = sl._Reduced(Ug, obs.astype(float), True, True, 1e-4, sl.Grid(*obs.shape), precondition=False).dense()
    Sp = sl._Reduced(Up, np.ones(i.size), True, True, 1e-4, sl.Pairs(i, j, *obs.shape), precondition=False).dense()
    np.testing.assert_allclose(Sg, Sp, rtol=0, atol=1e-12 * np.abs(Sg).max())


def test_dense_reduced_matrix_is_the_cg_operator() -> None:
    """``dense()`` is the matrix of the matrix-free product ``smul`` (column by column)."""
    th0, Y, lay, gauge = _problem(12, 6, "both", 3, 0.1, seed=5)
    xK, xE, _, _ = sl._Oriented(lay).split(th0)
    pat = sl.Grid(lay.k_idx.shape[0], lay.e_idx.shape[0])
    YK = Y if lay.k_is_receivers else Y.T
    U, _ = sl.directions(xK, xE, pat)
    red = sl._Reduced(U, np.isfinite(YK).astype(float), True, True, 1e-3, pat)
    S = red.dense()
    cols = np.column_stack([red.smul(e) for e in np.eye(S.shape[0])])
    np.testing.assert_allclose(S, cols, rtol=0, atol=1e-10 * np.abs(S).max())


def test_direct_step_with_a_robust_loss_reaches_the_cg_minimum() -> None:
    """Robust weights enter S like the data weights: same stationary point as the CG path."""
    th0, Y, lay, gauge = _problem(10, 14, "receivers", 3, 0.0, seed=4)
    Y = Y.copy()
    Y[2, 3] += 5.0  # a gross entry, down-weighted by soft-L1
    a = sl.solve_schur_lm(th0, Y, lay, "soft_l1", 0.01, 200, 1e-12, gauge, step="reduced")
    b = sl.solve_schur_lm(th0, Y, lay, "soft_l1", 0.01, 200, 1e-12, gauge, step="cg")
    assert a[1] and b[1]
    ra = nls.toa_residuals(a[0], Y, 3, "receivers")
    rb = nls.toa_residuals(b[0], Y, 3, "receivers")
    ca = float(np.sum(2 * (np.sqrt(1 + (ra / 0.01) ** 2) - 1)))
    cb = float(np.sum(2 * (np.sqrt(1 + (rb / 0.01) ** 2) - 1)))
    assert abs(ca - cb) <= 1e-6 * cb


@pytest.mark.parametrize("case", CASES, ids=[f"{c[0]}x{c[1]}-{c[2]}-{c[3]}d" for c in CASES])
def test_dense_step_gives_the_iterates_of_the_reduced_step(case: tuple) -> None:
    """The full normal matrix and its Schur reduction solve the same damped system exactly: the
    same iterates (to round-off times cond, ~1e-8) and iteration counts at every cap."""
    th0, Y, lay, gauge = _problem(*case, seed=2)
    for nfev in (1, 5, 25):
        a = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, nfev, 1e-10, gauge, step="dense")
        b = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, nfev, 1e-10, gauge, step="reduced")
        assert a[2] == b[2] and a[1] == b[1]
        np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-8 * np.abs(b[0]).max())
    i, j = np.nonzero(np.isfinite(Y))
    c = sl.solve_schur_lm(th0, Y[i, j], lay, "linear", 1.0, 5, 1e-10, gauge, pairs=(i, j), step="dense")
    d = sl.solve_schur_lm(th0, Y, lay, "linear", 1.0, 5, 1e-10, gauge, step="dense")
    np.testing.assert_allclose(c[0], d[0], rtol=0, atol=1e-6 * np.abs(d[0]).max())


@pytest.mark.parametrize("offsets,d", [("both", 3), ("none", 3), ("receivers", 2), ("both", 2)])
def test_analytic_gauge_projector_equals_the_qr_basis_projector(offsets: str, d: int) -> None:
    """The dense step's projector (translations, rotations by Gram-Schmidt, common shift) is
    ``I - Q Q^T`` with Q the orthonormal QR basis of nls.gauge_basis (independent computation)."""
    from selfcal.toa.engine.model import GaugeProjector

    g = np.random.default_rng(7)
    I, J = 7, 5
    r, s = g.normal(size=(I, d)), g.normal(size=(J, d)) * 3
    hr, hs = nls._flags(offsets)
    th = nls._pack(r, s, g.normal(size=I) if hr else None, g.normal(size=J) if hs else None)
    Q = nls.gauge_basis(r, s, offsets)
    proj = GaugeProjector(th, I + J, d, I, offsets == "both")
    for _ in range(3):
        dx = g.normal(size=th.size)
        want = dx - Q @ (Q.T @ dx)
        np.testing.assert_allclose(proj.apply(dx.copy()), want, rtol=0, atol=1e-12 * np.abs(dx).max())


def test_dense_step_with_free_parameters_holds_the_others_and_reaches_a_stationary_point() -> None:
    """A partial refit (the search's move ranking): fixed parameters keep their values exactly,
    and the free ones end where the gradient of the cost over them vanishes (checked on the
    analytic Jacobian of nls.toa_jacobian, an independent computation)."""
    from selfcal.toa.engine.dense_lm import solve_dense_lm

    th0, Y, lay, _ = _problem(12, 6, "both", 3, 0.0, seed=1)
    free = np.zeros(th0.size, bool)
    free[3:6] = True  # receiver 1
    free[(12 + 4) * 3:(12 + 5) * 3] = True  # source 4
    free[18 * 3 + 1] = True  # its receiver offset
    ii, jj = np.nonzero(np.isfinite(Y))
    th, conv, _ = solve_dense_lm(th0, Y[ii, jj], ii, jj, 12, 6, 3, "both", "linear", 1.0, 200, 1e-12, free=free)
    assert conv
    np.testing.assert_array_equal(th[~free], th0[~free])
    Jm = nls.toa_jacobian(th, Y, 3, "both").toarray()
    grad = Jm.T @ nls.toa_residuals(th, Y, 3, "both")
    assert np.abs(grad[free]).max() <= 1e-6 * np.abs(Jm[:, free]).max() * np.sqrt(np.nanmean(Y**2))


@pytest.mark.parametrize("seed", range(8))
def test_inv_blocks_decides_as_the_svd_condition_of_every_block(seed):
    """_inv_blocks runs the SVD only where the Frobenius bound does not clear a block: the
    same inverse and the same raise / no raise as ``np.linalg.cond(blocks) < COND_MAX`` over
    blocks conditioned from 1 to 1e16 (and exactly singular ones)."""
    from selfcal.errors import DegenerateGeometryError
    from selfcal.toa.engine.schur_lm import COND_MAX, _inv_blocks

    g = np.random.default_rng(seed)
    for m in (3, 4):
        Q = np.linalg.qr(g.standard_normal((200, m, m)))[0]
        cond = 10.0 ** g.uniform(0, 16, 200)
        ev = np.exp(np.log(cond)[:, None] * g.uniform(0, 1, (200, m)))
        ev[:, 0], ev[:, 1] = 1.0, cond
        B = np.einsum("nij,nj,nkj->nik", Q, ev, Q)
        if seed % 2:
            B[g.integers(200)] = np.outer(np.arange(1.0, m + 1), np.arange(1.0, m + 1))  # rank one
        for blocks in (B, B[np.linalg.cond(B) < COND_MAX]):
            ok = np.linalg.cond(blocks) < COND_MAX
            if ok.all():
                np.testing.assert_array_equal(_inv_blocks(blocks), np.linalg.inv(blocks))
            else:
                with pytest.raises(DegenerateGeometryError, match=f"node {int(np.flatnonzero(~ok)[0])} "):
                    _inv_blocks(blocks)
