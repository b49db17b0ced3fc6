"""The smoother's range-noise update and its model average (issue 31), against independent
linear-Gaussian computations."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.slac import ranging


def _linear_problem(seed: int, D: int = 20, K: int = 100, sigma: float = 0.5):  # type: ignore[no-untyped-def]
    """r = H x + e with x ~ N(0, I), e ~ N(0, sigma^2): the posterior mode's residuals and the
    posterior variance h P h^T of each prediction (mean leverage ~ D / K = 0.2)."""
    g = np.random.default_rng(seed)
    H = g.normal(size=(K, D))
    x = g.normal(size=D)
    r = H @ x + g.normal(0, sigma, K)
    P = np.linalg.inv(np.eye(D) + H.T @ H / sigma**2)
    xh = P @ H.T @ r / sigma**2
    return r - H @ xh, np.einsum("ki,ij,kj->k", H, P, H)


def test_noise_from_residuals_is_unbiased_where_the_naive_median_is_not() -> None:
    """A residual at the posterior mode has variance ``sigma^2 - h P h^T`` (the fit takes up its
    leverage). Over 200 linear problems with 20 % mean leverage the estimate's mean is within
    2.5 % of the true sigma (measured 1.019: the median estimator's relative std is 0.09 per
    problem of 100 residuals, 0.0065 for the mean of 200, and it has a small-sample bias of
    its own), while the median of the residuals alone is low by ~sqrt(1 - 0.2) (measured 0.911)."""
    sigma = 0.5
    est, naive = [], []
    for seed in range(200):
        e, hph = _linear_problem(seed, sigma=sigma)
        est.append(ranging._noise_from_residuals(e, hph, sigma))
        naive.append(ranging._noise_from_innovations(e, np.zeros_like(e)))
    assert np.mean(est) / sigma == pytest.approx(1.0, abs=0.025), np.mean(est)
    assert np.mean(naive) / sigma < 0.95, np.mean(naive)


@pytest.mark.parametrize("seed", range(5))
def test_model_average_is_the_mixture_moments(seed: int) -> None:
    """``_mix``: the mean and covariance of the Gaussian mixture (law of total variance),
    checked against moments of draws from the mixture."""
    g = np.random.default_rng(seed)
    N, D = 3, 4
    sols = []
    for w in (0.3, 0.7):
        A = g.normal(size=(N, D, D))
        sols.append((w, ranging._Smoothed(ms=g.normal(size=(N, D)), Ps=A @ A.transpose(0, 2, 1) * 0.1,
                                          weights=np.ones(5), sigma=1.0, var=np.ones((N, 2)), lam=np.ones(2),
                                          iterations=3, converged=True)))
    m = ranging._mix(sols)
    n = 200_000
    pick = g.random(n) < 0.3
    for i in range(N):
        draws = np.where(pick[:, None], g.multivariate_normal(sols[0][1].ms[i], sols[0][1].Ps[i], n),
                         g.multivariate_normal(sols[1][1].ms[i], sols[1][1].Ps[i], n))
        assert np.allclose(m.ms[i], draws.mean(axis=0), atol=0.02)
        assert np.allclose(m.Ps[i], np.cov(draws.T), atol=0.03)
    assert m.iterations == 6 and m.converged
