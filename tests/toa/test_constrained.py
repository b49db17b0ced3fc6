"""Constrained refine_toa (fixed masks, offset constraints, priors) against a dense reference.

The reference is written independently here: a plain numpy residual over the free
unknowns, ``scipy.optimize.least_squares`` with a 2-point numeric Jacobian, and the
covariance ``sigma^2 (J^T J)^+`` from a central-difference Jacobian and a dense
pseudo-inverse (the Moore-Penrose inverse removes whatever gauge the constraints leave).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
import pytest
from scipy.optimize import least_squares

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.toa.engine.nls import refine_toa, toa_model

NOISE = 0.01  # m; small against the 4 m network so the fit is in its linear regime


@pytest.fixture(params=["auto", "schur"])
def solver(request):
    """Each dense-reference test runs on both constrained engines: "auto" (SciPy trf on
    these small problems) and "schur" (the Schur-reduced Newton-LM of toa/engine/schur_affine.py,
    forced), so the new engine is checked against the independent dense computation."""
    return request.param


def _network(seed: int, I: int = 6, J: int = 8, d: int = 3):
    rng = np.random.default_rng(seed)
    r = rng.uniform(-2, 2, (I, d))
    s = rng.uniform(-2, 2, (J, d))
    dr = rng.normal(0, 0.1, I)
    os_ = rng.normal(0, 0.1, J)
    return rng, r, s, dr, os_


class _Dense:
    """Free-parameter residual built by hand: positions with a mask, offsets via a basis."""

    def __init__(self, Y, r0, s0, fr, fs, Br, Bs, d0r, d0s, prior_idx=(), prior_mu=(), prior_w=()):
        self.Y, self.obs = Y, np.isfinite(Y)
        self.pos0 = np.concatenate([r0.ravel(), s0.ravel()])
        self.free = np.nonzero(~np.concatenate([fr.ravel(), fs.ravel()]))[0]
        self.I, self.d = r0.shape
        self.Br, self.Bs, self.d0r, self.d0s = Br, Bs, d0r, d0s
        self.kr = 0 if Br is None else Br.shape[1]
        self.prior_idx = np.asarray(prior_idx, int)
        self.prior_mu = np.asarray(prior_mu, float)
        self.prior_w = np.asarray(prior_w, float)

    def split(self, x):
        pos = self.pos0.copy()
        pos[self.free] = x[: self.free.size]
        n = self.I * self.d
        r = pos[:n].reshape(self.I, self.d)
        s = pos[n:].reshape(-1, self.d)
        k = self.free.size
        dr = None if self.Br is None else self.d0r + self.Br @ x[k : k + self.kr]
        os_ = None if self.Bs is None else self.d0s + self.Bs @ x[k + self.kr :]
        return r, s, dr, os_

    def resid(self, x):
        r, s, dr, os_ = self.split(x)
        D = np.sqrt(((r[:, None] - s[None]) ** 2).sum(-1))
        if dr is not None:
            D = D + dr[:, None]
        if os_ is not None:
            D = D + os_[None, :]
        f = (D - self.Y)[self.obs]
        if self.prior_idx.size:
            f = np.concatenate([f, self.prior_w * (x[self.prior_idx] - self.prior_mu)])
        return f

    def x0(self, dr0, os0):
        parts = [self.pos0[self.free]]
        if self.Br is not None:
            parts.append(np.linalg.lstsq(self.Br, dr0 - self.d0r, rcond=None)[0])
        if self.Bs is not None:
            parts.append(np.linalg.lstsq(self.Bs, os0 - self.d0s, rcond=None)[0])
        return np.concatenate(parts)


def _num_jac(fun: Callable, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(x.size):
        e = np.zeros_like(x)
        e[k] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.column_stack(cols)


def _dense_solution(dense: _Dense, x0: np.ndarray, loss: str = "linear", f_scale: float = 1.0):
    sol = least_squares(dense.resid, x0, jac="2-point", method="trf", loss=loss, f_scale=f_scale,
                        xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=20000)
    return sol


def _dense_cov(dense: _Dense, x: np.ndarray, m: int):
    Jm = _num_jac(dense.resid, x)
    f = dense.resid(x)
    sv = np.linalg.svd(Jm, compute_uv=False)
    rank = int((sv > 1e-8 * sv[0]).sum())
    sigma2 = float(f @ f) / (f.size - rank)
    return sigma2 * np.linalg.pinv(Jm.T @ Jm, rcond=1e-10), sigma2, rank


def _node_block(dense: _Dense, C: np.ndarray, which: str, k: int) -> np.ndarray:
    """Position covariance of receiver/source k, mapped from x (fixed coordinates: zero)."""
    d = dense.d
    base = (0 if which == "r" else dense.I * d) + k * d
    T = np.zeros((d, C.shape[0]))
    for a in range(d):
        hit = np.nonzero(dense.free == base + a)[0]
        if hit.size:
            T[a, hit[0]] = 1.0
    return T @ C @ T.T


def _assert_same_fit(sol, dense: _Dense, ref, Y, atol: float = 2e-7):
    # gauge-invariant comparison: the fitted range matrix and the cost (the minimiser may
    # differ by a motion the constraints leave free); atol far below the 1 cm noise
    rr, sr, drr, osr = dense.split(ref.x)
    np.testing.assert_allclose(Y - sol.residuals, toa_model(rr, sr, drr, osr), atol=atol)
    np.testing.assert_allclose(sol.cost, ref.cost, rtol=1e-5)


@pytest.mark.parametrize("seed", range(2))
def test_fixed_heights_match_dense(seed, solver):
    """Known heights (z columns fixed), both offsets: same minimum and covariance as dense."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, dr, os_ = _network(seed)
    I, J, d = 6, 8, 3
    Y = toa_model(r, s, dr, os_) + rng.normal(0, NOISE, (I, J))
    fr = np.zeros((I, d), bool)
    fr[:, 2] = True
    fs = np.zeros((J, d), bool)
    fs[:, 2] = True
    r0 = r + rng.normal(0, 0.05, r.shape)
    s0 = s + rng.normal(0, 0.05, s.shape)
    r0[:, 2], s0[:, 2] = r[:, 2], s[:, 2]
    sol = fit(Y, r0, s0, offsets="both", fixed_receivers=fr, fixed_sources=fs)
    assert sol.solver == ("trf-constrained" if solver == "auto" else "schur-lm-constrained") and sol.converged
    np.testing.assert_array_equal(sol.receivers[:, 2], r[:, 2])  # heights stay exact
    np.testing.assert_array_equal(sol.sources[:, 2], s[:, 2])
    dense = _Dense(Y, r0, s0, fr, fs, np.eye(I), np.eye(J), np.zeros(I), np.zeros(J))
    ref = _dense_solution(dense, dense.x0(np.zeros(I), np.zeros(J)))
    _assert_same_fit(sol, dense, ref, Y)
    # covariance: gauge-free in both (horizontal rigid motion + common shift removed); the
    # in-frame reference is the dense pinv at the dense minimum moved to our frame: compare
    # rotation-invariant quantities (trace, determinant of the xy block) per node
    C, sigma2, rank = _dense_cov(dense, ref.x, int(np.isfinite(Y).sum()))
    n_free = dense.free.size + I + J
    assert rank == n_free - 4  # 3 horizontal motions + the offset shift are left
    np.testing.assert_allclose(sol.sigma**2, sigma2, rtol=1e-4)
    for k in range(I):
        Cd = _node_block(dense, C, "r", k)[:2, :2]
        Cs = sol.receiver_cov[k][:2, :2]
        np.testing.assert_allclose(np.trace(Cs), np.trace(Cd), rtol=2e-3)
        np.testing.assert_allclose(np.linalg.det(Cs), np.linalg.det(Cd), rtol=5e-3)
        assert np.all(sol.receiver_cov[k][2] == 0)


