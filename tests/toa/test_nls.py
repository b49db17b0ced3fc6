"""Spec of the sparse TOA NLS engine (toa/engine/nls.py) and the gauge-free CRLB (toa/engine/crlb.py)."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.errors import DegenerateGeometryError, InputError
from selfcal.geometry import align
from selfcal.metrics import aligned_rmse
from selfcal.toa import refine_toa, toa_crlb, toa_jacobian, toa_model, toa_residuals
from selfcal.toa.engine.nls import _pack, gauge_basis

MODES = ["none", "receivers", "sources", "both"]


def network(rng: np.random.Generator, I: int, J: int, d: int, offsets: str = "none"):
    """Receivers in a 10 m box, sources around them, offsets of a few metres (truth)."""
    r = rng.uniform(-5, 5, (I, d))
    s = rng.uniform(-7, 7, (J, d))
    dr = rng.normal(0, 1, I) if offsets in ("receivers", "both") else None
    o = rng.normal(0, 1, J) if offsets in ("sources", "both") else None
    return r, s, dr, o


def dense_pinv_blocks(theta, Y, d, offsets, I, J, sigma=1.0):
    """Independent reference: per-point blocks of sigma^2 pinv(J^T J) from the dense Jacobian."""
    Jm = toa_jacobian(theta, Y, d, offsets).toarray()
    C = np.linalg.pinv(Jm.T @ Jm, rcond=1e-12) * sigma**2
    Cr = np.array([C[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(I)])
    o = I * d
    Cs = np.array([C[o + j * d:o + (j + 1) * d, o + j * d:o + (j + 1) * d] for j in range(J)])
    return Cr, Cs, C


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("offsets", MODES)
def test_analytic_jacobian_matches_finite_differences(rng, d, offsets):
    I, J = 5, 7
    r, s, dr, o = network(rng, I, J, d, offsets)
    Y = toa_model(r, s, dr, o) + rng.normal(0, 0.1, (I, J))
    Y[1, 2] = Y[3, 0] = np.nan  # missing entries have no rows
    theta = _pack(r, s, dr, o)
    Ja = toa_jacobian(theta, Y, d, offsets).toarray()
    h = 1e-6
    Jn = np.column_stack([
        (toa_residuals(theta + h * e, Y, d, offsets) - toa_residuals(theta - h * e, Y, d, offsets)) / (2 * h)
        for e in np.eye(theta.size)
    ])
    assert Ja.shape == (I * J - 2, theta.size)
    np.testing.assert_allclose(Ja, Jn, atol=1e-7)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("offsets", MODES)
@pytest.mark.parametrize("solver", ["trf", "schur"])
def test_noise_free_network_recovered_from_perturbed_start(rng, d, offsets, solver):
    I, J = 8, 11
    r, s, dr, o = network(rng, I, J, d, offsets)
    Y = toa_model(r, s, dr, o)
    sol = refine_toa(
        Y, r + rng.normal(0, 0.2, r.shape), s + rng.normal(0, 0.2, s.shape), offsets=offsets,
        receiver_offsets0=None if dr is None else dr + 0.1, source_offsets0=None if o is None else o - 0.1,
        solver=solver,
    )
    err = aligned_rmse(sol.receivers, r, sol.sources, s)
    assert sol.converged
    assert err.rmse_receivers < 1e-6 and err.rmse_sources < 1e-6
    assert sol.residual_rms < 1e-8
    if offsets == "both":
        # canonical gauge of the offsets: first source offset is 0, the shift sits in d_i
        assert sol.source_offsets[0] == 0.0
        np.testing.assert_allclose(sol.receiver_offsets, dr + o[0], atol=1e-6)
        np.testing.assert_allclose(sol.source_offsets, o - o[0], atol=1e-6)
    elif offsets == "receivers":
        np.testing.assert_allclose(sol.receiver_offsets, dr, atol=1e-6)
    elif offsets == "sources":
        np.testing.assert_allclose(sol.source_offsets, o, atol=1e-6)


def test_canonical_gauge_of_the_output(rng):
    r, s, _, _ = network(rng, 6, 9, 3)
    sol = refine_toa(toa_model(r, s), r + 0.05, s - 0.05)
    np.testing.assert_allclose(sol.receivers.mean(axis=0), 0.0, atol=1e-9)
    cov = sol.receivers.T @ sol.receivers
    np.testing.assert_allclose(cov - np.diag(np.diag(cov)), 0.0, atol=1e-8)  # principal axes


@pytest.mark.parametrize("offsets", MODES)
@pytest.mark.parametrize("shape", [(7, 10), (11, 6)])
def test_covariance_is_the_gauge_free_pseudo_inverse(rng, offsets, shape):
    """003 eq. 17 with the gauge removed == dense pinv of J^T J (independent computation)."""
    I, J = shape
    d = 3
    r, s, dr, o = network(rng, I, J, d, offsets)
    Y = toa_model(r, s, dr, o) + rng.normal(0, 0.01, (I, J))
    Y[0, 1] = np.nan
    sol = refine_toa(Y, r, s, offsets=offsets, receiver_offsets0=dr, source_offsets0=o)
    theta = _pack(sol.receivers, sol.sources, sol.receiver_offsets, sol.source_offsets)
    Cr, Cs, C = dense_pinv_blocks(theta, Y, d, offsets, I, J, sol.sigma)
    np.testing.assert_allclose(sol.receiver_cov, Cr, rtol=1e-5, atol=1e-5 * np.abs(Cr).max())
    np.testing.assert_allclose(sol.source_cov, Cs, rtol=1e-5, atol=1e-5 * np.abs(Cs).max())
    if offsets in ("receivers", "both"):
        k = (I + J) * d
        np.testing.assert_allclose(sol.receiver_offset_std, np.sqrt(np.diag(C)[k:k + I]), rtol=1e-4)


def test_sigma_uses_the_right_degrees_of_freedom(rng):
    """E[RSS] = sigma^2 (m - n + g): the estimate is unbiased over many noise draws."""
    I, J, d, sig = 6, 8, 2, 0.05
    r, s, _, _ = network(rng, I, J, d)
    est = []
    for _ in range(40):
        Y = toa_model(r, s) + rng.normal(0, sig, (I, J))
        est.append(refine_toa(Y, r, s).sigma ** 2)
    # m - n + g = 48 - 28 + 3 = 23 dof; the mean of 40 draws has ~5% relative std
    assert abs(np.mean(est) / sig**2 - 1) < 0.2


def _min_norm_errors(est_r, est_s, r, s):
    """Errors in the minimum-norm gauge: rigid alignment fitted on all points."""
    al = align(np.vstack([est_r, est_s]), np.vstack([r, s]), reflection=True)
    return al.apply(est_r) - r, al.apply(est_s) - s


def _monte_carlo(rng, runs):
    I, J, d, sig = 8, 10, 2, 0.05
    r, s, _, _ = network(rng, I, J, d)
    er, es, pred = [], [], []
    for _ in range(runs):
        Y = toa_model(r, s) + rng.normal(0, sig, (I, J))
        sol = refine_toa(Y, r, s)
        a, b = _min_norm_errors(sol.receivers, sol.sources, r, s)
        er.append(a)
        es.append(b)
        pred.append(np.trace(sol.receiver_cov, axis1=1, axis2=2).sum() + np.trace(sol.source_cov, axis1=1, axis2=2).sum())
    er, es = np.array(er), np.array(es)
    mc = (er**2).sum(axis=(1, 2)).mean() + (es**2).sum(axis=(1, 2)).mean()
    crlb = toa_crlb(r, s, sig)
    bound = crlb.receiver_trace.sum() + crlb.source_trace.sum()
    return mc, float(np.mean(pred)), bound


def test_covariance_matches_monte_carlo_scatter(rng):
    mc, pred, bound = _monte_carlo(rng, 30)
    assert abs(pred / mc - 1) < 0.2
    assert abs(bound / mc - 1) < 0.2


@pytest.mark.slow
def test_covariance_matches_monte_carlo_scatter_200_runs(rng):
    mc, pred, bound = _monte_carlo(rng, 200)
    assert abs(pred / mc - 1) < 0.2
    assert abs(bound / mc - 1) < 0.2


@pytest.mark.parametrize("offsets", MODES)
def test_crlb_equals_dense_fisher_pseudo_inverse(rng, offsets):
    I, J, d, sig = 8, 12, 3, 0.02
    r, s, dr, o = network(rng, I, J, d, offsets)
    mask = rng.random((I, J)) > 0.1
    Y = np.where(mask, toa_model(r, s, dr, o), np.nan)
    crlb = toa_crlb(r, s, sig, offsets=offsets, mask=mask)
    Cr, Cs, _ = dense_pinv_blocks(_pack(r, s, dr, o), Y, d, offsets, I, J, sig)
    np.testing.assert_allclose(crlb.receiver_bounds, Cr, rtol=1e-6, atol=1e-9 * sig**2)
    np.testing.assert_allclose(crlb.source_bounds, Cs, rtol=1e-6, atol=1e-9 * sig**2)
    assert crlb.rmse_receivers == pytest.approx(np.sqrt(np.trace(Cr, axis1=1, axis2=2).mean()))


def test_crlb_scales_with_sigma_and_shrinks_with_more_sources(rng):
    r, s, _, _ = network(rng, 6, 20, 3)
    a = toa_crlb(r, s[:10], 0.01)
    b = toa_crlb(r, s[:10], 0.02)
    c = toa_crlb(r, s, 0.01)
    assert b.rmse_receivers == pytest.approx(2 * a.rmse_receivers)
    assert c.rmse_receivers < a.rmse_receivers


def test_gauge_basis_spans_the_null_space(rng):
    for offsets in MODES:
        r, s, dr, o = network(rng, 7, 9, 3, offsets)
        theta = _pack(r, s, dr, o)
        Y = toa_model(r, s, dr, o)
        Jm = toa_jacobian(theta, Y, 3, offsets).toarray()
        Q = gauge_basis(r, s, offsets)
        assert np.abs(Jm @ Q).max() < 1e-12
        # and nothing else: the null space dimension is exactly the number of gauge freedoms
        assert Jm.shape[1] - np.linalg.matrix_rank(Jm) == Q.shape[1]


def test_missing_entries_are_skipped(rng):
    I, J, d = 9, 12, 3
    r, s, _, _ = network(rng, I, J, d)
    Y = toa_model(r, s)
    Y[rng.random((I, J)) < 0.25] = np.nan
    sol = refine_toa(Y, r + rng.normal(0, 0.1, r.shape), s + rng.normal(0, 0.1, s.shape))
    err = aligned_rmse(sol.receivers, r, sol.sources, s)
    assert err.rmse_receivers < 1e-6 and err.rmse_sources < 1e-6
    assert np.isnan(sol.residuals[np.isnan(Y)]).all()
    assert np.isfinite(sol.residuals[np.isfinite(Y)]).all()


@pytest.mark.parametrize("loss", ["huber", "cauchy", "soft_l1"])
def test_robust_loss_rejects_outliers(loss):
    """8% late arrivals of 1-3 m: every robust loss beats least squares by far; the
    redescending Cauchy loss reaches the outlier-free accuracy (CRLB) and noise level."""
    rng = np.random.default_rng(12345)
    I, J, d, sig = 10, 20, 3, 0.01
    r, s, _, _ = network(rng, I, J, d)
    Y = toa_model(r, s) + rng.normal(0, sig, (I, J))
    bad = rng.random((I, J)) < 0.08
    Y[bad] += rng.uniform(1.0, 3.0, bad.sum())  # e.g. reflections: late arrivals
    start = (r + rng.normal(0, 0.05, r.shape), s + rng.normal(0, 0.05, s.shape))
    lin_sol = refine_toa(Y, *start)
    lin = aligned_rmse(lin_sol.receivers, r, lin_sol.sources, s)
    sol = refine_toa(Y, *start, loss=loss)
    rob = aligned_rmse(sol.receivers, r, sol.sources, s)
    assert rob.rmse_receivers < lin.rmse_receivers / 5
    assert rob.rmse_sources < lin.rmse_sources / 5
    if loss == "cauchy":
        bound = toa_crlb(r, s, sig)
        assert rob.rmse_receivers < 2 * bound.rmse_receivers
        assert rob.rmse_sources < 2 * bound.rmse_sources
        assert sol.sigma == pytest.approx(sig, rel=0.5)  # robust noise estimate ignores outliers


def test_schur_solver_agrees_with_trf(rng):
    I, J, d = 10, 14, 3
    r, s, _, _ = network(rng, I, J, d)
    Y = toa_model(r, s) + rng.normal(0, 0.02, (I, J))
    a = refine_toa(Y, r, s, solver="trf")
    b = refine_toa(Y, r, s, solver="schur")
    assert b.cost == pytest.approx(a.cost, rel=1e-6)
    np.testing.assert_allclose(a.receivers, b.receivers, atol=1e-6)
    np.testing.assert_allclose(a.receiver_cov, b.receiver_cov, rtol=1e-4, atol=1e-10)


def test_collinear_configuration_is_degenerate():
    r = np.c_[np.arange(5.0), np.zeros(5)]
    s = np.c_[np.arange(6.0) + 0.5, np.zeros(6)]
    with pytest.raises(DegenerateGeometryError):
        refine_toa(toa_model(r, s), r, s)


def test_bad_arguments_raise_input_error(rng):
    r, s, _, _ = network(rng, 5, 6, 2)
    Y = toa_model(r, s)
    with pytest.raises(InputError):
        refine_toa(Y, r, s, offsets="all")
    with pytest.raises(InputError):
        refine_toa(Y, r, s, loss="l2")
    with pytest.raises(InputError):
        refine_toa(Y, r[:4], s)
    with pytest.raises(InputError):
        refine_toa(Y, r, np.c_[s, s[:, :1]])
    with pytest.raises(InputError):
        refine_toa(Y, r, s, offsets="receivers", receiver_offsets0=np.ones(3))


def test_offset_covariance_matches_monte_carlo_scatter(rng):
    """offsets='both' (004 model): position and offset scatter in the minimum-norm gauge
    (rigid alignment on all points, common offset shift projected out) vs eq. 17."""
    I, J, d, sig = 12, 20, 3, 0.01
    r, s, dr, o = network(rng, I, J, d, "both")
    pos, off, pred_pos, pred_off = [], [], [], []
    for _ in range(30):
        Y = toa_model(r, s, dr, o) + rng.normal(0, sig, (I, J))
        sol = refine_toa(Y, r, s, offsets="both", receiver_offsets0=dr, source_offsets0=o)
        a, b = _min_norm_errors(sol.receivers, sol.sources, r, s)
        pos.append((a**2).sum() + (b**2).sum())
        ed, eo = sol.receiver_offsets - dr, sol.source_offsets - o
        c = (ed.sum() - eo.sum()) / (I + J)  # the common shift d + c, o - c is gauge
        off.append(((ed - c) ** 2).sum() + ((eo + c) ** 2).sum())
        pred_pos.append(np.trace(sol.receiver_cov, axis1=1, axis2=2).sum()
                        + np.trace(sol.source_cov, axis1=1, axis2=2).sum())
        pred_off.append((sol.receiver_offset_std**2).sum() + (sol.source_offset_std**2).sum())
    assert abs(np.mean(pred_pos) / np.mean(pos) - 1) < 0.2
    assert abs(np.mean(pred_off) / np.mean(off) - 1) < 0.2


@pytest.mark.parametrize("axis", [0, 1])
def test_node_with_too_few_ranges_is_named(rng, axis):
    r, s, _, _ = network(rng, 8, 10, 3)
    Y = toa_model(r, s)
    if axis == 0:
        Y[2, 1:] = np.nan  # receiver 2 keeps a single range
    else:
        Y[1:, 4] = np.nan  # source 4 keeps a single range
    with pytest.raises(DegenerateGeometryError, match="receiver 2" if axis == 0 else "source 4"):
        refine_toa(Y, r, s)
