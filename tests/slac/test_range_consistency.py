"""Consistency of the range-SLAC smoother's reported covariances against the truth of simulated
CMU-style logs (tests/datasets/cmu_logs.py), over many seeds.

Statistic: the time-averaged NEES of the position, ``mean_t e_t^T C_t^-1 e_t``, per log (one
log is the unit: the errors along one track are strongly correlated, so poses are not
independent draws). A consistent estimator has E[NEES_t] = 2 (chi-square, 2 dof); the time
average of identically distributed terms is smaller in convex order than one term, so it
exceeds chi2_2(0.99) = 9.21 with probability at most ~1 %. A log above that bound is an
overconfident result; the thresholds on the count follow from the binomial at 1 %.

Before the fix (each heading-noise candidate adapting its own range noise in the model
selection), seeds 3 and 7 of the plain log chose a heading noise 10x too stiff and ended at
NEES 8.1 and 21.8 (95 % ellipses covering 30 % and 18 % of the poses).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scipy.io import savemat

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import solve_range_slac
from tests.datasets.cmu_logs import cmu_log

NEES_BOUND = float(stats.chi2.ppf(0.99, 2))


def _nees(seed: int, method: str = "smoother", **kw: object) -> tuple[float, float]:
    m, tr = cmu_log(seed, **kw)  # type: ignore[arg-type]
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "log.mat"
        savemat(p, m)
        data = load_plaza(p)
    r = solve_range_slac(data, method=method)
    assert r.success, r.message
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    q = np.einsum("ni,nij,nj->n", e, np.linalg.inv(r.pose_cov), e)
    return float(np.mean(q)), float(np.mean(q <= stats.chi2.ppf(0.95, 2)))


def test_pose_covariance_is_the_smoothers_marginal() -> None:
    m, _ = cmu_log(0, duration=30.0)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve_range_slac(load_plaza(p), method="smoother")
    assert r.pose_cov.shape == (r.poses.shape[0], 2, 2)
    assert np.allclose(np.sqrt(np.diagonal(r.pose_cov, axis1=1, axis2=2)), r.pose_std[:, :2])
    assert np.all(np.linalg.eigvalsh(r.pose_cov) > 0)


def test_smoother_is_consistent_on_short_logs() -> None:
    # 6 short logs (60 s, ~1 s CPU each); P(one of 6 above the bound | consistent) <= 6 %
    nees = [_nees(seed, duration=60.0)[0] for seed in range(6)]
    assert max(nees) < NEES_BOUND, nees


@pytest.mark.slow
@pytest.mark.parametrize("kw", [
    {}, {"outliers": 0.05}, {"n_beacons": 5, "silent": 1, "gaps": 2, "heading_offset": -np.pi / 2},
    {"far_beacon": 120.0, "n_beacons": 5}, {"dropouts": 2}, {"stand": 2},
], ids=["plain", "outliers-5pc", "gaps-outliers-silent", "far-beacon", "dropouts", "standing"])
def test_smoother_is_consistent_over_seeds(kw: dict) -> None:  # type: ignore[type-arg]
    # 10 logs of 240 s; at most 1 above the bound (binomial(10, 0.01): P(>= 2) = 0.4 %)
    nees = [_nees(seed, **kw)[0] for seed in range(10)]
    assert sum(v > NEES_BOUND for v in nees) <= 1, nees
