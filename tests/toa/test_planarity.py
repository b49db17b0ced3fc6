"""The one planarity decision (``selfcal.toa.verdict.planarity.planarity`` / ``dimension_test``).

Used by ``dim="auto"`` (``solve_toa``, ``calibrate toa``), the acoustic pipeline and
``selfcal plan``. Its two parts are tested against what they promise:

- the thickness chi-square ``T = min over planes of sum (n^T (p_k - c))^2 / (n^T C_k n)``
  against an independent minimisation, and its level: points jittered off a plane exactly by their
  stated covariances are called resolved at about ``PLANAR_ALPHA`` (the plane fitted to the
  points takes 3 of the chi-square's degrees of freedom);
- on fitted layouts, the F test of the 2-D fit against the 3-D one: planar truths stay 2-D
  (the chi-square alone calls most of them resolved: the 3-D fit bends off a planar truth by
  about ``sqrt(noise x extent)``, beyond its linearised error bars), generic 3-D layouts 3-D.
  At a planar truth the asymptotic F test's rate exceeds its nominal level (4 % of 200
  draws); where it says 3-D on a layout within a few bending scales of flat, the statistic
  is corrected by a parametric bootstrap's Bartlett factor (``bartlett_corrected``): its
  level is tested on the factor's own law and over planar draws (slow).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.optimize
import scipy.stats

from selfcal.acoustics.calibrate import _toa_options, _toa_solver
from selfcal.toa import solve_toa
from selfcal.toa.verdict.planarity import (
    BOOT_REPLICATES,
    PLANAR_ALPHA,
    bartlett_corrected,
    compare_fits,
    planarity,
)
from selfcal.toa.verdict.select import dimension_test

C = 343.0
NOISE = 1e-6  # s: 0.34 mm of range


def _cloud(g: np.random.Generator, n: int, thickness: float, sd: np.ndarray) -> np.ndarray:
    P = np.c_[g.uniform(0, 8, n), g.uniform(0, 7, n), g.normal(0, thickness, n)]
    P[:, 2] += g.normal(0, 1.0, n) * sd  # off the plane by exactly the stated z std
    return P


@pytest.mark.parametrize("seed", range(5))
def test_thickness_statistic_is_the_chi_square_of_the_out_of_plane_coordinates(seed):
    g = np.random.default_rng(seed)
    n = 30
    sd = g.uniform(0.001, 0.01, n)
    P = _cloud(g, n, 0.02, sd)
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = 1e-4
    cov[:, 2, 2] = sd**2
    pl = planarity(P, cov)
    # independent: minimise T over the normal's two angles (the best offset given a normal
    # is the weighted centroid) from several starts with a generic optimiser

    def T_of(angles):
        a, b = angles
        nv = np.array([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)])
        var = np.einsum("i,kij,j->k", nv, cov, nv)
        c = (P / var[:, None]).sum(axis=0) / (1.0 / var).sum()
        return float(np.sum(((P - c) @ nv) ** 2 / var))

    T = min(scipy.optimize.minimize(T_of, x0, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12}).fun
            for x0 in ([0.01, 0.0], [0.2, 1.0], [0.3, -2.0]))
    # the re-weighted plane is the weights' fixed point: with error bars this anisotropic
    # (x, y std 1 cm, z std 1-10 mm) it sits within 1e-4 of the minimum, never below it
    assert T * (1 - 1e-9) <= pl.thickness_chi2 <= T * (1 + 1e-4)
    assert pl.thickness_p == pytest.approx(scipy.stats.chi2.sf(pl.thickness_chi2, n - 3), rel=1e-9)
    assert pl.near_planar == (pl.thickness_p > PLANAR_ALPHA)


def test_thickness_test_holds_its_level_and_finds_a_thickness_of_a_few_error_bars():
    """Level: 4000 planar clouds, 40 points with z stds of 1-10 mm jittered by exactly
    them: called resolved at most at 3x PLANAR_ALPHA (expected 4; 12 is beyond the
    binomial's 0.9999 quantile). Power: a real thickness of 3 z stds (noncentrality
    ~ 9 x 37 = 333 against a critical value of 70) is resolved in every draw."""
    g = np.random.default_rng(7)
    n, draws = 40, 4000
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = 1e-6
    alarms = 0
    for _ in range(draws):
        sd = g.uniform(0.001, 0.01, n)
        cov[:, 2, 2] = sd**2
        alarms += not planarity(_cloud(g, n, 0.0, sd), cov).near_planar
    assert alarms <= 3 * PLANAR_ALPHA * draws
    for _ in range(200):
        sd = g.uniform(0.001, 0.01, n)
        cov[:, 2, 2] = sd**2
        P = _cloud(g, n, 0.0, sd)
        P[:, 2] += 3 * sd * g.choice([-1, 1], n)
        assert not planarity(P, cov).near_planar


def test_an_insignificant_f_test_keeps_a_layout_planar_whatever_its_covariances():
    g = np.random.default_rng(1)
    P = _cloud(g, 20, 0.5, np.zeros(20))
    cov = np.tile(np.eye(3) * 1e-8, (20, 1, 1))
    assert not planarity(P, cov).near_planar
    flat_f = compare_fits(1.0e-3, 0.99e-3, 400, 20)
    assert not flat_f.significant and planarity(P, cov, comparison=flat_f).near_planar
    thick_f = compare_fits(1e-2, 1e-3, 400, 20)
    assert not planarity(P, cov, comparison=thick_f).near_planar


def _draw(seed: int, planar: bool, I: int = 8, J: int = 10) -> np.ndarray:
    """The pipeline's model: seconds, both offsets, 1 us noise, an 8 x 7 m floor."""
    g = np.random.default_rng(seed)
    R = np.c_[g.uniform(0, 8, I), g.uniform(0, 7, I), np.zeros(I) if planar else g.uniform(0, 3, I)]
    S = np.c_[g.uniform(0, 8, J), g.uniform(0, 7, J), np.zeros(J) if planar else g.uniform(0, 3, J)]
    D = np.linalg.norm(R[:, None] - S[None], axis=-1)
    return D / C + g.uniform(0, 0.02, I)[:, None] + g.uniform(0, 0.03, J)[None] + g.normal(0, NOISE, (I, J))


