"""``dim="auto"`` does not hand a generic 3-D network the 2-D fit because the 3-D search
stopped in a wrong basin (issue 27, ``benchmarks/cli_audit.py`` ``gen-3d-6x8`` seed 43).

A wrong-basin 3-D fit (RMS far above the noise) makes the F test small and its noise estimate
large, so the layout falls in the bootstrap band and the 2-D fit was kept (5.2 m off at 9 of
its error bars, exit 0). :func:`selfcal.toa.verdict.select.dimension_test` now refits the 3-D
model from the 2-D fit lifted off its plane (the bootstrap replicates' second start).

Properties, over generic 6 x 8 networks (1 cm noise, 10 m box), each given a 3-D fit from a
wrong basin (a refinement from a random start whose RMS is above 10 x the noise; the 3-D
minimum is at the noise): the 3-D fit the test reports is never worse (sum of squares) than
the one it was given; where the lift found nothing better, every statistic and the decision
are those of the test without the lift (its heights come from a stream of their own, so the
bootstrap's replicates are unchanged: behaviour elsewhere is preserved); and at least one draw
of the reduced set is rescued (range(12): seed 1, RMS 0.21 m -> 4.5 cm, F 17 -> 211, the
bootstrap no longer needed). What it does not give: a wrong basin whose asymptotic F is not
significant never reaches the band, and the 2-D fit is kept there (seeds 0, 2-6, 10 here;
``benchmarks/cli_audit.py`` meets it on 0 of 180 generic draws, docs/design.md).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from selfcal.toa import solve_toa
from selfcal.toa.engine.model import toa_model
from selfcal.toa.engine.nls import refine_toa
from selfcal.toa.options import ToaOptions
from selfcal.toa.solve import _solve_fixed
from selfcal.toa.verdict.select import dimension_test

NOISE = 0.01


def _wrong_basin(seed: int):
    g = np.random.default_rng([2791, seed])
    R, S = g.uniform(0, 10, (6, 3)), g.uniform(0, 10, (8, 3))
    M = toa_model(R, S) + g.normal(0, NOISE, (6, 8))
    for _ in range(30):
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            sol = refine_toa(M, g.uniform(0, 10, (6, 3)), g.uniform(0, 10, (8, 3)), covariance=False)
        if np.sqrt(np.nanmean(sol.residuals**2)) > 10 * NOISE:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return M, solve_toa(M, dim=3, init=(sol.receivers, sol.sources), method="nls", rng=seed)
    return M, None


def _opts(seed: int) -> ToaOptions:
    return ToaOptions(speed=None, loss="auto", method="auto", rng=np.random.default_rng(seed), f_scale=None,
                      max_nfev=None, covariance=True, sweep=True, noise=None, budget=None)


def _check(seed: int) -> str:
    """"skip" (no wrong basin), "same" (no lift: identical to the test without it), "lifted"."""
    M, r3 = _wrong_basin(seed)
    if r3 is None or np.sqrt(np.nanmean(r3.residuals**2)) < 10 * NOISE:
        return "skip"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        keep3, _, _, st, rep = dimension_test(M, r3, "none", _solve_fixed, _opts(seed))
        keep3b, _, _, stb, repb = dimension_test(M, r3, "none", _solve_fixed, _opts(seed), lift=False)
    rss = lambda f: float(np.nansum(f.residuals[~f.outliers] ** 2))  # noqa: E731
    assert rss(rep) <= rss(r3) * (1 + 1e-9), seed
    if not st.get("fit3_lifted"):
        assert keep3 == keep3b and rep is repb, seed
        assert {k: v for k, v in st.items()} == stb, seed
        return "same"
    assert rss(rep) < rss(r3), seed
    return "lifted"


def test_lifted_start_never_worse_and_changes_nothing_else_reduced() -> None:
    out = [_check(s) for s in range(12)]
    assert "lifted" in out


@pytest.mark.slow
def test_lifted_start_never_worse_and_changes_nothing_else() -> None:
    out = [_check(s) for s in range(12, 60)]
    assert out.count("skip") < len(out)
