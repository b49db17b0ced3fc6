"""The forced-model F test on heavy-tailed noise (:mod:`selfcal.toa.verdict.model_test`).

The offsets comparison (``offsets="none"`` against ``"both"``) refers F to
``F(k / c, dof / c_d)`` with the kurtosis estimated from the larger fit's residuals (Box &
Watson 1962, a two-moment match; the module docstring). Properties, each over many draws
of generic networks whose truth has no offsets (the forced model is right):

- the level holds on heavy tails: rejections at ``alpha = 0.01`` (a level 200 draws can
  measure; the issue's 1e-3 cannot be resolved without ~1e4 draws) stay within twice the
  level. Why twice: the correction matches two moments and estimates the kurtosis from the
  sample, which under-states Student t3 (infinite kurtosis: the sample value is bounded by
  the number of entries); measured on these draws (``benchmarks/model_test_tails.py``) the
  Gaussian F test rejects t3 at 8.5 % and Laplace at 1.5 %, the corrected one at 1.5 % and
  0 %. The assertion allows ``binom.ppf(0.999, n, 2 alpha)`` rejections: a test whose true
  rate is 2 alpha fails it with probability 1e-3;
- Gaussian draws keep the exact F test: the factor ``c`` is near 1, and the corrected test
  never rejects where the Gaussian F test does not (``c, c_d >= 1``: the kurtosis clipped
  at 0), with the same decisions at the test's own level;
- power kept: true receiver offsets under Laplace noise are still caught and named.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import binom
from scipy.stats import f as fdist

from selfcal.toa import toa_model
from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.verdict.model_test import MODEL_ALPHA, forced_model_test

NOISE = 0.01  # m: 1 cm noise in a 10 m box, as the families


def _noise(g: np.random.Generator, shape: tuple[int, int], law: str) -> np.ndarray:
    if law == "gauss":
        return g.normal(0, NOISE, shape)
    if law == "laplace":
        return g.laplace(0, NOISE / np.sqrt(2), shape)
    nu = int(law[1:])
    return NOISE * np.sqrt((nu - 2) / nu) * g.standard_t(nu, shape)


def _draw(I: int, J: int, dim: int, law: str, seed: int, delays: np.ndarray | None = None):
    """A generic network, the forced fit (offsets none, refined from the truth), the test."""
    g = np.random.default_rng([27, 92, I, dim, len(law), seed])
    R, S = g.uniform(0, 10, (I, dim)), g.uniform(0, 10, (J, dim))
    Y = toa_model(R, S, None if delays is None else delays(g, I)) + _noise(g, (I, J), law)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = refine_toa(Y, R, S, offsets="none", covariance=False)
        return forced_model_test(Y, fit.receivers, fit.sources, offsets="none", test_dim=False)


def _gaussian_p(t) -> float:
    """The uncorrected F test's p-value of the same statistic."""
    return float(fdist.sf(t.statistic, t.dof, t.dof_noise))


def _level(I: int, J: int, dim: int, law: str, draws: int, alpha: float = 0.01) -> None:
    p = np.array([_draw(I, J, dim, law, s).p_value for s in range(draws)])
    assert (p < alpha).sum() <= binom.ppf(0.999, draws, 2 * alpha), ((p < alpha).sum(), draws)


@pytest.mark.parametrize("shape,law", [((12, 40, 3), "t3"), ((10, 30, 2), "laplace"), ((10, 30, 2), "t5")])
def test_heavy_tailed_level_holds(shape, law):
    _level(*shape, law, draws=150)


@pytest.mark.slow
@pytest.mark.parametrize("shape,law", [((12, 40, 3), "t3"), ((12, 40, 3), "laplace"), ((10, 30, 2), "laplace"),
                                       ((10, 30, 2), "t5"), ((10, 30, 2), "t3")])
def test_heavy_tailed_level_holds_full(shape, law):
    _level(*shape, law, draws=600)


def test_gaussian_draws_keep_the_f_test():
    cs, same = [], 0
    for seed in range(60):
        for shape in ((10, 30, 2), (12, 40, 3)):
            t = _draw(*shape, "gauss", seed)
            p0 = _gaussian_p(t)
            cs.append(t.scale)
            assert t.scale >= 1.0 and t.kurtosis >= 0.0
            assert t.p_value >= p0 or p0 > 0.05  # never stricter in the tail (upper F quantiles fall with dof)
            same += (t.p_value < MODEL_ALPHA) == (p0 < MODEL_ALPHA)
    # the kurtosis estimate's Gaussian standard error (sqrt(24 n) / sum M_ii^2 ~ 0.6-0.75 here)
    # moves c by ~ 0.05 per unit: its median stays at 1 (half the estimates are clipped)
    assert np.median(cs) < 1.02
    assert same == len(cs)


def test_offsets_still_caught_under_laplace_noise():
    """Delays of 2-20 noise stds per receiver under Laplace noise: rejected, the receivers' offsets named."""
    for seed in range(20):
        t = _draw(10, 30, 2, "laplace", seed, delays=lambda g, I: g.uniform(0.02, 0.2, I))
        assert not t.passed and t.better == "offsets=receivers", (seed, t)


def test_kurtosis_estimate_undoes_the_fit():
    """The leverage-corrected estimate (``_excess_kurtosis``) against the errors' own sample kurtosis.

    A linear least-squares fit with p/n = 1/3 (as a 10 x 30 2-D network with both offsets)
    and uneven leverages; 10 entries held out enter as prediction residuals. Over 200 draws
    the estimate from the residuals is compared with the sample excess kurtosis of the
    (unobservable) errors themselves, the best a residual-based estimate can do (for Laplace
    noise it is itself biased low at n = 310: 2.75 against 3). Measured over 300 draws:
    2.50 from the residuals against 2.75 from the errors, where the plain sample kurtosis of
    the residuals reads 1.98; for Gaussian noise median 0 (half clipped), mean 0.19. The
    tolerances (0.4, 0.35) are a few standard errors of these means (per-draw sd 1.7 Laplace,
    0.4 Gaussian).
    """
    from selfcal.toa.verdict.model_test import _excess_kurtosis

    n, p, n_out = 300, 100, 10
    for law in ("laplace", "gauss"):
        est, own = [], []
        for seed in range(200):
            g = np.random.default_rng([27, 93, seed])
            X = g.normal(size=(n + n_out, p)) * g.uniform(0.2, 3.0, (n + n_out, 1))  # uneven leverages
            e = g.laplace(0, 1, n + n_out) if law == "laplace" else g.normal(0, 1, n + n_out)
            Xf = X[:n]
            G = np.linalg.inv(Xf.T @ Xf)
            res = e - X @ (G @ Xf.T @ e[:n])
            lev = np.einsum("ij,jk,ik->i", X, G, X)
            est.append(_excess_kurtosis(res, lev, np.arange(n + n_out) >= n))
            own.append(max(np.mean(e ** 4) / np.mean(e ** 2) ** 2 - 3.0, 0.0))
        if law == "laplace":
            assert abs(np.mean(est) - np.mean(own)) < 0.4, (np.mean(est), np.mean(own))
        else:
            assert np.median(est) < 0.1 and np.mean(est) < 0.35, (np.median(est), np.mean(est))
