"""Specification of the shared numerics: one home each (alignment, rotations, angle wrap,
plane fit, robust scale), checked against independent computations."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.linalg import orthogonal_procrustes

from selfcal.geometry import align, fit_plane, rotation_from_rotvec, skew, wrap_angle
from selfcal.robust import mad_std

FAST = settings(max_examples=50, deadline=None)


def _random_orthogonal(rng: np.random.Generator, d: int, proper: bool) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    if proper and np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    return Q


@FAST
@given(seed=st.integers(0, 10_000), d=st.sampled_from([2, 3]), reflection=st.booleans())
def test_batched_align_is_the_per_item_align(seed: int, d: int, reflection: bool) -> None:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(4, 7, d))
    Y = rng.normal(size=(4, 7, d))
    batch = align(X, Y, reflection=reflection, scale=True)
    for b in range(4):
        one = align(X[b], Y[b], reflection=reflection, scale=True)
        np.testing.assert_allclose(batch.rotation[b], one.rotation, atol=1e-10)
        np.testing.assert_allclose(batch.translation[b], one.translation, atol=1e-10)
        np.testing.assert_allclose(batch.scale[b], one.scale, atol=1e-10)
    np.testing.assert_allclose(batch.apply(X)[2], align(X[2], Y[2], reflection=reflection, scale=True).apply(X[2]),
                               atol=1e-10)


@FAST
@given(seed=st.integers(0, 10_000), d=st.sampled_from([2, 3]))
def test_align_rotation_is_scipy_orthogonal_procrustes(seed: int, d: int) -> None:
    # independent computation: scipy's orthogonal Procrustes on the centred points
    rng = np.random.default_rng(seed)
    X, Y = rng.normal(size=(9, d)), rng.normal(size=(9, d))
    Xc, Yc = X - X.mean(0), Y - Y.mean(0)
    Q, _ = orthogonal_procrustes(Xc, Yc)  # argmin |Xc Q - Yc|, so R = Q^T
    np.testing.assert_allclose(align(X, Y, reflection=True).rotation, Q.T, atol=1e-10)


@FAST
@given(seed=st.integers(0, 10_000), d=st.sampled_from([2, 3]), proper=st.booleans())
def test_align_recovers_a_rigid_motion(seed: int, d: int, proper: bool) -> None:
    rng = np.random.default_rng(seed)
    R = _random_orthogonal(rng, d, proper)
    X = rng.normal(size=(6, d))
    Y = X @ R.T + rng.normal(size=d)
    a = align(X, Y, reflection=not proper)
    np.testing.assert_allclose(a.apply(X), Y, atol=1e-9)
    assert np.linalg.det(a.rotation) == pytest.approx(np.linalg.det(R))


@FAST
@given(v=arrays(np.float64, (5, 3), elements=st.floats(-4, 4)))
def test_rotation_from_rotvec_is_rodrigues(v: np.ndarray) -> None:
    # independent computation: the closed form exp([v]x) = I + sin t K + (1 - cos t) K^2, K = [v/t]x
    R = rotation_from_rotvec(v)
    for k in range(5):
        t = np.linalg.norm(v[k])
        if t < 1e-6:
            expect = np.eye(3) + skew(v[k])
        else:
            K = skew(v[k] / t)
            expect = np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
        np.testing.assert_allclose(R[k], expect, atol=1e-10)
    assert rotation_from_rotvec(v[0]).shape == (3, 3)


@FAST
@given(a=arrays(np.float64, 20, elements=st.floats(-1e3, 1e3)))
def test_wrap_angle_is_in_range_and_congruent(a: np.ndarray) -> None:
    w = wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.exp(1j * w), np.exp(1j * a), atol=1e-9)


@FAST
@given(seed=st.integers(0, 10_000), thickness=st.floats(0.0, 0.1))
def test_fit_plane_finds_the_thin_axis(seed: int, thickness: float) -> None:
    rng = np.random.default_rng(seed)
    R = _random_orthogonal(rng, 3, True)
    P = (rng.uniform(-1, 1, (30, 3)) * [3.0, 2.0, thickness]) @ R.T + [1.0, 2.0, 3.0]
    fit = fit_plane(P)
    np.testing.assert_allclose(fit.centroid, P.mean(0), atol=1e-12)
    # the normal is the third axis of R up to sign: the thin extent (<= 0.1) is far below the others (~1)
    assert abs(fit.normal @ R[:, 2]) > 0.99
    rms = np.sqrt(np.mean(((P - fit.centroid) @ fit.normal) ** 2))
    assert rms == pytest.approx(fit.singular_values[-1] / np.sqrt(30), rel=1e-9)


@FAST
@given(seed=st.integers(0, 10_000))
def test_mad_std_against_an_independent_computation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = rng.standard_t(3, size=(6, 11))
    x[rng.random(x.shape) < 0.1] = np.nan
    c = 1.0 / 0.6744897501960817  # 1 / Phi^-1(3/4)
    med = np.nanmedian(x, axis=1, keepdims=True)
    np.testing.assert_allclose(mad_std(x, axis=1), c * np.nanmedian(np.abs(x - med), axis=1))
    np.testing.assert_allclose(mad_std(x, axis=1, keepdims=True), c * np.nanmedian(np.abs(x - med), axis=1, keepdims=True))
    assert mad_std(x, centre=False) == pytest.approx(c * np.nanmedian(np.abs(x)))


def test_mad_std_is_consistent_for_gaussian_noise() -> None:
    # sd of the MAD estimator ~ 1.1 sigma / sqrt(n) (asymptotic efficiency 37 %): 5 sd at n = 1e5
    x = np.random.default_rng(1).normal(0.0, 2.0, 100_000)
    assert abs(mad_std(x) - 2.0) < 5 * 1.17 * 2.0 / np.sqrt(x.size)


@pytest.mark.parametrize("loss", ["linear", "huber", "soft_l1", "cauchy"])
def test_loss_table_is_a_consistent_robust_loss(loss: str) -> None:
    # rho' is the derivative of rho (central differences), every loss is the linear one at
    # z -> 0 (rho(0) = 0, rho'(0) = 1), and the robust ones grow sub-linearly (rho' <= 1, falling)
    from selfcal.robust import loss_rho

    z = np.linspace(0.01, 25.0, 400)
    h = 1e-6
    rho, drho = loss_rho(z, loss)
    fd = (loss_rho(z + h, loss)[0] - loss_rho(z - h, loss)[0]) / (2 * h)
    np.testing.assert_allclose(drho, fd, rtol=1e-6, atol=1e-8)
    r0, d0 = loss_rho(np.zeros(1), loss)
    assert r0[0] == 0.0 and d0[0] == 1.0
    assert np.all(drho <= 1.0 + 1e-12) and np.all(np.diff(drho) <= 1e-12)


def test_cauchy_cost_moments_match_a_monte_carlo() -> None:
    # the known-heights fit accepts a Cauchy cost below m mean + 3.09 sqrt(m) sd; mean and sd
    # come from quadrature: a 4e5-draw sample mean / sd must agree within 5 standard errors
    from selfcal.acoustics.calibrate import _cauchy_cost, _cauchy_cost_moments

    z = np.random.default_rng(7).normal(size=400_000)
    terms = np.log1p((z / 2.385) ** 2)
    mean, sd = _cauchy_cost_moments()
    se = terms.std() / np.sqrt(z.size)
    assert abs(terms.mean() - mean) < 5 * se
    m4 = np.mean((terms - terms.mean()) ** 4)  # se of a sample sd: sqrt((m4 - sd^4) / n) / (2 sd)
    assert abs(terms.std() - sd) < 5 * np.sqrt((m4 - sd**4) / z.size) / (2 * sd)
    assert _cauchy_cost(z) == pytest.approx(terms.sum())


@pytest.mark.parametrize("kind", ["gauss", "t3", "t5", "laplace"])
@pytest.mark.parametrize("seed", range(4))
def test_rejection_factor_is_the_hard_rejection_sandwich(kind: str, seed: int) -> None:
    # rejection_factor against the analytic P^2 / (P - 2 c f(c))^2 of the distribution (scipy's
    # density at the cut, not an estimate), cut at 4 of the sample's robust standard deviations.
    # 20000 draws: the kernel estimate's spread and its normal-reference smoothing bias are a
    # few per cent of the excess (t3 analytic 1.12); 0.02 absolute is ~3 of them, and far below
    # the excess 0.04-0.12 of the heavy tails it must find (Gaussian: analytic 1.002).
    from scipy import stats

    from selfcal.robust import rejection_factor

    dist = {"gauss": stats.norm(), "t3": stats.t(3), "t5": stats.t(5), "laplace": stats.laplace()}[kind]
    x = dist.rvs(size=20000, random_state=np.random.default_rng(seed))
    c = 4.0 * float(mad_std(x))
    p = 1.0 - 2.0 * float(dist.sf(c))
    want = p**2 / (p - 2.0 * c * float(dist.pdf(c))) ** 2
    assert abs(rejection_factor(x / c) - want) < 0.02
    assert rejection_factor(x / c) >= 1.0
