"""Consistency of the SLAC antenna-response prior and of the full-G filter (paper 002).

The sampling-matrix prior (section IV: EM simulation or chamber measurement, widened by
``SlacConfig.g_rel_std``) must not be overconfident about the response that is really
installed, or no filter built on it can be consistent. The full-G SLAC filter itself is
known to be overconfident in heading (see ``docs/slac_consistency.md``); that test is a
strict xfail so a fix shows up as an unexpected pass. The fixed-lag smoother
(``SlacConfig(smoother_lag=10)``) is consistent on the same run.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from selfcal.experiments.slac import score_slac
from selfcal.scenarios.rovers import make_rover_scenario
from selfcal.slac.filter import SlacConfig, SlacFilter
from selfcal.slac.likelihood import pack_g
from selfcal.slac.run import SlacLog, solve_slac

N = 32


@pytest.fixture(scope="module")
def log() -> SlacLog:
    return SlacLog.from_scenario(make_rover_scenario(0.2, n_subcarriers=N, rng=11, bias_std=0.3), seed=11)


def _prior_mahalanobis(log: SlacLog, which: str) -> dict[int, tuple[float, int]]:
    f = SlacFilter(log.anchors, log.ports, log.prior(which), log.init_poses, log.init_cov, log.probe, mode="slac")
    out = {}
    for i, idx in f.g_index.items():
        d = pack_g(log.prior("true")[i]) - f.x[idx]
        out[i] = (float(d @ np.linalg.solve(f.P[np.ix_(idx, idx)], d)), int(idx.size))
    return out


def test_antenna_priors_are_consistent_with_the_installed_response(log: SlacLog) -> None:
    em = _prior_mahalanobis(log, "em")
    ch = _prior_mahalanobis(log, "chamber")
    assert em.keys() == ch.keys() and len(em) == 1  # one 4-port rover in the replica
    for i in em:
        (m_em, dof), (m_ch, _) = em[i], ch[i]
        assert dof == 2 * 4 * 13
        # the true installed G is a plausible draw of either prior (not overconfident)
        assert m_em < chi2.ppf(0.999, dof) and m_ch < chi2.ppf(0.999, dof)
        # the chamber measurement is closer to the installed antenna than the EM simulation
        assert m_ch < m_em


@pytest.mark.xfail(strict=True, reason="the full-G SLAC filter is overconfident in heading; docs/slac_consistency.md")
def test_full_slac_filter_with_chamber_prior_is_consistent(log: SlacLog) -> None:
    r = score_slac(log, solve_slac(log, mode="slac", prior="chamber", init="snapshot"))
    # per rover: the multi-port rover's time-averaged NEES is the one far above its band
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    assert np.all((lo <= r["nees_mean"]) & (r["nees_mean"] <= hi)), r["nees_mean"]


def test_full_slac_with_chamber_prior_is_consistent(log: SlacLog) -> None:
    # the fixed-lag smoother (10 steps = 1 s) re-solves the early steps jointly: the heading /
    # G ridge error of the filter is not locked in (docs/slac_consistency.md)
    r = score_slac(log, solve_slac(log, mode="slac", prior="chamber", init="snapshot", config=SlacConfig(smoother_lag=10)))
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    assert np.all((lo <= r["nees_mean"]) & (r["nees_mean"] <= hi)), r["nees_mean"]
    assert np.mean(r["nees_mean"]) < 5.0
