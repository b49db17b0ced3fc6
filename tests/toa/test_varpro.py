"""Variable projection of the offsets (selfcal.toa.engine.varpro) against the joint dense LM.

Both engines minimise the same cost, so at a converged point they must agree; the checks use
independent computations (the sparse analytic Jacobian of :func:`selfcal.toa.engine.nls.toa_jacobian`,
the joint engine) and many seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.robust import loss_rho
from selfcal.toa.engine import dense_lm, model, nls
from selfcal.toa.engine.dense_lm import solve_varpro_lm

MODES = ("both", "receivers", "sources")


def _problem(seed: int, offsets: str, I: int = 12, J: int = 8, d: int = 3, miss: float = 0.0,
             noise: float = 1e-3, start: float = 0.05) -> tuple:
    g = np.random.default_rng(seed)
    r = g.uniform(0, 1.5, (I, d))
    s = 0.75 + g.normal(0, 1.5, (J, d))
    hr, hs = nls._flags(offsets)
    Y = nls.toa_model(r, s, g.uniform(0, 3, I) if hr else None, g.uniform(0, 30, J) if hs else None)
    Y = Y + g.normal(0, noise, Y.shape)
    if miss:
        drop = g.uniform(size=Y.shape) < miss
        drop[:, 0] = drop[0, :] = False  # keeps every node observed and the graph connected
        Y[drop] = np.nan
    th0 = nls._pack(r + g.normal(0, start, r.shape), s + g.normal(0, start, s.shape),
                    np.zeros(I) if hr else None, np.zeros(J) if hs else None)
    ii, jj = np.nonzero(np.isfinite(Y))
    return th0, Y, ii, jj, I, J, d


def _cost(th: np.ndarray, Y: np.ndarray, d: int, offsets: str, loss: str, fs: float) -> float:
    f = nls.toa_residuals(th, Y, d, offsets)
    f = f[np.isfinite(f)]
    if loss == "linear":
        return 0.5 * float(f @ f)
    return 0.5 * fs**2 * float(loss_rho((f / fs) ** 2, loss)[0].sum())


@pytest.fixture
def tight(monkeypatch: pytest.MonkeyPatch) -> None:
    """Run both engines to stationarity (no relative-cost stop): the comparison at 1e-8 is then
    a property of the minimum, not of where each engine's ftol happened to stop it."""
    monkeypatch.setattr(dense_lm, "FTOL", 0.0)


@pytest.mark.parametrize("offsets", MODES)
def test_varpro_minimum_is_the_joint_lm_minimum(offsets: str, tight: None) -> None:
    """Over 8 seeds (10 % missing on half of them): run to stationarity from the same start,
    both engines end at the same point: modelled ranges and offsets equal to 1e-8 of their
    scale (plus the conditioning bound below), positions likewise after the rigid gauge is removed (both conserve the centroid and
    ``sum d - sum o``; rotations only to first order per step, so positions are compared
    after a rigid Procrustes fit of one onto the other, and the offsets, which are
    rotation-invariant, directly)."""
    from selfcal.geometry import align

    for seed in range(8):
        th0, Y, ii, jj, I, J, d = _problem(seed, offsets, miss=0.1 if seed % 2 else 0.0)
        a = dense_lm.full_lm(th0, Y[ii, jj], ii, jj, I, J, d, offsets, "linear", 1.0, 3000, 1e-15)
        b = solve_varpro_lm(th0, Y[ii, jj], ii, jj, I, J, d, offsets, "linear", 1.0, 3000, 1e-15)
        assert a[1] and b[1]
        ua, ub = model._unpack(a[0], I, J, d, offsets), model._unpack(b[0], I, J, d, offsets)
        # the observable (modelled ranges) agrees to 1e-8; in the flat directions of the cost
        # that fixes the parameters only to |J dx| / sigma_min(J) (sigma_min the smallest
        # non-gauge singular value): that bound, on the measured model difference, is added to
        # the parameters' 1e-8 (it matters on the worst-conditioned draws, cond(J^T J) ~ 1e7)
        ma, mb = nls.toa_model(*ua), nls.toa_model(*ub)
        np.testing.assert_allclose(mb, ma, rtol=0, atol=1e-8 * np.abs(ma).max())
        Jm = nls.toa_jacobian(a[0], Y, d, offsets).toarray()
        ev = np.linalg.eigvalsh(Jm.T @ Jm)
        n_gauge = nls.gauge_basis(ua[0], ua[1], offsets).shape[1]
        flat = float(np.linalg.norm((ma - mb)[np.isfinite(Y)])) / np.sqrt(ev[n_gauge])
        off = a[0][(I + J) * d:]
        np.testing.assert_allclose(b[0][(I + J) * d:], off, rtol=0, atol=1e-8 * np.abs(off).max() + flat)
        Pa, Pb = np.vstack(ua[:2]), np.vstack(ub[:2])
        scale = np.abs(Pa).max()
        np.testing.assert_allclose(align(Pb, Pa, reflection=False).apply(Pb), Pa, rtol=0, atol=1e-8 * scale + flat)
        # the gauge the dense engine keeps: centroid and the common offset shift of the start
        P0, Pb = th0[:(I + J) * d].reshape(-1, d), b[0][:(I + J) * d].reshape(-1, d)
        np.testing.assert_allclose(Pb.mean(axis=0), P0.mean(axis=0), rtol=0, atol=1e-12 * scale)
        if offsets == "both":
            v = np.r_[np.ones(I), -np.ones(J)]
            assert abs(v @ b[0][(I + J) * d:] - v @ th0[(I + J) * d:]) <= 1e-9 * np.abs(off).max()