def _decide(seed: int, planar: bool):
    T = _draw(seed, planar)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r3 = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
        # the acoustic pipeline's form of the test (solve_toa seeded per call, user units)
        return dimension_test(T, r3, "both", _toa_solver(seed), _toa_options(C, None))


# draws 1001, 1015, 1022, 1032 once ended 3-D: the 2-D refinement started with offsets 343x
# too large (seconds multiplied by the speed twice), stopped at 0.1-1 ms RMS and inflated F
@pytest.mark.parametrize("seed", [1001, 1015, 1022, 1032, 1100, 1101])
def test_planar_layouts_stay_planar_and_their_2d_fit_reaches_the_noise(seed):
    keep3, pl, r2, stats, _ = _decide(seed, planar=True)
    assert not keep3 and pl.near_planar and stats["chosen"] == 2
    assert stats["residual_2d"] < 1.5 * NOISE  # the 2-D model's own minimum, not a wrong basin


@pytest.mark.parametrize("seed", range(4))
def test_generic_layouts_are_3d(seed):
    keep3, pl, _, stats, _ = _decide(2000 + seed, planar=False)
    assert keep3 and not pl.near_planar and stats["p_value"] <= PLANAR_ALPHA and stats["thickness_p"] <= PLANAR_ALPHA


@pytest.mark.parametrize("scale", [1.0, 2.0, 5.0])
def test_bartlett_correction_holds_its_level_when_the_null_is_a_scaled_f(scale):
    """Statistics and their 32 replicates drawn from ``scale x F(k, dof)`` (the law the
    correction assumes, with the factor 1-2 measured at planar truths and beyond): the
    corrected test rejects at about its level, whatever the scale (the uncorrected one at
    ``scale`` 2 rejects 37 % at 5 %). Level 0.05 so 2,000 draws measure it: the Monte
    Carlo error of the factor (32 replicates) makes the rate a little above the level
    (measured 4.8 %, 5.6 %, 5.0 % at scales 1, 2, 5); bound 8 %, 5 binomial standard errors above 5 % at n = 2000.
    """
    g = np.random.default_rng(int(scale * 10))
    k, dof, n = 15, 15, 2000
    base = compare_fits(1.0, 1.0, 80, 18)  # k = 15, dof = 15 with both offsets
    assert (base.extra_parameters, base.dof_3d) == (k, dof)
    F = scale * scipy.stats.f.rvs(k, dof, size=(n, BOOT_REPLICATES + 1), random_state=g)
    rejected = 0
    for row in F:
        p0 = float(scipy.stats.f.sf(row[0], k, dof))
        cmp = dataclasses.replace(base, f_statistic=float(row[0]), p_value=p0, significant=p0 < 0.05)
        rejected += bartlett_corrected(cmp, row[1:], alpha=0.05).significant
    assert rejected / n < 0.08


