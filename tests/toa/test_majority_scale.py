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
