"""The majority-scale breakdown test (``toa.verdict.high_breakdown.majority_scale_test``, issue 27).

Ground truth: the least-squares fit of every entry, started at the true geometry, of a
network whose ranges are 30 % gross (U(1, 5) m on 1 cm noise) is the fit the outlier rule
cannot judge (its noise estimate inflates to ~1 m); the test must find the majority's fit
(scale ~1 cm) and report it. On clean networks (Gaussian or Student t3 noise) the same
least-squares fit is consistent and the test must hold: its scale ratio is ~1 against the
cut of ~4.3 (the outlier rule's Bonferroni quantile; measured at most 2.1 over 60 draws).
"""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.toa import toa_model
from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.result import n_parameters
from selfcal.toa.verdict.high_breakdown import lts_scale, majority_scale_check, majority_scale_test


def _ls_fit(seed: int, gross: float, tails: str = "gauss") -> tuple:
    g = np.random.default_rng([27, 99, seed])
    r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (40, 3))
    e = g.normal(0, 0.01, (12, 40)) if tails == "gauss" else 0.01 / np.sqrt(3) * g.standard_t(3, (12, 40))
    Y = toa_model(r, s) + e
    bad = g.random(Y.shape) < gross
    Y[bad] += g.uniform(1, 5, bad.sum())
    sol = refine_toa(Y, r, s, covariance=False)  # least squares on every entry, from the truth
    return Y, sol, n_parameters(12, 40, 3, "none")


def _ratios(seeds: range, gross: float, tails: str = "gauss") -> list[tuple[float, float]]:
    out = []
    for seed in seeds:
        Y, sol, n_par = _ls_fit(seed, gross, tails)
        s_f, s_m, k = majority_scale_test(Y, sol.receivers, sol.sources, None, None, "none", n_par)
        out.append((s_f / s_m, k))
    return out


@pytest.mark.parametrize("tails", ["gauss", "t3"])
def test_clean_least_squares_fit_holds(tails):
    for ratio, k in _ratios(range(3), 0.0, tails):
        assert ratio < k, (ratio, k)  # measured at most 2.1 over 60 draws (Gaussian and t3), k = 4.3


def test_gross_errors_spread_by_least_squares_are_a_breakdown():
    # a search: from the least-squares basin it reached the majority in 17 of 30 draws (ratio 5.8-166
    # against the cut 4.3; the other 13 stalled at 2.3-4.2), 2 of these 6
    hits = [ratio > k for ratio, k in _ratios(range(6), 0.3)]
    assert sum(hits) >= 2, hits


@pytest.mark.slow
def test_majority_scale_over_many_draws():
    clean = _ratios(range(30), 0.0) + _ratios(range(30), 0.0, "t3")
    gross = _ratios(range(30), 0.3)
    assert all(r < k for r, k in clean), max(r for r, _ in clean)  # measured at most 2.1 (k = 4.3)
    # the search can miss the majority (it then reports nothing): 17 of these 30 reached
    assert sum(r > k for r, k in gross) >= 0.5 * len(gross), sorted(r for r, _ in gross)


def _truth_scales(seeds: range, gross: float) -> list[tuple[float, float]]:
    """(trimmed scale, the test's majority scale) at the true geometry of 12 x 40 with ``gross`` of the ranges off."""
    out = []
    for seed in seeds:
        g = np.random.default_rng([27, 98, seed])
        r, s = g.uniform(0, 10, (12, 3)), g.uniform(0, 10, (40, 3))
        Y = toa_model(r, s) + g.normal(0, 0.01, (12, 40))
        bad = g.random(Y.shape) < gross
        Y[bad] += g.uniform(1, 5, bad.sum())
        n_par = n_parameters(12, 40, 3, "none")
        _, s_m, _ = majority_scale_test(Y, r, s, None, None, "none", n_par)  # the fit: the truth
        out.append((lts_scale(Y - toa_model(r, s), n_par), s_m))
    return out


def test_majority_scale_holds_beyond_the_trimmed_scale():
    # at 35-40 % gross entries on 12 x 40 (480 entries, 150 unknowns) the trimmed scale's
    # h = (m + n_par + 1) / 2 = 315 covers gross entries: at the true geometry it was 0.3-1.1 m against
    # 1 cm noise (19 of 20 draws at 38 %), so the test could not fire even from the truth's basin. Its start is
    # now the lower of that and the MAD scale (breakdown point 1/2): 2.2-2.9 cm over those 20 draws (the
    # median of a 38 %-contaminated sample sits ~1.5-2x above the noise's), far below the ~1 m scale of
    # the fit that gross errors pull off (the breakdown is s_f > 4.3 s_m); 5 cm = 5 noise std
    for trimmed, s_m in _truth_scales(range(4), 0.38):
        assert trimmed > 0.2  # these 4 draws: 0.31-0.87 m, the trimmed scale alone breaks down
        assert s_m < 0.05, s_m


@pytest.mark.slow
def test_majority_scale_holds_beyond_the_trimmed_scale_over_many_draws():
    assert all(s_m < 0.05 for _, s_m in _truth_scales(range(20), 0.38))  # measured 1.4-2.9 cm


def test_lts_scale_is_normal_consistent():
    g = np.random.default_rng(5)
    for n_par in (0, 100):
        r = g.normal(0, 0.5, 4000)
        assert abs(lts_scale(r, n_par) / 0.5 - 1) < 0.1


def test_check_message_names_the_scales():
    msgs = []
    for seed in range(6):
        Y, sol, n_par = _ls_fit(seed, 0.3)
        msgs.append(majority_scale_check(Y, sol.receivers, sol.sources, None, None, "none", n_par))
    said = [m for m in msgs if m is not None]
    assert said and all("majority of the ranges" in m and " m against" in m for m in said), msgs