def test_the_bootstrap_runs_where_the_f_test_is_borderline_and_not_on_generic_layouts():
    """Reduced version of the slow level test: planar draws 1037 and 1041 were called 3-D
    by the asymptotic F test (p 2e-4, 8e-4 at level 1e-3); the bootstrap's factor (about 2
    at 8 x 10) makes them 2-D. Generic 3-D draws are out of the band: no replicate runs."""
    for seed in (1037, 1041):
        keep3, pl, _, stats, _ = _decide(seed, planar=True)
        assert stats["p_asymptotic"] < PLANAR_ALPHA and stats["replicates"] >= BOOT_REPLICATES - 2
        assert stats["bartlett"] > 1.0 and not keep3 and pl.near_planar
    for seed in range(2):
        keep3, _, _, stats, _ = _decide(2000 + seed, planar=False)
        assert keep3 and stats["replicates"] == 0 and stats["bartlett"] == 1.0


@pytest.mark.slow
def test_bootstrap_level_over_200_planar_draws():
    """200 planar 8 x 10 draws (seeds 1000-1199, ``benchmarks/planarity_rates.py 200
    planar``'s): the asymptotic F test called 8 of them 3-D (4 % at a nominal 0.1 %); with
    the bootstrap correction at most 2 (1 %: the correction is a mean factor from 32
    replicates, not an exact p-value; measured 0)."""
    assert sum(_decide(1000 + s, True)[0] for s in range(200)) <= 2


@pytest.mark.slow
def test_planar_false_alarm_and_generic_power_over_many_draws():
    """100 planar and 100 generic draws: at most 10 planar draws called 3-D, and every
    generic draw 3-D unless its 3-D fit is broken.

    The planar bound is not the nominal 1e-3: at a planar truth the 3-D model is not
    regular and the F test's likelihood ratio has heavier tails than F(k, dof)
    (benchmarks/planarity_rates.py: 8 of 200 planar draws, 4 %; 10 of 100 has probability
    0.2 % at that rate; measured here 3); the per-point rule it replaced called 39 of 200
    3-D. Generic: 97 of 100 called 3-D; the other 3 (seeds 4005, 4047, 4054) are 3-D fits
    in a wrong basin (RMS 16-51 us at 1 us noise, nodes 190-500 m off, yet "success"):
    their covariances, scaled by that residual, do not resolve the thickness, and the
    2-D answer then fails its own tests (exit 1) instead of a 3-D one passing them.
    """
    planar3 = sum(_decide(3000 + s, True)[0] for s in range(100))
    generic = [_decide(4000 + s, False) for s in range(100)]
    assert planar3 <= 10
    assert all(keep3 or stats["residual_3d"] > 5 * NOISE for keep3, _, _, stats, _ in generic)


@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("offsets", ["both", "auto"])
def test_the_model_choice_is_the_same_in_seconds_with_a_speed_as_in_metres(planar, offsets):
    """Units equivariance of the choice (``dim="auto"``, ``offsets="auto"``): the matrix in
    seconds with ``speed`` and the same matrix in metres give the same model and positions.
    The choice's nested and projected starts carry offsets in its solver's units (metres;
    the pipeline's solve_toa form converts them back to seconds). On these draws the
    refinements also recover from a start in the wrong units, so this asserts the end
    result, not the start."""
    for seed in (2001, 2002):
        T = _draw(seed, planar)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a = solve_toa(T, dim="auto", offsets=offsets, speed=C, rng=seed)
            b = solve_toa(T * C, dim="auto", offsets=offsets, rng=seed)
        assert a.dim == b.dim and a.offsets == b.offsets, (seed, a.dim, b.dim, a.offsets, b.offsets)
        # same fit up to the solver's tolerance (1e-6 of a 10 m layout)
        np.testing.assert_allclose(a.receivers, b.receivers, atol=1e-5)
        np.testing.assert_allclose(a.sources, b.sources, atol=1e-5)