@pytest.mark.parametrize("seed", range(2))
def test_fixed_anchor_rows_match_dense(seed, solver):
    """Three known anchors (rows fixed, no gauge left), receiver offsets."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, dr, _ = _network(seed + 10, I=6, J=9)
    I, J, d = 6, 9, 3
    Y = toa_model(r, s, dr, None) + rng.normal(0, NOISE, (I, J))
    fr = np.zeros(I, bool)
    fr[:3] = True
    fs = np.zeros(J, bool)
    r0 = r + rng.normal(0, 0.05, r.shape)
    r0[:3] = r[:3]
    s0 = s + rng.normal(0, 0.05, s.shape)
    sol = fit(Y, r0, s0, offsets="receivers", fixed_receivers=fr)
    np.testing.assert_array_equal(sol.receivers[:3], r[:3])
    dense = _Dense(Y, r0, s0, np.repeat(fr[:, None], d, 1), np.repeat(fs[:, None], d, 1),
                   np.eye(I), None, np.zeros(I), None)
    ref = _dense_solution(dense, dense.x0(np.zeros(I), None))
    _assert_same_fit(sol, dense, ref, Y)
    rr, sr, _, _ = dense.split(ref.x)
    np.testing.assert_allclose(sol.receivers, rr, atol=1e-6)  # no gauge: same point
    np.testing.assert_allclose(sol.sources, sr, atol=1e-6)
    C, _, _ = _dense_cov(dense, ref.x, 0)
    for k in range(J):
        np.testing.assert_allclose(sol.source_cov[k], _node_block(dense, C, "s", k), rtol=2e-3,
                                   atol=1e-9)


@pytest.mark.parametrize("seed", range(2))
def test_common_receiver_offset_matches_dense(seed, solver):
    """All receivers share one offset; the rigid gauge stays (canonical gauge output)."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, _, _ = _network(seed + 20)
    I, J, d = 6, 8, 3
    Y = toa_model(r, s, np.full(I, -0.15), None) + rng.normal(0, NOISE, (I, J))
    r0 = r + rng.normal(0, 0.05, r.shape)
    s0 = s + rng.normal(0, 0.05, s.shape)
    sol = fit(Y, r0, s0, offsets="receivers", common_offsets="receivers")
    assert np.ptp(sol.receiver_offsets) == 0
    z = np.zeros((I, d), bool)
    dense = _Dense(Y, r0, s0, z, np.zeros((J, d), bool), np.ones((I, 1)), None, np.zeros(I), None)
    ref = _dense_solution(dense, dense.x0(np.zeros(I), None))
    _assert_same_fit(sol, dense, ref, Y)
    # 1.96 sigma of the common offset from the covariance contains the truth most of the
    # time; here only check it against the dense standard deviation
    C, _, _ = _dense_cov(dense, ref.x, 0)
    k = dense.free.size
    np.testing.assert_allclose(sol.receiver_offset_std, np.sqrt(C[k, k]), rtol=2e-3)