def test_varpro_converges_to_a_stationary_point_of_the_full_cost(tight: None) -> None:
    """The gradient of the full cost (positions *and* offsets) vanishes at the VarPro point, on
    the independent sparse Jacobian: the offsets are optimal, the positions stationary.
    Bound: 1e-7 of |J| |f|, well above the round-off floor of a gradient of 72-96 terms at this
    conditioning (measured 1e-14 - 1e-10 |f|). 6 seeds x 3 offset modes, 10 % missing.
    (Robust losses run the joint engine, see the module notes.)"""
    loss = "linear"
    for seed in range(6):
        for offsets in MODES:
            th0, Y, ii, jj, I, J, d = _problem(seed, offsets, miss=0.1)
            fs = 3e-3
            th, ok, _ = solve_varpro_lm(th0, Y[ii, jj], ii, jj, I, J, d, offsets, loss, fs, 3000, 1e-15)
            assert ok
            f = nls.toa_residuals(th, Y, d, offsets)
            obs = np.isfinite(f)
            Jm = nls.toa_jacobian(th, Y, d, offsets).toarray()
            w = np.ones(f.size) if loss == "linear" else loss_rho((f[obs] / fs) ** 2, loss)[1]
            grad = Jm.T @ (w * f[obs])
            assert np.abs(grad).max() <= 1e-7 * np.abs(Jm).max() * np.sqrt(float(f[obs] @ f[obs]))


@pytest.mark.parametrize("offsets", MODES)
def test_varpro_never_ends_above_its_start_and_its_offsets_are_the_projection(offsets: str) -> None:
    """From far starts (0.5 m perturbations, 20 seeds) the cost never rises above the start's
    with its offsets re-solved, and at the returned geometry the offsets are the least-squares
    offsets (the variable-projection invariant): re-solving them by lstsq on the offset design
    changes the cost by at most 1e-9 relative."""
    for seed in range(20):
        th0, Y, ii, jj, I, J, d = _problem(seed, offsets, J=6, start=0.5, noise=5e-3)
        th, _, _ = solve_varpro_lm(th0, Y[ii, jj], ii, jj, I, J, d, offsets, "linear", 1.0, 60, 1e-10)
        c0 = _cost(th0, Y, d, offsets, "linear", 1.0)
        c = _cost(th, Y, d, offsets, "linear", 1.0)
        assert c <= c0
        k = (I + J) * d
        P = th[:k].reshape(I + J, d)
        dist = np.linalg.norm(P[ii] - P[I + jj], axis=1)
        hr, hs = nls._flags(offsets)
        cols = ([np.eye(I)[ii]] if hr else []) + ([np.eye(J)[jj]] if hs else [])
        A = np.hstack(cols)
        z = np.linalg.lstsq(A, Y[ii, jj] - dist, rcond=None)[0]
        res = A @ z + dist - Y[ii, jj]
        assert abs(c - 0.5 * float(res @ res)) <= 1e-9 * c


def test_routing_keyword_and_partial_refits() -> None:
    """``solve_dense_lm(varpro=True)`` is the VarPro engine; a partial refit (``free`` mask) and
    the offsets-free model are the joint engine's, bit for bit."""
    th0, Y, ii, jj, I, J, d = _problem(3, "both")
    a = dense_lm.solve_dense_lm(th0, Y[ii, jj], ii, jj, I, J, d, "both", "linear", 1.0, 30, 1e-10, varpro=True)
    b = solve_varpro_lm(th0, Y[ii, jj], ii, jj, I, J, d, "both", "linear", 1.0, 30, 1e-10)
    np.testing.assert_array_equal(a[0], b[0])
    free = np.zeros(th0.size, bool)
    free[:3] = True
    free[(I + J) * d] = True
    a = dense_lm.solve_dense_lm(th0, Y[ii, jj], ii, jj, I, J, d, "both", "linear", 1.0, 30, 1e-10, free=free,
                                varpro=True)
    b = dense_lm.full_lm(th0, Y[ii, jj], ii, jj, I, J, d, "both", "linear", 1.0, 30, 1e-10, free=free)
    np.testing.assert_array_equal(a[0], b[0])
    th0n, Yn, ii, jj, I, J, d = _problem(3, "none")
    a = dense_lm.solve_dense_lm(th0n, Yn[ii, jj], ii, jj, I, J, d, "none", "linear", 1.0, 30, 1e-10, varpro=True)
    b = dense_lm.full_lm(th0n, Yn[ii, jj], ii, jj, I, J, d, "none", "linear", 1.0, 30, 1e-10)
    np.testing.assert_array_equal(a[0], b[0])