def _near_draw(seed: int, c: float = 2.0, I: int = 8, J: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``benchmarks/planarity_rates.py``'s near-c family: heights N(0, c sqrt(sigma L)), L = 5 m,
    the bending scale at which a thickness becomes detectable by a fit (c = 2: 8 cm)."""
    g = np.random.default_rng(seed)
    R = np.c_[g.uniform(0, 8, I), g.uniform(0, 7, I), np.zeros(I)]
    S = np.c_[g.uniform(0, 8, J), g.uniform(0, 7, J), np.zeros(J)]
    h = c * np.sqrt(NOISE * C * 5.0)
    R[:, 2], S[:, 2] = g.normal(0, h, I), g.normal(0, h, J)
    D = np.linalg.norm(R[:, None] - S[None], axis=-1)
    T = D / C + g.uniform(0, 0.02, I)[:, None] + g.uniform(0, 0.03, J)[None] + g.normal(0, NOISE, (I, J))
    return R, S, T


def _beyond_3_bars(res, R: np.ndarray, S: np.ndarray) -> int:
    """Nodes whose aligned 3-D error exceeds 3 of its error bars (chi-square(3)'s 0.9973 quantile)."""
    from selfcal.geometry import align

    est, true = np.vstack([res.receivers, res.sources]), np.vstack([R, S])
    cov = np.concatenate([res.receiver_cov, res.source_cov])
    tr = align(est, true, reflection=True)
    e, Rm = tr.apply(est) - true, np.asarray(tr.rotation)
    return sum(float(x @ np.linalg.solve(Rm @ c @ Rm.T, x)) > scipy.stats.chi2.ppf(0.9973, 3)
               for x, c in zip(e, cov, strict=True))


def _check_widened_bars(seeds) -> int:
    """Over near-planar draws (heights N(0, 8 cm) on an 8 x 7 m floor): where the planarity
    bootstrap ran and the answer stayed 3-D, every node lies within 3 of its (widened) bars;
    where it did not run, the reported 3-D fit is the input fit (bars unchanged). Returns the
    number of draws whose bars were widened."""
    widened = 0
    for seed in seeds:
        R, S, T = _near_draw(seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r3 = solve_toa(T, dim=3, offsets="both", speed=C, rng=seed)
            keep3, _, _, stats, reported = dimension_test(T, r3, "both", _toa_solver(seed), _toa_options(C, None))
        if stats["replicates"] == 0 or not keep3:
            assert reported is r3 and not stats["bars_widened"]
            continue
        widened += 1
        assert stats["bars_widened"] and "bootstrap" in stats["bars_note"]
        assert stats["bar_widening_median"] >= 1.0
        assert _beyond_3_bars(reported, R, S) == 0, seed
    return widened


def test_near_planar_3d_answers_whose_bars_the_bootstrap_widened_cover_the_truth():
    """Reduced version of the slow test below (draws 5019-5023; 5019 and 5022 are widened:
    5022 had 3-D nodes beyond 3 linearised bars, covered with the widened ones)."""
    assert _check_widened_bars(range(5019, 5024)) >= 2


@pytest.mark.slow
def test_near_planar_widened_bars_cover_over_many_draws():
    """120 draws (5000-5119, 2.5 min on a loaded machine): measured 16 bootstrap runs, 10 of
    them stayed 3-D and were widened (bars x3.8-8.7 median per draw), 5 of those had nodes
    beyond 3 linearised bars, none beyond 3 widened ones. The bound asserted is the
    property (every widened draw covers), with at least 5 widened draws so it is not vacuous."""
    assert _check_widened_bars(range(5000, 5120)) >= 5