@pytest.mark.parametrize("seed", range(2))
def test_priors_with_given_noise_match_dense(seed, solver):
    """Gaussian priors on four receivers (std 2 cm) with the noise given: the weighted LS."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, _, _ = _network(seed + 30)
    I, J, d = 6, 8, 3
    Y = toa_model(r, s) + rng.normal(0, NOISE, (I, J))
    std = np.full(I, 0.02)
    mu = np.full((I, d), np.nan)
    mu[:4] = r[:4] + rng.normal(0, 0.02, (4, d))
    r0 = r + rng.normal(0, 0.05, r.shape)
    s0 = s + rng.normal(0, 0.05, s.shape)
    sol = fit(Y, r0, s0, receiver_prior=(mu, std), noise=NOISE)
    z = np.zeros((I, d), bool)
    dense = _Dense(Y, r0, s0, z, np.zeros((J, d), bool), None, None, None, None,
                   prior_idx=np.arange(4 * d), prior_mu=mu[:4].ravel(),
                   prior_w=np.full(4 * d, NOISE / 0.02))
    ref = _dense_solution(dense, dense.x0(None, None))
    rr, sr, _, _ = dense.split(ref.x)
    np.testing.assert_allclose(sol.receivers, rr, atol=1e-6)  # priors fix the frame
    np.testing.assert_allclose(sol.sources, sr, atol=1e-6)
    np.testing.assert_allclose(sol.cost, ref.cost, rtol=1e-5)


def test_priors_estimated_noise_converges_to_self_consistent_weight(solver):
    """Without ``noise`` the prior weight uses the fit's own sigma estimate (fixed point)."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, _, _ = _network(40, I=8, J=12)
    Y = toa_model(r, s) + rng.normal(0, NOISE, (8, 12))
    mu = np.full((8, 3), np.nan)
    mu[:4] = r[:4]
    sol = fit(Y, r + 0.03, s - 0.03, receiver_prior=(mu, np.full(8, 0.01)))
    # sigma from 96 ranges, ~50 dof: within a factor 1.6 of the truth (chi2 0.1% tails)
    assert 0.6 * NOISE < sol.sigma < 1.6 * NOISE
    np.testing.assert_allclose(sol.receivers[:4], r[:4], atol=0.05)


