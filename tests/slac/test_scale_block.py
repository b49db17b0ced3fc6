"""The smoother's per-beacon range-scale block (R1: ``r = s_b |p - b_b| + o_b``) and its
empirical-Bayes prior ``s ~ N(1, a^2 11^T + tau^2 I)`` (issue 31).

Measured (``benchmarks/slac_scale_block.py 8``, 150 s simulated CMU-style logs, mean position
RMSE over 8 seeds): exact scales 0.058 m with the empirical prior, 0.082 m with the fixed
``N(1, 0.1^2)`` prior, 0.055 m offset-only; one 6 % scale shared by all beacons 0.059 / 0.085 /
3.032 m; independent 2-9 % errors 0.078 / 0.078 / 2.825 m. The tests pin what must hold on
every seed: the evidence the prior maximises is the Gaussian marginal likelihood (independent
computation), the scales come out within their own error bars, exact scales cost no more than
the offset-only model by more than a small factor, and a real scale error is never shrunk away.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat
from scipy.stats import multivariate_normal

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import RangeModelConfig, solve_range_slac
from selfcal.slac.scale_prior import SCALE_PRIOR_FLOOR, scale_prior_eb
from tests.datasets.cmu_logs import cmu_log


def _solve(seed: int, range_scale: tuple[float, float], cfg: RangeModelConfig | None = None, **kw):  # type: ignore[no-untyped-def]
    m, tr = cmu_log(seed, duration=150.0, range_scale=range_scale, **kw)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve_range_slac(load_plaza(p), method="smoother", config=cfg)
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    return r, tr, float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.mark.parametrize("seed", range(12))
def test_evidence_is_the_gaussian_marginal(seed: int) -> None:
    """The hyper-parameters maximise log N(s_lik; 1, L^-1 + a^2 11^T + tau^2 I), the marginal
    likelihood written the textbook way (invertible data precision L), over a dense grid."""
    g = np.random.default_rng(seed)
    B = int(g.integers(3, 7))
    a_true, tau_true = g.choice([0.0, 0.05]), g.choice([0.0, 0.02])
    A = g.normal(size=(B, B))
    Vlik = (A @ A.T / B + np.eye(B)) * g.uniform(0.001, 0.004) ** 2  # data covariance of the scales
    s_true = 1 + a_true * g.normal() + tau_true * g.normal(size=B)
    s_lik = g.multivariate_normal(s_true, Vlik)
    # the posterior under the fixed N(1, 0.1^2 I) prior, as the smoother reports it
    P0 = np.eye(B) / 0.1**2
    V = np.linalg.inv(np.linalg.inv(Vlik) + P0)
    s_hat = V @ (np.linalg.solve(Vlik, s_lik) + P0 @ np.ones(B))
    S, (a, tau) = scale_prior_eb(s_hat, V, 0.1)
    assert np.allclose(S, a**2 * np.ones((B, B)) + tau**2 * np.eye(B))

    def ll(a: float, t: float) -> float:
        return float(multivariate_normal(np.ones(B), Vlik + a**2 * np.ones((B, B)) + t**2 * np.eye(B)).logpdf(s_lik))

    grid = np.exp(np.linspace(np.log(SCALE_PRIOR_FLOOR), 0.0, 61))
    best = max(ll(x, y) for x in grid for y in grid)
    assert ll(a, tau) >= best - 1e-6  # at least as good as the best grid point


@pytest.mark.parametrize("range_scale", [(0.02, 0.09), (0.0, 0.0), (0.06, 0.06)])
def test_scale_recovered_within_error_bar(range_scale: tuple[float, float]) -> None:
    z, err = [], []
    for seed in range(3):
        r, tr, e = _solve(seed, range_scale)
        assert np.array_equal(r.beacon_ids, tr.beacon_ids)
        heard = tr.heard
        # with the prior at its floor the error bar is the prior's (1e-4); the test allows
        # the floor on top of the posterior std so that an exact scale held at 1 passes
        z.append((r.scale[heard] - tr.scale[heard]) / np.hypot(r.scale_std[heard], SCALE_PRIOR_FLOOR))
        err.append(e)
        if range_scale[1] > 0:  # a real error of >= 2 % is never shrunk to the floor
            assert max(r.scale_prior_std) > 0.01, r.scale_prior_std
    z = np.concatenate(z)
    # 4 sigma: per-parameter false alarm 6e-5 for a consistent Gaussian posterior
    assert np.all(np.abs(z) < 4), z
    # the range noise is 0.15 m; with or without a scale error the smoother stays at the
    # decimetre level (measured means 0.08-0.13 m), far below the metres an unmodelled
    # 2-9 % scale costs
    assert np.mean(err) < 0.25, err


def _compare(seeds: range, range_scale: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    eb, fixed, off = [], [], []
    for s in seeds:
        eb.append(_solve(s, range_scale)[2])
        fixed.append(_solve(s, range_scale, RangeModelConfig(scale_prior="fixed"))[2])
        off.append(_solve(s, range_scale, RangeModelConfig(scale_prior="fixed", scale_std=1e-4))[2])
    return np.array(eb), np.array(fixed), np.array(off)


def _check_exact(eb: np.ndarray, fixed: np.ndarray, off: np.ndarray) -> None:
    # exact scales: the empirical prior shrinks them to 1, so it must beat the fixed prior
    # on average (measured 0.058 vs 0.082 m, 8 seeds) and stay near the offset-only model,
    # the right one here (measured 0.055 m); 1.3x leaves room for the seeds where one
    # common scale is kept at a type-II ML just above the floor (|z| of its mean > 1)
    assert eb.mean() < fixed.mean(), (eb, fixed)
    assert eb.mean() < 1.3 * off.mean(), (eb, off)


def test_exact_scales_cost_little() -> None:
    _check_exact(*_compare(range(4), (0.0, 0.0)))


@pytest.mark.slow
def test_exact_scales_cost_little_many_seeds() -> None:
    _check_exact(*_compare(range(4, 20), (0.0, 0.0)))


@pytest.mark.slow
def test_scale_errors_not_shrunk_many_seeds() -> None:
    """Independent 2-9 % errors: the empirical prior loses nothing measurable against the
    fixed one (measured 0.078 vs 0.078 m, 8 seeds): within 10 % on average, and the offset-only
    model is metres off (measured 2.8 m)."""
    eb, fixed, off = _compare(range(4, 16), (0.02, 0.09))
    assert eb.mean() < 1.1 * fixed.mean(), (eb, fixed)
    assert np.all(off > 5 * eb), (eb, off)


@pytest.mark.parametrize("odo_scale", [1.0, 1.03])
def test_odometry_scale_recovered(odo_scale: float) -> None:
    """The smoother's odometry distance scale ``k`` (``dd_true = k dd``) under its empirical
    prior: a 3 % wheel-radius error is found (``k = 1 / 1.03``) within its error bar, and a
    log without one keeps ``k`` at 1 within its error bar. Without the state a 3 % error cost
    the smoother 0.078 -> 0.25 m mean RMSE (``benchmarks/slac_scale_block.py``, odo-exact)."""
    for seed in range(3):
        r, _, e = _solve(seed, (0.0, 0.0), odo_scale=odo_scale)
        z = (r.odometry_scale - 1 / odo_scale) / np.hypot(r.odometry_scale_std, SCALE_PRIOR_FLOOR)
        assert abs(z) < 4, (r.odometry_scale, r.odometry_scale_std)  # 4 sigma, as above
        if odo_scale != 1.0:
            # the error is found, not shrunk away: its prior std is of its size, not the floor
            assert r.odometry_scale_prior_std > 0.01, r.odometry_scale_prior_std
            assert r.odometry_scale_weight > 0.5, r.odometry_scale_weight  # the model with k is the more probable
        assert e < 0.25, e  # decimetre level, as the exact-scale logs (measured <= 0.12 m)


def test_scale_prior_option_refused_by_name() -> None:
    from selfcal.errors import InputError

    with pytest.raises(InputError, match="RangeModelConfig.scale_prior"):
        RangeModelConfig(scale_prior="ebayes")
    assert RangeModelConfig().scale_prior == "empirical"


def test_flat_evidence_keeps_the_given_prior() -> None:
    """No information about the scales (posterior = prior): the evidence is flat in (a, tau)
    and the estimate is the given prior, not the floor (which would claim exact scales)."""
    for B in (1, 4):
        S, (a, tau) = scale_prior_eb(np.ones(B), 0.1**2 * np.eye(B), 0.1)
        assert a == pytest.approx(SCALE_PRIOR_FLOOR) and tau == pytest.approx(0.1)


def test_odometry_scale_weight_is_the_bayes_factor() -> None:
    """The weight of ``k ~ N(1, ODO_SCALE_STD^2)`` is ``BF / (1 + BF)`` (prior odds 1), with the
    Bayes factor computed independently as the ratio of the two Gaussian marginals of the data's
    ``k_lik`` (scipy.stats.norm); it crosses 1/2 exactly where ``z^2 = (1 + r) log(1 + 1 / r)``,
    ``r = v_lik / ODO_SCALE_STD^2`` (the rule that selected the model before the average)."""
    from scipy.stats import norm

    from selfcal.slac.scale_prior import ODO_SCALE_STD, odo_scale_weight

    g = np.random.default_rng(7)
    for v_lik in (1e-6, 1e-5, 1e-4):
        r = v_lik / ODO_SCALE_STD**2
        z_star = np.sqrt((1 + r) * np.log(1 + 1 / r))
        v = 1 / (1 / v_lik + 1 / ODO_SCALE_STD**2)  # the posterior variance under the prior
        for z in [0.98 * z_star, 1.02 * z_star, *g.normal(0, 3, 20)]:
            k_hat = 1 + z * np.sqrt(v_lik) * v / v_lik  # posterior mean for k_lik - 1 = z sqrt(v_lik)
            d = z * np.sqrt(v_lik)
            bf = norm.pdf(d, 0, np.sqrt(v_lik + ODO_SCALE_STD**2)) / norm.pdf(d, 0, np.sqrt(v_lik))
            w = odo_scale_weight(k_hat, v)
            assert w == pytest.approx(bf / (1 + bf), rel=1e-6, abs=1e-12), (v_lik, z)
            if abs(abs(z) / z_star - 1) > 0.01:
                assert (w > 0.5) == (abs(z) > z_star)
    assert odo_scale_weight(1.0, ODO_SCALE_STD**2) == 0.0  # no information about k: k = 1


def _avg_vs_select(seed: int, monkeypatch: pytest.MonkeyPatch) -> tuple[float, float]:
    from selfcal.slac import ranging

    case = {"range_noise": 0.5, "outliers": 0.0, "odo_scale": 1.005}
    _, _, e_avg = _solve(seed, (0.06, 0.06), **case)
    orig = ranging.odo_scale_weight
    with monkeypatch.context() as mp:
        mp.setattr(ranging, "odo_scale_weight", lambda k, v: float(orig(k, v) >= 0.5))
        _, _, e_sel = _solve(seed, (0.06, 0.06), **case)
    return e_avg, e_sel


@pytest.mark.parametrize("seed", range(2))
def test_small_odometry_error_the_average_is_not_worse_than_the_selection(seed: int, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A 0.5 % odometry distance-scale error (the size the ground truth of Plaza 1 shows) on
    plaza-like logs (one 6 % range scale, 0.5 m noise): the Bayes factor is not decisive and
    the selection keeps ``k = 1``; averaging the two models by their posterior probabilities
    is not worse on any seed (measured over 8 seeds, ``benchmarks/slac_odo_average.py 8
    odo-small``: selection / average 1.00-1.30, mean RMSE 0.202 vs 0.188 m). 2 % slack: the
    two can tie to round-off of a second solve."""
    e_avg, e_sel = _avg_vs_select(seed, monkeypatch)
    assert e_avg <= 1.02 * e_sel, (e_avg, e_sel)


@pytest.mark.slow
def test_small_odometry_error_the_average_is_not_worse_than_the_selection_many_seeds(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """As above over 12 seeds: never worse by more than 2 % and better in the mean."""
    r = np.array([_avg_vs_select(s, monkeypatch) for s in range(12)])
    assert np.all(r[:, 0] <= 1.02 * r[:, 1]), r
    assert r[:, 0].mean() < r[:, 1].mean(), r
