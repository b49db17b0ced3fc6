"""The smoother's per-beacon range-scale block (R1: ``r = s_b |p - b_b| + o_b``) on simulated
CMU-style logs, with scale errors (2-9 % long) and with exact scales (issue 31).

Measured (benchmarks/slac_scale_block.py, 10 seeds, 150 s logs): with scale errors the
block takes the smoother's RMSE from 2.85 m (offset only) to 0.12 m; with exact scales it
costs 0.124 m against 0.074 m (the price of four more weakly-observed parameters). The
tests below pin what holds on every seed: the scales are recovered within their own error
bars in both cases, and the cost without a scale error stays bounded."""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat

from selfcal.datasets.plaza import load_plaza
from selfcal.slac.ranging import solve_range_slac
from tests.datasets.cmu_logs import cmu_log


def _solve(seed: int, range_scale: tuple[float, float]):  # type: ignore[no-untyped-def]
    m, tr = cmu_log(seed, duration=150.0, range_scale=range_scale)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = Path(d) / "log.mat"
        savemat(p, m)
        r = solve_range_slac(load_plaza(p), method="smoother")
    t = r.times
    e = r.poses[:, :2] - np.column_stack([np.interp(t, tr.times, tr.poses[:, 0]), np.interp(t, tr.times, tr.poses[:, 1])])
    return r, tr, float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.mark.parametrize("range_scale", [(0.02, 0.09), (0.0, 0.0)])
def test_scale_recovered_within_error_bar(range_scale: tuple[float, float]) -> None:
    z, err = [], []
    for seed in range(4):
        r, tr, e = _solve(seed, range_scale)
        assert np.array_equal(r.beacon_ids, tr.beacon_ids)
        heard = tr.heard
        z.append((r.scale[heard] - tr.scale[heard]) / r.scale_std[heard])
        err.append(e)
    z = np.concatenate(z)
    # 4 sigma: per-parameter false alarm 6e-5 for a consistent Gaussian posterior
    assert np.all(np.abs(z) < 4), z
    # the range noise is 0.15 m; with or without a scale error the smoother stays at the
    # decimetre level (measured mean 0.12 m in both cases), far below the metres an
    # unmodelled 2-9 % scale costs
    assert np.mean(err) < 0.25, err