def test_fixed_source_offsets_and_huber_match_dense(solver):
    """Some source offsets fixed, both kinds, Huber loss with a given scale."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, dr, os_ = _network(50, I=6, J=9)
    I, J, d = 6, 9, 3
    Y = toa_model(r, s, dr, os_) + rng.normal(0, NOISE, (I, J))
    Y[1, 2] += 0.5  # one gross outlier
    fso = np.zeros(J, bool)
    fso[:2] = True
    os0 = np.where(fso, os_, 0.0)
    r0 = r + rng.normal(0, 0.05, r.shape)
    s0 = s + rng.normal(0, 0.05, s.shape)
    sol = fit(Y, r0, s0, offsets="both", source_offsets0=os0, fixed_source_offsets=fso,
                     loss="huber", f_scale=0.02)
    np.testing.assert_allclose(sol.source_offsets[:2], os_[:2], atol=0)  # held exactly
    z = np.zeros((I, d), bool)
    dense = _Dense(Y, r0, s0, z, np.zeros((J, d), bool), np.eye(I), np.eye(J)[:, 2:],
                   np.zeros(I), os0)
    ref = _dense_solution(dense, dense.x0(np.zeros(I), os0), loss="huber", f_scale=0.02)
    # the Huber cost is flat near its minimum: 1e-5 m (a thousandth of the noise) apart
    _assert_same_fit(sol, dense, ref, Y, atol=1e-5)


def test_2d_fixed_row_and_offset_basis(solver):
    """2-D, one fixed receiver, receiver offsets with a fixed mean (zero-sum deviations)."""
    fit = partial(refine_toa, solver=solver)
    rng, r, s, _, _ = _network(60, I=5, J=8, d=2)
    I, J, d = 5, 8, 2
    dr = rng.normal(0, 0.1, I)
    dr -= dr.mean() - 0.2
    Y = toa_model(r, s, dr) + rng.normal(0, NOISE, (I, J))
    B = np.vstack([np.eye(I - 1), -np.ones((1, I - 1))])
    fr = np.zeros(I, bool)
    fr[0] = True
    r0 = r.copy()
    r0[1:] += rng.normal(0, 0.05, (I - 1, d))
    sol = fit(Y, r0, s + 0.03, offsets="receivers", receiver_offsets0=np.full(I, 0.2),
                     receiver_offset_basis=B, fixed_receivers=fr)
    np.testing.assert_allclose(sol.receiver_offsets.mean(), 0.2, atol=1e-12)
    np.testing.assert_array_equal(sol.receivers[0], r[0])
    dense = _Dense(Y, r0, s + 0.03, np.repeat(fr[:, None], d, 1), np.zeros((J, d), bool), B, None,
                   np.full(I, 0.2), None)
    ref = _dense_solution(dense, dense.x0(np.full(I, 0.2), None))
    _assert_same_fit(sol, dense, ref, Y)


def test_unconstrained_call_unchanged():
    """No constraint keyword: the gauge-free Schur path, as before."""
    rng, r, s, _, _ = _network(70)
    Y = toa_model(r, s) + rng.normal(0, NOISE, (6, 8))
    sol = refine_toa(Y, r + 0.02, s - 0.02)
    assert sol.solver == "schur-lm"


def test_constraint_errors():
    rng, r, s, _, _ = _network(80)
    Y = toa_model(r, s)
    with pytest.raises(InputError):
        refine_toa(Y, r, s, fixed_receivers=np.zeros((6, 2), bool))
    with pytest.raises(InputError):
        refine_toa(Y, r, s, common_offsets="receivers")  # offsets not estimated
    with pytest.raises(InputError):
        refine_toa(Y, r, s, receiver_prior=(r, np.zeros(6)))
    Y2 = Y.copy()
    Y2[0, 2:] = np.nan  # receiver 0 keeps 2 ranges for 3 free coordinates
    with pytest.raises(DegenerateGeometryError):
        refine_toa(Y2, r, s, fixed_sources=np.arange(8) < 3)
    # fixed receiver 0 with 2 ranges: the rest of the network keeps 6 - 2 = 4 free motions
    # relative to it, one more than the 3 rotations about it: not identifiable
    fr = np.zeros(6, bool)
    fr[0] = True
    with pytest.raises(DegenerateGeometryError):
        refine_toa(Y2 + 1e-3 * rng.normal(size=Y.shape), r, s, fixed_receivers=fr)
    Y3 = Y.copy()
    Y3[0, 3:] = np.nan  # 3 ranges fix the translation: only the rotations about it remain
    sol = refine_toa(Y3 + 1e-3 * rng.normal(size=Y.shape), r, s, fixed_receivers=fr)
    np.testing.assert_array_equal(sol.receivers[0], r[0])
    assert np.isfinite(sol.receiver_cov).all()


@pytest.mark.parametrize("seed", range(3))
def test_covariance_subset_equals_full_blocks(seed, solver):
    """A covariance request on the constrained path computes exactly the requested blocks.

    Same fit, same sparse factorization: the requested blocks must equal the full
    computation's to round-off and every block not asked for is NaN (as on the
    unconstrained path of toa/engine/covariance.py).
    """
    fit = partial(refine_toa, solver=solver)
    rng, r, s, dr, os_ = _network(seed + 30, I=7, J=9)
    I, J, d = 7, 9, 3
    Y = toa_model(r, s, dr, os_) + rng.normal(0, NOISE, (I, J))
    Y[rng.random((I, J)) < 0.1] = np.nan
    fr = np.zeros((I, d), bool)
    fr[:, 2] = True
    r0 = r + rng.normal(0, 0.05, r.shape)
    s0 = s + rng.normal(0, 0.05, s.shape)
    r0[:, 2] = r[:, 2]
    kw = dict(offsets="both", fixed_receivers=fr)
    full = fit(Y, r0, s0, covariance="all", **kw)
    ri, si = np.array([0, 3, 6]), np.array([1, 8])
    for spec, want_r, want_s in (("receivers", np.arange(I), []), ("sources", [], np.arange(J)),
                                 ({"receivers": ri, "sources": si}, ri, si), ((None, si), [], si)):
        sub = fit(Y, r0, s0, covariance=spec, **kw)
        np.testing.assert_allclose(sub.receivers, full.receivers, atol=1e-12)
        mr = np.zeros(I, bool)
        mr[want_r] = True
        ms = np.zeros(J, bool)
        ms[want_s] = True
        np.testing.assert_allclose(sub.receiver_cov[mr], full.receiver_cov[mr], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(sub.source_cov[ms], full.source_cov[ms], rtol=1e-9, atol=1e-15)
        assert np.isnan(sub.receiver_cov[~mr]).all() and np.isnan(sub.source_cov[~ms]).all()
        if ms.any():
            np.testing.assert_allclose(sub.source_offset_std[ms], full.source_offset_std[ms], rtol=1e-9)
    none = fit(Y, r0, s0, covariance="none", **kw)
    assert np.isnan(none.receiver_cov).all() and np.isnan(none.source_cov).all()
    with pytest.raises(InputError):
        fit(Y, r0, s0, covariance={"receivers": [I]}, **kw)
